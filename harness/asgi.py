"""A gateway in process: requests through its ASGI app without a socket.

:func:`call` hands a request over as an ASGI server does (the body in two chunks, the
client staying connected); :func:`request` goes through httpx's ASGI transport;
:func:`demo_app` is the demo deployment's gateway on a clock the test may drive.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
from starlette.applications import Starlette
from starlette.types import ASGIApp, Message

from antireplay.cli.demo import JSON, command, load_operator_key, write_demo_config
from antireplay.config import AppConfig
from antireplay.core.clock import Clock
from antireplay.wiring import create_app
from harness.stores import aged_state

NOW = 1_800_000_000.0
LIMIT = 4096


def config(state: Path, public: Path, **overrides: Any) -> AppConfig:
    """The default deployment's shape: SQLite seen-set and audit trail on disk, of a
    deployment started before the test's now (:func:`~harness.stores.aged_state`:
    the real clock's, below every manual clock's ``NOW``)."""
    state.mkdir(exist_ok=True)
    if "store" not in overrides:
        aged_state(state / "state.db")
    return AppConfig.from_mapping({
        "store": f"sqlite:{state / 'state.db'}", "audit": str(state / "audit.db"),
        "max_body_bytes": LIMIT,
        "keys": [{"kid": "operator", "owner": "operator", "alg": "ed25519",
                  "public_keys": [str(public)], "scopes": ["control", "safety"]}],
        **overrides,
    })  # fmt: skip


@dataclass
class Answer:
    status: int
    headers: dict[bytes, bytes]
    body: bytes

    def json(self) -> dict[str, Any]:
        loaded: dict[str, Any] = json.loads(self.body)
        return loaded


async def call(
    app: ASGIApp,
    body: bytes,
    headers: list[tuple[bytes, bytes]] | None = None,
    *,
    length: bool = True,
    method: str = "POST",
    path: str = "/v1/messages",
) -> Answer:
    """One request through ``app`` as an ASGI server hands it over (body in two chunks)."""
    given = [(b"content-type", b"application/json")] if headers is None else headers
    if length:
        given = [*given, (b"content-length", b"%d" % len(body))]
    scope = {
        "type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": method,
        "scheme": "http", "path": path, "raw_path": path.encode(), "query_string": b"",
        "root_path": "", "headers": given, "client": ("127.0.0.1", 1),
        "server": ("127.0.0.1", 80),
    }  # fmt: skip
    chunks = [body[:7], body[7:]]
    sent: list[Message] = []

    async def receive() -> Message:
        if chunks:
            chunk = chunks.pop(0)
            return {"type": "http.request", "body": chunk, "more_body": bool(chunks)}
        await asyncio.Event().wait()  # the client stays connected
        raise AssertionError

    async def send(message: Message) -> None:
        sent.append(message)

    await app(scope, receive, send)
    start = next(m for m in sent if m["type"] == "http.response.start")
    answer = b"".join(m.get("body", b"") for m in sent if m["type"] == "http.response.body")
    return Answer(start["status"], dict(start["headers"]), answer)


def request(app: Starlette, method: str, path: str, content: bytes | None = None) -> httpx.Response:
    """One request to ``app`` through httpx's ASGI transport."""

    async def once() -> httpx.Response:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://gateway") as http:
            return await http.request(method, path, content=content, headers=JSON)

    return asyncio.run(once())


@contextmanager
def demo_app(state: Path, clock: Clock | None = None, **overrides: Any) -> Iterator[Starlette]:
    """The demo deployment's gateway (its files in ``state``) in process; its store closed
    afterwards."""
    written = AppConfig.from_yaml(write_demo_config(state, **overrides))
    if written.store.startswith("sqlite:"):  # a deployment started before the test's now
        aged_state(written.store.removeprefix("sqlite:"), clock)
    app = create_app(written, clock=clock)
    try:
        yield app
    finally:
        app.state.receiver.cache.store.close()


def send_command(app: Starlette, state: Path, age_s: float = 0.0) -> httpx.Response:
    """A fresh command signed with the demo operator key of ``state``, ``age_s`` old."""
    return request(app, "POST", "/v1/messages", command(load_operator_key(state), age_s))
