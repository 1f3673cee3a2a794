"""Sealed DDS topics, the announcement relay and binding pings on a real Cyclone DDS.

Every test joins its own domain id with a loopback-only configuration (127.0.0.1,
no multicast), so tests never hear each other and no packet leaves the host.
DDS delivery is waited for by bounded polling on a condition; a ManualClock drives
epochs and freshness.
"""

from __future__ import annotations

import gc
import itertools
import json
import os
import random
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from antireplay import ManualClock
from antireplay.audit import AuditLog
from antireplay.core.errors import Code, ConfigError, StateFileError
from antireplay.dds.config import MAX_FORWARD_S, DdsConfig
from antireplay.epochs import EpochSigner, Kind, derive_key, signer_state
from antireplay.epochs.policy import seal
from antireplay.state import open_store
from harness import Reaper, dds_junk_process, dds_writer_process, started_before, until
from harness.stores import aged_state

try:
    from antireplay.dds import relay as relay_module
    from antireplay.dds.domain import join_domain
    from antireplay.dds.ping import PingListener, PingSender
    from antireplay.dds.relay import AnnouncementRelay, RelayedAnnouncement
    from antireplay.dds.topics import (
        AUDIT_PER_S,
        PingChannel,
        SampleVerdict,
        SealedReader,
        SealedWriter,
    )
    from antireplay.dds.wire import SealedSample
except ImportError as exc:  # the dds extra is part of CI: missing means broken, not skipped
    pytest.fail(f"Cyclone DDS missing ({exc}): pip install -e '.[dev,dds]'", pytrace=False)

ROOT = Path(__file__).resolve().parents[2]
PSK = b"dds-fleet-pre-shared-key-0123456789"
TOPIC = "robot/cmd"
#: Domain ids for this run: a random block, so a parallel run is unlikely to share one.
_IDS = itertools.count(random.randrange(1, 120))


@pytest.fixture
def participant() -> Any:
    """A participant on a domain id no other test uses."""
    return join_domain(next(_IDS))


def peer(participant: Any) -> Any:
    """A second, independent participant on the same domain (a peer, a restart or a rogue)."""
    return join_domain(int(participant.domain_id))


def collect(reader: SealedReader, count: int, timeout_s: float = 10.0) -> list[SampleVerdict]:
    """Judge samples until ``count`` verdicts arrived (bounded)."""
    verdicts: list[SampleVerdict] = []
    deadline = time.monotonic() + timeout_s
    while len(verdicts) < count:
        if time.monotonic() >= deadline:
            pytest.fail(f"{len(verdicts)} of {count} samples arrived within {timeout_s} s")
        verdicts += reader.poll(0.05)
    return verdicts


def pair(
    participant: Any, clock: ManualClock, **reader_opts: Any
) -> tuple[SealedWriter, SealedReader]:
    reader = started_before(
        clock, lambda: SealedReader(participant, TOPIC, PSK, clock=clock, **reader_opts)
    )
    writer = SealedWriter(participant, TOPIC, PSK, clock=clock)
    until("DDS discovery", lambda: writer.matched_readers() >= 1)
    return writer, reader


def rogue_writer(participant: Any, topic: str = TOPIC) -> SealedWriter:
    """A participant without the fleet key that republishes what it captured."""
    rogue = SealedWriter(peer(participant), topic, os.urandom(32))
    until("DDS discovery", lambda: rogue.matched_readers() >= 1)
    return rogue


def flipped(sample: SealedSample, index: int) -> SealedSample:
    raw = bytearray(bytes(sample.sealed))
    raw[index] ^= 0x01
    return SealedSample(instance=sample.instance, sealed=bytes(raw))


def test_round_trip_keyed_instances_and_several_writers(
    participant: Any, clock: ManualClock
) -> None:
    reader = started_before(clock, lambda: SealedReader(participant, TOPIC, PSK, clock=clock))
    writers = [SealedWriter(peer(participant), TOPIC, PSK, clock=clock) for _ in range(2)]
    for writer in writers:
        until("DDS discovery", lambda w=writer: w.matched_readers() >= 1)  # type: ignore[misc]
    for n in range(3):
        for i, writer in enumerate(writers):
            writer.write(f"w{i} #{n}".encode(), instance=f"arm-{i}")
    verdicts = collect(reader, 6)
    assert all(v.accepted for v in verdicts), [v.line() for v in verdicts]
    by_writer = {w.nonce_prefix: [v.value for v in verdicts if v.nonce_prefix == w.nonce_prefix]
                 for w in writers}  # fmt: skip
    for i, writer in enumerate(writers):
        assert by_writer[writer.nonce_prefix] == [f"w{i} #{n}".encode() for n in range(3)]
        assert {v.instance for v in verdicts if v.nonce_prefix == writer.nonce_prefix} == {
            f"arm-{i}"
        }
    assert reader.counts == {"accepted": 6}


