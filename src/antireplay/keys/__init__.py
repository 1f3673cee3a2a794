"""Keys kept outside the process: PKCS#11 tokens named by RFC 7512 URIs.

:mod:`.uri` parses a URI (pure); :mod:`.pkcs11` opens the key it names and signs, MACs
or digests through the token (python-pkcs11, the ``pkcs11`` extra, imported only when a
URI is opened).  Wiring and the CLI open keys here; the layers below see only the
objects (``.sign``, ``.mac``, ``.digest``), never the token.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal, overload

from antireplay.core.errors import ConfigError
from antireplay.keys.uri import Pkcs11Uri, is_uri, mask_pins, parse

if TYPE_CHECKING:
    from antireplay.keys.pkcs11 import TokenDigestKey, TokenMac, TokenSigner


@overload
def open_key(text: str, kind: Literal["ed25519"], what: str = ...) -> TokenSigner: ...
@overload
def open_key(text: str, kind: Literal["hmac"], what: str = ...) -> TokenMac: ...
@overload
def open_key(text: str, kind: Literal["digest"], what: str = ...) -> TokenDigestKey: ...
def open_key(text: str, kind: str, what: str = "key") -> TokenSigner | TokenMac | TokenDigestKey:
    """The token key ``text`` names, logged in, as ``kind`` uses it; a
    :class:`~antireplay.core.errors.ConfigError` (one line) if it cannot be used."""
    try:
        from antireplay.keys import pkcs11  # noqa: PLC0415 - python-pkcs11 only when used
    except ImportError as exc:
        shown = mask_pins(text)
        raise ConfigError(what, shown, "a usable PKCS#11 key", message=(
            f"{what} {shown}: python-pkcs11 is not installed ({exc}); "
            "pip install 'antireplay[pkcs11]'"))  from None  # fmt: skip
    if kind == "ed25519":
        return pkcs11.TokenSigner(text, what)
    if kind == "hmac":
        return pkcs11.TokenMac(text, what)
    return pkcs11.TokenDigestKey(text, what)


__all__ = ["Pkcs11Uri", "is_uri", "mask_pins", "open_key", "parse"]
