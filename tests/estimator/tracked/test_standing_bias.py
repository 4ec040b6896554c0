"""The zero-rate update while standing weighs a tick's mean rate by the gyro's own noise
(:func:`estimator.tracked.step.standing_rate_var`): a stop pins the bias as well as its
samples allow, ``√r·ARW/√T``, once the hull has stopped turning
(:func:`estimator.tracked.step.hull_settled`)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from estimator.config import TrackedConfig
from estimator.gyro import ADIS16470
from estimator.tracked import TrackedEstimatorConfig
from estimator.tracked.model import TrackedState as S
from estimator.tracked.params import VehicleParams
from estimator.tracked.step import initial_filter, standing_rate_var, tick_step
from estimator.tracked.vehicle import TickInputs
from tests.estimator.tracked._ticks import quiet_tick


def _standing_tick(gyro_radps: float, tick_ns: int) -> TickInputs:
    """One tick of a crawler standing still with its engine running and GNSS lost."""
    one = np.ones(1)
    return quiet_tick(
        1,
        tick_ns,
        gyro_radps=gyro_radps * one,
        odometer_mps=0.0 * one,
        odometer_lag_s=0.05 * one,
        sprocket_pair_mps=np.zeros((1, 2)),
        sprocket_missing=np.zeros(1, dtype=bool),
        sprocket_before_pair_mps=np.zeros((1, 2)),
        steady_s=10.0 * one,
    )


def test_a_ticks_standing_rate_varies_by_the_gyros_white_noise_over_the_tick() -> None:
    p = VehicleParams.stack([VehicleParams.of(TrackedConfig())] * 2)
    var = standing_rate_var(p, np.array([1.0, 2.5]), 0.1)
    arw2 = ADIS16470.arw_rad_rt_s**2
    assert var == pytest.approx([arw2 / 0.1, 2.5 * arw2 / 0.1])


def _stop(seconds: float, bias_radps: float, seed: int) -> tuple[float, float]:
    """A started filter standing ``seconds`` on an ADIS16470 whose bias is ``bias_radps``:
    the bias's estimate error and 1-sigma at the end."""
    cfg = TrackedEstimatorConfig()
    p = VehicleParams.stack([VehicleParams.of(TrackedConfig())])
    f = initial_filter(cfg)
    f.started[:] = True
    f.x[0, [S.EAST, S.NORTH, S.HEADING, S.SPEED]] = 0.0
    f.P[0, [S.EAST, S.NORTH], [S.EAST, S.NORTH]] = 1.0
    f.P[0, S.HEADING, S.HEADING] = 1e-4
    rng = np.random.default_rng(seed)
    tick_std = ADIS16470.arw_rad_rt_s / np.sqrt(cfg.tick_s)
    n = round(seconds / cfg.tick_s)
    for k in range(n):
        gyro = bias_radps + tick_std * rng.standard_normal()
        tick_step(f, _standing_tick(gyro, (k + 1) * 100_000_000), p, cfg)
    return float(f.x[0, S.GYRO_BIAS] - bias_radps), float(np.sqrt(f.P[0, S.GYRO_BIAS, S.GYRO_BIAS]))


def test_a_stop_pins_the_gyro_bias_as_well_as_its_samples_allow() -> None:
    # 6 s standing: the mean of 600 samples of an ADIS16470 knows its bias to ARW/√6 s
    # (about 40 µrad/s); a fixed 1 mrad/s per tick would leave about 130 µrad/s
    seconds = 6.0
    floor = ADIS16470.arw_rad_rt_s / np.sqrt(seconds)
    runs = [_stop(seconds, 4e-4, seed) for seed in range(40)]
    err = np.array([e for e, _ in runs])
    std = np.array([s for _, s in runs])
    assert np.all(std < 1.3 * floor)
    assert np.all(std > 0.9 * floor)
    # the stated 1-sigma is what the errors show over 40 stops
    assert np.sqrt(np.mean(err**2)) == pytest.approx(np.mean(std), rel=0.35)


def test_a_hull_still_turning_after_its_stop_is_not_read_as_the_gyros_bias() -> None:
    # braked to a stop, the hull keeps turning at the rate its tracks' last speeds gave it,
    # dying out with its lag τ: the first ticks' mean rate is that turn, not the bias
    cfg = TrackedEstimatorConfig()
    p = VehicleParams.stack([VehicleParams.of(TrackedConfig())])
    f = initial_filter(cfg)
    f.started[:] = True
    f.x[0, [S.EAST, S.NORTH, S.HEADING, S.SPEED]] = 0.0
    f.x[0, S.ACCEL_LAG] = 0.4
    bias, yaw0 = 2e-4, 3e-3
    prior = float(np.sqrt(f.P[0, S.GYRO_BIAS, S.GYRO_BIAS]))
    for k in range(30):  # 3 s standing, the hull's yaw decaying from 3 mrad/s
        t = (k + 1) * cfg.tick_s
        tick = _standing_tick(bias + yaw0 * np.exp(-t / 0.4), (k + 1) * 100_000_000)
        tick = dataclasses.replace(tick, steady_s=np.array([t]))
        tick_step(f, tick, p, cfg)
        if t < 5 * 0.4 - 1e-9:  # not settled: the bias is not learnt from these ticks
            assert np.sqrt(f.P[0, S.GYRO_BIAS, S.GYRO_BIAS]) == pytest.approx(prior, rel=1e-3)
    # settled for 1 s: learnt from the still hull, within a few µrad/s of the bias
    assert np.sqrt(f.P[0, S.GYRO_BIAS, S.GYRO_BIAS]) < 0.5 * prior
    assert abs(f.x[0, S.GYRO_BIAS] - bias) < 2e-5
