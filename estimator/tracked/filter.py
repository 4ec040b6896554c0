"""The INS/odometer/GNSS extended Kalman filter of the tracked estimator, batched over vehicles.

State :class:`~estimator.tracked.model.TrackedState` (``n = 21``), arrays ``x (k, n)``,
``P (k, n, n)``. Heading ``ψ`` is from north, clockwise; the gyro's yaw rate
``ω = (g_z − b_g)·(1 − s_g)`` is counter-clockwise about the hull's own up axis, the pitch and
roll gyros' rates less their biases are ``ω_x = g_x − b_θ``, ``ω_y = g_y − b_φ``. The hull's
attitude is Z-X-Y Euler angles (heading, pitch ``θ`` nose up, roll ``φ`` right side down):

    θ̇ = ω_x·cos φ + ω·sin φ       φ̇ = ω_y − tan θ·(ω·cos φ − ω_x·sin φ)
    ψ̇ = −Ω,  Ω = (ω·cos φ − ω_x·sin φ)/cos θ

(a turn on a side slope turns the yaw rate into pitch rate). Over a tick ``Δ``, with the
mid-tick heading ``ψ_m = ψ − Ω·Δ/2``, the hull's along-ground speed ``V`` and lateral speed
``v_x`` (right +: the turns' side-slip and, on a side slope, the creep downhill):

    E' = E + Δ·(V·cos θ·sin ψ_m + v_x·cos ψ_m)   N' = N + Δ·(V·cos θ·cos ψ_m − v_x·sin ψ_m)
    ψ' = ψ − Ω·Δ      V' = V + Δ·(f_y − b_y − g·sin θ − ω·v_x)      θ' = θ + Δ·θ̇      φ' = φ + Δ·φ̇

``f_y`` the forward specific force (the accelerometer reads gravity's ``g·sin θ`` on a
grade), ``b_y`` its bias (``ACCEL_BIAS_Y``). Updates are masked per vehicle; the Joseph
form keeps ``P`` symmetric positive definite.
"""

from __future__ import annotations

import numpy as np

from estimator._arrays import BoolArray, FloatArray
from estimator.tracked.model import N_STATES
from estimator.tracked.model import TrackedState as S

__all__ = ["GRAVITY_MPS2", "hull_accel", "kalman_update", "predict", "yaw_rate"]

GRAVITY_MPS2 = 9.80665


def yaw_rate(x: FloatArray, gyro_z_radps: FloatArray) -> FloatArray:
    """``ω = (g_z − b_g)·(1 − s_g)``, shape ``(k,)``."""
    return (gyro_z_radps - x[:, S.GYRO_BIAS]) * (1.0 - x[:, S.GYRO_SCALE])


def hull_accel(x: FloatArray, accel_fwd_mps2: FloatArray) -> FloatArray:
    """The hull's forward acceleration along the ground, ``f_y − b_y − g·sin θ`` ``(k,)``: the
    accelerometer's forward specific force less its bias, gravity taken out by the pitch."""
    return accel_fwd_mps2 - x[:, S.ACCEL_BIAS_Y] - GRAVITY_MPS2 * np.sin(x[:, S.PITCH])


