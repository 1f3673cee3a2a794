"""The loss decision: whether a SQLite state proves its continuity, from values alone.

Theory of operation
-------------------
At open the driver (:mod:`.sqlite`) reads what it finds (the database's meta row, its
witness, whether it holds rows, each anchor copy) and hands the values to
:func:`decide`, which answers the state to carry on with and, when continuity is not
proven, why (the fence then rises to the wall time, no lower than the highest commit
time seen).  No I/O here: the table below is tested row by row, as litestream compares
generations and positions.

==========================================  =====================================
what is found                               what it means / what happens
==========================================  =====================================
neither database nor witness (nor anchor)   **no history** (a first start, an emptied
                                            directory, a new deployment id): **fence**,
                                            like a memory store's start; not a loss
witness, database missing or empty          deleted or truncated: **fence**
witness of another deployment               the file was replaced: **fence**
database generation below the witness's     rolled back (a restored copy): **fence**
database with state but no witness          witness lost (or older version): **fence**
any anchor copy: unreadable, missing for    a restored copy of the whole directory or
existing state, of another deployment, or   an anchor copy lost: **fence** (a lazy
ahead of the database                       anchor's lease end also raises the fence)
==========================================  =====================================

Only a database whose witness (and every anchor copy) vouches for it opens unfenced: an
anchor that matches removes nothing it proves, and a brand-new anchor proves nothing
about what ran before it.  What remains: a restore of the whole directory when no
anchor is configured (database and witness agree; nothing outside says otherwise).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Final, Literal

#: SQLite REAL has no -inf literal that round-trips everywhere: "nothing yet".
FLOOR: Final = -1e300
#: The reason given for a state with no history (its prefix is what the audit row shows).
NO_HISTORY: Final = (
    "no history: a new, emptied or replaced state (first start?); fenced like a "
    "memory store's start"
)

#: The meta row, decoded: deployment id, generation, watermark, fence, data-loss events.
MetaRow = tuple[str, int, float, float, int]
#: The witness as read: ``(deployment, generation, wall)``, ``None`` absent, ``False``
#: unreadable.
WitnessRead = tuple[str, int, float] | bool | None


@dataclass(frozen=True)
class Anchored:
    """What one anchor copy vouches for: the deployment, its generation and the time (a
    lease end when written lazily, the last commit's time otherwise)."""

    deployment: str
    generation: int
    time: float


#: One anchor copy as read: the record, ``None`` if there is none yet, ``False`` if unreadable.
Read = Anchored | Literal[False] | None


@dataclass(frozen=True)
class Decision:
    """The state to carry on with; ``reason`` (None: continuity proven) says why it fenced."""

    deployment: str
    generation: int
    watermark: float
    fence: float
    losses: int
    wall_hw: float
    reason: str | None
    no_history: bool


def known_deployment(meta: MetaRow | None, witness: WitnessRead) -> str | None:
    """The deployment the database or its witness names (the anchor copies to read)."""
    if meta is not None:
        return meta[0]
    return witness[0] if isinstance(witness, tuple) else None


def decide(
    meta: MetaRow | None,
    witness: WitnessRead,
    has_state: bool,
    copies: Mapping[str, Read],
    *,
    lazy: bool,
    wall: float,
    wall_hw: float,
    new_id: str,
) -> Decision:
    """The decision of the module docstring's table; ``new_id`` names a new deployment."""
    reason = loss_reason(meta, witness, has_state)
    for where, copy in copies.items():
        reason = reason or anchor_reason(meta, witness, copy, where)
    anchored = [copy for copy in copies.values() if isinstance(copy, Anchored)]
    known = known_deployment(meta, witness)
    if meta is None:
        deployment = known or (anchored[0].deployment if anchored else new_id)
        generation, watermark, fence, losses = 0, FLOOR, FLOOR, 0
    else:
        deployment, generation, watermark, fence, losses = meta
    if isinstance(witness, tuple):
        generation = max(generation, witness[1])
        wall_hw = max(wall_hw, witness[2])
    lease = FLOOR
    for copy in anchored:
        generation = max(generation, copy.generation)
        if lazy:
            lease = max(lease, copy.time)  # commits since its last write came before
        else:  # the last commit's time
            wall_hw = max(wall_hw, copy.time)
    if reason is None and lease > max(fence, wall):
        reason = (
            f"restart fence to the lazy state anchor's lease end {lease:.3f}: a copy "
            "as new as the anchor may lack commits made under that lease"
        )
    no_history = reason is None and meta is None
    if no_history:
        reason = NO_HISTORY
    if reason is not None:
        fence = max(fence, wall, wall_hw, lease)
        losses += 0 if no_history else 1
    return Decision(deployment, generation, watermark, fence, losses, wall_hw, reason, no_history)


def loss_reason(meta: MetaRow | None, witness: WitnessRead, has_state: bool) -> str | None:  # noqa: PLR0911 - one answer per row of the table
    """Why the database may have lost state (None: it provably has not, or it is new)."""
    if meta is None:
        if witness is None and not has_state:
            return None  # no history: :func:`decide` fences it as such
        if witness is None:
            return "state without meta or witness (made by an older version?)"
        return "database missing, truncated or replaced (the witness says it existed)"
    if witness is None:
        return "witness file missing"
    if witness is False:
        return "witness file unreadable"
    assert isinstance(witness, tuple)
    if witness[0] != meta[0]:
        return "database belongs to another deployment than its witness (replaced)"
    if meta[1] < witness[1]:
        return f"database generation {meta[1]} is behind its witness's {witness[1]} (rolled back)"
    return None


def anchor_reason(  # noqa: PLR0911 - one answer per anchor row of the table
    meta: MetaRow | None, witness: WitnessRead, anchor: Read, where: str = ""
) -> str | None:
    """Why a database its witness vouches for may still have lost state, by one copy of
    its anchor (at ``where``): what a restored copy of the whole directory, or a lost
    anchor copy, shows."""
    at = f" ({where})" if where else ""
    if anchor is False:
        return f"state anchor{at} unreadable"
    if anchor is None:
        if meta is None and witness is None:
            return None  # no history: anchored from its first commit, fenced by decide
        return f"no state anchor{at} for existing state (the anchor was lost, or is new here)"
    if meta is None:
        return (
            f"database and witness missing but the state anchor{at} vouches for generation "
            f"{anchor.generation} (deleted, or restored from before the anchor)"
        )
    if meta[0] != anchor.deployment:
        return f"database belongs to another deployment than its state anchor{at} (replaced)"
    if meta[1] < anchor.generation:
        return (
            f"database generation {meta[1]} is behind its state anchor{at}'s "
            f"{anchor.generation} (the state directory was restored from an older copy)"
        )
    return None
