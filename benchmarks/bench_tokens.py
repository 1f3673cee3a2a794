"""Keys in a PKCS#11 token against the same operation with the key in memory: an Ed25519
envelope signature (CKM_EDDSA), the audit head's HMAC-SHA256 (CKM_SHA256_HMAC) and a
MAVLink signature's SHA-256 over the key (C_DigestKey), on a real SoftHSMv2 token.

Run: ``python -m benchmarks tokens`` (``--repeats N --batch N``).  Batches of the token
and the in-memory key interleave (:func:`~benchmarks._timing.interleaved_ns_per_op`), so
the ratio is of one run on one machine state.  SoftHSMv2 is software: a hardware token
(a USB HSM, a TPM) adds its bus round trip to every token row.
"""

from __future__ import annotations

import argparse
import hashlib
import hmac
import tempfile
from collections.abc import Callable
from pathlib import Path

from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

from antireplay.keys import open_key
from benchmarks._timing import interleaved_ns_per_op
from harness.softhsm import make_token

KEY = bytes(range(32))
ENVELOPE = b'{"cmd":"move_forward","msg_id":"0b7e...","params":{"distance_m":0.5}}' * 4
FRAME = bytes(range(48))  # a signed MAVLink frame's header, payload, CRC, link id, timestamp


def _batch(action: Callable[[], object], n: int) -> Callable[[int], None]:
    def run(_: int) -> None:
        for _ in range(n):
            action()

    return run


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m benchmarks tokens")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--batch", type=int, default=500)
    args = parser.parse_args(argv or [])
    with tempfile.TemporaryDirectory(prefix="bench-tokens-") as scratch:
        token = make_token(Path(scratch))
        token.generate_ed25519("operator")
        token.import_secret("secret", KEY)
        signer, mac = (
            open_key(token.uri("operator"), "ed25519"),
            open_key(token.uri("secret"), "hmac"),
        )
        digest, memory = open_key(token.uri("secret"), "digest"), Ed25519PrivateKey.generate()
        pairs = [
            ("Ed25519 sign (envelope)", lambda: signer.sign(ENVELOPE),
             lambda: memory.sign(ENVELOPE)),
            ("HMAC-SHA256 (audit head)", lambda: mac.mac(ENVELOPE),
             lambda: hmac.digest(KEY, ENVELOPE, "sha256")),
            ("SHA-256(key || frame) (MAVLink)", lambda: digest.digest(FRAME),
             lambda: hashlib.sha256(KEY + FRAME).digest()),
        ]  # fmt: skip
        n = args.batch
        contenders = [(_batch(f, n), n) for _, token_op, memory_op in pairs
                      for f in (token_op, memory_op)]  # fmt: skip
        medians = interleaved_ns_per_op(contenders, args.repeats)
    print(f"{'operation':34} {'token (SoftHSMv2)':>18} {'in memory':>12} {'ratio':>8}")
    for i, (name, _, _) in enumerate(pairs):
        through, local = medians[2 * i], medians[2 * i + 1]
        print(f"{name:34} {through / 1000:15.1f} us {local / 1000:9.1f} us {through / local:7.1f}x")


if __name__ == "__main__":
    main()
