"""Field-report numbers on series small enough to compute by hand."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.types import EstimateFlag, empty_estimates
from server.analytics.reports import (
    REPORT_FIELDS,
    IngestCounts,
    flatten_report,
    ingest_counts,
    vehicle_report,
)

S = 1_000_000_000
L = int(EstimateFlag.SLIP_LEFT_VALID)
R = int(EstimateFlag.SLIP_RIGHT_VALID)
D = int(EstimateFlag.DEGRADED)


def hand_series() -> np.ndarray:
    """10 rows, one per second from t = 0.

    vg: 0 0 2 2 2 2 4 4 0.1 0 (moving rows 2..7 with min speed 0.2 m/s)
    left slip valid on rows 2..7: 1 3 10 20 -30 5
    right slip valid on rows 2..4: 0 0 NaN (NaN is not a sample)
    rows 0 and 1 GNSS-degraded.
    """
    rows = empty_estimates(10)
    rows["stamp_ns"] = np.arange(10) * S
    rows["vg_mps"] = [0, 0, 2, 2, 2, 2, 4, 4, 0.1, 0]
    rows["slip_left_pct"][2:8] = [1, 3, 10, 20, -30, 5]
    rows["slip_right_pct"][2:5] = [0, 0, np.nan]
    rows["flags"][2:8] |= L
    rows["flags"][2:5] |= R
    rows["flags"][0:2] |= D
    return rows


def test_hand_series() -> None:
    rep = vehicle_report(hand_series(), start_ns=0, end_ns=10 * S)
    assert rep.rows == 10
    assert (rep.first_stamp_ns, rep.last_stamp_ns) == (0, 9 * S)
    assert rep.covered_s == 10.0  # 9 steps of 1 s + the last row's 1 s period
    assert rep.moving_s == 6.0
    assert rep.distance_m == pytest.approx(2 * 4 + 4 * 2)
    assert rep.degraded_s == 2.0
    assert rep.speed.mean_mps == pytest.approx(16 / 6)
    assert rep.speed.median_mps == 2.0
    assert rep.speed.p95_mps == pytest.approx(4.0)
    assert rep.speed.max_mps == 4.0

    left = rep.slip_left
    assert left.samples == 6
    assert left.valid_s == 6.0
    assert left.mean_pct == pytest.approx(9 / 6)
    assert left.median_pct == pytest.approx(4.0)  # sorted -30 1 3 5 10 20 → (3 + 5) / 2
    assert left.p95_pct == pytest.approx(17.5)  # position 4.75 between 10 and 20
    assert (left.min_pct, left.max_pct) == (-30.0, 20.0)
    # |slip|: 1 3 → [0,5); 10 5 → [5,15) (5 is on the edge: upper band); 20 30 → [15,∞)
    assert [(b.lower_pct, b.upper_pct) for b in left.bands] == [(0, 5), (5, 15), (15, None)]
    assert [b.seconds for b in left.bands] == [2.0, 2.0, 2.0]
    assert [b.share for b in left.bands] == pytest.approx([1 / 3] * 3)

    right = rep.slip_right
    assert right.samples == 2
    assert right.mean_pct == 0.0
    assert [b.seconds for b in right.bands] == [2.0, 0.0, 0.0]
    assert [b.share for b in right.bands] == [1.0, 0.0, 0.0]


def test_band_edges_and_min_speed_come_from_arguments() -> None:
    rep = vehicle_report(
        hand_series(), start_ns=0, end_ns=10 * S, band_edges_pct=(10.0,), min_ground_speed_mps=3.0
    )
    assert rep.moving_s == 2.0  # only the two rows at 4 m/s
    assert rep.distance_m == pytest.approx(8.0)
    assert [b.seconds for b in rep.slip_left.bands] == [
        3.0,
        3.0,
    ]  # |s|<10: 1 3 5; else 10 20 30


def test_gaps_are_not_counted() -> None:
    rows = empty_estimates(5)
    rows["stamp_ns"] = np.array([0, 1, 2, 10, 11]) * S
    rows["vg_mps"] = 1.0
    rep = vehicle_report(rows, start_ns=0, end_ns=20 * S, max_gap_s=1.0)
    # steps 1 1 8 1: the 8 s gap counts one 1 s period; last row one period
    assert rep.covered_s == 5.0
    assert rep.moving_s == 5.0
    assert rep.distance_m == pytest.approx(5.0)


def test_last_row_clipped_to_range_end() -> None:
    rows = empty_estimates(3)
    rows["stamp_ns"] = [0, 2 * S, 4 * S]
    rows["vg_mps"] = 1.0
    rep = vehicle_report(rows, start_ns=0, end_ns=4 * S + S // 2, max_gap_s=5)
    assert rep.covered_s == 4.5


def test_empty_series() -> None:
    rep = vehicle_report(empty_estimates(0)[list(REPORT_FIELDS)], start_ns=0, end_ns=S)
    assert rep.rows == 0
    assert rep.first_stamp_ns is None
    assert rep.covered_s == rep.moving_s == rep.distance_m == 0.0
    assert rep.speed.mean_mps is None and rep.speed.max_mps is None
    assert rep.slip_left.samples == 0 and rep.slip_left.mean_pct is None
    assert all(b.share is None and b.seconds == 0.0 for b in rep.slip_left.bands)


def test_bad_band_edges() -> None:
    with pytest.raises(ValueError):
        vehicle_report(hand_series(), start_ns=0, end_ns=S, band_edges_pct=(15.0, 5.0))


def test_ingest_counts() -> None:
    counts = ingest_counts(
        {
            "received": 100,
            "accepted": 90,
            "rejected_bad_payload": 3,
            "rejected.unknown_vehicle": 2,
            "late": 4,
            "duplicate": 1,
            "lost": 7,
            "resets": 1,
        }
    )
    assert counts == IngestCounts(
        received=100,
        accepted=90,
        rejected=5,
        rejected_by_reason={"bad_payload": 3, "unknown_vehicle": 2},
        late=4,
        duplicate=1,
        lost=7,
        other={"resets": 1},
    )
    assert ingest_counts({"rejected": 9, "rejected_x": 1}).rejected == 9
    # the ingest's own names (server.ingest.counters)
    ingest = ingest_counts(
        {
            "received": 5,
            "rejected": 1,
            "rejected_decode": 1,
            "lost_by_seq_gap": 3,
            "seq_restarts": 1,
        }
    )
    assert (ingest.rejected, ingest.lost, ingest.other) == (1, 3, {"seq_restarts": 1})
    assert ingest_counts({}) == IngestCounts()


def test_flatten_report() -> None:
    rep = vehicle_report(hand_series(), start_ns=0, end_ns=10 * S)
    row = flatten_report("t1", rep, ingest_counts({"received": 3, "rejected_late_clock": 1}))
    assert row["vehicle_id"] == "t1"
    assert row["distance_m"] == pytest.approx(16.0)
    assert row["slip_left_share_0_5"] == pytest.approx(1 / 3)
    assert row["slip_left_share_15_up"] == pytest.approx(1 / 3)
    assert row["packets_received"] == 3
    assert row["packets_rejected_late_clock"] == 1
