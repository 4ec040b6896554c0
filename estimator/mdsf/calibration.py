"""Online calibration of MDSF's sensors: clock offsets, rolling radii, IMU mounting pitch and yaw.

Every vehicle of a fleet has four small Kalman filters here, stepped once per tick for all
vehicles at once (arrays indexed by the engine's slot), each with its uncertainty:

* **GNSS clock offset** ``δ_g`` (:class:`GnssClock`): a GNSS sample stamped ``t`` describes
  the instant ``t − δ_g`` of the IMU's clock (the simulator's ``clock_offset_ms`` sign), so its
  speed, the antenna's lever-arm velocity ``L = x1·ωz − h1·ωx`` at ``t`` taken off, reads
  ``y = Vg − L ≈ V − δ_g·(a + L')``: the regressor is the *antenna's* acceleration. A cab
  swaying at 0.3-3 Hz on a mast puts metres per second squared into ``L'`` and into the IMU's
  ``a`` that the tick's samples cannot resolve, so the filter runs on both sides low-passed
  (two first-order stages, ``gnss_clock_lowpass_tau_s``; the relation is linear and the
  low-pass commutes with the derivative, so it holds for the slow driving accelerations and
  the sway drops out). States ``[Ṽ, b, δ_g]``: the low-passed speed carried by the
  low-passed acceleration ``ã`` less a bias ``b`` (``Ṽ' = Ṽ + dt·(ã − b)``), observed as
  ``ỹ = Ṽ − δ_g·r̃``. The regressor ``r`` is the antenna's acceleration over the fix's own
  span ``[t_f − δ̂, t_f]`` (``t_f`` the fix's stamp, ``δ̂`` the offset so far), not the tick's:
  ``r = (U(t_f) − U(t_f − δ̂))/δ̂`` with ``U = ∫a·dt + L`` from the ticks' accelerations and
  rates (cubic through the last ticks, :func:`~estimator.mdsf.clock_shift._node_weights`).
  A fix is on average half a tick older than its tick, which under a mast's sway of a few
  hertz is a large phase; the filter learns from the round two ticks back, so a span that
  reaches past its fix (``δ̂ < 0``) has its ticks in. Observable whenever ``ã`` changes; what
  it makes of a fix's speed and, once converged, of the RTK distance is
  :mod:`estimator.mdsf.clock_shift`'s.
* **Rolling radius per wheel and the wheels' clock offset** (:class:`WheelCal`): where slip is
  ~0 (a wheel the config declares free-rolling, or any wheel during an operator's calibration
  drive) the measured rim speed is ``r·W = V/s − δ_w·a_w`` with ``s`` the true over the
  configured radius; states ``[κ_L, κ_R, δ_w]`` with ``κ = 1 − 1/s``, observed as
  ``r·W − V = −κ·V − δ_w·a_w`` (``V`` the filter's ground speed of that wheel, ``a_w`` its
  low-passed rate: what the rims feel, :meth:`MdsfFleet._wheel_accel`). Applied as
  ``s·(r·W + δ_w·a_w)``.
* **IMU mounting pitch** ``β``: a pitched IMU reads the forward specific force
  ``g·sin(θ + β)`` at standstill (``θ`` the body pitch of the tilt track, anchored by the GNSS
  attitude or velocity); a scalar filter of ``asin(f/g) − θ`` over standstill ticks. Applied
  as ``a − g·(sin(θ + β) − sin θ)``. An accelerometer bias reads the same at standstill: the
  two are one correction here.
* **IMU mounting yaw** ``γ`` (:class:`MountYaw`): an IMU turned by ``γ`` about the vertical
  reads the lateral specific force ``f_x' = f_x + γ·f_y`` (first order; ``f_y`` forward).
  The body's lateral force is known without the IMU's lateral axis, ``f_x = −V·ωz −
  g·sin φ·cos θ`` (centripetal and gravity, :mod:`estimator.sim.kinematics`), so
  ``f_x' + V·ωz + g·sin φ·cos θ = γ·f_y + b_lat``: states ``[γ, b_lat]``, ``b_lat`` a slow
  walk that takes the lateral accelerometer's bias and the roll's slow error. Observable
  whenever the forward force changes (speed changes, slopes). The regressor ``f_y`` is the
  forward force at ``O``: a cab rolling on its axle shakes a raised IMU sideways by ``h0·ω̇y``
  (metres per second squared), which the turned IMU reads on its forward axis as ``−γ·h0·ω̇y``
  and its pitch gyro as ``γ·ωy``, so the IMU's forward force plus the forward lever term
  ``h0·ω̇x'`` is free of it to first order; on a creeping drive that leak is larger than the
  drive's own forward force and, taken as excitation, ran the yaw away. Both lever terms are
  window estimates, so a tick's regressor error is counted up to their size (errors in
  variables): ``r += (γ̂² + P_γγ)·((h0·ω̇y)² + (h0·ω̇x')²)``, which keeps the stated std honest
  where the only excitation is the sway's. Applied to the forward acceleration as
  ``f_y = f_y' + γ·f_x'`` once converged and significant: a turn's centripetal force leaks
  ``γ·V·ωz`` into it otherwise.

:class:`MdsfCalibration` is one vehicle's calibration as plain values (state out and in: the
server stores it and gives it back after a restart).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from estimator._arrays import BoolArray, FloatArray, IntArray
from estimator._slots import grow_slot_array
from estimator.config import CalibrationConfig, WheeledRearDriveConfig
from estimator.mdsf.clock_shift import _SHIFT_TICKS, GnssClockShift, _node_weights
from estimator.mdsf.model import GRAVITY_MPS2, MdsfConfig

__all__ = [
    "CalibrationBank",
    "GnssClock",
    "MdsfCalibration",
    "MountYaw",
    "WheelCal",
]

_GATE_SIGMAS = 4.0
"""Innovations beyond this many sigmas are outliers (GNSS outlier, a calibration wheel that
slips), not used."""
_OFFSET_WALK_S_PER_SQRT_S = 1e-4
"""Random walk of a clock offset [s/√s] (clocks drift slowly)."""
_RADIUS_WALK_PER_SQRT_S = 2e-5
"""Random walk of a radius ratio [1/√s] (load, pressure, wear)."""
_PITCH_WALK_RAD_PER_SQRT_S = 2e-5
"""Random walk of the mounting pitch [rad/√s]."""
_FREE_SLIP_STD = 0.002
"""Slip of a free-rolling wheel (rolling resistance, texture) as noise [-]."""
_REF_CORR_S = 1.0
"""Correlation time of the filter's ground-speed error (its variance counts this many seconds
of ticks, so correlated errors do not read as independent evidence) [s]."""
_STILL_PITCH_FLOOR_RAD = math.radians(0.3)
"""Floor of a standstill pitch reading's std: body pitch error of the tilt track [rad]."""
_YAW_WALK_RAD_PER_SQRT_S = 2e-5
"""Random walk of the mounting yaw [rad/√s]."""
_YAW_APPLY_SIGMAS = 2.0
"""The mounting yaw is applied once it is this many stds from 0."""
_LAT_BIAS_PRIOR_MPS2 = 0.3
"""Prior std of the lateral force's bias (accelerometer bias, roll error ``g·δφ``) [m/s²]."""
_LAT_BIAS_WALK_MPS2_PER_SQRT_S = 0.01
"""Random walk of the lateral bias: the roll's error moves with the ground [m/s²/√s]."""
_LAT_FLOOR_MPS2 = 0.05
"""Floor of a tick's lateral-force model error (body sway, side slip, the IMU's lever arm in
a changing turn) [m/s²]."""
_RESIDUAL_TAU_S = 20.0
"""Time constant of the GNSS clock filter's running mean of its normalised innovation
squared, by which its speed noise is inflated (model error the filter does not explain) [s]."""
_STILL_SPEED_MPS = 0.05
_CLOCK_DELAY_TICKS = 2
"""The GNSS clock filter learns from the round this many ticks back: the span ``[t_f − δ̂,
t_f]`` of a fix up to a tick old under an offset down to −0.1 s then lies within the kept
ticks."""
_MIN_SPAN_S = 0.01
"""Shortest span the regressor's difference is taken over (``δ̂`` near 0: the acceleration at
the fix) [s]."""
_MIN_CAL_SPEED_MPS = 1.0
"""Wheel calibration uses ticks above this ground speed (the radius term ``κ·V`` then
stands out of the rim-speed noise)."""


