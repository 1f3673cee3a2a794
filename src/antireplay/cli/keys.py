"""``keygen``, ``sign`` and ``send``: keys, signed envelopes, and sending one to a gateway;
``keys revoke|unrevoke|list|reload``: operator keys at runtime, on the state every gateway
shares (:mod:`antireplay.state.revocations`), each change audited.

Size: one idea, the `keys` commands an operator runs (keygen, sign, send, revoke,
unrevoke, list, reload) over one set of shared options and messages.
"""

from __future__ import annotations

import contextlib
import difflib
import importlib
import json
import os
import secrets
import sys
import time
import uuid
from pathlib import Path
from typing import TYPE_CHECKING, Any
from urllib.parse import urlsplit

import click
import httpx
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ed25519, mldsa, mlkem, x25519
from rich.table import Table

from antireplay.config import AppConfig
from antireplay.config.gateway import kid_problem
from antireplay.core.errors import ConfigError, ReplayAttackError
from antireplay.core.messages import MessageType
from antireplay.rcan.auth import (
    ALGORITHMS,
    SDK_PRIVATE_MAGIC,
    PrivateKey,
    SdkKeyPair,
    SigningKey,
    UnsignedFieldsError,
    sdk_key_id,
    sign_envelope,
    sign_sdk,
    write_key_pair,
)
from antireplay.rcan.envelope import parse, safety_class

if TYPE_CHECKING:
    pass

from antireplay.cli._common import _fail, console, load_with_flags, warn_if_shared
from antireplay.cli._token import KeyOrUri, token_signer

KEY_TYPES: dict[str, Any] = {
    "ed25519": ed25519.Ed25519PrivateKey,
    "ml-dsa-65": mldsa.MLDSA65PrivateKey,
    "ml-dsa-87": mldsa.MLDSA87PrivateKey,
    "ml-kem-1024": mlkem.MLKEM1024PrivateKey,  # a vehicle's key for `mavlink-pq`
    "x25519": x25519.X25519PrivateKey,  # a vehicle's hybrid key for `mavlink-pq`
}


