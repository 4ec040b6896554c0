"""The four-wheel simulator: reproducible per seed, physically consistent, sensors as stated."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimator.sim.four_wheel import (
    FOUR_WHEEL_CONFIG,
    LEAD_S,
    FourWheelRun,
    Manoeuvre,
    random_config,
    random_manoeuvre,
    simulate_four_wheel,
)
from estimator.sim.four_wheel.dynamics import GRAVITY_MPS2
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
        m = random_manoeuvre(rng, k)
        speeds = [v for _, v in m.speed_knots]
        assert min(speeds) >= 10 * KMH - 1e-9 and max(speeds) <= 110 * KMH + 1e-9
        assert all(abs(a) <= math.radians(90) + 1e-12 for _, a in m.steer_knots)
        assert all(0.2 <= mu <= 1.1 for _, mu in m.mu_knots)
    assert FOUR_WHEEL_CONFIG.chassis.driven_axle.value == "rear"
