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
the data sheet: a few seconds of standing cannot tell a quieter unit from luck. A vehicle
whose config turns the measurement off (``VehicleParams.gyro_noise_measured`` 0) keeps
``r = 1`` and counts no pair.

``stats (k, 3)`` per vehicle: the last standing tick's mean rate (NaN if the last tick did not
stand), the sum of squared changes ``s`` (rad²/s²) and the pair count ``n``.

As a calibration (the rows' ``gyro_arw_deg_rt_h`` and its 1-sigma, :func:`arw_fields`) the
unit's ARW is ``√(s·Δt/(2n))`` in °/√h, the measurement alone (the data sheet is the config's),
NaN before the first pair; its 1-sigma ``ARW·√(3/(4n))``: the mean of ``n`` squared changes
is known to ``√(3/n)`` of itself, not ``√(2/n)``, because a run of standing ticks makes
overlapping pairs (``m₂ − m₁`` and ``m₃ − m₂`` share ``m₂``: correlation −½, so neighbouring
squares covary by ``σ⁴/2``), and its root to half that. Both together give ``n`` and ``s``
back (:func:`stats_from_fields`), independent of the data sheet, so a stored measurement goes
on against whatever part the config names when it is restored.
"""

from __future__ import annotations

import math

import numpy as np

from estimator._arrays import BoolArray, FloatArray
from estimator.tracked.params import VehicleParams
from estimator.tracked.settings import TrackedEstimatorConfig

__all__ = [
    "LAST",
    "PAIRS",
    "SUM_SQ",
    "arw_fields",
    "initial_stats",
    "learn_standing",
    "noise_ratio",
    "stats_from_fields",
]

LAST, SUM_SQ, PAIRS = 0, 1, 2

_DEG_RT_H_PER_RAD_RT_S = math.degrees(1.0) * 60.0
"""An ARW of 1 rad/√s in °/√h (√3600 s in an hour)."""

_REL_VAR_PER_PAIR = 3.0
"""``n`` times the relative variance of the mean of ``n`` overlapping pairs' squared changes."""


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
    ratio = np.clip(blended, 1.0, cfg.gyro_noise_ratio_max)
    return np.where(p.gyro_noise_measured > 0.0, ratio, 1.0)


def arw_fields(stats: FloatArray, cfg: TrackedEstimatorConfig) -> tuple[FloatArray, FloatArray]:
    """The unit's ARW measured standing and its 1-sigma, °/√h, ``(k,)`` each (module
    docstring); NaN where no pair was counted."""
    n = stats[:, PAIRS]
    some = n > 0.0
    pairs = np.where(some, n, 1.0)
    arw = np.sqrt(stats[:, SUM_SQ] * cfg.tick_s / (2.0 * pairs)) * _DEG_RT_H_PER_RAD_RT_S
    std = arw * np.sqrt(_REL_VAR_PER_PAIR / (4.0 * pairs))
    return np.where(some, arw, np.nan), np.where(some, std, np.nan)


def stats_from_fields(
    arw_deg_rt_h: FloatArray, std_deg_rt_h: FloatArray, cfg: TrackedEstimatorConfig
) -> FloatArray:
    """``stats (k, 3)`` that give ``arw_deg_rt_h`` and ``std_deg_rt_h (k,)`` back through
    :func:`arw_fields`: ``n = (3/4)·(ARW/σ)²`` (rounded: pairs are counted) and ``s =
    2n·ARW²/Δt``; no last standing tick. A value that is not finite and positive, or a std
    that is not, gives no pair (an ARW of exactly 0, which no real gyro's standing ticks
    give, cannot say its count)."""
    value = np.asarray(arw_deg_rt_h, dtype=np.float64)
    std = np.asarray(std_deg_rt_h, dtype=np.float64)
    ok = np.isfinite(value) & np.isfinite(std) & (value > 0.0) & (std > 0.0)
    safe_std = np.where(ok, std, 1.0)
    n = np.where(ok, np.round(_REL_VAR_PER_PAIR / 4.0 * (value / safe_std) ** 2), 0.0)
    arw_rad = np.where(ok, value, 0.0) / _DEG_RT_H_PER_RAD_RT_S
    stats = initial_stats(value.shape[0])
    stats[:, PAIRS] = n
    stats[:, SUM_SQ] = 2.0 * n * arw_rad**2 / cfg.tick_s
    return stats
