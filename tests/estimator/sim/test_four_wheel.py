"""The four-wheel simulator: reproducible per seed, physically consistent, sensors as stated."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np
import pytest

from estimator.friction.frontend import antenna_arm_m, antenna_velocity_at_cg, tilted_arm_m
from estimator.geo import EnuFrame
from estimator.sim.four_wheel import (
    FOUR_WHEEL_CONFIG,
    INSTANT_WHEEL_SENSOR,
    LEAD_S,
    FourWheelRun,
    Manoeuvre,
    WheelSpeedSensor,
    antenna_motion,
    random_config,
    random_manoeuvre,
    random_wheel_sensor,
    simulate_four_wheel,
    tooth_mean_speed,
)
from estimator.sim.four_wheel.dynamics import DT_S, GRAVITY_MPS2, Truth
from estimator.types import GnssSample, ImuBatch, SteeringAngles, WheelSpeeds4

KMH = 1 / 3.6
STEER = Manoeuvre(
    "short_steer",
    LEAD_S + 3.0,
    ((0.0, 60 * KMH), (1e4, 60 * KMH)),
    ((0.0, 0.0), (LEAD_S, 0.0), (LEAD_S + 0.3, math.radians(40)), (1e4, math.radians(40))),
    ((0.0, 0.8), (1e4, 0.8)),
)
ACCEL = Manoeuvre(
    "short_accel",
    LEAD_S + 3.0,
    ((0.0, 30 * KMH), (LEAD_S, 30 * KMH), (LEAD_S + 3, 50 * KMH)),
    ((0.0, 0.0), (1e4, 0.0)),
    ((0.0, 0.8), (1e4, 0.8)),
    damaged_wheel=2,
)


@pytest.fixture(scope="module")
def runs() -> list[FourWheelRun]:
    return simulate_four_wheel([STEER, ACCEL], seeds=[5, 6])


def test_a_run_depends_on_its_seed_alone(runs: list[FourWheelRun]) -> None:
    alone = simulate_four_wheel([ACCEL], seeds=[6])[0]
    assert np.array_equal(alone.truth.omega_radps, runs[1].truth.omega_radps)
    a = [m for m in alone.measurements if isinstance(m, ImuBatch)]
    b = [m for m in runs[1].measurements if isinstance(m, ImuBatch)]
    assert all(np.array_equal(x.accel_mps2, y.accel_mps2) for x, y in zip(a, b, strict=True))


def test_loads_sum_to_the_weight(runs: list[FourWheelRun]) -> None:
    for r in runs:
        weight = r.config.chassis.mass_kg * GRAVITY_MPS2
        assert np.allclose(r.truth.fz_n.sum(axis=-1), weight, rtol=1e-9)


def test_steady_turn_is_kinematically_consistent(runs: list[FourWheelRun]) -> None:
    t = runs[0].truth
    end = slice(-50, None)  # the last 0.5 s: settled
    assert np.allclose(t.ay_mps2[end], t.vx_mps[end] * t.yaw_rate_radps[end], rtol=0.03)
    assert np.all(t.ay_mps2[end] > 2.0)  # a real turn: outer wheels loaded
    assert np.all(t.fz_n[end, 1] > t.fz_n[end, 0]) and np.all(t.fz_n[end, 3] > t.fz_n[end, 2])


def test_tyres_stay_within_the_friction_circle(runs: list[FourWheelRun]) -> None:
    for r in runs:
        t = r.truth
        used = np.hypot(t.fx_n, t.fy_n) / (t.mu[:, None] * t.fz_n)
        assert np.all(used <= 1 + 1e-9)


def test_undriven_wheels_roll_free_and_driven_ones_slip(runs: list[FourWheelRun]) -> None:
    t = runs[1].truth
    lead = (t.t_s > 1.0) & (t.t_s < LEAD_S)
    accel = t.t_s > LEAD_S + 1.0
    assert np.max(np.abs(t.kappa[lead][:, :2])) < 1e-3  # rear drive: the fronts roll free
    assert np.all(t.kappa[accel][:, 2:] > 2e-3)


def test_a_soft_tyre_spins_faster(runs: list[FourWheelRun]) -> None:
    """kz 50,000 N/m on the rear left: more deflection, smaller rolling radius, faster wheel."""
    t = runs[1].truth
    lead = (t.t_s > 1.0) & (t.t_s < LEAD_S)
    assert np.all(t.omega_radps[lead, 2] > 1.01 * t.omega_radps[lead, 3])


def test_an_open_differential_balances_torque_not_force(runs: list[FourWheelRun]) -> None:
    """The soft rear-left tyre rolls on a smaller radius: the same axle torque pushes it harder
    (``F_L r_L = F_R r_R`` within the differential's ±2 % friction and the wheels' inertia)."""
    t = runs[1].truth
    accel = t.t_s > LEAD_S + 1.0
    radius = t.vx_mps[accel, None] * (1 + t.kappa[accel][:, 2:]) / t.omega_radps[accel][:, 2:]
    moment = t.fx_n[accel][:, 2:] * radius
    assert np.allclose(moment[:, 0], moment[:, 1], rtol=0.05)
    assert np.all(t.fx_n[accel, 2] > 1.05 * t.fx_n[accel, 3])


def test_accelerometers_read_the_tilt(runs: list[FourWheelRun]) -> None:
    r = runs[0]
    acc = np.concatenate([m.accel_mps2 for m in r.measurements if isinstance(m, ImuBatch)])
    n = min(acc.shape[0], r.truth.t_s.size)
    left = -acc[:n, 0]
    expected = r.truth.ay_mps2[:n] + GRAVITY_MPS2 * np.sin(r.truth.roll_rad[:n])
    assert abs(float(np.mean(left - expected))) < 0.06  # the bias bound, noise averaged out
    assert np.max(np.abs(r.truth.roll_rad)) > math.radians(0.5)  # there is a tilt to read


def test_streams_and_rates(runs: list[FourWheelRun]) -> None:
    r = runs[0]
    kinds = {type(m) for m in r.measurements}
    assert kinds == {ImuBatch, WheelSpeeds4, SteeringAngles, GnssSample}
    gnss = [m for m in r.measurements if isinstance(m, GnssSample)]
    assert len(gnss) == pytest.approx(r.manoeuvre.duration_s * 10, abs=2)
    wheels = np.concatenate([m.stamp_ns for m in r.measurements if isinstance(m, WheelSpeeds4)])
    assert np.all(np.diff(wheels) == 20_000_000)


def test_random_draws_within_stated_ranges() -> None:
    rng = np.random.default_rng(9)
    for k in range(20):
        c = random_config(rng)
        assert 1200 <= c.chassis.mass_kg <= 3500 and 0.30 <= c.tyre.unloaded_radius_m <= 0.40
        right, ahead, up = c.chassis.antenna_lever_arm_m
        assert abs(right) <= 0.4 and -1.5 <= ahead <= 2.0 and 1.5 <= up <= 3.2
        assert 0.05 <= c.chassis.tilt_axis_height_m <= 0.5
        m = random_manoeuvre(rng, k)
        speeds = [v for _, v in m.speed_knots]
        assert min(speeds) >= 10 * KMH - 1e-9 and max(speeds) <= 110 * KMH + 1e-9
        assert all(abs(a) <= math.radians(90) + 1e-12 for _, a in m.steer_knots)
        assert all(0.2 <= mu <= 1.1 for _, mu in m.mu_knots)
    assert FOUR_WHEEL_CONFIG.chassis.driven_axle.value == "rear"


def _wheel_speeds(run: FourWheelRun) -> tuple[np.ndarray, np.ndarray]:
    ms = [m for m in run.measurements if isinstance(m, WheelSpeeds4)]
    return (
        np.concatenate([m.stamp_ns for m in ms]),
        np.concatenate([m.omega_radps for m in ms]),
    )


def test_the_wheel_sensor_changes_no_other_stream(runs: list[FourWheelRun]) -> None:
    instant = simulate_four_wheel([ACCEL], seeds=[6], wheel_sensors=[INSTANT_WHEEL_SENSOR])[0]
    tooth = runs[1]
    assert len(instant.measurements) == len(tooth.measurements)
    for a, b in zip(instant.measurements, tooth.measurements, strict=True):
        assert type(a) is type(b)
        if isinstance(a, WheelSpeeds4) and isinstance(b, WheelSpeeds4):
            assert np.array_equal(a.stamp_ns, b.stamp_ns)
        elif isinstance(a, GnssSample):
            assert a == b
        else:
            for f in dataclasses.fields(a):
                assert np.array_equal(getattr(a, f.name), getattr(b, f.name))
    stamps, omega = _wheel_speeds(instant)
    rows = (stamps - instant.start_ns) // 10_000_000
    assert np.array_equal(omega, np.round(instant.truth.omega_radps[rows] / 0.025) * 0.025)
    assert not np.array_equal(omega, _wheel_speeds(tooth)[1])


def _spinning(truth: Truth, angle: Callable[[np.ndarray], np.ndarray], rate: np.ndarray) -> Truth:
    """``truth`` with every wheel turned by ``angle(t)`` [rad] (rate ``rate`` at the rows)."""
    every = truth.angle_sub_rad.shape[1]
    t_grid = DT_S * np.arange(truth.t_s.size * every)
    theta = np.repeat(angle(t_grid)[:, None], 4, axis=1).reshape(-1, every, 4)
    return dataclasses.replace(
        truth, angle_sub_rad=theta, omega_radps=np.repeat(rate[:, None], 4, axis=1)
    )


def test_a_tooth_mean_reads_the_speed_half_a_period_back(runs: list[FourWheelRun]) -> None:
    t = runs[0].truth.t_s
    omega0, accel = 30.0, 4.0  # rad/s, rad/s²
    truth = _spinning(runs[0].truth, lambda x: omega0 * x + 0.5 * accel * x**2, omega0 + accel * t)
    sensor = WheelSpeedSensor(teeth=48)
    at = t[100:200:2]
    read = tooth_mean_speed(truth, at, np.array([0.0, 1.0, 2.0, 3.0]), sensor)
    expected = omega0 + accel * (at - sensor.period_s / 2)
    assert np.max(np.abs(read - expected[:, None])) < 1e-9 * omega0 + accel * 2.2e-3
    assert np.mean(read - expected[:, None]) == pytest.approx(0.0, abs=accel * 3e-4)


def test_at_a_crawl_the_last_full_tooth_is_read(runs: list[FourWheelRun]) -> None:
    t = runs[0].truth.t_s
    sensor = WheelSpeedSensor(teeth=40)
    omega0 = 2 * math.pi / 40 / (3 * sensor.period_s)  # a tooth every three periods
    truth = _spinning(runs[0].truth, lambda x: omega0 * x, np.full(t.size, omega0))
    phases = np.random.default_rng(3).uniform(0, 2 * math.pi, 4)
    read = tooth_mean_speed(truth, t[50::2], phases, sensor)
    np.testing.assert_allclose(read, omega0, rtol=1e-9)


def test_a_tooth_mean_cancels_a_ring_at_the_sampling_rate(runs: list[FourWheelRun]) -> None:
    t = runs[0].truth.t_s
    sensor = WheelSpeedSensor(teeth=96)
    omega0, ring, hz = 30.0, 2.0, 1.0 / sensor.period_s

    def angle(x: np.ndarray) -> np.ndarray:
        return omega0 * x + ring / (2 * math.pi * hz) * np.sin(2 * math.pi * hz * x)

    rate = omega0 + ring * np.cos(2 * math.pi * hz * t)
    truth = _spinning(runs[0].truth, angle, rate)
    at = t[50:250:2]
    read = tooth_mean_speed(truth, at, np.zeros(4), sensor)
    sampled = rate[50:250:2]
    # the instantaneous samples alias the ring into a standing offset of its full size; the
    # mean over whole teeth (not quite the whole period) leaves a small part of it
    assert abs(np.mean(sampled) - omega0) > 0.9 * ring
    assert abs(np.mean(read) - omega0) < 0.15 * ring


def test_random_wheel_sensors_within_stated_ranges() -> None:
    rng = np.random.default_rng(4)
    drawn = [random_wheel_sensor(rng) for _ in range(400)]
    assert {s.teeth for s in drawn} <= set(range(40, 101))
    assert min(s.teeth for s in drawn) < 45 and max(s.teeth for s in drawn) > 95
    assert 0.06 < np.mean([not s.tooth_mean for s in drawn]) < 0.14


def test_a_wheel_sensor_states_what_it_can_be() -> None:
    with pytest.raises(ValueError):
        WheelSpeedSensor(teeth=2)
    with pytest.raises(ValueError):
        WheelSpeedSensor(period_s=0.025)  # not on the truth's 10 ms rows
    assert WheelSpeedSensor(period_s=0.03).period_s == 0.03


def _antenna_run(lever_arm_m: tuple[float, float, float]) -> FourWheelRun:
    chassis = dataclasses.replace(FOUR_WHEEL_CONFIG.chassis, antenna_lever_arm_m=lever_arm_m)
    config = dataclasses.replace(FOUR_WHEEL_CONFIG, chassis=chassis)
    return simulate_four_wheel([STEER], seeds=[5], configs=[config])[0]


def _receiver(run: FourWheelRun) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Row index, ENU position (the simulator's frame) and ENU velocity of each epoch."""
    gnss = [m for m in run.measurements if isinstance(m, GnssSample)]
    rows = np.array([round((g.stamp_ns - run.start_ns) / 10_000_000) for g in gnss])
    lat, lon, h = (
        np.array([getattr(g, f) for g in gnss]) for f in ("lat_deg", "lon_deg", "height_m")
    )
    pos = np.stack(EnuFrame(48.0, 11.0, 500.0).to_enu(lat, lon, h), axis=-1)
    return rows, pos, np.array([g.vel_enu_mps for g in gnss])