class GnssClock(IntEnum):
    """States of the GNSS clock filter."""

    SPEED = 0
    BIAS = 1
    OFFSET = 2


class _ClockLowpass(IntEnum):
    """Columns of the GNSS clock filter's low-passes: first and second stage of the
    acceleration ``a``, the regressor ``r`` (the antenna's acceleration over the fix's span)
    and the speed ``y``."""

    ACCEL_1 = 0
    ACCEL_2 = 1
    REG_1 = 2
    REG_2 = 3
    SPEED_1 = 4
    SPEED_2 = 5


class _Delayed(IntEnum):
    """Columns of the GNSS clock filter's delay line: a round's inputs."""

    ACCEL = 0
    ACCEL_VAR = 1
    SPEED = 2
    SPEED_VAR = 3
    LEVER = 4
    AGE = 5


class MountYaw(IntEnum):
    """States of the mounting-yaw filter: yaw [rad], lateral force bias [m/s²]."""

    YAW = 0
    LAT_BIAS = 1


class WheelCal(IntEnum):
    """States of the wheel calibration filter: ``κ = 1 − configured/true radius``, offset."""

    KAPPA_LEFT = 0
    KAPPA_RIGHT = 1
    OFFSET = 2


@dataclass(slots=True)
class MdsfCalibration:
    """One vehicle's calibration, each value with its 1-sigma (state out and in).

    Attributes
    ----------
    gnss_clock_offset_s, wheel_clock_offset_s : float
        A sample stamped ``t`` describes the instant ``t − offset`` of the IMU clock [s].
    radius_scale_left, radius_scale_right : float
        True over configured rolling radius [-].
    imu_pitch_rad : float
        The IMU's forward axis pitched up against the body's [rad].
    imu_yaw_rad : float
        The IMU's axes turned about the vertical against the body's (``Rz(γ)``, the
        simulator's ``imu_misalign_deg[0]``) [rad]; 0 ± the prior for a calibration stored
        before it existed.
    """

    gnss_clock_offset_s: float
    gnss_clock_offset_std_s: float
    wheel_clock_offset_s: float
    wheel_clock_offset_std_s: float
    radius_scale_left: float
    radius_scale_left_std: float
    radius_scale_right: float
    radius_scale_right_std: float
    imu_pitch_rad: float
    imu_pitch_std_rad: float
    imu_yaw_rad: float = 0.0
    imu_yaw_std_rad: float = math.radians(3.0)


def _lowpass_noise_share(alpha: float) -> float:
    """Variance of white noise of variance 1 after two first-order low-passes of gain
    ``alpha`` each (``Σ h_k²`` of their impulse response ``h_k = α²·(k + 1)·(1 − α)^k``)."""
    k = np.arange(int(50.0 / alpha) + 1)
    return float(np.sum((alpha**2 * (k + 1) * (1.0 - alpha) ** k) ** 2))


