"""The sections every command shares: ``state:`` (the anchor), ``audit:`` and ``audit_space:``.

Theory of operation
-------------------
The audit trail of ``serve``, ``mavlink-router``, ``mavlink-pq`` and the ``dds`` commands
is rotated, retained and floored by these blocks alike: a command with a trail of its own
by default (``.antireplay/mavlink-audit.db``) keeps that path unless ``audit.path`` is
set (:meth:`AuditConfig.path_set`), so one file can serve several commands without two of
them writing one trail.  Values are range-checked and strictly typed; ``audit.max_bytes``
must hold two segments (retention never removes the live one).  A Redis anchor URL is
checked by the one store grammar (:meth:`~antireplay.state.StoreSpec.parse`).
"""

from __future__ import annotations

from typing import Any

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationInfo,
    field_validator,
    model_validator,
)

from antireplay.core.errors import ConfigError
from antireplay.state.spec import StoreSpec


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
    #: The head key: a file (default PATH.key, made on first use), or a generic secret in a
    #: PKCS#11 token (``pkcs11:token=...;object=...``) that computes the HMAC itself.
    head_key: str | None = Field(default=None, min_length=1)

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

    def path_set(self) -> bool:
        """Whether the file named the path (else a command's own default stands)."""
        return "path" in self.model_fields_set

    def at(self, path: str) -> AuditConfig:
        """This block with its trail at ``path`` (a command's flag or its own default)."""
        return self.model_copy(update={"path": path})

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
