"""The ``dds:`` configuration block: keys, state files, domain id.  Validated, never clamped.

Theory of operation
-------------------
Unknown keys are errors (a typo cannot leave a default in force; a key that was
renamed says what it is called now), and every error names the dotted key, the
value and what is allowed (:class:`~antireplay.core.errors.ConfigError`); when
several keys are wrong, the first is the error and the others follow in its
text.  The pre-shared key is read from a file holding it in hex, never from the
YAML itself.  The block is read as a section of the whole file
(``AppConfig.from_yaml(path).dds``), so a DDS key outside it is refused by name instead
of leaving a default in force.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from pydantic import AwareDatetime, Field, ValidationError, field_validator, model_validator
from pydantic_core import ErrorDetails

from antireplay.config.loader import Section
from antireplay.core.errors import ConfigError
from antireplay.epochs.policy import KeyRotation
from antireplay.state import STORE_SPECS, StoreSpec

MAX_DOMAIN_ID = 232  # Cyclone's port arithmetic; antireplay.dds.domain checks the same
#: The freshness bounds every DDS endpoint defaults to: readers and listeners refuse a sample
#: older than ``MAX_AGE_S`` or sealed more than ``MAX_FORWARD_S`` ahead; writers rotate their
#: prefix past the same ``MAX_FORWARD_S`` (a forward glitch the readers would refuse).
MAX_AGE_S, MAX_FORWARD_S = 30.0, 5.0


def _store_spec(value: str) -> str:
    """A replay store spec, checked by the one grammar (:meth:`StoreSpec.parse`)."""
    StoreSpec.parse(value)
    return value


#: What each constrained key allows, in words (pydantic's wording names no unit or spec).
ALLOWED: dict[str, str] = {
    "store": STORE_SPECS,
    "verifier_store": STORE_SPECS,
    "max_age_s": "a number of seconds above 0 and at most 86400",
    "max_forward_s": "a number of seconds above 1 (writers reserve 1 s of epochs at a time) "
    "and at most 3600",
    "key_cutover": "an ISO 8601 time with its zone (e.g. 2026-12-06T14:00:00Z), "
    "set together with key_next_file",
}
#: Keys of earlier releases, by their dotted path under ``dds``, and what replaced them.
RENAMED: dict[str, str] = {
    "relay.verifier_state": "dds.relay.verifier_store (a store spec, e.g. sqlite:PATH)",
    "reader.state_file": "dds.reader.store (a store spec, e.g. sqlite:PATH)",
}


class ReaderConfig(Section):
    topic: str = Field(default="antireplay/commands", min_length=1, max_length=256)
    #: ``memory`` fences at start (module docstring of antireplay.dds.topics).
    store: str = "memory"

    @field_validator("store")
    @classmethod
    def _spec(cls, value: str) -> str:
        return _store_spec(value)


class WriterConfig(Section):
    topic: str = Field(default="antireplay/commands", min_length=1, max_length=256)
    state_file: str | None = None


class RelayConfig(Section):
    service_name: str = Field(min_length=1, max_length=128)
    signer_state: str
    verifier_store: str
    ping_listen: str | None = None  # host:port, UDP

    @field_validator("verifier_store")
    @classmethod
    def _spec(cls, value: str) -> str:
        return _store_spec(value)


class DdsConfig(Section):
    """The whole ``dds:`` block."""

    domain_id: int = Field(default=0, ge=0, le=MAX_DOMAIN_ID)
    loopback_only: bool = True
    psk_file: str
    #: Required bounds (null is an error, never "unbounded").
    max_age_s: float = Field(default=MAX_AGE_S, gt=0, le=86_400)
    max_forward_s: float = Field(default=MAX_FORWARD_S, gt=1, le=3_600)
    audit: str | None = None
    #: A fleet key rotation: the successor's file (hex) and the moment writers switch to it;
    #: readers accept both until then (:class:`~antireplay.epochs.policy.KeyRing`).
    key_next_file: str | None = None
    key_cutover: AwareDatetime | None = None
    reader: ReaderConfig = Field(default_factory=ReaderConfig)
    writer: WriterConfig = Field(default_factory=WriterConfig)
    relay: RelayConfig | None = None

    @classmethod
    def from_mapping(cls, data: Any) -> DdsConfig:
        if not isinstance(data, dict):
            raise ConfigError("dds", data, "a mapping (the dds: block)")
        data = {k: float(v) if k.endswith("_s") and type(v) is int else v for k, v in data.items()}
        try:
            return cls.model_validate(data)
        except ValidationError as exc:
            raise _config_error(exc.errors()) from None

    @model_validator(mode="after")
    def _rotation_pair(self) -> DdsConfig:
        if (self.key_next_file is None) != (self.key_cutover is None):
            raise ConfigError("dds.key_cutover", self.key_cutover, ALLOWED["key_cutover"])
        return self

    def psk(self) -> bytes:
        """The pre-shared key from ``psk_file`` (hex, at least 16 bytes)."""
        return _key_file("dds.psk_file", self.psk_file)

    def rotation(self) -> KeyRotation | None:
        """The fleet key's rotation (``key_next_file`` + ``key_cutover``), if one is set."""
        if self.key_next_file is None or self.key_cutover is None:
            return None
        cutover_ns = int(self.key_cutover.timestamp() * 1_000_000_000)
        return KeyRotation(_key_file("dds.key_next_file", self.key_next_file), cutover_ns)


