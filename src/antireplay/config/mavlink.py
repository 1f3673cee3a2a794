"""The drone sections: ``mavlink:`` (the signing router) and ``mavlink_pq:`` (the PQ ends).

Theory of operation
-------------------
Each key is the router's or an end's command-line option under its own name (``--key-file``
is ``mavlink.key_file``, ``--queue-ttl`` is ``mavlink_pq.ground.queue_ttl_s``); a flag
given on the command line overrides its key (:meth:`~antireplay.config.AppConfig.load`).
Values are range-checked and strictly typed, unknown keys are errors, and the router's
store spec is checked by the one grammar (:meth:`~antireplay.state.StoreSpec.parse`).
Endpoints, message names and key files are named here, never opened or read:
:mod:`antireplay.wiring.mavlink` does that.  Keys a command needs but no default can give
(the vehicle endpoint, the air link, the ends' key files) are optional here and demanded
by the command, which says which flag or key supplies them.
"""

from __future__ import annotations

from pydantic import Field, PrivateAttr, field_validator, model_validator

from antireplay.config.loader import Section
from antireplay.core.counters import DEFAULT_WINDOW
from antireplay.state.spec import StoreSpec


class MetricsConfig(Section):
    """Where a command serves its Prometheus metrics (``metrics:`` of its section)."""

    port: int | None = Field(default=None, ge=0, le=65_535)  # None: no metrics
    host: str = Field(default="127.0.0.1", min_length=1)  # loopback unless asked


class MavlinkConfig(Section):
    """``mavlink:``: the ``mavlink-router`` command."""

    vehicle: list[str] = Field(default_factory=list)
    ground: list[str] = Field(default_factory=list)
    trusted: list[str] = Field(default_factory=list)
    #: Trusted endpoints on the network the operator acknowledges, each exactly as in
    #: ``trusted`` (a trusted endpoint must otherwise be loopback or a serial device).
    trust_network: list[str] = Field(default_factory=list)
    key_file: str | None = Field(default=None, min_length=1)
    passphrase_env: str | None = Field(default=None, min_length=1)
    signing_keys: str | None = Field(default=None, min_length=1)
    system_id: int = Field(default=1, ge=1, le=255)
    store: str = "sqlite:.antireplay/mavlink.db"
    allow_unsigned: list[str] = Field(default_factory=list)
    reorder_window: int = Field(default=0, ge=0, le=DEFAULT_WINDOW)
    max_forward_s: float = Field(default=60.0, gt=0, le=86_400)
    new_stream_max_age_s: float = Field(default=60.0, gt=0, le=86_400)
    sign_link_id: int = Field(default=251, ge=0, le=255)
    write_through: bool = False
    metrics: MetricsConfig = Field(default_factory=MetricsConfig)

    _store_spec: StoreSpec = PrivateAttr()

    @field_validator("store")
    @classmethod
    def _store_grammar(cls, value: str) -> str:
        StoreSpec.parse(value, "mavlink.store")  # the one grammar names what is allowed
        return value

    @model_validator(mode="after")
    def _parsed(self) -> MavlinkConfig:
        self._store_spec = StoreSpec.parse(self.store, "mavlink.store")
        return self

    @property
    def store_spec(self) -> StoreSpec:
        """The router's ``store``, parsed once (when the file was validated)."""
        return self._store_spec


class PqGroundConfig(Section):
    """``mavlink_pq.ground:``: the end next to the ground station."""

    local: str = Field(default="udpin:127.0.0.1:14550", min_length=1)
    air: str | None = Field(default=None, min_length=1)
    identity: str = Field(default="gcs", min_length=1)
    signing_key: str | None = Field(default=None, min_length=1)  # ML-DSA-87 private PEM
    vehicle_key: str | None = Field(default=None, min_length=1)  # ML-KEM-1024 public PEM
    vehicle_x25519: str | None = Field(default=None, min_length=1)  # hybrid handshakes
    system_id: int = Field(default=255, ge=1, le=255)
    queue_ttl_s: float = Field(default=5.0, ge=0, le=600)
    air_bps: int | None = Field(default=None, ge=1_200, le=10_000_000)
    metrics: MetricsConfig = Field(default_factory=MetricsConfig)


class PqVehicleConfig(Section):
    """``mavlink_pq.vehicle:``: the end next to the autopilot."""

    fc: str | None = Field(default=None, min_length=1)
    air: str | None = Field(default=None, min_length=1)
    kem_key: str | None = Field(default=None, min_length=1)  # ML-KEM-1024 private PEM
    peers: dict[str, str] = Field(default_factory=dict)  # operator name -> ML-DSA-87 PEM
    x25519_key: str | None = Field(default=None, min_length=1)  # hybrid handshakes
    system_id: int = Field(default=1, ge=1, le=255)
    max_sessions: int = Field(default=4, ge=1, le=256)
    max_age_s: float = Field(default=10.0, ge=0.5, le=86_400)
    air_bps: int | None = Field(default=None, ge=1_200, le=10_000_000)
    metrics: MetricsConfig = Field(default_factory=MetricsConfig)


class MavlinkPqConfig(Section):
    """``mavlink_pq:``: the two post-quantum ends, one block each."""

    ground: PqGroundConfig = Field(default_factory=PqGroundConfig)
    vehicle: PqVehicleConfig = Field(default_factory=PqVehicleConfig)
