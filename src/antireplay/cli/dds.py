"""``antireplay dds …``: run the relay, a reader that prints verdicts, a writer, a rogue replayer.

Registered by :mod:`antireplay.cli`; Cyclone DDS is imported only when a command runs, so
``antireplay --help`` works without the ``dds`` extra.  Every command reads the one
configuration file (``--config``: its ``dds:`` block, and ``audit:``, ``audit_space:`` and
``state:`` as for every command; a key out of place is refused, naming where it belongs)
and builds what it runs on through :class:`antireplay.wiring.dds.DdsCommand`.
"""

from __future__ import annotations

import contextlib
import json
import math
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from antireplay.cli._common import _fail, stop_on_signal, until_stopped, warn_if_shared
from antireplay.cli.dds_io import (
    RELAYED_TOPIC,
    FenceFold,
    answer_pending,
    shown,
    start_line,
    stdin_lines,
)
from antireplay.config import AppConfig
from antireplay.core.errors import AntiReplayError, ConfigError

if TYPE_CHECKING:
    from antireplay.wiring.dds import DdsCommand

CONFIG = click.option(
    "--config",
    "config_path",
    required=True,
    type=click.Path(path_type=Path, dir_okay=False),
    help="YAML file with a dds: block (domain, fleet key, reader, writer, relay).",
)


@contextlib.contextmanager
def _wired(path: Path) -> Iterator[DdsCommand]:
    """The command's leaves and participant from the file at ``path``; a configuration or
    state error is one line and exit 2; everything opened is closed on the way out."""
    try:
        config = AppConfig.from_yaml(path)  # every section checked: no key out of place
    except ConfigError as exc:
        _fail(str(exc))
    if config.dds is not None:
        warn_if_shared(Path(config.dds.psk_file), "dds.psk_file")
    try:
        from antireplay.wiring.dds import DdsCommand  # noqa: PLC0415 - needs the dds extra
    except ImportError as exc:
        _fail(f"{exc}; install the dds extra: pip install 'antireplay[dds]'")
    try:
        command = DdsCommand(config)
    except (AntiReplayError, ValueError, OSError) as exc:
        _fail(str(exc))
    with command:
        yield command


METRICS_PORT = click.option(
    "--metrics-port",
    type=click.IntRange(0, 65535),
    default=None,
    help="Serve Prometheus metrics here (verdicts per outcome, the trail's bytes).",
)
METRICS_HOST = click.option(
    "--metrics-host",
    default="127.0.0.1",
    show_default=True,
    help="The address the metrics port binds (0.0.0.0 for a Prometheus on another host).",
)


def _serve_metrics(wired: DdsCommand, counts: dict[str, Any], port: int | None, host: str) -> None:
    """``--metrics-port``: the command's counters, read at each scrape."""
    if port is None:
        return
    from antireplay.wiring.metrics import serve_metrics  # noqa: PLC0415

    try:
        serve_metrics(lambda: wired.metrics(counts), port, host)
    except (OSError, ValueError) as exc:  # an unknown host, a busy port, a bad name
        _fail(
            f"--metrics-host {host} --metrics-port {port}: cannot serve metrics there "
            f"({getattr(exc, 'strerror', None) or exc})"
        )


def _built(build: Any, *args: Any) -> Any:
    """``build(*args)``, a configuration or state error as one line and exit 2."""
    try:
        return build(*args)
    except (AntiReplayError, ValueError, OSError) as exc:
        _fail(str(exc))


@click.group()
def dds() -> None:
    """Replay-proof DDS topics and announcements (Cyclone DDS; the antireplay[dds] extra)."""


