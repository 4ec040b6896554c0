"""Series builders shared by the API tests."""

from __future__ import annotations

import numpy as np

from estimator.reference_speed_spec import REFERENCE_SPEED_SPEC as REF
from estimator.types import EstimateFlag, empty_estimates

S = 1_000_000_000
T0 = 1_714_564_800 * S  # 2024-05-01T12:00:00Z
T0_ISO = "2024-05-01T12:00:00Z"


def hand_series(t0: int = T0) -> np.ndarray:
    """10 rows, 1 s apart from ``t0`` (the series of tests/server/analytics/test_reports.py)."""
    rows = empty_estimates(10)
    rows["stamp_ns"] = t0 + np.arange(10) * S
    rows["vg_mps"] = [0, 0, 2, 2, 2, 2, 4, 4, 0.1, 0]
    rows["slip_left_pct"][2:8] = [1, 3, 10, 20, -30, 5]
    rows["slip_right_pct"][2:5] = [0, 0, np.nan]
    rows["flags"][2:8] |= int(EstimateFlag.SLIP_LEFT_VALID)
    rows["flags"][2:5] |= int(EstimateFlag.SLIP_RIGHT_VALID)
    rows["flags"][0:2] |= int(EstimateFlag.DEGRADED)
    return rows


def ramp_series(n: int, step_ns: int = S // 10, t0: int = T0) -> np.ndarray:
    """``n`` rows at ``step_ns`` with every float field finite and a smooth ramp in ``vg_mps``."""
    rows = empty_estimates(n)
    rows["stamp_ns"] = t0 + np.arange(n, dtype=np.int64) * step_ns
    names = rows.dtype.names or ()
    for i, name in enumerate(names):
        if rows.dtype[name].kind == "f":
            rows[name] = np.sin(np.arange(n) * 0.01 + i)
    rows["vg_mps"] = 2.0 + np.arange(n) * 1e-4
    rows["flags"] = int(EstimateFlag.GNSS_OK | EstimateFlag.SLIP_LEFT_VALID)
    return rows


def reference_series(t0: int = T0) -> np.ndarray:
    """10 rows, 1 s apart: speed 0 0 1 2 2 3 3 1 0.1 0; the wheel lost on rows 2 and 3."""
    rows = REF.empty_rows(10)
    rows["stamp_ns"] = t0 + np.arange(10) * S
    rows["speed_mps"] = [0, 0, 1, 2, 2, 3, 3, 1, 0.1, 0]
    rows["rim_mps"] = 1.5
    rows["flags"] = REF.flag_mask("WHEEL_OK")
    rows["flags"][2:4] = REF.flag_mask("NO_WHEEL")
    return rows
