"""Fuzz targets: every adapter input a peer controls, and the contract each must keep.

Each target is a function of raw bytes that raises only when the contract is
broken: an exception outside the typed :class:`ReplayAttackError` family, an
HTTP 5xx, or a typed answer with the wrong shape.  The same functions run under
atheris (``python -m tests.fuzz``, coverage-guided, millions of inputs) and under
pytest (``tests/fuzz/test_corpus.py`` replays ``tests/corpus/<target>/``), so a
finding, once saved in the corpus, is a regression test forever.

Targets (the names are the corpus folders):

* ``envelope``: :func:`antireplay.rcan.envelope.parse` and everything the pipeline
  then asks of an envelope (canonical bytes, re-encoding, ``sig``, SDK subset,
  window check);
* ``receiver``: :meth:`Receiver.receive` with headers (JWT, SDK-compat keys);
* ``http``: the real gateway app (:func:`antireplay.wiring.create_app` on its
  embedded default: SQLite state and audit in a temporary folder), called as
  ASGI with fuzzed headers and body;
* ``mavlink``: :func:`split_frames`, :class:`FrameReader`, :func:`parse_frame`,
  :meth:`MavlinkGuard.check`;
* ``session``: :func:`parse_frame_head`, :meth:`Responder.open`,
  :meth:`Responder.accept_handshake`;
* ``epochs``: :meth:`EpochVerifier.open` and ``open_ping``.
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import tempfile
from collections.abc import Callable, MutableMapping
from functools import cache
from pathlib import Path
from typing import Any

from cryptography.hazmat.primitives.asymmetric import ed25519, mldsa, mlkem

from antireplay import ManualClock, ReplayAttackError, SecurityConfig
from antireplay.audit import sanitize
from antireplay.core.errors import Code
from antireplay.epochs import EpochSigner, EpochVerifier
from antireplay.mavlink import FrameReader, MavlinkGuard, parse_frame, split_frames
from antireplay.mavlink.codec import MAX_FRAME
from antireplay.pq.session import Initiator, Responder, parse_frame_head
from antireplay.rcan.auth import JwtVerifier, KeyRegistry, b64encode, sign_envelope, write_key_pair
from antireplay.rcan.envelope import (
    canonical_bytes,
    encode,
    parse,
    safety_class,
    sdk_signed_bytes,
    unsigned_policy_fields,
    without_delivery_hints,
)
from antireplay.rcan.receive import Receiver
from antireplay.state.memory import MemoryStore
from antireplay.state.replay import ReplayCache
from antireplay.wiring import DEMO_KID, create_app, embedded_default

NOW = 1_800_000_000.0
#: Fixed keys, so the seed corpus stays valid from one run to the next.
ED = ed25519.Ed25519PrivateKey.from_private_bytes(bytes(range(32)))
PQ = mldsa.MLDSA65PrivateKey.from_seed_bytes(bytes(range(32)))
HS256 = b"fuzz-secret-fuzz-secret-fuzz-secret!"
MAV_KEY = bytes(range(32, 64))
PSK = bytes(range(64, 96))
CONTENT_TYPES = (
    "application/json",
    "application/json; charset=utf-8",
    "text/plain",
    "",
    "APPLICATION/JSON",
)
TYPED = tuple(Code)


def _typed(exc: ReplayAttackError) -> None:
    assert exc.code in TYPED
    assert 400 <= exc.http_status < 600
    assert isinstance(exc.reason, str)
    json.dumps(exc.to_nack(sanitize("x")))


# --- envelope --------------------------------------------------------------------------------


@cache
def _window() -> ReplayCache:
    return ReplayCache(30, 1_000, 5.0, ManualClock(wall=NOW))


def check_envelope(data: bytes) -> None:
    """parse() and every later use of an envelope: typed errors only."""
    try:
        env = parse(data)
    except ReplayAttackError as exc:
        assert exc.code in (Code.INVALID_ENVELOPE, Code.INVALID_TIMESTAMP), exc
        _typed(exc)
        return
    canonical_bytes(env)
    sanitize(env.msg_id)
    unsigned_policy_fields(env)
    without_delivery_hints(env)
    for step in (env.signature, lambda: sdk_signed_bytes(env), lambda: json.loads(encode(env))):
        try:
            step()
        except ReplayAttackError as exc:
            _typed(exc)
    try:
        _window().check(env.msg_id, env.seconds, *safety_class(env))
    except ReplayAttackError as exc:
        _typed(exc)


# --- receiver ------------------------------------------------------------------------------


@cache
def _receiver() -> Receiver:
    keys = KeyRegistry(sdk_compat=True)
    keys.add("op-ed", "operator", "ed25519", ED.public_key(), {"control", "safety"})
    keys.add("op-pq", "operator", "ml-dsa-65", PQ.public_key(), {"control"})
    jwt = JwtVerifier({"op-ed": ED.public_key()}, hs256_secret=HS256, clock=ManualClock(wall=NOW))
    return Receiver(SecurityConfig(), keys, MemoryStore(), None, ManualClock(wall=NOW), jwt=jwt)


def _split_headers(data: bytes) -> tuple[dict[str, str], bytes]:
    """First byte: length of a header value (as latin-1, like ASGI servers decode it)."""
    if not data:
        return {}, data
    size = data[0]
    value, rest = data[1 : 1 + size], data[1 + size :]
    return {"authorization": "Bearer " + value.decode("latin-1")}, rest


def check_receiver(data: bytes) -> None:
    """Receiver.receive never raises and answers with a code and a 4xx on rejection."""
    headers, body = _split_headers(data)
    outcome = _receiver().receive(body, headers)
    if outcome.accepted:
        assert outcome.status == 200
        json.dumps(outcome.ack)
        return
    assert outcome.code in TYPED and 400 <= outcome.status < 500, outcome
    json.dumps(outcome.nack)


# --- http ----------------------------------------------------------------------------------


class _Http:
    """The real gateway app on its embedded default, spoken to as ASGI on one event loop."""

    def __init__(self) -> None:
        self.dir = Path(tempfile.mkdtemp(prefix="antireplay-fuzz-"))
        write_key_pair(ED, self.dir / f"{DEMO_KID}.key.pem", self.dir / f"{DEMO_KID}.pub.pem")
        self.app = create_app(embedded_default(self.dir), clock=ManualClock(wall=NOW))
        self.loop = asyncio.new_event_loop()

    def request(self, headers: list[tuple[bytes, bytes]], body: bytes) -> tuple[int, bytes]:
        return self.loop.run_until_complete(self._call(headers, body))

    async def _call(self, headers: list[tuple[bytes, bytes]], body: bytes) -> tuple[int, bytes]:
        scope = {
            "type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1",
            "method": "POST", "scheme": "http", "path": "/v1/messages", "raw_path": b"",
            "query_string": b"", "root_path": "", "headers": headers,
            "client": ("127.0.0.1", 1), "server": ("127.0.0.1", 80),
        }  # fmt: skip
        sent: list[MutableMapping[str, Any]] = []
        chunks = [body[:7], body[7:]] if len(body) > 7 else [body]

        async def receive() -> dict[str, Any]:
            if chunks:
                chunk = chunks.pop(0)
                return {"type": "http.request", "body": chunk, "more_body": bool(chunks)}
            return {"type": "http.disconnect"}

        async def send(message: MutableMapping[str, Any]) -> None:
            sent.append(message)

        await self.app(scope, receive, send)
        start = next(m for m in sent if m["type"] == "http.response.start")
        answer = b"".join(m.get("body", b"") for m in sent if m["type"] == "http.response.body")
        return int(start["status"]), answer


@cache
def http_app() -> _Http:
    return _Http()


def http_request(data: bytes) -> tuple[list[tuple[bytes, bytes]], bytes]:
    """Byte 0: content type and framing flags; byte 1: raw header length; then header, body."""
    flags = data[0] if data else 0
    size = data[1] if len(data) > 1 else 0
    raw_header, body = data[2 : 2 + size], data[2 + size :]
    headers = [(b"content-type", CONTENT_TYPES[flags % len(CONTENT_TYPES)].encode())]
    if flags & 0x08:
        headers.append((b"content-length", str(len(body)).encode()))
    if flags & 0x10:
        headers.append((b"content-length", raw_header or b"x"))
    if flags & 0x20:
        headers.append((b"transfer-encoding", b"chunked"))
    if flags & 0x40:
        headers.append((b"authorization", b"Bearer " + raw_header))
    if flags & 0x80:
        headers.append((b"x-" + hashlib.sha256(raw_header).hexdigest()[:6].encode(), raw_header))
    return headers, body


def check_http(data: bytes) -> None:
    """The gateway answers every request with 200 or a 4xx carrying a NACK code."""
    headers, body = http_request(data)
    status, answer = http_app().request(headers, body)
    assert 200 <= status < 500, (status, answer[:200])
    if status != 200:
        assert json.loads(answer)["code"] in TYPED


# --- mavlink -------------------------------------------------------------------------------


@cache
def _guard() -> MavlinkGuard:
    clock = ManualClock(wall=NOW)
    return MavlinkGuard(MAV_KEY, store=MemoryStore(), clock=clock, system_id=1,
                        allow_unsigned=frozenset({0}), reorder_window=4)  # fmt: skip


def check_mavlink(data: bytes) -> None:
    """split_frames, the stream reader, parse_frame and the guard raise typed errors only;
    the reader returns only frames that parse and holds at most one frame's bytes."""
    reader = FrameReader()
    cut = reader.feed(data[: len(data) // 2]) + reader.feed(data[len(data) // 2 :])
    if reader.pending > MAX_FRAME:
        raise AssertionError(f"the reader holds {reader.pending} bytes")
    for raw in cut:
        parse_frame(raw)
    try:
        frames = split_frames(data)
    except ReplayAttackError as exc:
        _typed(exc)
        frames = [data]
    for frame in frames:
        for step in (parse_frame, _guard().check):
            try:
                step(frame)
            except ReplayAttackError as exc:
                _typed(exc)


# --- session -------------------------------------------------------------------------------

RESPONDER_KEY = mlkem.MLKEM1024PrivateKey.from_seed_bytes(bytes(range(64)))
INITIATOR_KEY = mldsa.MLDSA87PrivateKey.from_seed_bytes(bytes(range(1, 33)))


@cache
def _responder() -> Responder:
    return Responder(
        RESPONDER_KEY, {"ground": INITIATOR_KEY.public_key()}, clock=ManualClock(wall=NOW)
    )


def check_session(data: bytes) -> None:
    """Frame heads, session frames and handshakes: typed errors only."""
    steps: tuple[Callable[[bytes], object], ...] = (
        parse_frame_head,
        _responder().open,
        _responder().accept_handshake,
    )
    for step in steps:
        try:
            step(data)
        except ReplayAttackError as exc:
            _typed(exc)


# --- epochs --------------------------------------------------------------------------------


@cache
def _verifier() -> EpochVerifier:
    return EpochVerifier(PSK, max_age_s=60, max_forward_s=60, clock=ManualClock(wall=NOW))


def check_epochs(data: bytes) -> None:
    """Announcements and pings: typed errors only."""
    for step in (_verifier().open, _verifier().open_ping):
        try:
            step(data)
        except ReplayAttackError as exc:
            _typed(exc)


TARGETS: dict[str, Callable[[bytes], None]] = {
    "envelope": check_envelope,
    "receiver": check_receiver,
    "http": check_http,
    "mavlink": check_mavlink,
    "session": check_session,
    "epochs": check_epochs,
}


# --- seeds: valid inputs the mutations start from ------------------------------------------


def _envelopes() -> list[bytes]:
    base = {
        "rcan": "3.2", "rcan_version": "3.2", "msg_id": "seed-1", "timestamp": NOW - 1,
        "cmd": "move_forward", "target": "rcan://registry.rcan.dev/acme/arm/v2/unit-001",
        "params": {"distance_m": 1.0, "nested": [{"a": [1, 2.5, None, True]}]},
    }  # fmt: skip
    estop = {**base, "msg_id": "seed-2", "type": 6, "safety_event": "ESTOP", "cmd": "estop"}
    millis = {k: v for k, v in base.items() if k != "timestamp"}
    millis.update(msg_id="seed-3", timestamp_ms=int(NOW * 1000) - 500, qos=1, scope="control")
    signed = [sign_envelope(m, "op-ed", "ed25519", ED) for m in (base, estop, millis)]
    signed.append(sign_envelope({**base, "msg_id": "seed-4"}, "op-pq", "ml-dsa-65", PQ))
    sdk: dict[str, Any] = {**base, "msg_id": "seed-5"}
    sdk["sig"] = {"alg": "ml-dsa-65", "kid": "op-pq", "value": ""}
    sdk_bytes = sdk_signed_bytes(parse(json.dumps(sdk).encode()))
    sdk["sig"]["value"] = b64encode(PQ.sign(sdk_bytes))
    # Safety by signed cmd (an SDK ESTOP with its qos hint), and a contradicting event.
    sdk_estop: dict[str, Any] = {**base, "msg_id": "seed-6", "cmd": "ESTOP", "qos": 2}
    sdk_estop["sig"] = {**sdk["sig"], "value": ""}
    estop_bytes = sdk_signed_bytes(parse(json.dumps(sdk_estop).encode()))
    sdk_estop["sig"]["value"] = b64encode(PQ.sign(estop_bytes))
    stop = {**base, "msg_id": "seed-7", "cmd": "STOP"}
    signed.append(sign_envelope(stop, "op-ed", "ed25519", ED))
    contradiction = {**base, "msg_id": "seed-8", "cmd": "ESTOP", "safety_event": "RESUME"}
    return [json.dumps(m).encode() for m in [*signed, sdk, sdk_estop, contradiction, base]]


def seeds(target: str) -> list[bytes]:
    """Valid (or nearly valid) inputs for ``target``."""
    if target in ("envelope",):
        return _envelopes()
    if target == "receiver":
        return [b"\x00" + e for e in _envelopes()]
    if target == "http":
        return [bytes([0x08, 0]) + e for e in _envelopes()] + [bytes([0x28, 0]) + _envelopes()[0]]
    if target == "mavlink":
        from pymavlink.dialects.v20 import common  # noqa: PLC0415

        from antireplay.mavlink import TimestampSource, sign_frame  # noqa: PLC0415

        mav = common.MAVLink(None, srcSystem=255, srcComponent=190)
        heartbeat = common.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3).pack(mav)
        stamps = TimestampSource(ManualClock(wall=NOW))
        return [heartbeat, sign_frame(heartbeat, MAV_KEY, 0, stamps)]
    if target == "session":
        initiator = Initiator("ground", INITIATOR_KEY, clock=ManualClock(wall=NOW))
        hs1 = initiator.start(RESPONDER_KEY.public_key())
        _, hs2 = _responder().accept_handshake(hs1)
        session = initiator.finish(hs1, hs2)
        fresh = initiator.start(RESPONDER_KEY.public_key())
        return [fresh, session.seal(b"hello"), session.seal(b"hello")]
    signer = EpochSigner(PSK, clock=ManualClock(wall=NOW))
    return [signer.seal(b"announce"), signer.seal_ping(b"ping")]
