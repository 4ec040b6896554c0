"""Reference speed from acceleration and wheel speed, ``method.md`` §3 (source 001, second part).

State ``[v, a0]``: speed and the accelerometer's slowly varying bias. With ``a_m`` the measured
(gravity-free) forward acceleration over one step ``dT`` (the source's transition, whose printed
matrix is garbled, discretised consistently)::

    v(k+1)  = v(k) − dT·a0(k) + dT·a_m(k) + w1
    a0(k+1) = a0(k) + w2,          w2 = 0.527·(a_f(k) − a_f(k−1))   (adaptive, source 001)

``a_f`` is the low-passed acceleration: the bias noise opens while the acceleration changes
(the bias is then least observable against the wheel speed) and closes in steady driving.

Measurement ``v_m = v + w_v``:

* while GNSS is good the MDSF speed is the measurement, so the filter learns the bias, and the
  ratio ``c = V0/(r·W)`` between ground speed and mean rim speed is tracked (low-passed): it is
  ``1/(1 + slip)`` to first order;
* while GNSS is lost the rim speed corrected by that ratio, ``v_m = c·r·W``, is the measurement
  (the source's slip correction ``s = (v − v_m)/v`` with the last known slip), with a variance
  that grows with the time since GNSS was lost (slip drifts). This is the DEGRADED mode.

All functions work on a batch dimension ``N`` (vectorised over vehicles).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import numpy as np
import numpy.typing as npt

from estimator import kalman
from estimator._arrays import FloatArray
from estimator.config import ConfigError

__all__ = ["RefAux", "RefState", "ReferenceSpeedConfig", "reference_step", "transition"]


class RefState(IntEnum):
    """Indices of the reference-speed state ``[v, a0]``."""

    V = 0
    A0 = 1


class RefAux(IntEnum):
    """Indices of the auxiliary per-vehicle values carried between steps."""

    ACCEL_FILTERED = 0
    """``a_f``, low-passed acceleration [m/s²]."""
    WHEEL_RATIO = 1
    """``c``, ground speed over mean rim speed (1 without slip)."""
    LOST_S = 2
    """Time since the last speed reference (GNSS) [s]."""


@dataclass(frozen=True, slots=True)
class ReferenceSpeedConfig:
    """Settings of the reference-speed filter.

    Attributes
    ----------
    accel_std_mps2 : float
        Noise of the step-mean acceleration (drives ``w1 = dT·noise``) [m/s²].
    bias_gain : float
        Source constant of the adaptive bias noise, ``w2 = bias_gain·Δa_f`` (0.527).
    bias_walk_mps2_per_sqrt_s : float
        Floor of the bias random walk [m/s²/√s].
    accel_filter_tau_s : float
        Time constant of ``a_f`` [s].
    wheel_rel_std : float
        Relative 1-sigma error of the slip-corrected wheel speed right after GNSS is lost.
    wheel_rel_std_growth_per_s : float
        Growth of that relative error per second of outage (slip changes).
    ratio_tau_s : float
        Time constant of the tracked ground/rim speed ratio [s].
    min_speed_mps : float
        Below this rim speed the ratio is not updated and the wheel measurement is absolute.
    """

    accel_std_mps2: float = 0.05
    bias_gain: float = 0.527
    bias_walk_mps2_per_sqrt_s: float = 0.003
    accel_filter_tau_s: float = 0.5
    wheel_rel_std: float = 0.02
    wheel_rel_std_growth_per_s: float = 0.002
    ratio_tau_s: float = 3.0
    min_speed_mps: float = 0.3

    def __post_init__(self) -> None:
        for f in (
            "accel_std_mps2",
            "bias_gain",
            "bias_walk_mps2_per_sqrt_s",
            "accel_filter_tau_s",
            "wheel_rel_std",
            "wheel_rel_std_growth_per_s",
            "ratio_tau_s",
            "min_speed_mps",
        ):
            v = getattr(self, f)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise ConfigError(f"{f} must be a finite number > 0, got {v!r}")


def transition(dt_s: float) -> tuple[FloatArray, FloatArray]:
    """``F`` (2, 2) and the input column ``B`` (2,) of ``method.md`` §3:
    ``v' = v − dT·a0 + dT·a_m``, ``a0' = a0``."""
    F = np.array([[1.0, -dt_s], [0.0, 1.0]])
    B = np.array([dt_s, 0.0])
    return F, B


def reference_step(
    x: FloatArray,
    P: FloatArray,
    aux: FloatArray,
    accel_mps2: FloatArray,
    dt_s: float,
    speed_ref_mps: FloatArray,
    speed_ref_var: FloatArray,
    rim_speed_mps: FloatArray,
    config: ReferenceSpeedConfig,
) -> tuple[FloatArray, FloatArray, FloatArray, npt.NDArray[np.bool_]]:
    """One batched step of the reference-speed filter, ``method.md`` §3.

    Parameters
    ----------
    x : ndarray, shape (N, 2)
        ``[v, a0]``.
    P : ndarray, shape (N, 2, 2)
    aux : ndarray, shape (N, 3)
        See :class:`RefAux`.
    accel_mps2 : ndarray, shape (N,)
        Mean gravity-free forward acceleration over the step; NaN if unknown (then 0 is used
        with a larger noise).
    dt_s : float
        Step ``dT`` [s].
    speed_ref_mps : ndarray, shape (N,)
        GNSS-backed speed (MDSF ``V0``) when GNSS is good, NaN while it is lost.
    speed_ref_var : ndarray, shape (N,)
        Its variance.
    rim_speed_mps : ndarray, shape (N,)
        Mean rim speed ``r·W`` of the driven wheels; NaN if unknown.
    config : ReferenceSpeedConfig

    Returns
    -------
    x, P, aux : updated arrays, same shapes
    used_wheels : ndarray, shape (N,), bool
        The wheel speed was the measurement (GNSS lost).
    """
    xp, Pp, af = _predict(x, P, aux[:, RefAux.ACCEL_FILTERED], accel_mps2, dt_s, config)
    have_ref = np.isfinite(speed_ref_mps)
    rim_ok = np.isfinite(rim_speed_mps)
    lost = np.where(have_ref, 0.0, aux[:, RefAux.LOST_S] + dt_s)
    moving = rim_ok & (np.abs(np.where(rim_ok, rim_speed_mps, 0.0)) >= config.min_speed_mps)
    ratio = _track_wheel_ratio(
        aux[:, RefAux.WHEEL_RATIO], speed_ref_mps, rim_speed_mps, moving, have_ref, dt_s, config
    )
    use_wheels = ~have_ref & rim_ok
    vm = np.where(
        have_ref, speed_ref_mps, np.where(moving, ratio, 1.0) * np.where(rim_ok, rim_speed_mps, 0.0)
    )
    rel = config.wheel_rel_std + config.wheel_rel_std_growth_per_s * lost
    wheel_var = (rel * np.abs(np.where(rim_ok, rim_speed_mps, 0.0))) ** 2 + 0.02**2
    r = np.where(have_ref, np.maximum(speed_ref_var, 1e-6), wheel_var)
    mask = (have_ref | use_wheels)[:, None]
    res = kalman.update(xp, Pp, vm[:, None], np.array([[1.0, 0.0]]), r[:, None, None], mask)
    aux_new = np.stack([af, ratio, lost], axis=1)
    return res.x, res.P, aux_new, use_wheels


def _predict(
    x: FloatArray,
    P: FloatArray,
    af_old: FloatArray,
    accel_mps2: FloatArray,
    dt_s: float,
    config: ReferenceSpeedConfig,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Prediction of :func:`reference_step` with its adaptive bias noise; ``(x⁻, P⁻, a_f)``."""
    n = x.shape[0]
    F, B = transition(dt_s)
    a_ok = np.isfinite(accel_mps2)
    a_m = np.where(a_ok, accel_mps2, 0.0)
    a_var = np.where(a_ok, config.accel_std_mps2**2, 1.0)
    # Adaptive bias noise from the change of the filtered acceleration (source: w2 = 0.527·Δa_f).
    alpha = dt_s / (config.accel_filter_tau_s + dt_s)
    af = np.where(a_ok, af_old + alpha * (a_m - af_old), af_old)
    w2 = config.bias_gain * (af - af_old)
    Q = np.zeros((n, 2, 2))
    Q[:, RefState.V, RefState.V] = dt_s * dt_s * a_var
    Q[:, RefState.A0, RefState.A0] = w2 * w2 + config.bias_walk_mps2_per_sqrt_s**2 * dt_s
    u = np.zeros((n, 2))
    u[:, RefState.V] = B[RefState.V] * a_m
    xp, Pp = kalman.predict(x, P, F, Q, u)
    return xp, Pp, af


def _track_wheel_ratio(
    ratio: FloatArray,
    speed_ref_mps: FloatArray,
    rim_speed_mps: FloatArray,
    moving: npt.NDArray[np.bool_],
    have_ref: npt.NDArray[np.bool_],
    dt_s: float,
    config: ReferenceSpeedConfig,
) -> FloatArray:
    """The ground/rim speed ratio, low-passed while the reference is there and the wheels turn."""
    beta = dt_s / (config.ratio_tau_s + dt_s)
    with np.errstate(divide="ignore", invalid="ignore"):
        inst = np.where(
            moving & have_ref, speed_ref_mps / np.where(moving, rim_speed_mps, 1.0), ratio
        )
    inst = np.clip(inst, 0.3, 3.0)
    return np.where(moving & have_ref, ratio + beta * (inst - ratio), ratio)
