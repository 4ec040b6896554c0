"""Combined-slip brush tyre with load-adaptive stiffness (``method.md`` §5, source 004).

The source's equation images are missing; this is the textbook anisotropic brush model
(Pacejka, *Tire and Vehicle Dynamics*, §3.2; Svendenius 2007) on theoretical slips

    σx = κ / (1 + κ),   σy = tan α / (1 + κ),   ψ = hypot(cx·σx, cy·σy),   λ = ψ / (3 μ Fz)
    F  = 3 μ Fz (λ − λ² + λ³/3)  for λ < 1,   F = μ Fz  otherwise (full sliding)
    Fx = F · cx σx / ψ,          Fy = F · cy σy / ψ

with ``α`` the slip angle (wheel heading minus the direction of the wheel centre's velocity,
so a positive ``α`` pushes the wheel towards +y) and ``κ`` the longitudinal slip (positive
driving). The stiffness follows the load (source eq. 16-19): the tyre deflects ``d = Fz/kz``,
the contact half-length is ``a = √(r_u² − (r_u − d)²)`` and ``c = 2 a² c_p``.

Every function broadcasts over any shape of arrays (vehicles × cubature points × wheels).
"""

from __future__ import annotations

import numpy as np

from estimator._arrays import FloatArray

Values = FloatArray | float
"""An array or a plain number (every function broadcasts)."""

__all__ = ["brush_forces", "contact_half_length_m", "load_adaptive_stiffness_n", "utilisation"]

_TINY_N = 1e-9


def contact_half_length_m(fz_n: Values, kz_npm: Values, radius_m: Values) -> FloatArray:
    """Half-length ``a`` of the contact patch [m] from the deflection ``Fz/kz`` (eq. 18-19)."""
    d_m = np.clip(np.asarray(fz_n) / kz_npm, 0.0, radius_m)
    return np.sqrt(np.maximum(2.0 * radius_m * d_m - d_m * d_m, 0.0))


def load_adaptive_stiffness_n(
    fz_n: Values, kz_npm: Values, radius_m: Values, c_p_npm2: Values
) -> FloatArray:
    """Slip stiffness ``c = 2 a² c_p`` [N per unit slip] at load ``fz_n`` (eq. 16-17)."""
    a_m = contact_half_length_m(fz_n, kz_npm, radius_m)
    return 2.0 * a_m * a_m * c_p_npm2


def brush_forces(
    kappa: Values,
    alpha_rad: Values,
    fz_n: Values,
    mu: Values,
    cx_n: Values,
    cy_n: Values,
) -> tuple[FloatArray, FloatArray]:
    """Longitudinal and lateral tyre force ``(Fx, Fy)`` [N] of the combined-slip brush model.

    Inputs broadcast together; ``κ > −1``. ``Fz ≤ 0`` (a wheel off the ground) gives no force.
    """
    one_k = np.maximum(1.0 + np.asarray(kappa), 1e-3)
    sx = cx_n * (kappa / one_k)
    sy = cy_n * (np.tan(alpha_rad) / one_k)
    psi = np.hypot(sx, sy)
    cap_n = np.maximum(mu * np.maximum(fz_n, 0.0), _TINY_N)
    lam = np.minimum(psi / (3.0 * cap_n), 1.0)
    force = 3.0 * cap_n * lam * (1.0 - lam + lam * lam / 3.0)
    scale = np.where(psi > _TINY_N, force / np.maximum(psi, _TINY_N), 0.0)
    scale = np.where(fz_n > 0.0, scale, 0.0)
    return sx * scale, sy * scale


def utilisation(fx_n: Values, fy_n: Values, fz_n: Values, mu: Values) -> FloatArray:
    """Share of the available grip in use, ``hypot(Fx, Fy) / (μ Fz)`` (0..1; NaN without load)."""
    cap_n = mu * np.asarray(fz_n)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(cap_n > 0.0, np.hypot(fx_n, fy_n) / cap_n, np.nan)
