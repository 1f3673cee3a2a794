"""Configuration: YAML in, validated values or a ConfigError naming key, value and range."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from antireplay import AppConfig, ConfigError, ManualClock, ReplayCache
from antireplay.state.memory import MemoryStore


def test_yaml_config_round_trip(impl: Callable[..., ReplayCache], tmp_path: Path) -> None:
    path = tmp_path / "robot.yaml"
    path.write_text("security:\n  replay_window_s: 60\n  msg_id_cache_size: 500\n  skew_s: 2\n")
    cfg = AppConfig.from_yaml(path).security
    cache = ReplayCache.from_config(cfg, ManualClock())
    assert isinstance(cache.store, MemoryStore)
    assert (cache.window_s, cache.store.max_entries, cache.policy.skew_s) == (60, 500, 2)


@pytest.mark.parametrize(
    ("yaml_text", "key", "value"),
    [
        ("security:\n  replay_window_s: 1000\n", "security.replay_window_s", 1000),
        ("security:\n  replay_window_s: 2\n", "security.replay_window_s", 2),
        ("security:\n  replay_window_s: fast\n", "security.replay_window_s", "fast"),
        ("security:\n  msg_id_cache_size: -5\n", "security.msg_id_cache_size", -5),
        ("security:\n  nack_type: 19\n", "security.nack_type", 19),
        ("security:\n  skew_s: true\n", "security.skew_s", True),
        ("security: 5\n", "security", 5),
    ],
)
def test_yaml_errors_name_key_value_and_range(
    tmp_path: Path, yaml_text: str, key: str, value: object
) -> None:
    path = tmp_path / "robot.yaml"
    path.write_text(yaml_text)
    with pytest.raises(ConfigError) as err:
        AppConfig.from_yaml(path)
    assert err.value.key == key
    assert err.value.value == value
    assert "allowed" in str(err.value)


def test_legacy_nack_type_31_is_accepted(tmp_path: Path) -> None:
    path = tmp_path / "robot.yaml"
    path.write_text("security:\n  nack_type: 31\n")
    assert AppConfig.from_yaml(path).security.nack_type == 31


def test_missing_and_broken_yaml_are_config_errors(tmp_path: Path) -> None:
    with pytest.raises(ConfigError):
        AppConfig.from_yaml(tmp_path / "absent.yaml")
    broken = tmp_path / "broken.yaml"
    broken.write_text("security: [\n")
    with pytest.raises(ConfigError):
        AppConfig.from_yaml(broken)
    empty = tmp_path / "empty.yaml"
    empty.write_text("")
    assert AppConfig.from_yaml(empty).security.replay_window_s == 30


@pytest.mark.parametrize("spec", ["memroy", "sqlite:", "sqlite: state.db", "postgres://h"])
def test_app_config_store_is_checked_by_the_store_grammar(spec: str) -> None:
    with pytest.raises(ConfigError) as refused:
        AppConfig.from_mapping({"store": spec})
    assert (refused.value.key, refused.value.value) == ("store", spec)
    assert "sqlite:PATH" in refused.value.allowed


@pytest.mark.parametrize(
    ("yaml_text", "message"),
    [
        ("replay_window_s: 30\n",
         "replay_window_s: not a top-level key; it belongs under security:"),
        ("security:\n  replay_windows_s: 30\n",
         "unknown key `security.replay_windows_s` (did you mean `security.replay_window_s`?)"),
        ("stor: memory\n", "unknown key `stor` (did you mean `store`?)"),
        ("jwt: {requird: true}\n", "unknown key `jwt.requird` (did you mean `jwt.required`?)"),
        ("keys: [{kid: a, owner: o, alg: ed25519, public_key: [p.pem]}]\n",
         "unknown key `keys[].public_key` (did you mean `keys[].public_keys`?)"),
        ("frobnicate: 1\n", "unknown key `frobnicate`"),
    ],
)  # fmt: skip
def test_unknown_keys_name_the_key_they_resemble_at_any_level(
    tmp_path: Path, yaml_text: str, message: str
) -> None:
    path = tmp_path / "antireplay.yaml"
    path.write_text(yaml_text)
    with pytest.raises(ConfigError) as err:
        AppConfig.from_yaml(path)
    assert str(err.value) == message


def test_a_missing_file_is_said_in_those_words(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as err:
        AppConfig.from_yaml(tmp_path / "absent.yaml")
    assert str(err.value) == f"config: file not found: {tmp_path / 'absent.yaml'}"


def test_audit_is_a_path_or_a_block_of_retention_keys(tmp_path: Path) -> None:
    """A bare path keeps working (the defaults rotate and bound the trail); the block names
    each limit; either way ``config.audit`` is usable as the trail's path."""
    bare = AppConfig.from_mapping({"audit": "trail/audit.db"})
    assert (str(bare.audit), Path(bare.audit)) == ("trail/audit.db", Path("trail/audit.db"))
    assert (bare.audit.segment_bytes, bare.audit.max_bytes) == (64 << 20, 1 << 30)
    path = tmp_path / "antireplay.yaml"
    path.write_text(
        "audit:\n  path: a.db\n  segment_bytes: 1048576\n  segment_age_s: 3600\n"
        "  max_bytes: null\n  max_age_s: 604800\n"
    )
    block = AppConfig.from_yaml(path).audit
    assert (block.path, block.segment_bytes, block.segment_age_s) == ("a.db", 1 << 20, 3600)
    assert (block.max_bytes, block.max_age_s) == (None, 604_800)


