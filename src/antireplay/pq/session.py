"""Post-quantum sessions with session-bound counters (CleitonQ style, with its gaps closed).

Theory of operation
-------------------
Two roles.  The **initiator** (a ground station or operator) owns an ML-DSA-87
identity key; the **responder** (the robot) owns an ML-KEM-1024 key and a
registry of initiator public keys.

Handshake (two messages)::

    HS1  i -> r : 0xA1 | ver | ts_ms u64 | id_len u16 | initiator_id
                  | responder_key_hash[32] | kem_ct[1568] | nonce_i[32] | ML-DSA-87 sig
    HS2  r -> i : 0xA2 | ver | session_id[16] | nonce_r[32] | HMAC-SHA256(confirm_key, transcript)

The signature (context ``antireplay/v1 hs1``) covers everything before it, so
the encapsulation is bound to the initiator's identity and to this responder's
KEM key.  The responder runs the cheap checks first (shape, a 30 s freshness
window and a seen-set on the HS1 digest, :class:`~antireplay.core.window.ReplayCache`),
then verifies the signature and decapsulates, and only then commits the digest.
It picks a **session sequence** (strictly increasing, from a
:class:`~antireplay.core.counters.NonceCounter`) and a fresh ``nonce_r``::

    transcript = SHA-256("antireplay/v1 transcript" | HS1 | seq u64 | nonce_r)
    session_id = seq u64 | transcript[:8]
    key(label) = HKDF-SHA256(ikm=shared_secret, salt=transcript, info="antireplay/v1 " + label)

with labels ``i2r data``, ``r2i data`` and ``confirm``.  A responder that refuses a
parsed HS1 may say why, MACed under :func:`refusal_key` (HKDF of the ML-KEM secret alone,
salted with SHA-256 of that HS1): only the KEM key's holder and that HS1's initiator know it.

**Hybrid option** (X25519 + ML-KEM-1024, for operators who must keep a classical
guarantee): the responder also owns a static X25519 key (``x25519_key``) that the
initiator knows; HS1 then starts with ``0xA3`` and carries an ephemeral X25519 share
after ``kem_ct`` (signed with the rest), and ``shared_secret`` becomes
``SHA3-256(kem_secret | X25519(ephemeral, static) | share | static_pub |
"antireplay/v1 hybrid")``, the concatenation combiner of CleitonQ's ``hybrid.rs``
with both public values bound.  The session keys stand while either ML-KEM-1024 or
X25519 does.  A hybrid responder refuses a PQ-only HS1 (a downgrade) and a PQ-only
one a hybrid HS1, both ``INVALID_FRAME`` before any cryptography.  The X25519 half is
forward-secret against a later theft of the initiator's keys only (the responder's
X25519 key is static; rotate it per mission where that matters).  Because the responder
contributes ``nonce_r`` and a new sequence, even an HS1 replayed after its
window could never reopen a session with the same keys or id.

Frames::

    0xA5 | ver | purpose | direction | session_id[16] | counter u64 | payload | tag

``purpose`` is ``data`` (tag = HMAC-SHA256 under the direction's data key, truncated
to 128 bits: bytes on a 57,600-baud radio count, RFC 2104 allows it) or
``command`` (initiator to responder only; tag = ML-DSA-87 signature by the
initiator's identity key, context ``antireplay/v1 cmd``).  The tag covers the
whole header and the payload, so a frame moved to another session, direction
or purpose fails.  Each (direction, purpose) has its own counter starting at
0 and its own :class:`~antireplay.core.counters.CounterWindow` on the receiving
side, so reordering within 8,128 frames is fine and each counter is accepted
once.  Two phases, as everywhere (:mod:`antireplay.core.counters`): ``check``
records nothing, ``commit`` records; :meth:`Session.open` and
:meth:`Responder.open` are the recipe: parse, window ``check`` (before crypto),
verify, window ``commit``, so a forged far-future counter changes nothing.

Rekeying: :attr:`Session.needs_rekey` turns true at ``REKEY_AFTER`` (2**60)
frames in either direction, long before the hard limit where ``seal`` raises
:class:`~antireplay.core.errors.NonceExhaustedError`.  Bounded memory: a responder
keeps its sessions in a :class:`~antireplay.core.counters.FencedTable` of at most
``max_sessions``, keyed and marked by sequence; the oldest sequence is evicted
*with its keys*, so none of its frames can ever verify again (eviction forces a
new session rather than re-opening a window).  A frame never brings a new key
to that table (only a handshake does), so its fence plays no part in routing:
a frame for a session the responder issued but no longer holds, closed after
a rekey or evicted, gets ``SESSION_CLOSED`` (one event, one code, whatever
happened to other sessions since; the answer is a new handshake), one for a
sequence never issued ``UNKNOWN_SESSION``, and a frame sent in this side's
own direction (reflected back at its sender) ``WRONG_DIRECTION``, as in
MAVLink; all three before any cryptography.

Size: one idea, the handshake both roles run: the transcript, the key schedule and the
refusal key are shared by initiator and responder, and apart they would be written twice.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import struct
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import IntEnum

from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.asymmetric import mldsa, mlkem, x25519
from cryptography.hazmat.primitives.kdf.hkdf import HKDF

from antireplay.core.clock import Clock, resolve
from antireplay.core.counters import COUNTER_LIMIT, CounterWindow, FencedTable, NonceCounter
from antireplay.core.errors import (
    InvalidFrameError,
    SessionClosedError,
    SignatureInvalidError,
    UnknownSenderError,
    UnknownSessionError,
    WrongDirectionError,
)
from antireplay.state.memory import MemoryStore
from antireplay.state.replay import ReplayCache

VERSION = 1
HS1_MAGIC, HS2_MAGIC, FRAME_MAGIC = 0xA1, 0xA2, 0xA5
HS1_HYBRID_MAGIC = 0xA3  # HS1 with an X25519 share (hybrid key establishment)
X25519_LEN = 32
_HYBRID_LABEL = b"antireplay/v1 hybrid"
KEM_CT_LEN, NONCE_LEN, SIG_LEN, MAC_LEN, SESSION_ID_LEN = 1568, 32, 4627, 32, 16
TAG_LEN = 16  # a data frame's tag: HMAC-SHA256 truncated to 128 bits
MAX_ID_LEN = 128
MAX_FRAME = 65_536
REKEY_AFTER = 2**60
HANDSHAKE_WINDOW_S = 30.0
MAX_PENDING = 64
AVOID_TRIES = 64  # Responder.accept_handshake's draws of a session id
_HS1_HEAD = struct.Struct(">BBQH")
_FRAME_HEAD = struct.Struct(">BBBB16sQ")
_HS2_LEN = 2 + SESSION_ID_LEN + NONCE_LEN + MAC_LEN
_CTX_HS1, _CTX_CMD = b"antireplay/v1 hs1", b"antireplay/v1 cmd"


class Purpose(IntEnum):
    DATA = 1
    COMMAND = 2


class Direction(IntEnum):
    I2R = 1
    R2I = 2


@dataclass(frozen=True)
class Opened:
    """An authenticated, fresh frame."""

    payload: bytes
    counter: int
    purpose: Purpose
    session_id: bytes


def _hkdf(secret: bytes, salt: bytes, label: str) -> bytes:
    kdf = HKDF(
        algorithm=hashes.SHA256(), length=32, salt=salt, info=b"antireplay/v1 " + label.encode()
    )
    return kdf.derive(secret)


def refusal_key(kem_secret: bytes, hs1_digest: bytes) -> bytes:
    """A refusal's MAC key: only the KEM key's holder (the responder the HS1 is addressed
    to) and that HS1's initiator know it, and it is new for every HS1 (one attempt)."""
    return _hkdf(kem_secret, hs1_digest, "refusal")


