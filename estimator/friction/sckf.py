"""Square-root cubature Kalman filter (Arasaratnam & Haykin 2009), batched, with the source's
minimum-error-entropy (MEE) measurement covariance (``method.md`` §5, source 004 steps 5.1-5.17).

Shapes: ``B`` filters side by side (vehicles), ``n`` states, ``m`` measurements, ``2n``
equally weighted cubature points ``X_i = x + S ξ_i``, ``ξ = √n [I, −I]``. ``S`` is the lower
square root of the covariance (``P = S Sᵀ``), kept by QR: ``tria(A)`` is the lower triangular
``T`` with ``T Tᵀ = A Aᵀ`` (the transpose of the R of ``qr(Aᵀ)``, diagonal made positive).

``ckf_predict`` / ``ckf_update`` are the same filter on full covariances: the oracle the tests
hold the square-root form to.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from estimator._arrays import BoolArray, FloatArray

__all__ = [
    "MeeResult",
    "Update",
    "ckf_predict",
    "ckf_update",
    "cubature_points",
    "mee_measurement_sqrt",
    "sckf_predict",
    "sckf_update",
    "tria",
]

PointMap = Callable[[FloatArray], FloatArray]
"""Maps points ``(B, 2n, n)`` to ``(B, 2n, k)`` (the transition or the measurement function)."""


def tria(a: FloatArray) -> FloatArray:
    """Lower triangular ``T`` ``(B, r, r)``, ``T Tᵀ = A Aᵀ``, of ``A`` ``(B, r, k)``, ``k ≥ r``."""
    r = np.linalg.qr(np.swapaxes(a, -1, -2), mode="r")
    t = np.swapaxes(r, -1, -2)
    sign = np.where(np.diagonal(t, axis1=-2, axis2=-1) < 0.0, -1.0, 1.0)
    return t * sign[..., None, :]


def cubature_points(x: FloatArray, s: FloatArray) -> FloatArray:
    """The ``2n`` points ``x + S ξ_i`` ``(B, 2n, n)`` of means ``(B, n)``, roots ``(B, n, n)``."""
    n = x.shape[-1]
    spread = np.sqrt(n) * np.swapaxes(s, -1, -2)  # row j: √n · column j of S
    return x[..., None, :] + np.concatenate([spread, -spread], axis=-2)


def _centred(points: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Mean ``(B, k)`` and the weighted centred matrix ``(B, k, 2n)`` of points ``(B, 2n, k)``."""
    mean = points.mean(axis=-2)
    dev = (points - mean[..., None, :]) / np.sqrt(points.shape[-2])
    return mean, np.swapaxes(dev, -1, -2)


