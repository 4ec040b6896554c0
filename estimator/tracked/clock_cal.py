"""The receiver's clock as a calibration: the filter's ``GNSS_CLOCK`` out to the rows and back.

The clock ``c`` (s, the receiver's clock less the IMU's, :class:`~estimator.tracked.model.
TrackedState`) is a state of the product filter, learnt beside GNSS. As a calibration its
value and 1-sigma are the state's mean and ``√P[c, c]`` (NaN in the paper modes, which hold
it at 0 without variance). Restored, a stored clock is the state's prior: mean ``c₀`` and
variance ``σ₀²``, its covariance with every other state 0 (nothing else is known of how it was
learnt); reset, the config's prior again (0 ± ``gnss_clock_offset_std_s``).
"""

from __future__ import annotations

import numpy as np

from estimator._arrays import FloatArray
from estimator.tracked.model import TrackedState as S
from estimator.tracked.settings import TrackedEstimatorConfig
from estimator.tracked.step import Filter

__all__ = ["clock_fields", "reset_clock", "restore_clock"]


def clock_fields(f: Filter, cfg: TrackedEstimatorConfig) -> tuple[FloatArray, FloatArray]:
    """``(c (k,), σ (k,))`` in seconds of the ``k`` vehicles of ``f``; NaN outside the product
    mode."""
    if not cfg.learns:
        nan = np.full(f.x.shape[0], np.nan)
        return nan, nan.copy()
    std = np.sqrt(np.maximum(f.P[:, S.GNSS_CLOCK, S.GNSS_CLOCK], 0.0))
    return f.x[:, S.GNSS_CLOCK].copy(), std


def _set_prior(f: Filter, value_s: float, std_s: float) -> None:
    """The clock of ``f``'s vehicles set to ``value_s ± std_s``, uncorrelated with the rest."""
    c = S.GNSS_CLOCK
    x, P = f.x.copy(), f.P.copy()
    x[:, c] = value_s
    P[:, c, :] = 0.0
    P[:, :, c] = 0.0
    P[:, c, c] = std_s * std_s
    f.x, f.P = x, P


def restore_clock(f: Filter, cfg: TrackedEstimatorConfig, value_s: float, std_s: float) -> bool:
    """Go on from a stored clock (``value_s``, ``std_s``: a row's fields) as the prior of the
    clock state of ``f`` (one vehicle); nothing outside the product mode or where the two are
    not a finite value and a finite positive 1-sigma. Whether it was restored."""
    ok = bool(np.isfinite(value_s) and np.isfinite(std_s) and std_s > 0.0)
    if ok and cfg.learns:
        _set_prior(f, float(value_s), float(std_s))
        return True
    return False


def reset_clock(f: Filter, cfg: TrackedEstimatorConfig) -> None:
    """The clock state of ``f`` back to the config's prior, 0 ± ``gnss_clock_offset_std_s``
    (0 without variance outside the product mode, as :func:`~estimator.tracked.step.
    initial_filter` starts it)."""
    _set_prior(f, 0.0, cfg.gnss_clock_offset_std_s if cfg.learns else 0.0)
