"""Post-quantum MAVLink commands over a lossy, slow telemetry radio, beside signed MAVLink.

Run: ``python -m benchmarks pq-radio [--commands N] [--seeds 1,2] [--loss 0,1,2,5,10]
[--bps 0,57600] [--queue-bytes 2048]`` (``--help`` for the rest).  The default (20
commands, one seed, five loss levels, unlimited and 57,600 baud) takes about ten minutes;
the full size is ``--commands 100 --seeds 1,2`` (about an hour: a lost command costs the
ground station its four tries, 6 s).

Per loss level and link (each its own processes, keys made once by ``antireplay keygen``):

- **PQ**: a pymavlink ground station (heartbeat at 1 Hz; each COMMAND_LONG tried up to
  ``--tries`` times ``--retry-s`` apart until its COMMAND_ACK comes, as QGroundControl and
  MAVProxy do) -> ``antireplay mavlink-pq ground`` -> the radio
  (:class:`harness.radio.Radio`: independent loss per datagram, optionally a serial
  line at ``--bps`` with a SiK-sized queue) -> ``antireplay mavlink-pq vehicle`` -> a
  pymavlink vehicle (heartbeat at 1 Hz, a COMMAND_ACK for every COMMAND_LONG).  The ends
  get ``--air-bps`` when the link is limited and the CLI has the option.
- **signed MAVLink**, the deployed path of the MAVLink guide: the same ground station
  signing by passphrase -> the radio -> ``antireplay mavlink-router`` (ground link
  verified, vehicle key the same) -> the vehicle, signing its telemetry.

Printed per row: commands delivered (an ACK within the tries) of N, p90 time to the ACK of
those delivered, air bytes (both directions, lost datagrams included, heartbeats too) per
delivered command from the first command to the last, and the time from the ground end's
first datagram to its session.  The vehicle counts each execution by command and by the
ground station's MAVLink sequence number, which tells one transmission from another:
**replays** (a transmission executed twice) must be 0; **re-executed** counts commands run
again because a retry came after a lost ACK; **no ACK** counts commands executed while the
ground station reported failure.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

from harness.pq_radio import Plan, Row, make_keys, run_pq, run_signed, supports_air_bps
from harness.radio import SIK_BAUD, SIK_QUEUE_BYTES


def _numbers(text: str) -> list[int]:
    return [int(part) for part in text.split(",") if part.strip()]


def parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks pq-radio",
        description="PQ MAVLink commands over a lossy, slow radio, beside signed MAVLink.",
    )
    parser.add_argument("--commands", type=int, default=20, help="per run (default 20)")
    parser.add_argument("--seeds", type=_numbers, default=[1], help="comma-separated (1)")
    parser.add_argument(
        "--loss", type=_numbers, default=[0, 1, 2, 5, 10], help="percent, comma-separated"
    )
    parser.add_argument(
        "--bps", type=_numbers, default=[0, SIK_BAUD], help="baud, 0 = unlimited (0,57600)"
    )
    parser.add_argument("--queue-bytes", type=int, default=SIK_QUEUE_BYTES)
    parser.add_argument("--tries", type=int, default=4)
    parser.add_argument("--retry-s", type=float, default=1.5)
    parser.add_argument("--session-timeout-s", type=float, default=45.0)
    parser.add_argument("--paths", default="pq,signed", help="pq, signed or both (pq,signed)")
    return parser.parse_args(argv)


def _row_text(link: str, loss: int, seed: int, pq: Row | None, signed: Row | None) -> str:
    def cells(row: Row | None, session: bool) -> list[str]:
        if row is None:
            return ["—"] * (4 if session else 3)
        out = [f"{row.delivered}/{row.commands}", row.p90(), row.per_command()]
        if session:
            out.append(f"{row.session_s:.3f} s" if row.session_s is not None else row.note)
        return out

    replays = "/".join(str(r.replays) if r else "—" for r in (pq, signed))
    again = "/".join(f"{r.re_executed}, {r.unacked_executed}" if r else "—" for r in (pq, signed))
    texts = [link, f"{loss} %", str(seed), *cells(pq, True), *cells(signed, False)]
    return " | ".join(["", *texts, replays, again, ""]).strip()


HEADER = (
    "| link | loss | seed | PQ delivered | PQ p90 to ACK | PQ air B / delivered | session up "
    "| signed delivered | signed p90 | signed air B / delivered | replays executed PQ/signed "
    "| re-executed on retry, executed without ACK: PQ/signed |\n"
    "|---|---|---|---|---|---|---|---|---|---|---|---|"
)


def main(argv: list[str] | None = None) -> None:
    args = parse([] if argv is None else argv)
    paths = set(args.paths.split(","))
    with tempfile.TemporaryDirectory() as keys:
        make_keys(Path(keys))
        plan = Plan(
            args.commands, args.tries, args.retry_s, args.session_timeout_s, args.queue_bytes,
            Path(keys), supports_air_bps(),
        )  # fmt: skip
        print(
            f"{args.commands} commands per run, {args.tries} tries {args.retry_s} s apart; "
            f"radio queue {args.queue_bytes:,} B; --air-bps passed to the ends: "
            f"{'yes' if plan.air_bps else 'no (this CLI has no such option)'}",
            flush=True,
        )
        print(HEADER, flush=True)
        replays = 0
        for bps in args.bps:
            link = "unlimited" if bps == 0 else f"{bps:,} bd"
            for loss in args.loss:
                for seed in args.seeds:
                    limit = bps or None
                    pq = run_pq(loss / 100, limit, seed, plan) if "pq" in paths else None
                    signed = (
                        run_signed(loss / 100, limit, seed, plan) if "signed" in paths else None
                    )
                    replays += sum(r.replays for r in (pq, signed) if r is not None)
                    print(_row_text(link, loss, seed, pq, signed), flush=True)
    print(f"replayed transmissions executed: {replays} (must be 0)")
    if replays:
        raise SystemExit(1)


if __name__ == "__main__":
    main(sys.argv[1:])
