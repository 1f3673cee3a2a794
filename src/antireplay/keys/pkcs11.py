"""Keys in a PKCS#11 token (python-pkcs11): sign, MAC and digest without the key in memory.

Theory of operation
-------------------
:func:`antireplay.keys.open_key` turns an RFC 7512 URI (:mod:`.uri`) into one of three
key objects, each holding one logged-in session on its token for the life of the process:

* :class:`TokenSigner` signs with an Ed25519 private key (``CKM_EDDSA``), for ``sign``;
* :class:`TokenMac` computes HMAC-SHA256 with a generic secret key (``CKM_SHA256_HMAC``):
  the audit head key, a DDS fleet key (``.mac(data) -> bytes``);
* :class:`TokenDigestKey` computes ``SHA-256(key || data)`` inside the token
  (``C_DigestInit``, ``C_DigestKey``, ``C_DigestUpdate``): a MAVLink v2 signature.

Everything that can be wrong at start (module not found, no such token, no PIN, a wrong
or locked PIN, no such object, an object of another kind) is one :class:`TokenError`, a
:class:`~antireplay.core.errors.ConfigError`: one line and exit 2 from every command.
A token that fails later (removed, session closed) raises :class:`TokenUnavailableError`,
an ``OSError``, so a caller's existing I/O failure path answers (the audit writer's ESTOP
spill, ``STATE_UNAVAILABLE``).  A session is not safe for two threads at once: each
operation holds the key's lock.  The PIN comes from the URI (``pin-value``,
``pin-source``) or ``$ANTIREPLAY_PKCS11_PIN``; the module from ``module-path``,
``$ANTIREPLAY_PKCS11_MODULE`` or SoftHSMv2's Debian path.
"""

from __future__ import annotations

import contextlib
import os
import stat
import sys
import threading
from pathlib import Path
from typing import Any

import pkcs11
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey
from pkcs11 import Attribute, KeyType, Mechanism, ObjectClass
from pkcs11 import exceptions as p11

from antireplay.core.errors import ConfigError
from antireplay.keys.uri import Pkcs11Uri, mask_pins, parse

PIN_ENV = "ANTIREPLAY_PKCS11_PIN"
MODULE_ENV = "ANTIREPLAY_PKCS11_MODULE"
#: Where Debian's softhsm2 (libsofthsm2) puts its module.
DEFAULT_MODULE = "/usr/lib/softhsm/libsofthsm2.so"
#: ``type=`` in a URI (RFC 7512) as the object class it names.
_CLASSES = {"public": ObjectClass.PUBLIC_KEY, "private": ObjectClass.PRIVATE_KEY,
            "secret-key": ObjectClass.SECRET_KEY, "cert": ObjectClass.CERTIFICATE,
            "data": ObjectClass.DATA}  # fmt: skip
_LOCKED = (p11.PinIncorrect, p11.PinLocked, p11.PinExpired, p11.PinInvalid, p11.PinLenRange)


class TokenError(ConfigError):
    """A token key that cannot be used at start: one line naming the URI (PIN redacted)."""

    def __init__(self, what: str, uri: str, problem: str) -> None:
        uri = mask_pins(uri)
        message = f"{what} {uri}: {mask_pins(problem)}"
        super().__init__(what, uri, "a usable PKCS#11 key", message=message)


class TokenUnavailableError(OSError):
    """The token failed while serving (removed, session closed, device error)."""


def module_path(uri: Pkcs11Uri) -> str:
    """The PKCS#11 module: the URI's ``module-path``, else the environment, else SoftHSMv2."""
    return uri.module_path or os.environ.get(MODULE_ENV) or DEFAULT_MODULE


def _warn_if_shared(path: Path) -> None:
    """The PIN file is a secret like a key file: one warning if group or others may read it."""
    with contextlib.suppress(OSError):  # unreadable: the read below names why
        mode = path.stat().st_mode
        if mode & (stat.S_IRWXG | stat.S_IRWXO):
            print(f"antireplay: warning: pin-source {path} is open to group or others (mode "
                  f"{stat.S_IMODE(mode):04o}); keep a secret mode 0600: chmod 600 {path}",
                  file=sys.stderr)  # fmt: skip


def _pin(uri: Pkcs11Uri, what: str) -> str:
    if uri.pin_value is not None:
        return uri.pin_value
    if uri.pin_source is not None:
        path = Path(uri.pin_source.removeprefix("file:"))
        _warn_if_shared(path)
        try:
            return path.read_text(encoding="utf-8").strip()
        except (OSError, UnicodeDecodeError) as exc:
            reason = exc.strerror if isinstance(exc, OSError) else "not UTF-8 text"
            raise TokenError(what, uri.redacted(), f"pin-source {path}: {reason}") from None
    pin = os.environ.get(PIN_ENV)
    if pin is None:
        raise TokenError(
            what, uri.redacted(), f"no PIN (pin-source=FILE in the URI, or ${PIN_ENV})"
        )
    return pin


