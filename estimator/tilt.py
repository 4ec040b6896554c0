"""Tilt (pitch and roll) and heading tracks: body rates integrated, corrected at GNSS fixes.

Gravity is taken out of the forward acceleration with the pitch (``method.md`` §1, gravity
removal), so the pitch must hold between fixes and through outages. Pitch ``θ`` and roll ``φ``
are one tilt ``z = θ + iφ``. The Euler kinematics ``θ̇ = ωx·cos φ + ωz·sin φ``,
``φ̇ = ωy − tan θ·(ωz·cos φ − ωx·sin φ)`` are, to first order in the angles,

    ż = (ωx − b_x) + i·(ωy − b_y) − i·ωz·z,

solved between fixes in closed form with ``Ψ(t) = ∫ωz dt`` over segmented cumulative sums of the
samples (:func:`tilt_integrals`, :func:`tilt_at`):
``z(t) = e^{−iΨ(t)}·[e^{iΨ(t₀)}·z(t₀) + ∫e^{iΨ}·(ωx + iωy) dt − (b_x + i·b_y)·∫e^{iΨ} dt]``.
A turn on a side slope thus turns the bank's roll into pitch and back. At each fix angle and
gyro bias are a two-state Kalman filter (:func:`pitch_kf_update`, for the pitch and, the same,
for the roll); the source's mode takes each GNSS pitch as it is (:func:`pitch_fix_update`). The
heading track learns the yaw-gyro bias (:func:`yaw_fix_update`).

Every function takes arrays of vehicles (one entry per vehicle with this fix), so a fleet's
tracks update together. Columns are named by :class:`Integral`, :class:`PitchSum`,
:class:`RollSum` and :class:`AngleCov`. Settings come from any object with the attributes of
:class:`TiltSettings` (e.g. :class:`estimator.mdsf.MdsfConfig`).
"""

from __future__ import annotations

from enum import IntEnum
from typing import Protocol

import numpy as np

from estimator._arrays import BoolArray, CArray, FloatArray, IntArray, seg_cumsum

__all__ = [
    "N_INTEGRALS_UNCOUPLED",
    "PITCH_SUM_OF",
    "ROLL_SUM_OF",
    "AngleCov",
    "Integral",
    "PitchSum",
    "RollSum",
    "TiltSettings",
    "angle_var_after",
    "pitch_fix_update",
    "pitch_kf_update",
    "shrunk_roll",
    "tilt_at",
    "tilt_integrals",
    "yaw_fix_update",
]

_NS = 1e-9
_TWO_PI = 2 * np.pi


class TiltSettings(Protocol):
    """Settings the tracks read (1-sigma noises; :class:`estimator.mdsf.MdsfConfig` has them)."""

    @property
    def pitch_std_rad(self) -> float: ...  # noise of a measured angle [rad]
    @property
    def gyro_bias_std_radps(self) -> float: ...  # prior std of a gyro bias [rad/s]
    @property
    def gyro_bias_walk_radps_per_sqrt_s(self) -> float: ...  # bias random walk [rad/s/√s]
    @property
    def gate_chi2(self) -> float: ...  # chi-square gate of the standstill update [-]
    @property
    def attitude_tau_s(self) -> float: ...  # heading's pull to the GNSS heading [s]
    @property
    def gyro_bias_tau_s(self) -> float: ...  # yaw-gyro bias learning [s]


class Integral(IntEnum):
    """Columns of :func:`tilt_integrals`, each summed from a row's first sample.

    The first three are all the source's mode needs; the rest feed the coupled tilt, the angle
    noise and the accelerometer's pitch and roll."""

    TIME = 0  # ∫dt
    RATE_X = 1  # ∫ωx·dt
    SAMPLES = 2  # number of samples
    TURNED_RATE_RE = 3  # ∫e^{iΨ}·(ωx + iωy)·dt, real part
    TURNED_RATE_IM = 4  # its imaginary part
    TURN_RE = 5  # ∫e^{iΨ}·dt, real part
    TURN_IM = 6  # its imaginary part
    RATE_Y = 7  # ∫ωy·dt
    GYRO_VAR = 8  # Σσ²·dt², the gyro's white noise as angle variance
    YAW_RATE_SQ = 9  # ∫ωz²·dt
    FORCE_LAT = 10  # ∫f_x·dt over the samples with a lateral force
    FORCE_LAT_TIME = 11  # ∫dt over those samples
    FORCE_FWD = 12  # ∫f_y·dt


N_INTEGRALS_UNCOUPLED = 3
"""Columns :func:`tilt_integrals` gives without the coupled tilt (``TIME``..``SAMPLES``)."""


