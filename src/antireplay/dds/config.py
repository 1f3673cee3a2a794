"""The ``dds:`` configuration block: keys, state files, domain id.  Validated, never clamped.

Unknown keys are errors (a typo cannot leave a default in force), and every
error names the dotted key, the value and what is allowed
(:class:`~antireplay.errors.ConfigError`).  The pre-shared key is read from a
file holding it in hex, never from the YAML itself.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from antireplay.config import load_yaml
from antireplay.errors import ConfigError

MAX_DOMAIN_ID = 232  # Cyclone's port arithmetic; antireplay.dds.domain checks the same
#: The freshness bounds every DDS endpoint defaults to: readers and listeners refuse a sample
#: older than ``MAX_AGE_S`` or sealed more than ``MAX_FORWARD_S`` ahead; writers rotate their
#: prefix past the same ``MAX_FORWARD_S`` (a forward glitch the readers would refuse).
MAX_AGE_S, MAX_FORWARD_S = 30.0, 5.0


class _Block(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)


#: The replay store specs a reader accepts (:func:`antireplay.stores.open_store`).
STORE_SPEC = r"^(memory|sqlite:.+|rediss?://.+|unix://.+|redis\+cluster://.+)$"


class ReaderConfig(_Block):
    topic: str = Field(default="antireplay/commands", min_length=1, max_length=256)
    #: ``memory`` fences at start (module docstring of antireplay.dds.topics).
    store: str = Field(default="memory", pattern=STORE_SPEC)


class WriterConfig(_Block):
    topic: str = Field(default="antireplay/commands", min_length=1, max_length=256)
    state_file: str | None = None


class RelayConfig(_Block):
    service_name: str = Field(min_length=1, max_length=128)
    signer_state: str
    verifier_store: str = Field(pattern=STORE_SPEC)
    ping_listen: str | None = None  # host:port, UDP


class DdsConfig(_Block):
    """The whole ``dds:`` block."""

    domain_id: int = Field(default=0, ge=0, le=MAX_DOMAIN_ID)
    loopback_only: bool = True
    psk_file: str
    #: Required bounds (null is an error, never "unbounded").
    max_age_s: float = Field(default=MAX_AGE_S, gt=0, le=86_400)
    max_forward_s: float = Field(default=MAX_FORWARD_S, gt=0, le=3_600)
    audit: str | None = None
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
            err = exc.errors()[0]
            key = ".".join(["dds", *(str(p) for p in err["loc"])])
            raise ConfigError(key, err.get("input"), err["msg"]) from None

    @classmethod
    def from_yaml(cls, path: str | Path) -> DdsConfig:
        return cls.from_mapping(load_yaml(path).get("dds"))

    def psk(self) -> bytes:
        """The pre-shared key from ``psk_file`` (hex, at least 16 bytes)."""
        try:
            text = Path(self.psk_file).read_text(encoding="ascii").strip()
        except (OSError, UnicodeDecodeError) as exc:
            raise ConfigError("dds.psk_file", self.psk_file, f"a readable file ({exc})") from None
        try:
            key = bytes.fromhex(text)
        except ValueError:
            raise ConfigError("dds.psk_file", self.psk_file, "a file holding hex") from None
        if len(key) < 16:
            raise ConfigError("dds.psk_file", self.psk_file, "a key of at least 16 bytes")
        return key


def parse_udp(spec: str) -> tuple[str, int]:
    """``host:port`` for the ping listener."""
    host, _, port = spec.rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65_536:
        raise ConfigError("dds.relay.ping_listen", spec, "host:port")
    return host, int(port)