def test_the_receiver_reports_the_antennas_velocity_and_position() -> None:
    """An antenna 2 m ahead of the CG, 0.3 m right, 2.5 m up, in a steady 40° steering-wheel
    turn at 60 km/h: across the heading the receiver reads the CG's ``v_y`` plus ``r·2.0``
    (over 0.3 m/s), along it ``v_x + r·0.3`` (the noise, 0.03 m/s per epoch, averaged over
    the last second); its position is the CG's plus the arm turned with the heading; and
    over the whole run (the steering ramp's roll included) the velocity is what the
    position moves by between epochs. The same run with the antenna above the CG reads the
    CG's velocity."""
    run = _antenna_run((0.3, 2.0, 2.5))
    t = run.truth
    rows, pos, vel = _receiver(run)
    last = rows >= rows[-1] - 100  # the last second
    yaw, r = t.yaw_rad[rows[last]], t.yaw_rate_radps[rows[last]]
    ahead = vel[last, 0] * np.cos(yaw) + vel[last, 1] * np.sin(yaw)
    left = -vel[last, 0] * np.sin(yaw) + vel[last, 1] * np.cos(yaw)
    assert np.mean(r) > 0.15  # a real turn: the arm's term is over 0.3 m/s
    assert abs(float(np.mean(left - t.vy_mps[rows[last]] - 2.0 * r))) < 0.02
    assert abs(float(np.mean(ahead - t.vx_mps[rows[last]] - 0.3 * r))) < 0.02
    arm = pos[last, :2] - np.stack([t.east_m[rows[last]], t.north_m[rows[last]]], axis=-1)
    assert np.allclose(np.hypot(*arm.T), math.hypot(2.0, 0.3), atol=0.05)
    moved = np.diff(pos[:, :2], axis=0) / 0.1
    between = 0.5 * (vel[1:, :2] + vel[:-1, :2])
    assert float(np.sqrt(np.mean((moved - between) ** 2))) < 0.04
    axis_m = FOUR_WHEEL_CONFIG.chassis.tilt_axis_height_m
    centred = _receiver(_antenna_run((0.0, 0.0, axis_m)))[2]  # on the tilt axis: no arm
    cg = np.stack([t.vx_mps, t.vy_mps], axis=-1)[rows]
    c, s = np.cos(t.yaw_rad[rows]), np.sin(t.yaw_rad[rows])
    cg_enu = np.stack([cg[:, 0] * c - cg[:, 1] * s, cg[:, 0] * s + cg[:, 1] * c], axis=-1)
    assert float(np.max(np.abs(centred[:, :2] - cg_enu))) < 0.15  # the noise, 5 σ


