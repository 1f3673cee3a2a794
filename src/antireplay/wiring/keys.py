"""The gateway's key watcher: the shared revocation list and key reloads, off the request path.

Theory of operation
-------------------
A request never reads the store for its key: :class:`KeyWatcher` polls the state's
:class:`~antireplay.state.revocations.RevocationList` every :data:`POLL_S` from one daemon
thread (one small read), swaps a new ``revoked`` set into the
:class:`~antireplay.rcan.auth.KeyRegistry` when the revocation counter moved, and moves the
registry's ``fresh_until`` to the last good poll plus :data:`PROMISE_S`.  So a revocation
reaches every gateway on the state within :data:`PROMISE_S`, or the gateway fails closed:
past ``fresh_until`` the registry answers ``STATE_UNAVAILABLE`` to everything but an ESTOP
(whose key must still not be known revoked and its signature verify).  The first failure
and the recovery are each logged once and audited; while it fails, the watcher retries every
:data:`RETRY_S`, so a store that is back serves again at once.  The revocation counter only
grows (unrevoke bumps it too): one that went backwards (a flushed or restarted Redis, an older
SQLite file) is a lost list: the watcher keeps the kids it knew, writes them back, logs once,
audits ``REVOCATIONS_LOST`` and counts ``antireplay_revocations_lost_total``.

Reloads: ``SIGHUP`` (:meth:`KeyWatcher.request_reload`, safe in a signal handler: it sets a
flag the next poll reads) or ``antireplay keys reload`` (the list's ``reloads`` counter,
seen by every gateway on the state) re-reads the configuration through the ``load``
callable and swaps the new key set in one assignment (:meth:`KeyRegistry.replace`); a file
that does not load keeps the old keys, logs one line and counts a failed reload.
:class:`KeyMetrics` exports seconds to expiry per kid, the revoked set's size, the list's
freshness and the reload counts.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
import weakref
from collections.abc import Callable, Iterator

from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from antireplay.audit import AuditLog
from antireplay.audit.chain import AuditRow
from antireplay.config import AppConfig
from antireplay.core.clock import Clock, resolve
from antireplay.core.errors import AntiReplayError, Code, StateUnavailableError
from antireplay.rcan.auth import KeyRegistry
from antireplay.state.revocations import RELOADS, REVOCATIONS, RevocationList, open_revocations
from antireplay.wiring.leaves import open_trail

log = logging.getLogger("antireplay.keys")

#: How often the watcher reads the list's counters.
POLL_S = 0.25
#: How often while the list is unreachable (so a recovered store serves again at once).
RETRY_S = 0.05
#: How long after its last good read the revocation list is still trusted.
PROMISE_S = 1.0


class KeyWatcher:
    """Keeps one registry's revoked set fresh and reloads its keys (module docstring)."""

    def __init__(
        self,
        registry: KeyRegistry,
        revocations: RevocationList,
        *,
        load: Callable[[], KeyRegistry] | None = None,
        audit: AuditLog | None = None,
        clock: Clock | None = None,
    ) -> None:
        self.registry = registry
        self.revocations = revocations
        self.load = load
        self.audit = audit
        self.clock = resolve(clock)  # real time: the thread polls on it (tests: a manual one)
        registry.freshness = clock  # the registry reads fresh_until on the same clock
        self.reloads = {"ok": 0, "failed": 0}
        self.lost = 0  # times the shared list went backwards (flushed / restored) and was re-seeded
        self._seen: dict[str, int] | None = None
        self._reload_asked = False
        self._failing = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._reloading: threading.Thread | None = None
        registry.fresh_until = -1.0  # unknown until the first good read
        self.refresh()

    def request_reload(self) -> None:
        """Re-read the keys at the next poll (async-signal-safe: only sets a flag)."""
        self._reload_asked = True

    def refresh(self) -> None:
        """One poll: the counters, the revoked set if it moved, a reload if one was asked."""
        try:
            counters = self.revocations.counters()
            if self._seen is not None and counters[REVOCATIONS] < self._seen[REVOCATIONS]:
                counters = self._reseed()
            if self._seen is None or counters[REVOCATIONS] != self._seen[REVOCATIONS]:
                self.registry.revoked = self.revocations.revoked()
            asked = self._seen is not None and counters[RELOADS] != self._seen[RELOADS]
            self._seen = counters
        except StateUnavailableError as exc:
            if not self._failing:
                self._failing = True
                why = f"revocation list unreachable ({exc.reason}); after {PROMISE_S:g} s " \
                    "without it only a fresh ESTOP passes"  # fmt: skip
                log.error("antireplay: %s", why)
                self._record(Code.STATE_UNAVAILABLE, why)
            asked = False
        else:
            self.registry.fresh_until = self.clock.monotonic() + PROMISE_S
            if self._failing:
                self._failing = False
                log.warning("antireplay: revocation list reachable again")
                self._record("REVOCATIONS_RESTORED", "revocation list reachable again")
        if (asked or self._reload_asked) and self.load is not None:
            self._reload_asked = False
            self._reload_soon()

    def _reload_soon(self) -> None:
        """On the poll thread, reload on a thread of its own: a slow load (a big ``keys:``, a
        slow disk) must not stop the polls that keep the list fresh (else every request but
        an ESTOP would be refused meanwhile); inline when called directly."""
        if threading.current_thread() is not self._thread:
            self.reload()
        elif self._reloading is not None and self._reloading.is_alive():
            self._reload_asked = True  # after the one under way
        else:
            self._reloading = threading.Thread(
                target=self.reload, name="antireplay-keys-reload", daemon=True
            )
            self._reloading.start()

    def _reseed(self) -> dict[str, int]:
        """The list's counter only grows (``unrevoke`` bumps it too), so a smaller one means the
        store lost the list (flushed, restarted without persistence, an older file): keep what
        we knew, write it back so a restarted replica learns it, say so once per loss."""
        known = self.registry.revoked
        missing = sorted(known - self.revocations.revoked())
        for kid in missing:
            self.revocations.revoke(kid)
        self.lost += 1
        kids = ",".join(missing)
        why = f"revocation list went backwards; re-seeded {len(missing)} kid(s): {kids}"
        log.error("antireplay: %s", why)
        self._record("REVOCATIONS_LOST", why[:200])
        return self.revocations.counters()

    def reload(self) -> bool:
        """Swap in the keys ``load`` returns; a failure keeps the old keys (one log line)."""
        assert self.load is not None
        try:
            fresh = self.load()
        except (AntiReplayError, OSError, ValueError) as exc:
            self.reloads["failed"] += 1
            kept = len({e.kid for e in self.registry.entries.values()})
            why = " ".join(str(exc).split())  # one line, whatever the parser said
            log.error("antireplay: keys reload failed, keeping the %d loaded keys: %s", kept, why)
            self._record("KEYS_RELOAD_FAILED", why[:200])
            return False
        self.registry.replace(fresh)
        self.reloads["ok"] += 1
        kids = sorted({e.kid for e in fresh.entries.values()})
        log.warning("antireplay: keys reloaded: %s", ", ".join(kids) or "no keys")
        self._record("KEYS_RELOADED", ",".join(kids)[:200])
        return True

    def _record(self, code: str, what: str) -> None:
        if self.audit is None:
            return
        with contextlib.suppress(AntiReplayError):
            self.audit.append(AuditRow(resolve(self.registry.clock).wall(), "keys", code, what))

    def start(self) -> KeyWatcher:
        """Poll every :data:`POLL_S` on a daemon thread until :meth:`stop`, or until the
        watcher is dropped: the thread holds it weakly, so an app that is never shut down
        (no lifespan) does not keep its receiver, trail and list open for the process."""
        self._thread = threading.Thread(
            target=_poll, args=(weakref.ref(self), self._stop), name="antireplay-keys", daemon=True
        )
        self._thread.start()
        return self

    def stop(self) -> None:
        """End the thread and release the list's connection."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5)
        self.revocations.close()


def _poll(ref: weakref.ref[KeyWatcher], stop: threading.Event) -> None:
    """The watcher's thread: refresh while the watcher lives and is not stopped."""
    while (watcher := ref()) is not None:
        wait = RETRY_S if watcher._failing else POLL_S
        del watcher  # not held across the wait: a dropped watcher ends this loop
        if stop.wait(wait) or (watcher := ref()) is None:
            return
        watcher.refresh()
        del watcher


