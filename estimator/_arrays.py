"""Array helpers shared by the fleet front end and engine: the same results as their numpy
counterparts in fewer array calls (each numpy call costs microseconds on the small arrays of
one assembly, whatever their size)."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

__all__ = ["nan_to_num"]

_F64_MAX = float(np.finfo(np.float64).max)


def nan_to_num(x: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """``np.nan_to_num(x)`` of a float array (NaN → 0, ±inf → ± the largest float) in three
    array calls instead of its dozen."""
    return np.where(np.isfinite(x), x, np.where(np.isnan(x), 0.0, np.copysign(_F64_MAX, x)))
