"""The HTTP adapter: the ASGI gateway (``Guard``, ``RcanGuard``) and its status page.

It reads requests, asks :mod:`antireplay.rcan.receive` to decide, and answers;
the rules live below it.
"""
