"""The information bound's pieces against hand-computed cases, and on the simulator."""

from __future__ import annotations

import itertools
import math
from types import SimpleNamespace
from typing import Any

import numpy as np

from estimator.friction.brush import load_adaptive_stiffness_n
from estimator.friction.model import Chassis, Measured
from estimator.sim.four_wheel import named_manoeuvre, simulate_four_wheel
from server.tooling.bench.friction_info import (
    COLUMNS,
    TIMES_S,
    Column,
    Info,
    Param,
    Ticks,
    _jacobian,
    bound_series,
    first_within,
    information,
    table,
)

MASS_KG = 1500.0
YAW_INERTIA_KGM2 = 2500.0
LF_M, LR_M = 1.2, 1.4
FZ_N = 4000.0
KZ_NPM = 2.5e5
RADIUS_M = 0.35
C_PX_NPM2 = 1e7
VX_MPS = 15.0


def _one_loaded_wheel(kappa: float, alpha_rad: float, mu: float) -> Any:
    """A truth row where only the rear-left wheel carries load, with slip ``kappa`` and slip
    angle ``alpha_rad``, driving straight at ``VX_MPS`` (no yaw rate, no steer)."""
    truth = SimpleNamespace(
        fz_n=np.array([[0.0, 0.0, FZ_N, 0.0]]),
        kappa=np.array([[0.0, 0.0, kappa, 0.0]]),
        alpha_rad=np.array([[0.0, 0.0, alpha_rad, 0.0]]),
        delta_rad=np.zeros((1, 4)),
        mu=np.array([mu]),
        vx_mps=np.array([VX_MPS]),
        vy_mps=np.array([0.0]),
        yaw_rate_radps=np.array([0.0]),
    )
    chassis = SimpleNamespace(
        mass_kg=MASS_KG,
        yaw_inertia_kgm2=YAW_INERTIA_KGM2,
        cg_to_front_axle_m=LF_M,
        cg_to_rear_axle_m=LR_M,
        front_track_m=1.5,
        rear_track_m=1.5,
    )
    config = SimpleNamespace(tyre=SimpleNamespace(unloaded_radius_m=RADIUS_M), chassis=chassis)
    return SimpleNamespace(
        truth=truth,
        config=config,
        tyre_kz_npm=np.full(4, KZ_NPM),
        tyre_c_px_npm2=np.full(4, C_PX_NPM2),
        tyre_c_py_npm2=np.full(4, 0.7 * C_PX_NPM2),
    )


def _jacobian_of(run: Any) -> tuple[np.ndarray, np.ndarray]:
    return _jacobian(run, Chassis.of([run.config]), 0)


def test_the_jacobian_is_the_brush_curves_slope_in_mu_and_in_kappa() -> None:
    """``F = 3μFz(λ − λ² + λ³/3)``, ``λ = cσ/(3μFz)``: ``∂F/∂ln μ = μFz(3λ² − 2λ³)`` and
    ``∂F/∂κ = c(1 − λ)²/(1 + κ)²``; ``a_x = F/m``."""
    kappa, mu = 0.012, 0.8
    c = float(load_adaptive_stiffness_n(FZ_N, KZ_NPM, RADIUS_M, C_PX_NPM2))
    lam = c * kappa / (1 + kappa) / (3 * mu * FZ_N)
    assert 0.1 < lam < 1.0
    jac, per_wheel = _jacobian_of(_one_loaded_wheel(kappa, 0.0, mu))
    ax = Measured.AX
    assert math.isclose(
        jac[ax, Param.LN_MU], mu * FZ_N * (3 * lam**2 - 2 * lam**3) / MASS_KG, rel_tol=1e-5
    )
    slope = c * (1 - lam) ** 2 / (1 + kappa) ** 2 / MASS_KG
    assert math.isclose(per_wheel[ax, 2], slope, rel_tol=1e-5)
    assert math.isclose(jac[ax, Param.B_KAPPA], slope, rel_tol=1e-5)
    assert per_wheel[ax, 0] == 0.0
    assert jac[ax, Param.LN_GX_FRONT] == 0.0


