"""Fixed-lag output: a state change backdated by hand, rows held and given in order."""

from __future__ import annotations

import numpy as np

from estimator.tracked.lag import HeldRows, backdate
from estimator.tracked_spec import TRACKED_SPEC, TrackedFlag

_VALID = int(TrackedFlag.SLIP_LEFT_VALID | TrackedFlag.SLIP_RIGHT_VALID)


def _rows(states: list[int]) -> np.ndarray:
    rows = TRACKED_SPEC.empty_rows(len(states))
    rows["stamp_ns"] = np.arange(len(states)) * 100_000_000
    rows["motion_state"] = states
    rows["state_confidence"] = np.linspace(0.5, 1.0, len(states))
    rows["slip_left_pct"] = rows["slip_right_pct"] = 2.0
    rows["flags"] = _VALID
    return rows


def test_a_change_moves_back_over_the_ticks_already_under_way() -> None:
    # straight (1) to arc (3) seen at row 5; rows 3 and 4 show the lever moving (onset of
    # rows 4 and 5), row 2 does not: rows 3 and 4 become arc, nothing before
    rows = _rows([1, 1, 1, 1, 1, 3, 3, 3])
    onset = np.array([0, 0, 0, 0, 1, 1, 1, 0], dtype=bool)
    moved = backdate(rows, onset, 0, 4, 0.9)
    assert rows["motion_state"].tolist() == [1, 1, 1, 3, 3, 3, 3, 3]
    assert moved.tolist() == [False, False, False, True, True, False, False, False]
    assert (
        np.isnan(rows["slip_left_pct"][moved]).all() and (rows["slip_left_pct"][~moved] == 2).all()
    )
    assert (rows["flags"][moved] & _VALID == 0).all()
    assert (rows["flags"][moved] & int(TrackedFlag.STATE_BACKDATED)).all()
    assert (rows["state_confidence"][moved] == rows["state_confidence"][5]).all()


def test_backdating_stops_at_the_lag_and_at_another_state() -> None:
    rows = _rows([1, 1, 1, 1, 1, 1, 3])
    backdate(rows, np.ones(7, dtype=bool), 0, 2, 0.9)  # no further back than 2 ticks
    assert rows["motion_state"].tolist() == [1, 1, 1, 1, 3, 3, 3]
    rows = _rows([1, 4, 1, 3])  # separated on the way: the walk stops at it
    backdate(rows, np.ones(4, dtype=bool), 3, 4, 0.9)
    assert rows["motion_state"].tolist() == [1, 4, 3, 3]


def test_an_intermediate_state_is_overwritten_by_the_one_it_leads_to() -> None:
    rows = _rows([1, 1, 4, 4, 3, 3])  # straight, separated for two ticks, then arc
    backdate(rows, np.array([0, 0, 1, 1, 1, 0], dtype=bool), 0, 4, 0.9)
    assert rows["motion_state"].tolist() == [1, 3, 3, 3, 3, 3]


def test_rows_are_held_only_while_a_change_can_still_reach_them() -> None:
    held = HeldRows()
    rows = _rows([1, 1, 1, 1, 1, 1, 3, 3, 3, 3])
    onset = np.zeros(10, dtype=bool)
    onset[5:7] = True  # the change under way on rows 5 and 6, seen as a change on row 6
    given = [held.give(rows[a : a + 3], onset[a : a + 3], 4, 0.9) for a in (0, 3, 6)]
    given.append(held.give(rows[9:], onset[9:], 4, 0.9))
    got = np.concatenate(given)
    # steady: the last row held; rows 4, 5 held while row 5 shows a change under way
    assert [g.size for g in given] == [2, 2, 4, 1]
    assert np.array_equal(got["stamp_ns"], rows["stamp_ns"][:9])  # each row its own stamp
    assert got["motion_state"].tolist() == [1, 1, 1, 1, 3, 3, 3, 3, 3]  # 4, 5 backdated
    assert held.state.size == 1 and len(held.data) == TRACKED_SPEC.dtype.itemsize


def test_no_lag_gives_every_row_at_once() -> None:
    rows = _rows([1, 1, 3])
    got = HeldRows().give(rows, np.ones(3, dtype=bool), 0, 0.9)
    assert got.size == 3 and got["motion_state"].tolist() == [1, 1, 3]


def test_flush_gives_the_held_rows_as_they_stand_and_holds_none() -> None:
    held = HeldRows()
    rows = _rows([1, 1, 1, 3, 3])
    onset = np.array([0, 0, 0, 1, 1], dtype=bool)  # a change under way on the last rows
    given = held.give(rows, onset, 4, 0.9)
    flushed = held.flush()
    assert given.size + flushed.size == 5 and flushed.size >= 1
    assert np.array_equal(np.concatenate([given, flushed])["stamp_ns"], rows["stamp_ns"])
    assert held.flush().size == 0 and held.state.size == 0 and held.data == b""
    assert held.give(_rows([3]), np.zeros(1, dtype=bool), 4, 0.9).size == 0  # holds anew


def test_rows_given_tick_by_tick_equal_rows_given_at_once() -> None:
    # steady runs (no onset: the short path) broken by changes under way, as the fleet gives them
    rng = np.random.default_rng(7)
    for _ in range(20):
        states = np.repeat(rng.choice([1, 2, 3, 4], size=8), rng.integers(1, 7, size=8))
        rows = _rows(states.tolist())
        onset = rng.random(states.size) < 0.2
        one, each = HeldRows(), HeldRows()
        whole = np.concatenate([one.give(rows.copy(), onset, 4, 0.9), one.flush()])
        parts = [
            each.give(rows[i : i + 1].copy(), onset[i : i + 1], 4, 0.9) for i in range(states.size)
        ]
        ticked = np.concatenate([*parts, each.flush()])
        assert whole.tobytes() == ticked.tobytes()
        assert max(p.size for p in parts) <= 5  # at most the lag and the newest row at once
