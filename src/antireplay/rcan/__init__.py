"""RCAN: the envelope, its authentication, the receive core and the held answers.

:mod:`.envelope` parses and canonicalises; :mod:`.auth` verifies signatures and
bearer tokens; :mod:`.receive` is the recipe check -> authenticate -> commit
(the :class:`~antireplay.rcan.receive.Receiver`); :mod:`.answers` keeps the
answer of each accepted command for its QoS retries.
"""
