"""The gateway's own sections: the sender keys (``keys:``) and bearer tokens (``jwt:``).

Theory of operation
-------------------
Each block is a strict, frozen model: a wrong type or an unknown key is an error, never a
default.  Key files are named here, never read: :mod:`antireplay.wiring.gateway` loads
them into a key registry (the one loader, :func:`~antireplay.rcan.auth.load_public_key`).
A key may carry a validity period (``not_before`` / ``not_after``, ISO 8601 with a zone,
e.g. ``2027-01-01T00:00:00Z``): outside it the gateway refuses the key
(``KEY_NOT_YET_VALID`` / ``KEY_EXPIRED``), so a rotation overlaps two kids of one owner.
The store, anchor and audit sections the gateway shares with every other command live in
:mod:`antireplay.config.common`; the whole file is :class:`~antireplay.config.AppConfig`.
"""

from __future__ import annotations

from datetime import datetime
from typing import Literal

from pydantic import AwareDatetime, BaseModel, ConfigDict, Field, field_validator, model_validator

#: The longest kid (config and ``antireplay keys``).
KID_MAX = 128


def kid_problem(kid: str) -> str | None:
    """Why ``kid`` is not a kid (``None``: it is): printable, no whitespace or control
    characters, at most :data:`KID_MAX` characters, valid UTF-8 (a kid ends up in lists,
    audit rows and NACKs an operator reads)."""
    if not kid:
        return "a kid is not empty"
    if len(kid) > KID_MAX:
        return f"a kid is at most {KID_MAX} characters (this one has {len(kid)})"
    try:
        kid.encode()
    except UnicodeEncodeError:
        return "a kid is valid UTF-8"
    if any(c.isspace() or not c.isprintable() for c in kid):
        return "a kid has no whitespace or control characters"
    return None


class KeyConfig(BaseModel):
    """One signing key of the registry (``keys:`` list)."""

    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)

    kid: str = Field(min_length=1, max_length=KID_MAX)
    owner: str = Field(min_length=1, max_length=128)
    alg: Literal["ed25519", "ml-dsa-65", "ml-dsa-87", "ed25519+ml-dsa-65"]
    public_keys: list[str] = Field(min_length=1, max_length=2)  # PEM file paths
    scopes: list[str] = Field(default_factory=lambda: ["control"])
    not_before: AwareDatetime | None = Field(default=None, strict=False)  # ISO 8601, a zone
    not_after: AwareDatetime | None = Field(default=None, strict=False)

    @field_validator("kid")
    @classmethod
    def _kid(cls, kid: str) -> str:
        problem = kid_problem(kid)
        if problem is not None:
            raise ValueError(problem)
        return kid

    @model_validator(mode="after")
    def _period(self) -> KeyConfig:
        if self.not_before and self.not_after and self.not_after <= self.not_before:
            raise ValueError("not_after must be later than not_before")
        return self

    @staticmethod
    def seconds(moment: datetime | None) -> float | None:
        """A bound as Unix seconds (``None``: unbounded)."""
        return None if moment is None else moment.timestamp()


class JwtConfig(BaseModel):
    """Bearer tokens (``jwt:``)."""

    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)

    required: bool = False
    audience: str | None = None
    issuer: str | None = None
    keys: dict[str, str] = Field(default_factory=dict)  # kid -> PEM path (EdDSA / ES256)
    hs256_secret_env: str | None = None  # name of an environment variable; HS256 only if set
    leeway_s: float = Field(default=0.0, ge=0, le=300)