def _attitude_rows(
    F: FloatArray, x: FloatArray, w: FloatArray, gyro: FloatArray, wx: FloatArray, dt_s: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The attitude's rates ``(Ω, θ̇, φ̇)`` ``(k,)`` and their rows of ``F`` (in place)."""
    theta, phi = x[:, S.PITCH], x[:, S.ROLL]
    ct, tt = np.cos(theta), np.tan(theta)
    cp, sp = np.cos(phi), np.sin(phi)
    scale = 1.0 - x[:, S.GYRO_SCALE]
    up = w * cp - wx * sp  # the rate about the vertical, times cos θ
    side = w * sp + wx * cp
    turn = up / ct
    h, p, r = S.HEADING, S.PITCH, S.ROLL
    F[:, h, S.GYRO_BIAS] = dt_s * scale * cp / ct
    F[:, h, S.GYRO_SCALE] = dt_s * (gyro - x[:, S.GYRO_BIAS]) * cp / ct
    F[:, h, p] = -dt_s * turn * tt
    F[:, h, r] = dt_s * side / ct
    F[:, h, S.PITCH_GYRO_BIAS] = -dt_s * sp / ct
    F[:, p, S.PITCH_GYRO_BIAS] = -dt_s * cp
    F[:, p, r] = dt_s * up
    F[:, p, S.GYRO_BIAS] = -dt_s * scale * sp
    F[:, r, S.ROLL_GYRO_BIAS] = -dt_s
    F[:, r, p] = -dt_s * up / (ct * ct)
    F[:, r, r] = 1.0 + dt_s * tt * side
    F[:, r, S.PITCH_GYRO_BIAS] = -dt_s * tt * sp
    F[:, r, S.GYRO_BIAS] = dt_s * tt * cp * scale
    return turn, side, -tt * up


def predict(
    x: FloatArray,
    P: FloatArray,
    gyro_z_radps: FloatArray,
    accel_fwd_mps2: FloatArray,
    lateral_mps: FloatArray,
    dt_s: float,
    q_diag: FloatArray,
    lateral_by_gain: FloatArray | None = None,
    tilt_rates_radps: tuple[FloatArray, FloatArray] | None = None,
    lateral_by_roll: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray]:
    """One tick of the model above; ``q_diag (k, n)`` is the process noise added to ``P``,
    ``lateral_by_gain (k,)`` and ``lateral_by_roll (k,)`` the derivatives of ``v_x`` by the
    side-slip gain and by the roll (a side slope's creep; 0 if None),
    ``tilt_rates_radps`` the pitch and roll gyros' mean rates over the tick ``(k,)`` each
    (0 if None)."""
    k = x.shape[0]
    w = yaw_rate(x, gyro_z_radps)
    zero = np.zeros(k)
    g_x, g_y = (zero, zero) if tilt_rates_radps is None else tilt_rates_radps
    wx = g_x - x[:, S.PITCH_GYRO_BIAS]
    F = np.broadcast_to(np.eye(N_STATES), (k, N_STATES, N_STATES)).copy()
    turn, d_pitch, roll_part = _attitude_rows(F, x, w, gyro_z_radps, wx, dt_s)
    theta = x[:, S.PITCH]
    ct, st = np.cos(theta), np.sin(theta)
    psi_m = x[:, S.HEADING] - 0.5 * turn * dt_s
    s, c = np.sin(psi_m), np.cos(psi_m)
    v, vx = x[:, S.SPEED], lateral_mps
    vh = v * ct  # horizontal
    out = x.copy()
    out[:, S.EAST] += dt_s * (vh * s + vx * c)
    out[:, S.NORTH] += dt_s * (vh * c - vx * s)
    out[:, S.HEADING] -= turn * dt_s
    out[:, S.SPEED] += dt_s * (hull_accel(x, accel_fwd_mps2) - w * vx)
    out[:, S.PITCH] += dt_s * d_pitch
    out[:, S.ROLL] += dt_s * (g_y - x[:, S.ROLL_GYRO_BIAS] + roll_part)
    F[:, S.EAST, S.HEADING] = dt_s * (vh * c - vx * s)
    F[:, S.NORTH, S.HEADING] = dt_s * (-vh * s - vx * c)
    F[:, S.EAST, S.SPEED] = dt_s * ct * s
    F[:, S.NORTH, S.SPEED] = dt_s * ct * c
    F[:, S.EAST, S.PITCH] = -dt_s * v * st * s
    F[:, S.NORTH, S.PITCH] = -dt_s * v * st * c
    F[:, S.SPEED, S.PITCH] = -dt_s * GRAVITY_MPS2 * ct
    F[:, S.SPEED, S.ACCEL_BIAS_Y] = -dt_s
    if lateral_by_gain is not None:
        F[:, S.EAST, S.SIDE_SLIP] = dt_s * c * lateral_by_gain
        F[:, S.NORTH, S.SIDE_SLIP] = -dt_s * s * lateral_by_gain
        F[:, S.SPEED, S.SIDE_SLIP] = -dt_s * w * lateral_by_gain
    if lateral_by_roll is not None:
        F[:, S.EAST, S.ROLL] = dt_s * c * lateral_by_roll
        F[:, S.NORTH, S.ROLL] = -dt_s * s * lateral_by_roll
        F[:, S.SPEED, S.ROLL] = -dt_s * w * lateral_by_roll
    P = F @ P @ np.swapaxes(F, 1, 2)
    idx = np.arange(N_STATES)
    P[:, idx, idx] += q_diag
    return out, 0.5 * (P + np.swapaxes(P, 1, 2))


def _inverse(Sm: FloatArray) -> FloatArray:
    """Inverse of each ``(m, m)`` innovation covariance; closed form for ``m`` = 1 and 2."""
    m = Sm.shape[-1]
    if m == 1:
        return 1.0 / Sm
    if m == 2:
        a, b, c, d = Sm[:, 0, 0], Sm[:, 0, 1], Sm[:, 1, 0], Sm[:, 1, 1]
        det = a * d - b * c
        adj = np.stack([np.stack([d, -b], axis=1), np.stack([-c, a], axis=1)], axis=1)
        out: FloatArray = adj / det[:, None, None]
        return out
    return np.asarray(np.linalg.inv(Sm), dtype=np.float64)


def kalman_update(
    x: FloatArray,
    P: FloatArray,
    innovation: FloatArray,
    H: FloatArray,
    R: FloatArray,
    mask: BoolArray,
    gate_nis: float | FloatArray = np.inf,
) -> tuple[FloatArray, FloatArray, FloatArray, BoolArray]:
    """Masked EKF update of ``m``-dimensional measurements.

    ``innovation (k, m)`` is ``z − h(x)``, ``H (k, m, n)``, ``R (k, m, m)``. Vehicles where
    ``mask`` is False, or whose NIS ``yᵀS⁻¹y`` exceeds ``gate_nis`` (a number, or one per
    vehicle), keep ``x`` and ``P``.
    Returns ``(x, P, nis (k,), used (k,))``; NIS is NaN where masked.
    """
    k = x.shape[0]
    rows = np.flatnonzero(mask)
    nis = np.full(k, np.nan)
    used = np.zeros(k, dtype=bool)
    if rows.size == 0:  # nobody measured: no (k, n, n) work at all
        return x, P, nis, used
    gate = np.broadcast_to(np.asarray(gate_nis, dtype=np.float64), (k,))
    if rows.size == k:
        return _update_rows(x, P, innovation, H, R, gate)
    x_r, P_r, nis[rows], used[rows] = _update_rows(
        x[rows], P[rows], innovation[rows], H[rows], R[rows], gate[rows]
    )
    x_out, P_out = x.copy(), P.copy()
    x_out[rows], P_out[rows] = x_r, P_r
    return x_out, P_out, nis, used


def _update_rows(
    x: FloatArray, P: FloatArray, y: FloatArray, H: FloatArray, R: FloatArray, gate: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, BoolArray]:
    """The update of :func:`kalman_update` for vehicles that all measured (each vehicle's
    products are its own, so a subset of rows gives the same numbers as the whole)."""
    Ht = np.swapaxes(H, 1, 2)
    Sm = H @ P @ Ht + R
    Sinv = _inverse(Sm)
    nis = np.einsum("ki,kij,kj->k", y, Sinv, y)
    used = np.isfinite(nis) & (nis <= gate)
    K = P @ Ht @ Sinv
    x_new = x + np.einsum("kij,kj->ki", K, y)
    IKH = np.eye(N_STATES)[None] - K @ H
    P_new = IKH @ P @ np.swapaxes(IKH, 1, 2) + K @ R @ np.swapaxes(K, 1, 2)
    P_new = 0.5 * (P_new + np.swapaxes(P_new, 1, 2))
    if used.all():
        return x_new, P_new, nis, used
    x_out = np.where(used[:, None], x_new, x)
    P_out = np.where(used[:, None, None], P_new, P)
    return x_out, P_out, nis, used