def test_rogue_participant_republishing_captured_samples_is_refused(
    participant: Any, clock: ManualClock, tmp_path: Path
) -> None:
    audit = AuditLog(tmp_path / "audit.db")
    writer, reader = pair(participant, clock, audit=audit)
    captured = [
        writer.write(b"ARM", instance="drone-7"),
        writer.write(b"TAKEOFF", instance="drone-7"),
    ]
    assert [v.value for v in collect(reader, 2)] == [b"ARM", b"TAKEOFF"]
    rogue = rogue_writer(participant)
    for sample in captured:
        rogue.publish(sample)
    refused = collect(reader, 2)
    assert [(v.code, v.outcome) for v in refused] == [(Code.EPOCH_REPLAYED, "replayed")] * 2
    assert all(v.value is None for v in refused)
    records = audit.tail(10)
    assert [r.code for r in records] == ["EPOCH_REPLAYED"] * 2
    assert records[0].sender == writer.nonce_prefix.hex() and records[0].sender_verified


def test_bit_flip_anywhere_is_refused(participant: Any, clock: ManualClock) -> None:
    writer, reader = pair(participant, clock)
    originals = [writer.seal(b"move_forward 1m", instance="arm") for _ in range(4)]
    # version, prefix, epoch, payload, tag: the head is parsed, the rest is under the MAC
    positions = [0, 5, 15, 25, -1]
    rogue = rogue_writer(participant)
    for sample, index in zip(itertools.cycle(originals), positions, strict=False):
        rogue.publish(flipped(sample, index))
    verdicts = collect(reader, len(positions))
    assert [v.code for v in verdicts] == [
        Code.INVALID_FRAME, Code.SIGNATURE_INVALID, Code.SIGNATURE_INVALID,
        Code.SIGNATURE_INVALID, Code.SIGNATURE_INVALID,
    ]  # fmt: skip
    assert not any(v.accepted for v in verdicts)
    assert verdicts[1].reason == "sample tag does not verify"  # named as its reader knows it
    writer.publish(originals[0])  # the untouched sample still passes: nothing was committed
    assert collect(reader, 1)[0].accepted


def test_sample_moved_to_another_instance_is_refused_before_crypto(
    participant: Any, clock: ManualClock
) -> None:
    writer, reader = pair(participant, clock)
    sample = writer.seal(b"ESTOP", instance="arm-1")
    rogue = rogue_writer(participant)
    rogue.publish(SealedSample(instance="arm-2", sealed=bytes(sample.sealed)))
    (verdict,) = collect(reader, 1)
    assert (verdict.code, verdict.outcome) == (Code.INVALID_FRAME, "wrong_instance")
    rogue.publish(sample)
    assert collect(reader, 1)[0].accepted


def test_sample_replayed_onto_another_topic_is_refused(
    participant: Any, clock: ManualClock
) -> None:
    cmd_writer = SealedWriter(participant, "robot/cmd", PSK, clock=clock)
    other_reader = started_before(
        clock, lambda: SealedReader(participant, "robot/cmd_vel", PSK, clock=clock)
    )
    cmd_reader = started_before(
        clock, lambda: SealedReader(participant, "robot/cmd", PSK, clock=clock)
    )
    until("DDS discovery", lambda: cmd_writer.matched_readers() >= 1)
    captured = cmd_writer.write(b"RESUME", instance="arm")
    assert collect(cmd_reader, 1)[0].accepted
    rogue = rogue_writer(participant, "robot/cmd_vel")
    rogue.publish(captured)
    (verdict,) = collect(other_reader, 1)
    assert (verdict.code, verdict.outcome) == (Code.SIGNATURE_INVALID, "forged")


def test_too_far_ahead_and_stale_are_refused(participant: Any, clock: ManualClock) -> None:
    writer, reader = pair(participant, clock, max_age_s=30, max_forward_s=5)
    early = writer.seal(b"old", instance="a")
    clock.advance(60)
    writer.publish(early)
    clock.step_wall(120)
    ahead = writer.seal(b"ahead", instance="a")
    clock.step_wall(-120)
    writer.publish(ahead)
    verdicts = collect(reader, 2)
    assert [(v.code, v.outcome) for v in verdicts] == [
        (Code.MESSAGE_STALE, "stale"),
        (Code.EPOCH_TOO_FAR_AHEAD, "ahead"),
    ]


def test_writer_restarted_with_its_state_file_is_accepted(
    participant: Any, clock: ManualClock, tmp_path: Path
) -> None:
    state = tmp_path / "writer.state"
    reader = started_before(clock, lambda: SealedReader(participant, TOPIC, PSK, clock=clock))
    first = SealedWriter(peer(participant), TOPIC, PSK, clock=clock, state=signer_state(state))
    until("DDS discovery", lambda: first.matched_readers() >= 1)
    for n in range(3):
        first.write(f"before #{n}".encode(), instance="arm")
    assert all(v.accepted for v in collect(reader, 3))
    prefix = first.nonce_prefix
    first.close()  # the process stops
    # the same host, the clock not moved on: only the state file keeps epochs above the old ones
    second = SealedWriter(peer(participant), TOPIC, PSK, clock=clock, state=signer_state(state))
    assert second.nonce_prefix == prefix
    until("DDS discovery", lambda: second.matched_readers() >= 1)
    second.write(b"after restart", instance="arm")
    (verdict,) = collect(reader, 1)
    assert verdict.accepted and verdict.value == b"after restart"


