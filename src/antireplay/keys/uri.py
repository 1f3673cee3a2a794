"""RFC 7512 PKCS#11 URIs, parsed: which module, which token, which object, which PIN.

Theory of operation
-------------------
``pkcs11:token=ops;object=audit-mac?pin-source=file:/run/pin`` names a key by its
token's label and its object's label (``id=`` by its CKA_ID, percent-encoded bytes);
``type=`` narrows the object class (``private``, ``secret-key``...).  The query may name
the module (``module-path=/usr/lib/softhsm/libsofthsm2.so``) and the PIN: ``pin-value=``
inline (RFC 7512 section 2.3) or ``pin-source=`` (a file, ``file:`` or a path); without
either the driver reads ``$ANTIREPLAY_PKCS11_PIN``.  Parsing is pure: values in, a
:class:`Pkcs11Uri` or a one-line :class:`ValueError` out (never the PIN in a message:
:meth:`Pkcs11Uri.redacted`; :func:`mask_pins` for raw text).  Unknown attributes refuse
(RFC 7512 lets a consumer ignore them, but a typo in ``objet=`` must not select "any object").
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from urllib.parse import unquote_to_bytes

SCHEME = "pkcs11:"
#: Path attributes (RFC 7512 section 2.3) this driver selects by.
PATH_ATTRS = frozenset({"token", "object", "id", "type", "manufacturer", "model", "serial",
                        "library-manufacturer", "library-description", "library-version",
                        "slot-id", "slot-description", "slot-manufacturer"})  # fmt: skip
QUERY_ATTRS = frozenset({"pin-value", "pin-source", "module-path"})
TYPES = frozenset({"public", "private", "cert", "secret-key", "data"})


@dataclass(frozen=True)
class Pkcs11Uri:
    """One parsed URI: its path attributes (decoded text; ``id`` as bytes) and query."""

    token: str | None = None
    object: str | None = None
    id: bytes | None = None
    type: str | None = None
    serial: str | None = None
    module_path: str | None = None
    pin_value: str | None = None
    pin_source: str | None = None

    def redacted(self) -> str:
        """The URI for messages and logs: the PIN value replaced."""
        parts = [f"token={self.token}" if self.token else "",
                 f"object={self.object}" if self.object else "",
                 f"id={self.id.hex()}" if self.id else "",
                 f"type={self.type}" if self.type else ""]  # fmt: skip
        query = [f"module-path={self.module_path}" if self.module_path else "",
                 "pin-value=***" if self.pin_value else "",
                 f"pin-source={self.pin_source}" if self.pin_source else ""]  # fmt: skip
        text = SCHEME + ";".join(p for p in parts if p)
        tail = "&".join(q for q in query if q)
        return text + (f"?{tail}" if tail else "")


_PIN = re.compile(r"(pin-value\s*(?:=|%3d))[^;&?\s'\"]*", re.IGNORECASE)


def mask_pins(text: str) -> str:
    """``text`` with every ``pin-value=`` value replaced by ``***``, wherever it stands (path
    or query, a malformed URI, a whole error message): the one mask every message uses."""
    return _PIN.sub(r"\1***", text)


def is_uri(text: object) -> bool:
    """Whether a configured key names a token (``pkcs11:``) rather than a file."""
    return isinstance(text, str) and text.startswith(SCHEME)


def _decode(name: str, raw: str) -> bytes:
    if any(c in raw for c in " \t\r\n"):
        raise ValueError(f"pkcs11 URI: {name} has whitespace (percent-encode it)")
    try:
        return unquote_to_bytes(raw)
    except ValueError as exc:  # pragma: no cover - unquote_to_bytes keeps bad escapes
        raise ValueError(f"pkcs11 URI: {name} is not percent-encoded ({exc})") from None


def _text(name: str, raw: str) -> str:
    try:
        return _decode(name, raw).decode("utf-8")
    except UnicodeDecodeError:
        raise ValueError(f"pkcs11 URI: {name} is not UTF-8 text") from None


def parse(text: str) -> Pkcs11Uri:
    """``text`` as a :class:`Pkcs11Uri`; one line naming what is wrong otherwise."""
    if not is_uri(text):
        raise ValueError("not a pkcs11 URI (pkcs11:token=...;object=...)")
    path, _, query = text[len(SCHEME) :].partition("?")
    found: dict[str, str] = {}
    ident: bytes | None = None
    for part, sep, allowed in ((path, ";", PATH_ATTRS), (query, "&", QUERY_ATTRS)):
        for item in filter(None, part.split(sep)):
            name, eq, raw = item.partition("=")
            if not eq:
                raise ValueError(f"pkcs11 URI: {name!r} has no value (name=value)")
            if name not in allowed:
                where = "path" if sep == ";" else "query"
                raise ValueError(
                    f"pkcs11 URI: unknown {where} attribute {name!r} "
                    f"(known: {', '.join(sorted(allowed))})"
                )
            if name in found:
                raise ValueError(f"pkcs11 URI: {name} given twice")
            if name == "id":
                ident = _decode(name, raw)
                found[name] = ""
            else:
                found[name] = _text(name, raw)
    kind = found.get("type")
    if kind is not None and kind not in TYPES:
        raise ValueError(f"pkcs11 URI: type={kind} (allowed: {', '.join(sorted(TYPES))})")
    if "pin-value" in found and "pin-source" in found:
        raise ValueError("pkcs11 URI: pin-value and pin-source both given (one PIN)")
    if "token" not in found and "serial" not in found:
        raise ValueError("pkcs11 URI: names no token (token=LABEL or serial=...)")
    if "object" not in found and ident is None:
        raise ValueError("pkcs11 URI: names no object (object=LABEL or id=%XX...)")
    return Pkcs11Uri(
        token=found.get("token"), object=found.get("object"), id=ident, type=kind,
        serial=found.get("serial"), module_path=found.get("module-path"),
        pin_value=found.get("pin-value"), pin_source=found.get("pin-source"),
    )  # fmt: skip