class PitchSum(IntEnum):
    """What a pitch track sums over the interval since its last fix."""

    ANGLE_VAR = 0  # angle noise variance added [rad²]
    RATE = 1  # ∫ωx·dt [rad]
    TIME = 2  # ∫dt [s]
    SAMPLES = 3  # number of samples
    FORCE_FWD = 4  # ∫f_y·dt [m/s]


class RollSum(IntEnum):
    """What a roll track sums over the interval since its last fix."""

    ANGLE_VAR = 0  # angle noise variance added [rad²]
    RATE = 1  # ∫ωy·dt [rad]
    FORCE_LAT = 2  # ∫f_x·dt [m/s]
    FORCE_LAT_TIME = 3  # ∫dt over the samples with a lateral force [s]
    YAW = 4  # ∫ωz·dt [rad]
    RATE_Y_CHANGE = 5  # ωy(end) − ωy(start) [rad/s]: the roll rate's change over the interval
    RATE_Z_CHANGE = 6  # ωz(end) − ωz(start) [rad/s]
    LAST_RATE_Y = 7  # ωy of the last sample summed (kept through a fix) [rad/s]
    LAST_RATE_Z = 8  # ωz of the same [rad/s]
    HAS_LAST = 9  # 1 once a sample was summed, else 0


PITCH_SUM_OF = np.array([Integral.RATE_X, Integral.TIME, Integral.SAMPLES], dtype=np.intp)
"""Integral columns of :attr:`PitchSum.RATE`, ``TIME``, ``SAMPLES`` (in that order)."""
ROLL_SUM_OF = np.array(
    [Integral.RATE_Y, Integral.FORCE_LAT, Integral.FORCE_LAT_TIME], dtype=np.intp
)
"""Integral columns of :attr:`RollSum.RATE`, ``FORCE_LAT``, ``FORCE_LAT_TIME``."""


class AngleCov(IntEnum):
    """Covariance of an angle and its gyro's bias, ``[P_aa, P_ab, P_bb]``."""

    ANGLE = 0
    CROSS = 1
    BIAS = 2


# ---------------------------------------------------------------------------------------------
# Between fixes
# ---------------------------------------------------------------------------------------------


def tilt_integrals(
    dts: FloatArray,
    wx: FloatArray,
    wy: FloatArray,
    wz: FloatArray,
    fx: FloatArray,
    fy: FloatArray,
    gyro_var: FloatArray,
    begin_of: IntArray,
    coupled: bool,
) -> tuple[FloatArray, FloatArray, CArray]:
    """The integrals of every sample since its row's first, :class:`Integral` columns.

    Parameters
    ----------
    dts : ndarray, shape (n,)
        Time step ending at each sample [s].
    wx, wy, wz : ndarray, shape (n,)
        Body rates (pitch, roll, yaw axes) [rad/s].
    fx, fy : ndarray, shape (n,)
        Lateral (NaN: none) and forward specific force [m/s²].
    gyro_var : ndarray, shape (n,)
        Gyro noise variance of each sample's vehicle [(rad/s)²].
    begin_of : ndarray, shape (n,), int
        Index of each sample's row's first sample.
    coupled : bool
        Compute the coupled tilt's columns; otherwise only the first
        :data:`N_INTEGRALS_UNCOUPLED` and ``Ψ = 0``.

    Returns
    -------
    (cum (n, c), psi (n,), rot (n,))
        The integrals, ``Ψ = ∫ωz·dt`` and ``e^{iΨ}``.
    """
    n = dts.shape[0]
    cols = [dts, wx * dts, np.ones(n)]
    psi = np.zeros(n)
    rot = np.ones(n, dtype=np.complex128)
    if coupled:
        psi = seg_cumsum(wz * dts, begin_of)
        rot = np.exp(1j * psi)
        u = rot * (wx + 1j * wy) * dts
        cols += [u.real, u.imag, rot.real * dts, rot.imag * dts, wy * dts]
        cols += [gyro_var * dts * dts, wz * wz * dts]
        has_fx = np.isfinite(fx)
        cols += [np.where(has_fx, fx, 0.0) * dts, has_fx * dts, fy * dts]
    return seg_cumsum(np.column_stack(cols), begin_of), psi, rot


