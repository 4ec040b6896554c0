"""The crawler simulator on ground that is not flat: attitude, specific force, body rates,
along-ground distance, GNSS height, slip on grades, and the terrain's own draws."""

from __future__ import annotations

import dataclasses
from functools import cache

import numpy as np
import pytest

from estimator.sim.tracked import TrackedRun, simulate_route, simulate_tracked
from estimator.sim.tracked.physics import GRAVITY_MPS2, RATE_HZ, integrate_route
from estimator.sim.tracked.route import RANDOM_RANGES, SOFT
from estimator.sim.tracked.sensors import body_rates, tilt_bias_walk
from estimator.sim.tracked.terrain import FLAT, TERRAIN_RANGES, hill_terrain, random_terrain
from estimator.tracked.model import MotionState
from estimator.types import GnssSample, ImuBatch, OdometerEdges, SprocketEdges

M = MotionState
G = GRAVITY_MPS2


@cache
def _run(name: str, seed: int, flat: bool = False) -> TrackedRun:
    return simulate_tracked(name, seed, flat=flat)


def _imu(run: TrackedRun) -> tuple[np.ndarray, np.ndarray]:
    batches = [m for _, m in run.measurements if isinstance(m, ImuBatch)]
    return np.concatenate([b.accel_mps2 for b in batches]), np.concatenate(
        [b.gyro_radps for b in batches]
    )


def _fixes(run: TrackedRun) -> list[GnssSample]:
    return [m for _, m in run.measurements if isinstance(m, GnssSample) and np.isfinite(m.lat_deg)]


def test_named_level_routes_stay_level() -> None:
    run = _run("route_firm", 1)
    assert run.route.terrain == FLAT
    assert not run.truth.pitch_rad.any() and not run.truth.roll_rad.any()
    accel, _ = _imu(run)
    assert np.all(np.abs(accel[:, 2] - G) < 0.5)  # gravity on z alone, within the noise


def test_a_random_routes_terrain_leaves_its_other_draws_alone() -> None:
    sloped, level = _run("random", 1003), _run("random", 1003, True)
    assert sloped.route.segments == level.route.segments
    assert sloped.route.ground == level.route.ground
    assert not sloped.route.terrain.flat and level.route.terrain.flat
    # the gearbox and the sprockets do not feel the grade: their edges are the same
    for kind in (OdometerEdges, SprocketEdges):
        a = [m.stamp_ns for _, m in sloped.measurements if isinstance(m, kind)]
        b = [m.stamp_ns for _, m in level.measurements if isinstance(m, kind)]
        assert len(a) == len(b) and all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    # while the hull's ground speed does (the slip feels the grade)
    assert not np.allclose(sloped.truth.speed_mps, level.truth.speed_mps)


def test_random_terrain_draws_within_its_stated_ranges() -> None:
    tops, crosses = [], []
    for k in range(200):
        t = random_terrain(np.random.default_rng(k), 5000.0)
        g, c = np.abs(t.grade), np.abs(t.cross)
        tops.append(g.max())
        crosses.append(c.max())
        gaps = np.diff(t.grade_at_m)
        lo, hi = TERRAIN_RANGES["grade_spacing_m"]
        assert gaps.min() >= lo and gaps.max() <= hi
    assert max(tops) <= TERRAIN_RANGES["grade_max"][1] and max(crosses) <= 0.10
    assert min(tops) >= 0.8 * TERRAIN_RANGES["grade_max"][0]  # each route has some hill
    d = np.linspace(0.0, 5000.0, 20001)
    g = t.grade_of(d)
    assert np.abs(np.diff(g)).max() < 0.01  # smooth between knots: no steps


def test_the_grade_at_one_distance_is_the_grade_of_the_array() -> None:
    for t in (hill_terrain(), random_terrain(np.random.default_rng(7)), FLAT):
        d = np.random.default_rng(1).uniform(-10.0, 21_000.0, 2000)
        d[:3] = (0.0, 40.0, 1e6)  # a knot, and beyond the last
        assert np.array_equal(t.grade_of(d), [t.grade_at(float(x)) for x in d])


