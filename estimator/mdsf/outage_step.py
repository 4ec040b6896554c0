"""A slip step inside a GNSS outage, told from the inertial drift and from a turn.

While GNSS is lost the rims less the accelerometer's integral,

    r(t) = r̄W(t) − ∫ā·dt − Δ_lever(t) − ε_a(t)·V1(t)

(``r̄W`` the mean of both rim speeds, ``Δ_lever`` the wheels' mean ground speed less ``V1``,
``ε_a`` the slip level the outage reverts to, ``method.md`` §1 eq. (4)(5), (8)), moves
smoothly with the inertial error (a bias, a tilt leak: a line over a few seconds) and by
``δ·V1`` when the slip steps by ``δ``. A turn moves it too: the slip follows the lateral load,
a yaw misalignment leaks the lateral acceleration into ``ā``, an IMU ahead of the axle feels
the centripetal term. Over a window of ``2L`` ticks the test fits

    r_i = c0 + c1·t_i + β_load·V1_i·|ωz_i| + β_yaw·Σ_{j≤i} V1_j·ωz_j·dt
          + β_cent·Σ_{j≤i} ωz_j²·dt + g·Σ_{j≤i} (φ·sin ψ_j + θ·(cos ψ_j − 1))·dt
          + γ·(ε_a,i − ε̄_a)·V1_i + δ·V1_i·[i ≥ L] + w_i

(``ψ_j = Σ_{l≤j} ωz_l·dt`` the heading turned in the window: a tilt error ``(θ, φ)`` fixed in
the level frame leaks into the forward axis as the heading turns; ``γ`` the tyre model's level
off by a factor, which reads as a step when the demand moves across the middle)

with Gaussian priors on the turn coefficients and on ``δ`` (ridge: a step coincident with a
turn is shared by their prior variances, not given to the step), and reports ``δ`` at the
window's middle when its posterior mean is ``z_min`` posterior std from 0 and at least
``min_step``, where the speed is steady (for a linear model the likelihood ratio of the step
is ``z²``). The noise variance is the fit's residual variance (floored), so a noisier inertial
integral widens the test. The posterior mean is the step estimate: shrunk toward 0 by the
prior.

A step must also move the rims by more than one of their readings scatters: ``|δ|·V̄1`` (the
mean speed after the middle) at least ``rim_sigmas`` times ``σ_rim``, the rims' mean std as the
wheel front end reports it (``√((σ_L² + σ_R²)/4)``, its median over the window's ticks: the
few ticks of a wheel restarting near a stop carry a std that would mask the window). The fit's noise
is per tick; where the encoder gives few edges per fit (a slow wheel, a coarse ring) one
edge's error stays in the fits for several ticks and a run of them reads as a shift, while
the step's own size in speed, ``δ·V1``, shrinks with the speed.

The tilt error's prior is the front end's own: the window's mean pitch and roll variance of
the tilt track (large with one antenna in an outage, small with a receiver's attitude), so
the tilt competes with a step only as far as the track does not know its angles.
"""

from __future__ import annotations

import contextlib
import warnings
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from estimator._arrays import BoolArray, FloatArray
from estimator.mdsf.model import GRAVITY_MPS2

__all__ = [
    "StepBuf",
    "StepCol",
    "StepFit",
    "StepPrior",
    "step_columns",
    "step_inverse_prior",
    "step_test",
]


class StepBuf(IntEnum):
    """Channels of the per-vehicle window (:func:`step_test`'s ``buf``)."""

    R = 0  # rims less the inertial speed and the slip level [m/s]
    V1 = 1  # filter speed at the IMU [m/s]
    YAW = 2  # yaw rate [rad/s]
    OK = 3  # 1 where both rims were measured, else 0
    BIAS = 4  # the filter's accelerometer bias [m/s²] (not a regressor: what a step gives back)
    LEVEL = 5  # the tyre model's slip level ε_a without the steps taken (ratio) [-]
    PITCH_VAR = 6  # the tilt track's pitch variance [rad²] (NaN: unknown, the prior's tilt_rad)
    ROLL_VAR = 7  # the tilt track's roll variance [rad²] (NaN: unknown, the prior's tilt_rad)
    RIM_VAR = 8  # variance of the mean of both rim speeds, the wheel front end's [m²/s²]


class StepCol(IntEnum):
    """Columns of the test's regression."""

    LEVEL = 0
    TREND = 1
    TURN_LOAD = 2
    TURN_YAW = 3
    TURN_CENT = 4
    TILT_SIN = 5
    TILT_COS = 6
    GAIN = 7
    STEP = 8


