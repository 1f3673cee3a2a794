"""``--key`` values that name a key in a PKCS#11 token (``pkcs11:...``, RFC 7512) rather
than a file: the parameter type, and opening the key as one line and exit 2 on failure."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from antireplay.cli._common import _fail
from antireplay.core.errors import ConfigError
from antireplay.keys import is_uri, open_key

if TYPE_CHECKING:
    from antireplay.keys.pkcs11 import TokenSigner


class KeyOrUri(click.ParamType):
    """An existing key file (a :class:`~pathlib.Path`), or a ``pkcs11:`` URI (kept as text)."""

    name = "FILE|pkcs11:URI"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        if is_uri(value):
            return str(value)
        kind = click.Path(exists=True, dir_okay=False, path_type=Path)
        return kind.convert(value, param, ctx)


def token_signer(uri: str, what: str = "--key") -> TokenSigner:
    """The Ed25519 key ``uri`` names, logged in; one line and exit 2 if it cannot be used."""
    try:
        return open_key(uri, "ed25519", what)
    except ConfigError as exc:
        _fail(str(exc))