def test_hill_route_has_ten_percent_grades_and_a_four_minute_outage() -> None:
    run = _run("route_firm_hill", 1)
    grade = np.tan(run.truth.pitch_rad)
    assert 0.099 < grade.max() <= 0.1 and -0.1 <= grade.min() < -0.099
    assert np.abs(np.tan(run.truth.roll_rad)).max() <= 0.05 + 1e-12
    assert run.route.outages_s[0][1] == 240.0
    k = run.index_at(np.array(run.outages_ns[0]))
    assert run.distance_m()[k[1]] - run.distance_m()[k[0]] > 1000.0


def test_horizontal_distance_is_the_along_ground_distance_times_cos_pitch() -> None:
    run = _run("route_firm_hill", 1)
    tr, dt = run.truth, 1.0 / RATE_HZ
    along = np.sum(tr.speed_mps) * dt
    level = np.sum(tr.speed_mps * np.cos(tr.pitch_rad)) * dt
    horizontal = run.distance_m()[-1]
    assert abs(horizontal - level) / level < 2e-3
    assert along - horizontal > 0.003 * along  # ±10 % grades: ~0.5 % of the way is climbing
    climb = np.cumsum(tr.speed_mps * np.sin(tr.pitch_rad)) * dt
    assert np.allclose(tr.up_m, climb, atol=0.05 + 1e-3 * np.abs(climb).max())


def test_the_accelerometer_reads_gravity_along_the_slope() -> None:
    run = _run("route_firm_hill", 1)
    tr = run.truth
    accel, _ = _imu(run)
    n = min(accel.shape[0], tr.t_s.size - 1)
    dv = np.gradient(tr.speed_mps, 1.0 / RATE_HZ)[1 : n + 1]
    theta, phi = tr.pitch_rad[1 : n + 1], tr.roll_rad[1 : n + 1]
    straight = (tr.state[1 : n + 1] == int(M.STRAIGHT)) & (
        np.abs(tr.yaw_rate_radps[1 : n + 1]) < 1e-3
    )
    fwd = accel[:n, 1] - dv - G * np.sin(theta)
    # what is left is the accelerometer's bias and noise, not the grade
    assert abs(np.mean(fwd[straight]) - run.errors.accel_bias_mps2[1]) < 0.01
    assert np.std(fwd[straight]) < 0.1
    up = accel[:n, 2] - G * np.cos(theta) * np.cos(phi)
    assert abs(np.mean(up[straight])) < 0.02
    side = accel[:n, 0] + G * np.cos(theta) * np.sin(phi) - run.errors.accel_bias_mps2[0]
    assert abs(np.mean(side[straight])) < 0.02
    uphill = straight & (theta > 0.09)
    assert np.mean(accel[:n, 1][uphill] - dv[uphill]) > 0.9  # ~ g·0.1 over the hull's own


def test_the_gyros_see_the_pitch_and_roll_changes() -> None:
    run = _run("route_firm_hill", 2)
    tr = run.truth
    rates = body_rates(tr)
    dt = 1.0 / RATE_HZ
    # Euler rates back from the body rates: θ̇ = ω_x·cos φ + ω_z·sin φ
    d_theta = rates[:, 0] * np.cos(tr.roll_rad) + rates[:, 2] * np.sin(tr.roll_rad)
    assert np.allclose(np.cumsum(d_theta) * dt, tr.pitch_rad - tr.pitch_rad[0], atol=2e-3)
    _, gyro = _imu(run)
    n = min(gyro.shape[0], tr.t_s.size - 1)
    err = gyro[:n, 0] - rates[1 : n + 1, 0]
    assert np.std(err) < 0.01 and abs(np.mean(err)) < 3e-3  # noise and a turn-on bias only
    assert np.abs(rates[:, 0]).max() > 0.05  # the ramps pitch the hull at tens of mrad/s