def test_writer_whose_state_file_is_missing_is_refused_naming_the_file(
    participant: Any, clock: ManualClock, tmp_path: Path
) -> None:
    state = tmp_path / "writer.state"
    reader = started_before(clock, lambda: SealedReader(participant, TOPIC, PSK, clock=clock))
    first = SealedWriter(
        participant, TOPIC, PSK, clock=clock, state=signer_state(state), service_name="arm"
    )
    until("DDS discovery", lambda: first.matched_readers() >= 1)
    first.write(b"before", instance="arm")
    assert collect(reader, 1)[0].accepted
    first.close()  # the process stops
    state.unlink()  # the witness stays: the loss is visible
    with pytest.raises(StateFileError) as refused:
        SealedWriter(
            peer(participant),
            TOPIC,
            PSK,
            clock=clock,
            state=signer_state(state),
            service_name="arm",
        )
    assert str(state) in str(refused.value)
    # wiping the witness too makes a fresh start, but its epochs are not above the old ones
    # under the same service-name prefix, so the reader refuses what it sends
    Path(str(state) + ".gen").unlink()
    amnesiac = SealedWriter(peer(participant), TOPIC, PSK, clock=clock, state=signer_state(state),
                            service_name="arm")  # fmt: skip
    until("DDS discovery", lambda: amnesiac.matched_readers() >= 1)
    amnesiac.write(b"after losing state", instance="arm")
    (verdict,) = collect(reader, 1)
    assert verdict.code == Code.EPOCH_REPLAYED and verdict.outcome == "prefix_collision"


def test_reader_restarted_with_its_state_file_still_refuses_old_samples(
    participant: Any, clock: ManualClock, tmp_path: Path
) -> None:
    state = f"sqlite:{tmp_path / 'reader.db'}"
    writer = SealedWriter(participant, TOPIC, PSK, clock=clock)
    first = started_before(
        clock,
        lambda: SealedReader(
            peer(participant), TOPIC, PSK, clock=clock, store=open_store(state, clock=clock)
        ),
    )
    until("DDS discovery", lambda: writer.matched_readers() >= 1)
    captured = [writer.write(f"cmd {n}".encode(), instance="arm") for n in range(3)]
    assert all(v.accepted for v in collect(first, 3))
    first.close()  # the process stops
    first.verifier.store.close()
    restarted = started_before(
        clock,
        lambda: SealedReader(
            peer(participant), TOPIC, PSK, clock=clock, store=open_store(state, clock=clock)
        ),
    )
    # Issue 18: a reader without persistent state fences at its start, so it refuses the
    # captures too (it cannot know what a previous process accepted)
    forgetful = SealedReader(peer(participant), TOPIC, PSK, clock=clock)
    rogue = rogue_writer(participant)
    until(
        "DDS discovery",
        lambda: restarted.matched_writers() >= 2 and forgetful.matched_writers() >= 2,
    )
    for sample in captured:
        rogue.publish(sample)
    assert [v.code for v in collect(restarted, 3)] == [Code.EPOCH_REPLAYED] * 3
    assert [(v.code, v.outcome) for v in collect(forgetful, 3)] == [
        (Code.MESSAGE_STALE, "stale")
    ] * 3
    clock.advance(5.001)  # past the start fence (max_forward_s): new samples pass
    writer.write(b"fresh", instance="arm")
    assert collect(forgetful, 1)[0].accepted


def pump_until(relay: AnnouncementRelay, condition: Callable[[], bool]) -> None:
    """Run the relay's loop (as its serve() does) until ``condition`` holds (bounded)."""
    until("the relay's loop", lambda: relay.pump(0.02) is not None and condition())


def relay_at(
    participant: Any, tmp_path: Path, name: str, clock: ManualClock, tag: str
) -> AnnouncementRelay:
    return started_before(
        clock,
        lambda: AnnouncementRelay(
            participant,
            PSK,
            service_name=name,
            signer_state=signer_state(tmp_path / f"{tag}-signer.state"),
            verifier_store=open_store(f"sqlite:{tmp_path / f'{tag}-verifier.db'}", clock=clock),
            clock=clock,
        ),
    )


def test_relay_reannounces_authentic_announcements_only(
    participant: Any, clock: ManualClock, tmp_path: Path
) -> None:
    relay = relay_at(participant, tmp_path, "cds-1", clock, "a")
    announcer = SealedWriter(peer(participant), "antireplay/announce", PSK, clock=clock)
    subscriber = started_before(
        clock, lambda: SealedReader(peer(participant), "antireplay/relayed", PSK, clock=clock)
    )
    until(
        "DDS discovery",
        lambda: announcer.matched_readers() >= 1 and relay.egress.matched_readers() >= 2,
    )
    sealed = announcer.write(b"participant guid=01 locator=udpv4://127.0.0.1:7410", instance="01")
    pump_until(relay, lambda: relay.relayed == 1)
    rogue = rogue_writer(participant, "antireplay/announce")
    rogue.publish(sealed)
    pump_until(relay, lambda: relay.ingress.counts["replayed"] == 1)
    (verdict,) = collect(subscriber, 1)
    assert verdict.accepted and verdict.nonce_prefix == relay.egress.nonce_prefix
    body = RelayedAnnouncement.decode(verdict.value)
    assert body.origin_prefix == announcer.nonce_prefix
    assert body.payload.startswith(b"participant guid=01")
    assert relay.relayed == 1 and relay.twins == []


