"""Post-quantum sessions over MAVLink v2: the carriage (dialect, chunks, reassembly, two ends).

Theory of operation
-------------------
:mod:`antireplay.pq.session` makes the blobs (HS1, HS2, session frames); this module
carries them in MAVLink v2 messages of a four-message dialect of ours,
``antireplay_pq.xml`` (published next to this module, ids 61000 to 61003), so that
every router (MAVProxy, mavlink-router, ours) forwards them untouched: a router that
does not know the dialect passes an unknown message id as it is.  The messages are
packed with :mod:`struct`; the CRC extra of each is computed from the XML by
pymavlink's own parser (:mod:`pymavlink.generator.mavparse`), the standard way, so
the published XML and the bytes on air cannot drift apart.

``PQ_CHUNK`` (61000, 255-byte payload)::

    transfer u16 | index u8 | count u8 | len u8 | kind u4 parity u4 | data[249]

A blob is cut into ``count`` (at most 32) data chunks sharing the sender's ``transfer``
number, followed by ``parity`` (one per ten data chunks, at most 4) **parity chunks**:
parity chunk ``j`` (index ``count + j``) is the XOR of the data chunks whose index is
``j`` modulo ``parity``, so one loss in each such group is rebuilt without a round trip
(its ``len`` repeats the last data chunk's, so that one can be rebuilt to length).
``kind`` says what the blob is: 1 HS1, 2 HS2, 3 a session frame in one chunk,
4 a session frame in several chunks, each of whose ``data[:len]`` (parity chunks too)
ends with an 8-byte **chunk MAC**: ``HMAC-SHA256(chunk key, sysid | compid | header |
piece)[:8]``, the chunk key derived from the sender's session data key.  Senders trim
trailing zero bytes (MAVLink v2); ``len`` says what is data.

Beyond what parity rebuilds, a lost chunk costs that chunk (:mod:`.repair`): the
receiver sends ``PQ_REPAIR`` (61002) NACKs naming the fewest missing indices, the sender
resends them from a bounded copy, and a ground station's retry of a command in flight is
a POKE (35 bytes) answered by the vehicle end with a NACK or the held ``COMMAND_ACK``,
never a new signature.  Airtime at 0 % loss: 2 parity chunks per command and the
COMMAND_ACK twice, about 5,850 to 5,980 bytes per delivered command (1.10x to 1.12x the
5,327 without them), 3 parity chunks per HS1; through a lossy UDP radio at 57,600 baud
(``python -m benchmarks pq-radio``), 30 of 30 commands at 5 % and 10 % loss, p90 to the
ACK 1.29 s and 1.42 s, a session within 1.3 s (the figures: the MAVLink guide).

Receiving (:class:`Reassembler`), cheap first: strict MAVLink parse and our CRC, the
header's bounds (``index < count <= 32``, ``len`` fits, a kind that needs one chunk
has one), then the chunk MAC for kind 4 under the keys of the live sessions, then its
transfer number against the newest one that opened from that sender under that key
(16-bit serial arithmetic: at or behind it, a recorded chunk, ``REPLAY_DETECTED``),
and only then the chunk is buffered.  A chunk flood without a session key therefore
cannot occupy the frame pool at all, nor can chunks replayed from the session's own
history; the handshake pool (HS1 from an unknown peer cannot carry a MAC) is separate
and small, and a full one evicts the transfer with the fewest chunks (the oldest among
equals), so a flood of first chunks cannot push out a handshake that is almost
complete, nor any command.  Transfers expire after ``timeout_s``; duplicates are
ignored, a conflicting chunk is refused; chunks of a blob completed lately that it did
not need (parity after a whole blob) are counted ``late``, one it had already taken is a
replay; evictions, expiries and duplicates are counted (:class:`ReassemblyStats`,
exported by the link).  No other blob can complete with a chunk (the MAC binds each
chunk, parity too, to its transfer, index, count and parity; the session frame's tag
binds everything again).  Transfer numbers are 16 bits:
a ground end rekeys after ``REKEY_TRANSFERS`` of them and stops sending in a session at
``TRANSFER_LIMIT``, so they never wrap within a session towards the vehicle; the
vehicle end's do wrap (it cannot rekey), so a chunk of its telemetry recorded more than
32,768 transfers ago can still take a slot of the ground end's pool until it expires
(its tag refuses it at the end).  An HS1 goes out under a random transfer number, so a
chunk planted ahead of it cannot spoil it; one injected in reaction to it (conflicting
count or piece) can, as jamming could; the ground end tries again after ``retry_s``.
Memory: ``(max_transfers + max_handshakes) * (32 + 4) * 249`` bytes at most.

Session frames travel **compact**, ``handle u8 | purpose u8 | counter u64 | inner |
tag``: magic, version and direction are implied, and the 16-byte session id is cut to
its last byte; the receiver rebuilds the full frame for each live session with that
handle (normally one) and the tag, computed over the full frame, decides (18 bytes
fewer per message, nothing less bound).  A session frame carries one plain MAVLink
message, the **inner**::

    src_sys u8 | src_comp u8 | seq u8 | msgid u24 LE | payload (as on the wire)

and the session frame's tag covers session id, direction, purpose, counter and the
inner, hence the message id, the source, and the target system/component (fields of
the payload; :func:`~antireplay.mavlink.codec.target`); the frame rebuilt from it is the
sender's frame, byte for byte (unsigned).  Choice of tag per message
(:data:`SIGNED_MESSAGES`): whatever changes what the vehicle does (commands, mode,
parameters, missions, guided setpoints, home and origin, file transfer, the serial
shell, log erasure) is a ``command`` frame, signed with the operator's ML-DSA-87 key
(non-repudiable, 4,627 bytes: 20 chunks), and the vehicle end refuses any of them in a
data frame (``SIGNATURE_REQUIRED``, before any cryptography); everything else (GCS
heartbeats, RC/manual control, and all telemetry from the vehicle) is a ``data`` frame
under the session's HMAC-SHA256-128 key (one chunk for messages up to 217 bytes of
payload: 38 bytes more on air than plain MAVLink, 25 more than MAVLink signing).

The two ends are sans-I/O here (:class:`GroundEnd`, :class:`VehicleEnd`); the
adapter that moves their bytes is :mod:`antireplay.mavlink.pq.link`.  Ground end:
starts a handshake at once and again (``retry_s`` after the last at first, doubling,
within an airtime budget: :mod:`.ground`) whenever the
session nears its counter limit (:attr:`~antireplay.pq.session.Session.needs_rekey`) or
its transfer limit, when nothing authenticated came from the vehicle for ``silence_s``
(a restarted vehicle end), or when the vehicle end reports it has no session
(``PQ_STATUS``, unauthenticated, so heeded only when nothing authenticated came from
the vehicle for ``retry_s``); while it has no session, queues at most ``max_queued``
commands, each for at most ``queue_ttl_s``, and drops the rest, every drop counted
(:attr:`GroundEnd.drops`); wraps every local message; unwraps telemetry.  Vehicle
end: answers HS1 with HS2 (:meth:`~antireplay.pq.session.Responder.accept_handshake`:
shape, freshness and the seen-set before the signature, commit after, so a replayed
HS1 opens nothing; it draws a session id whose handle no live session has; a refused
one is answered with a ``PQ_REFUSAL``, :mod:`.vehicle`), opens
frames with :meth:`~antireplay.pq.session.Responder.open` (window ``check`` before the
signature, ``commit`` after; for a handle two live sessions still share, under each
candidate in turn, so the tag decides and one session's window never refuses
another's frame), rebuilds the plain MAVLink frame for the flight controller, and
wraps the flight controller's telemetry under the newest session that authenticated.
The first frame that authenticates in a peer's new session closes that peer's older
sessions (:meth:`~antireplay.pq.session.Responder.close`), so a frame withheld from an
old session (jammed, recorded) can never be played later (``SESSION_CLOSED``); one
ground end per operator identity.  Every refusal is a typed error the caller counts.
Only MAVLink v2 travels: a v1 frame is refused on both sides (:class:`PlainFrameError`,
as plain MAVLink on the air is).
"""