def test_uphill_slips_more_than_downhill() -> None:
    run = _run("route_firm_hill", 1)
    tr = run.truth
    steady = (tr.state == int(M.STRAIGHT)) & (np.abs(np.gradient(tr.gearbox_mps)) < 1e-4)
    slip = tr.slip.mean(axis=1)
    up, down = steady & (tr.pitch_rad > 0.09), steady & (tr.pitch_rad < -0.09)
    assert up.sum() > 500 and down.sum() > 500
    # drawbar demand g·sin θ: 0.3 slip per g on firm ground gives ±3 points at ±10 %
    gap = np.nanmean(slip[up]) - np.nanmean(slip[down])
    assert 0.04 < gap < 0.08


def test_the_slip_is_loaded_by_the_hulls_own_acceleration() -> None:
    # soft ground over the hill route's grades, without the slip's texture and patches:
    # the drawbar pull accelerates the hull, so on a straight at a steady gearbox a grade's
    # change moves the slip, the slip slows or speeds the hull, and that acceleration loads
    # the slip again: s = rolling + k·(a_h + g·sin θ)/g with a_h the hull's, not the gearbox's
    named = _run("route_firm_hill", 1)
    ground = dataclasses.replace(SOFT, texture_std=0.0, patch_std=0.0)
    route = dataclasses.replace(named.route, ground=ground)
    tr = integrate_route(route, named.config, np.random.default_rng(1))
    dt, tau = 1.0 / RATE_HZ, 0.4  # the hull's lag (s)
    vs, u = tr.sprocket_mps[:, 0], tr.track_mps
    # each track's ground speed lags the speed its slip drives it to: ū = u + τ·du/dt
    driven_to = u[1:] + tau * np.diff(u, axis=0) / dt
    ubar = driven_to.mean(axis=1)
    slip = (vs[1:] - ubar) / np.maximum(np.maximum(vs[1:], ubar), 1e-3)
    a_hull = np.diff(tr.speed_mps) / dt
    # straight, the sprockets unchanged over the last 3 s (the hull has caught up with them)
    changed = np.concatenate([[False], np.any(np.diff(tr.sprocket_mps, axis=0) != 0.0, axis=1)])
    recent = np.convolve(changed, np.ones(3 * RATE_HZ))[: changed.size] > 0.0
    steady = (
        (tr.state[1:] == int(M.STRAIGHT))
        & (tr.sprocket_mps[1:, 0] == tr.sprocket_mps[1:, 1])
        & ~recent[1:]
        & (vs[1:] > 1.0)
    )
    k = ground.accel_slip_per_g / G
    from_grade = ground.rolling_slip + k * G * np.sin(tr.pitch_rad[1:])
    from_hull = k * a_hull
    assert steady.sum() > 5000
    # the hull's acceleration at steady sprockets is the grades' doing, and not small
    assert np.percentile(np.abs(from_hull[steady]), 90) > 5e-3
    # the slip follows it as the equation says, to rounding
    left = slip[steady] - from_grade[steady] - from_hull[steady]
    assert np.abs(left).max() < 1e-9
    # (loaded by the gearbox's acceleration instead, the slip would not move with it: slope 0)
    fit = np.polyfit(from_hull[steady], slip[steady] - from_grade[steady], 1)[0]
    assert abs(fit - 1.0) < 1e-6


def _mast_climb(run: TrackedRun) -> np.ndarray:
    """By hand: the antenna's up velocity over the hull centre's on the truth's grid, the
    rate of its lever arm's height ``z·cos θ·cos φ + y·sin θ − x·sin φ`` by the chain rule
    (the pitch's and roll's rates by differences)."""
    x, y, z = run.config.geometry.antenna_lever_arm_m
    theta, phi = run.truth.pitch_rad, run.truth.roll_rad
    d_theta, d_phi = np.gradient(theta, 1.0 / RATE_HZ), np.gradient(phi, 1.0 / RATE_HZ)
    ct, st, cp, sp = np.cos(theta), np.sin(theta), np.cos(phi), np.sin(phi)
    return np.asarray(
        -z * (st * cp * d_theta + ct * sp * d_phi) + y * ct * d_theta - x * cp * d_phi
    )


