"""The PQ ends' wiring: keys loaded and type-checked, the trail opened as ``serve`` opens it."""

from __future__ import annotations

from pathlib import Path

import pytest

from antireplay.audit import Retention
from antireplay.config import AppConfig
from antireplay.core.errors import ConfigError
from antireplay.wiring import open_pq_end
from harness import free_udp_port, pq_keys


def test_a_vehicle_end_opens_its_trail_rotated_retained_and_floored(tmp_path: Path) -> None:
    pq_keys(tmp_path)
    config = AppConfig.from_mapping({
        "audit": {"segment_bytes": 1 << 20, "max_bytes": 4 << 20},
        "audit_space": {"min_free_bytes": 1 << 62, "refuse_free_bytes": 0},
        "mavlink_pq": {"vehicle": {
            "fc": f"udpout:127.0.0.1:{free_udp_port()}", "air": "udpin:127.0.0.1:0",
            "kem_key": str(tmp_path / "vehicle.key.pem"),
            "peers": {"gcs": str(tmp_path / "gcs.pub.pem")},
        }},
    })  # fmt: skip
    parts = open_pq_end(config, "vehicle", str(tmp_path / "vehicle.db"))
    try:
        assert parts.audit.retention == Retention(1 << 20, 86_400, 4 << 20, None)
        assert tmp_path.joinpath("vehicle.db.spill").exists()
        assert parts.refusals.auditor.quiet()  # below the first floor: counted, not written
    finally:
        parts.close()


@pytest.mark.parametrize(
    ("block", "key", "said"),
    [
        ({"air": "udpin:127.0.0.1:0"}, "mavlink_pq.ground.signing_key", "give --signing-key"),
        ({"signing_key": "vehicle.key.pem", "vehicle_key": "vehicle.pub.pem"},
         "mavlink_pq.ground.signing_key", "not a MLDSA87PrivateKey"),
        ({"signing_key": "gcs.key.pem", "vehicle_key": "gone.pem"},
         "mavlink_pq.ground.vehicle_key", "not a PEM public key"),
        ({"signing_key": "gcs.key.pem", "vehicle_key": "vehicle.pub.pem"},
         "mavlink_pq.ground.air", "give --air"),
    ],
)  # fmt: skip
def test_a_ground_ends_keys_are_named_by_their_key(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, block: dict[str, str], key: str, said: str
) -> None:
    pq_keys(tmp_path)
    monkeypatch.chdir(tmp_path)
    config = AppConfig.from_mapping({"mavlink_pq": {"ground": block}})
    with pytest.raises(ConfigError) as refused:
        open_pq_end(config, "ground", str(tmp_path / "ground.db"))
    assert refused.value.key == key and said in str(refused.value)
