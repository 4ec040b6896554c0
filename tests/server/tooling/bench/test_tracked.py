"""Tracked bench's dead-reckoning consistency figure, attitude errors and learnt receiver clock,
by hand."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.tracked.model import TrackedState as S
from estimator.tracked_spec import TRACKED_SPEC
from estimator.types import GnssFix, GnssSample
from server.tooling.bench.tracked import (
    _attitude_metrics,
    _clock_before_outage,
    _clock_metrics,
    _dr_metrics,
    _nees,
)


def test_nees_per_degree_of_freedom_by_hand() -> None:
    rows = TRACKED_SPEC.empty_rows(2)
    rows["east_std_m"], rows["north_std_m"] = 2.0, 1.0
    rows["east_north_cov_m2"] = [0.0, 1.0]  # second: correlated, det = 4 − 1 = 3
    d_east, d_north = np.array([2.0, 1.0]), np.array([1.0, 1.0])
    got = _nees(rows, d_east, d_north)
    # [2, 1]ᵀ diag(4, 1)⁻¹ [2, 1] = 1 + 1; [1, 1]ᵀ [[4, 1], [1, 1]]⁻¹ [1, 1] = (1 − 2 + 4)/3
    assert got == pytest.approx([1.0, 0.5])


class _Truth:
    pitch_rad = np.array([0.10, 0.10, 0.10])
    roll_rad = np.array([0.00, 0.05, -0.05])


class _Run:
    truth = _Truth()
    outages_ns = ((15, 30),)  # rows stamped 20 and 30 lost GNSS


def test_attitude_errors_by_hand_over_the_rows_that_give_it() -> None:
    rows = TRACKED_SPEC.empty_rows(4)  # the first without an attitude (NaN): not scored
    rows["pitch_rad"][1:] = [0.101, 0.098, 0.10]
    rows["roll_rad"][1:] = [0.002, 0.05, -0.052]
    rows["pitch_std_rad"][1:] = rows["roll_std_rad"][1:] = 0.0008
    rows["stamp_ns"] = [0, 10, 20, 30]
    m = _attitude_metrics(_Run(), rows, np.array([0, 0, 1, 2]))  # type: ignore[arg-type]
    assert m["attitude_pct"] == 75.0
    # pitch errors 1, −2, 0 mrad; roll 2, 0, −2 mrad; each over a 0.8 mrad σ (z ±1.25, ±2.5)
    assert m["pitch_rms_mrad"] == pytest.approx(np.sqrt(5 / 3))
    assert m["pitch_max_mrad"] == pytest.approx(2.0)
    assert m["roll_rms_mrad"] == pytest.approx(np.sqrt(8 / 3))
    assert m["roll_z_rms"] == pytest.approx(np.sqrt(2 * 2.5**2 / 3))
    # beside GNSS the row stamped 10 (pitch z 1.25, roll 2.5); in the outage pitch z −2.5, 0 and
    # roll 0, −2.5: NEES 2.5²/2, half within 2σ
    assert (m["attitude_rows_gnss"], m["attitude_rows_outage"]) == (1, 2)
    assert (m["pitch_nees_gnss"], m["pitch_in2s_gnss_pct"]) == pytest.approx((1.5625, 100.0))
    assert (m["roll_nees_gnss"], m["roll_in2s_gnss_pct"]) == pytest.approx((6.25, 0.0))
    for name in ("pitch", "roll"):
        assert m[f"{name}_nees_outage"] == pytest.approx(3.125)
        assert m[f"{name}_in2s_outage_pct"] == pytest.approx(50.0)


class _Sensors:
    gnss_clock_offset_s = 0.065


class _ClockRun:
    sensors = _Sensors()
    outages_ns = ((5_000_000_000, 9_000_000_000),)


class _Fleet:
    def __init__(self, clock_s: float, std_s: float) -> None:
        self.x = np.zeros(len(S))
        self.P = np.zeros((len(S), len(S)))
        self.x[S.GNSS_CLOCK], self.P[S.GNSS_CLOCK, S.GNSS_CLOCK] = clock_s, std_s**2

    def filter_state(self, vid: str) -> tuple[np.ndarray, np.ndarray]:
        return self.x, self.P


def test_the_learnt_clock_is_read_before_the_first_outage_and_scored_against_the_runs() -> None:
    run = _ClockRun()
    held = _clock_before_outage(_Fleet(0.07, 0.002), "v", run, 5_000_000_000, (0.0, 0.0))  # type: ignore[arg-type]
    assert held == pytest.approx((0.07, 0.002))
    # after the outage starts the filter's clock is no longer what the dead reckoning began with
    later = _clock_before_outage(_Fleet(0.09, 0.01), "v", run, 6_000_000_000, held)  # type: ignore[arg-type]
    assert later == held
    m = _clock_metrics(run, held)  # type: ignore[arg-type]
    assert m["gnss_clock_ms"] == pytest.approx(70.0)
    assert m["gnss_clock_err_ms"] == pytest.approx(5.0)
    assert m["gnss_clock_z"] == pytest.approx(2.5)


def _fix(stamp_ns: int, fix: GnssFix = GnssFix.RTK_FIXED) -> tuple[int, GnssSample]:
    nan = float("nan")
    return stamp_ns, GnssSample(stamp_ns, (0.0, 0.0, 0.0), nan, nan, nan, 52.0, 5.6, 0.0, fix, 0.03)


class _DrTruth:
    east_m = np.array([0.0, 100.0, 200.0, 300.0, 400.0])
    north_m = np.zeros(5)


class _DrRun:
    """Outage (10, 40] ns on the IMU's clock; the receiver's clock leads at its start (its
    last fix before the outage is stamped 15, after the outage began) and lags at its end
    (its first fix after it is stamped 35, before the outage's end)."""

    truth = _DrTruth()
    outages_ns = ((10, 40),)
    measurements = (_fix(15), _fix(25, GnssFix.NONE), _fix(35), _fix(45))

    def distance_m(self) -> np.ndarray:
        return np.asarray(self.truth.east_m)

    def index_at(self, stamp_ns: np.ndarray) -> np.ndarray:
        return np.asarray(stamp_ns) // 10


def test_the_dead_reckoning_ends_at_the_last_row_before_the_first_fix_after_the_outage() -> None:
    rows = TRACKED_SPEC.empty_rows(4)
    rows["stamp_ns"] = [10, 20, 30, 40]
    rows["east_m"] = [100.0, 201.0, 303.0, 400.1]  # the row stamped 40 has fused the fix of 35
    rows["north_m"] = 0.0
    rows["east_std_m"] = rows["north_std_m"] = 1.0
    rows["east_north_cov_m2"] = 0.0
    m = _dr_metrics(_DrRun(), rows, np.array([1, 2, 3, 4]))  # type: ignore[arg-type]
    # the row stamped 30: 3 m after 200 m (truth index 3 less the outage's start, index 1)
    assert m["dr_end_m"] == pytest.approx(3.0)
    assert m["dr_end_pct"] == pytest.approx(1.5)
    assert m["outage_km"] == pytest.approx(0.2)
    assert m["dr_max_m"] == pytest.approx(3.0)
