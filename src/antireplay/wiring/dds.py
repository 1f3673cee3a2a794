"""The DDS commands, wired: a configuration in, readers, writers and relays out.

Theory of operation
-------------------
The DDS commands open their leaves through :mod:`antireplay.wiring.leaves` like every
other command (the audit trail as ``audit:`` and ``audit_space:`` say); their readers,
writers and relays are built here from the ``dds:`` block of
:class:`~antireplay.config.AppConfig`.
"""

from __future__ import annotations

__all__: list[str] = []