def sckf_predict(
    x: FloatArray, s: FloatArray, f: PointMap, sq_q: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Time update (steps 5.1-5.3): propagated mean and ``S⁻ = tria([X*, √Q])``."""
    mean, dev = _centred(f(cubature_points(x, s)))
    sq_q = np.broadcast_to(sq_q, s.shape)
    return mean, tria(np.concatenate([dev, sq_q], axis=-1))


@dataclass(frozen=True, slots=True)
class Update:
    """A measurement update's result and diagnostics.

    ``x`` ``(B, n)``, ``s`` ``(B, n, n)``; ``innovation`` ``(B, m)``; ``s_zz`` the innovation
    covariance's root ``(B, m, m)``; ``gain`` ``(B, n, m)``.
    """

    x: FloatArray
    s: FloatArray
    innovation: FloatArray
    s_zz: FloatArray
    gain: FloatArray


def sckf_update(
    x: FloatArray,
    s: FloatArray,
    z: FloatArray,
    h: PointMap,
    sq_r: FloatArray,
    gain_mask: FloatArray | None = None,
    z_centre: FloatArray | None = None,
) -> Update:
    """Measurement update (steps 5.11-5.16) with the measurement root ``sq_r`` ``(B, m, m)``.

    ``gain_mask`` ``(B, n)`` (optional, 0 or 1) zeroes the gain rows of states the update must
    leave alone (Schmidt's *consider* states: their uncertainty still enters ``P_zz``); the
    root ``S⁺ = tria([X − K Z, K √R])`` holds for any gain, so the covariance stays exact.
    ``z_centre`` ``(B, m)`` (optional) replaces the points' mean of ``h`` as the prediction the
    innovation is taken from (the spreads stay the points').
    """
    points = cubature_points(x, s)
    z_mean, z_dev = _centred(h(points))
    if z_centre is not None:
        z_mean = z_centre
    _, x_dev = _centred(points)
    s_zz = tria(np.concatenate([z_dev, sq_r], axis=-1))
    p_xz = x_dev @ np.swapaxes(z_dev, -1, -2)
    p_zz = s_zz @ np.swapaxes(s_zz, -1, -2)
    gain = np.swapaxes(np.linalg.solve(p_zz, np.swapaxes(p_xz, -1, -2)), -1, -2)
    if gain_mask is not None:
        gain = gain * gain_mask[..., None]
    innovation = z - z_mean
    x_new = x + (gain @ innovation[..., None])[..., 0]
    s_new = tria(np.concatenate([x_dev - gain @ z_dev, gain @ sq_r], axis=-1))
    return Update(x_new, s_new, innovation, s_zz, gain)


@dataclass(frozen=True, slots=True)
class MeeResult:
    """The MEE measurement root ``sq_r`` ``(B, m, m)`` and where it is positive definite
    (``ok`` ``(B,)``; elsewhere ``sq_r`` is the nominal root: the standard step runs)."""

    sq_r: FloatArray
    ok: BoolArray
    weight: FloatArray


def mee_measurement_sqrt(
    z: FloatArray, z_mean: FloatArray, n_states: int, sq_r: FloatArray, kernel_sigma: float
) -> MeeResult:
    """Measurement root re-estimated by the minimum-error-entropy criterion (steps 5.4-5.10).

    The augmented regression ``[x⁻; z] = [x; h(x)] + [−e_prior; v]`` whitened by
    ``B = diag(S⁻, √R)`` has, at ``x = x⁻``, the residuals ``e = [0 (n); √R⁻¹ (z − ẑ)]``.
    With ``Φ_ij = exp(−(e_i − e_j)² / 2σ²)`` each entry's weight is its mean kernel to the
    others, ``λ_i = Σ_{j≠i} Φ_ij / (L − 1)``; the source rebuilds ``R̄ = √R diag(λ̄ₓ/λ_y) √Rᵀ``
    from the diagonal (only ``R`` is replaced, so the measurement weights are taken relative
    to the states' mean ``λ̄ₓ``, the ratio the MEE fixed point uses). An entry far from every
    other gets ``λ → 0``: ``R̄`` is not positive definite and ``ok`` is False.
    """
    white = np.linalg.solve(sq_r, (z - z_mean)[..., None])[..., 0]
    b = white.shape[0]
    e = np.concatenate([np.zeros((b, n_states)), white], axis=-1)
    diff = e[..., :, None] - e[..., None, :]
    phi = np.exp(-0.5 * (diff / kernel_sigma) ** 2)
    lam = (phi.sum(axis=-1) - 1.0) / (e.shape[-1] - 1)
    lam_x = lam[..., :n_states].mean(axis=-1, keepdims=True)
    lam_y = lam[..., n_states:]
    ok = np.all(lam_y > 1e-12 * lam_x, axis=-1) & np.all(np.isfinite(white), axis=-1)
    weight = np.where(ok[..., None], lam_y / lam_x, 1.0)
    sq_bar = sq_r / np.sqrt(weight)[..., None, :]
    return MeeResult(np.where(ok[..., None, None], sq_bar, sq_r), ok, weight)


def _root(p: FloatArray) -> FloatArray:
    return np.asarray(np.linalg.cholesky(p), dtype=np.float64)


def ckf_predict(
    x: FloatArray, p: FloatArray, f: PointMap, q: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Cubature time update on full covariances ``P`` ``(B, n, n)`` (the SCKF's oracle)."""
    mean, dev = _centred(f(cubature_points(x, _root(p))))
    return mean, dev @ np.swapaxes(dev, -1, -2) + q


def ckf_update(
    x: FloatArray, p: FloatArray, z: FloatArray, h: PointMap, r: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Cubature measurement update on full covariances (the SCKF's oracle)."""
    points = cubature_points(x, _root(p))
    z_mean, z_dev = _centred(h(points))
    _, x_dev = _centred(points)
    p_zz = z_dev @ np.swapaxes(z_dev, -1, -2) + r
    p_xz = x_dev @ np.swapaxes(z_dev, -1, -2)
    gain = np.swapaxes(np.linalg.solve(p_zz, np.swapaxes(p_xz, -1, -2)), -1, -2)
    x_new = x + (gain @ (z - z_mean)[..., None])[..., 0]
    return x_new, p - gain @ p_zz @ np.swapaxes(gain, -1, -2)