def test_relay_resumes_above_its_epochs_after_a_restart(
    participant: Any, clock: ManualClock, tmp_path: Path
) -> None:
    subscriber = started_before(
        clock, lambda: SealedReader(participant, "antireplay/relayed", PSK, clock=clock)
    )
    announcer = SealedWriter(participant, "antireplay/announce", PSK, clock=clock)
    relay = relay_at(peer(participant), tmp_path, "cds-1", clock, "a")
    until(
        "DDS discovery",
        lambda: announcer.matched_readers() >= 1 and relay.egress.matched_readers() >= 1,
    )
    announcer.write(b"first", instance="p")
    pump_until(relay, lambda: relay.relayed == 1)
    before = collect(subscriber, 1)[0]
    relay.close()  # the process stops
    restarted = relay_at(peer(participant), tmp_path, "cds-1", clock, "a")
    until(
        "DDS discovery",
        lambda: announcer.matched_readers() >= 1 and restarted.egress.matched_readers() >= 1,
    )
    announcer.write(b"second", instance="p")
    pump_until(restarted, lambda: restarted.relayed == 1)
    after = collect(subscriber, 1)[0]
    assert after.accepted and before.epoch is not None and after.epoch is not None
    assert after.epoch > before.epoch and after.nonce_prefix == before.nonce_prefix


def test_two_relays_with_one_service_name_are_reported(
    participant: Any, clock: ManualClock, tmp_path: Path
) -> None:
    audit = AuditLog(tmp_path / "audit.db")
    one = relay_at(participant, tmp_path, "cds-1", clock, "one")
    one.audit = audit
    two = relay_at(peer(participant), tmp_path, "cds-1", clock, "two")
    subscriber = started_before(
        clock, lambda: SealedReader(peer(participant), "antireplay/relayed", PSK, clock=clock)
    )
    announcer = SealedWriter(peer(participant), "antireplay/announce", PSK, clock=clock)
    until(
        "DDS discovery",
        lambda: announcer.matched_readers() >= 2 and one.egress.matched_readers() >= 3,
    )
    for n in range(3):
        announcer.write(f"participant {n}".encode(), instance=str(n))
        clock.advance(0.001)
    pump_until(one, lambda: two.pump(0.02) is not None and bool(one.twins and two.twins))
    assert one.twins[0].service_name == "cds-1"
    assert one.twins[0].nonce_prefix == one.egress.nonce_prefix == two.egress.nonce_prefix
    assert one.counts["duplicate_service_name"] >= 1
    assert any(
        r.outcome == "alert" and r.warning and "DUPLICATE" in r.warning for r in audit.tail(20)
    )
    verdicts = collect(subscriber, 6)
    assert subscriber.counts["prefix_collision"] >= 1, [v.line() for v in verdicts]


def test_binding_ping_learns_an_address_only_from_an_authentic_fresh_ping(
    clock: ManualClock,
) -> None:
    listener = started_before(
        clock, lambda: PingListener(PSK, clock=clock, max_age_s=30, max_forward_s=5)
    )
    sender = PingSender(PSK, clock=clock)
    attacker = PingSender(os.urandom(32), clock=clock)
    try:
        datagram = sender.ping(listener.address, b"guid=01")
        verdict = listener.receive(5.0)
        assert verdict is not None and verdict.accepted and verdict.value == b"guid=01"
        assert listener.peers == {sender.signer.nonce_prefix: sender.address}
        attacker.sock.sendto(datagram, listener.address)  # captured ping, attacker's address
        attacker.ping(listener.address, b"guid=01")  # the attacker's own key
        attacker.sock.sendto(b"short", listener.address)
        announcement_kind = bytearray(datagram)
        announcement_kind[1] = 1  # a ping presented as an announcement is refused by kind
        attacker.sock.sendto(bytes(announcement_kind), listener.address)
        refused = [listener.receive(5.0) for _ in range(4)]
        assert [(v.code, v.outcome) for v in refused if v is not None] == [
            (Code.EPOCH_REPLAYED, "replayed"),
            (Code.SIGNATURE_INVALID, "forged"),
            (Code.INVALID_FRAME, "malformed"),
            (Code.INVALID_FRAME, "malformed"),
        ]
        assert refused[1] is not None and refused[1].reason == "binding ping tag does not verify"
        assert listener.peers == {sender.signer.nonce_prefix: sender.address}
    finally:
        for endpoint in (listener, sender, attacker):
            endpoint.close()


