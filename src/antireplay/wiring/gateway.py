"""The gateway, wired: a configuration in, a receiver, an application or a guard out.

Theory of operation
-------------------
:func:`build_receiver` builds the gateway's :class:`~antireplay.rcan.receive.Receiver`
from :class:`~antireplay.config.AppConfig`, leaves first: the key registry
(:func:`build_registry`), the JWT verifier when configured, the store (bounded and skewed
as ``security`` says, anchored as ``state.anchor`` says: :func:`~.leaves.open_state`)
checked for data loss at boot (``verify()``: a store that is down now is noticed on the
first commit instead), and the audit trail with its floors (:func:`~.leaves.open_trail`,
the one every command opens its trail through).  :func:`create_app` hands the receiver,
the resolved upstream and its time budget to :func:`~antireplay.http.app.gateway_app`;
The app's keys are watched (:func:`watch_keys`: the shared revocation list, reloads).
:class:`Guard` and :class:`RcanGuard` are the guard middleware and dependency on a
receiver built from a configuration (without one, :func:`embedded_default`: SQLite under
``./.antireplay/`` and a demo key pair).
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable
from pathlib import Path

from cryptography.hazmat.primitives.asymmetric import ed25519
from starlette.applications import Starlette
from starlette.types import ASGIApp

from antireplay.config import AppConfig, AuditConfig, KeyConfig
from antireplay.core.clock import Clock
from antireplay.core.errors import ConfigError, StateUnavailableError
from antireplay.http.app import gateway_app
from antireplay.http.dependency import GuardDependency
from antireplay.http.metrics import Metrics
from antireplay.http.middleware import GuardMiddleware
from antireplay.http.upstream import resolve_upstream
from antireplay.rcan.auth import (
    JwtVerifier,
    KeyRegistry,
    load_public_key,
    sdk_key_id,
    write_key_pair,
)
from antireplay.rcan.receive import Receiver
from antireplay.state.revocations import open_revocations
from antireplay.state.sqlite import SqliteStore
from antireplay.wiring.keys import KeyMetrics, KeyWatcher
from antireplay.wiring.leaves import open_state, open_trail

DEMO_KID = "demo-operator"
#: How much longer than the upstream budget a QoS retry waits for its original's answer.
ANSWER_SLACK_S = 1.0
#: Audit records and log lines per second for refused MAVLink frames (the rest are counted).


def build_registry(config: AppConfig, clock: Clock | None = None) -> KeyRegistry:
    """The sender keys the configuration names, loaded by the one loader
    (:func:`~antireplay.rcan.auth.load_public_key`: PEM or the RCAN SDK's raw key file; a bad
    key file is a ConfigError), for ``config check`` and ``serve`` alike.  With
    ``sdk_compat``, an ML-DSA-65 key also answers to its SDK key id
    (:func:`~antireplay.rcan.auth.sdk_key_id`), the kid the SDK always signs with.  Each
    key keeps its validity period (``not_before`` / ``not_after``, read on ``clock``)."""
    keys = KeyRegistry(sdk_compat=config.sdk_compat, clock=clock)
    added = []
    for entry in config.keys:
        if entry.kid in keys.entries:
            raise ConfigError(f"keys.{entry.kid}.kid", entry.kid, "a kid no other key uses")
        try:
            loaded = tuple(load_public_key(Path(p).read_bytes()) for p in entry.public_keys)
            period = {
                "not_before": KeyConfig.seconds(entry.not_before),
                "not_after": KeyConfig.seconds(entry.not_after),
            }
            added.append(
                keys.add(entry.kid, entry.owner, entry.alg, loaded, set(entry.scopes), **period)
            )
        except FileNotFoundError as exc:
            raise ConfigError.file_not_found(
                f"keys.{entry.kid}.public_keys", exc.filename
            ) from None
        except (OSError, ValueError) as exc:
            raise ConfigError(
                f"keys.{entry.kid}.public_keys", entry.public_keys, str(exc)
            ) from None
    for key in added if config.sdk_compat else ():
        if key.alg == "ml-dsa-65":
            try:
                keys.alias(sdk_key_id(key.public_keys[0]), key)
            except ValueError as exc:
                allowed = f"a key whose SDK key id no other key uses as its kid ({exc})"
                raise ConfigError(f"keys.{key.kid}.kid", key.kid, allowed) from None
    return keys


def check_gateway(config: AppConfig) -> None:
    """What ``serve`` loads before it opens anything, loaded and dropped (``config check``,
    ``serve``'s preflight): the key registry, the JWT keys, the upstream; ConfigError."""
    build_registry(config)
    for kid, pem in config.jwt.keys.items():
        try:
            load_public_key(Path(pem).read_bytes())
        except FileNotFoundError:
            raise ConfigError.file_not_found(f"jwt.keys.{kid}", pem) from None
        except (OSError, ValueError) as exc:
            allowed = f"a readable PEM public key ({exc})"
            raise ConfigError(f"jwt.keys.{kid}", pem, allowed) from None
    resolve_upstream(config.upstream, config.upstream_timeout_s)


def build_receiver(config: AppConfig, clock: Clock | None = None) -> Receiver:
    """Wire a Receiver from configuration: keys, store, audit, JWT."""
    verifier = None
    if config.jwt.keys or config.jwt.hs256_secret_env:
        secret = os.environ.get(config.jwt.hs256_secret_env or "", "") or None
        verifier = JwtVerifier(
            {kid: load_public_key(Path(p).read_bytes()) for kid, p in config.jwt.keys.items()},
            audience=config.jwt.audience,
            issuer=config.jwt.issuer,
            hs256_secret=secret.encode() if secret else None,
            leeway_s=config.jwt.leeway_s,
            clock=clock,
        )
    store = open_state(
        config, config.store_spec, audit_path=config.audit.path, clock=clock,
        max_entries=config.security.msg_id_cache_size, skew_s=config.security.skew_s,
    )  # fmt: skip
    with contextlib.suppress(StateUnavailableError):  # down now: noticed on the first commit
        store.verify()  # loss detection at boot, not on the first command
    audit, space = open_trail(config, clock=clock)
    if isinstance(store, SqliteStore):  # one fsync per batch: audit rows in the state's commits
        audit.attach(store.outbox())
    return Receiver(
        config.security,
        build_registry(config, clock),
        store,
        audit,
        clock,
        space=space,
        jwt=verifier,
        jwt_required=config.jwt.required,
        versions=frozenset(config.versions),
        max_bytes=config.max_body_bytes,
    )


def embedded_default(state_dir: Path = Path(".antireplay")) -> AppConfig:
    """SQLite state and audit under ``state_dir`` and a demo Ed25519 key pair (made once)."""
    state_dir.mkdir(parents=True, exist_ok=True)
    private, public = state_dir / f"{DEMO_KID}.key.pem", state_dir / f"{DEMO_KID}.pub.pem"
    if not private.exists():
        write_key_pair(ed25519.Ed25519PrivateKey.generate(), private, public)
    return AppConfig(
        store=f"sqlite:{state_dir / 'state.db'}",
        audit=AuditConfig(path=str(state_dir / "audit.db")),
        keys=[
            KeyConfig(
                kid=DEMO_KID,
                owner="operator",
                alg="ed25519",
                public_keys=[str(public)],
                scopes=["control", "safety"],
            )
        ],
    )


def create_app(
    config: AppConfig,
    *,
    clock: Clock | None = None,
    reload: Callable[[], AppConfig] | None = None,
) -> Starlette:
    """The gateway application for ``config`` (:func:`~antireplay.http.app.gateway_app`),
    its keys watched (:func:`watch_keys`; ``reload`` re-reads the configuration)."""
    receiver = build_receiver(config, clock)
    # A retry waits for its original while that is still within its upstream budget.
    receiver.answer_wait_s = config.upstream_timeout_s + ANSWER_SLACK_S
    upstream = resolve_upstream(config.upstream, config.upstream_timeout_s)
    app = gateway_app(receiver, upstream, config.upstream_timeout_s)
    app.state.keys = watch_keys(config, receiver, reload, clock)
    if app.state.keys is not None:
        app.state.metrics.registry.register(KeyMetrics(app.state.keys))
    return app


def watch_keys(
    config: AppConfig,
    receiver: Receiver,
    reload: Callable[[], AppConfig] | None = None,
    clock: Clock | None = None,
) -> KeyWatcher | None:
    """The running watcher of ``receiver``'s keys (:mod:`.keys`): the revocation list of
    the state ``config`` names and, with ``reload``, key reloads.  ``None`` for a memory
    store without ``reload`` (no other process can reach its list)."""
    if config.store_spec.backend == "memory" and reload is None:
        return None
    try:
        revocations = open_revocations(config.store_spec)
    except StateUnavailableError as exc:
        raise ConfigError("store", config.store_spec.redacted(), exc.reason) from None

    def load() -> KeyRegistry:
        assert reload is not None
        return build_registry(reload(), clock)

    watcher = KeyWatcher(
        receiver.keys, revocations, load=None if reload is None else load, audit=receiver.audit
    )
    return watcher.start()


def _guard_receiver(
    config: AppConfig | None, clock: Clock | None, receiver: Receiver | None
) -> tuple[Receiver, bool]:
    """``receiver``, or one built from ``config`` (the embedded default without one) that
    the guard then owns (its ``close`` closes the audit trail)."""
    if receiver is not None:
        return receiver, False
    return build_receiver(config if config is not None else embedded_default(), clock), True


class Guard(GuardMiddleware):
    """:class:`~antireplay.http.middleware.GuardMiddleware` on ``receiver``, or on one built
    from ``config`` (the embedded default without one; ``clock`` drives it)."""

    def __init__(
        self,
        app: ASGIApp,
        config: AppConfig | None = None,
        *,
        paths: tuple[str, ...] = ("/v1/messages",),
        clock: Clock | None = None,
        receiver: Receiver | None = None,
        metrics: Metrics | None = None,
        accepted: ASGIApp | None = None,
    ) -> None:
        built, owned = _guard_receiver(config, clock, receiver)
        super().__init__(
            app, built, paths=paths, metrics=metrics, accepted=accepted, owns_receiver=owned
        )


class RcanGuard(GuardDependency):
    """:class:`~antireplay.http.dependency.GuardDependency` on ``receiver``, or on one built
    from ``config`` (the embedded default without one; ``clock`` drives it)."""

    def __init__(
        self,
        config: AppConfig | None = None,
        *,
        clock: Clock | None = None,
        receiver: Receiver | None = None,
    ) -> None:
        built, owned = _guard_receiver(config, clock, receiver)
        super().__init__(built, owns_receiver=owned)
