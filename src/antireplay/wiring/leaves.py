"""The leaves every command is built on: its replay store, the store's anchor, its audit trail.

Theory of operation
-------------------
Every long-running command (``serve``, ``mavlink-router``, ``mavlink-pq``, the ``dds``
commands) opens its leaves here, from one :class:`~antireplay.config.AppConfig`, so what
the file says about them holds for each alike:

* :func:`open_trail` opens the audit trail at ``audit.path`` (or a command's own path:
  :func:`trail_path`, so two commands never share one trail unasked),
  rotated and retained as ``audit:`` says (:func:`open_audit`), with its ESTOP spill
  (``audit_space.spill``) and the free-space floors under it (``audit_space``, a
  :class:`~antireplay.audit.space.DiskSpace` the command's refusal auditor goes quiet by),
  its head key a file or a key in a PKCS#11 token (``audit.head_key``, :mod:`antireplay.keys`);
* :func:`open_state` opens a store from its parsed spec (:class:`~antireplay.state.StoreSpec`)
  with its anchor outside its directory when ``state.anchor`` names one
  (:func:`build_anchor`); :func:`anchor_summary` and :func:`anchor_warnings` say, for the
  start line and ``config check``, what a snapshot restore would re-open without it.

Only built objects leave this module: a store, an anchor, a trail, a disk watcher.
"""

from __future__ import annotations

from pathlib import Path

from antireplay.audit import AuditLog, Retention
from antireplay.audit.chain import MacKey
from antireplay.audit.space import DiskSpace
from antireplay.config import AppConfig, AuditConfig
from antireplay.core.clock import Clock
from antireplay.core.errors import ConfigError
from antireplay.keys import is_uri, open_key
from antireplay.state import ReplayStore, StoreSpec, open_store
from antireplay.state.anchor import StateAnchor, check_anchor_path


def open_trail(
    config: AppConfig, path: str | None = None, clock: Clock | None = None
) -> tuple[AuditLog, DiskSpace]:
    """The audit trail the ``audit:`` block describes, at ``path`` if given (a command's
    flag or default; else ``audit.path``), with its spill and its free-space floors."""
    block = config.audit if path is None else config.audit.at(path)
    floors = config.audit_space
    space = DiskSpace(
        block.path, min_free_bytes=floors.min_free_bytes,
        refuse_free_bytes=floors.refuse_free_bytes, clock=clock,
    )  # fmt: skip
    return open_audit(block, clock, spill=floors.spill), space


def trail_path(config: AppConfig, default: str) -> str:
    """A command's audit trail: ``audit.path`` when the file (or ``--audit``) names it,
    else the command's own ``default``, so two commands never share one trail unasked."""
    return config.audit.path if config.audit.path_set() else default


def open_state(
    config: AppConfig,
    spec: StoreSpec,
    *,
    audit_path: str,
    clock: Clock | None = None,
    max_entries: int = 10_000,
    skew_s: float = 5.0,
) -> ReplayStore:
    """The store ``spec`` names, anchored as ``state.anchor`` says (a SQLite store only)."""
    return open_store(
        spec, clock=clock, max_entries=max_entries, skew_s=skew_s,
        anchor=build_anchor(config, spec, audit_path),
    )  # fmt: skip


def check_state(spec: StoreSpec) -> None:
    """What a command's first commit would find, found without using anything up: a SQLite
    file is read read-only (opening it would use up its loss detection); another store is
    reached (the PING and eviction check ``ready()`` runs), then closed."""
    if spec.backend == "sqlite":
        from antireplay.state.sqlite import check_readable  # noqa: PLC0415

        check_readable(spec.target)
        return
    store = open_store(spec)
    try:
        store.ready()
    finally:
        store.close()