def test_ping_refusal_audits_are_rate_limited_but_all_counted(
    tmp_path: Path, clock: ManualClock
) -> None:
    """A garbage flood writes a bounded number of audit records (review finding 2); every
    datagram is counted, and a replay's refusal still reaches the trail (its own budget)."""
    audit = AuditLog(tmp_path / "audit.db")
    listener = started_before(clock, lambda: PingListener(PSK, clock=clock, audit=audit))
    sender = PingSender(PSK, clock=clock)
    flood = 3 * int(AUDIT_PER_S)
    try:
        for _ in range(flood):  # the clock stands still: no budget comes back
            listener.judge(os.urandom(60), ("192.0.2.1", 9))
        ping = sender.signer.seal_ping(b"guid=01")
        assert listener.judge(ping, sender.address).accepted
        assert listener.judge(ping, ("192.0.2.1", 9)).outcome == "replayed"
        refused = sum(n for k, n in listener.counts.items() if k not in {"accepted",
                      "audit_rate_limited"})  # fmt: skip
        assert refused == flood + 1
        assert listener.counts["audit_rate_limited"] == flood - AUDIT_PER_S
        assert audit.count() == AUDIT_PER_S + 1
        assert audit.tail(1)[0].warning == "dds ping: replayed"
    finally:
        listener.close()
        sender.close()
        audit.close()


def test_reader_refusal_audits_are_rate_limited(
    participant: Any, tmp_path: Path, clock: ManualClock
) -> None:
    audit = AuditLog(tmp_path / "audit.db")
    reader = started_before(
        clock, lambda: SealedReader(participant, TOPIC, PSK, clock=clock, audit=audit)
    )
    for _ in range(2 * int(AUDIT_PER_S)):
        reader.judge(SealedSample(instance="", sealed=os.urandom(100)))
    assert sum(reader.counts[k] for k in ("malformed", "wrong_instance", "forged")) == 100
    assert (audit.count(), reader.counts["audit_rate_limited"]) == (AUDIT_PER_S, AUDIT_PER_S)
    audit.close()


