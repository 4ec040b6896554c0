"""The open differential's torque balance and the slips' load sensitivity (:mod:`.axle`), and
what the balance does in the product filter."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from estimator.config import ChassisConfig, Differential, DrivenAxle, Wheeled4wdSteeredConfig
from estimator.friction.axle import (
    AxleArrays,
    AxleConfig,
    balance_std_n,
    effective_radii_m,
    load_slip_std,
)
from estimator.friction.brush import brush_forces
from estimator.friction.filter import (
    FilterConfig,
    TickInputs,
    TyreArrays,
    _torque_balance,
    filter_step,
    initial_state,
    mu_of,
)
from estimator.friction.model import Chassis, body_accelerations

CFG = AxleConfig()
REAR = Wheeled4wdSteeredConfig(chassis=ChassisConfig(driven_axle=DrivenAxle.REAR))


def _axles(**chassis: object) -> AxleArrays:
    return AxleArrays.of([Wheeled4wdSteeredConfig(chassis=ChassisConfig(**chassis))])  # type: ignore[arg-type]


def test_balance_is_zero_where_the_moments_are_equal() -> None:
    fx = np.array([[[100.0, 100.0, 1100.0, 1000.0]]])
    radius = np.array([[0.3, 0.3, 0.3, 0.33]])
    np.testing.assert_allclose(_torque_balance(fx, radius), [[[0.0, 0.0]]], atol=1e-9)
    fx_equal = np.array([[[0.0, 0.0, 1000.0, 1000.0]]])  # equal forces: the smaller rim lags
    assert _torque_balance(fx_equal, radius)[0, 0, 1] == pytest.approx(-30.0 / 0.315)


def test_balance_noise_by_hand_and_where_it_is_not_applied() -> None:
    """Rear drive, 2,500 kg at 2 m/s²: 2,500 N a rear wheel, 3 % of it with 30 N in quadrature;
    the front axle, braking, a spinning wheel, a turn or a locked differential: weightless."""
    axles = AxleArrays.of([REAR])
    fz = np.full((1, 4), 6000.0)
    kz = np.full((1, 4), 250_000.0)
    kappa = np.full((1, 4), 0.01)
    z = np.array([[2.0, 0.0, 0.0]])
    std = balance_std_n(fz, kz, kappa, z, axles, CFG)
    assert std[0, 0] == CFG.weightless_std_n
    assert std[0, 1] == pytest.approx(np.hypot(30.0, 0.03 * 2500.0))
    off = CFG.weightless_std_n
    assert balance_std_n(fz, kz, kappa, -z, axles, CFG)[0, 1] == off
    spinning = kappa.copy()
    spinning[0, 3] = 0.03
    assert balance_std_n(fz, kz, spinning, z, axles, CFG)[0, 1] == off
    turning = np.array([[2.0, 1.5, 0.0]])
    assert balance_std_n(fz, kz, kappa, turning, axles, CFG)[0, 1] == off
    locked = _axles(driven_axle=DrivenAxle.REAR, differential=Differential.LOCKED)
    assert np.all(balance_std_n(fz, kz, kappa, z, locked, CFG) == off)
    both = balance_std_n(fz, kz, kappa, z, _axles(driven_axle=DrivenAxle.ALL), CFG)
    assert both[0] == pytest.approx([np.hypot(30.0, 0.03 * 1250.0)] * 2)


def test_a_soft_tyre_widens_its_balance_and_its_slip() -> None:
    """kz 50,000 N/m on the rear left: its deflection is 0.096 m more than its partner's, whose
    ρ is known to 0.05 (1.5 % of the radius), and its slip sinks five times a sound tyre's."""
    axles = AxleArrays.of([REAR])
    fz = np.full((1, 4), 6000.0)
    kz = np.array([[250_000.0, 250_000.0, 50_000.0, 250_000.0]])
    z = np.array([[2.0, 0.0, 0.0]])
    std = balance_std_n(fz, kz, np.zeros((1, 4)), z, axles, CFG)
    spread = 0.05 * (6000.0 / 50_000 - 6000.0 / 250_000) / 0.33
    assert std[0, 1] == pytest.approx(np.hypot(30.0, 2500.0 * np.hypot(0.03, spread)))
    slip = load_slip_std(fz, kz, axles, CFG)
    assert slip[0, 0] == pytest.approx(30.0 / (3 * 250_000.0 * 0.33))
    assert slip[0, 2] == pytest.approx(5 * slip[0, 3])


