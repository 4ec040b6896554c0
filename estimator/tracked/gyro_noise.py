"""The gyro's own noise, measured while the vehicle stands.

A config names the gyro's data-sheet part, whose figures are typical values: the unit
fitted may be noisier (unit-to-unit spread, temperature, vibration). Standing, the true yaw
rate is zero and the bias barely moves over a tick, so the change of the tick's mean rate
from one standing tick to the next is white noise of variance ``2·ARW²/Δt`` (the mean of
``Δt`` seconds of samples has variance ``ARW²/Δt``). Over ``n`` such pairs with squared
changes summing to ``s``, the unit's ARW² is ``s·Δt/(2n)``, and its ratio to the data
sheet's, blended with a prior of ``gyro_noise_prior_pairs`` pairs at 1,

    r = (n₀ + n·ARW²_unit/ARW²_sheet) / (n₀ + n),   clipped to [1, gyro_noise_ratio_max],

scales the heading's and the gyro bias's process noise (``ARW²·Δt``, ``walk²·Δt``): the bias
walk taken as worse by the same ratio as the white noise (both grow with the unit's spread,
its temperature and vibration; the bias walk cannot be measured over a stop). Never below
the data sheet: a few seconds of standing cannot tell a quieter unit from luck.

``stats (k, 3)`` per vehicle: the last standing tick's mean rate (NaN if the last tick did not
stand), the sum of squared changes ``s`` (rad²/s²) and the pair count ``n``.
"""

from __future__ import annotations

import numpy as np

from estimator._arrays import BoolArray, FloatArray
from estimator.tracked.params import VehicleParams
from estimator.tracked.settings import TrackedEstimatorConfig

__all__ = ["LAST", "PAIRS", "SUM_SQ", "initial_stats", "learn_standing", "noise_ratio"]

LAST, SUM_SQ, PAIRS = 0, 1, 2


def initial_stats(k: int) -> FloatArray:
    """``(k, 3)``: no standing tick seen."""
    stats = np.zeros((k, 3))
    stats[:, LAST] = np.nan
    return stats


def learn_standing(stats: FloatArray, gyro_radps: FloatArray, still: BoolArray) -> FloatArray:
    """``stats`` after a tick whose mean rates are ``gyro_radps (k,)``, standing where
    ``still (k,)``: a pair counted where this and the last tick both stood."""
    out = stats.copy()
    d = gyro_radps - stats[:, LAST]
    pair = still & np.isfinite(d)
    out[:, SUM_SQ] += np.where(pair, d * d, 0.0)
    out[:, PAIRS] += pair
    out[:, LAST] = np.where(still & np.isfinite(gyro_radps), gyro_radps, np.nan)
    return out


def noise_ratio(stats: FloatArray, p: VehicleParams, cfg: TrackedEstimatorConfig) -> FloatArray:
    """``r (k,)`` of the module docstring: the unit's ARW² over the data sheet's."""
    n = stats[:, PAIRS]
    arw2 = stats[:, SUM_SQ] * cfg.tick_s / np.maximum(2.0 * n, 1.0)
    measured = arw2 / p.gyro_arw_rad_rt_s**2
    n0 = cfg.gyro_noise_prior_pairs
    blended = (n0 + n * measured) / np.maximum(n0 + n, 1e-12)
    return np.clip(blended, 1.0, cfg.gyro_noise_ratio_max)