@dataclass(frozen=True)
class _HandshakeKeys:
    """Everything both sides derive from the KEM secret and the transcript."""

    i2r: bytes
    r2i: bytes
    confirmation: bytes  # the HS2 MAC

    @classmethod
    def derive(cls, secret: bytes, transcript: bytes) -> _HandshakeKeys:
        confirm = _hkdf(secret, transcript, "confirm")
        return cls(
            _hkdf(secret, transcript, "i2r data"),
            _hkdf(secret, transcript, "r2i data"),
            hmac.digest(confirm, b"hs2" + transcript, "sha256"),
        )


def _combine(
    kem_secret: bytes, dh_secret: bytes, share: bytes, responder: x25519.X25519PublicKey
) -> bytes:
    """The hybrid secret: a concatenation combiner (NIST SP 800-227; CleitonQ's
    ``hybrid.rs``) that also binds both X25519 public values, secure while either the
    ML-KEM or the X25519 secret is."""
    return hashlib.sha3_256(
        kem_secret + dh_secret + share + responder.public_bytes_raw() + _HYBRID_LABEL
    ).digest()


def _transcript(hs1: bytes, seq: int, nonce_r: bytes) -> bytes:
    return hashlib.sha256(
        b"antireplay/v1 transcript" + hs1 + seq.to_bytes(8, "big") + nonce_r
    ).digest()


