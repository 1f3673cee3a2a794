"""The HTTP adapter: the guard (middleware and dependency), upstream forwarding, metrics,
the gateway app and its status page.

It reads requests, asks :mod:`antireplay.rcan.receive` to decide, and answers; the rules
live below it.  Every module here takes built objects: :mod:`antireplay.wiring` builds them
from the configuration.
"""
