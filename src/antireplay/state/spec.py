"""The one store-spec grammar: the text a config file or an option names a store with.

Theory of operation
-------------------
Like a MAVLink connection string, one line of text selects a backend and where
its state lives:

* ``memory``: this process only (fences at start: it cannot know what a
  previous process accepted);
* ``sqlite:PATH``: one machine; the path must not be blank nor start or end
  with blanks (a stray space would name another file);
* ``redis://…``, ``rediss://…`` (TLS), ``unix://PATH``: standalone Redis;
* ``redis+cluster://HOST:PORT``: Redis Cluster.

:meth:`StoreSpec.parse` is the only parser: configuration validation, the
commands' options and :func:`~antireplay.state.open_store` all call it, so a
spec accepted by one is accepted by every one.  Anything else is a
:class:`~antireplay.core.errors.ConfigError` naming the key, the text and the
forms allowed.  Parsing opens nothing; :func:`~antireplay.state.open_store` builds the store.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from antireplay.core.errors import ConfigError

Backend = Literal["memory", "sqlite", "redis", "redis-cluster"]

#: The forms :meth:`StoreSpec.parse` accepts, in words (errors and docs).
ALLOWED = (
    "a store spec: memory, sqlite:PATH (a non-blank path), redis://HOST:PORT/DB, "
    "rediss://..., unix://PATH or redis+cluster://HOST:PORT"
)
_REDIS = {"redis://": "redis", "rediss://": "redis", "unix://": "redis"}
_CLUSTER = "redis+cluster://"


@dataclass(frozen=True)
class StoreSpec:
    """A parsed store spec: the backend and where (``target``: a path or a URL)."""

    backend: Backend
    text: str
    target: str = ""

    @classmethod
    def parse(cls, text: object, key: str = "store") -> StoreSpec:
        """The spec ``text`` names; ``ConfigError(key, text, ALLOWED)`` if it names none."""
        if not isinstance(text, str):
            raise ConfigError(key, text, ALLOWED)
        if text == "memory":
            return cls("memory", text)
        if text.startswith("sqlite:"):
            path = text[len("sqlite:") :]
            if path and path == path.strip():
                return cls("sqlite", text, path)
            raise ConfigError(key, text, f"{ALLOWED}; the sqlite path is blank or padded")
        if text.startswith(_CLUSTER) and len(text) > len(_CLUSTER) and text == text.strip():
            return cls("redis-cluster", text, "redis://" + text[len(_CLUSTER) :])
        for scheme in _REDIS:
            if text.startswith(scheme) and len(text) > len(scheme) and text == text.strip():
                return cls("redis", text, text)
        raise ConfigError(key, text, ALLOWED)

    def redacted(self) -> str:
        """The spec fit to print: a URL's user and password masked."""
        scheme, sep, rest = self.text.partition("://")
        userinfo, at, location = rest.rpartition("@")
        return f"{scheme}{sep}***@{location}" if sep and at and userinfo else self.text

    def __str__(self) -> str:
        return self.text


__all__ = ["ALLOWED", "Backend", "StoreSpec"]
