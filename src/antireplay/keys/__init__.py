"""Keys kept outside the process: PKCS#11 tokens named by RFC 7512 URIs.

:mod:`.uri` parses a URI (pure); :mod:`.pkcs11` opens the key it names and signs, MACs
or digests through the token (python-pkcs11).  Wiring and the CLI open keys here; the
layers below see only the objects (``.sign``, ``.mac``, ``.digest``), never the token.
"""

from antireplay.keys.uri import Pkcs11Uri, is_uri, parse

__all__ = ["Pkcs11Uri", "is_uri", "parse"]