@click.command()
@click.option(
    "--alg",
    type=click.Choice(sorted([*KEY_TYPES, "psk"])),
    default="ed25519",
    show_default=True,
    help="The key's algorithm (ml-kem-1024 and x25519 are vehicle keys for mavlink-pq; psk "
    "is a DDS fleet key, 32 random bytes in hex).",
)
@click.option("--out", required=True, type=click.Path(path_type=Path), help="File prefix.")
def keygen(alg: str, out: Path) -> None:
    """Write PREFIX.key.pem (mode 0600) and PREFIX.pub.pem, or PREFIX.psk (mode 0600)."""
    if alg == "psk":
        secret = out.with_name(out.name + ".psk")
        try:
            fd = os.open(secret, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        except FileExistsError:
            _fail(f"{secret} exists; refusing to overwrite a key")
        with os.fdopen(fd, "w", encoding="ascii") as handle:
            handle.write(secrets.token_hex(32) + "\n")
        console.print(f"[green]fleet key (mode 0600):[/green] {secret}")
        return
    key = KEY_TYPES[alg].generate()
    private = out.with_name(out.name + ".key.pem")
    public = out.with_name(out.name + ".pub.pem")
    try:
        write_key_pair(key, private, public)
    except FileExistsError:
        _fail(f"{private} exists; refusing to overwrite a key")
    console.print(f"[green]{alg} key pair:[/green] {private} {public}")


#: What ``sign --key`` accepts, for its errors.
_SIGNING_KEYS = "an unencrypted PEM private key (Ed25519, ML-DSA-65 or ML-DSA-87)"
_SDK_KEYS = "an unencrypted PEM ML-DSA-65 private key or an RCAN SDK key file (MLDSAKeyPair.save)"
#: The sizes of an ML-DSA-65 key pair (FIPS 204), as the SDK's key file holds them.
_SDK_KEY_SIZES = (1952, 4032)


def _private_key(
    paths: tuple[Path, ...], accepted: str = _SIGNING_KEYS
) -> PrivateKey | tuple[PrivateKey, ...]:
    keys = []
    for path in paths:
        data = path.read_bytes()
        if data.startswith(SDK_PRIVATE_MAGIC) and accepted == _SIGNING_KEYS:
            _fail(f"--key {path}: an RCAN SDK key file; sign with it using --sdk")
        try:
            key = serialization.load_pem_private_key(data, None)
        except (ValueError, TypeError) as exc:
            why = str(exc).split(". See https://", 1)[0]  # not cryptography's FAQ link
            _fail(f"--key {path}: not {accepted} ({why})")
        if not isinstance(key, PrivateKey):
            _fail(f"--key {path}: a {type(key).__name__}; accepted: {accepted}")
        warn_if_shared(path, "--key")
        keys.append(key)
    return keys[0] if len(keys) == 1 else tuple(keys)


@click.command()
@click.option(
    "--key",
    "key_paths",
    multiple=True,
    required=True,
    type=KeyOrUri(),
    help="Private key (PEM, or an Ed25519 key in a token: pkcs11:token=...;object=...); "
    "twice for ed25519+ml-dsa-65, Ed25519 first.",
)
@click.option("--kid", default=None, help="Required, except with --sdk (the key's SDK key id).")
@click.option(
    "--alg",
    type=click.Choice(sorted(ALGORITHMS)),
    default="ed25519",
    show_default=True,
    help="Signature algorithm; must match the --key type(s).",
)
@click.option(
    "--sdk",
    is_flag=True,
    help="Sign as the RCAN SDK's sign_message does (ML-DSA-65; its verify_message accepts it).",
)
@click.option("--json", "json_file", type=click.File("r"), help="Base message (JSON file or -).")
@click.option("--cmd", default=None, help="Command name (ESTOP, STOP and RESUME are safety).")
@click.option("--target", default=None, help="Robot URI the message is for (rcan://…).")
@click.option(
    "--qos",
    type=click.IntRange(0, 2),
    default=None,
    help="Delivery hint: 0 at most once, 1 at least once, 2 exactly once.",
)
@click.option(
    "--param", "params", multiple=True, help="key=value (value parsed as JSON if it can be)"
)
@click.option("--type", "msg_type", type=int, default=None, help="RCAN message type number.")
@click.option(
    "--safety-event", default=None, help="Safety event of a SAFETY message (ESTOP, STOP, RESUME)."
)
@click.option("--scope", default=None, help="Scope the message needs of its key.")
def sign(  # noqa: PLR0917 - one option per envelope field
    key_paths: tuple[Path | str, ...],
    kid: str | None,
    alg: str,
    sdk: bool,
    json_file: Any,
    cmd: str | None,
    target: str | None,
    qos: int | None,
    params: tuple[str, ...],
    msg_type: int | None,
    safety_event: str | None,
    scope: str | None,
) -> None:
    """Build and sign an envelope (fresh msg_id and timestamp unless given); print it."""
    if not sdk and target is not None and not _robot_uri(target):  # --sdk: the SDK's parser
        _fail(f"--target {target}: not a robot URI (rcan://REGISTRY/MANUFACTURER/MODEL/...)")
    try:
        body: Any = json.load(json_file) if json_file is not None else {}
    except ValueError as exc:
        _fail(f"--json {json_file.name}: not JSON ({exc})")
    if not isinstance(body, dict):
        _fail(f"--json {json_file.name}: a JSON object is needed, got {type(body).__name__}")
    body.setdefault("rcan", "3.2")
    body.setdefault("rcan_version", "3.2")
    body.setdefault("msg_id", str(uuid.uuid4()))
    if "timestamp_ms" not in body:
        body.setdefault("timestamp", round(time.time(), 6))
    extra = {"cmd": cmd, "target": target, "type": msg_type, "safety_event": safety_event,
             "qos": qos}  # fmt: skip
    body.update({k: v for k, v in {**extra, "scope": scope}.items() if v is not None})
    for item in params:
        name, _, raw = item.partition("=")
        try:
            value: Any = json.loads(raw)
        except ValueError:
            value = raw
        body.setdefault("params", {})[name] = value
    try:
        if sdk:
            signed = sign_sdk(body, _sdk_key(_files(key_paths), kid))
        elif kid is None:
            _fail("--kid is required (except with --sdk)")
        else:
            signed = sign_envelope(body, kid, alg, _signing_keys(key_paths, alg))
    except (ValueError, ReplayAttackError) as exc:
        hint = ""
        if isinstance(exc, UnsignedFieldsError) and {"type", "safety_event", "scope"} & set(
            exc.fields
        ):
            hint = "; with --sdk, --cmd ESTOP/STOP/RESUME is a safety message"
        _fail(f"cannot sign: {exc}{hint}")
    click.echo(json.dumps(signed))


def _signing_keys(keys: tuple[Path | str, ...], alg: str) -> SigningKey | tuple[SigningKey, ...]:
    """The keys to sign with: files, or one Ed25519 key in a token (a ``pkcs11:`` URI)."""
    uris = [k for k in keys if isinstance(k, str)]
    if not uris:
        return _matching(_private_key(tuple(Path(k) for k in keys)), alg)
    if alg != "ed25519" or len(keys) != 1:
        _fail(f"--key {uris[0]}: a token key signs --alg ed25519 alone (CKM_EDDSA)")
    signer: SigningKey = token_signer(uris[0])
    return signer


def _robot_uri(text: str) -> bool:
    url = urlsplit(text)
    return url.scheme == "rcan" and bool(url.netloc) and not any(c.isspace() for c in text)


def _matching(
    keys: PrivateKey | tuple[PrivateKey, ...], alg: str
) -> PrivateKey | tuple[PrivateKey, ...]:
    """The keys, if they are the ones ``alg`` signs with (in its order); else one line."""
    given = keys if isinstance(keys, tuple) else (keys,)
    wanted = ALGORITHMS[alg]
    names = ", ".join(_KEY_NAMES.get(type(k).__name__, type(k).__name__) for k in given)
    if len(given) != len(wanted) or not all(
        isinstance(k.public_key(), w) for k, w in zip(given, wanted, strict=True)
    ):
        _fail(f"--alg {alg}: the --key given is {names}; give --alg matching the key")
    return keys


#: A private key's class name -> the --alg that signs with it.
_KEY_NAMES = {"Ed25519PrivateKey": "ed25519", "MLDSA65PrivateKey": "ml-dsa-65",
              "MLDSA87PrivateKey": "ml-dsa-87"}  # fmt: skip


def _files(keys: tuple[Path | str, ...]) -> tuple[Path, ...]:
    """``--key`` files (``--sdk`` signs with files only)."""
    if any(isinstance(k, str) for k in keys):
        _fail("--sdk signs with a key file (ML-DSA-65), not a token key")
    return tuple(Path(k) for k in keys)


def _sdk_key(paths: tuple[Path, ...], kid: str | None) -> mldsa.MLDSA65PrivateKey | SdkKeyPair:
    """One ML-DSA-65 key for ``sign --sdk``: a PEM key, or the RCAN SDK's own key file
    (``MLDSAKeyPair.save``; signed with the SDK, which must be installed)."""
    if len(paths) != 1:
        _fail("--sdk signs with exactly one --key (ML-DSA-65)")
    data = paths[0].read_bytes()
    key: mldsa.MLDSA65PrivateKey | SdkKeyPair
    if data.startswith(SDK_PRIVATE_MAGIC):
        size = int.from_bytes(data[4:6], "big")
        if (size, len(data) - 6 - size) != _SDK_KEY_SIZES:
            _fail(f"--key {paths[0]}: a damaged RCAN SDK key file; accepted: {_SDK_KEYS}")
        warn_if_shared(paths[0], "--key")  # a PEM key's is _private_key's
        try:  # the SDK signs its own files with dilithium-py (``rcan[pq]``)
            from rcan.signing import MLDSAKeyPair  # noqa: PLC0415 - only for the SDK's files

            importlib.import_module("dilithium_py.ml_dsa")
        except ImportError as exc:
            _fail(
                f"--key {paths[0]}: an RCAN SDK key file, and the SDK cannot sign with it here "
                f"({exc}); install it: pip install 'rcan[pq]' (or give a PEM ML-DSA-65 key)"
            )
        key = MLDSAKeyPair.load(paths[0])
        key_id = key.key_id
    else:
        pem = _private_key(paths, _SDK_KEYS)
        if not isinstance(pem, mldsa.MLDSA65PrivateKey):
            _fail(
                f"--key {paths[0]}: the RCAN SDK signs with ML-DSA-65 only; accepted: {_SDK_KEYS}"
            )
        key, key_id = pem, sdk_key_id(pem.public_key())
    if kid is not None and kid != key_id:
        _fail(f"--kid {kid}: the SDK signs with the key's SDK key id, {key_id}")
    return key


@click.command()
@click.argument("url")
@click.argument("message", type=click.File("rb"), default="-")
@click.option("--bearer", default=None, help="JWT for the Authorization header.")
@click.option(
    "--json",
    "as_json",
    is_flag=True,
    help="Print one JSON object (status, code, reason, body, sent_as) instead of the table.",
)
def send(url: str, message: Any, bearer: str | None, as_json: bool) -> None:
    """POST a signed envelope to a gateway and print the verdict (exit 1 if refused)."""
    headers = {"content-type": "application/json"}
    if bearer:
        headers["authorization"] = f"Bearer {bearer}"
    if not url.rstrip("/").endswith("/v1/messages"):
        url = url.rstrip("/") + "/v1/messages"
    raw = message.read()
    try:
        reply = httpx.post(url, content=raw, headers=headers, timeout=10)
    except httpx.HTTPError as exc:
        _fail(f"cannot reach {url}: {exc}")
    try:
        body = reply.json()
    except ValueError:
        body = {"body": reply.text[:200]}
    if as_json:
        fields = body if isinstance(body, dict) else {}
        answer = {"status": reply.status_code, "code": fields.get("code"),
                  "reason": fields.get("reason"), "body": body,
                  "sent_as": _sent_as(raw)}  # fmt: skip
        click.echo(json.dumps(answer))
        sys.exit(0 if reply.status_code < 300 else 1)
    table = Table(title=f"{url} answered HTTP {reply.status_code}", caption=_sent_as(raw))
    table.add_column("field")
    table.add_column("value")
    for name, value in body.items():
        table.add_row(str(name), json.dumps(value) if not isinstance(value, str) else value)
    console.print(table)
    sys.exit(0 if reply.status_code < 300 else 1)


def _sent_as(raw: bytes) -> str | None:
    """How the gateway classes what was sent (``cmd ESTOP as SAFETY/ESTOP``): the answer
    does not say, and the class sets the window and the scope a key needs."""
    try:
        env = parse(raw)
    except ReplayAttackError:
        return None  # the gateway's answer says what is wrong with it
    kind, event = safety_class(env)
    try:
        name = MessageType(kind).name
    except ValueError:
        name = str(kind)
    return f"sent cmd {env.cmd} as {name}" + (f"/{event}" if event else "")


@click.group("keys")
def keys_group() -> None:
    """Operator keys at runtime: revoke, unrevoke, reload, list (every gateway on the state)."""


_STATE_OPTIONS = (
    click.option(
        "--config",
        "config_path",
        type=click.Path(path_type=Path),
        default=None,
        help="The gateways' YAML configuration (its store and audit trail).",
    ),
    click.option("--store", default=None, help="The gateways' store spec (over --config's)."),
    click.option(
        "--audit",
        "audit_path",
        default=None,
        help="Audit trail to record the change in (over --config's).",
    ),
    click.option(
        "--state-dir",
        default=Path(".antireplay"),
        show_default=True,
        type=click.Path(path_type=Path),
        help="Without --config or --store: the embedded default's state (as `serve`).",
    ),
)


def _state_options(fn: Any) -> Any:
    for option in reversed(_STATE_OPTIONS):
        fn = option(fn)
    return fn


def _state_config(
    config_path: Path | None, store: str | None, audit_path: str | None, state_dir: Path
) -> AppConfig:
    """The configuration naming the gateways' state (serve's embedded default without one)."""
    if config_path is None and store is None:
        store = f"sqlite:{state_dir / 'state.db'}"
        audit_path = audit_path or str(state_dir / "audit.db")
    return load_with_flags(
        config_path, {"store": ("--store", store), "audit.path": ("--audit", audit_path)}
    )


_FORCE = click.option(
    "--force",
    is_flag=True,
    help="Change a kid --config's keys: does not name (e.g. revoke one before it is deployed).",
)


def _configured(config: AppConfig, kid: str) -> None:
    """Refuse a kid the configuration names no key by (a typo would protect nothing)."""
    from antireplay.wiring.gateway import build_registry  # noqa: PLC0415

    kids = {entry.kid for entry in config.keys}
    with contextlib.suppress(ConfigError):
        kids |= set(build_registry(config).entries)  # and the SDK aliases (sdk_compat)
    if kid in kids:
        return
    near = [k for k in kids if k.casefold() == kid.casefold()]
    near = near or difflib.get_close_matches(kid, sorted(kids), n=1)
    hint = f" (did you mean {near[0]}?)" if near else ""
    _fail(
        f"kid {kid} names no key in the configuration's keys:{hint}; to change it anyway "
        "(e.g. revoke a key before it is deployed) add --force"
    )


def _change(
    config_path: Path | None, config: AppConfig, kid: str, *, revoke: bool, force: bool
) -> None:
    from antireplay.state.revocations import open_revocations  # noqa: PLC0415
    from antireplay.wiring.keys import change_revocation  # noqa: PLC0415

    problem = kid_problem(kid)
    if problem is not None:
        _fail(f"kid {kid!a}: {problem}")
    spec = config.store_spec.redacted()
    if config.store_spec.backend == "memory":
        _fail("store memory: a revocation list in this process reaches no gateway; "
              "name the gateways' sqlite: or redis:// store")  # fmt: skip
    if config_path is not None and not force:
        _configured(config, kid)
    verb = "revoked" if revoke else "unrevoked"
    try:
        changed = change_revocation(config, kid, revoke=revoke)
    except (ReplayAttackError, ConfigError, OSError) as exc:
        with contextlib.suppress(ReplayAttackError, OSError):
            revocations = open_revocations(config.store_spec)
            try:
                applied = (kid in revocations.revoked()) == revoke
            finally:
                revocations.close()
            if applied:  # the list changed; only the audit row did not
                click.echo(f"antireplay: {verb} {kid} on {spec}; its audit row could not be "
                           f"written to {config.audit}: {exc}", err=True)  # fmt: skip
                sys.exit(1)
        _fail(f"store {spec}: {kid} not {verb}: {exc}")
    already = "" if changed else f" (it already was {'' if revoke else 'not '}revoked)"
    click.echo(
        f"{verb} {kid}{already}: every gateway on {spec} applies it within 1 s; "
        f"audited in {config.audit}"
    )


@keys_group.command("revoke")
@click.argument("kid")
@_state_options
@_FORCE
def keys_revoke(  # noqa: PLR0917 - the state options
    kid: str,
    config_path: Path | None,
    store: str | None,
    audit_path: str | None,
    state_dir: Path,
    force: bool,
) -> None:
    """Put KID on the shared revocation list: its key is refused (401 KEY_REVOKED) under
    every kid that names it."""
    config = _state_config(config_path, store, audit_path, state_dir)
    _change(config_path, config, kid, revoke=True, force=force)


@keys_group.command("unrevoke")
@click.argument("kid")
@_state_options
@_FORCE
def keys_unrevoke(  # noqa: PLR0917 - the state options
    kid: str,
    config_path: Path | None,
    store: str | None,
    audit_path: str | None,
    state_dir: Path,
    force: bool,
) -> None:
    """Take KID off the shared revocation list."""
    config = _state_config(config_path, store, audit_path, state_dir)
    _change(config_path, config, kid, revoke=False, force=force)


@keys_group.command("list")
@_state_options
def keys_list(
    config_path: Path | None, store: str | None, audit_path: str | None, state_dir: Path
) -> None:
    """Print the revoked kids, one a line."""
    from antireplay.state.revocations import open_revocations  # noqa: PLC0415

    config = _state_config(config_path, store, audit_path, state_dir)
    try:
        revocations = open_revocations(config.store_spec)
        try:
            kids = sorted(revocations.revoked())
        finally:
            revocations.close()
    except ReplayAttackError as exc:
        _fail(f"store {config.store_spec.redacted()}: {exc}")
    for kid in kids:
        click.echo(kid)


@keys_group.command("reload")
@_state_options
def keys_reload(
    config_path: Path | None, store: str | None, audit_path: str | None, state_dir: Path
) -> None:
    """Ask every gateway on the state to re-read its keys configuration (within 0.25 s)."""
    from antireplay.state.revocations import open_revocations  # noqa: PLC0415

    config = _state_config(config_path, store, audit_path, state_dir)
    try:
        revocations = open_revocations(config.store_spec)
        try:
            revocations.request_reload()
        finally:
            revocations.close()
    except ReplayAttackError as exc:
        _fail(f"store {config.store_spec.redacted()}: {exc}")
    click.echo(f"reload asked of every gateway on {config.store_spec.redacted()}")
