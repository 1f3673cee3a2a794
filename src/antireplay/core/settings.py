"""The RCAN ``security:`` block (§8.3): validated, never clamped.

A misconfigured replay window is a security bug, so a value out of range is an
error that names the key, the value and the allowed range
(:class:`~antireplay.core.errors.ConfigError`), never a silent clamp (the RCAN SDK
clamps ``replay_window_s=1000`` to 300 without a word).  Unknown keys are errors
too, so a typo such as ``replay_windows_s`` cannot leave the default in force
unnoticed.  pydantic does the type work; this module only turns its errors into
ours.  The window policy reads these settings, so they live in the core, which reads no
files: the YAML is read by the configuration layer (:mod:`antireplay.config`; a
``security:`` block alone is ``AppConfig.from_yaml(path).security``).

``nack_type`` is 18 (COMMAND_NACK in the current canonical RCAN numbering) or
31, the number §8.3's text uses, which dates from RCAN v1.5/v1.6; set 31 only
for peers that still speak that numbering.
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from antireplay.core.errors import ConfigError

#: Allowed range of each key, in words, for error messages and the docs.
ALLOWED: dict[str, str] = {
    "replay_window_s": "a number of seconds from 5 to 300",
    "safety_window_s": "a number of seconds from 1 to 10",
    "msg_id_cache_size": "an integer from 1 to 100000000",
    "skew_s": "a number of seconds from 0 to 60",
    "nack_type": "18 (current RCAN numbering) or 31 (RCAN v1.5/v1.6)",
}


class SecurityConfig(BaseModel):
    """The §8.3 settings; every field is range-checked and strictly typed."""

    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)

    replay_window_s: float = Field(default=30.0, ge=5, le=300)
    safety_window_s: float = Field(default=10.0, ge=1, le=10)
    msg_id_cache_size: int = Field(default=10_000, ge=1, le=100_000_000)
    skew_s: float = Field(default=5.0, ge=0, le=60)
    nack_type: Literal[18, 31] = 18

    @classmethod
    def from_mapping(cls, data: Any, *, section: str = "security") -> SecurityConfig:
        """Validate a mapping, raising :class:`ConfigError` on the first bad key."""
        if data is None:
            data = {}
        if not isinstance(data, dict):
            raise ConfigError(section, data, "a mapping of settings")
        for key in data:
            if key not in cls.model_fields:
                raise unknown_key(f"{section}.{key}", [f"{section}.{k}" for k in cls.model_fields])
        for key, value in data.items():
            if isinstance(value, bool):
                raise ConfigError(f"{section}.{key}", value, ALLOWED.get(str(key), "no booleans"))
        try:
            return cls.model_validate(_widen_ints(data))
        except ValidationError as exc:
            err = exc.errors()[0]
            key = ".".join(str(p) for p in err["loc"]) or section
            allowed = ALLOWED.get(key, "only " + ", ".join(sorted(cls.model_fields)))
            raise ConfigError(f"{section}.{key}", err.get("input"), allowed) from None


def unknown_key(path: str, known: Iterable[str]) -> ConfigError:
    """An unknown key, with the known one it most resembles: the same name at another level
    (``replay_window_s`` at the top is ``security.replay_window_s``), else a near spelling."""
    known = list(known)
    leaf = path.rpartition(".")[2]
    same_name = [k for k in known if k.rpartition(".")[2] == leaf]
    close = same_name or difflib.get_close_matches(path, known, 1, 0.7)
    if not close:
        leaves = {k.rpartition(".")[2]: k for k in known}
        close = [leaves[m] for m in difflib.get_close_matches(leaf, list(leaves), 1, 0.7)]
    hint = f" (did you mean `{close[0]}`?)" if close else ""
    return ConfigError(path, path, "a known key", message=f"unknown key `{path}`{hint}")


def _widen_ints(data: dict[Any, Any]) -> dict[Any, Any]:
    """Strict mode refuses ``30`` for a float field; YAML users write ints for seconds."""
    float_keys = {"replay_window_s", "safety_window_s", "skew_s"}
    return {k: float(v) if k in float_keys and type(v) is int else v for k, v in data.items()}