def build_anchor(
    config: AppConfig, spec: StoreSpec | None = None, audit_path: str | None = None
) -> StateAnchor | None:
    """The SQLite store's anchor outside its directory (``state.anchor``), if configured;
    ``spec`` is the store it anchors (default: the gateway's ``store``), ``audit_path`` the
    trail beside it (default: ``audit.path``)."""
    anchor = config.state.anchor
    if not anchor.configured:
        return None
    spec = spec or config.store_spec
    if spec.backend != "sqlite":
        raise ConfigError(
            "state.anchor", anchor.model_dump(exclude_defaults=True),
            f"only with a sqlite store (store {spec.redacted()} has no directory to restore)",
        )  # fmt: skip
    db = Path(spec.target)
    if anchor.path is not None:  # never a file it would damage, nor one a snapshot restores
        check_anchor_path(Path(anchor.path), {
            "state database": db, "state witness": db.with_name(f".{db.name}.witness"),
            "audit trail": Path(audit_path or config.audit.path),
        })  # fmt: skip
    return StateAnchor(
        db,
        path=anchor.path,
        redis_url=anchor.redis,
        every_s=anchor.every_ms / 1000,
    )


def anchor_summary(config: AppConfig, spec: StoreSpec | None = None) -> str:
    """What guards the store (``spec``; default the gateway's) against a restored copy, for
    the startup line."""
    anchor = config.state.anchor
    if (spec or config.store_spec).backend != "sqlite":
        return ""
    if not anchor.configured:
        return "no state anchor, "
    places = [
        p for p in (anchor.path, anchor.redis and StoreSpec.parse(anchor.redis).redacted()) if p
    ]
    lazy = f" every {anchor.every_ms} ms" if anchor.every_ms else ""
    return f"anchor {' + '.join(places)}{lazy}, "


def anchor_warnings(config: AppConfig, spec: StoreSpec | None = None) -> list[str]:
    """What a snapshot restore could re-open with this configuration (``config check``,
    ``serve``): a SQLite store (``spec``; default the gateway's) without an anchor, or an
    anchor file beside the state."""
    spec = spec or config.store_spec
    if spec.backend != "sqlite":
        return []
    anchor, window = config.state.anchor, config.security.replay_window_s
    if not anchor.configured:
        return [
            f"store {spec.text} has no state anchor (state.anchor): restoring a snapshot "
            f"or backup of its directory within replay_window_s ({window:g} s) of a command "
            "re-opens that command's replay (deleting or restoring the database alone is "
            "detected)"
        ]
    if anchor.path is not None and _same_volume(Path(anchor.path), Path(spec.target)):
        return [
            f"state.anchor.path {anchor.path} is on the same filesystem as {spec.target}: "
            "a snapshot of that volume restores both, which the anchor cannot notice"
        ]
    return []


def _same_volume(one: Path, other: Path) -> bool:
    """Both paths' nearest existing directories are on one filesystem."""

    def device(path: Path) -> int:
        for parent in (path.absolute(), *path.absolute().parents):
            if parent.exists():
                return parent.stat().st_dev
        return -1

    return device(one) == device(other)


def check_head_key(config: AppConfig) -> bool:
    """``config check``: log in to the token holding ``audit.head_key`` and find the key
    (a ``ConfigError`` if it cannot be used), then log out; ``False`` for a key file."""
    if not is_uri(config.audit.head_key):
        return False
    open_key(str(config.audit.head_key), "hmac", "audit.head_key").close()
    return True


def open_audit(
    config: AuditConfig, clock: Clock | None = None, *, spill: str | None = None
) -> AuditLog:
    """The audit trail at ``audit.path``, rotated and retained as ``audit:`` says, with its
    ESTOP spill file (``audit_space.spill``, beside the trail by default) and its head key
    (``audit.head_key``: a file, or a key in a token, opened here: a ``ConfigError`` if not)."""
    retention = Retention(
        segment_bytes=config.segment_bytes,
        segment_age_s=config.segment_age_s,
        max_bytes=config.max_bytes,
        max_age_s=config.max_age_s,
    )
    head_key: str | MacKey | None = config.head_key
    if is_uri(head_key):
        head_key = open_key(str(head_key), "hmac", "audit.head_key")
    return AuditLog(
        config.path, head_key=head_key, clock=clock, retention=retention, spill_path=spill
    )