def test_the_lateral_rows_follow_the_cornering_curve_and_the_wheels_place() -> None:
    """Pure side slip on the rear-left wheel (``x = −lr``, ``δ = 0``): ``a_y = F_y/m``,
    ``ṙ = −lr F_y / I_z`` with ``F_y`` the brush curve in ``λ = c_y tan α/(3μFz)``;
    ``∂F_y/∂ln μ = μFz(3λ² − 2λ³)``, ``∂F_y/∂ln g_y = ∂F_y/∂ln c = c_y tan α (1 − λ)²`` and a
    lateral speed error moves ``α`` by ``−1/v_x``: ``∂F_y/∂v_y = −c_y (1 − λ)² sec²α / v_x``."""
    alpha, mu = 0.02, 0.8
    c_y = float(load_adaptive_stiffness_n(FZ_N, KZ_NPM, RADIUS_M, 0.7 * C_PX_NPM2))
    lam = c_y * math.tan(alpha) / (3 * mu * FZ_N)
    assert 0.1 < lam < 1.0
    jac, _ = _jacobian_of(_one_loaded_wheel(0.0, alpha, mu))
    d_mu = mu * FZ_N * (3 * lam**2 - 2 * lam**3)
    d_g = c_y * math.tan(alpha) * (1 - lam) ** 2
    d_vy = -c_y * (1 - lam) ** 2 / math.cos(alpha) ** 2 / VX_MPS
    for param, expected in ((Param.LN_MU, d_mu), (Param.LN_GY_REAR, d_g), (Param.VY, d_vy)):
        assert math.isclose(jac[Measured.AY, param], expected / MASS_KG, rel_tol=1e-4)
        assert math.isclose(
            jac[Measured.YAW_ACCEL, param], -LR_M * expected / YAW_INERTIA_KGM2, rel_tol=1e-4
        )
    assert jac[Measured.AY, Param.LN_GY_FRONT] == 0.0
    assert abs(jac[Measured.AX, Param.LN_MU]) < 1e-9


def _ticks(jac: np.ndarray, vy_std: np.ndarray | None = None) -> Ticks:
    n = jac.shape[0]
    std = np.full(n, np.nan) if vy_std is None else vy_std
    return Ticks(jac, np.zeros((n, 3, 5)), np.ones(n, dtype=bool), std, std)


def test_mu_alone_is_bounded_by_sigma_over_its_slope_and_root_n() -> None:
    """One row, one parameter, the same slope ``j`` each tick: after ``k`` ticks the
    information is ``k j²/σ²``, the bound ``σ/(|j|√k)``."""
    jac = np.zeros((9, 3, len(Param)))
    jac[:, Measured.AX, Param.LN_MU] = 0.7
    col = Column("μ alone", (Measured.AX,), vy="known")
    got = bound_series(_ticks(jac), col, (0.2, 0.2, 1.0))
    k = np.arange(1, 10)
    np.testing.assert_allclose(got, 0.2 / (0.7 * np.sqrt(k)), rtol=1e-12)


def test_constant_nuisances_with_priors_give_the_schur_complement() -> None:
    """No walk: the bound is ``√((Σ Hᵀ R⁻¹ H + diag(0, σ_g⁻², …))⁻¹)₀₀`` over μ, the four
    factors and ``v_y`` (its start prior), computed here as the inverse of the whole matrix."""
    rng = np.random.default_rng(3)
    jac = rng.normal(size=(12, 3, len(Param)))
    sigma = np.array([0.2, 0.3, 1.0])
    col = Column("g, v_y", g_std=0.1)
    got = bound_series(_ticks(jac), col, sigma, vy0_std_mps=0.05, vy_walk_mps_per_sqrt_s=0.0)
    free = [Param.LN_MU, Param.LN_GX_REAR, Param.LN_GX_FRONT, Param.LN_GY_FRONT]
    free += [Param.LN_GY_REAR, Param.VY]
    info = np.diag([0.0, *[0.1**-2] * 4, 0.05**-2])
    for k in range(12):
        h = jac[k][:, free]
        info += h.T @ np.diag(sigma**-2) @ h
        assert math.isclose(got[k], math.sqrt(np.linalg.inv(info)[0, 0]), rel_tol=1e-9)