@dataclass(frozen=True, slots=True)
class StepPrior:
    """Prior 1-sigma of the regression's coefficients and the test's thresholds.

    Attributes
    ----------
    load_s, yaw_rad, cent_m : float
        Turn coefficients: slip per lateral acceleration [s], yaw misalignment [rad], IMU
        forward offset [m].
    tilt_rad : float
        Tilt error fixed in the level frame, leaking ``g`` times it into ``ā`` as the heading
        turns, where the window carries no variance of the tilt track's [rad].
    tilt_floor_rad : float
        Floor of the tilt error's prior taken from the tilt track [rad].
    gain : float
        Relative error of the tyre model's level about its window mean [-].
    step : float
        Slip step (ratio) [-].
    noise_floor_mps : float
        Floor of the residual std [m/s].
    z_min : float
        Posterior mean over posterior std of ``δ`` above which a step is reported [-].
    min_step : float
        Smallest reported step (ratio) [-].
    rim_sigmas : float
        Smallest reported step's speed change ``|δ|·V̄1`` in units of the rims' mean std [-].
    min_speed_mps : float
        Mean ``V1`` after the window's middle below which nothing is reported [m/s].
    max_speed_change : float
        Change of the mean ``V1`` across the window's middle, as a share of it, above which
        nothing is reported: while the speed changes the slip moves with the demand through
        the tyre's relaxation (a braking dip), which a step cannot be told from [-].
    """

    load_s: float = 0.05
    yaw_rad: float = 0.05
    cent_m: float = 2.0
    tilt_rad: float = 0.035
    tilt_floor_rad: float = 1e-4
    gain: float = 1.0
    step: float = 0.05
    noise_floor_mps: float = 0.005
    z_min: float = 6.0
    min_step: float = 0.015
    rim_sigmas: float = 1.0
    min_speed_mps: float = 0.3
    max_speed_change: float = 0.4


@dataclass(slots=True)
class StepFit:
    """What :func:`step_test` found, shapes (k,): ``found``, the step ``delta`` (ratio, posterior
    mean; 0 where not found), its posterior variance ``delta_var`` and ``z``."""

    found: BoolArray
    delta: FloatArray
    delta_var: FloatArray
    z: FloatArray


def step_columns(buf: FloatArray, dt_s: float) -> FloatArray:
    """The regression's design ``A`` (k, N, len(StepCol)) from the window ``buf`` (k, C, N)."""
    k, _, n = buf.shape
    half = n // 2
    v1 = buf[:, StepBuf.V1]
    yaw = buf[:, StepBuf.YAW]
    a = np.empty((k, n, len(StepCol)))
    a[:, :, StepCol.LEVEL] = 1.0
    a[:, :, StepCol.TREND] = (np.arange(n) - half) * dt_s
    a[:, :, StepCol.TURN_LOAD] = v1 * np.abs(yaw)
    a[:, :, StepCol.TURN_YAW] = np.cumsum(v1 * yaw, axis=1) * dt_s
    a[:, :, StepCol.TURN_CENT] = np.cumsum(yaw * yaw, axis=1) * dt_s
    psi = np.cumsum(yaw, axis=1) * dt_s
    a[:, :, StepCol.TILT_SIN] = np.cumsum(GRAVITY_MPS2 * np.sin(psi), axis=1) * dt_s
    a[:, :, StepCol.TILT_COS] = np.cumsum(GRAVITY_MPS2 * (np.cos(psi) - 1.0), axis=1) * dt_s
    level = buf[:, StepBuf.LEVEL]
    a[:, :, StepCol.GAIN] = (level - level.mean(axis=1, keepdims=True)) * v1
    a[:, :, StepCol.STEP] = np.where(np.arange(n) >= half, v1, 0.0)
    return a


def step_inverse_prior(buf: FloatArray, prior: StepPrior) -> FloatArray:
    """``1/σ_j²`` of each window's coefficients, shape (k, len(StepCol)); 0 for level and trend.

    The tilt columns' ``σ`` is the tilt track's own over the window, ``√(mean var)`` of pitch
    (``TILT_COS``: the error along the heading at the window's start) and of roll
    (``TILT_SIN``), floored at ``tilt_floor_rad``; ``tilt_rad`` where the window has none.
    """
    k = buf.shape[0]
    inv = np.zeros((k, len(StepCol)))
    inv[:, StepCol.TURN_LOAD] = prior.load_s**-2
    inv[:, StepCol.TURN_YAW] = prior.yaw_rad**-2
    inv[:, StepCol.TURN_CENT] = prior.cent_m**-2
    inv[:, StepCol.GAIN] = prior.gain**-2
    inv[:, StepCol.STEP] = prior.step**-2
    for col, chan in ((StepCol.TILT_COS, StepBuf.PITCH_VAR), (StepCol.TILT_SIN, StepBuf.ROLL_VAR)):
        var = buf[:, chan].mean(axis=1)
        var = np.where(
            np.isfinite(var), np.maximum(var, prior.tilt_floor_rad**2), prior.tilt_rad**2
        )
        inv[:, col] = 1.0 / var
    return inv