def test_gnss_height_and_up_velocity_follow_the_climb() -> None:
    run = _run("route_firm_hill", 1)
    fixes = _fixes(run)
    k = run.index_at(np.array([f.stamp_ns for f in fixes]))
    vu = np.array([f.vel_enu_mps[2] for f in fixes])
    true_vu = run.truth.speed_mps[k] * np.sin(run.truth.pitch_rad[k]) + _mast_climb(run)[k]
    assert np.sqrt(np.mean((vu - true_vu) ** 2)) < 0.05
    h = np.array([f.height_m for f in fixes])
    # the antenna's height: the hull's climb plus its lever arm (mostly up)
    z = run.config.geometry.antenna_lever_arm_m[2]
    assert np.abs(h - run.frame.h0_m - run.truth.up_m[k] - z).max() < 0.5
    assert np.ptp(h) > 5.0


@pytest.mark.parametrize(("name", "seed"), [("route_firm_hill", 1), ("random", 1001)])
def test_the_fixes_velocity_is_the_derivative_of_their_positions(name: str, seed: int) -> None:
    # without the receiver's noise, at the instants the fixes were taken (a random route's
    # receiver has a clock offset and an epoch jitter): the antenna's velocity less the hull
    # centre's against the central difference of its position less the hull centre's over
    # the neighbouring fixes (0.2 s), in the ENU frame. (The hull's own path is rough at a
    # tenth of a second: its slip's texture moves its difference by up to 4 cm/s.)
    quiet = dataclasses.replace(_run(name, seed).sensors, gnss_pos_std_m=0.0, gnss_vel_std_mps=0.0)
    run = simulate_tracked(name, seed, sensors=quiet)
    fixes = _fixes(run)
    taken_s = (np.array([f.stamp_ns for f in fixes]) - run.start_ns) * 1e-9
    taken_s -= run.sensors.gnss_clock_offset_s
    tr = run.truth

    def at(values: np.ndarray) -> np.ndarray:
        return np.interp(taken_s, tr.t_s, values)

    enu = run.frame.to_enu(
        np.array([f.lat_deg for f in fixes]),
        np.array([f.lon_deg for f in fixes]),
        np.array([f.height_m for f in fixes]),
    )
    offset = np.stack(enu, axis=1) - np.stack([at(tr.east_m), at(tr.north_m), at(tr.up_m)], 1)
    psi, theta, speed, lateral = (
        at(a) for a in (tr.heading_rad, tr.pitch_rad, tr.speed_mps, tr.lateral_mps)
    )
    level = speed * np.cos(theta)
    hull = np.stack(
        [
            level * np.sin(psi) + lateral * np.cos(psi),
            level * np.cos(psi) - lateral * np.sin(psi),
            speed * np.sin(theta),
        ],
        axis=1,
    )
    swing = np.array([f.vel_enu_mps for f in fixes]) - hull
    span_s = taken_s[2:] - taken_s[:-2]
    inner = span_s < 0.21  # both neighbours are the next epochs (not across an outage)
    diff = (offset[2:] - offset[:-2])[inner] / span_s[inner, None]
    assert inner.sum() > 1000
    assert np.abs(diff - swing[1:-1][inner]).max() <= 0.02
    # the mast swings by more than that: the fixes' velocity is not the hull centre's alone
    assert np.abs(swing[:, :2]).max() > 0.1


def test_hill_terrain_is_fixed() -> None:
    assert hill_terrain() == hill_terrain()