@dataclass
class Session:
    """One established session; use :meth:`seal` to send and :meth:`open` to receive."""

    session_id: bytes
    role: Direction  # the direction this side *sends* in
    peer_id: str
    send_key: bytes
    recv_key: bytes
    signing_key: mldsa.MLDSA87PrivateKey | None = None
    peer_verify_key: mldsa.MLDSA87PublicKey | None = None
    _send: dict[Purpose, NonceCounter] = field(default_factory=dict)
    _recv: dict[Purpose, CounterWindow] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for purpose in Purpose:
            self._send[purpose] = NonceCounter(0)
            self._recv[purpose] = CounterWindow()

    @property
    def seq(self) -> int:
        return int.from_bytes(self.session_id[:8], "big")

    @property
    def needs_rekey(self) -> bool:
        """True once any counter passed ``REKEY_AFTER``: start a new handshake now."""
        sent = max(c.peek for c in self._send.values())
        received = max(w.last for w in self._recv.values())
        return max(sent, received) >= REKEY_AFTER

    def seal(self, payload: bytes, purpose: Purpose = Purpose.DATA) -> bytes:
        """Frame ``payload`` with the next counter; commands are signed with ML-DSA-87."""
        counter = self._send[purpose].next()
        head = _FRAME_HEAD.pack(FRAME_MAGIC, VERSION, purpose, self.role, self.session_id, counter)
        if len(head) + len(payload) + (TAG_LEN if purpose is Purpose.DATA else SIG_LEN) > MAX_FRAME:
            raise ValueError("payload too large for one frame")
        if purpose is Purpose.DATA:
            return head + payload + hmac.digest(self.send_key, head + payload, "sha256")[:TAG_LEN]
        if self.signing_key is None:
            raise ValueError("only the initiator signs command frames")
        return head + payload + self.signing_key.sign(head + payload, _CTX_CMD)

    def check(self, frame: bytes) -> None:
        """Raise the typed reason ``frame`` would be refused, its tag aside; records nothing."""
        self.check_parsed(frame, parse_frame_head(frame))

    def open(self, frame: bytes) -> Opened:
        """The recipe: parse, :meth:`check` (pre-crypto), verify, commit."""
        return self.open_parsed(frame, parse_frame_head(frame))

    def check_parsed(self, frame: bytes, head: tuple[Purpose, Direction, bytes, int]) -> None:
        """:meth:`check` for a frame whose header the caller already parsed."""
        purpose, direction, sid, counter = head
        if sid != self.session_id:
            raise UnknownSessionError("frame belongs to another session")
        if direction is self.role:
            raise WrongDirectionError("frame travels in this side's own direction (reflected)")
        if len(frame) < _FRAME_HEAD.size + (TAG_LEN if purpose is Purpose.DATA else SIG_LEN):
            raise InvalidFrameError("frame too short for its tag")
        self._recv[purpose].check(counter)

    def open_parsed(self, frame: bytes, head: tuple[Purpose, Direction, bytes, int]) -> Opened:
        """:meth:`open` for a frame whose header the caller already parsed."""
        self.check_parsed(frame, head)
        purpose, counter = head[0], head[3]
        tag_len = TAG_LEN if purpose is Purpose.DATA else SIG_LEN
        body, tag = frame[:-tag_len], frame[-tag_len:]
        if purpose is Purpose.DATA:
            mac = hmac.digest(self.recv_key, body, "sha256")[:TAG_LEN]
            good = hmac.compare_digest(mac, tag)
        else:
            good = self._verify_command(body, tag)
        if not good:
            raise SignatureInvalidError("frame tag does not verify")
        self._recv[purpose].commit(counter)
        return Opened(body[_FRAME_HEAD.size :], counter, purpose, self.session_id)

    def _verify_command(self, body: bytes, tag: bytes) -> bool:
        if self.peer_verify_key is None:
            return False
        try:
            self.peer_verify_key.verify(tag, body, _CTX_CMD)
        except InvalidSignature:
            return False
        return True


