"""Tracked bench's dead-reckoning consistency figure, by hand."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.tracked_spec import TRACKED_SPEC
from server.tooling.bench.tracked import _nees


def test_nees_per_degree_of_freedom_by_hand() -> None:
    rows = TRACKED_SPEC.empty_rows(2)
    rows["east_std_m"], rows["north_std_m"] = 2.0, 1.0
    rows["east_north_cov_m2"] = [0.0, 1.0]  # second: correlated, det = 4 − 1 = 3
    d_east, d_north = np.array([2.0, 1.0]), np.array([1.0, 1.0])
    got = _nees(rows, d_east, d_north)
    # [2, 1]ᵀ diag(4, 1)⁻¹ [2, 1] = 1 + 1; [1, 1]ᵀ [[4, 1], [1, 1]]⁻¹ [1, 1] = (1 − 2 + 4)/3
    assert got == pytest.approx([1.0, 0.5])
