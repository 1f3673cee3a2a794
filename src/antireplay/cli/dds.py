"""``antireplay dds …``: run the relay, a reader that prints verdicts, a writer, a rogue replayer.

Registered by :mod:`antireplay.cli`; Cyclone DDS is imported only when a
command runs, so ``antireplay --help`` works without the ``dds`` extra.
Every command reads the ``dds:`` block of ``--config`` (see
:mod:`antireplay.dds.config`).
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import click

from antireplay.cli._common import _fail, stop_on_signal
from antireplay.core.errors import AntiReplayError, ConfigError
from antireplay.dds.config import DdsConfig, parse_udp
from antireplay.epochs import signer_state
from antireplay.state import open_store

CONFIG = click.option(
    "--config",
    "config_path",
    required=True,
    type=click.Path(path_type=Path, dir_okay=False),
    help="YAML file with a dds: block (domain, fleet key, reader, writer, relay).",
)


def _load(path: Path) -> DdsConfig:
    from antireplay.config import AppConfig  # noqa: PLC0415

    try:
        block = AppConfig.from_yaml(path).dds  # every section checked: no key out of place
    except ConfigError as exc:
        _fail(str(exc))
    if block is None:
        _fail(f"{path}: no dds: block (allowed: a mapping with at least psk_file)")
    return block


def _participant(cfg: DdsConfig) -> Any:
    try:
        from antireplay.dds.domain import join_domain  # noqa: PLC0415 - needs the dds extra
    except ImportError as exc:
        _fail(f"{exc}; install the dds extra: pip install 'antireplay[dds]'")
    return join_domain(cfg.domain_id, loopback=cfg.loopback_only)


def _audit(cfg: DdsConfig) -> Any:
    """The ``dds.audit`` trail, rotated and retained by the ``audit:`` defaults, with a spill."""
    from antireplay.config import AuditConfig  # noqa: PLC0415
    from antireplay.wiring import open_audit  # noqa: PLC0415

    return None if cfg.audit is None else open_audit(AuditConfig(path=cfg.audit))


@click.group()
def dds() -> None:
    """Replay-proof DDS topics and announcements (Cyclone DDS; the antireplay[dds] extra)."""


@dds.command()
@CONFIG
@click.option("--topic", default=None, help="Topic to read (default: dds.reader.topic).")
@click.option("--count", default=0, type=int, help="Stop after this many verdicts (0: never).")
@click.option("--timeout", "timeout_s", default=0.0, type=float, help="Stop after S seconds.")
def read(config_path: Path, topic: str | None, count: int, timeout_s: float) -> None:
    """Print one verdict per received sample: ACCEPTED, or REFUSED with its code."""
    from antireplay.dds.topics import SealedReader  # noqa: PLC0415

    cfg = _load(config_path)
    try:
        reader = SealedReader(
            _participant(cfg),
            topic or cfg.reader.topic,
            cfg.psk(),
            store=open_store(cfg.reader.store),
            max_age_s=cfg.max_age_s,
            max_forward_s=cfg.max_forward_s,
            audit=_audit(cfg),
        )
    except (AntiReplayError, ValueError) as exc:
        _fail(str(exc))
    click.echo(f"reading {reader.topic_name} on domain {cfg.domain_id}", err=True)
    stop = stop_on_signal()
    deadline = time.monotonic() + timeout_s if timeout_s > 0 else None
    seen = 0
    while not stop.is_set() and (count == 0 or seen < count):
        if deadline is not None and time.monotonic() >= deadline:
            break
        for verdict in reader.poll(0.1)[: count - seen if count else None]:
            click.echo(verdict.line())
            seen += 1
    summary = ", ".join(f"{k}={v}" for k, v in sorted(reader.counts.items()))
    click.echo(f"verdicts: {summary or 'none'}", err=True)
    if count and seen < count:
        sys.exit(1)


@dds.command()
@CONFIG
@click.option("--topic", default=None, help="Topic to write (default: dds.writer.topic).")
@click.option("--instance", default="", help="Instance key of the samples.")
@click.option(
    "--wait-readers",
    default=1,
    type=click.IntRange(0),
    show_default=True,
    help="Publish once this many readers matched (0: at once; DDS drops unmatched samples).",
)
@click.option(
    "--capture",
    type=click.Path(path_type=Path, dir_okay=False),
    help="Also write this run's sealed samples here, one JSON line each (the file is replaced).",
)
@click.argument("messages", nargs=-1, required=True)
def write(  # noqa: PLR0917 - one option per knob
    config_path: Path,
    topic: str | None,
    instance: str,
    wait_readers: int,
    capture: Path | None,
    messages: tuple[str, ...],
) -> None:
    """Seal and publish MESSAGES (after waiting for readers to match)."""
    from antireplay.dds.topics import SealedWriter  # noqa: PLC0415

    cfg = _load(config_path)
    try:
        writer = SealedWriter(
            _participant(cfg),
            topic or cfg.writer.topic,
            cfg.psk(),
            state=None if cfg.writer.state_file is None else signer_state(cfg.writer.state_file),
            max_forward_s=cfg.max_forward_s,
        )
    except (AntiReplayError, ValueError) as exc:
        _fail(str(exc))
    _wait_readers(writer, wait_readers)
    if capture is not None:
        capture.write_text("", encoding="ascii")  # this run's samples only: re-runnable
    for message in messages:
        sample = writer.write(message.encode(), instance=instance)
        if capture is not None:
            line = {"topic": writer.topic_name, "instance": instance,
                    "sealed": bytes(sample.sealed).hex()}  # fmt: skip
            with capture.open("a", encoding="ascii") as handle:
                handle.write(json.dumps(line) + "\n")
        click.echo(f"sent {message!r} prefix={writer.nonce_prefix.hex()}")
    writer.flush()


@dds.command()
@CONFIG
@click.option(
    "--wait-readers",
    default=1,
    type=click.IntRange(0),
    show_default=True,
    help="Republish once this many readers matched.",
)
@click.argument("captured", type=click.Path(path_type=Path, exists=True, dir_okay=False))
def replay(config_path: Path, wait_readers: int, captured: Path) -> None:
    """Play the attacker: republish captured samples from a participant without the key."""
    from antireplay.dds.topics import SealedWriter  # noqa: PLC0415
    from antireplay.dds.wire import SealedSample  # noqa: PLC0415

    cfg = _load(config_path)
    participant, own_key = _participant(cfg), os.urandom(32)  # the attacker's key, not the fleet's
    writers: dict[str, SealedWriter] = {}
    for raw in captured.read_text(encoding="ascii").splitlines():
        line = json.loads(raw)
        topic = str(line["topic"])
        if topic not in writers:
            writers[topic] = SealedWriter(participant, topic, own_key)
            _wait_readers(writers[topic], wait_readers)
        sealed = bytes.fromhex(str(line["sealed"]))
        writers[topic].publish(SealedSample(instance=str(line["instance"]), sealed=sealed))
        click.echo(f"replayed a captured sample on {topic}")
    for writer in writers.values():
        writer.flush()


@dds.command()
@CONFIG
@click.option("--duration", "duration_s", default=0.0, type=float, help="Stop after S seconds.")
def relay(config_path: Path, duration_s: float) -> None:
    """Run the announcement relay (Cloud Discovery Service role) until stopped."""
    from antireplay.dds.ping import PingListener  # noqa: PLC0415
    from antireplay.dds.relay import AnnouncementRelay  # noqa: PLC0415

    cfg = _load(config_path)
    if cfg.relay is None:
        _fail(f"{config_path} has no dds.relay block (service_name, signer_state, verifier_store)")
    try:
        psk = cfg.psk()
        audit = _audit(cfg)
        listen = cfg.relay.ping_listen
        ping = None if listen is None else PingListener(
            psk, bind=parse_udp(listen), max_age_s=cfg.max_age_s,
            max_forward_s=cfg.max_forward_s, audit=audit,
        )  # fmt: skip
        service = AnnouncementRelay(
            _participant(cfg),
            psk,
            service_name=cfg.relay.service_name,
            signer_state=signer_state(cfg.relay.signer_state),
            verifier_store=open_store(cfg.relay.verifier_store),
            max_age_s=cfg.max_age_s,
            max_forward_s=cfg.max_forward_s,
            audit=audit,
            ping=ping,
        )
    except (AntiReplayError, ValueError, OSError) as exc:
        _fail(str(exc))
    click.echo(f"relay {cfg.relay.service_name!r} on domain {cfg.domain_id}", err=True)
    stop = stop_on_signal()
    deadline = time.monotonic() + duration_s if duration_s > 0 else None
    reported = 0
    while not stop.is_set() and (deadline is None or time.monotonic() < deadline):
        for verdict in service.pump(0.1):
            click.echo(verdict.line())
        for twin in service.twins[reported:]:
            click.echo(twin.line())
        reported = len(service.twins)
    click.echo(f"relayed {service.relayed}; twins reported {reported}", err=True)


def _wait_readers(writer: Any, count: int) -> None:
    """DDS drops samples that no reader matched yet: wait (bounded) for the readers."""
    if count and not writer.wait_for_readers(count, 20.0):
        _fail(f"no {count} reader(s) matched within 20 s", 1)