@dds.command()
@CONFIG
@click.option("--topic", default=None, help="Topic to read (default: dds.reader.topic).")
@click.option("--count", default=0, type=int, help="Stop after this many verdicts (0: never).")
@click.option("--timeout", "timeout_s", default=0.0, type=float, help="Stop after S seconds.")
@METRICS_PORT
@METRICS_HOST
def read(  # noqa: PLR0917 - one option per knob
    config_path: Path,
    topic: str | None,
    count: int,
    timeout_s: float,
    metrics_port: int | None,
    metrics_host: str,
) -> None:
    """Print one verdict per received sample: ACCEPTED, or REFUSED with its code (refusals
    behind the start fence: one summary line per second)."""
    with _wired(config_path) as wired:
        reader = _built(wired.reader, topic)
        _serve_metrics(wired, {reader.topic_name: reader.counts}, metrics_port, metrics_host)
        click.echo(start_line(reader, wired), err=True)
        relayed = reader.topic_name == RELAYED_TOPIC
        stop = stop_on_signal()
        deadline = time.monotonic() + timeout_s if timeout_s > 0 else None
        seen, fold = 0, FenceFold(reader)
        while not stop.is_set() and (count == 0 or seen < count):
            if deadline is not None and time.monotonic() >= deadline:
                break
            for verdict in reader.poll(0.1)[: count - seen if count else None]:
                if not fold.took(verdict):
                    click.echo(shown(verdict, relayed=relayed))
                seen += 1
            fold.report(time.monotonic())
        fold.report(math.inf)
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
@click.option(
    "--linger",
    "linger_s",
    default=1.0,
    type=click.FloatRange(0, 60),
    show_default=True,
    help="Seconds to wait for, and answer, fresh readers' challenges before the first sample.",
)
@click.option("--stdin", "from_stdin", is_flag=True, help="Publish each line read from stdin.")
@click.argument("messages", nargs=-1)
def write(  # noqa: PLR0917 - one option per knob
    config_path: Path,
    topic: str | None,
    instance: str,
    wait_readers: int,
    capture: Path | None,
    linger_s: float,
    from_stdin: bool,
    messages: tuple[str, ...],
) -> None:
    """Seal and publish MESSAGES (or, with --stdin, each line read) after waiting for readers
    to match and answering their challenges; "sent" once the readers acknowledged it."""
    if from_stdin == bool(messages):
        _fail("give MESSAGES or --stdin (one sample per line), not both")
    with _wired(config_path) as wired:
        writer = _built(wired.writer, topic)
        sent: list[str] = []
        total = "" if from_stdin else f" of {len(messages)}"
        with until_stopped(lambda: f"sent {len(sent)}{total} messages"):
            _wait_readers(writer, wait_readers)
            if capture is not None:
                capture.write_text("", encoding="ascii")  # this run's samples only: re-runnable
            answered = answer_pending(writer, linger_s)
            if answered:
                click.echo(f"answered {answered} reader challenge(s)", err=True)
            lines = stdin_lines(writer.answer_challenges) if from_stdin else iter(messages)
            unacknowledged = 0
            for message in lines:
                sample = writer.write(message.encode(), instance=instance)
                if capture is not None:
                    line = {"topic": writer.topic_name, "instance": instance,
                            "sealed": bytes(sample.sealed).hex()}  # fmt: skip
                    with capture.open("a", encoding="ascii") as handle:
                        handle.write(json.dumps(line) + "\n")
                if writer.flush():
                    click.echo(f"sent {message!r} prefix={writer.nonce_prefix.hex()}")
                    sent.append(message)
                else:
                    unacknowledged += 1
                    click.echo(f"NOT acknowledged {message!r}: no reader confirmed it in 2 s")
            writer.answer_challenges()  # a reader that matched meanwhile: answered on the way out
    if unacknowledged:
        sys.exit(1)


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
    from antireplay.dds.wire import SealedSample  # noqa: PLC0415 - needs the dds extra

    with _wired(config_path) as wired:
        writers: dict[str, Any] = {}
        for raw in captured.read_text(encoding="ascii").splitlines():
            line = json.loads(raw)
            topic = str(line["topic"])
            if topic not in writers:
                writers[topic] = wired.rogue(topic)
                _wait_readers(writers[topic], wait_readers)
            sealed = bytes.fromhex(str(line["sealed"]))
            writers[topic].publish(SealedSample(instance=str(line["instance"]), sealed=sealed))
            click.echo(f"replayed a captured sample on {topic}")
        for writer in writers.values():
            writer.flush()


@dds.command()
@CONFIG
@click.option("--duration", "duration_s", default=0.0, type=float, help="Stop after S seconds.")
@METRICS_PORT
@METRICS_HOST
def relay(
    config_path: Path, duration_s: float, metrics_port: int | None, metrics_host: str
) -> None:
    """Run the announcement relay (Cloud Discovery Service role) until stopped."""
    with _wired(config_path) as wired:
        service = _built(wired.relay)
        counts = {"relay": service.counts, service.ingress.topic_name: service.ingress.counts}
        if service.ping is not None:
            counts["ping"] = service.ping.counts
        _serve_metrics(wired, counts, metrics_port, metrics_host)
        click.echo(f"relay {service.service_name!r} on domain {wired.domain_id}", err=True)
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
    if count:
        click.echo(f"waiting for {count} reader(s) of {writer.topic_name} (20 s)", err=True)
    if count and not writer.wait_for_readers(count, 20.0):
        _fail(f"no {count} reader(s) matched within 20 s", 1)
