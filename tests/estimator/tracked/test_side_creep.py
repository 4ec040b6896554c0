"""A side slope's creep: the hull slides downhill sideways at a slip angle set by gravity's
cross share against the ground's lateral resistance, driven by the filter's roll beyond its
uncertainty (zero on level ground), and learnt with the turns' side-slip gain."""

from __future__ import annotations

import math
from functools import cache

import numpy as np
import pytest

from estimator.config import TrackedConfig
from estimator.sim.tracked import simulate_tracked
from estimator.tracked import TrackedEstimatorConfig
from estimator.tracked.filter import GRAVITY_MPS2, predict
from estimator.tracked.model import N_STATES
from estimator.tracked.model import TrackedState as S
from estimator.tracked.odometer import side_creep
from estimator.tracked.params import VehicleParams
from estimator.tracked.step import TickOut, creep_roll_band, initial_filter, tick_step

from ._ticks import quiet_tick, run_to_first_outage

SECOND = 1_000_000_000


def test_the_creep_is_gravitys_cross_share_over_the_grounds_resistance_beyond_the_band() -> None:
    # right side down 0.08 rad, band 0.006 rad: φ_e = 0.074; left side down likewise
    v = np.array([4.0, -4.0, 4.0, 4.0])
    roll = np.array([0.08, 0.08, -0.08, 0.005])
    band, mu, k_c, gain = np.full(4, 0.006), np.full(4, 0.5), 0.05, np.full(4, 1.2)
    creep, by_gain, by_roll = side_creep(v, roll, band, mu, k_c, gain)
    beyond = 0.05 * 4.0 * math.sin(0.074) / 0.5
    # downhill (right +) whichever way the hull drives; none within the band
    assert creep == pytest.approx([1.2 * beyond, 1.2 * beyond, -1.2 * beyond, 0.0], abs=1e-15)
    assert by_gain == pytest.approx([beyond, beyond, -beyond, 0.0], abs=1e-15)
    slope = 1.2 * 0.05 * 4.0 * math.cos(0.074) / 0.5
    assert by_roll == pytest.approx([slope, slope, slope, 0.0], abs=1e-15)


def test_the_band_is_the_rolls_own_variance() -> None:
    cfg = TrackedEstimatorConfig()
    f = initial_filter(cfg)
    f.P[0, S.ROLL, S.ROLL] = 0.002**2
    # the lateral accelerometer's bias is a state: the roll's variance holds its share
    assert creep_roll_band(f, cfg) == pytest.approx([cfg.creep_roll_sigmas * 0.002], rel=1e-12)


def _driving_north(roll_rad: float, roll_std_rad: float) -> tuple[TickOut, float]:
    """A started filter at 5 m/s due north with ``roll_rad``; one quiet tick of the product.
    Returns the tick's output and how far east the hull moved."""
    cfg = TrackedEstimatorConfig()
    p = VehicleParams.of(TrackedConfig())
    f = initial_filter(cfg)
    f.started[:] = True
    f.x[0, S.SPEED], f.x[0, S.HEADING], f.x[0, S.ROLL] = 5.0, 0.0, roll_rad
    f.P = np.eye(N_STATES)[None] * 1e-8
    f.P[0, S.ROLL, S.ROLL] = roll_std_rad**2
    # the accelerometer reads gravity's cross share of the roll (a straight, no turn)
    lateral = np.array([-GRAVITY_MPS2 * math.sin(roll_rad)])
    out = tick_step(f, quiet_tick(1, SECOND, lateral_accel_mps2=lateral), p, cfg)
    return out, float(f.x[0, S.EAST])


def test_a_side_slopes_roll_moves_the_hull_downhill_and_the_level_ground_not() -> None:
    cfg, mu = TrackedEstimatorConfig(), TrackedConfig().motion.lateral_resistance
    roll = math.atan(0.08)  # an 8 % cross grade, right side down
    out, east = _driving_north(roll, 0.001)
    band = cfg.creep_roll_sigmas * 0.001
    creep = cfg.side_creep * 5.0 * math.sin(roll - band) / mu
    assert out.lateral_mps[0] == pytest.approx(creep, rel=1e-3)
    assert east == pytest.approx(cfg.tick_s * creep, rel=1e-3)
    # a level hull whose roll holds an accelerometer's bias of 0.03 m/s² (3 mrad), its
    # variance the bias's (1σ 0.03 m/s², which the roll cannot tell from a tilt): no creep
    sigma = math.hypot(0.001, cfg.accel_bias_std_mps2 / GRAVITY_MPS2)
    out, east = _driving_north(0.03 / 9.80665, sigma)
    assert out.lateral_mps[0] == 0.0
    assert east == 0.0


def test_the_rolls_uncertainty_reaches_the_position_through_the_creep() -> None:
    x = np.zeros((1, N_STATES))
    x[0, S.SPEED], x[0, S.ROLL] = 5.0, 0.08
    P = np.zeros((1, N_STATES, N_STATES))
    P[0, S.ROLL, S.ROLL] = 0.01**2
    args = (np.zeros(1), np.zeros(1), np.zeros(1), 0.1, np.zeros((1, N_STATES)), None, None)
    _, p_next = predict(x, P, *args, np.full(1, 0.4))
    assert p_next[0, S.EAST, S.EAST] == pytest.approx((0.1 * 0.4 * 0.01) ** 2)
    assert p_next[0, S.EAST, S.ROLL] == pytest.approx(0.1 * 0.4 * 0.01**2)
    _, without = predict(x, P, *args)
    assert without[0, S.EAST, S.EAST] == 0.0


@cache
def _hill_before_outage() -> tuple[np.ndarray, np.ndarray]:
    """``route_firm_hill[3]`` up to its outage: the truth's lateral speed, roll and yaw rate
    ``(n, 3)`` at each row's tick, and the filter's lateral speed ``(n,)``."""
    run = simulate_tracked("route_firm_hill", 3)
    _, out = run_to_first_outage(run)
    rows = np.concatenate([r for _, r in out])
    k = run.index_at(rows["stamp_ns"])
    tr = run.truth
    truth = np.stack([tr.lateral_mps[k], tr.roll_rad[k], tr.yaw_rate_radps[k]], axis=1)
    return truth, np.asarray(rows["lateral_mps"], dtype=np.float64)


def test_on_a_side_slope_the_filters_lateral_speed_follows_the_hulls_creep() -> None:
    truth, lateral = _hill_before_outage()
    # driving straight across a cross grade of over 3 %, after the start
    sloped = (np.abs(truth[:, 1]) > 0.03) & (np.abs(truth[:, 2]) < 0.01) & np.isfinite(lateral)
    sloped[:200] = False
    assert sloped.sum() > 200
    creep, err = truth[sloped, 0], lateral[sloped] - truth[sloped, 0]
    # the creep is a few cm/s; a filter that models none misses all of it
    creep_rms = float(np.sqrt(np.mean(creep**2)))
    assert creep_rms > 0.01
    assert float(np.sqrt(np.mean(err**2))) < 0.5 * creep_rms