def test_a_walking_lateral_speed_with_gnss_is_the_kalman_filters_covariance() -> None:
    """With ``v_y``'s error walking and measured every other tick, the bound is the linear
    Kalman filter's posterior 1-σ of μ (covariance form, Joseph update, written out here; μ's
    prior 1e3, a millionth of one tick's information)."""
    rng = np.random.default_rng(4)
    n, tick_s, walk, gnss_std = 40, 0.02, 0.05, 0.1
    jac = rng.normal(size=(n, 3, len(Param)))
    vy_std = np.where(np.arange(n) % 2 == 0, gnss_std, np.nan)
    sigma = np.array([0.2, 0.2, 1.0])
    got = bound_series(_ticks(jac, vy_std), Column("v_y"), sigma, 0.0, 0.05, walk, tick_s)
    free = [Param.LN_MU, Param.VY]
    p = np.diag([1e3**2, 0.05**2])
    for k in range(n):
        p[1, 1] += walk**2 * tick_s
        h, r = jac[k][:, free], np.diag(sigma**2)
        if k % 2 == 0:
            h, r = np.vstack([h, [0.0, 1.0]]), np.diag([*sigma**2, gnss_std**2])
        gain = p @ h.T @ np.linalg.inv(h @ p @ h.T + r)
        keep = np.eye(2) - gain @ h
        p = keep @ p @ keep.T + gain @ r @ gain.T
        assert math.isclose(got[k], math.sqrt(p[0, 0]), rel_tol=1e-6)


def test_first_within_is_the_first_time_from_the_start() -> None:
    t_s = np.array([-0.5, 0.0, 0.5, 1.0, 1.5])
    bound = np.array([0.01, 0.2, 0.06, 0.04, 0.06])
    assert first_within(t_s, bound, 0.05) == 1.0
    assert math.isnan(first_within(t_s, bound, 0.01))


def test_the_table_prints_the_times_within_the_run() -> None:
    """A run of ticks from −1 to 6.5 s prints the rows up to 6 s (not 8 and 10, which a
    10-s accelerating manoeuvre has), each at its nearest tick."""
    t_s = np.arange(-1.0, 6.5 + 1e-9, 0.02)
    n = t_s.size
    info = Info(
        t_s,
        np.zeros(n),
        np.zeros(n),
        np.full((n, len(COLUMNS)), 0.1),
        np.full(n, 0.8),
        np.full(n, 0.1),
        np.zeros(n, dtype=bool),
        1e-4,
    )
    rows = table(info, 0.8).splitlines()[2:-2]
    want = [t for t in TIMES_S if t <= 6.5]
    printed = [float(r.split("|")[1]) for r in rows]
    assert len(printed) == len(want) < len(TIMES_S)
    assert np.allclose(printed, want, atol=0.011)


def test_on_the_steering_step_the_lateral_rows_only_add_information() -> None:
    """The simulator's 60° steering step on μ 0.8: the bound from ``a_x``, ``a_y`` and ``ṙ``
    is never above ``a_x``'s alone (same nuisances), and the lateral rows are what carry μ
    there (at 0.88 s under a third of ``a_x``'s); tighter priors never raise it."""
    (run,) = simulate_four_wheel([named_manoeuvre("steer_mu08")], [1])
    info = information(run)
    col = {c.name: k for k, c in enumerate(COLUMNS)}
    ax_only, both = info.crlb[:, col["a_x, g ±1.7 %"]], info.crlb[:, col["g ±1.7 %"]]
    assert np.all(both <= ax_only * (1 + 1e-9))
    k = int(np.argmin(np.abs(info.t_s - 0.88)))
    assert both[k] < ax_only[k] / 3
    order = ["known", "g ±1.7 %, v_y known", "g ±1.7 %", "g ±10 %", "g ±10 %, no GNSS"]
    for tight, loose in itertools.pairwise(order):
        assert np.all(info.crlb[:, col[tight]] <= info.crlb[:, col[loose]] * (1 + 1e-9))
