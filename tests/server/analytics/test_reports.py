"""Field-report numbers on series small enough to compute by hand."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.mdsf_spec import MDSF_SPEC as MDSF
from estimator.reference_speed_spec import REFERENCE_SPEED_SPEC as REF
from estimator.spec import EstimatorSpec, FieldSpec, SlipChannel, WheelPosition
from estimator.types import EstimateFlag, empty_estimates
from server.analytics.reports import (
    IngestCounts,
    flatten_report,
    ingest_counts,
    report_fields,
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
    rep = vehicle_report(hand_series(), MDSF, start_ns=0, end_ns=10 * S)
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

    assert (rep.motion, rep.motion_field) == ("ground", "vg_mps")
    assert list(rep.slips) == ["left", "right"]
    left = rep.slips["left"]
    assert (left.label, left.field, left.band_edges_pct) == (
        "rear left wheel",
        "slip_left_pct",
        (5, 15),
    )
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

    right = rep.slips["right"]
    assert right.samples == 2
    assert right.mean_pct == 0.0
    assert [b.seconds for b in right.bands] == [2.0, 0.0, 0.0]
    assert [b.share for b in right.bands] == [1.0, 0.0, 0.0]


def test_band_edges_and_min_speed_come_from_arguments() -> None:
    rep = vehicle_report(
        hand_series(),
        MDSF,
        start_ns=0,
        end_ns=10 * S,
        band_edges_pct=(10.0,),
        min_ground_speed_mps=3.0,
    )
    assert rep.moving_s == 2.0  # only the two rows at 4 m/s
    assert rep.distance_m == pytest.approx(8.0)
    assert [b.seconds for b in rep.slips["left"].bands] == [
        3.0,
        3.0,
    ]  # |s|<10: 1 3 5; else 10 20 30


def test_gaps_are_not_counted() -> None:
    rows = empty_estimates(5)
    rows["stamp_ns"] = np.array([0, 1, 2, 10, 11]) * S
    rows["vg_mps"] = 1.0
    rep = vehicle_report(rows, MDSF, start_ns=0, end_ns=20 * S, max_gap_s=1.0)
    # steps 1 1 8 1: the 8 s gap counts one 1 s period; last row one period
    assert rep.covered_s == 5.0
    assert rep.moving_s == 5.0
    assert rep.distance_m == pytest.approx(5.0)


def test_last_row_clipped_to_range_end() -> None:
    rows = empty_estimates(3)
    rows["stamp_ns"] = [0, 2 * S, 4 * S]
    rows["vg_mps"] = 1.0
    rep = vehicle_report(rows, MDSF, start_ns=0, end_ns=4 * S + S // 2, max_gap_s=5)
    assert rep.covered_s == 4.5


def test_empty_series() -> None:
    rep = vehicle_report(MDSF.empty_rows(0)[report_fields(MDSF)], MDSF, start_ns=0, end_ns=S)
    assert rep.rows == 0
    assert rep.first_stamp_ns is None
    assert rep.covered_s == rep.moving_s == rep.distance_m == 0.0
    assert rep.speed.mean_mps is None and rep.speed.max_mps is None
    assert rep.slips["left"].samples == 0 and rep.slips["left"].mean_pct is None
    assert all(b.share is None and b.seconds == 0.0 for b in rep.slips["left"].bands)


def test_bad_band_edges() -> None:
    with pytest.raises(ValueError):
        vehicle_report(hand_series(), MDSF, start_ns=0, end_ns=S, band_edges_pct=(15.0, 5.0))


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
    rep = vehicle_report(hand_series(), MDSF, start_ns=0, end_ns=10 * S)
    row = flatten_report(
        "t1", "mdsf", rep, ingest_counts({"received": 3, "rejected_late_clock": 1})
    )
    assert (row["vehicle_id"], row["estimator"]) == ("t1", "mdsf")
    assert row["slip_left_mean_pct"] == pytest.approx(9 / 6)
    assert row["slip_right_samples"] == 2
    assert row["distance_m"] == pytest.approx(16.0)
    assert row["slip_left_share_0_5"] == pytest.approx(1 / 3)
    assert row["slip_left_share_15_up"] == pytest.approx(1 / 3)
    assert row["packets_received"] == 3
    assert row["packets_rejected_late_clock"] == 1


def test_report_fields_follow_the_spec() -> None:
    assert report_fields(MDSF) == ["stamp_ns", "vg_mps", "slip_left_pct", "slip_right_pct", "flags"]
    assert report_fields(REF) == ["stamp_ns", "speed_mps", "flags"]


def test_spec_without_slip_channels_gives_time_speed_and_distance() -> None:
    """The reference-speed estimator: motion from ``speed_mps``, degraded from NO_WHEEL."""
    rows = REF.empty_rows(6)
    rows["stamp_ns"] = np.arange(6) * S
    rows["speed_mps"] = [0.0, 1.0, -2.0, 2.0, 0.1, 3.0]
    rows["flags"][[1, 2]] = REF.flag_mask("NO_WHEEL")
    rows["flags"][3] = REF.flag_mask("WHEEL_OK")
    rep = vehicle_report(rows[report_fields(REF)], REF, start_ns=0, end_ns=6 * S)
    assert (rep.motion, rep.motion_field) == ("reference", "speed_mps")
    assert rep.slips == {}
    assert rep.moving_s == 4.0  # |v| >= 0.2 on rows 1, 2, 3, 5
    assert rep.distance_m == pytest.approx(1 + 2 + 2 + 3)
    assert rep.degraded_s == 2.0
    assert rep.speed.max_mps == 3.0
    row = flatten_report("r1", "reference_speed", rep, IngestCounts())
    assert not any(k.startswith("slip_") for k in row)


TRACKS = EstimatorSpec(
    name="tracks",
    title="track slip",
    kinds=("tracked",),
    inputs=("imu",),
    fields=(
        FieldSpec("stamp_ns", "i8", "ns", "time"),
        FieldSpec("track_slip_pct", "f8", "%", "track slip"),
    ),
    slips=(
        SlipChannel(
            "track",
            "left track",
            "track_slip_pct",
            WheelPosition.TRACK_LEFT,
            band_edges_pct=(10.0,),
        ),
    ),
)


def test_channel_without_flag_or_motion_uses_finite_values_and_its_own_edges() -> None:
    rows = TRACKS.empty_rows(4)
    rows["stamp_ns"] = np.arange(4) * S
    rows["track_slip_pct"] = [2.0, np.nan, 12.0, -4.0]
    rep = vehicle_report(rows, TRACKS, start_ns=0, end_ns=4 * S)
    assert rep.moving_s is None and rep.distance_m is None and rep.speed.mean_mps is None
    assert rep.degraded_s == 0.0
    track = rep.slips["track"]
    assert track.samples == 3 and track.band_edges_pct == (10.0,)
    assert [b.seconds for b in track.bands] == [2.0, 1.0]
    # the vehicle's edges, when given, win over the channel's
    rep5 = vehicle_report(rows, TRACKS, start_ns=0, end_ns=4 * S, band_edges_pct=(3.0,))
    assert [b.seconds for b in rep5.slips["track"].bands] == [1.0, 2.0]
