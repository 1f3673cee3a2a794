"""``--key`` and ``--head-key`` values that name a key in a PKCS#11 token (``pkcs11:...``,
RFC 7512) rather than a file: the parameter type, and opening the key as one line and
exit 2 on failure."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from antireplay.cli._common import _fail
from antireplay.core.errors import ConfigError
from antireplay.keys import is_uri, mask_pins, open_key

if TYPE_CHECKING:
    from antireplay.keys.pkcs11 import TokenMac, TokenSigner


class KeyOrUri(click.ParamType):  # type: ignore[type-arg]
    """A key file (a :class:`~pathlib.Path`; ``exists``: it must), or a ``pkcs11:`` URI
    (kept as text, opened by the command: its errors are one line, not a usage error)."""

    name = "FILE|pkcs11:URI"

    def __init__(self, *, exists: bool = True) -> None:
        self.exists = exists

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        if is_uri(value):
            return str(value)
        kind = click.Path(exists=self.exists, dir_okay=False, path_type=Path)
        try:
            return kind.convert(value, param, ctx)
        except click.BadParameter as exc:  # a mistyped URI (PKCS11:...) may carry a PIN
            self.fail(mask_pins(exc.message), param, ctx)


def head_key(value: Path | str | None, what: str = "--head-key") -> Path | TokenMac | None:
    """``--head-key``: a key file, or the audit head key in a token, logged in."""
    if not isinstance(value, str):
        return value
    try:
        return open_key(value, "hmac", what)
    except ConfigError as exc:
        _fail(str(exc))


def token_signer(uri: str, what: str = "--key") -> TokenSigner:
    """The Ed25519 key ``uri`` names, logged in; one line and exit 2 if it cannot be used."""
    try:
        return open_key(uri, "ed25519", what)
    except ConfigError as exc:
        _fail(str(exc))