def step_test(buf: FloatArray, dt_s: float, prior: StepPrior) -> StepFit:
    """Test each window ``buf`` (k, C, N; channels :class:`StepBuf`, oldest tick first) for a
    slip step between ticks ``N//2 − 1`` and ``N//2`` (module docstring).

    Ridge regression ``θ = (AᵀWA + σ̂²Λ)⁻¹AᵀWr`` with ``Λ = diag(1/σ_j²)`` per window
    (:func:`step_inverse_prior`) and ``W`` the rows' ``OK`` weights; ``σ̂²`` the residual
    variance of the unpenalised fit's degrees of freedom, floored at ``noise_floor_mps²``,
    found by two passes (the first with the floor). Posterior covariance ``σ̂²(AᵀWA + σ̂²Λ)⁻¹``.
    A window whose fit overflows (inputs far outside any drive's, e.g. a corrupted sensor's
    inertial speed) finds no step; the other windows are solved as they would be alone.
    """
    with np.errstate(over="ignore", invalid="ignore"):
        delta, delta_var, z, n_ok = _fit(buf, dt_s, prior)
        half = buf.shape[2] // 2
        w = buf[:, StepBuf.OK]
        after = np.abs(buf[:, StepBuf.V1, half:]).mean(axis=1)
        before = np.abs(buf[:, StepBuf.V1, :half]).mean(axis=1)
        fast = after >= prior.min_speed_mps
        fast &= np.abs(after - before) <= prior.max_speed_change * np.maximum(after, before)
        full = n_ok >= 0.8 * buf.shape[2]
        rim_sd = np.sqrt(_median_ok(buf[:, StepBuf.RIM_VAR], w > 0))
        seen = np.abs(delta) * after >= prior.rim_sigmas * rim_sd
        found = fast & full & seen & (np.abs(z) >= prior.z_min) & (np.abs(delta) >= prior.min_step)
        found &= np.isfinite(delta) & np.isfinite(delta_var)
    return StepFit(found, np.where(found, delta, 0.0), delta_var, z)


def _fit(
    buf: FloatArray, dt_s: float, prior: StepPrior
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """The ridge fit of :func:`step_test`: the step ``delta``, its variance, ``z`` and the
    window's count of ``OK`` ticks, each (k,)."""
    a = step_columns(buf, dt_s)
    w = buf[:, StepBuf.OK]
    r = np.where(w > 0, buf[:, StepBuf.R], 0.0)
    lam = np.zeros((buf.shape[0], len(StepCol), len(StepCol)))
    diag = np.arange(len(StepCol))
    lam[:, diag, diag] = step_inverse_prior(buf, prior)
    ata = np.einsum("kni,kn,knj->kij", a, w, a)
    atr = np.einsum("kni,kn,kn->ki", a, w, r)
    n_ok = w.sum(axis=1)
    dof = np.maximum(n_ok - len(StepCol), 1.0)
    var = np.full(buf.shape[0], prior.noise_floor_mps**2)
    for _ in range(2):
        cov = _inverse(ata + var[:, None, None] * lam)
        theta = np.einsum("kij,kj->ki", cov, atr)
        res = r - np.einsum("kni,ki->kn", a, theta)
        var = np.maximum((w * res * res).sum(axis=1) / dof, prior.noise_floor_mps**2)
    cov = _inverse(ata + var[:, None, None] * lam)
    theta = np.einsum("kij,kj->ki", cov, atr)
    delta = theta[:, StepCol.STEP]
    delta_var = var * cov[:, StepCol.STEP, StepCol.STEP]
    z = delta / np.sqrt(np.maximum(delta_var, 1e-30))
    return delta, delta_var, z, n_ok


def _median_ok(x: FloatArray, ok: BoolArray) -> FloatArray:
    """Median of each window's ``x`` (k, N) over its ``ok`` ticks, (k,); 0 where none is."""
    masked = np.where(ok, x, np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        med = np.nanmedian(masked, axis=1)
    return np.where(ok.any(axis=1), med, 0.0)


def _inverse(m: FloatArray) -> FloatArray:
    """``m⁻¹`` per window, (k, n, n); NaN for a window whose matrix is singular (a window
    of degenerate inputs, e.g. a speed of 0 throughout), so that it finds no step while the
    other windows are solved as they would be alone."""
    try:
        return np.asarray(np.linalg.inv(m))
    except np.linalg.LinAlgError:
        out = np.full_like(m, np.nan)
        for i in range(m.shape[0]):
            with contextlib.suppress(np.linalg.LinAlgError):
                out[i] = np.linalg.inv(m[i])
        return out
