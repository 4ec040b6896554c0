"""The receiver's clock in the tracked filter: a fix stamped on the receiver's clock is
compared with the antenna where it was when the fix was taken, its age on the stamps, the
predicted state's lead past its tick (the IMU samples' mean instant) and the receiver's
clock less the IMU's (a state, learnt beside GNSS)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from estimator.base import ImuBatch
from estimator.config import TrackedConfig, TrackedGeometry
from estimator.sim.tracked import TrackedRun, simulate_tracked
from estimator.tracked import TrackedEstimatorConfig, TrackedMode
from estimator.tracked.model import N_STATES
from estimator.tracked.model import TrackedState as S
from estimator.tracked.params import VehicleParams
from estimator.tracked.step import _fuse_gnss, initial_filter, state_lead_s
from estimator.tracked.vehicle import VehicleInputs
from tests.estimator.tracked._ticks import quiet_tick, rows_over

SPEED_MPS, HEADING_RAD, YAW_RADPS, ACCEL_MPS2 = 10.0, 0.4, 0.3, 0.5
LEVER_M = (0.3, 1.2, 2.0)  # antenna right, ahead, up of the hull centre


def _antenna(clock_s: float, age_s: float) -> tuple[np.ndarray, np.ndarray]:
    """By hand: where the antenna was ``age + clock`` before the tick, and its velocity
    then, for a hull at the origin turning at ``YAW_RADPS`` (counter-clockwise) and speeding
    up at ``ACCEL_MPS2``, level, with no side-slip."""
    x_a, y_a, _ = LEVER_M
    s, c = math.sin(HEADING_RAD), math.cos(HEADING_RAD)
    vf, vr = SPEED_MPS + YAW_RADPS * x_a, -YAW_RADPS * y_a
    u = np.array([vf * s + vr * c, vf * c - vr * s])
    fwd = ACCEL_MPS2 + YAW_RADPS * vr
    rate = np.array([fwd * s - YAW_RADPS * vf * c, fwd * c + YAW_RADPS * vf * s])
    tau = age_s + clock_s
    at_tick = np.array([x_a * c + y_a * s, -x_a * s + y_a * c])
    return at_tick - tau * u, u - tau * rate


def _fused(
    clock_s: float,
    age_s: float,
    fix_clock_s: float,
    mode: TrackedMode,
    imu_age_s: float = 0.05,
) -> tuple[np.ndarray, np.ndarray]:
    """The state before and after one fix taken ``age + fix_clock_s`` before the state, the
    filter's clock at ``clock_s`` (1-sigma 50 ms); the tick's IMU samples ``imu_age_s``
    before it on average (0.05 s: the state stands at the tick)."""
    cfg = TrackedEstimatorConfig(mode=mode, gnss_gate_nis=1e9)
    geo = TrackedGeometry(antenna_lever_arm_m=LEVER_M)
    p = VehicleParams.of(TrackedConfig(geometry=geo))
    f = initial_filter(cfg)
    f.started[:] = True
    f.x[0, S.HEADING], f.x[0, S.SPEED], f.x[0, S.GNSS_CLOCK] = HEADING_RAD, SPEED_MPS, clock_s
    diag = np.full(N_STATES, 1e-4)
    diag[S.GNSS_CLOCK] = 0.05**2 if mode == TrackedMode.PRODUCT else 0.0
    f.P = np.diag(diag)[None]
    before = f.x[0].copy()
    pos, vel = _antenna(fix_clock_s, age_s)
    inp = quiet_tick(
        1,
        100_000_000,
        accel_mps2=np.array([ACCEL_MPS2]),
        gnss_pos_pair_m=pos[None],
        gnss_vel_pair_mps=vel[None],
        gnss_vel_std_mps=np.array([0.03]),
        gnss_age_s=np.array([age_s]),
        imu_age_s=np.array([imu_age_s]),
    )
    lateral = (np.zeros(1), None, None)
    used, _, _ = _fuse_gnss(f, inp, p, cfg, lateral, np.array([YAW_RADPS]), np.zeros(1, bool))
    assert used[0]
    return before, np.asarray(f.x[0])


@pytest.mark.parametrize("age_s", [0.0, 0.01, 0.07])
def test_a_fix_where_the_antenna_was_at_its_age_plus_the_clock_moves_nothing(
    age_s: float,
) -> None:
    before, after = _fused(0.06, age_s, 0.06, TrackedMode.PRODUCT)
    moved = np.abs(after - before)
    assert moved.max() < 1e-9, S(int(np.argmax(moved))).name


def test_the_state_stands_half_a_tick_past_its_imu_samples_mean_instant() -> None:
    cfg = TrackedEstimatorConfig()
    inputs = VehicleInputs(TrackedConfig(), cfg)
    t0 = 1_000_000_000
    stamps = t0 + 10_000_000 * np.arange(1, 21)  # 100 Hz; the first tick ends at t0 + 110 ms
    inputs.push_imu(ImuBatch(stamps, np.zeros((20, 3)), np.zeros((20, 3))))
    ticks = inputs.due(int(stamps[-1]))
    got = inputs.take(ticks)
    # ten samples 10 ms apart ending at the tick lie 45 ms before it on average; Δ·mean
    # integrates 95 ms before it to 5 ms after it
    np.testing.assert_allclose(got.imu_age_s, 0.045, atol=1e-12)
    np.testing.assert_allclose(state_lead_s(got, cfg.tick_s), 0.005, atol=1e-12)
    none = quiet_tick(2, t0, imu_age_s=np.array([np.nan, 0.02]))
    np.testing.assert_allclose(state_lead_s(none, cfg.tick_s), [0.0, 0.03], atol=1e-12)


def test_a_fix_where_the_antenna_was_before_the_state_it_leads_moves_nothing() -> None:
    # samples ending at the tick: the state stands 5 ms past it, so a fix 10 ms old on the
    # stamps with the clock at 60 ms was taken 75 ms before the state
    before, after = _fused(0.06, 0.01, 0.065, TrackedMode.PRODUCT, imu_age_s=0.045)
    moved = np.abs(after - before)
    assert moved.max() < 1e-9, S(int(np.argmax(moved))).name
    # the same fix read as taken 70 ms before (the lead left out) moves the clock to it
    _, stale = _fused(0.06, 0.01, 0.06, TrackedMode.PRODUCT, imu_age_s=0.045)
    assert stale[S.GNSS_CLOCK] < 0.06 - 0.0025


def test_a_fix_older_than_the_filter_says_moves_the_clock_toward_it() -> None:
    # taken 40 ms before the filter's clock says: the position is behind along the course
    # and the velocity is the turn's, 40 ms earlier; the clock learns most of it in one fix
    _, after = _fused(0.02, 0.01, 0.06, TrackedMode.PRODUCT)
    assert 0.02 + 0.5 * 0.04 < after[S.GNSS_CLOCK] < 0.06 + 0.005
    # without the state (paper modes) the fix is compared with the antenna at its age alone
    _, paper = _fused(0.0, 0.01, 0.04, TrackedMode.PAPER)
    assert paper[S.GNSS_CLOCK] == 0.0
    assert abs(paper[S.EAST]) + abs(paper[S.NORTH]) > 0.1  # the hull pulled back instead


def test_the_clock_is_a_product_state_from_its_prior() -> None:
    cfg = TrackedEstimatorConfig()
    f = initial_filter(cfg)
    assert f.x[0, S.GNSS_CLOCK] == 0.0
    assert math.isclose(f.P[0, S.GNSS_CLOCK, S.GNSS_CLOCK], cfg.gnss_clock_offset_std_s**2)
    assert 0.1 <= cfg.gnss_clock_offset_std_s <= 0.2
    paper = initial_filter(TrackedEstimatorConfig(mode=TrackedMode.PAPER))
    assert paper.P[0, S.GNSS_CLOCK, S.GNSS_CLOCK] == 0.0
    with pytest.raises(ValueError):
        TrackedEstimatorConfig(gnss_clock_offset_std_s=-0.1)


def _clocked(offset_s: float) -> TrackedRun:
    """``route_firm[5]`` (not a bench seed) with the receiver ``offset_s`` ahead of the IMU."""
    run = simulate_tracked("route_firm", 5)
    spec = dataclasses.replace(run.sensors, gnss_clock_offset_s=offset_s)
    return simulate_tracked("route_firm", 5, sensors=spec)


@pytest.mark.parametrize("offset_s", [0.08, -0.06])
def test_the_receivers_clock_is_learnt_before_the_outage(offset_s: float) -> None:
    run = _clocked(offset_s)
    rows = rows_over(run, TrackedEstimatorConfig(), 149.0)
    idx = run.index_at(rows["stamp_ns"])
    late = (rows["stamp_ns"] > run.start_ns + 100_000_000_000) & (run.truth.speed_mps[idx] > 8.0)
    # the hull where it was at its stamp: the along-track error a receiver's lead makes,
    # offset·V (0.6-0.9 m at 10-12 m/s), is gone
    err = np.hypot(rows["east_m"] - run.truth.east_m[idx], rows["north_m"] - run.truth.north_m[idx])
    assert np.median(err[late]) < 0.25 * abs(offset_s) * 10.0