def change_revocation(config: AppConfig, kid: str, *, revoke: bool) -> bool:
    """Revoke (or unrevoke) ``kid`` on the state ``config`` names and audit it in its
    trail (``antireplay keys revoke``); whether the list changed.  The row is written
    after the change (the change is what gateways obey; a failed row raises)."""
    revocations = open_revocations(config.store_spec)
    try:
        changed = revocations.revoke(kid) if revoke else revocations.unrevoke(kid)
    finally:
        revocations.close()
    audit, _ = open_trail(config)
    try:
        code = "KEY_REVOKE" if revoke else "KEY_UNREVOKE"
        audit.append(AuditRow(time.time(), "keys", code, f"kid={kid}"[:200], sender=kid))
    finally:
        audit.close()
    return changed


class KeyMetrics(Collector):
    """Prometheus view of the key lifecycle (see the module docstring)."""

    def __init__(self, watcher: KeyWatcher) -> None:
        self.watcher = watcher

    def collect(self) -> Iterator[Metric]:
        registry = self.watcher.registry
        expiry = GaugeMetricFamily(
            "antireplay_key_expiry_seconds",
            "Seconds until the key's not_after (negative: expired)",
            labels=["kid"],
        )
        now = resolve(registry.clock).wall()  # key periods run on the registry's clock
        for entry in {e.kid: e for e in registry.entries.values()}.values():
            if entry.not_after is not None:
                expiry.add_metric([entry.kid], entry.not_after - now)
        yield expiry
        yield GaugeMetricFamily(
            "antireplay_keys_revoked", "Kids on the revocation list", value=len(registry.revoked)
        )
        yield GaugeMetricFamily(
            "antireplay_revocations_fresh",
            "1 while the revocation list is within its refresh promise, else 0",
            value=0 if registry.stale() else 1,
        )
        reloads = CounterMetricFamily(
            "antireplay_key_reloads", "Keys configuration reloads", labels=["result"]
        )
        for result, count in self.watcher.reloads.items():
            reloads.add_metric([result], count)
        yield reloads
        yield CounterMetricFamily(
            "antireplay_revocations_lost",
            "Times the shared revocation list went backwards and was re-seeded",
            value=self.watcher.lost,
        )


__all__ = ["POLL_S", "PROMISE_S", "KeyMetrics", "KeyWatcher", "change_revocation"]
