"""RFC 7512 URIs: what selects a key, percent-decoding, and one line for each mistake."""

from __future__ import annotations

import pytest

from antireplay.keys import is_uri, mask_pins, parse


def test_path_and_query_attributes_are_decoded() -> None:
    uri = parse(
        "pkcs11:token=my%20ops;object=audit-mac;id=%01%ff;type=secret-key"
        "?module-path=/usr/lib/softhsm/libsofthsm2.so&pin-source=file:/run/pin"
    )
    assert (uri.token, uri.object, uri.id, uri.type) == (
        "my ops",
        "audit-mac",
        b"\x01\xff",
        "secret-key",
    )
    assert uri.module_path == "/usr/lib/softhsm/libsofthsm2.so"
    assert (uri.pin_source, uri.pin_value) == ("file:/run/pin", None)


def test_the_pin_value_never_shows() -> None:
    uri = parse("pkcs11:token=t;object=o?pin-value=123456")
    assert uri.pin_value == "123456"
    assert "123456" not in uri.redacted() and "pin-value=***" in uri.redacted()


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("token=t;object=o", "not a pkcs11 URI"),
        ("pkcs11:token=t;objet=o", "unknown path attribute 'objet'"),
        ("pkcs11:token=t;object=o?pin=1", "unknown query attribute 'pin'"),
        ("pkcs11:token=t;token=u;object=o", "token given twice"),
        ("pkcs11:token=t;object=o?pin-value=1&pin-source=/p", "both given"),
        ("pkcs11:object=o", "names no token"),
        ("pkcs11:token=t", "names no object"),
        ("pkcs11:token=t;object=o;type=secret", "type=secret"),
        ("pkcs11:token=t;object", "has no value"),
        ("pkcs11:token=a b;object=o", "whitespace"),
        ("pkcs11:token=%ff;object=o", "not UTF-8"),
    ],
)
def test_each_mistake_is_one_line(text: str, needle: str) -> None:
    with pytest.raises(ValueError, match=None) as caught:
        parse(text)
    message = str(caught.value)
    assert needle in message and "\n" not in message, message


def test_only_pkcs11_text_is_a_uri() -> None:
    assert is_uri("pkcs11:token=t;object=o")
    assert not is_uri("/etc/antireplay/audit.key") and not is_uri(None)


@pytest.mark.parametrize(
    "text",
    [
        "pkcs11:token=nope;object=x;pin-value=SECRET123",
        "pkcs11:token=rk;object=ed&pin-value=SECRET123",
        "pkcs11:token=rk;object=ed?PIN-VALUE=SECRET123&module-path=/x.so",
        "PKCS11:token=rk;object=ed?pin-value=SECRET123",
    ],
    ids=["in-path", "ampersand-typo", "upper-case", "not-a-uri"],
)
def test_mask_pins_hides_a_pin_value_wherever_it_stands(text: str) -> None:
    assert "SECRET123" not in mask_pins(text) and "***" in mask_pins(text)
