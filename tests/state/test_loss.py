"""The loss decision (:mod:`antireplay.state.loss`), row by row from a table: values in, a
decision out, as litestream compares generations."""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from antireplay.state.loss import FLOOR, NO_HISTORY, Anchored, MetaRow, Read, WitnessRead, decide

WALL = 2_000_000_000.0
LAST = WALL - 30.0  # the last commit's time, as the witness or an anchor records it
OURS, OTHER = "a" * 32, "b" * 32
META: MetaRow = (OURS, 7, FLOOR, FLOOR, 0)
WITNESS: WitnessRead = (OURS, 7, LAST)


@dataclass(frozen=True)
class Row:
    """One row of the table: what open finds, and what it must decide."""

    name: str
    meta: MetaRow | None
    witness: WitnessRead
    has_state: bool = False
    copies: tuple[Read, ...] = ()
    lazy: bool = False
    #: A substring of the reason (None: continuity proven, no fence).
    reason: str | None = None
    no_history: bool = False


TABLE = [
    Row("a clean restart", META, WITNESS),
    Row("a clean restart, its anchor exact", META, WITNESS, copies=(Anchored(OURS, 7, LAST),)),
    Row("a clean restart, the anchor behind (a power cut)", META, WITNESS,
        copies=(Anchored(OURS, 6, LAST),)),
    Row("nothing at all: no history", None, None, reason="no history", no_history=True),
    Row("nothing, a new anchor proves nothing about before", None, None, copies=(None,),
        reason="no history", no_history=True),
    Row("rows without meta or witness", None, None, has_state=True, reason="older version"),
    Row("witness, no database", None, WITNESS, reason="database missing"),
    Row("witness of another deployment", META, (OTHER, 7, LAST), reason="another deployment"),
    Row("database behind its witness", META, (OURS, 8, LAST), reason="rolled back"),
    Row("no witness", META, None, reason="witness file missing"),
    Row("unreadable witness", META, False, reason="witness file unreadable"),
    Row("unreadable anchor", META, WITNESS, copies=(False,), reason="unreadable"),
    Row("no anchor for existing state", META, WITNESS, copies=(None,), reason="no state anchor"),
    Row("database and witness gone, anchor left", None, None, copies=(Anchored(OURS, 7, LAST),),
        reason="vouches for generation 7"),
    Row("anchor of another deployment", META, WITNESS, copies=(Anchored(OTHER, 7, LAST),),
        reason="another deployment"),
    Row("restored directory behind its anchor", META, WITNESS, copies=(Anchored(OURS, 9, LAST),),
        reason="restored from an older copy"),
    Row("one good copy does not hide a lost one", META, WITNESS,
        copies=(Anchored(OURS, 7, LAST), None), reason="no state anchor"),
    Row("a lazy anchor's lease ahead", META, WITNESS, copies=(Anchored(OURS, 7, WALL + 20),),
        lazy=True, reason="lease end"),
    Row("a lazy anchor's lease past", META, WITNESS, copies=(Anchored(OURS, 7, WALL - 20),),
        lazy=True),
]  # fmt: skip


@pytest.mark.parametrize("row", TABLE, ids=[row.name for row in TABLE])
def test_the_loss_table(row: Row) -> None:
    copies = {f"copy{i}": copy for i, copy in enumerate(row.copies)}
    decision = decide(
        row.meta, row.witness, row.has_state, copies, lazy=row.lazy, wall=WALL,
        wall_hw=FLOOR, new_id=OTHER,
    )  # fmt: skip
    assert decision.no_history is row.no_history
    if row.reason is None:
        assert decision.reason is None
        assert decision.fence == (FLOOR if row.meta is None else row.meta[3])
        return
    assert decision.reason is not None and row.reason in decision.reason, decision.reason
    assert decision.fence >= WALL  # the fence: at the wall time, or the lease's end
    # A state with no history is fenced, not counted as a loss (nothing is known lost).
    assert decision.losses == (META[4] if row.meta else 0) + (0 if row.no_history else 1)


def test_no_history_fences_at_the_wall_time_like_a_memory_store() -> None:
    decision = decide(None, None, False, {}, lazy=False, wall=WALL, wall_hw=FLOOR, new_id=OTHER)
    assert decision.reason == NO_HISTORY
    assert (decision.fence, decision.deployment, decision.generation) == (WALL, OTHER, 0)


def test_a_fence_is_no_lower_than_the_last_commit_time() -> None:
    """The clock stepped back since the last commit: the fence stays above that commit."""
    decision = decide(
        META, None, True, {}, lazy=False, wall=LAST - 100, wall_hw=FLOOR, new_id=OTHER
    )
    assert decision.fence == LAST - 100  # no witness: nothing says when the last commit was
    behind = decide(
        META, (OURS, 8, LAST), True, {}, lazy=False, wall=LAST - 100, wall_hw=FLOOR, new_id=OTHER
    )
    assert behind.fence == LAST and behind.generation == 8


def test_the_deployment_is_kept_from_what_names_it() -> None:
    kept = decide(None, WITNESS, False, {}, lazy=False, wall=WALL, wall_hw=FLOOR, new_id=OTHER)
    assert kept.deployment == OURS and kept.generation == 7
    anchored = decide(
        None, None, False, {"file": Anchored(OURS, 9, LAST)}, lazy=False, wall=WALL,
        wall_hw=FLOOR, new_id=OTHER,
    )  # fmt: skip
    assert anchored.deployment == OURS and anchored.generation == 9