def _soft_tyre_tick(kappa_rl_bias: float, balance: bool) -> tuple[TickInputs, TyreArrays, Chassis]:
    """A rear-driven vehicle accelerating straight on μ 0.8, its rear-left tyre soft
    (kz 50,000 N/m: four times the sound tyres' brush stiffness): the rear slips are the ones
    the open differential gives (``F_L r_L = F_R r_R``), measured ``[a_x, a_y, ṙ]`` from the
    model; the soft tyre's slip is read ``kappa_rl_bias`` off, as its sinking radius makes it."""
    ty = REAR.tyre
    kz = np.array([[ty.kz_npm, ty.kz_npm, 50_000.0, ty.kz_npm]])
    tyres = TyreArrays(
        kz,
        np.array([[ty.unloaded_radius_m]]),
        np.array([[ty.c_px_npm2]]),
        np.array([[ty.c_py_npm2]]),
    )
    fz = np.array([[5500.0, 5500.0, 6760.0, 6760.0]])
    radius = effective_radii_m(fz, kz, AxleArrays.of([REAR]), CFG)
    cx, cy = tyres.stiffness(fz)
    zero = np.zeros((1, 4))

    def fx_of(kappa: np.ndarray) -> np.ndarray:
        return brush_forces(kappa, zero, fz, np.array([[0.8]]), cx, cy)[0]

    kappa = np.array([[0.0, 0.0, 0.0, 0.012]])
    target = fx_of(kappa)[0, 3] * radius[0, 3] / radius[0, 2]
    lo, hi = 0.0, 0.05
    for _ in range(60):  # the soft tyre's slip that carries its share of the torque
        kappa[0, 2] = (lo + hi) / 2
        lo, hi = (kappa[0, 2], hi) if fx_of(kappa)[0, 2] < target else (lo, kappa[0, 2])
    chassis = Chassis.of([REAR])
    fx = fx_of(kappa)
    z = body_accelerations(fx[:, None], zero[:, None], zero[:, None], chassis)[:, 0]
    read = kappa + np.array([[0.0, 0.0, kappa_rl_bias, 0.0]])
    std = np.array([[3e-4, 3e-4, 2e-3, 3e-4]])
    u = TickInputs(
        fz_n=fz,
        alpha_rad=zero,
        delta_rad=zero,
        kappa=read,
        kappa_std=std,
        kappa_common_std=np.zeros(1),
        alpha_std_rad=np.full((1, 4), 3e-4),
        z=z,
        valid=np.array([True]),
        vx_mps=np.array([15.0]),
        yaw_rate_radps=np.zeros(1),
        vy_meas_mps=np.zeros(1),
        vy_meas_std_mps=np.array([0.05]),
        alpha_lag_rad=zero,
        radius_m=radius,
        balance_std_n=balance_std_n(fz, kz, read, z, AxleArrays.of([REAR]), CFG)
        if balance
        else np.full((1, 2), CFG.weightless_std_n),
    )
    return u, tyres, chassis


@pytest.mark.parametrize("bias", [8e-4, -8e-4])
def test_the_balance_reads_a_soft_tyres_force_from_its_partner(bias: float) -> None:
    """The soft tyre's slip 8e-4 off is ~30 % of its force: without the balance μ follows it;
    with it, μ comes from the sound tyre and the body's acceleration."""
    errors = {}
    for balance in (False, True):
        u, tyres, chassis = _soft_tyre_tick(bias, balance)
        cfg = FilterConfig()
        st = initial_state(cfg, tyres, u.fz_n)
        for _ in range(150):
            st = filter_step(st, cfg, tyres, chassis, u)
        errors[balance] = abs(float(mu_of(st.x[0, 0], cfg.mode)) / 0.8 - 1)
    assert errors[True] < 0.03
    assert errors[False] > 2 * errors[True]


def _mu_after(u: TickInputs, tyres: TyreArrays, chassis: Chassis, cfg: FilterConfig) -> float:
    st = initial_state(cfg, tyres, u.fz_n)
    for _ in range(150):
        st = filter_step(st, cfg, tyres, chassis, u)
    return float(mu_of(st.x[0, 0], cfg.mode))


def test_the_balance_leaves_a_consistent_tick_alone() -> None:
    """Slips as the differential gives them: the balance's innovation is zero and μ is found
    with it as without it."""
    cfg = FilterConfig(central_prediction=True)
    alone, balanced = (_mu_after(*_soft_tyre_tick(0.0, b), cfg) for b in (False, True))
    assert balanced == pytest.approx(0.8, rel=0.01)
    assert alone == pytest.approx(balanced, rel=0.005)


def test_the_central_prediction_removes_the_considered_factors_bias() -> None:
    """The stiffness factors held (considered) at 1 ± 10 %: the points' mean of ``h`` over
    their spread settles μ off the truth; ``h`` with them at their centre does not."""
    tick = _soft_tyre_tick(0.0, True)
    spread = _mu_after(*tick, FilterConfig())
    centre = _mu_after(*tick, FilterConfig(central_prediction=True))
    assert abs(centre / 0.8 - 1) < 0.01
    assert abs(spread / 0.8 - 1) > 2 * abs(centre / 0.8 - 1)


def test_fleet_batches_the_axles_of_mixed_vehicles() -> None:
    """``concat`` keeps each vehicle's row: a rear-drive and an all-wheel-drive one."""
    parts = [AxleArrays.of([REAR]), _axles(driven_axle=DrivenAxle.ALL)]
    both = AxleArrays.concat(parts)
    assert both.open_share.tolist() == [[0.0, 1.0], [0.5, 0.5]]
    assert dataclasses.asdict(AxleArrays.concat(parts[:1]))["mass_kg"].tolist() == [2500.0]