@pytest.mark.parametrize(
    ("audit", "key", "allowed"),
    [
        ({"segment_bytes": 1000}, "audit.segment_bytes", "greater than or equal to 65536"),
        ({"segment_bytes": "64MiB"}, "audit.segment_bytes", "valid integer"),
        ({"max_bytes": 200_000, "segment_bytes": 131_072}, "audit.max_bytes",
         "at least twice audit.segment_bytes (262144), or null"),
        ({"max_age_s": 0}, "audit.max_age_s", "greater than or equal to 60"),
        ({"segment_age_s": True}, "audit.segment_age_s", "valid number"),
    ],
)  # fmt: skip
def test_audit_retention_errors_name_the_key(
    audit: dict[str, object], key: str, allowed: str
) -> None:
    with pytest.raises(ConfigError) as err:
        AppConfig.from_mapping({"audit": audit})
    assert err.value.key == key and allowed in str(err.value)


def test_an_unknown_audit_key_names_the_one_it_resembles() -> None:
    with pytest.raises(ConfigError) as err:
        AppConfig.from_mapping({"audit": {"max_byte": 1}})
    assert str(err.value) == "unknown key `audit.max_byte` (did you mean `audit.max_bytes`?)"


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"max_age_s": 5}, "max_age_s: not a top-level key; it belongs under "
         "audit: or mavlink_pq.vehicle: or dds:"),
        ({"reader": {"store": "memory"}},
         "reader: not a top-level key; it belongs under dds:"),
        ({"signing_key": "op.pem"},
         "signing_key: not a top-level key; it belongs under mavlink_pq.ground:"),
        ({"key_file": "k"}, "key_file: not a top-level key; it belongs under mavlink:"),
        ({"dds": {"psk_file": "k", "key_file": "k"}},
         "dds.key_file: not a key of dds:; it belongs under mavlink:"),
        ({"mavlink": {"replay_window_s": 30}},
         "mavlink.replay_window_s: not a key of mavlink:; it belongs under security:"),
        ({"mavlink_pq": {"ground": {"kem_key": "k"}}}, "mavlink_pq.ground.kem_key: not a key "
         "of mavlink_pq.ground:; it belongs under mavlink_pq.vehicle:"),
        ({"mavlink": {"store": "memory", "metrics": {"prot": 1}}},
         "unknown key `mavlink.metrics.prot` (did you mean `mavlink.metrics.port`?)"),
        ({"audit": {"store": "memory"}},
         "audit.store: not a key of audit:; it belongs at the top level or under "
         "mavlink: or dds.reader:"),
    ],
)  # fmt: skip
def test_a_key_out_of_its_block_names_where_it_belongs(
    data: dict[str, object], message: str
) -> None:
    """Every section, at any depth: a key in the wrong block is refused by name before a
    default could stand in for it."""
    with pytest.raises(ConfigError) as err:
        AppConfig.from_mapping(data)
    assert str(err.value) == message


