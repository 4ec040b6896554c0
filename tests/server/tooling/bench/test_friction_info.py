"""The information bound's pieces against hand-computed cases (no simulation)."""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import Any

import numpy as np

from estimator.friction.brush import load_adaptive_stiffness_n
from server.tooling.bench.friction_info import _bound, _jacobian

MASS_KG = 1500.0
FZ_N = 4000.0
KZ_NPM = 2.5e5
RADIUS_M = 0.35
C_PX_NPM2 = 1e7


def _one_driven_wheel(kappa: float, mu: float) -> Any:
    """A truth row where only the rear-left wheel carries load and slips straight ahead."""
    fz = np.array([[0.0, 0.0, FZ_N, 0.0]])
    truth = SimpleNamespace(
        fz_n=fz,
        kappa=np.array([[0.0, 0.0, kappa, 0.0]]),
        alpha_rad=np.zeros((1, 4)),
        delta_rad=np.zeros((1, 4)),
        mu=np.array([mu]),
    )
    config = SimpleNamespace(
        tyre=SimpleNamespace(unloaded_radius_m=RADIUS_M),
        chassis=SimpleNamespace(mass_kg=MASS_KG),
    )
    return SimpleNamespace(
        truth=truth,
        config=config,
        tyre_kz_npm=np.full(4, KZ_NPM),
        tyre_c_px_npm2=np.full(4, C_PX_NPM2),
        tyre_c_py_npm2=np.full(4, 0.7 * C_PX_NPM2),
    )


def test_the_jacobian_is_the_brush_curves_slope_in_mu_and_in_kappa() -> None:
    """``F = 3μFz(λ − λ² + λ³/3)``, ``λ = cσ/(3μFz)``: ``∂F/∂ln μ = μFz(3λ² − 2λ³)`` and
    ``∂F/∂κ = c(1 − λ)²/(1 + κ)²``; ``a_x = F/m``."""
    kappa, mu = 0.012, 0.8
    c = float(load_adaptive_stiffness_n(FZ_N, KZ_NPM, RADIUS_M, C_PX_NPM2))
    lam = c * kappa / (1 + kappa) / (3 * mu * FZ_N)
    assert 0.1 < lam < 1.0
    jac, per_wheel = _jacobian(_one_driven_wheel(kappa, mu), 0)
    assert math.isclose(jac[0], mu * FZ_N * (3 * lam**2 - 2 * lam**3) / MASS_KG, rel_tol=1e-5)
    slope = c * (1 - lam) ** 2 / (1 + kappa) ** 2 / MASS_KG
    assert math.isclose(per_wheel[2], slope, rel_tol=1e-5)
    assert math.isclose(jac[3], slope, rel_tol=1e-5)
    assert per_wheel[0] == 0.0
    assert jac[2] == 0.0


def test_the_bound_takes_the_nuisances_prior_into_account() -> None:
    """μ alone: ``1/√I₀₀``; with a factor correlated with μ and a prior ``σ_g``, the Schur
    complement ``I₀₀ − I₀₁²/(I₁₁ + σ_g⁻²)``."""
    fisher = np.zeros((4, 4))
    fisher[:2, :2] = [[4.0, 2.0], [2.0, 4.0]]
    assert math.isclose(_bound(fisher, 0.0, 0.0), 0.5)
    assert math.isclose(_bound(fisher, 0.5, 0.0), 1.0 / math.sqrt(4.0 - 4.0 / 8.0))
    assert _bound(fisher, 10.0, 0.0) > _bound(fisher, 0.5, 0.0)
    assert math.isinf(_bound(np.zeros((4, 4)), 0.1, 0.0))
