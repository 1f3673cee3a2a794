"""Configuration: the gateway's whole file (keys, JWT, store, audit, upstream), validated.

Theory of operation
-------------------
Every value is range-checked and strictly typed, and an unknown key is an error
(:class:`~antireplay.core.errors.ConfigError` names the dotted key, the value and
what is allowed), never a silent default; the store spec is checked by the one
grammar (:meth:`~antireplay.state.StoreSpec.parse`); ``state.anchor`` (a SQLite store's
anchor outside its directory) is refused with any other store.  The ``security:`` block and the YAML
reader live in :mod:`antireplay.core.settings` (the window policy reads them);
they are re-exported here.  Only :mod:`antireplay.wiring` and the adapters read
this object; it is never handed to a core.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from antireplay.core.errors import ConfigError
from antireplay.core.settings import ALLOWED, SecurityConfig, load_yaml, unknown_key
from antireplay.state.spec import StoreSpec

__all__ = [
    "ALLOWED",
    "AnchorConfig",
    "AppConfig",
    "AuditConfig",
    "AuditSpaceConfig",
    "JwtConfig",
    "KeyConfig",
    "SecurityConfig",
    "load_yaml",
]


class KeyConfig(BaseModel):
    """One signing key of the registry (``keys:`` list)."""

    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)

    kid: str = Field(min_length=1, max_length=128)
    owner: str = Field(min_length=1, max_length=128)
    alg: Literal["ed25519", "ml-dsa-65", "ml-dsa-87", "ed25519+ml-dsa-65"]
    public_keys: list[str] = Field(min_length=1, max_length=2)  # PEM file paths
    scopes: list[str] = Field(default_factory=lambda: ["control"])


class JwtConfig(BaseModel):
    """Bearer tokens (``jwt:``)."""

    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)

    required: bool = False
    audience: str | None = None
    issuer: str | None = None
    keys: dict[str, str] = Field(default_factory=dict)  # kid -> PEM path (EdDSA / ES256)
    hs256_secret_env: str | None = None  # name of an environment variable; HS256 only if set
    leeway_s: float = Field(default=0.0, ge=0, le=300)


class AnchorConfig(BaseModel):
    """``state.anchor``: where the SQLite store's anchor lives, outside its directory
    (:mod:`antireplay.state.anchor`): a file on another volume, a Redis URL, or both."""

    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)

    path: str | None = Field(default=None, min_length=1)
    redis: str | None = None
    every_ms: int = Field(default=0, ge=0, le=10_000)  # 0: every commit; else a lease

    @field_validator("redis")
    @classmethod
    def _redis_url(cls, value: str | None) -> str | None:
        if value is not None and StoreSpec.parse(value, "state.anchor.redis").backend != "redis":
            raise ConfigError("state.anchor.redis", value, "a redis://, rediss:// or unix:// URL")
        return value

    @property
    def configured(self) -> bool:
        return self.path is not None or self.redis is not None


class StateConfig(BaseModel):
    """``state:``: what keeps the replay state honest beyond the store itself."""

    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)

    anchor: AnchorConfig = Field(default_factory=AnchorConfig)


_MIB = 1 << 20


class AuditConfig(BaseModel):
    """The audit trail (``audit:``): its path, when its live segment rotates and how much
    of it is kept.  A bare string is the path, with these defaults (``None``: no limit)."""

    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)

    path: str = Field(default=".antireplay/audit.db", min_length=1)
    segment_bytes: int = Field(default=64 * _MIB, ge=64 * 1024, le=1 << 40)
    segment_age_s: float = Field(default=86_400.0, ge=1, le=366 * 86_400)
    max_bytes: int | None = Field(default=1024 * _MIB, ge=2 * 64 * 1024, le=1 << 50)
    max_age_s: float | None = Field(default=None, ge=60, le=100 * 366 * 86_400)

    @model_validator(mode="before")
    @classmethod
    def _path_only(cls, value: Any) -> Any:
        return {"path": value} if isinstance(value, str) else value

    @model_validator(mode="after")
    def _budget_holds_two_segments(self) -> AuditConfig:
        """Retention never removes the live segment: a budget under two segments would
        remove every rotated one at once, or be exceeded."""
        if self.max_bytes is not None and self.max_bytes < 2 * self.segment_bytes:
            raise ConfigError(
                "audit.max_bytes", self.max_bytes,
                f"at least twice audit.segment_bytes ({2 * self.segment_bytes}), or null",
            )  # fmt: skip
        return self

    def __fspath__(self) -> str:
        return self.path

    def __str__(self) -> str:
        return self.path


class AuditSpaceConfig(BaseModel):
    """Free-space floors under the audit trail (``audit_space:``) and the ESTOP spill."""

    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)

    #: Below: refusals get no rows and no summaries (still counted in metrics).
    min_free_bytes: int = Field(default=64 * 1024 * 1024, ge=0)
    #: Below: new commands other than a fresh ESTOP are refused 503 STATE_UNAVAILABLE.
    refuse_free_bytes: int = Field(default=16 * 1024 * 1024, ge=0)
    #: The reserved file for ESTOP rows the trail could not take (default: beside it).
    spill: str | None = None

    @field_validator("refuse_free_bytes")
    @classmethod
    def _below_first(cls, value: int, info: ValidationInfo) -> int:
        first = info.data.get("min_free_bytes")
        if first is not None and value > first:
            raise ConfigError("audit_space.refuse_free_bytes", value, f"at most {first}")
        return value


class AppConfig(BaseModel):
    """The whole gateway configuration file; ``security:`` is the §8.3 block."""

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

    @field_validator("store")
    @classmethod
    def _store_spec(cls, value: str) -> str:
        StoreSpec.parse(value)  # the one grammar; its ConfigError names what is allowed
        return value

    @model_validator(mode="after")
    def _anchor_backend(self) -> AppConfig:
        backend = StoreSpec.parse(self.store).backend
        if self.state.anchor.configured and backend != "sqlite":
            raise ConfigError(
                "state.anchor", self.state.anchor.model_dump(exclude_defaults=True),
                f"only with a sqlite store (store is {backend}: it has no directory to restore)",
            )  # fmt: skip
        return self

    @classmethod
    def from_mapping(cls, data: dict[str, Any]) -> AppConfig:
        """Validate the whole file; errors name the dotted key, the value and what is allowed."""
        known = sorted(_known_keys(cls))
        _check_keys(cls, data, "", known)
        data = dict(data)
        security = SecurityConfig.from_mapping(data.pop("security", None))
        try:
            return cls.model_validate({**data, "security": security})
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


def _nested(annotation: Any) -> tuple[type[BaseModel] | None, bool]:
    """The model a field holds (and whether as a list of them), else ``(None, False)``."""
    args = getattr(annotation, "__args__", ())
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation, False
    if getattr(annotation, "__origin__", None) is list and args:
        inner, _ = _nested(args[0])
        return inner, inner is not None
    return None, False


def _known_keys(model: type[BaseModel], prefix: str = "") -> list[str]:
    """Every key the file may hold, dotted (``keys[].kid`` for an entry of a list)."""
    found = []
    for name, field in model.model_fields.items():
        found.append(prefix + name)
        inner, many = _nested(field.annotation)
        if inner is not None:
            found += _known_keys(inner, f"{prefix}{name}{'[]' if many else ''}.")
    return found


def _check_keys(model: type[BaseModel], data: Any, prefix: str, known: list[str]) -> None:
    """Refuse an unknown key at any level, naming the known key it most resembles."""
    if not isinstance(data, dict):
        return  # pydantic names the wrong type
    for key, value in data.items():
        field = model.model_fields.get(str(key))
        if field is None:
            raise unknown_key(prefix + str(key), known)
        inner, many = _nested(field.annotation)
        if inner is None:
            continue
        if not many:
            _check_keys(inner, value, f"{prefix}{key}.", known)
        elif isinstance(value, list):
            for item in value:
                _check_keys(inner, item, f"{prefix}{key}[].", known)
