"""Tracked bench's dead-reckoning consistency figure and attitude errors, by hand."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.tracked_spec import TRACKED_SPEC
from server.tooling.bench.tracked import _attitude_metrics, _nees


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