class _TokenKey:
    """One key object in one logged-in session; operations serialized by a lock."""

    _class: ObjectClass
    _key_type: KeyType
    _noun: str
    #: Whether the key is used through C_Sign (a signature or an HMAC).
    _signs = True

    def __init__(self, text: str, what: str = "key") -> None:
        try:
            uri = parse(text)
        except ValueError as exc:
            raise TokenError(what, text, str(exc)) from None
        self.uri, self._lock = uri.redacted(), threading.Lock()
        if uri.type is not None and _CLASSES[uri.type] != self._class:
            raise TokenError(what, self.uri, f"type={uri.type} names no {self._noun}")
        module = module_path(uri)
        try:
            lib = pkcs11.lib(module)
        except p11.PKCS11Error:
            raise TokenError(
                what, self.uri, f"PKCS#11 module {module} not found or not loadable "
                f"(module-path= in the URI or ${MODULE_ENV}; Debian: apt-get install softhsm2)",
            ) from None  # fmt: skip
        try:
            token = lib.get_token(token_label=uri.token, token_serial=uri.serial)
        except p11.NoSuchToken:
            raise TokenError(what, self.uri, "no such token in the module") from None
        except p11.MultipleTokensReturned:
            raise TokenError(what, self.uri, "more than one token matches (add serial=)") from None
        try:
            self._session = token.open(user_pin=_pin(uri, what))
        except p11.UserAlreadyLoggedIn:  # login is per process: another key's session did
            self._session = token.open()
        except _LOCKED as exc:
            raise TokenError(what, self.uri, f"login refused ({type(exc).__name__}: "
                             "wrong or locked PIN)") from None  # fmt: skip
        except p11.PKCS11Error as exc:
            raise TokenError(what, self.uri, f"cannot log in ({type(exc).__name__})") from None
        try:
            self._key: Any = self._session.get_key(
                object_class=self._class, key_type=self._key_type, label=uri.object, id=uri.id
            )
        except p11.NoSuchKey:
            other = self._kind_of(uri)
            self._session.close()
            problem = (f"wrong key type: the object is {other} (wanted: {self._noun})" if other
                       else f"no such object: {self._noun}")  # fmt: skip
            raise TokenError(what, self.uri, problem) from None
        except p11.MultipleObjectsReturned:
            self._session.close()
            raise TokenError(what, self.uri, f"more than one {self._noun} matches") from None
        if self._signs and not hasattr(self._key, "sign"):  # python-pkcs11: by CKA_SIGN
            self._session.close()
            raise TokenError(what, self.uri, f"the {self._noun} may not sign (CKA_SIGN false)")

    def _kind_of(self, uri: Pkcs11Uri) -> str | None:
        """What the object the URI names is, if it exists but is not the key wanted."""
        for cls in (self._class, None):
            with contextlib.suppress(p11.PKCS11Error):
                found = self._session.get_key(object_class=cls, label=uri.object, id=uri.id)
                kind = getattr(getattr(found, "key_type", None), "name", "other")
                return f"a {kind} {getattr(found.object_class, 'name', 'other')}".lower()
        return None

    def _call(self, operation: str, *args: Any, **kwargs: Any) -> bytes:
        with self._lock:
            try:
                return bytes(getattr(self._key, operation)(*args, **kwargs))
            except p11.PKCS11Error as exc:
                raise TokenUnavailableError(f"token key {self.uri}: {type(exc).__name__}") from None

    def close(self) -> None:
        """Log out and close the session; later operations raise TokenUnavailableError."""
        with self._lock, contextlib.suppress(p11.PKCS11Error):
            self._session.close()


class TokenSigner(_TokenKey):
    """An Ed25519 private key in a token (``CKM_EDDSA``, pure Ed25519 as RFC 8032)."""

    _class, _key_type, _noun = ObjectClass.PRIVATE_KEY, KeyType.EC_EDWARDS, "Ed25519 private key"

    def __init__(self, text: str, what: str = "key") -> None:
        super().__init__(text, what)
        try:
            public = self._session.get_key(
                object_class=ObjectClass.PUBLIC_KEY, key_type=KeyType.EC_EDWARDS,
                label=self._key[Attribute.LABEL], id=self._key[Attribute.ID],
            )  # fmt: skip
            point = bytes(public[Attribute.EC_POINT])
        except p11.PKCS11Error as exc:
            self._session.close()
            raise TokenError(
                what, self.uri, f"no public key beside it ({type(exc).__name__})"
            ) from None
        raw = point[2:] if len(point) == 34 and point[:2] == b"\x04\x20" else point  # DER octets
        self._public = Ed25519PublicKey.from_public_bytes(raw)

    def sign(self, data: bytes) -> bytes:
        return self._call("sign", data, mechanism=Mechanism.EDDSA)

    def public_key(self) -> Ed25519PublicKey:
        return self._public


class TokenMac(_TokenKey):
    """A generic secret key in a token; HMAC-SHA256 computed by the token."""

    _class, _key_type, _noun = ObjectClass.SECRET_KEY, KeyType.GENERIC_SECRET, "secret key"

    def mac(self, data: bytes) -> bytes:
        return self._call("sign", data, mechanism=Mechanism.SHA256_HMAC)


class TokenDigestKey(_TokenKey):
    """A generic secret key digested inside the token: ``SHA-256(key || data)``."""

    _class, _key_type, _noun = ObjectClass.SECRET_KEY, KeyType.GENERIC_SECRET, "secret key"
    _signs = False

    def digest(self, data: bytes) -> bytes:
        with self._lock:
            try:
                parts = iter((self._key, data))  # C_DigestKey, then C_DigestUpdate
                return bytes(self._session.digest(parts, mechanism=Mechanism.SHA256))
            except p11.PKCS11Error as exc:
                raise TokenUnavailableError(f"token key {self.uri}: {type(exc).__name__}") from None