_PURPOSES = {int(p): p for p in Purpose}
_DIRECTIONS = {int(d): d for d in Direction}


def parse_frame_head(frame: bytes) -> tuple[Purpose, Direction, bytes, int]:
    """Strictly parse a frame header; every failure is a typed INVALID_FRAME."""
    if type(frame) is not bytes:
        if not isinstance(frame, bytes | bytearray | memoryview):
            raise InvalidFrameError("frame must be bytes")
        frame = bytes(frame)
    if len(frame) > MAX_FRAME:
        raise InvalidFrameError(f"frame longer than {MAX_FRAME} bytes")
    if len(frame) < _FRAME_HEAD.size + TAG_LEN:
        raise InvalidFrameError("frame too short")
    magic, ver, purpose, direction, sid, counter = _FRAME_HEAD.unpack_from(frame)
    if magic != FRAME_MAGIC or ver != VERSION:
        raise InvalidFrameError("not an antireplay v1 frame")
    p, d = _PURPOSES.get(purpose), _DIRECTIONS.get(direction)
    if p is None or d is None:
        raise InvalidFrameError("unknown purpose or direction")
    return p, d, sid, counter


class Initiator:
    """The side that owns an ML-DSA-87 identity key and opens sessions."""

    def __init__(
        self, identity: str, signing_key: mldsa.MLDSA87PrivateKey, clock: Clock | None = None
    ) -> None:
        raw = identity.encode()
        if not 0 < len(raw) <= MAX_ID_LEN:
            raise ValueError(f"identity must be 1..{MAX_ID_LEN} bytes of UTF-8")
        self.identity = identity
        self.signing_key = signing_key
        self._clock = resolve(clock)
        self._pending: dict[bytes, tuple[bytes, bytes]] = {}
        self._refusal_keys: dict[bytes, bytes] = {}  # by HS1 digest (:func:`refusal_key`)

    def start(
        self,
        responder_key: mlkem.MLKEM1024PublicKey,
        hybrid: x25519.X25519PublicKey | None = None,
    ) -> bytes:
        """Build HS1 for a responder; keep the shared secret until HS2 arrives.  With
        ``hybrid`` (the responder's static X25519 key) HS1 carries an ephemeral X25519
        share too and the secret combines both (module docstring)."""
        kem_secret, kem_ct = responder_key.encapsulate()
        raw_id = self.identity.encode()
        magic = HS1_MAGIC if hybrid is None else HS1_HYBRID_MAGIC
        head = _HS1_HEAD.pack(magic, VERSION, int(self._clock.wall() * 1000), len(raw_id))
        key_hash = hashlib.sha256(responder_key.public_bytes_raw()).digest()
        share, secret = b"", kem_secret
        if hybrid is not None:
            ephemeral = x25519.X25519PrivateKey.generate()
            share = ephemeral.public_key().public_bytes_raw()
            secret = _combine(kem_secret, ephemeral.exchange(hybrid), share, hybrid)
        body = head + raw_id + key_hash + kem_ct + share + os.urandom(NONCE_LEN)
        hs1 = body + self.signing_key.sign(body, _CTX_HS1)
        if len(self._pending) >= MAX_PENDING:
            oldest = next(iter(self._pending))  # the oldest unanswered handshake
            del self._pending[oldest], self._refusal_keys[oldest]
        digest = hashlib.sha256(hs1).digest()
        self._pending[digest] = (hs1, secret)
        self._refusal_keys[digest] = refusal_key(kem_secret, digest)
        return hs1

    def refusal_key(self, hs1: bytes) -> bytes | None:
        """The key the responder MACs its refusal of ``hs1`` under (None: not pending here)."""
        return self._refusal_keys.get(hashlib.sha256(hs1).digest())

    def finish(self, hs1: bytes, hs2: bytes) -> Session:
        """Check the responder's key confirmation and derive the session; a forged HS2
        changes nothing (the genuine one can still finish)."""
        digest = hashlib.sha256(hs1).digest()
        pending = self._pending.get(digest)  # consumed only by an HS2 that confirms
        if pending is None:
            raise UnknownSessionError("no handshake in progress for this HS1")
        _, secret = pending
        if len(hs2) != _HS2_LEN or hs2[0] != HS2_MAGIC or hs2[1] != VERSION:
            raise InvalidFrameError("malformed HS2")
        sid, nonce_r, mac = hs2[2:18], hs2[18:50], hs2[50:]
        seq = int.from_bytes(sid[:8], "big")
        transcript = _transcript(hs1, seq, nonce_r)
        keys = _HandshakeKeys.derive(secret, transcript)
        if sid[8:] != transcript[:8] or not hmac.compare_digest(mac, keys.confirmation):
            raise SignatureInvalidError("HS2 key confirmation failed")
        del self._pending[digest], self._refusal_keys[digest]
        return Session(
            sid, Direction.I2R, "responder", keys.i2r, keys.r2i, signing_key=self.signing_key
        )


