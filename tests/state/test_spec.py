"""The one store-spec grammar: each accepted form, and a typed refusal for the rest."""

from __future__ import annotations

import pytest

from antireplay.core.errors import ConfigError
from antireplay.state import StoreSpec, open_store
from antireplay.state.memory import MemoryStore
from antireplay.state.spec import ALLOWED


@pytest.mark.parametrize(
    ("text", "backend", "target"),
    [
        ("memory", "memory", ""),
        ("sqlite:state.db", "sqlite", "state.db"),
        ("sqlite:/var/lib/antireplay/state db.db", "sqlite", "/var/lib/antireplay/state db.db"),
        ("redis://127.0.0.1:6379/0", "redis", "redis://127.0.0.1:6379/0"),
        ("rediss://user:pw@redis.example:6380/1", "redis", "rediss://user:pw@redis.example:6380/1"),
        ("unix:///run/redis.sock", "redis", "unix:///run/redis.sock"),
        ("redis+cluster://10.0.0.1:7000", "redis-cluster", "redis://10.0.0.1:7000"),
    ],
)
def test_each_accepted_form(text: str, backend: str, target: str) -> None:
    spec = StoreSpec.parse(text)
    assert (spec.backend, spec.target, str(spec)) == (backend, target, text)


@pytest.mark.parametrize(
    "text",
    [
        "", "memroy", "Memory", "memory ", "sqlite:", "sqlite: ", "sqlite:\t", "sqlite: x.db",
        "sqlite:x.db ", "postgres://x", "redis://", "redis+cluster://", " redis://h:1",
        "/tmp/state.db", "redis:/h:1",
    ],
)  # fmt: skip
def test_anything_else_is_a_config_error_naming_the_input(text: str) -> None:
    with pytest.raises(ConfigError) as refused:
        StoreSpec.parse(text, key="dds.reader.store")
    assert (refused.value.key, refused.value.value) == ("dds.reader.store", text)
    assert ALLOWED in refused.value.allowed


@pytest.mark.parametrize("value", [None, 3, b"memory", ["memory"]])
def test_a_spec_that_is_not_text_is_refused(value: object) -> None:
    with pytest.raises(ConfigError) as refused:
        StoreSpec.parse(value)
    assert refused.value.key == "store" and refused.value.value == value


def test_a_url_prints_without_its_secret() -> None:
    assert StoreSpec.parse("rediss://u:secret@h:1/0").redacted() == "rediss://***@h:1/0"
    assert StoreSpec.parse("sqlite:a@b.db").redacted() == "sqlite:a@b.db"


def test_open_store_takes_a_parsed_spec_or_its_text() -> None:
    assert isinstance(open_store(StoreSpec.parse("memory")), MemoryStore)
    with pytest.raises(ConfigError, match="redis\\+cluster"):
        open_store("memroy")