def tilt_at(
    cum: FloatArray,
    rot: CArray,
    m: IntArray | slice,
    a: CArray,
    beta: CArray,
    coupled: BoolArray,
    coupled_model: bool,
) -> CArray:
    """``θ + iφ`` at samples ``m`` of segments with parameters ``a``, ``beta``.

    Uncoupled: ``θ = Re a + ∫ωx·dt − Re β·∫dt``, ``φ = Im a``. Coupled (where ``coupled`` and
    ``coupled_model``): ``e^{−iΨ}·(a + ∫e^{iΨ}·(ωx + iωy)·dt − β·∫e^{iΨ}·dt)``. ``cum`` and
    ``rot`` are :func:`tilt_integrals`' ``(n, c)`` and ``(n,)``; ``a``, ``beta``, ``coupled`` have
    the shape of ``cum[m]``'s rows.
    """
    c = cum[m] if isinstance(m, slice) else np.take(cum, m, axis=0)
    flat = None
    if not (coupled_model and coupled.all()):
        flat = (a.real + c[:, Integral.RATE_X] - beta.real * c[:, Integral.TIME]) + 1j * a.imag
    if not (coupled_model and coupled.any()):
        assert flat is not None
        return flat
    cz = c[:, Integral.TURNED_RATE_RE] + 1j * c[:, Integral.TURNED_RATE_IM]
    ez = c[:, Integral.TURN_RE] + 1j * c[:, Integral.TURN_IM]
    z = rot[m].conj() * (a + cz - beta * ez)
    return z if flat is None else np.where(coupled, z, flat)


