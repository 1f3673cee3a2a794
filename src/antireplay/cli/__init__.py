"""The ``antireplay`` command line (click + rich): a thin adapter over the library.

Errors are for people: an ordinary mistake (a bad option value, a missing or
foreign file, a busy port, a configuration ``serve`` would refuse) is one line
on stderr, ``antireplay: error: <what> (<what is allowed>)``, never wrapped,
with exit status 2, and never a traceback (:mod:`._common` holds that idiom, and
gives click's own usage errors the same shape).  ``config check`` runs the same
preflight as ``serve``, so a configuration that passes the check starts.

One click group, :func:`main`; each module holds one family of commands: ``serve``,
``config check``, ``demo``, ``bench`` (:mod:`.serve`), ``keygen``, ``sign``, ``send``, ``keys``
(:mod:`.keys`), ``audit`` (:mod:`.audit`), ``state`` (:mod:`.state`),
``mavlink-router``, ``mavlink-sim`` (:mod:`.mavlink`), ``mavlink-keys``
(:mod:`.mavlink_keys`), ``mavlink-pq`` (:mod:`.mavlink_pq`), ``dds`` (:mod:`.dds`).
"""

from __future__ import annotations

import copy

import click

from antireplay.cli import audit, dds, keys, mavlink, mavlink_keys, mavlink_pq, serve, state
from antireplay.cli._common import _Cli

__all__ = ["main"]


@click.group(cls=_Cli)
@click.version_option(package_name="antireplay")
def main() -> None:
    """Stop captured robot and drone commands from working twice."""


for command in (
    serve.serve,
    serve.demo,
    serve.config,
    serve.bench,
    keys.keygen,
    keys.sign,
    keys.send,
    keys.keys_group,
    audit.audit,
    state.state,
    mavlink.mavlink_router,
    mavlink.mavlink_sim,
    mavlink_keys.mavlink_keys,
    mavlink_pq.mavlink_pq,
    dds.dds,
):
    main.add_command(command)
# The command's first name still works, unlisted: one name per command in the help.
_alias = copy.copy(mavlink.mavlink_router)
_alias.hidden = True
main.add_command(_alias, "mavlink-proxy")