from __future__ import annotations

from antireplay.mavlink.pq.chunks import (
    Chunk,
    ChunkSender,
    PlainFrameError,
    Reassembler,
    ReassemblyStats,
    chunk_key,
    parse_chunk,
)
from antireplay.mavlink.pq.ground import GroundEnd
from antireplay.mavlink.pq.repair import Output
from antireplay.mavlink.pq.vehicle import VehicleEnd
from antireplay.mavlink.pq.wire import (
    CHUNK_DATA,
    DIALECT,
    MAX_CHUNKS,
    MSG_CHUNK,
    MSG_REFUSAL,
    MSG_REPAIR,
    MSG_STATUS,
    REKEY_TRANSFERS,
    SIGNED_MESSAGES,
    TRANSFER_LIMIT,
    ChunkKind,
    compact,
    inner_of,
    open_compact,
    pack_v2,
    plain_frame,
)

__all__ = [
    "CHUNK_DATA",
    "DIALECT",
    "MAX_CHUNKS",
    "MSG_CHUNK",
    "MSG_REFUSAL",
    "MSG_REPAIR",
    "MSG_STATUS",
    "REKEY_TRANSFERS",
    "SIGNED_MESSAGES",
    "TRANSFER_LIMIT",
    "Chunk",
    "ChunkKind",
    "ChunkSender",
    "GroundEnd",
    "Output",
    "PlainFrameError",
    "Reassembler",
    "ReassemblyStats",
    "VehicleEnd",
    "chunk_key",
    "compact",
    "inner_of",
    "open_compact",
    "pack_v2",
    "parse_chunk",
    "plain_frame",
]