def _up_noise(run: TrackedRun) -> tuple[np.ndarray, np.ndarray]:
    """The fixes' up and east velocity errors against the antenna's climb (the hull's and its
    mast's, :func:`_mast_climb`) and the fixes' east velocity, read where each fix was taken
    (its stamp less the receiver's clock offset)."""
    fixes = _fixes(run)
    stamp_s = (np.array([f.stamp_ns for f in fixes]) - run.start_ns) * 1e-9
    taken_s = stamp_s - run.sensors.gnss_clock_offset_s
    vu = np.array([f.vel_enu_mps[2] for f in fixes])
    if run.sensors.gnss_clock_offset_s == 0.0 and run.sensors.gnss_epoch_jitter_s == 0.0:
        k = run.index_at(np.array([f.stamp_ns for f in fixes]))
        true_vu = run.truth.speed_mps[k] * np.sin(run.truth.pitch_rad[k]) + _mast_climb(run)[k]
    else:  # as the simulator reads the truth between its grid points
        speed = np.interp(taken_s, run.truth.t_s, run.truth.speed_mps)
        true_vu = speed * np.sin(np.interp(taken_s, run.truth.t_s, run.truth.pitch_rad))
        true_vu += np.interp(taken_s, run.truth.t_s, _mast_climb(run))
    return vu - true_vu, np.array([f.vel_enu_mps[0] for f in fixes])


def test_a_random_routes_receiver_states_a_noisier_vertical_by_its_own_draw() -> None:
    ratios = []
    for seed in (1000, 1001, 1002, 1003):
        run = _run("random", seed)
        ratio = run.sensors.gnss_up_vel_std_ratio
        lo, hi = RANDOM_RANGES["gnss_up_vel_std_ratio"]
        assert lo <= ratio <= hi
        err, _ = _up_noise(run)
        # thousands of fixes: the up error's spread is the ratio times the horizontal 1-sigma
        measured = float(np.std(err)) / run.sensors.gnss_vel_std_mps
        assert abs(measured / ratio - 1.0) < 0.1, (seed, measured, ratio)
        ratios.append(ratio)
    assert np.ptp(ratios) > 0.05  # drawn per route, not one figure
    # its own generator: a receiver as the named routes' (ratio 1) leaves every other draw
    run = _run("random", 1001)
    same = simulate_tracked(
        "random", 1001, sensors=dataclasses.replace(run.sensors, gnss_up_vel_std_ratio=1.0)
    )
    err, east = _up_noise(run)
    err1, east1 = _up_noise(same)
    assert np.array_equal(east, east1)
    # (the mast's climb by the chain rule here, by differences of its height in the
    # simulator: they agree to a micrometre per second)
    assert np.allclose(err, run.sensors.gnss_up_vel_std_ratio * err1, atol=1e-6)


def test_named_routes_keep_a_vertical_as_noisy_as_the_horizontal() -> None:
    run = _run("route_firm_hill", 1)
    assert run.sensors.gnss_up_vel_std_ratio == 1.0
    err, _ = _up_noise(run)
    assert abs(float(np.std(err)) / run.sensors.gnss_vel_std_mps - 1.0) < 0.1


def test_the_pitch_and_roll_gyros_walk_as_the_yaw_gyro_by_their_own_draw() -> None:
    named = _run("route_firm_hill", 2)
    route, spec = named.route, named.sensors

    def gyros(walk: bool) -> np.ndarray:
        run = simulate_route(
            route,
            2,
            config=named.config,
            sensors=spec,
            rng=np.random.default_rng(2),
            extra_rng=np.random.default_rng((2, 4)),
            walk_rng=np.random.default_rng((2, 6)) if walk else None,
        )
        return _imu(run)[1]

    walked, still = gyros(True), gyros(False)
    assert np.array_equal(walked, _imu(named)[1])  # what simulate_tracked gives
    assert np.array_equal(walked[:, 2], still[:, 2])  # the yaw gyro and every draw as before
    drift = walked[:, :2] - still[:, :2]
    n = drift.shape[0]
    expected = tilt_bias_walk(np.random.default_rng((2, 6)), named.truth.t_s.size, spec)
    # the IMU packets give the grid's samples from its second on
    assert np.allclose(drift, expected[1 : n + 1], atol=1e-12)
    # a random walk of the part's figure: per-second steps of 1-sigma walk·√1 s
    steps = np.diff(expected[::RATE_HZ], axis=0)
    ratio = np.std(steps, axis=0) / spec.gyro_bias_walk_radps
    assert np.all(np.abs(ratio - 1.0) < 0.1), ratio
