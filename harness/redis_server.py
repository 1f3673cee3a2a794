"""Real redis-servers for tests, on free ports, started and stopped by the tests themselves:
a standalone server (optionally persistent, optionally a replica, optionally with a wall
clock the test steps) and a 3-node cluster."""

from __future__ import annotations

import contextlib
import os
import shutil
import socket
import subprocess
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
import redis

from harness import free_port


def _binary(name: str) -> str:
    found = shutil.which(name)
    if found is None:
        pytest.fail(f"{name} is not installed: the store tests need a real server")
    return found


def _wait_ping(port: int) -> None:
    client = redis.Redis(port=port, socket_connect_timeout=0.2)
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        try:
            if client.ping():
                return
        except redis.ConnectionError:
            time.sleep(0.02)
    raise RuntimeError(f"redis-server on port {port} did not start")


def _cluster_port() -> int:
    """A free port whose cluster bus port (port + 10000) is free and valid too."""
    for _ in range(200):
        port = free_port()
        if port > 55_000:
            continue
        with socket.socket() as probe:
            try:
                probe.bind(("127.0.0.1", port + 10_000))
            except OSError:
                continue
        return port
    raise RuntimeError("no free port pair for a cluster node")


class RedisServer:
    """One redis-server process.

    ``persistent`` turns on AOF with fsync on every write; ``snapshots`` keeps an RDB
    file (``dump.rdb``) that ``save()`` writes, so a test can restart from older data.
    ``stepped_clock`` preloads ``clockstep.c`` (compiled here) so that ``step_clock(s)``
    sets the server's wall clock ``s`` seconds ahead of the real one, as an NTP step or an
    operator's ``date -s`` would: its TTLs then run out early (monotonic time untouched).
    """

    def __init__(
        self,
        directory: Path,
        *,
        persistent: bool = False,
        snapshots: bool = False,
        extra: tuple[str, ...] = (),
        stepped_clock: bool = False,
    ) -> None:
        self.binary = _binary("redis-server")
        self.directory = directory
        self.persistent = persistent
        self.snapshots = snapshots
        self.extra = extra
        self.port = free_port()
        self.proc: subprocess.Popen[bytes] | None = None
        self.env: dict[str, str] | None = None
        if stepped_clock:
            shim = directory / "clockstep.so"
            source = Path(__file__).with_name("clockstep.c")
            subprocess.run(
                [_binary("cc"), "-shared", "-fPIC", "-O2", "-o", str(shim), str(source)],
                check=True,
                timeout=60,
            )
            self.env = {**os.environ, "LD_PRELOAD": str(shim)}
            self.env["CLOCK_STEP_FILE"] = str(directory / "clock-step")
            self.step_clock(0)

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def client(self) -> redis.Redis:
        return redis.Redis(port=self.port)

    def start(self) -> None:
        args = [self.binary, "--port", str(self.port), "--bind", "127.0.0.1", "--save", ""]
        args += ["--dir", str(self.directory), "--dbfilename", "dump.rdb"]
        args += (
            ["--appendonly", "yes", "--appendfsync", "always"]
            if self.persistent
            else [
                "--appendonly",
                "no",
            ]
        )
        args += list(self.extra)
        self.proc = subprocess.Popen(
            args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=self.env
        )
        _wait_ping(self.port)

    def step_clock(self, seconds: int) -> None:
        """Set this server's wall clock ``seconds`` ahead of the real one (0: back to it)."""
        assert self.env is not None, "start the server with stepped_clock=True"
        Path(self.env["CLOCK_STEP_FILE"]).write_text(f"{seconds}\n")

    def save(self) -> None:
        """Write an RDB snapshot now (what a periodic ``save`` rule would do)."""
        self.client().save()

    def kill(self) -> None:
        """kill -9: no shutdown save, nothing flushed."""
        if self.proc is not None:
            self.proc.kill()
            self.proc.wait(timeout=10)
            self.proc = None

    def stop(self) -> None:
        if self.proc is not None:
            self.proc.terminate()
            self.proc.wait(timeout=10)
            self.proc = None


