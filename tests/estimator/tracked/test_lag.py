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


_BRAKED_R = int(TrackedFlag.BRAKED_RIGHT)


def _pivot_then(after: int, braked_rows: int = 6) -> np.ndarray:
    """Rows of a pivot (5) whose right track is braked (−100 %), then one row of ``after``
    with the right track no longer braked."""
    rows = _rows([5] * braked_rows + [after])
    rows["flags"][:braked_rows] = int(TrackedFlag.SLIP_LEFT_VALID) | _BRAKED_R
    rows["slip_right_pct"][:braked_rows] = -100.0
    rows["slip_right_std_pct"] = 0.5
    return rows


def _tick_by_tick(rows: np.ndarray, reach: int, lag: int = 4) -> tuple[np.ndarray, list[int]]:
    held = HeldRows()
    no = np.zeros(1, dtype=bool)
    parts = [held.give(rows[i : i + 1].copy(), no, lag, 0.9, reach) for i in range(rows.size)]
    return np.concatenate([*parts, held.flush()]), [p.size for p in parts]


def test_a_release_takes_the_braked_track_back_over_the_rows_it_may_have_turned_in() -> None:
    # right track braked on rows 0-5 and released on row 6 (its first edges): rows 3-5 (reach
    # 3) may have had it turning before its first edge, so they give no slip for it; rows
    # 0-2 keep the −100 % and the flag, the left track is untouched everywhere
    got, sizes = _tick_by_tick(_pivot_then(1), reach=3)
    assert np.array_equal(got["stamp_ns"], _pivot_then(1)["stamp_ns"])
    assert (got["slip_right_pct"][:3] == -100.0).all()
    assert (got["flags"][:3] & _BRAKED_R).all()
    assert (
        np.isnan(got["slip_right_pct"][3:6]).all()
        and np.isnan(got["slip_right_std_pct"][3:6]).all()
    )
    assert not (got["flags"][3:6] & _BRAKED_R).any()
    assert (got["slip_left_pct"] == 2.0).all()
    assert (got["flags"] & int(TrackedFlag.SLIP_LEFT_VALID)).all()
    # while braked the last three rows are held (given from the fourth tick on, one a tick)
    assert sizes == [0, 0, 0, 1, 1, 1, 3]


def test_no_release_without_reach_or_into_a_stop() -> None:
    got, sizes = _tick_by_tick(_pivot_then(1), reach=0)  # paper modes: nothing taken back
    assert (got["slip_right_pct"][:6] == -100.0).all() and sizes == [0, 1, 1, 1, 1, 1, 1]
    got, _ = _tick_by_tick(_pivot_then(0), reach=3)  # a stop: the other track stopped instead
    assert (got["slip_right_pct"][:6] == -100.0).all() and (got["flags"][:6] & _BRAKED_R).all()


def test_the_release_reach_is_the_lever_travel_in_ticks_within_the_fixed_lag() -> None:
    from estimator.tracked import TrackedEstimatorConfig, TrackedMode

    assert TrackedEstimatorConfig().release_reach_ticks == 3  # 0.3 s of lever travel, 0.1 s ticks
    assert TrackedEstimatorConfig(lever_travel_s=0.65).release_reach_ticks == 4  # the lag's 4
    assert TrackedEstimatorConfig(mode=TrackedMode.PAPER).release_reach_ticks == 0


def test_braked_rows_given_tick_by_tick_equal_rows_given_at_once() -> None:
    rng = np.random.default_rng(11)
    for _ in range(20):
        states = np.repeat(rng.choice([0, 1, 3, 5], size=8), rng.integers(1, 7, size=8))
        rows = _rows(states.tolist())
        pivot = states == 5
        rows["flags"][pivot] |= _BRAKED_R
        rows["slip_right_pct"][pivot] = -100.0
        onset = rng.random(states.size) < 0.2
        one, each = HeldRows(), HeldRows()
        whole = np.concatenate([one.give(rows.copy(), onset, 4, 0.9, 3), one.flush()])
        parts = [
            each.give(rows[i : i + 1].copy(), onset[i : i + 1], 4, 0.9, 3)
            for i in range(states.size)
        ]
        ticked = np.concatenate([*parts, each.flush()])
        assert whole.tobytes() == ticked.tobytes()
