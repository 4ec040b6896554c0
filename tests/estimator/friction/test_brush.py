"""Brush tyre forces against hand-computed cases and their limits (method.md §5)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimator.friction.brush import (
    brush_forces,
    contact_half_length_m,
    load_adaptive_stiffness_n,
    utilisation,
)


def test_load_adaptive_stiffness_by_hand() -> None:
    # r_u 0.3 m, Fz 3000 N, kz 2e5 N/m: d = 0.015 m, a² = 2·0.3·0.015 − 0.015² = 0.008775 m²
    assert contact_half_length_m(3000.0, 2e5, 0.3) == pytest.approx(math.sqrt(0.008775))
    assert load_adaptive_stiffness_n(3000.0, 2e5, 0.3, 1e7) == pytest.approx(2 * 0.008775 * 1e7)
    # a softer tyre (damaged: kz 5e4) has a longer patch and a stiffer brush
    assert load_adaptive_stiffness_n(3000.0, 5e4, 0.3, 1e7) > 3 * load_adaptive_stiffness_n(
        3000.0, 2e5, 0.3, 1e7
    )


def test_pure_longitudinal_slip_by_hand() -> None:
    # κ 0.01, cx 1e5 N, μ 1, Fz 4000: σx = 0.01/1.01, ψ = 990.099 N, 3μFz = 12000 N
    psi = 1e5 * 0.01 / 1.01
    expected = psi - psi**2 / 12000 + psi**3 / (3 * 12000**2)
    fx, fy = brush_forces(0.01, 0.0, 4000.0, 1.0, 1e5, 8e4)
    assert fx == pytest.approx(expected, rel=1e-12)
    assert fx == pytest.approx(910.654, abs=1e-3)
    assert fy == 0.0


def test_pure_lateral_slip_by_hand() -> None:
    # α 0.02 rad, cy 8e4 N, μ 0.5, Fz 3000: ψ = 8e4·tan 0.02 = 1600.21 N, 3μFz = 4500 N
    psi = 8e4 * math.tan(0.02)
    expected = psi - psi**2 / 4500 + psi**3 / (3 * 4500**2)
    fx, fy = brush_forces(0.0, 0.02, 3000.0, 0.5, 1e5, 8e4)
    assert fy == pytest.approx(expected, rel=1e-12)
    assert fx == 0.0
    fx_neg, fy_neg = brush_forces(-0.01, -0.02, 3000.0, 0.5, 1e5, 8e4)
    assert fx_neg < 0 and fy_neg < 0


def test_linear_range_is_the_stiffness() -> None:
    fx, fy = brush_forces(1e-6, 1e-6, 5000.0, 0.8, 2e5, 1.5e5)
    assert fx == pytest.approx(2e5 * 1e-6, rel=1e-4)
    assert fy == pytest.approx(1.5e5 * 1e-6, rel=1e-4)


def test_saturation_gives_mu_fz() -> None:
    fx, fy = brush_forces(0.5, 0.0, 4000.0, 0.3, 1e5, 8e4)
    assert fx == pytest.approx(0.3 * 4000.0, rel=1e-12)
    assert fy == 0.0
    # the curve reaches μFz at λ = 1 continuously and never exceeds it
    kappa = np.linspace(0.0, 0.2, 2001)
    f, _ = brush_forces(kappa, 0.0, 4000.0, 0.3, 1e5, 8e4)
    assert np.all(np.diff(f) >= -1e-9)
    assert f.max() == pytest.approx(1200.0, rel=1e-12)


@pytest.mark.parametrize(("kappa", "alpha"), [(0.3, 0.2), (-0.4, 0.1), (0.05, -0.6)])
def test_combined_slip_friction_ellipse(kappa: float, alpha: float) -> None:
    cx, cy = 1e5, 6e4
    fx, fy = brush_forces(kappa, alpha, 3500.0, 0.7, cx, cy)
    assert math.hypot(fx, fy) == pytest.approx(0.7 * 3500.0, rel=1e-12)
    # the force points along the stiffness-weighted slip (cx σx, cy σy)
    sx, sy = cx * kappa / (1 + kappa), cy * math.tan(alpha) / (1 + kappa)
    assert math.atan2(fy, fx) == pytest.approx(math.atan2(sy, sx), abs=1e-12)


def test_combined_slip_stays_inside_the_circle() -> None:
    rng = np.random.default_rng(3)
    kappa = rng.uniform(-0.5, 0.5, 500)
    alpha = rng.uniform(-0.5, 0.5, 500)
    fx, fy = brush_forces(kappa, alpha, 4000.0, 0.9, 1.2e5, 9e4)
    assert np.all(np.hypot(fx, fy) <= 0.9 * 4000.0 * (1 + 1e-12))
    assert np.all(utilisation(fx, fy, 4000.0, 0.9) <= 1 + 1e-12)


def test_no_load_no_force() -> None:
    fx, fy = brush_forces(0.1, 0.1, 0.0, 0.9, 1e5, 1e5)
    assert fx == 0.0 and fy == 0.0
    assert np.isnan(utilisation(0.0, 0.0, 0.0, 0.9))