def test_relay_pump_judges_a_bounded_number_of_pings(
    participant: Any, tmp_path: Path, clock: ManualClock, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A ping flood cannot hold the relay's loop: each pump judges at most PINGS_PER_PUMP."""
    monkeypatch.setattr(relay_module, "PINGS_PER_PUMP", 3)
    listener = started_before(clock, lambda: PingListener(PSK, clock=clock))
    relay = relay_at(participant, tmp_path, "cds-1", clock, "a")
    relay.ping = listener
    sender = PingSender(PSK, clock=clock)
    try:
        for _ in range(10):
            sender.sock.sendto(b"garbage", listener.address)

        def pumped_within_bound() -> bool:
            before = listener.counts.total()
            relay.pump(0.0)
            assert listener.counts.total() - before <= 3
            return listener.counts.total() >= 10

        until("the relay's loop", pumped_within_bound)
        assert listener.counts["malformed"] == 10
    finally:
        relay.close()
        listener.close()
        sender.close()


#: Every child process a test here starts (killed when the test ends, passed or failed).
_CHILDREN = Reaper()


@pytest.fixture(autouse=True)
def _reaped() -> Iterator[None]:
    """Each test starts after a full garbage collection (earlier tests' DDS objects freed:
    a topic filter whose callback is freed under a live C topic crashes here every run,
    not at random) and ends with its children killed."""
    gc.collect()
    yield
    _CHILDREN.reap()


def _antireplay(*args: str, **kwargs: Any) -> subprocess.Popen[str]:
    command = [str(Path(sys.executable).with_name("antireplay")), "dds", *args]
    return _CHILDREN(
        subprocess.Popen(
            command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kwargs
        )
    )


def test_cli_reader_prints_verdicts_across_processes(tmp_path: Path) -> None:
    (tmp_path / "fleet.psk").write_text(os.urandom(32).hex())
    config = tmp_path / "dds.yaml"
    config.write_text(
        f"dds:\n  domain_id: {next(_IDS)}\n  psk_file: {tmp_path / 'fleet.psk'}\n"
        f"  reader: {{topic: robot/cmd, store: 'sqlite:{aged_state(tmp_path / 'reader.db')}'}}\n"
        f"  writer: {{topic: robot/cmd, state_file: {tmp_path / 'writer.state'}}}\n"
    )
    cfg = ["--config", str(config)]
    (tmp_path / "cap.jsonl").write_text('{"left": "by an earlier run"}\n')
    reader = _antireplay("read", *cfg, "--count", "4", "--timeout", "60")
    try:
        writer = _antireplay("write", *cfg, "--instance", "arm-1", "--capture",
                             str(tmp_path / "cap.jsonl"), "move 1", "move 2")  # fmt: skip
        assert writer.wait(60) == 0, writer.communicate()
        rogue = _antireplay("replay", *cfg, str(tmp_path / "cap.jsonl"))
        assert rogue.wait(60) == 0, rogue.communicate()
        out, err = reader.communicate(timeout=60)
    finally:
        reader.kill()
    assert reader.returncode == 0, err
    lines = out.splitlines()
    assert [line.split(" instance=")[0] for line in lines] == [
        "ACCEPTED", "ACCEPTED", "REFUSED EPOCH_REPLAYED replayed", "REFUSED EPOCH_REPLAYED replayed"
    ]  # fmt: skip
    assert "'move 1'" not in lines[2] and "verdicts: accepted=2, replayed=2" in err
    captured = (tmp_path / "cap.jsonl").read_text().splitlines()
    assert len(captured) == 2 and len(json.loads(captured[0])["sealed"]) > 0  # this run's only


def test_cli_relay_reannounces_for_another_process(tmp_path: Path) -> None:
    psk = os.urandom(32)
    (tmp_path / "fleet.psk").write_text(psk.hex())
    domain_id = next(_IDS)
    config = tmp_path / "dds.yaml"
    config.write_text(
        f"dds:\n  domain_id: {domain_id}\n  psk_file: {tmp_path / 'fleet.psk'}\n"
        f"  relay: {{service_name: cds-1, signer_state: {tmp_path / 's.state'},"
        f" verifier_store: 'sqlite:{aged_state(tmp_path / 'v.db')}'}}\n"
    )
    relay = _antireplay("relay", "--config", str(config), "--duration", "15")
    try:
        participant = join_domain(domain_id)
        # a store of a deployment started earlier: its first start's fence is long past
        subscriber = SealedReader(
            participant,
            "antireplay/relayed",
            psk,
            store=open_store(f"sqlite:{aged_state(tmp_path / 'sub.db')}"),  # started earlier
        )
        announcer = SealedWriter(participant, "antireplay/announce", psk)
        until(
            "DDS discovery",
            lambda: announcer.matched_readers() >= 1 and subscriber.matched_writers() >= 1,
            20.0,
        )
        announcer.write(b"participant guid=02", instance="02")
        (verdict,) = collect(subscriber, 1, 20)
        assert verdict.accepted and verdict.nonce_prefix != announcer.nonce_prefix
        assert RelayedAnnouncement.decode(verdict.value).payload == b"participant guid=02"
    finally:
        relay.terminate()
        out, err = relay.communicate(timeout=30)
    assert relay.returncode == 0, err
    assert out.startswith("ACCEPTED instance='02'") and "relayed 1; twins reported 0" in err


def test_writer_on_the_readers_forward_bound_recovers_from_a_short_glitch(
    participant: Any, clock: ManualClock
) -> None:
    """A 30 s forward glitch: on the readers' 5 s bound (both sides' default) the writer
    rotates its prefix at once; with the signer's own 60 s default it would be refused
    until real time caught up (review finding 4)."""
    reader = started_before(clock, lambda: SealedReader(participant, TOPIC, PSK, clock=clock))
    writer = SealedWriter(participant, TOPIC, PSK, clock=clock)
    until("DDS discovery", lambda: writer.matched_readers() >= 1)
    clock.step_wall(30)
    writer.seal(b"during the glitch", instance="a")  # never delivered: NTP corrects the clock
    clock.step_wall(-30)
    writer.write(b"after the glitch", instance="a")
    (verdict,) = collect(reader, 1)
    assert verdict.accepted and verdict.value == b"after the glitch"


@pytest.mark.parametrize("case", [(None, 30, 1), (10.0, 7, 0)])
def test_relay_egress_signs_on_the_subscribers_forward_bound(
    participant: Any, tmp_path: Path, clock: ManualClock, case: tuple[float | None, int, int]
) -> None:
    """The relay's egress signer gets the readers' ``max_forward_s`` (its default, or the
    configured one): after a corrected forward glitch subscribers accept it at once."""
    bound, glitch_s, rotations = case
    options: dict[str, Any] = {} if bound is None else {"max_forward_s": bound}
    relay = started_before(clock, lambda: AnnouncementRelay(
        participant, PSK, service_name="cds-1",
        signer_state=signer_state(tmp_path / "signer.state"),
        verifier_store=open_store(f"sqlite:{tmp_path / 'verifier.db'}", clock=clock),
        clock=clock, **options,
    ))  # fmt: skip
    subscriber = started_before(clock, lambda: SealedReader(
        peer(participant), "antireplay/relayed", PSK, clock=clock, **options
    ))  # fmt: skip
    clock.step_wall(glitch_s)
    relay.egress.seal(b"during the glitch")  # never delivered: NTP corrects the clock
    clock.step_wall(-glitch_s)
    clock.advance(1)
    verdict = subscriber.judge(relay.egress.seal(b"after the glitch"))
    assert verdict.accepted, verdict.line()
    assert relay.egress.signer.rotations == rotations
    relay.close()


def test_ping_sender_signs_on_the_listeners_forward_bound(clock: ManualClock) -> None:
    listener = started_before(clock, lambda: PingListener(PSK, clock=clock))
    sender = PingSender(PSK, clock=clock)
    try:
        clock.step_wall(30)
        sender.signer.seal_ping(b"during the glitch")
        clock.step_wall(-30)
        verdict = listener.judge(sender.signer.seal_ping(b"after"), sender.address)
        assert verdict.accepted, verdict.line()
    finally:
        listener.close()
        sender.close()


@pytest.mark.parametrize("key", ["max_age_s", "max_forward_s"])
def test_config_requires_the_freshness_bounds(key: str) -> None:
    """Issue 18: ``null`` is an error naming the field, never "unbounded" nor a clamp."""
    with pytest.raises(ConfigError, match=rf"dds\.{key}"):
        DdsConfig.from_mapping({"psk_file": "k", key: None})


def test_config_store_spec_is_validated() -> None:
    with pytest.raises(ConfigError, match=r"dds\.reader\.store"):
        DdsConfig.from_mapping({"psk_file": "k", "reader": {"store": "/tmp/reader.state"}})


@pytest.mark.parametrize(
    ("block", "key", "named"),
    [
        ({"relay": {"service_name": "cds", "signer_state": "s", "verifier_state": "sqlite:v"}},
         "dds.relay.verifier_state", "renamed to dds.relay.verifier_store"),
        ({"reader": {"state_file": "r.state"}}, "dds.reader.state_file",
         "renamed to dds.reader.store"),
    ],
)  # fmt: skip
def test_config_names_a_renamed_key(block: dict[str, Any], key: str, named: str) -> None:
    """Review finding 9: an obsolete key is reported by name with its new name, not as a
    "Field required" on the new one."""
    with pytest.raises(ConfigError) as refused:
        DdsConfig.from_mapping({"psk_file": "k", **block})
    assert refused.value.key == key
    assert named in str(refused.value)


def test_config_reports_every_wrong_key() -> None:
    with pytest.raises(ConfigError) as refused:
        DdsConfig.from_mapping({"max_age_s": -1, "reader": {"topic": ""}})
    assert refused.value.key == "dds.psk_file"
    assert "required" in str(refused.value)
    assert "dds.max_age_s=-1.0" in str(refused.value) and "dds.reader.topic=''" in str(
        refused.value
    )


def test_config_nan_bound_is_not_a_number() -> None:
    with pytest.raises(ConfigError, match="not a number") as refused:
        DdsConfig.from_mapping({"psk_file": "k", "max_age_s": float("nan")})
    assert refused.value.key == "dds.max_age_s"
    assert "86400" in refused.value.allowed and "should be less" not in str(refused.value)


@pytest.mark.parametrize("spec", ["sqlite: ", "sqlite:", "sqlite:\t"])
def test_config_blank_sqlite_path_is_refused(spec: str) -> None:
    with pytest.raises(ConfigError, match="non-blank path") as refused:
        DdsConfig.from_mapping({"psk_file": "k", "reader": {"store": spec}})
    assert refused.value.key == "dds.reader.store"


def test_config_forward_bound_leaves_room_for_the_writers_reservation() -> None:
    with pytest.raises(ConfigError, match="reserve 1 s") as refused:
        DdsConfig.from_mapping({"psk_file": "k", "max_forward_s": 1})
    assert refused.value.key == "dds.max_forward_s"


def first_accepted(
    reader: SealedReader, tick: Callable[[], object], timeout_s: float = 20.0
) -> SampleVerdict:
    """Poll ``reader`` (``tick`` between polls: the writer's period) until it accepts."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        tick()
        accepted = [v for v in reader.poll(0.05) if v.accepted]
        if accepted:
            return accepted[0]
    pytest.fail(f"nothing accepted within {timeout_s} s: {dict(reader.counts)}")


def test_fresh_reader_accepts_after_an_answer_without_waiting_out_its_fence(
    participant: Any, clock: ManualClock
) -> None:
    """The manual clock stands still: only an answered challenge can open the fence."""
    writer = SealedWriter(peer(participant), TOPIC, PSK, clock=clock)
    captured = writer.seal(b"sealed before the reader started", instance="arm")
    clock.advance(0.5)
    reader = SealedReader(participant, TOPIC, PSK, clock=clock)  # memory store: fenced
    until("the writer matches a reader", lambda: writer.matched_readers() >= 1)
    sent: list[SealedSample] = []
    verdict = first_accepted(reader, lambda: sent.append(writer.write(b"tick", instance="arm")))
    assert verdict.epoch is not None and verdict.epoch <= reader.verifier.restart_fence()
    assert reader.counts["answer_accepted"] >= 1 and writer.counts["challenge_answered"] >= 1
    clock.advance(MAX_FORWARD_S + 1)  # the fence ends: the reader leaves the ping topic

    def left() -> bool:
        reader.poll(0.01)
        return writer.challenge_peers() == 0

    until("past its fence, the reader leaves the challenge channel at once", left, 10.0)
    rogue = rogue_writer(participant)
    for sample in (captured, *sent):
        rogue.publish(sample)
    refused = collect(reader, len(sent) + 1)
    assert not any(v.accepted for v in refused), [v.line() for v in refused]


def test_forged_or_replayed_answer_leaves_the_reader_fenced(
    participant: Any, clock: ManualClock
) -> None:
    reader = SealedReader(participant, TOPIC, PSK, clock=clock)
    writer = SealedWriter(peer(participant), TOPIC, PSK, clock=clock)
    challenge = reader.verifier.challenge()
    assert challenge is not None
    old_answer = writer.signer.answer(challenge)  # a previous run's exchange, captured
    reader.verifier.policy.nonces.clear()  # that run is gone: its nonce with it
    stranger = EpochSigner(os.urandom(32), nonce_prefix=writer.nonce_prefix, clock=clock)
    rogue = PingChannel(peer(participant), TOPIC)
    until("the rogue writer sees both peers", lambda: rogue.peers() >= 2)
    reader.poll(0.05)  # the reader's own challenge goes out; we forge the answers to it

    def forged_and_replayed() -> bool:
        for nonce in list(reader.verifier.policy.nonces):
            rogue.send(seal(derive_key(os.urandom(32), Kind.PING), Kind.ANSWER,
                            writer.nonce_prefix, 1, nonce))  # fmt: skip
        rogue.send(old_answer)
        reader.poll(0.05)
        counts = reader.counts
        return counts["ping_dropped_forged"] >= 1 and counts["ping_dropped_stale"] >= 1

    until("the forged and replayed answers are dropped on arrival", forged_and_replayed)
    assert reader.verifier.policy.answered == {} and stranger.rotations == 0
    reader.judge(writer.seal(b"still fenced", instance="arm"))
    assert reader.counts["stale"] == 1


@pytest.mark.parametrize("forward_s", [5.0, 60.0])
def test_fresh_reader_in_another_process_accepts_within_a_second(
    forward_s: float, record_property: Callable[[str, object], None]
) -> None:
    """Two processes, real clocks, the memory store: the time from the reader's start to
    its first accepted sample, and every capture refused."""
    domain_id = next(_IDS)
    writer = _CHILDREN(
        dds_writer_process(domain_id, PSK, TOPIC, period_s=0.1, max_forward_s=forward_s)
    )
    try:
        assert writer.stdout is not None
        captures = [bytes.fromhex(writer.stdout.readline()) for _ in range(3)]
        participant = join_domain(domain_id)
        start = time.monotonic()
        reader = SealedReader(participant, TOPIC, PSK, max_forward_s=forward_s)
        verdict = first_accepted(reader, lambda: None)
        elapsed = time.monotonic() - start
        record_property(f"time_to_first_accept_s[{forward_s}]", round(elapsed, 3))
        print(f"max_forward_s={forward_s}: first accept after {elapsed:.3f} s")
        assert verdict.epoch is not None and verdict.epoch <= reader.verifier.restart_fence()
        captures += [bytes.fromhex(writer.stdout.readline()) for _ in range(2)]
    finally:
        writer.kill()
        writer.communicate()
    while reader.poll(0.5):  # the dead writer's last samples, if any are still in flight
        pass
    rogue = rogue_writer(participant)
    for sealed in captures:
        rogue.publish(SealedSample(instance="arm", sealed=sealed))
    replayed = collect(reader, len(captures))
    assert not any(v.accepted for v in replayed), [v.line() for v in replayed]


def test_flush_says_false_when_readers_do_not_acknowledge_in_time(
    participant: Any, clock: ManualClock
) -> None:
    """A reader that has not acknowledged in time is ``False``, never a traceback: the
    cyclonedds writer reports that timeout as an ``AttributeError`` (its own bug)."""
    from cyclonedds.core import DDSException  # noqa: PLC0415

    writer, _reader = pair(participant, clock)
    assert writer.flush() is True
    inner = writer._writer  # the library's writer, its timeout path forced
    inner._wait_for_acks = lambda *_: DDSException.DDS_RETCODE_TIMEOUT
    assert writer.flush(timeout_s=0.01) is False


def test_fresh_reader_leaves_its_fence_through_a_keyless_challenge_flood(
    record_property: Callable[[str, object], None],
) -> None:
    """Two processes with no key flood ``antireplay/ping`` with challenges and answers
    (review finding 5: the topic kept 64 samples, every genuine one was pushed out and the
    reader stayed fenced for its whole ``max_forward_s``).  Now junk is dropped by the
    topic filter before it takes history: a fresh reader with a 30 s fence accepts the
    genuine writer's fresh command within seconds, and counts the junk it dropped."""
    domain_id = next(_IDS)
    floods = [_CHILDREN(dds_junk_process(domain_id, TOPIC)) for _ in range(2)]
    writer = _CHILDREN(dds_writer_process(domain_id, PSK, TOPIC, period_s=0.1, max_forward_s=30.0))
    try:
        for flood in floods:
            assert flood.stdout is not None and flood.stdout.readline() == "flooding\n"
        assert writer.stdout is not None and writer.stdout.readline()  # it writes
        reader = SealedReader(join_domain(domain_id), TOPIC, PSK, max_forward_s=30.0)
        start = time.monotonic()
        verdict = first_accepted(reader, lambda: None, timeout_s=10.0)
        elapsed = time.monotonic() - start
        record_property("flooded_time_to_first_accept_s", round(elapsed, 3))
        assert verdict.epoch is not None and verdict.epoch <= reader.verifier.restart_fence()
        dropped = {k: n for k, n in reader.counts.items() if k.startswith("ping_dropped_")}
        assert sum(dropped.values()) > 0, dict(reader.counts)  # no nonce of ours, or forged
        assert [f.poll() for f in floods] == [None, None]  # still flooding all along
    finally:
        for process in (*floods, writer):
            process.kill()
            process.communicate()
    assert reader.counts["answer_accepted"] >= 1, dict(reader.counts)
    print(f"first accept after {elapsed:.3f} s through the flood: {dict(reader.counts)}")