def _kf_update(
    x: FloatArray, p: FloatArray, h: FloatArray, y: FloatArray, r: FloatArray
) -> BoolArray:
    """Scalar-observation Kalman update in place, rows gated at ``_GATE_SIGMAS``.

    ``x`` (k, n), ``p`` (k, n, n), ``h`` (k, n), ``y``, ``r`` (k,); Joseph form. Returns which
    rows were used."""
    ph = np.einsum("kij,kj->ki", p, h)
    s = np.einsum("ki,ki->k", h, ph) + r
    nu = y - np.einsum("ki,ki->k", h, x)
    use = nu * nu <= _GATE_SIGMAS**2 * s
    if not use.any():
        return use
    gain = ph / s[:, None]
    k = np.where(use[:, None], gain, 0.0)
    x += k * nu[:, None]
    eye = np.eye(x.shape[1])[None]
    a = eye - k[:, :, None] * h[:, None, :]
    p[:] = np.einsum("kij,kjl,kml->kim", a, p, a) + k[:, :, None] * k[:, None, :] * r[:, None, None]
    return use


class CalibrationBank:
    """The calibration filters of every vehicle of a fleet, by slot.

    :meth:`apply` corrects a round's tick inputs with the estimates so far; :meth:`observe_gnss`,
    :meth:`observe_wheels` and :meth:`observe_still` then learn from that round.
    """

    def __init__(self, config: MdsfConfig) -> None:
        self.dt_s = config.dt_s
        self.lowpass_tau_s = config.gnss_clock_lowpass_tau_s
        self.apply_std_s = config.gnss_clock_apply_std_s
        self.gnss_gap_s = config.gnss_timeout_s
        self.lowpass_noise = _lowpass_noise_share(config.dt_s / (self.lowpass_tau_s + config.dt_s))
        self.speed_walk = config.speed_walk_mps_per_sqrt_s
        self.bias_prior = config.accel_bias_std_mps2
        self.bias_walk = config.accel_bias_extra_walk_mps2_per_sqrt_s
        self.shift = GnssClockShift(config)
        """What the GNSS clock offset moves each fix's speed by (applied by the fleet)."""
        cap = 0
        self.gx = np.zeros((cap, 3))
        self.gp = np.zeros((cap, 3, 3))
        self.g_started = np.zeros(cap, dtype=bool)
        self.g_lowpass = np.zeros((cap, len(_ClockLowpass)))
        self.g_held = np.zeros(cap)  # the last speed y (filled between fixes) [m/s]
        self.g_gap = np.zeros(cap)  # time since the last GNSS speed [s]
        self.g_nis = np.ones(cap)  # running mean of the normalised innovation squared
        self.g_fast = np.zeros(cap)  # the regressor's error variance [m²/s⁴]
        self.g_reg = np.zeros(cap)  # the last fix's regressor r [m/s²]
        self.g_delay = np.zeros((cap, _CLOCK_DELAY_TICKS, len(_Delayed)))  # newest first
        self.g_u = np.zeros((cap, _SHIFT_TICKS))  # U = ∫a·dt + L at the ticks, newest first
        self.g_accum = np.zeros(cap)  # ∫a·dt to the newest tick [m/s]
        self.wx = np.zeros((cap, 3))
        self.wp = np.zeros((cap, 3, 3))
        self.pitch = np.zeros(cap)
        self.pitch_var = np.zeros(cap)
        self.yx = np.zeros((cap, 2))
        self.yp = np.zeros((cap, 2, 2))
        self.yaw_limit = np.zeros(cap)  # the mounting yaw converged below this std [rad]
        self.free = np.zeros((cap, 2), dtype=bool)  # wheels declared free-rolling
        self.drive = np.zeros(cap, dtype=bool)  # a calibration drive is on
        self.drove = np.zeros(cap, dtype=bool)  # a calibration drive was started
        self.on = np.zeros((cap, 3), dtype=bool)  # clocks, radius, mounting enabled
        self.limit = np.zeros((cap, 3))  # converged below these stds (s, ratio, rad)

    def _grow(self, slot: int) -> None:
        if slot < self.gx.shape[0]:
            return
        cap = max(2 * self.gx.shape[0], slot + 1)
        for name, shape, fill in (
            ("gx", (3,), 0.0),
            ("gp", (3, 3), 0.0),
            ("g_started", (), False),
            ("g_lowpass", (len(_ClockLowpass),), 0.0),
            ("g_held", (), 0.0),
            ("g_gap", (), 0.0),
            ("g_nis", (), 1.0),
            ("g_fast", (), 0.0),
            ("g_reg", (), 0.0),
            ("g_delay", (_CLOCK_DELAY_TICKS, len(_Delayed)), np.nan),
            ("g_u", (_SHIFT_TICKS,), np.nan),
            ("g_accum", (), 0.0),
            ("wx", (3,), 0.0),
            ("wp", (3, 3), 0.0),
            ("pitch", (), 0.0),
            ("pitch_var", (), 0.0),
            ("yx", (2,), 0.0),
            ("yp", (2, 2), 0.0),
            ("yaw_limit", (), 0.0),
            ("free", (2,), False),
            ("drive", (), False),
            ("drove", (), False),
            ("on", (3,), False),
            ("limit", (3,), 0.0),
        ):
            grow_slot_array(self, name, cap, shape, fill)

    def add(self, slot: int, vehicle: WheeledRearDriveConfig) -> None:
        """Start ``slot``'s calibration from the config's priors."""
        self._grow(slot)
        self.shift.add(slot)
        c: CalibrationConfig = vehicle.calibration
        geo = vehicle.geometry
        self.free[slot] = (not geo.wheel_driven_left, not geo.wheel_driven_right)
        self.drive[slot] = False
        self.drove[slot] = False
        self.on[slot] = (c.clock_offsets, c.wheel_radius, c.imu_mounting)
        self.limit[slot] = (
            c.clock_offset_converged_ms * 1e-3,
            c.radius_converged_pct * 1e-2,
            math.radians(c.imu_pitch_converged_deg),
        )
        off_var = (c.clock_offset_prior_ms * 1e-3) ** 2
        rad_var = (c.radius_prior_pct * 1e-2) ** 2
        self.gx[slot] = 0.0
        self.gp[slot] = np.diag([1.0, self.bias_prior**2, off_var])
        self.g_started[slot] = False
        self.g_gap[slot] = 0.0
        self.g_nis[slot] = 1.0
        self.g_fast[slot] = 0.0
        self.g_reg[slot] = 0.0
        self.g_delay[slot] = np.nan
        self.g_u[slot] = np.nan
        self.g_accum[slot] = 0.0
        self.wx[slot] = 0.0
        self.wp[slot] = np.diag([rad_var, rad_var, off_var])
        self.pitch[slot] = 0.0
        self.pitch_var[slot] = math.radians(c.imu_pitch_prior_deg) ** 2
        self.yaw_limit[slot] = math.radians(c.imu_yaw_converged_deg)
        self.yx[slot] = 0.0
        self.yp[slot] = np.diag([math.radians(c.imu_yaw_prior_deg) ** 2, _LAT_BIAS_PRIOR_MPS2**2])

    def set_drive(self, slot: int, on: bool) -> None:
        """An operator's calibration drive: while on, every wheel's slip is taken as ~0."""
        self.drive[slot] = on
        self.drove[slot] |= on

    # -- state out and in --------------------------------------------------------------------
    def state(self, slot: int) -> MdsfCalibration:
        """``slot``'s calibration as plain values."""
        kappa = self.wx[slot, :2]
        scale = 1.0 / (1.0 - kappa)
        scale_std = np.sqrt(np.diag(self.wp[slot])[:2]) * scale**2
        return MdsfCalibration(
            gnss_clock_offset_s=float(self.gx[slot, GnssClock.OFFSET]),
            gnss_clock_offset_std_s=float(np.sqrt(self.gp[slot, 2, 2])),
            wheel_clock_offset_s=float(self.wx[slot, WheelCal.OFFSET]),
            wheel_clock_offset_std_s=float(np.sqrt(self.wp[slot, 2, 2])),
            radius_scale_left=float(scale[0]),
            radius_scale_left_std=float(scale_std[0]),
            radius_scale_right=float(scale[1]),
            radius_scale_right_std=float(scale_std[1]),
            imu_pitch_rad=float(self.pitch[slot]),
            imu_pitch_std_rad=float(np.sqrt(self.pitch_var[slot])),
            imu_yaw_rad=float(self.yx[slot, MountYaw.YAW]),
            imu_yaw_std_rad=float(np.sqrt(self.yp[slot, 0, 0])),
        )

    def restore(self, slot: int, cal: MdsfCalibration) -> None:
        """Start ``slot`` from a stored calibration (values and stds; no cross-covariances)."""
        scale = np.array([cal.radius_scale_left, cal.radius_scale_right])
        scale_std = np.array([cal.radius_scale_left_std, cal.radius_scale_right_std])
        self.gx[slot, GnssClock.OFFSET] = cal.gnss_clock_offset_s
        g = self.gp[slot]
        g[2, :] = g[:, 2] = 0.0
        g[2, 2] = cal.gnss_clock_offset_std_s**2
        self.wx[slot] = (*(1.0 - 1.0 / scale), cal.wheel_clock_offset_s)
        kappa_std = scale_std / scale**2
        self.wp[slot] = np.diag([*(kappa_std**2), cal.wheel_clock_offset_std_s**2])
        self.pitch[slot] = cal.imu_pitch_rad
        self.pitch_var[slot] = cal.imu_pitch_std_rad**2
        self.yx[slot] = (cal.imu_yaw_rad, 0.0)
        self.yp[slot] = np.diag([cal.imu_yaw_std_rad**2, _LAT_BIAS_PRIOR_MPS2**2])

    def row_fields(self, slots: IntArray, radius_m: FloatArray) -> dict[str, FloatArray]:
        """The calibration's output fields of rows of vehicles ``slots`` (k,), the configured
        radii ``radius_m`` (k, 2) turned into calibrated ones (``ESTIMATE_FIELDS`` names)."""
        kappa = self.wx[slots, :2]
        scale = 1.0 / (1.0 - kappa)
        kappa_std = np.sqrt(np.stack([self.wp[slots, 0, 0], self.wp[slots, 1, 1]], axis=1))
        radius = radius_m * scale
        radius_std = radius_m * kappa_std * scale**2
        return {
            "gnss_clock_offset_s": self.gx[slots, GnssClock.OFFSET],
            "gnss_clock_offset_std_s": np.sqrt(self.gp[slots, 2, 2]),
            "wheel_clock_offset_s": self.wx[slots, WheelCal.OFFSET],
            "wheel_clock_offset_std_s": np.sqrt(self.wp[slots, 2, 2]),
            "radius_left_m": radius[:, 0],
            "radius_left_std_m": radius_std[:, 0],
            "radius_right_m": radius[:, 1],
            "radius_right_std_m": radius_std[:, 1],
            "imu_pitch_mount_rad": self.pitch[slots],
            "imu_pitch_mount_std_rad": np.sqrt(self.pitch_var[slots]),
        }

    # -- per round ---------------------------------------------------------------------------
    def _gnss_offset_weight(self, slots: IntArray) -> FloatArray:
        """Weight of the GNSS clock estimate ``δ`` in the fixes (k,), ``r(σ)·δ²/(δ² + σ²)``:
        ``r`` rises from 0 at ``σ = gnss_clock_apply_std_s`` to 1 at half of it (an estimate
        still learning is not applied, and one that converges is blended in, not switched),
        the second factor shrinks an estimate no larger than its std towards 0 (a receiver
        on time reads a few ms of noise, which applied would only move its fixes)."""
        off = self.gx[slots, GnssClock.OFFSET]
        var = self.gp[slots, 2, 2]
        bound = self.apply_std_s
        ramp = np.clip((bound - np.sqrt(var)) / (0.5 * bound), 0.0, 1.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            shrink = np.where(var > 0.0, off * off / (off * off + var), 1.0)
        return np.where(self.on[slots, 0], ramp * shrink, 0.0)

    def gnss_offset_s(self, slots: IntArray) -> FloatArray:
        """GNSS clock offset applied to the fixes per vehicle (k,): the estimate times its
        weight (:meth:`_gnss_offset_weight`; 0 where off)."""
        return self._gnss_offset_weight(slots) * self.gx[slots, GnssClock.OFFSET]

    def gnss_offset_std_s(self, slots: IntArray) -> FloatArray:
        """Std of the applied offset's error that goes into the fixes' variance (k,):
        ``√((w·σ)² + ((1 − w)·δ)²)`` with ``w`` the weight, 0 where nothing is applied (the
        prior's 100 ms times a swaying mast's acceleration would take the GNSS speed out of
        the filter at every start)."""
        w = self._gnss_offset_weight(slots)
        off = self.gx[slots, GnssClock.OFFSET]
        err = np.hypot(w * np.sqrt(self.gp[slots, 2, 2]), (1.0 - w) * off)
        return np.where(w > 0.0, err, 0.0)

    def gnss_offset_converged(self, slots: IntArray) -> BoolArray:
        """The GNSS clock offset is on and its std below the converged threshold (k,)."""
        return self.on[slots, 0] & (self.gp[slots, 2, 2] <= self.limit[slots, 0] ** 2)

    def wheel_correction(self, slots: IntArray) -> tuple[FloatArray, FloatArray]:
        """Radius ratios ``s`` (k, 2) and the wheel clock offset (k,) in force (1, 0 where off)."""
        scale = np.where(self.on[slots, 1:2], 1.0 / (1.0 - self.wx[slots, :2]), 1.0)
        return scale, np.where(self.on[slots, 0], self.wx[slots, WheelCal.OFFSET], 0.0)

    def mount_pitch_rad(self, slots: IntArray) -> FloatArray:
        """Mounting pitch in force per vehicle (k,): 0 where off, or where its gravity share
        ``g·β`` is within 3σ of the accelerometer bias's prior, which the filter's bias state
        takes up anyway (applying both cost up to 0.1 pp on drives without a tilted IMU)."""
        beta = self.pitch[slots]
        big = np.abs(beta) * GRAVITY_MPS2 > 3.0 * self.bias_prior
        return np.where(self.on[slots, 2] & big, beta, 0.0)

    def mount_yaw_rad(self, slots: IntArray) -> FloatArray:
        """Mounting yaw in force per vehicle (k,): 0 where off, not converged (an estimate
        still moving would put its error into every turn) or within ``_YAW_APPLY_SIGMAS`` of
        0 (an aligned IMU's estimate is its error: applied, it leaks into every turn)."""
        gamma = self.yx[slots, MountYaw.YAW]
        big = np.abs(gamma) > _YAW_APPLY_SIGMAS * np.sqrt(self.yp[slots, 0, 0])
        return np.where(self.mount_yaw_converged(slots) & big, gamma, 0.0)

    def mount_yaw_converged(self, slots: IntArray) -> BoolArray:
        """The mounting yaw is on and its std below the converged threshold (k,)."""
        return self.on[slots, 2] & (self.yp[slots, 0, 0] <= self.yaw_limit[slots] ** 2)

    def observe_gnss(
        self,
        slots: IntArray,
        accel_mps2: FloatArray,
        accel_var: FloatArray,
        vg_mps: FloatArray,
        vg_var: FloatArray,
        lever_mps: FloatArray | None = None,
        spans: tuple[FloatArray, FloatArray] | None = None,
    ) -> None:
        """One tick of the GNSS clock filter: the tick-mean acceleration ``a`` (NaN: no IMU,
        predicted with a wide walk), the tick's GNSS speed as the frontend moved it less the
        antenna's lever-arm velocity ``L`` at the tick (uncorrected; NaN: none) and ``L``
        itself (None: 0), all (k,); ``spans`` the tick's fixes' mean age and where the
        tick-mean acceleration's span ends (``TickInputs.gnss_age_span_s``,
        ``accel_span_end_s``; None: fixes at the tick, spans ending there). The tick's ``U``
        joins the kept ticks and the filter learns from the round ``_CLOCK_DELAY_TICKS``
        back (module docstring)."""
        k = slots.shape[0]
        age, span_end = (np.zeros(k), np.zeros(k)) if spans is None else spans
        lever = np.zeros(k) if lever_mps is None else np.nan_to_num(lever_mps)
        self._record_u(slots, accel_mps2, lever, np.nan_to_num(span_end))
        newest = np.stack([accel_mps2, accel_var, vg_mps, vg_var, lever, age], axis=1)
        old = self.g_delay[slots, -1]
        kept = self.g_delay[slots]
        kept[:, 1:] = kept[:, :-1]
        kept[:, 0] = newest
        self.g_delay[slots] = kept
        a_old = old[:, _Delayed.ACCEL]
        reg = self._span_regressor(slots, old[:, _Delayed.AGE], a_old)
        self._clock_step(slots, old, reg)

    def _record_u(
        self, slots: IntArray, accel_mps2: FloatArray, lever_mps: FloatArray, end_s: FloatArray
    ) -> None:
        """The newest tick's ``U = ∫a·dt + L`` (k,) at the tick: the running sum of ``dt·a``
        reaches ``end_s`` past the tick (the tick-mean's span), so ``end_s·a`` comes off;
        NaN where the tick has no IMU (a hole the regressor does not read across)."""
        imu = np.isfinite(accel_mps2)
        a = np.where(imu, accel_mps2, 0.0)
        self.g_accum[slots] += self.dt_s * a
        u = np.where(imu, self.g_accum[slots] - end_s * a + lever_mps, np.nan)
        kept = self.g_u[slots]
        kept[:, 1:] = kept[:, :-1]
        kept[:, 0] = u
        self.g_u[slots] = kept

    def _span_regressor(
        self, slots: IntArray, age_s: FloatArray, fallback: FloatArray
    ) -> FloatArray:
        """The antenna's acceleration over the span ``[t_f − δ̂, t_f]`` of the fixes of the
        round ``_CLOCK_DELAY_TICKS`` back, ``age_s`` (k,) before their tick:
        ``(U(t_f) − U(t_f − δ̂))/δ̂`` on the cubic through the kept ticks (``|δ̂|`` at least
        ``_MIN_SPAN_S``); ``fallback`` (k,) where a tick it weighs has no ``U`` or there is no
        fix."""
        off = self.gx[slots, GnssClock.OFFSET]
        span = np.where(off >= 0.0, np.maximum(off, _MIN_SPAN_S), np.minimum(off, -_MIN_SPAN_S))
        u_fix = _CLOCK_DELAY_TICKS + np.nan_to_num(age_s) / self.dt_s
        weights = _node_weights(np.concatenate([u_fix, u_fix + span / self.dt_s]))
        k = slots.shape[0]
        nodes = self.g_u[slots]
        holes = np.isnan(nodes)
        w = weights[:k] - weights[k:]
        reg = np.einsum("kj,kj->k", w, np.nan_to_num(nodes)) / span
        bad = ((w != 0.0) & holes).any(axis=1) | ~np.isfinite(age_s)
        return np.where(bad, np.nan_to_num(fallback), reg)

    def _clock_step(self, slots: IntArray, rnd: FloatArray, reg: FloatArray) -> None:
        """Predict and update the clock filter with a round's inputs ``rnd`` (k, len(_Delayed))
        and regressor ``reg`` (k,) on the low-passed signals (module docstring); a GNSS gap
        longer than ``gnss_timeout_s`` restarts the speed."""
        dt = self.dt_s
        accel, accel_var = rnd[:, _Delayed.ACCEL], rnd[:, _Delayed.ACCEL_VAR]
        vg_mps, vg_var = rnd[:, _Delayed.SPEED], rnd[:, _Delayed.SPEED_VAR]
        imu = np.isfinite(accel)
        a = np.where(imu, accel, 0.0)
        x, p = self.gx[slots], self.gp[slots]
        has = np.isfinite(vg_mps) & imu
        first = has & (~self.g_started[slots] | (self.g_gap[slots] > self.gnss_gap_s))
        regressor, y_low = self._clock_lowpass(slots, a, reg, np.where(has, vg_mps, np.nan))
        lp = self.g_lowpass[slots]
        x[:, GnssClock.SPEED] += dt * (lp[:, _ClockLowpass.ACCEL_2] - x[:, GnssClock.BIAS])
        f = np.eye(3)
        f[GnssClock.SPEED, GnssClock.BIAS] = -dt
        p = f @ p @ f.T
        q_v = np.where(imu, np.nan_to_num(accel_var), 1.0) * dt * dt + self.speed_walk**2 * dt
        p[:, 0, 0] += q_v
        p[:, 1, 1] += self.bias_walk**2 * dt
        p[:, 2, 2] += _OFFSET_WALK_S_PER_SQRT_S**2 * dt
        self._restart_speed(x, p, first, vg_mps, vg_var, a)
        upd = has & ~first
        if upd.any():
            h = np.zeros((int(upd.sum()), 3))
            h[:, GnssClock.SPEED] = 1.0
            h[:, GnssClock.OFFSET] = -regressor[upd]
            xu, pu = x[upd], p[upd]
            leak = (xu[:, GnssClock.OFFSET] ** 2 + pu[:, 2, 2]) * self.g_fast[slots[upd]]
            r = self._residual_scaled(slots[upd], xu, pu, h, y_low[upd], vg_var[upd] + leak)
            _kf_update(xu, pu, h, y_low[upd], r)
            x[upd], p[upd] = xu, pu
        self.g_started[slots] |= has
        self.gx[slots], self.gp[slots] = x, p

    def _residual_scaled(
        self,
        slots: IntArray,
        x: FloatArray,
        p: FloatArray,
        h: FloatArray,
        y: FloatArray,
        r: FloatArray,
    ) -> FloatArray:
        """The speed noise ``r`` (k,) scaled by the running mean of the normalised innovation
        squared ``ν²/(h·P·hᵀ + c·r)`` (at least 1; each tick's value capped at the gate's;
        ``c`` the share of white noise's variance the low-passes let through):
        what the model does not explain (sway left over, a tilt error's gravity) counts as
        noise, so the offset's std stays honest instead of shrinking on a misfit. ``x`` (k, 3),
        ``p`` (k, 3, 3), ``h`` (k, 3)."""
        s = np.einsum("ki,kij,kj->k", h, p, h) + r * self.lowpass_noise
        nu = y - np.einsum("ki,ki->k", h, x)
        nis = np.minimum(nu * nu / s, _GATE_SIGMAS**2)
        beta = self.dt_s / (_RESIDUAL_TAU_S + self.dt_s)
        self.g_nis[slots] += beta * (nis - self.g_nis[slots])
        return r * np.maximum(self.g_nis[slots], 1.0)

    def _clock_lowpass(
        self, slots: IntArray, a: FloatArray, reg: FloatArray, y: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """Step the clock filter's low-passes by one tick (acceleration ``a``, regressor ``r``,
        speed ``y``; NaN: no fix, filled by ``y + dt·a`` with the last fix's ``r``, whose clock
        term the filled speed carries; all (k,)); returns the low-passed regressor ``r̃`` and
        speed ``ỹ`` (k,). A chain's first fix (or the first after a gap) starts the speeds at
        their values and the accelerations at 0, as if the vehicle had moved steadily before:
        ``Ṽ' = ã`` holds from there."""
        dt = self.dt_s
        alpha = dt / (self.lowpass_tau_s + dt)
        has = np.isfinite(y)
        gap = np.where(has, 0.0, self.g_gap[slots] + dt)
        start = has & (~self.g_started[slots] | (self.g_gap[slots] > self.gnss_gap_s))
        y_in = np.where(has, y, self.g_held[slots] + dt * a)
        r_in = np.where(has, reg, self.g_reg[slots])
        lp = self.g_lowpass[slots]
        for col_1, col_2, raw in (
            (_ClockLowpass.ACCEL_1, _ClockLowpass.ACCEL_2, a),
            (_ClockLowpass.REG_1, _ClockLowpass.REG_2, r_in),
            (_ClockLowpass.SPEED_1, _ClockLowpass.SPEED_2, y_in),
        ):
            lp[:, col_1] += alpha * (raw - lp[:, col_1])
            lp[:, col_2] += alpha * (lp[:, col_1] - lp[:, col_2])
        zero = 0.0 * a
        lp[start] = np.stack([zero, zero, zero, zero, y_in, y_in], axis=1)[start]
        # the fast part the low-passes leave only attenuated (sway near the tick rate): the
        # raw regressor less the low-passed one, its mean square times the low-passes' share
        # of white noise is the regressor's error variance
        fast = r_in - lp[:, _ClockLowpass.REG_2]
        fast = np.where(start | ~self.g_started[slots], 0.0, fast)
        self.g_reg[slots] = r_in
        beta = dt / (_RESIDUAL_TAU_S + dt)
        self.g_fast[slots] += beta * (self.lowpass_noise * fast * fast - self.g_fast[slots])
        self.g_lowpass[slots] = lp
        self.g_held[slots] = y_in
        self.g_gap[slots] = gap
        return lp[:, _ClockLowpass.REG_2], lp[:, _ClockLowpass.SPEED_2]

    def _restart_speed(
        self,
        x: FloatArray,
        p: FloatArray,
        first: BoolArray,
        vg_mps: FloatArray,
        vg_var: FloatArray,
        a: FloatArray,
    ) -> None:
        """Start the low-passed speed of rows ``first`` at their GNSS speed (in place), its
        variance widened by what the unknown offset makes of the tick's acceleration
        ``(δ² + σ_δ²)·a²`` (the low-passes start from the raw sample)."""
        off = x[first, GnssClock.OFFSET] ** 2 + p[first, 2, 2]
        x[first, GnssClock.SPEED] = vg_mps[first]
        p[first, 0, :] = p[first, :, 0] = 0.0
        p[first, 0, 0] = vg_var[first] + off * a[first] ** 2

    def observe_wheels(
        self,
        slots: IntArray,
        rim_mps: FloatArray,
        rim_var: FloatArray,
        ground_mps: FloatArray,
        ground_var: FloatArray,
        accel_mps2: FloatArray,
        usable: BoolArray,
    ) -> None:
        """One tick of the wheel filter: measured rim speeds ``r·W`` with the configured radius
        and uncorrected clock (k, 2), the filter's ground speeds of the wheels (k, 2), their
        variances, each wheel's ground acceleration ``a_w`` (k, 2: the low-passed rate of its
        filtered speed, not the accelerometer's force, whose vibration would blur the
        regressor and shrink ``δ_w`` towards 0) and which rows may be used (k,: emitted,
        GNSS-anchored, not settling). Only zero-slip wheels above ``_MIN_CAL_SPEED_MPS``
        update."""
        x, p = self.wx[slots], self.wp[slots]
        p[:, 0, 0] += _RADIUS_WALK_PER_SQRT_S**2 * self.dt_s
        p[:, 1, 1] += _RADIUS_WALK_PER_SQRT_S**2 * self.dt_s
        p[:, 2, 2] += _OFFSET_WALK_S_PER_SQRT_S**2 * self.dt_s
        zero_slip = self.free[slots] | self.drive[slots][:, None]
        a = np.nan_to_num(accel_mps2)
        for w in (0, 1):
            v = ground_mps[:, w]
            ok = (
                usable
                & zero_slip[:, w]
                & np.isfinite(rim_mps[:, w])
                & np.isfinite(v)
                & (np.nan_to_num(v) > _MIN_CAL_SPEED_MPS)
            )
            if not ok.any():
                continue
            h = np.zeros((int(ok.sum()), 3))
            h[:, w] = -v[ok]
            h[:, WheelCal.OFFSET] = -a[ok, w]
            r = (
                rim_var[ok, w]
                + ground_var[ok, w] * (_REF_CORR_S / self.dt_s)
                + (_FREE_SLIP_STD * v[ok]) ** 2
            )
            xu, pu = x[ok], p[ok]
            _kf_update(xu, pu, h, rim_mps[ok, w] - v[ok], r)
            x[ok], p[ok] = xu, pu
        self.wx[slots], self.wp[slots] = x, p

    def observe_still(
        self,
        slots: IntArray,
        force_fwd_mps2: FloatArray,
        force_var: FloatArray,
        pitch_rad: FloatArray,
        still: BoolArray,
    ) -> None:
        """One tick of the mounting-pitch filter: at standstill (``still``, (k,)) the
        tick-mean forward specific force reads ``g·sin(θ + β)``."""
        self.pitch_var[slots] += _PITCH_WALK_RAD_PER_SQRT_S**2 * self.dt_s
        ok = still & np.isfinite(force_fwd_mps2) & np.isfinite(pitch_rad)
        if not ok.any():
            return
        s = slots[ok]
        ratio = np.clip(force_fwd_mps2[ok] / GRAVITY_MPS2, -1.0, 1.0)
        y = np.arcsin(ratio) - pitch_rad[ok]
        r = force_var[ok] / GRAVITY_MPS2**2 + _STILL_PITCH_FLOOR_RAD**2
        h = np.ones((s.shape[0], 1))
        x = self.pitch[s][:, None]
        p = self.pitch_var[s][:, None, None]
        _kf_update(x, p, h, y, r)
        self.pitch[s], self.pitch_var[s] = x[:, 0], p[:, 0, 0]

    def observe_yaw(
        self,
        slots: IntArray,
        force_mps2: tuple[FloatArray, FloatArray],
        force_var: FloatArray,
        speed_mps: FloatArray,
        yaw_rate_radps: FloatArray,
        tilt_rad: tuple[FloatArray, FloatArray],
        lever_mps2: tuple[FloatArray, FloatArray],
    ) -> None:
        """One tick of the mounting-yaw filter: the tick-mean forces at ``O`` ``(f_y, f_x')``
        (the IMU's, each lever arm's angular-acceleration term taken off, as the model is
        ``O``'s) and their variance, the ground speed ``V``, the yaw rate ``ωz``, the body's
        ``(θ, φ)`` and the two lever terms taken off ``(h0·ω̇x', h0·ω̇y)``, all (k,):
        ``f_x' + V·ωz + g·sin φ·cos θ = γ·f_y + b_lat`` (NaN anywhere: predicted only), the
        noise ``2·σ_f² + floor² + (γ̂² + P_γγ)·((h0·ω̇x')² + (h0·ω̇y)²)`` (module docstring)."""
        dt = self.dt_s
        x, p = self.yx[slots], self.yp[slots]
        p[:, 0, 0] += _YAW_WALK_RAD_PER_SQRT_S**2 * dt
        p[:, 1, 1] += _LAT_BIAS_WALK_MPS2_PER_SQRT_S**2 * dt
        f_fwd, f_lat = force_mps2
        theta, phi = tilt_rad
        y = f_lat + speed_mps * yaw_rate_radps + GRAVITY_MPS2 * np.sin(phi) * np.cos(theta)
        sway_var = lever_mps2[0] ** 2 + lever_mps2[1] ** 2
        ok = np.isfinite(y) & np.isfinite(f_fwd) & np.isfinite(force_var) & np.isfinite(sway_var)
        if ok.any():
            h = np.stack([f_fwd[ok], np.ones(int(ok.sum()))], axis=1)
            gamma_sq = x[ok, MountYaw.YAW] ** 2 + p[ok, 0, 0]
            r = 2.0 * force_var[ok] + _LAT_FLOOR_MPS2**2 + gamma_sq * sway_var[ok]
            xu, pu = x[ok], p[ok]
            _kf_update(xu, pu, h, y[ok], r)
            x[ok], p[ok] = xu, pu
        self.yx[slots], self.yp[slots] = x, p

    def uncalibrated(self, slots: IntArray) -> BoolArray:
        """Per vehicle and wheel (k, 2): an enabled calibration the wheel's slip depends on
        (GNSS and wheel clock offsets, its radius, the mounting pitch) is above its limit.
        Not the mounting yaw: it reaches the slip only through a turn's forward acceleration
        and is not stored in the rows, so a restarted vehicle learns it again.

        A driven wheel's radius and the wheels' clock are learnt only where slip is ~0 (a
        free-rolling wheel, a calibration drive): on a vehicle that has neither they stay at
        the configured values and do not hold the flag (nothing would ever clear it)."""
        on, lim = self.on[slots], self.limit[slots]
        learns = self.free[slots] | (self.drive[slots] | self.drove[slots])[:, None]
        gnss_clock = self.gp[slots, 2, 2] > lim[:, 0] ** 2
        wheel_clock = learns.any(axis=1) & (self.wp[slots, 2, 2] > lim[:, 0] ** 2)
        bad_clock = on[:, 0] & (gnss_clock | wheel_clock)
        bad_pitch = on[:, 2] & (self.pitch_var[slots] > lim[:, 2] ** 2)
        kappa_var = np.stack([self.wp[slots, 0, 0], self.wp[slots, 1, 1]], axis=1)
        bad_radius = on[:, 1:2] & learns & (kappa_var > (lim[:, 1:2]) ** 2)
        return bad_radius | (bad_clock | bad_pitch)[:, None]

    def still_pitch_rows(
        self, slots: IntArray, vg_mps: FloatArray, rim_mps: FloatArray, min_speed: FloatArray
    ) -> BoolArray:
        """Which rows stand still enough for the mounting pitch: GNSS speed below
        ``_STILL_SPEED_MPS`` and both rims below the standstill speed (k,)."""
        del slots
        return (np.abs(np.nan_to_num(vg_mps, nan=np.inf)) < _STILL_SPEED_MPS) & (
            np.abs(np.nan_to_num(rim_mps, nan=np.inf)) < min_speed[:, None]
        ).all(axis=1)
