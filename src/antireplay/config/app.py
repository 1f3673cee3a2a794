"""The whole configuration file: one :class:`AppConfig` with a section per concern.

Theory of operation
-------------------
One file serves every long-running command: ``security``, ``state``, ``audit`` and
``audit_space`` (:mod:`~antireplay.config.common`) hold for all of them; ``keys``,
``jwt``, ``store`` and ``upstream`` are the gateway's (:mod:`~antireplay.config.gateway`);
``mavlink`` and ``mavlink_pq`` the router's and the PQ ends'
(:mod:`~antireplay.config.mavlink`); ``dds`` the DDS commands' (:mod:`~antireplay.config.dds`).
Before any value is validated, every key is checked against the whole tree
(:func:`~antireplay.config.loader.check_keys`): a key where it does not belong is refused
naming where it does.  Then every value is range-checked and strictly typed
(:class:`~antireplay.core.errors.ConfigError` names the dotted key, the value and what is
allowed), never a silent default; ``state.anchor`` is refused beside a store that is not
SQLite.  :meth:`AppConfig.load` applies a command's flags over the file's keys and
validates the result as one, so a flag is held to the same rules as its key.  Only
:mod:`antireplay.wiring` and the CLI read this object; it is never handed to a core or an
adapter.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    PrivateAttr,
    ValidationError,
    field_validator,
    model_validator,
)

from antireplay.config.common import AuditConfig, AuditSpaceConfig, StateConfig
from antireplay.config.dds import RENAMED, DdsConfig
from antireplay.config.gateway import JwtConfig, KeyConfig
from antireplay.config.loader import check_keys, load_yaml
from antireplay.config.mavlink import MavlinkConfig, MavlinkPqConfig
from antireplay.core.errors import ConfigError
from antireplay.core.settings import SecurityConfig
from antireplay.state.spec import StoreSpec


class AppConfig(BaseModel):
    """The whole configuration file; ``security:`` is the §8.3 block."""

    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)

    security: SecurityConfig = Field(default_factory=SecurityConfig)
    store: str = "sqlite:.antireplay/state.db"
    state: StateConfig = Field(default_factory=StateConfig)
    audit: AuditConfig = Field(default_factory=AuditConfig)
    audit_space: AuditSpaceConfig = Field(default_factory=AuditSpaceConfig)
    keys: list[KeyConfig] = Field(default_factory=list)
    sdk_compat: bool = False
    jwt: JwtConfig = Field(default_factory=JwtConfig)
    versions: list[str] = Field(default_factory=lambda: ["3"])
    upstream: str | None = None  # http(s)://… or module:function
    upstream_timeout_s: float = Field(default=5.0, gt=0, le=120)
    max_body_bytes: int = Field(default=65_536, ge=256, le=16_777_216)
    mavlink: MavlinkConfig = Field(default_factory=MavlinkConfig)
    mavlink_pq: MavlinkPqConfig = Field(default_factory=MavlinkPqConfig)
    dds: DdsConfig | None = None  # its psk_file is required once the block is there

    _store_spec: StoreSpec = PrivateAttr()

    @field_validator("store")
    @classmethod
    def _store_grammar(cls, value: str) -> str:
        StoreSpec.parse(value)  # the one grammar; its ConfigError names what is allowed
        return value

    @property
    def store_spec(self) -> StoreSpec:
        """The gateway's ``store``, parsed once (when the file was validated)."""
        return self._store_spec

    @model_validator(mode="after")
    def _anchor_backend(self) -> AppConfig:
        self._store_spec = StoreSpec.parse(self.store)
        backend = self._store_spec.backend
        if self.state.anchor.configured and backend != "sqlite":
            raise ConfigError(
                "state.anchor", self.state.anchor.model_dump(exclude_defaults=True),
                f"only with a sqlite store (store is {backend}: it has no directory to restore)",
            )  # fmt: skip
        return self

    @classmethod
    def from_mapping(cls, data: dict[str, Any]) -> AppConfig:
        """Validate the whole file; errors name the dotted key, the value and what is allowed."""
        check_keys(cls, data, renamed={f"dds.{old}": new for old, new in RENAMED.items()})
        data = dict(data)
        security = SecurityConfig.from_mapping(data.pop("security", None))
        dds = DdsConfig.from_mapping(data.pop("dds")) if "dds" in data else None
        try:
            return cls.model_validate({**data, "security": security, "dds": dds})
        except ValidationError as exc:
            err = exc.errors()[0]
            cause = err.get("ctx", {}).get("error")
            if isinstance(cause, ConfigError):
                raise cause from None
            key = ".".join(str(p) for p in err["loc"]) or "config"
            raise ConfigError(key, err.get("input"), err["msg"]) from None

    @classmethod
    def from_yaml(cls, path: str | Path) -> AppConfig:
        return cls.from_mapping(load_yaml(path))

    @classmethod
    def load(cls, path: str | Path | None, overrides: dict[str, Any] | None = None) -> AppConfig:
        """The file at ``path`` (none: every default) with a command's flags over its keys:
        ``overrides`` maps a dotted key (``mavlink.store``) to the flag's value; ``None`` (a
        flag not given) and an empty tuple (a repeatable flag not given) leave the key."""
        data = load_yaml(path) if path is not None else {}
        for dotted, value in (overrides or {}).items():
            if value is None or value == ():
                continue
            *sections, leaf = dotted.split(".")
            block = data
            for section in sections:
                inner = block.get(section)
                if isinstance(inner, str):  # ``audit: PATH``, the short form
                    inner = {"path": inner}
                block[section] = inner = dict(inner) if isinstance(inner, dict) else {}
                block = inner
            block[leaf] = list(value) if isinstance(value, tuple) else value
        return cls.from_mapping(data)