class RedisCluster:
    """Three masters on loopback, slots split by ``redis-cli --cluster create``."""

    def __init__(self, directory: Path) -> None:
        self.nodes = []
        for i in range(3):
            node_dir = directory / f"node{i}"
            node_dir.mkdir()
            node = RedisServer(node_dir, extra=("--cluster-enabled", "yes"))
            node.port = _cluster_port()
            node.extra += ("--cluster-config-file", str(node_dir / "nodes.conf"))
            self.nodes.append(node)

    @property
    def url(self) -> str:
        return f"redis+cluster://127.0.0.1:{self.nodes[0].port}"

    def start(self) -> None:
        for node in self.nodes:
            node.start()
        hosts = [f"127.0.0.1:{n.port}" for n in self.nodes]
        subprocess.run(
            [_binary("redis-cli"), "--cluster", "create", *hosts, "--cluster-yes"],
            check=True,
            capture_output=True,
            timeout=60,
        )
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            info = self.nodes[0].client().cluster("info")
            if isinstance(info, dict) and info.get("cluster_state") == "ok":
                return
            time.sleep(0.05)
        raise RuntimeError("redis cluster did not become ready")

    def stop(self) -> None:
        for node in self.nodes:
            node.stop()


class Forwarder:
    """A TCP forwarder on loopback whose target can be switched: a virtual IP that moves.

    Clients connect to ``port``; ``point_to`` moves new connections to another server
    and drops the existing ones (as a failover does).
    """

    def __init__(self, target: int) -> None:
        self.target = target
        self.listener = socket.socket()
        self.listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.listener.bind(("127.0.0.1", 0))
        self.listener.listen(64)
        self.port = int(self.listener.getsockname()[1])
        self._open: list[socket.socket] = []
        self._lock = threading.Lock()
        threading.Thread(target=self._accept, daemon=True).start()

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def point_to(self, target: int) -> None:
        with self._lock:
            self.target = target
            for sock in self._open:
                sock.close()
            self._open.clear()

    def close(self) -> None:
        self.listener.close()
        self.point_to(self.target)

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self.listener.accept()
            except OSError:
                return
            with self._lock:
                try:
                    upstream = socket.create_connection(("127.0.0.1", self.target), timeout=2)
                    upstream.settimeout(None)
                except OSError:
                    client.close()
                    continue
                self._open += [client, upstream]
            for a, b in ((client, upstream), (upstream, client)):
                threading.Thread(target=self._pipe, args=(a, b), daemon=True).start()

    @staticmethod
    def _pipe(src: socket.socket, dst: socket.socket) -> None:
        try:
            while data := src.recv(65536):
                dst.sendall(data)
        except OSError:
            pass
        finally:
            for sock in (src, dst):
                with contextlib.suppress(OSError):
                    sock.close()


@contextmanager
def primary_and_replica(directory: Path) -> Iterator[tuple[RedisServer, RedisServer, Forwarder]]:
    """A primary and its replica, with a moving address (``Forwarder``) on the primary."""
    (directory / "p").mkdir()
    (directory / "r").mkdir()
    primary, replica = RedisServer(directory / "p"), RedisServer(directory / "r")
    primary.start()
    replica.start()
    vip = Forwarder(primary.port)
    try:
        replica.client().replicaof("127.0.0.1", primary.port)
        yield primary, replica, vip
    finally:
        vip.close()
        replica.stop()
        primary.stop()


def wait_replicated(primary: RedisServer, replica: RedisServer) -> None:
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        offset = primary.client().info("replication")["master_repl_offset"]
        info = replica.client().info("replication")
        if info.get("master_link_status") == "up" and info.get("slave_repl_offset") == offset:
            return
        time.sleep(0.02)
    raise AssertionError("the replica did not catch up")
