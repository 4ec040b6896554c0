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


def test_attitude_errors_by_hand_over_the_rows_that_give_it() -> None:
    rows = TRACKED_SPEC.empty_rows(4)  # the first without an attitude (NaN): not scored
    rows["pitch_rad"][1:] = [0.101, 0.098, 0.10]
    rows["roll_rad"][1:] = [0.002, 0.05, -0.052]
    rows["pitch_std_rad"][1:] = rows["roll_std_rad"][1:] = 0.001
    m = _attitude_metrics(_Run(), rows, np.array([0, 0, 1, 2]))  # type: ignore[arg-type]
    assert m["attitude_pct"] == 75.0
    # pitch errors 1, −2, 0 mrad; roll 2, 0, −2 mrad; each over a 1 mrad σ
    assert m["pitch_rms_mrad"] == pytest.approx(np.sqrt(5 / 3))
    assert m["pitch_max_mrad"] == pytest.approx(2.0)
    assert m["roll_rms_mrad"] == pytest.approx(np.sqrt(8 / 3))
    assert m["roll_z_rms"] == pytest.approx(np.sqrt(8 / 3))