def test_a_renamed_dds_key_is_named_in_the_whole_file() -> None:
    with pytest.raises(ConfigError) as err:
        AppConfig.from_mapping({"dds": {"psk_file": "k", "reader": {"state_file": "r"}}})
    assert err.value.key == "dds.reader.state_file"
    assert "renamed to dds.reader.store" in str(err.value)


def test_every_section_is_validated() -> None:
    config = AppConfig.from_mapping({
        "mavlink": {"vehicle": ["udpin:127.0.0.1:14555"], "store": "memory", "system_id": 3},
        "mavlink_pq": {"vehicle": {"peers": {"gcs": "gcs.pem"}, "max_age_s": 4}},
        "dds": {"psk_file": "fleet.psk", "max_age_s": 5},
    })  # fmt: skip
    assert (config.mavlink.system_id, config.mavlink.store) == (3, "memory")
    assert config.mavlink_pq.vehicle.peers == {"gcs": "gcs.pem"}
    assert config.dds is not None and config.dds.max_age_s == 5
    for data, key in (
        ({"mavlink": {"store": "memroy"}}, "mavlink.store"),
        ({"mavlink": {"system_id": 0}}, "mavlink.system_id"),
        ({"mavlink_pq": {"ground": {"air_bps": 10}}}, "mavlink_pq.ground.air_bps"),
        ({"dds": {"max_age_s": 5}}, "dds.psk_file"),
    ):
        with pytest.raises(ConfigError) as err:
            AppConfig.from_mapping(data)
        assert err.value.key == key, err.value


def test_flags_override_keys_and_are_held_to_the_same_rules(tmp_path: Path) -> None:
    path = tmp_path / "antireplay.yaml"
    path.write_text("audit: trail.db\nmavlink:\n  store: memory\n  vehicle: [udpin:h:1]\n")
    config = AppConfig.load(path, {"mavlink.store": None, "mavlink.vehicle": ("udpin:h:2",),
                                   "audit.max_bytes": 1 << 30})  # fmt: skip
    assert (config.mavlink.store, config.mavlink.vehicle) == ("memory", ["udpin:h:2"])
    assert (config.audit.path, config.audit.max_bytes) == ("trail.db", 1 << 30)
    with pytest.raises(ConfigError) as err:
        AppConfig.load(path, {"mavlink.system_id": 300})
    assert err.value.key == "mavlink.system_id"
    assert AppConfig.load(None).mavlink.store == "sqlite:.antireplay/mavlink.db"


@pytest.mark.parametrize(
    ("kid", "needle"),
    [("a b", "whitespace"), ("a\x07", "control"), ("k" * 129, "128"), ("\udcff", "unicode")],
    ids=["space", "control", "long", "not-utf8"],
)
def test_a_config_kid_is_printable_short_utf8_without_whitespace(kid: str, needle: str) -> None:
    """The grammar ``antireplay keys revoke`` holds a kid to (``config.gateway.kid_problem``)."""
    key = {"kid": kid, "owner": "op", "alg": "ed25519", "public_keys": ["op.pem"]}
    with pytest.raises(ConfigError) as err:
        AppConfig.from_mapping({"keys": [key]})
    assert err.value.key.startswith("keys") and needle in str(err.value), err.value