def _key_file(key: str, path: str) -> bytes:
    """A key from the file at ``path`` (hex, at least 16 bytes); ``key`` names it in errors."""
    try:
        text = Path(path).read_text(encoding="ascii").strip()
    except FileNotFoundError:
        raise ConfigError.file_not_found(key, path) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(key, path, f"a readable file ({exc})") from None
    try:
        value = bytes.fromhex(text)
    except ValueError:
        raise ConfigError(key, path, "a file holding hex") from None
    if len(value) < 16:
        raise ConfigError(key, path, "a key of at least 16 bytes")
    return value


class _Missing:
    """The value shown for a required key that is absent."""

    def __repr__(self) -> str:
        return "(missing)"


def _config_error(errors: list[ErrorDetails]) -> ConfigError:
    """One ConfigError for pydantic's errors: renamed keys first, then the rest in order;
    the first names its key and value, the others follow in its text."""
    found = sorted(
        (_explain(err) for err in errors), key=lambda e: not e[2].startswith("no such key")
    )
    key, value, allowed = found[0]
    if len(found) > 1:
        allowed += "; and " + "; ".join(f"{k}={v!r}: allowed {a}" for k, v, a in found[1:])
    return ConfigError(key, value, allowed)


def _explain(err: ErrorDetails) -> tuple[str, object, str]:
    """(dotted key, value, what is allowed) for one pydantic error."""
    path = ".".join(str(part) for part in err["loc"])
    value = err.get("input")
    if err["type"] == "missing":
        return f"dds.{path}", _Missing(), "a value: the key is required"
    if err["type"] == "extra_forbidden":
        renamed = RENAMED.get(path)
        allowed = "no such key" + (f": it was renamed to {renamed}" if renamed else "")
        return f"dds.{path}", value, allowed
    cause = err.get("ctx", {}).get("error")
    if isinstance(cause, ConfigError) and not err["loc"]:  # a rule across keys names its own
        return cause.key, cause.value, cause.allowed
    allowed = (
        cause.allowed
        if isinstance(cause, ConfigError)
        else ALLOWED.get(str(err["loc"][-1]), err["msg"])
    )
    if isinstance(value, float) and math.isnan(value):
        allowed = f"{allowed} (.nan is not a number)"
    return f"dds.{path}", value, allowed


def parse_udp(spec: str) -> tuple[str, int]:
    """``host:port`` for the ping listener."""
    host, _, port = spec.rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65_536:
        raise ConfigError("dds.relay.ping_listen", spec, "host:port")
    return host, int(port)
