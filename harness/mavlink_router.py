"""A real ``antireplay mavlink-router`` process for the CLI tests, and the parties around it:
a vehicle socket, ground stations signing with the real clock (or a stepped one), and the
host's own non-loopback address for the endpoints a finding needs on the network."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as dialect

from antireplay.mavlink import MAV_EPOCH, UNITS_PER_S, parse_frame
from antireplay.mavlink.codec import Frame
from harness import until
from harness.mavlink_frames import Sink

PASSPHRASE = "correct-horse-battery-staple"


def host_address() -> str | None:
    """This host's first non-loopback IPv4 address (``ip -4 addr``), None if it has none."""
    try:
        out = subprocess.run(
            ["ip", "-4", "-o", "addr"], capture_output=True, text=True, timeout=10, check=True
        ).stdout
    except (OSError, subprocess.SubprocessError):
        return None
    for line in out.splitlines():
        words = line.split()
        address = words[words.index("inet") + 1].partition("/")[0] if "inet" in words else ""
        if address and not address.startswith("127."):
            return address
    return None


def clockstep_shim(directory: Path) -> Path:
    """``clockstep.c`` compiled into ``directory``: preloaded, the process's wall clock runs
    ahead by the whole seconds in ``$CLOCK_STEP_FILE`` (monotonic time untouched)."""
    shim = directory / "clockstep.so"
    if not shim.exists():
        source = Path(__file__).with_name("clockstep.c")
        cc = [os.environ.get("CC", "cc"), "-shared", "-fPIC", "-O2", "-o", str(shim), str(source)]
        subprocess.run(cc, check=True, timeout=60)
    return shim


@dataclass
class RouterRun:
    """A running router: its process, its start line, and (once stopped) its stderr."""

    proc: subprocess.Popen[str]
    line: str
    step_file: Path | None = None
    stderr: str = field(default="")

    def step_clock(self, seconds: int) -> None:
        """Set the router's wall clock ``seconds`` ahead of the real one (an NTP step)."""
        assert self.step_file is not None, "started without a stepped clock"
        self.step_file.write_text(str(seconds))


@contextmanager
def router_process(
    args: list[str], *, tmp: Path | None = None, clock_ahead_s: int | None = None
) -> Iterator[RouterRun]:
    """``antireplay mavlink-router ARGS`` (the link passphrase in ``MAV_PASSPHRASE``), its
    wall clock ``clock_ahead_s`` ahead if given (a shim compiled in ``tmp``; stepped again
    with :meth:`RouterRun.step_clock`); yields once it printed its start line; stopped with
    SIGTERM (a clean stop), its stderr kept."""
    env = {**os.environ, "MAV_PASSPHRASE": PASSPHRASE}
    step = None
    if clock_ahead_s is not None:
        assert tmp is not None
        step = tmp / "clock-step"
        step.write_text(str(clock_ahead_s))
        env |= {"LD_PRELOAD": str(clockstep_shim(tmp)), "CLOCK_STEP_FILE": str(step)}
    cli = [sys.executable, "-m", "antireplay", "mavlink-router", "--passphrase-env"]
    proc = subprocess.Popen(
        [*cli, "MAV_PASSPHRASE", *args], env=env, text=True,
        stdout=subprocess.PIPE, stderr=subprocess.PIPE,
    )  # fmt: skip
    assert proc.stdout is not None
    run = RouterRun(proc, proc.stdout.readline(), step)
    try:
        assert run.line.startswith("mavlink-router "), proc.communicate(timeout=30)
        yield run
    finally:
        proc.send_signal(signal.SIGTERM)
        run.stderr = proc.communicate(timeout=30)[1]


def udp_socket(host: str = "127.0.0.1") -> socket.socket:
    """A UDP socket bound to a free port on ``host`` (a vehicle, a station, an attacker)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind((host, 0))
    sock.settimeout(0.2)
    return sock


def station(
    sysid: int = 255, compid: int = 190, *, link_id: int = 1, ahead_s: float = 0.0
) -> tuple[Any, Sink]:
    """A ground station signing with the link passphrase's key, stamping the real clock
    plus ``ahead_s`` (as a station whose clock runs ahead, or a router's stepped clock)."""
    from antireplay.mavlink import passphrase_key  # noqa: PLC0415

    sink = Sink()
    mav = dialect.MAVLink(sink, srcSystem=sysid, srcComponent=compid)
    mav.signing.secret_key, mav.signing.sign_outgoing = passphrase_key(PASSPHRASE), True
    mav.signing.link_id = link_id
    mav.signing.timestamp = int((time.time() + ahead_s - MAV_EPOCH) * UNITS_PER_S)
    return mav, sink


def frames_from(
    sock: socket.socket, msgid: int, what: str, timeout: float = 20.0
) -> list[tuple[Frame, Any]]:
    """Receive on ``sock`` until a frame with ``msgid`` arrived (within ``timeout``): every
    frame received, parsed, with the address it came from."""
    got: list[tuple[Frame, Any]] = []

    def arrived() -> bool:
        try:
            data, peer = sock.recvfrom(4096)
        except TimeoutError:
            return False
        got.append((parse_frame(data), peer))
        return got[-1][0].msgid == msgid

    until(what, arrived, timeout)
    return got


def drained(sock: socket.socket) -> list[Frame]:
    """Every frame already waiting on ``sock`` (none waited for)."""
    sock.setblocking(False)
    got: list[Frame] = []
    try:
        while True:
            got.append(parse_frame(sock.recv(4096)))
    except BlockingIOError:
        return got
    finally:
        sock.settimeout(0.2)