def shrunk_roll(roll_rad: FloatArray, var_rad2: FloatArray) -> FloatArray:
    """``φ·φ²/(φ² + var)``: a roll estimate shrunk toward 0 by its noise; NaN (unknown) → 0."""
    p2 = np.where(np.isfinite(roll_rad), roll_rad * roll_rad, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(p2 > 0, roll_rad * p2 / (p2 + var_rad2), 0.0)


# ---------------------------------------------------------------------------------------------
# At a fix (arrays of vehicles: one entry per vehicle that has this fix)
# ---------------------------------------------------------------------------------------------


def _fix_gap_s(stamp_ns: IntArray, fix_ns: IntArray) -> FloatArray:
    """Time since a track's previous fix, clipped to [0, 1] s (the per-fix updates' ``gap``)."""
    return np.minimum(np.maximum((stamp_ns - fix_ns) * _NS, 0.0), 1.0)


def pitch_fix_update(
    theta_rad: FloatArray,
    var_rad2: FloatArray,
    bias_radps: FloatArray,
    fix_ns: IntArray,
    known: BoolArray,
    pitch_gnss_rad: FloatArray,
    stamp_ns: IntArray,
    config: TiltSettings,
) -> tuple[FloatArray, FloatArray, FloatArray, IntArray, BoolArray]:
    """Paper-mode pitch at one GNSS pitch per vehicle (all arrays shape ``(k,)``).

    ``method.md`` §1, eq. (1): the source takes the pitch ``θ`` of eq. (1) as measured, so each
    GNSS pitch ``p`` sets ``θ = p`` with variance ``pitch_std_rad²``, whatever the track held;
    the pitch-gyro bias is left as it is (the source has none). A NaN pitch changes nothing.
    Product mode runs :func:`pitch_kf_update` instead.

    Returns the new ``(theta_rad, var_rad2, bias_radps, fix_ns, known)``.
    """
    has = np.isfinite(pitch_gnss_rad)
    theta = np.where(has, pitch_gnss_rad, theta_rad)
    var = np.where(has, config.pitch_std_rad**2, var_rad2)
    return theta, var, bias_radps.copy(), np.where(has, stamp_ns, fix_ns), known | has


def _standstill_bias_update(
    state: tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray],
    known: BoolArray,
    rate_radps: FloatArray,
    rate_var: FloatArray,
    gate_chi2: float,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """The standstill update of :func:`pitch_kf_update`: when the vehicle stood through the
    interval (the caller passes the interval's mean pitch rate ``rate_radps`` and its variance,
    NaN otherwise) the body did not rotate, so the gyro read its bias, ``z = b + noise`` (``H =
    [0, 1]``), chi-square gated; ``state`` is ``(θ, b, P_θθ, P_θb, P_bb)``, each ``(k,)``,
    returned updated where ``rate_radps`` is finite."""
    theta, bias, ptt, ptb, pbb = state
    with np.errstate(invalid="ignore"):
        s = pbb + rate_var
        yb = rate_radps - bias
        use = known & np.isfinite(rate_radps) & (yb * yb <= gate_chi2 * s)
    s = np.where(use, s, 1.0)
    yb = np.where(use, yb, 0.0)
    kt, kb = ptb / s, pbb / s
    return (
        theta + np.where(use, kt * yb, 0.0),
        bias + np.where(use, kb * yb, 0.0),
        np.where(use, ptt - kt * ptb, ptt),
        np.where(use, ptb - kt * pbb, ptb),
        np.where(use, pbb - kb * pbb, pbb),
    )


def pitch_kf_update(
    theta_rad: FloatArray,
    cov: FloatArray,
    bias_radps: FloatArray,
    fix_ns: IntArray,
    known: BoolArray,
    pitch_gnss_rad: FloatArray,
    stamp_ns: IntArray,
    config: TiltSettings,
    pitch_var_rad2: FloatArray | None = None,
    angle_walk_rad2: FloatArray | None = None,
    still_rate_radps: FloatArray | None = None,
    still_rate_var: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray, IntArray, BoolArray]:
    """Pitch and pitch-gyro bias ``[θ, b_x]`` as a Kalman filter, at one fix per vehicle;
    returns ``(theta_rad, cov, bias_radps, fix_ns, known)`` after the fix.

    Product mode (``method.md`` §1, gravity removal): the pitch rate integrated with the bias
    in force between fixes (:func:`_pitch_prior_cov`); at the fix a standstill update of the
    bias, then the GNSS pitch of variance ``pitch_var_rad2`` (default ``pitch_std_rad²``;
    :func:`_fix_updates`). The gains follow from the variances: the pitch averages the
    receiver's over as long as the gyro holds it, so the gravity leaking through its error
    (``g·δθ``) varies slowly, for the speed filter's accelerometer bias and RTK distance.

    Parameters
    ----------
    theta_rad, bias_radps, cov : ndarray, shape (k,), (k,), (k, 3)
        Pitch integrated up to the fix, the bias in force, covariance ``[P_θθ, P_θb, P_bb]``.
    fix_ns, stamp_ns, known : ndarray, shape (k,), int, int, bool
        Time of the previous fix of each track, of this one; the track has had a pitch.
    pitch_gnss_rad : ndarray, shape (k,)
        Measured pitch; NaN: no pitch update (the standstill update still applies).
    angle_walk_rad2 : ndarray, shape (k,), optional
        Variance the integrated rate's noise added since the previous fix.
    still_rate_radps, still_rate_var : ndarray, shape (k,), optional
        Standstill rate measurement of the bias and its variance (NaN: not standing).
    """
    k = theta_rad.shape[0]
    r2 = np.full(k, config.pitch_std_rad**2) if pitch_var_rad2 is None else pitch_var_rad2
    prior = _pitch_prior_cov(cov, fix_ns, known, stamp_ns, config, angle_walk_rad2)
    has = np.isfinite(pitch_gnss_rad)
    still = (still_rate_radps, still_rate_var)
    theta, bias, out = _fix_updates(
        (theta_rad, bias_radps, *prior), known, has, pitch_gnss_rad, r2, config, still
    )
    return theta, out, bias, np.where(has | known, stamp_ns, fix_ns), known | has


def angle_var_after(
    cov: FloatArray, gap_s: FloatArray, bias_walk_radps_per_sqrt_s: float
) -> FloatArray:
    """Variance of an angle integrated ``gap_s`` (k,) past its last fix with the bias in force,
    from its covariance there ``cov`` (k, 3; :class:`AngleCov`): ``P_aa − 2T·P_ab + T²·P_bb``
    plus the bias walk's ``q_b·T³/3`` (the gyro's white angle noise left out: small beside the
    bias's growth). Shape (k,) [rad²]."""
    return _propagate_angle_cov(cov, gap_s, np.zeros_like(gap_s), bias_walk_radps_per_sqrt_s**2)[0]


def _pitch_prior_cov(
    cov: FloatArray,
    fix_ns: IntArray,
    known: BoolArray,
    stamp_ns: IntArray,
    config: TiltSettings,
    angle_walk_rad2: FloatArray | None,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``(P_θθ, P_θb, P_bb)``, each ``(k,)``, carried from the previous fix to ``stamp_ns``: the
    pitch error grows as ``δθ' = δθ − T·δb`` plus the gyro's angle noise over the interval
    (``angle_walk_rad2``, summed over the samples by the caller; 0 if None), the bias is a
    random walk (``gyro_bias_walk_radps_per_sqrt_s``); no growth before a track's first fix."""
    q_ang = np.zeros(cov.shape[0]) if angle_walk_rad2 is None else angle_walk_rad2
    gap = np.where(known, np.maximum((stamp_ns - fix_ns) * _NS, 0.0), 0.0)
    return _propagate_angle_cov(cov, gap, q_ang, config.gyro_bias_walk_radps_per_sqrt_s**2)


def _fix_updates(
    state: tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray],
    known: BoolArray,
    has: BoolArray,
    pitch_gnss_rad: FloatArray,
    r2: FloatArray,
    config: TiltSettings,
    still: tuple[FloatArray | None, FloatArray | None],
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The updates at a fix of :func:`pitch_kf_update`, on the prior ``state`` ``(θ, b, P_θθ,
    P_θb, P_bb)``, each ``(k,)``: the standstill one (``still``: rate and variance, each
    ``(k,)``, if given), then the pitch where ``has``; ``(θ, b, cov (k, 3))``."""
    theta, bias, ptt, ptb, pbb = state
    theta, bias = theta.copy(), bias.copy()
    still_rate_radps, still_rate_var = still
    if still_rate_radps is not None and still_rate_var is not None:
        theta, bias, ptt, ptb, pbb = _standstill_bias_update(
            (theta, bias, ptt, ptb, pbb), known, still_rate_radps, still_rate_var, config.gate_chi2
        )
    return _pitch_measurement_update(
        (theta, bias, ptt, ptb, pbb), has & ~known, has & known, pitch_gnss_rad, r2, config
    )


def _propagate_angle_cov(
    cov: FloatArray, gap: FloatArray, q_ang: FloatArray, qb: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``P' = F·P·Fᵀ + Q`` with ``F = [[1, −T], [0, 1]]``, ``Q`` of the bias walk over ``T``."""
    ptt, ptb, pbb = cov[:, AngleCov.ANGLE], cov[:, AngleCov.CROSS], cov[:, AngleCov.BIAS]
    ptt = ptt - 2 * gap * ptb + gap * gap * pbb + q_ang + qb * gap**3 / 3
    ptb = ptb - gap * pbb - qb * gap * gap / 2
    pbb = pbb + qb * gap
    return ptt, ptb, pbb


def _pitch_measurement_update(
    state: tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray],
    first: BoolArray,
    follow: BoolArray,
    pitch_gnss_rad: FloatArray,
    r2: FloatArray,
    config: TiltSettings,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The pitch ``z = θ + noise`` (``H = [1, 0]``), each array ``(k,)``: update on ``follow``;
    set on ``first`` (a track's first fix: ``θ = p``, variance ``R``, bias variance
    ``gyro_bias_std_radps²``); ``(θ, b, cov (k, 3))``."""
    theta, bias, ptt, ptb, pbb = state
    s = np.where(follow, ptt + r2, 1.0)
    y = np.where(follow, pitch_gnss_rad - theta, 0.0)
    kt, kb = ptt / s, ptb / s
    theta = np.where(first, pitch_gnss_rad, theta + np.where(follow, kt * y, 0.0))
    bias = bias + np.where(follow, kb * y, 0.0)
    new_tt = np.where(follow, ptt - kt * ptt, ptt)
    new_tb = np.where(follow, ptb - kt * ptb, ptb)
    new_bb = np.where(follow, pbb - kb * ptb, pbb)
    out = np.stack(
        [
            np.where(first, r2, new_tt),
            np.where(first, 0.0, new_tb),
            np.where(first, config.gyro_bias_std_radps**2, new_bb),
        ],
        axis=1,
    )
    return theta, bias, out


def yaw_fix_update(
    psi_rad: FloatArray,
    bias_radps: FloatArray,
    fix_ns: IntArray,
    heading_gnss_rad: FloatArray,
    stamp_ns: IntArray,
    config: TiltSettings,
) -> tuple[FloatArray, FloatArray, IntArray]:
    """Heading track and yaw-gyro bias at one GNSS heading per vehicle (arrays ``(k,)``).

    The integrated heading ``ψ`` moves by ``(1 − exp(−gap/attitude_tau_s))·err`` toward the
    GNSS heading (``err`` wrapped to ±π) and the bias by
    ``b_z += gap/(attitude_tau_s·gyro_bias_tau_s)·err`` (``ψ̇ = −(ωz − b_z)/cos θ``: a heading
    that falls behind means ``b_z`` is too small); an unknown ``ψ`` (NaN) is set to the GNSS
    heading. Returns ``(psi_rad, bias_radps, fix_ns)``.
    """
    tau = config.attitude_tau_s
    known = np.isfinite(psi_rad)
    gap = _fix_gap_s(stamp_ns, fix_ns)
    d = heading_gnss_rad - psi_rad
    err = d - _TWO_PI * np.rint(d / _TWO_PI)  # IEEE remainder, as math.remainder
    psi = np.where(known, psi_rad + (1.0 - np.exp(-gap / tau)) * err, heading_gnss_rad)
    bias = np.where(known, bias_radps + gap / (tau * config.gyro_bias_tau_s) * err, bias_radps)
    return psi, bias, stamp_ns.copy()