class Responder:
    """The robot side: answers handshakes and routes frames to bounded sessions."""

    def __init__(
        self,
        kem_key: mlkem.MLKEM1024PrivateKey,
        peers: dict[str, mldsa.MLDSA87PublicKey],
        *,
        max_sessions: int = 256,
        sequence: NonceCounter | None = None,
        clock: Clock | None = None,
        x25519_key: x25519.X25519PrivateKey | None = None,
    ) -> None:
        self.kem_key = kem_key
        #: Hybrid mode: every HS1 must carry an X25519 share (a PQ-only HS1 is a downgrade).
        self.x25519_key = x25519_key
        self.peers = dict(peers)
        self._key_hash = hashlib.sha256(kem_key.public_key().public_bytes_raw()).digest()
        self._seq = sequence if sequence is not None else NonceCounter(1)
        # No restart fence: a replayed HS1 can never yield the keys of the session it
        # opens (the responder's fresh nonce and sequence enter the transcript), so after
        # a restart it costs one session slot, while a fence would refuse every
        # initiator for skew seconds.
        hs1_store = MemoryStore(max_entries=100_000, clock=clock, restart_fence=False)
        self._seen_hs1 = ReplayCache(HANDSHAKE_WINDOW_S, 100_000, 5.0, clock, store=hs1_store)
        self._sessions: FencedTable[int, Session] = FencedTable(max_sessions, what="session")
        self._lock = threading.Lock()

    @property
    def max_sessions(self) -> int:
        return self._sessions.max_keys

    def __len__(self) -> int:
        return len(self._sessions)

    def accept_handshake(
        self, hs1: bytes, avoid: Callable[[bytes], bool] | None = None
    ) -> tuple[Session, bytes]:
        """The handshake recipe: HS1 checks (shape, freshness, seen-set; records nothing),
        signature and KEM, then commit the HS1 digest and open a session; returns HS2.

        ``avoid``: session ids it is true of are drawn again (a fresh ``nonce_r``, at most
        ``AVOID_TRIES`` times), for a carriage that shortens ids on the air and would
        rather two live sessions never share the short form."""
        peer_id, digest, ts, body, sig, kem_ct, share = self._parse_hs1(hs1)
        self._seen_hs1.check(digest, ts)
        peer_key = self.peers.get(peer_id)
        if peer_key is None:
            raise UnknownSenderError("unknown initiator identity")
        try:
            peer_key.verify(sig, body, _CTX_HS1)
        except InvalidSignature:
            raise SignatureInvalidError("HS1 signature does not verify") from None
        try:
            secret = self.kem_key.decapsulate(kem_ct)
            if self.x25519_key is not None:
                dh = self.x25519_key.exchange(x25519.X25519PublicKey.from_public_bytes(share))
                secret = _combine(secret, dh, share, self.x25519_key.public_key())
        except ValueError:
            raise InvalidFrameError("KEM ciphertext or X25519 share is invalid") from None
        self._seen_hs1.commit(digest, ts)
        seq = self._seq.next()
        for _ in range(AVOID_TRIES):
            nonce_r = os.urandom(NONCE_LEN)
            transcript = _transcript(hs1, seq, nonce_r)
            sid = seq.to_bytes(8, "big") + transcript[:8]
            if avoid is None or not avoid(sid):
                break
        keys = _HandshakeKeys.derive(secret, transcript)
        session = Session(sid, Direction.R2I, peer_id, keys.r2i, keys.i2r, peer_verify_key=peer_key)
        hs2 = bytes([HS2_MAGIC, VERSION]) + sid + nonce_r + keys.confirmation
        with self._lock:  # a full table evicts the oldest sequence, its keys with it
            self._sessions.commit(seq, seq, lambda: session)
        return session, hs2

    def claimed(self, hs1: bytes) -> str | None:
        """The identity ``hs1`` claims (nothing verified), None when it does not parse."""
        try:
            return self._parse_hs1(hs1)[0]
        except InvalidFrameError:
            return None

    def refusal_key(self, hs1: bytes) -> bytes | None:
        """The key to MAC a refusal of ``hs1`` under (:func:`refusal_key`), None for an HS1
        that does not parse or is addressed to another key: its sender could not check it."""
        try:
            kem_ct = self._parse_hs1(hs1)[5]
            secret = self.kem_key.decapsulate(kem_ct)
        except (InvalidFrameError, ValueError):
            return None
        return refusal_key(secret, hashlib.sha256(hs1).digest())

    def _parse_hs1(self, hs1: bytes) -> tuple[str, str, float, bytes, bytes, bytes, bytes]:
        if not isinstance(hs1, bytes) or len(hs1) < _HS1_HEAD.size:
            raise InvalidFrameError("HS1 too short")
        magic, ver, ts_ms, id_len = _HS1_HEAD.unpack_from(hs1)
        if magic not in (HS1_MAGIC, HS1_HYBRID_MAGIC) or ver != VERSION:
            raise InvalidFrameError("not an antireplay v1 HS1")
        hybrid = self.x25519_key is not None
        if (magic == HS1_HYBRID_MAGIC) != hybrid:
            want = "hybrid (X25519 + ML-KEM-1024)" if hybrid else "ML-KEM-1024 only"
            raise InvalidFrameError(f"this responder takes {want} handshakes")
        share_len = X25519_LEN if hybrid else 0
        if not 0 < id_len <= MAX_ID_LEN:
            raise InvalidFrameError("bad identity length")
        expected = _HS1_HEAD.size + id_len + 32 + KEM_CT_LEN + share_len + NONCE_LEN + SIG_LEN
        if len(hs1) != expected:
            raise InvalidFrameError(f"HS1 must be {expected} bytes, got {len(hs1)}")
        at = _HS1_HEAD.size
        try:
            peer_id = hs1[at : at + id_len].decode()
        except UnicodeDecodeError:
            raise InvalidFrameError("identity is not UTF-8") from None
        at += id_len
        if not hmac.compare_digest(hs1[at : at + 32], self._key_hash):
            raise InvalidFrameError("HS1 is addressed to another responder key")
        at += 32
        kem_ct, share = (
            hs1[at : at + KEM_CT_LEN],
            hs1[at + KEM_CT_LEN : at + KEM_CT_LEN + share_len],
        )
        digest = hashlib.sha256(hs1).hexdigest()
        return peer_id, digest, ts_ms / 1000, hs1[:-SIG_LEN], hs1[-SIG_LEN:], kem_ct, share

    def _route(self, head: tuple[Purpose, Direction, bytes, int]) -> Session:
        """The frame's live session; records nothing and reads without the lock (the
        session's window commit is the re-check).  Issued but no longer held (closed
        after a rekey, or evicted): ``SESSION_CLOSED``; never issued: ``UNKNOWN_SESSION``."""
        sid = head[2]
        seq = int.from_bytes(sid[:8], "big")
        session = self._sessions.get(seq)
        if session is not None and session.session_id == sid:
            return session
        if session is None and seq < self._seq.peek:
            raise SessionClosedError("session closed or evicted, its keys gone; handshake again")
        raise UnknownSessionError("no such session")

    def check(self, frame: bytes) -> None:
        """Route and check a frame, its tag aside; records nothing."""
        head = parse_frame_head(frame)
        self._route(head).check_parsed(bytes(frame), head)

    def open(self, frame: bytes) -> Opened:
        """The recipe: route the frame to its session, then check, verify, commit."""
        head = parse_frame_head(frame)
        return self._route(head).open_parsed(bytes(frame), head)

    def close(self, session: Session) -> None:
        """End a session (after a rekey): its keys are dropped, so its frames can never pass."""
        with self._lock:
            self._sessions.discard(session.seq)


__all__ = ["COUNTER_LIMIT", "Direction", "Initiator", "Opened", "Purpose", "Responder", "Session"]
