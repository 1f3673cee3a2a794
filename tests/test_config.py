"""Configuration: YAML in, validated values or a ConfigError naming key, value and range."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from antireplay import ConfigError, ManualClock, ReplayCache, SecurityConfig
from antireplay.config import AppConfig
from antireplay.state.memory import MemoryStore


def test_yaml_config_round_trip(impl: Callable[..., ReplayCache], tmp_path: Path) -> None:
    path = tmp_path / "robot.yaml"
    path.write_text("security:\n  replay_window_s: 60\n  msg_id_cache_size: 500\n  skew_s: 2\n")
    cfg = SecurityConfig.from_yaml(path)
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
        ("security:\n  replay_windows_s: 30\n", "security.replay_windows_s", 30),
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
        SecurityConfig.from_yaml(path)
    assert err.value.key == key
    assert err.value.value == value
    assert "allowed" in str(err.value)


def test_legacy_nack_type_31_is_accepted(tmp_path: Path) -> None:
    path = tmp_path / "robot.yaml"
    path.write_text("security:\n  nack_type: 31\n")
    assert SecurityConfig.from_yaml(path).nack_type == 31


def test_missing_and_broken_yaml_are_config_errors(tmp_path: Path) -> None:
    with pytest.raises(ConfigError):
        SecurityConfig.from_yaml(tmp_path / "absent.yaml")
    broken = tmp_path / "broken.yaml"
    broken.write_text("security: [\n")
    with pytest.raises(ConfigError):
        SecurityConfig.from_yaml(broken)
    empty = tmp_path / "empty.yaml"
    empty.write_text("")
    assert SecurityConfig.from_yaml(empty).replay_window_s == 30


@pytest.mark.parametrize("spec", ["memroy", "sqlite:", "sqlite: state.db", "postgres://h"])
def test_app_config_store_is_checked_by_the_store_grammar(spec: str) -> None:
    with pytest.raises(ConfigError) as refused:
        AppConfig.from_mapping({"store": spec})
    assert (refused.value.key, refused.value.value) == ("store", spec)
    assert "sqlite:PATH" in refused.value.allowed