def test_the_front_ends_transfer_takes_the_antennas_velocity_back_to_the_cgs() -> None:
    """The steering ramp (40° in 0.3 s at 60 km/h) on a 3.2 m mast 2.0 m ahead and 0.3 m right
    of the CG, the body tilting about its axis 0.1 m above the ground: the simulator's
    antenna velocity (noise-free), turned into the heading's frame and moved back with the
    truth's rates as the gyro reads them and the truth's roll and pitch, is the truth's
    planar velocity within 0.01 m/s on every row. Left out, the roll moves the antenna by
    over 0.1 m/s across; measured from the CG instead of the axis, by over 0.02 m/s."""
    chassis = dataclasses.replace(
        FOUR_WHEEL_CONFIG.chassis, antenna_lever_arm_m=(0.3, 2.0, 3.2), tilt_axis_height_m=0.1
    )
    config = dataclasses.replace(FOUR_WHEEL_CONFIG, chassis=chassis)
    run = simulate_four_wheel([STEER], seeds=[5], configs=[config])[0]
    assert run.config.chassis.tilt_axis_height_m == 0.1  # the run's config states its axis
    t = run.truth
    vel = antenna_motion(t, chassis)[1]
    c, s = np.cos(t.yaw_rad), np.sin(t.yaw_rad)
    body = np.stack([vel[:, 0] * c + vel[:, 1] * s, -vel[:, 0] * s + vel[:, 1] * c], axis=-1)
    rates = np.stack([t.roll_rate_radps, -t.pitch_rate_radps, t.yaw_rate_radps], axis=-1)
    arm = np.array(antenna_arm_m(chassis))
    cg = np.stack([t.vx_mps, t.vy_mps], axis=-1)

    def worst(rates: np.ndarray, arm: np.ndarray) -> np.ndarray:
        got = antenna_velocity_at_cg(body, rates, tilted_arm_m(arm, t.roll_rad, t.pitch_rad))
        return np.max(np.abs(got - cg), axis=0)

    assert np.all(worst(rates, arm) < 0.01)
    assert worst(rates * [0.0, 0.0, 1.0], arm)[1] > 0.1
    from_cg = arm - [0.0, 0.0, chassis.cg_height_m - chassis.tilt_axis_height_m]
    assert worst(rates, from_cg)[1] > 0.02
