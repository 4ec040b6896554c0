"""Reports per state of a spec's state channel (a crawler's motion state), by hand."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.mdsf_spec import MDSF_SPEC
from estimator.tracked_spec import MOTION_STATES, TRACKED_SPEC, TrackedFlag
from server.analytics.reports import flatten_report, ingest_counts, report_fields, vehicle_report

S = 1_000_000_000
T0 = 1_700_000_000 * S


def test_time_distance_and_slip_per_state_by_hand() -> None:
    r = TRACKED_SPEC.empty_rows(6)
    r["stamp_ns"] = T0 + np.arange(6) * S  # 1 s a row, the last clipped to the end
    r["motion_state"] = [0, 1, 1, 3, 3, 1]  # stop, straight x2, arc x2, straight
    r["speed_mps"] = [0.0, 10.0, 12.0, 3.0, 3.0, 8.0]
    r["slip_left_pct"] = [np.nan, 2.0, 4.0, 10.0, 12.0, 3.0]
    r["slip_right_pct"] = [np.nan, 2.0, 2.0, -6.0, -8.0, 1.0]
    both = int(TrackedFlag.SLIP_LEFT_VALID | TrackedFlag.SLIP_RIGHT_VALID)
    r["flags"] = [0, both, both, both, both, int(TrackedFlag.SLIP_LEFT_VALID)]
    rep = vehicle_report(r, TRACKED_SPEC, start_ns=T0, end_ns=T0 + 6 * S)
    assert list(rep.states) == ["stop", "straight", "arc"]  # the channel's order; unseen out
    straight, arc = rep.states["straight"], rep.states["arc"]
    assert straight.seconds == 3.0 and straight.distance_m == 30.0
    assert arc.seconds == 2.0 and arc.distance_m == 6.0
    assert rep.states["stop"].seconds == 1.0 and rep.states["stop"].distance_m == 0.0
    assert straight.slip_mean_pct == {"left": 3.0, "right": 2.0}  # right: 2 valid rows
    assert arc.slip_mean_pct == {"left": 11.0, "right": -7.0}
    assert arc.slip_p95_pct["left"] == pytest.approx(11.9)
    assert rep.states["stop"].slip_mean_pct == {"left": None, "right": None}
    flat = flatten_report("c1", "tracked", rep, ingest_counts({}))
    assert flat["state_arc_s"] == 2.0 and flat["state_arc_slip_right_mean_pct"] == -7.0
    assert "motion_state" in report_fields(TRACKED_SPEC) and len(MOTION_STATES) == 7


def test_a_spec_without_a_state_channel_reports_no_states() -> None:
    rows = MDSF_SPEC.empty_rows(3)
    rows["stamp_ns"] = T0 + np.arange(3) * S
    assert vehicle_report(rows, MDSF_SPEC, start_ns=T0, end_ns=T0 + 3 * S).states == {}
