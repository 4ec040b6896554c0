"""Per-wheel slip, slip angle, steer angle and load from the sensors, with their uncertainty.

One :class:`FrontEnd` per vehicle turns IMU, CAN wheel speeds, steering-wheel angle and
(optional) GNSS into the μ filter's inputs each tick (``method.md`` §5, source eq. 7-15). The
fleet runs the same stages batched over vehicles (:class:`~.fleetfront.FleetFrontEnd`); this
class is where they are written out one vehicle at a time, and the reference the batched one
is tested against:

* speed ``v_x`` and the forward accelerometer's bias from a two-state Kalman filter driven by
  the accelerometer and corrected by GNSS forward speed (or, without GNSS, the undriven
  wheels' mean rim speed);
* side-slip ``v_y``: ``v̇_y = a_y − r v_x`` corrected by GNSS (velocity across the heading);
  the source's reading (``FrontEndConfig.paper``) integrates it with a slow leak to zero;
* tilt: body roll and pitch follow the accelerations behind the body's lag (``φ = k_φ ā_y/g``,
  ``θ = k_θ ā_x/g``, ``ā`` lagged), so the accelerometers read ``a + k ā``: the leak of the
  lagged reading taken out (not in the paper reading; in a steady turn ``a(1 + k)``, but in
  a 0.3 s steering ramp the body rolls only later, and the leak of the instantaneous
  reading, integrated into ``v_y``, would stay there as a side-slip error), with the
  gradients learnt from the receiver's roll and pitch where it gives them (their changes
  against the accelerations' changes; the config's gradients are the prior);
* loads: static + longitudinal ``m a_x h/L`` + lateral ``m a_y h/b`` split between the axles
  by the roll-stiffness share, through a first-order lag (paper: the static formula, lateral
  split ``lr/L``, no lag);
* radius: calibrated per wheel while driving straight and steady (the slip there is what the
  resistances need), then falling with load, ``r_e = r_u − ρ Fz/kz`` (paper: the statically
  loaded radius ``r_u − Fz/kz``). ``ρ`` (0.25-0.4 for real tyres) is learnt from the calibrated
  radii of the tyres the config describes, ``ρ = (r_u − r_e) kz/Fz`` (median over wheels); a
  tyre whose radius says it deflects far more or less (soft, damaged) gets its own vertical
  stiffness ``kz_i = ρ Fz/(r_u − r_e,i)``, and with it its contact length and brush stiffness;
* accelerometer biases: the forward and lateral speed filters' bias states are taken off
  ``a_x`` and ``a_y`` before the loads and the measurements (a lateral bias of 0.05 m/s² reads
  as a lateral tyre force and as ~45 N of load moved across, which a soft tyre's radius turns
  into a slip of ~5e-4);
* relaxation: κ and α pass a first-order lag over the tyre's relaxation length (not paper);
* a ringing wheel: the relaxed κ is rebuilt from one wheel-speed reading a tick, so a rim
  that moves between readings by more than their rounding (a torque step rings a wheel on
  its tyre, near ``r √(c_x/(I σ_x))``: ~300-600 rad/s for these road tyres, a stiff one
  highest, at or above the readings' rate, and they alias the ring into a slow swing)
  leaves κ uncertain by what it moved: that change passes the same lag into κ's 1-σ
  (:func:`ringing_slip_std`, not paper);
* timing: the IMU means of a tick lie on average ``lag`` before it (5 ms for 100 Hz samples
  in a 20 ms tick), the wheel speeds and the steering angle are the latest at it; the
  measured ``a_x``, ``a_y`` are carried to the tick along their change since the last one,
  ``a + (a − a_prev)·lag/dt`` (not paper): in a 0.3 s steering ramp to 4 m/s² the mean is
  0.07 m/s² behind, and the filter's ``v_y`` kept what that did to the update;
* the undriven wheels' spin-up slip: a wheel without torque is spun up by its contact force
  alone (``I ω̇ = −F r``, ``ω̇ = a_x/r``), so it rolls with ``κ = −I a_x/(r² c_x)`` (about
  −1e-4 at 2.3 m/s²), taken out of their rim speed before it reads ``v_x`` (not paper);
* the undriven wheels' brake slip: the service brakes act on every wheel, so while the tyres
  brake the body (``a_x`` plus the resistances below zero) the "free" rims slip by their
  unknown share of the braking force (:func:`brake_slip_std`). Where that slip may exceed
  the rims' own 1-σ they do not read the speed (a bias held for seconds, it would not
  average out over the ticks as noise does): the speed, and with it every κ's shared 1-σ,
  then leans on GNSS and the accelerometer (not paper);
* the speed's stated 1-σ (``vx_std_mps``, the row's): the speed filter's, with the rims'
  persistent errors considered (never estimated, :func:`consider_step`): the window's lag,
  the radii's shared scale (:func:`rim_persistent_std_mps`). They cancel in κ, so the slips
  and their shared 1-σ (``kappa_common_std``) are taken without them (not paper).

Frame: x forward, y left (the IMU's X right, Y forward: ``a_y = −accel[:, 0]``).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from estimator._arrays import FloatArray
from estimator.config import ChassisConfig, DrivenAxle, TyreConfig, Wheeled4wdSteeredConfig
from estimator.friction.brush import load_adaptive_stiffness_n
from estimator.friction.model import GRAVITY_MPS2
from estimator.types import GnssSample, ImuBatch, SteeringAngles, WheelSpeeds4

__all__ = [
    "DRIVE_SHARE",
    "GNSS_SPEED_STD_MPS",
    "UNDRIVEN",
    "FrontEnd",
    "FrontEndConfig",
    "FrontEndTick",
    "antenna_arm_m",
    "antenna_velocity_at_cg",
    "body_rates_radps",
    "brake_slip_std",
    "calibration_scale_var",
    "consider_step",
    "free_rolling_steer",
    "rim_persistent_std_mps",
    "ringing_slip_std",
    "spin_up_slip",
    "tilted_arm_m",
]

AIR_DENSITY_KGPM3 = 1.2
GNSS_SPEED_STD_MPS = 0.03
"""1-σ of a GNSS forward speed reading [m/s] (the speed filter's and the radius calibration's)."""
UNDRIVEN = {
    DrivenAxle.FRONT: np.array([False, False, True, True]),
    DrivenAxle.REAR: np.array([True, True, False, False]),
    DrivenAxle.ALL: np.zeros(4, dtype=bool),
}
"""Per driven axle, which wheels roll free ``(4,)`` (front left, front right, rear left, rear
right): their rim speed is the speed reference without GNSS."""
DRIVE_SHARE = {
    DrivenAxle.FRONT: np.array([0.5, 0.5, 0.0, 0.0]),
    DrivenAxle.REAR: np.array([0.0, 0.0, 0.5, 0.5]),
    DrivenAxle.ALL: np.full(4, 0.25),
}
"""Per driven axle, each wheel's share of the drive force ``(4,)`` (an open differential
splits an axle's torque evenly)."""


@dataclass(frozen=True, slots=True)
class FrontEndConfig:
    """Front-end settings: ``paper`` the source's reading (see the module docstring).

    ``min_speed_mps``: no μ update below it; ``gnss_timeout_s``: GNSS older than this is
    not used; ``steer_timeout_s``: a steering-wheel angle older than this counts as none (a dead
    stream is told within three periods of a 10 Hz steering message, the slowest rate such
    angles are commonly sent at, so a live stream's jitter never reads as a gap; a live
    angle is at most one period old, so its lag is the stream's, not the timeout's; at a
    driver's quick 300°/s the road wheels turn 4-6° in 0.3 s through a 14-20 ratio, so an
    angle held longer no longer stands for theirs); ``calib_time_s``: time constant of the
    radius calibration, which must hold
    ``calib_samples`` GNSS epochs before the μ filter updates; ``kz_tolerance``: relative
    difference of a wheel's radius sink ``r_u − r_e`` from the one the learnt ``ρ`` and the
    config's ``kz`` give (so of its ``kz``), beyond which the tyre is suspect and its own
    ``kz`` is learnt (a sink of ~8 mm is read to ~0.2 mm: 0.1 is many σ); ``radius_drop0``,
    ``radius_drop_range``: the prior ``ρ`` and the range the learnt one is held within;
    ``tilt_prior_weight``, ``tilt_highpass_s``: the roll and pitch gradients learnt from the
    receiver's attitude (:class:`_TiltGradient`): the config's worth this many ``(a/g)²`` of
    changes (0.2: a 0.1 g change held for 2 s of fixes), changes taken against this running mean;
    ``yaw_walk_radps``, ``gyro_bias_walk_radps_per_sqrt_s``, ``heading_std_rad``: the yaw
    gyro's bias filter (the yaw angle's walk, the bias's, the receiver heading's 1-σ), the
    roll and pitch gyros' alike with ``attitude_std_rad`` the receiver roll's and pitch's;
    ``wheel_inertia_kgm2``, ``wheel_inertia_rel_std``: a wheel's (rim and tyre) spin inertia
    and its relative 1-σ, for the undriven wheels' spin-up slip (:func:`spin_up_slip`; a
    road wheel of 0.3-0.4 m radius has 0.8-2 kg·m²); ``brake_share_std``: the 1-σ of the
    undriven axle's share of the braking force (:func:`brake_slip_std`);
    ``wheel_speed_resolution_radps``: the CAN wheel speed's rounding, below which a change
    between two readings may be rounding alone (:func:`ringing_slip_std`);
    ``wheel_speed_window_s``: the time a CAN wheel speed is averaged over (a tone ring timed
    by the ECU; :func:`rim_persistent_std_mps`).
    """

    paper: bool = False
    min_speed_mps: float = 3.0
    gnss_timeout_s: float = 0.5
    steer_timeout_s: float = 0.3
    calib_time_s: float = 3.0
    calib_samples: int = 15
    kz_tolerance: float = 0.1
    radius_drop0: float = 1.0 / 3.0
    radius_drop_range: tuple[float, float] = (0.15, 0.6)
    speed_walk_mps2: float = 0.3
    bias_walk_mps2_per_sqrt_s: float = 0.005
    side_slip_leak_s: float = 5.0
    tilt_prior_weight: float = 0.2
    yaw_walk_radps: float = 0.01
    gyro_bias_walk_radps_per_sqrt_s: float = 1e-4
    heading_std_rad: float = 0.005
    attitude_std_rad: float = 0.005
    tilt_highpass_s: float = 3.0
    wheel_inertia_kgm2: float = 1.4
    wheel_inertia_rel_std: float = 0.4
    brake_share_std: float = 0.5
    wheel_speed_resolution_radps: float = 0.025
    wheel_speed_window_s: float = 0.02


def antenna_arm_m(chassis: ChassisConfig) -> tuple[float, float, float]:
    """The antenna's lever arm as (ahead, left of the CG, up from the tilt axis) [m]: the
    config's ``antenna_lever_arm_m`` is x right, y forward, z up from the ground below the CG,
    the body rolls and pitches about the axis ``tilt_axis_height_m`` above the ground."""
    right, ahead, up = chassis.antenna_lever_arm_m
    return ahead, -right, up - chassis.tilt_axis_height_m


def body_rates_radps(gyro_radps: FloatArray, yaw_rate_radps: FloatArray | float) -> FloatArray:
    """The body's rates ``(p, q, r)`` about x forward, y left, z up from the gyro's
    ``(..., 3)`` (X right, Y forward, Z up: ``p = g_Y``, ``q = −g_X``), ``r`` the given
    yaw rate ``(...)`` → ``(..., 3)`` [rad/s]."""
    g = np.asarray(gyro_radps, dtype=np.float64)
    r = np.broadcast_to(np.asarray(yaw_rate_radps, dtype=np.float64), g.shape[:-1])
    return np.stack([g[..., 1], -g[..., 0], r], axis=-1)


def tilted_arm_m(
    arm_m: FloatArray, roll_rad: FloatArray | float, pitch_rad: FloatArray | float
) -> FloatArray:
    """The lever arm ``r`` ``(..., 3)`` (ahead, left, up) turned with the body about its tilt
    axis into the level frame, pitch ``θ`` (nose up) then roll ``φ`` (right side down):
    ``d = R_x(φ) R_y(−θ) r`` (``roll_rad``, ``pitch_rad`` ``(...)``) → ``(..., 3)`` [m]."""
    arm = np.asarray(arm_m, dtype=np.float64)
    th, ph = np.asarray(pitch_rad, dtype=np.float64), np.asarray(roll_rad, dtype=np.float64)
    x, y, z = arm[..., 0], arm[..., 1], arm[..., 2]
    x1, z1 = x * np.cos(th) - z * np.sin(th), x * np.sin(th) + z * np.cos(th)
    return np.stack([x1, y * np.cos(ph) - z1 * np.sin(ph), y * np.sin(ph) + z1 * np.cos(ph)], -1)


def antenna_velocity_at_cg(
    vel_mps: FloatArray, rates_radps: FloatArray, arm_m: FloatArray
) -> FloatArray:
    """The CG's level-frame horizontal velocity from the antenna's, through the lever arm.

    Rigid body: ``v_cg = v_ant − ω × d`` with ``ω = (p, q, r_z)`` (:func:`body_rates_radps`)
    and ``d = (x, y, z)`` the arm from the tilt axis's point below the CG in the level frame
    (:func:`antenna_arm_m`, :func:`tilted_arm_m`); its horizontal part
    ``v_x,cg = v_x,ant + r_z·y − q·z``, ``v_y,cg = v_y,ant − r_z·x + p·z``: the yaw moves the
    antenna by its horizontal arm, the roll and pitch by its height above their axis.
    ``vel_mps`` ``(..., 2)`` ``(v_x, v_y)`` (x forward, y left along the heading),
    ``rates_radps`` ``(..., 3)``, ``arm_m`` ``(..., 3)`` → ``(..., 2)``; with the arm negated
    it gives the antenna's velocity from the CG's (``v_cg + ω × d``).
    """
    vel = np.asarray(vel_mps, dtype=np.float64)
    arm = np.asarray(arm_m, dtype=np.float64)
    w = np.asarray(rates_radps, dtype=np.float64)
    return np.stack(
        [
            vel[..., 0] + w[..., 2] * arm[..., 1] - w[..., 1] * arm[..., 2],
            vel[..., 1] - w[..., 2] * arm[..., 0] + w[..., 0] * arm[..., 2],
        ],
        axis=-1,
    )


def brake_slip_std(
    brake_mps2: FloatArray | float, mass_kg: FloatArray | float, c_x_n: FloatArray
) -> FloatArray:
    """Per unit of ``FrontEndConfig.brake_share_std``: the 1-σ of a braked wheel's slip.

    The tyres brake the body by ``brake_mps2`` (≥ 0: ``−(a_x + resistances/m)``, 0 while
    driven); an axle whose share of it is ``s`` gives each of its two wheels ``F = s m a/2``
    and, in the linear range, ``κ = −F/c_x``. The share of an undriven axle is not in the
    config (a road vehicle's rear brakes take 25-45 %), so ``s`` enters as a 1-σ, not a mean.
    Shapes broadcast like :func:`spin_up_slip`'s."""
    force_n = np.asarray(mass_kg) * np.maximum(np.asarray(brake_mps2), 0.0) / 2.0
    slip: FloatArray = force_n / np.maximum(c_x_n, 1.0)
    return slip


def spin_up_slip(
    ax_mps2: FloatArray | float,
    radius_m: FloatArray,
    c_x_n: FloatArray,
    inertia_kgm2: float,
) -> FloatArray:
    """Slip of a wheel that no torque drives while the vehicle accelerates by ``a_x`` [m/s²].

    The contact force alone spins it up: ``I ω̇ = −F r`` with ``ω̇ = a_x/r``, so
    ``F = −I a_x/r²`` and, in the tyre's linear range, ``κ = F/c_x``. Shapes broadcast
    (``(4,)`` radii and stiffness with a scalar ``a_x``, or ``(B, 4)`` with ``(B, 1)``)."""
    force_n = -inertia_kgm2 * np.asarray(ax_mps2) / (radius_m * radius_m)
    slip: FloatArray = force_n / np.maximum(c_x_n, 1.0)
    return slip


def ringing_slip_std(
    kinematic: FloatArray,
    previous: FloatArray,
    ring: FloatArray,
    gain: FloatArray | float,
    rounding: FloatArray,
) -> FloatArray:
    """The relaxed κ's 1-σ from the wheel's movement between readings ``(…, 4)``.

    The relaxed slip is ``κ'_k = κ'_{k−1} + g (κ_k − κ'_{k−1})`` over one kinematic reading
    ``κ_k`` a tick (``g = gain``, the relaxation's), where the tyre integrates the slip
    between them. How far the slip went between two readings is unknown; what they show is
    ``|κ_k − κ_{k−1}|``, of which ``rounding`` (the readings' resolution in slip) may be the
    rounding alone. The rest is taken as the reading's error, whole (a ring above half the
    readings' rate aliases, so the change between readings does not bound it), and it passes
    into ``κ'`` as a reading does: ``ring_k = ring_{k−1} + g (excess_k − ring_{k−1})``.
    ``previous``: the last tick's kinematic κ (NaN: none yet); returns the new ``ring``."""
    change = np.where(np.isnan(previous), 0.0, np.abs(kinematic - previous))
    excess = np.maximum(change - rounding, 0.0)
    updated: FloatArray = ring + gain * (excess - ring)
    return updated


def free_rolling_steer(u_mps: FloatArray, w_mps: FloatArray) -> FloatArray:
    """The steer angles ``(…, 4)`` of wheels that carry no side force: the front pair's along
    its travel, ``δ = atan2(w, u)`` (``u``, ``w`` each wheel centre's velocity along and across
    the body ``(…, 4)``), the rear pair's 0.

    For the radius calibration without a steering angle: with ``|r|`` and ``|a_y|`` small and
    steady, the axles' side forces are small (``m a_y = F_yf + F_yr``, ``I ṙ = a F_yf − b F_yr``:
    0.3 m/s² is under 500 N an axle, a slip angle under 0.005 rad at 1e5 N/rad), so the front
    wheels point along their travel; a front axle sliding wide at a large ``δ`` would show as
    ``a_y``. A small yaw rate alone would not say so."""
    delta = np.zeros(np.shape(u_mps))
    delta[..., :2] = np.arctan2(w_mps[..., :2], u_mps[..., :2])
    return delta


def rim_persistent_std_mps(
    speed_accel_mps2: FloatArray | float,
    speed_mps: FloatArray | float,
    scale_rel: FloatArray | float,
    cross_mps: FloatArray | float,
    window_s: float,
) -> FloatArray:
    """1-σ of the part of the undriven rims' speed reading that persists over many ticks [m/s].

    ``hypot(|v̇| T/2, s v, c)``: a tone ring timed over the window ``T`` reads the mean over
    it, ``T/2`` behind (a 1-σ, not a correction: an ECU may sample the speed instead); the
    radii's shared scale error ``s`` (relative, held between calibrations:
    :func:`calibration_scale_var`); ``c`` the persistent cross terms (the lateral speed's error
    through the steered rims, the spin-up slip's inertia). Shapes broadcast. These errors
    are in every wheel's reading alike, so they cancel in the slips κ; they do not cancel in
    the speed reported against the ground."""
    lag = np.abs(np.asarray(speed_accel_mps2)) * window_s / 2.0
    scale = np.asarray(scale_rel) * np.abs(np.asarray(speed_mps))
    out: FloatArray = np.hypot(np.hypot(lag, scale), np.asarray(cross_mps))
    return out


def calibration_scale_var(
    var: FloatArray | float, gain: FloatArray | float, gnss_speed_mps: FloatArray | float
) -> FloatArray:
    """The radii's shared relative scale variance after one calibration epoch.

    The calibration is a running mean ``r ← r + g (z − r)`` of readings whose error is the
    GNSS speed's, ``σ_g/v`` relative and shared by the four wheels: its variance follows
    ``V ← (1 − g)² V + g² (σ_g/v)²`` (``σ_g`` :data:`GNSS_SPEED_STD_MPS`; with ``g`` held
    at ``0.1/calib_time_s`` it settles at ``(σ_g/v)² g/(2 − g)``). Shapes broadcast."""
    g = np.asarray(gain)
    rel = GNSS_SPEED_STD_MPS / np.maximum(np.abs(np.asarray(gnss_speed_mps)), 1.0)
    out: FloatArray = (1.0 - g) ** 2 * np.asarray(var) + (g * rel) ** 2
    return out


def consider_step(
    persist_mps: FloatArray | float, gain: FloatArray | float, reading_std_mps: FloatArray | float
) -> FloatArray:
    """The speed estimate's persistent error 1-σ after a reading taken with gain ``k``.

    A Schmidt (considered, never estimated) error: the estimate ``v ← v + k (z − v)`` takes
    ``k`` of the reading's persistent error and keeps ``1 − k`` of its own; the two are
    taken as fully correlated (a bound: the persistent parts follow the same acceleration
    and radii), ``p ← (1 − k) p + k σ_z``. A GNSS reading passes ``σ_z = 0``."""
    k = np.asarray(gain)
    out: FloatArray = (1.0 - k) * np.asarray(persist_mps) + k * np.asarray(reading_std_mps)
    return out


@dataclass(frozen=True, slots=True)
class FrontEndTick:
    """One tick's inputs (per wheel ``(4,)``) and measurements, with the 1-σ the filter uses."""

    fz_n: FloatArray
    kz_npm: FloatArray  # per wheel: the config's, or learnt for a suspect tyre
    alpha_rad: FloatArray
    delta_rad: FloatArray
    kappa: FloatArray
    kappa_std: FloatArray  # per wheel, apart from the shared part below
    kappa_common_std: float  # the speed's 1-σ over it: one error shared by the four κ
    alpha_std_rad: FloatArray
    alpha_lag_rad: FloatArray  # relaxed minus kinematic α (0 in the paper reading)
    z: FloatArray  # [a_x + resistances/m, a_y, ṙ]
    vx_mps: float
    vx_std_mps: float  # the speed's 1-σ with the rims' persistent errors (not κ's: they cancel)
    vy_mps: float
    yaw_rate_radps: float
    roll_pitch_rate_radps: FloatArray  # (p, q) about x forward, y left, less the gyros' biases
    vy_gnss_mps: float  # NaN without a fresh GNSS velocity
    gnss: bool
    steering: bool  # a steering angle (False: none yet or stale; the front pair's columns NaN)
    valid: bool
    tyre_suspect: bool


def _latest_sample(
    packets: list[tuple[np.ndarray, np.ndarray]], t_ns: int
) -> tuple[tuple[int, np.ndarray] | None, list[tuple[np.ndarray, np.ndarray]]]:
    """The last sample at or before ``t_ns`` of ``(stamps, values)`` packets as ``(stamp,
    value)`` (None if none), and the packets still holding later samples."""
    latest = None
    rest = []
    for stamps, values in packets:
        sel = np.flatnonzero(stamps <= t_ns)
        if sel.size:
            latest = int(stamps[sel[-1]]), values[sel[-1]]
        if stamps.size and stamps[-1] > t_ns:
            rest.append((stamps, values))
    return latest, rest


class _AxisFilter:
    """Speed along one body axis and its accelerometer's bias: ``v̇ = a − b + c``, ``ḃ = w``
    (or a yaw angle and its gyro's bias, the same way).

    ``c`` is the rotation term (``r v_y`` forward, ``−r v_x`` lateral); updates are speeds. In
    plain floats (a 2×2 covariance ``[[p_vv, p_vb], [p_vb, p_bb]]``): three of these run every
    tick of every vehicle, where numpy's per-call cost would be most of the work.
    """

    def __init__(self, speed_walk_mps2: float, bias_walk: float, bias0_std: float) -> None:
        self.speed, self.bias = math.nan, 0.0
        self.speed_var, self.p_vb, self.p_bb = 1.0, 0.0, bias0_std**2
        self.speed_walk, self.bias_walk = speed_walk_mps2, bias_walk

    def set_speed(self, value: float, var: float | None = None) -> None:
        """Put the speed (and its variance) at a value, as a start or an external reading."""
        self.speed = value
        if var is not None:
            self.speed_var = var

    def predict(self, accel: float, coupling: float, dt: float) -> None:
        """``x ← F x + [a + c, 0] dt``, ``P ← F P Fᵀ + Q`` with ``F = [[1, −dt], [0, 1]]``."""
        self.speed += (accel - self.bias + coupling) * dt
        self.speed_var += -2.0 * dt * self.p_vb + dt * dt * self.p_bb + (self.speed_walk * dt) ** 2
        self.p_vb -= dt * self.p_bb
        self.p_bb += self.bias_walk**2 * dt

    def update(self, z: float, var: float) -> None:
        """A reading ``z`` of the speed with variance ``var``."""
        s = self.speed_var + var
        k_v, k_b = self.speed_var / s, self.p_vb / s
        innovation = z - self.speed
        self.speed += k_v * innovation
        self.bias += k_b * innovation
        self.p_bb -= k_b * self.p_vb
        self.p_vb -= k_v * self.p_vb
        self.speed_var -= k_v * self.speed_var


class _TiltGradient:
    """The accelerometer's gravity leak per unit of its own reading, ``s = dθ/d(a/g)``, learnt
    from the receiver's attitude: the body tilts with the acceleration (``θ = k a/g``, ``k`` the
    roll or pitch gradient), so the sensor reads ``a_m = a (1 + k)`` and ``a = a_m (1 − s)`` with
    ``s = k/(1 + k)``. Fitted on changes only (angle and lagged reading each less its
    ``highpass_s`` running mean), so a bank or slope under the vehicle (which tilts the
    antennas but is no body roll) and the accelerometer's bias stay out; the config's gradient
    is the prior, worth ``prior_weight`` of ``(a/g)²`` changes.
    """

    def __init__(self, gradient_rad_per_g: float, prior_weight: float, highpass_s: float) -> None:
        self.s0 = gradient_rad_per_g / (1.0 + gradient_rad_per_g)
        self.sxy, self.sxx = prior_weight * self.s0, prior_weight
        self.highpass_s = highpass_s
        self.mean_x = self.mean_angle = math.nan
        self.last_ns = 0

    @property
    def slope(self) -> float:
        """The fitted ``s``, held within a quarter and four times the config's: the body leans
        out of the turn and back on acceleration whatever the receiver's noise or sign
        (and to 0.1, about 6°/g, where the config says none)."""
        return float(np.clip(self.sxy / self.sxx, 0.25 * self.s0, max(4.0 * self.s0, 0.1)))

    def fix(self, angle_rad: float, reading_g: float, t_ns: int) -> None:
        """One receiver angle with the lagged accelerometer reading (in g) at its time."""
        if not (math.isfinite(angle_rad) and math.isfinite(reading_g)):
            return
        if math.isnan(self.mean_x):
            self.mean_x, self.mean_angle, self.last_ns = reading_g, angle_rad, t_ns
            return
        gain = 1.0 - math.exp(-max(t_ns - self.last_ns, 0) * 1e-9 / self.highpass_s)
        self.last_ns = t_ns
        self.mean_x += gain * (reading_g - self.mean_x)
        self.mean_angle += gain * (angle_rad - self.mean_angle)
        dx, dy = reading_g - self.mean_x, angle_rad - self.mean_angle
        self.sxy += dx * dy
        self.sxx += dx * dx


class FrontEnd:
    """One vehicle's sensor buffers and the small filters between them and the μ filter."""

    def __init__(self, config: Wheeled4wdSteeredConfig, fe: FrontEndConfig, tick_s: float) -> None:
        ch, ty = config.chassis, config.tyre
        self.ch, self.ty, self.fe, self.dt = ch, ty, fe, tick_s
        self._set_geometry(ch)
        self._set_radii(ty, fe)
        self._set_buffers()
        self._set_filters(ch, fe)
        self.yaw_prev = math.nan
        self.accel_prev = np.full(2, math.nan)  # the last tick's [a_x, a_y] [m/s²]
        self.slip_lag = np.zeros((2, 4))
        self.kappa_prev = np.full(4, np.nan)  # the last tick's kinematic κ
        self.kappa_ring = np.zeros(4)  # the relaxed κ's 1-σ from a ringing wheel
        self.last_tick_ns = 0

    def _set_geometry(self, ch: ChassisConfig) -> None:
        """Wheel positions from the CG ``(4,)`` [m], static loads ``(4,)`` [N], the driven
        axle's wheels and drive shares, and the antenna's arm ``(3,)`` [m]."""
        self.wheel_x = np.array([1, 1, -1, -1]) * np.array(
            [ch.cg_to_front_axle_m] * 2 + [ch.cg_to_rear_axle_m] * 2
        )
        self.wheel_y = (
            np.array([ch.front_track_m, -ch.front_track_m, ch.rear_track_m, -ch.rear_track_m]) / 2
        )
        wheelbase = ch.cg_to_front_axle_m + ch.cg_to_rear_axle_m
        mg = ch.mass_kg * GRAVITY_MPS2
        self.fz_static = (
            mg
            * np.array([ch.cg_to_rear_axle_m] * 2 + [ch.cg_to_front_axle_m] * 2)
            / (2 * wheelbase)
        )
        self.undriven = UNDRIVEN[ch.driven_axle]
        self.drive_share = DRIVE_SHARE[ch.driven_axle]
        self.antenna_arm_m = np.array(antenna_arm_m(ch))

    def _set_radii(self, ty: TyreConfig, fe: FrontEndConfig) -> None:
        """The radius and tyre state before any calibration: each wheel's starting radius
        ``(4,)`` [m], vertical stiffness, suspect flag and spreads, and the loads ``(4,)`` [N]."""
        # the paper's statically loaded radius; the product starts from a third of the
        # deflection (a rolling tyre's effective radius) and calibrates from there
        self.radius = ty.unloaded_radius_m - self.fz_static / ty.kz_npm * (
            1.0 if fe.paper else 1 / 3
        )
        self.calib_n = 0
        self.radius_drop = fe.radius_drop0
        self.kz_wheel = np.full(4, ty.kz_npm)
        self.suspect = np.zeros(4, dtype=bool)
        self.radius_std = np.full(4, 0.01 * ty.unloaded_radius_m)  # each wheel's own
        self.radius_common_rel = 0.0  # the calibration's GNSS error, shared by the four
        self.radius_scale_var = 0.01**2  # its relative variance (calibration_scale_var)
        self.speed_persist = 0.0  # the speed's considered persistent 1-σ [m/s]
        self.fz_cal = self.fz_static.copy()

    def _set_buffers(self) -> None:
        """Empty sensor buffers and no wheel speed, steering angle or GNSS sample yet."""
        self.imu: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.wheel_packets: list[tuple[np.ndarray, np.ndarray]] = []
        self.steer_packets: list[tuple[np.ndarray, np.ndarray]] = []
        self.gnss_queue: deque[GnssSample] = deque()
        self.omega = np.full(4, np.nan)
        self.steer_rad = math.nan
        self.steer_ns = 0  # the held angle's stamp
        self.gnss: GnssSample | None = None
        self.gnss_fresh = False

    def _set_filters(self, ch: ChassisConfig, fe: FrontEndConfig) -> None:
        """The speed, yaw, roll and pitch filters, the lagged load transfer ``(3,)`` and tilt
        reading ``(2,)``, and the tilt gradients from the chassis' priors."""
        self.vx = _AxisFilter(fe.speed_walk_mps2, fe.bias_walk_mps2_per_sqrt_s, 0.1)
        self.vy = _AxisFilter(fe.speed_walk_mps2, fe.bias_walk_mps2_per_sqrt_s, 0.1)
        self.vy.set_speed(0.0)
        # yaw angle (from east, counter-clockwise) and the yaw gyro's bias, corrected by the
        # receiver's heading: the bias times v_x would read as a lateral acceleration
        self.yaw = _AxisFilter(fe.yaw_walk_radps, fe.gyro_bias_walk_radps_per_sqrt_s, 0.005)
        # roll and pitch angles and their gyros' biases, corrected by the receiver's attitude:
        # a bias times the antenna's height would read as the CG's speed
        self.roll_gyro = _AxisFilter(fe.yaw_walk_radps, fe.gyro_bias_walk_radps_per_sqrt_s, 0.005)
        self.pitch_gyro = _AxisFilter(fe.yaw_walk_radps, fe.gyro_bias_walk_radps_per_sqrt_s, 0.005)
        self.transfer = np.zeros(3)  # lagged [long, lat front, lat rear] [N]
        self.tilt_reading = np.zeros(2)  # lagged raw [a_x, a_y] [m/s²] the body tilts with
        self.pitch = _TiltGradient(
            math.radians(ch.pitch_gradient_deg_per_g), fe.tilt_prior_weight, fe.tilt_highpass_s
        )
        self.roll = _TiltGradient(
            math.radians(ch.roll_gradient_deg_per_g), fe.tilt_prior_weight, fe.tilt_highpass_s
        )

    # --- input ------------------------------------------------------------------------------
    def push_imu(self, m: ImuBatch) -> None:
        self.imu.append(
            (np.asarray(m.stamp_ns), np.asarray(m.accel_mps2), np.asarray(m.gyro_radps))
        )

    def push_wheels(self, m: WheelSpeeds4) -> None:
        self.wheel_packets.append((np.asarray(m.stamp_ns), np.asarray(m.omega_radps)))

    def push_steering(self, m: SteeringAngles) -> None:
        self.steer_packets.append((np.asarray(m.stamp_ns), np.asarray(m.angle_rad)))

    def push_gnss(self, m: GnssSample) -> None:
        self.gnss_queue.append(m)

    def imu_until_ns(self) -> int | None:
        """The last IMU sample time held (ticks up to it can be computed)."""
        return int(self.imu[-1][0][-1]) if self.imu and self.imu[-1][0].size else None

    # --- one tick ----------------------------------------------------------------------------
    def _imu_window(self, t_ns: int) -> tuple[FloatArray, FloatArray, float] | None:
        """Mean specific force and rate over ``(t − tick, t]`` and how far before ``t`` the
        samples' mean stamp lies [s]; drops samples before it."""
        lo = t_ns - round(self.dt * 1e9)
        acc, gyr, before = [], [], []
        keep = []
        for stamps, a, g in self.imu:
            sel = (stamps > lo) & (stamps <= t_ns)
            acc.append(a[sel])
            gyr.append(g[sel])
            before.append(t_ns - stamps[sel])
            if stamps.size and stamps[-1] > t_ns:
                keep.append((stamps, a, g))
        self.imu = keep
        a = np.concatenate(acc) if acc else np.zeros((0, 3))
        g = np.concatenate(gyr) if gyr else np.zeros((0, 3))
        if not a.size:
            return None
        return a.mean(axis=0), g.mean(axis=0), float(np.concatenate(before).mean()) * 1e-9

    def _latest(self, t_ns: int) -> None:
        """Latest wheel speeds, steering angle and GNSS sample at or before ``t_ns``."""
        omega, self.wheel_packets = _latest_sample(self.wheel_packets, t_ns)
        if omega is not None:
            self.omega = omega[1]
        steer, self.steer_packets = _latest_sample(self.steer_packets, t_ns)
        if steer is not None:
            self.steer_ns, self.steer_rad = steer[0], float(steer[1])
        while self.gnss_queue and self.gnss_queue[0].stamp_ns <= t_ns:
            self.gnss = self.gnss_queue.popleft()
            self.gnss_fresh = True

    def tick(self, t_ns: int) -> FrontEndTick | None:
        """The inputs at tick ``t_ns`` (None until the IMU covers it and wheels are known)."""
        window = self._imu_window(t_ns)
        self._latest(t_ns)
        self.last_tick_ns = t_ns
        if window is None or not np.all(np.isfinite(self.omega)):
            return None
        accel, gyro, imu_lag_s = window
        ax_raw, ay_raw = float(accel[1]), float(-accel[0])
        yaw_rate = self._yaw_step(float(gyro[2]))
        rates = self._tilt_rate_step(gyro, yaw_rate)
        gnss = self._gnss_step(t_ns, ax_raw, ay_raw, rates)
        # the speed filters integrate the tilt-free readings, so their bias states hold the
        # sensors' biases alone (not the leak of the body's pitch or roll), taken off here
        ax_tilt, ay_tilt = self._detilt(ax_raw, ay_raw)
        ax, ay = ax_tilt - self.vx.bias, ay_tilt - self.vy.bias
        fz = self._loads(ax, ay)
        steer, delta = self._steer_angles(t_ns)
        self._calibrate(gnss, fz, delta, yaw_rate, (ax, ay))
        self._speed_step(ax_tilt, yaw_rate, gnss, fz, delta)
        self._side_slip_step(ay_tilt, yaw_rate, gnss)
        yaw_accel = 0.0 if math.isnan(self.yaw_prev) else (yaw_rate - self.yaw_prev) / self.dt
        self.yaw_prev = yaw_rate
        z_in = (ax, ay, yaw_accel, imu_lag_s)
        return self._tick_output(fz, delta, steer, yaw_rate, rates, gnss, z_in)

    def _gnss_step(
        self, t_ns: int, ax_raw: float, ay_raw: float, rates: FloatArray
    ) -> tuple[float, float] | None:
        """A fresh receiver velocity corrects heading and attitude, the tilt gradients learn,
        and the CG's ``(v_x, v_y)`` is returned (None: no fresh GNSS); ``rates`` (3,)."""
        gnss_ant = self._gnss_velocity(t_ns)
        if gnss_ant is not None:
            self._heading_update()
            self._attitude_update()
        self._learn_tilt(ax_raw, ay_raw, gnss_ant is not None)
        return self._gnss_at_cg(gnss_ant, rates)

    def _steer_angles(self, t_ns: int) -> tuple[float, FloatArray]:
        """The steering-wheel angle at ``t_ns`` and the wheels' steer angles ``(4,)`` (the
        front pair's through the steering ratio). Before the vehicle's first angle, or with
        the last older than ``steer_timeout_s``, the angle is unknown: NaN, and so the front
        pair's ``δ``; the stages that need it skip it (:meth:`_calibrate`, :meth:`_speed_step`)
        or give NaN for those wheels (:meth:`_slips`)."""
        stale = t_ns - self.steer_ns > round(self.fe.steer_timeout_s * 1e9)
        steer = math.nan if stale else self.steer_rad
        delta = np.zeros(4)
        delta[:2] = steer / self.ch.steering_ratio
        return steer, delta

    def _tick_output(
        self,
        fz: FloatArray,
        delta: FloatArray,
        steer: float,
        yaw_rate: float,
        rates: FloatArray,
        gnss: tuple[float, float] | None,
        z_in: tuple[float, float, float, float],
    ) -> FrontEndTick:
        """The tick's slips and measurement ``z`` (``z_in``: ``a_x``, ``a_y``, ``ṙ``, the IMU's
        lag [s]) with their 1-σ as :class:`FrontEndTick` (``fz``, ``delta`` (4,))."""
        kappa, alpha, k_std, a_std, alpha_lag = self._slips(fz, delta, yaw_rate)
        # the radii's shared scale error is in the speed's (the rims correct it) and cancels
        # in κ with it: the speed's 1-σ alone is the shared part
        k_common = math.sqrt(max(self.vx.speed_var, 0.0)) / max(abs(self.vx.speed), 1.0)
        vx = self.vx.speed
        z = self._measurement(vx, fz, z_in)
        return FrontEndTick(
            fz_n=fz,
            kz_npm=self.kz_wheel,
            alpha_rad=alpha,
            delta_rad=delta,
            kappa=kappa,
            kappa_std=k_std,
            kappa_common_std=k_common,
            alpha_std_rad=a_std,
            alpha_lag_rad=alpha_lag,
            z=z,
            vx_mps=vx,
            vx_std_mps=math.hypot(math.sqrt(max(self.vx.speed_var, 0.0)), self.speed_persist),
            vy_mps=self.vy.speed,
            yaw_rate_radps=yaw_rate,
            roll_pitch_rate_radps=rates[:2],
            vy_gnss_mps=gnss[1] if gnss is not None else math.nan,
            gnss=gnss is not None,
            steering=math.isfinite(steer),
            valid=self._tick_valid(vx, steer),
            tyre_suspect=self.tyre_suspect,
        )

    def _measurement(
        self, vx: float, fz: FloatArray, z_in: tuple[float, float, float, float]
    ) -> FloatArray:
        """The μ filter's ``z`` ``(3,)``: ``[a_x + resistances/m, a_y, ṙ]``, the accelerations
        carried to the tick (``z_in``: ``a_x``, ``a_y``, ``ṙ``, the IMU's lag [s])."""
        ax, ay, yaw_accel, imu_lag_s = z_in
        resist = 0.0 if self.fe.paper else self._resistance(vx, fz)
        ax_now, ay_now = self._at_tick(ax, ay, imu_lag_s)
        return np.array([ax_now + resist, ay_now, yaw_accel])

    def _tick_valid(self, vx: float, steer: float) -> bool:
        """Whether the tick may inform μ: above the speed floor, a steering angle known,
        calibrated (paper: always) and a yaw rate before it.

        Without a steering angle (none yet, or stale) no row of the update is known: the front
        pair's slip angles hold ``δ`` (``a_y``, ``ṙ``), and their forces reach ``a_x`` through
        ``cos δ`` and ``sin δ`` (at 0.1 rad, 10 % of the front axle's lateral force). The
        rows share one update, so none runs; ``FrontEndTick.steering`` says why."""
        calibrated = self.fe.paper or self.calibrated
        valid = (
            vx >= self.fe.min_speed_mps
            and math.isfinite(steer)
            and calibrated
            and not math.isnan(self.yaw_prev)
        )
        return bool(valid)

    def _resistance(self, vx: float, fz: FloatArray) -> float:
        """Drag and rolling resistance over the mass [m/s²] at speed ``vx``."""
        ch = self.ch
        return (
            0.5 * AIR_DENSITY_KGPM3 * ch.drag_area_m2 * vx * abs(vx)
            + ch.rolling_resistance * float(fz.sum()) * math.tanh(vx)
        ) / ch.mass_kg

    # --- the small filters --------------------------------------------------------------------
    def _at_tick(self, ax: float, ay: float, lag_s: float) -> tuple[float, float]:
        """The accelerations at the tick from means ``lag_s`` before it, carried along their
        change since the last tick (paper: as read; the first tick: as read)."""
        prev = self.accel_prev
        self.accel_prev = np.array([ax, ay])
        if self.fe.paper or math.isnan(prev[0]):
            return ax, ay
        step = lag_s / self.dt
        return ax + (ax - float(prev[0])) * step, ay + (ay - float(prev[1])) * step

    def _gnss_velocity(self, t_ns: int) -> tuple[float, float] | None:
        """GNSS ``(v_x, v_y)`` in the body frame when a fresh sample arrived, else None (the
        antenna's, as the receiver reads it)."""
        g = self.gnss
        if not self.gnss_fresh or g is None:
            return None
        self.gnss_fresh = False
        if t_ns - g.stamp_ns > self.fe.gnss_timeout_s * 1e9 or not math.isfinite(g.heading_rad):
            return None
        ve, vn, _ = g.vel_enu_mps
        h = g.heading_rad
        return ve * math.sin(h) + vn * math.cos(h), -ve * math.cos(h) + vn * math.sin(h)

    def _gnss_at_cg(
        self, vel: tuple[float, float] | None, rates: FloatArray
    ) -> tuple[float, float] | None:
        """The CG's velocity from the antenna's, with the tick's body rates ``(3,)`` (its
        window holds the fix's instant) and the arm tilted by the body's roll and pitch as
        :meth:`_detilt` takes them out, ``g·sin φ ≈ s_φ ā_y`` (paper: the antenna's, as read)."""
        if vel is None or self.fe.paper:
            return vel
        lag_x, lag_y = self.tilt_reading
        roll = self.roll.slope * float(lag_y) / GRAVITY_MPS2
        pitch = self.pitch.slope * float(lag_x) / GRAVITY_MPS2
        arm = tilted_arm_m(self.antenna_arm_m, roll, pitch)
        vx, vy = antenna_velocity_at_cg(np.array(vel), rates, arm)
        return float(vx), float(vy)

    def _speed_step(
        self,
        ax_tilt: float,
        yaw_rate: float,
        gnss: tuple[float, float] | None,
        fz: FloatArray,
        delta: FloatArray,
    ) -> None:
        """Forward speed: accelerometer, corrected by GNSS and, once their radius is
        calibrated, by the undriven wheels' rims (free rolling: no slip), not while a steered
        one's angle is unknown (its rim reads ``v_x cos δ``: 0.5 % off at 0.1 rad, held
        through the turn, ten times the rim's error)."""
        if math.isnan(self.vx.speed):
            self.vx.set_speed(gnss[0] if gnss else float(np.mean(self.omega * self.radius)))
        self.vx.predict(ax_tilt, yaw_rate * self.vy.speed, self.dt)
        if gnss is not None:
            r_gnss = GNSS_SPEED_STD_MPS**2
            gain = self.vx.speed_var / (self.vx.speed_var + r_gnss)
            self.speed_persist = float(consider_step(self.speed_persist, gain, 0.0))
            self.vx.update(gnss[0], r_gnss)
        free = self.undriven
        if self.fe.paper or not free.any() or not (self.calibrated or not self._gnss_recent()):
            return
        if np.isnan(delta[free]).any():
            return
        radius = self._radius_now(fz)
        c_x = load_adaptive_stiffness_n(
            fz, self.kz_wheel, self.ty.unloaded_radius_m, self.ty.c_px_npm2
        )
        ax = ax_tilt - self.vx.bias
        spin = spin_up_slip(ax, radius, c_x, self.fe.wheel_inertia_kgm2)
        brake = -(ax + self._resistance(self.vx.speed, fz))
        braked = self.fe.brake_share_std * brake_slip_std(brake, self.ch.mass_kg, c_x)
        rim = self.omega * radius / (1.0 + spin)
        w = self.vy.speed + self.wheel_x * yaw_rate
        vx_rim = (rim - w * np.sin(delta)) / np.cos(delta) + self.wheel_y * yaw_rate
        v = float(np.mean(vx_rim[free]))
        rel = math.hypot(
            float(np.mean(self.radius_std[free] / self.radius[free])),
            self.radius_common_rel,
            self.fe.wheel_inertia_rel_std * float(np.mean(spin[free])),
        )
        if float(np.mean(braked[free])) > math.hypot(rel, 5e-4):
            return  # the brake slip is a bias: it would not average out over the ticks
        var = (rel * v) ** 2 + (5e-4 * v) ** 2
        v_dot = ax + yaw_rate * self.vy.speed
        cross = math.hypot(
            float(np.mean(np.abs(np.tan(delta[free])))) * math.sqrt(max(self.vy.speed_var, 0.0)),
            self.fe.wheel_inertia_rel_std * float(np.mean(spin[free])) * v,
        )
        persist = rim_persistent_std_mps(
            v_dot, v, math.sqrt(self.radius_scale_var), cross, self.fe.wheel_speed_window_s
        )
        gain = self.vx.speed_var / (self.vx.speed_var + var)
        self.speed_persist = float(consider_step(self.speed_persist, gain, persist))
        self.vx.update(v, var)

    def _yaw_step(self, gyro_z_radps: float) -> float:
        """The yaw rate less the gyro's bias (paper: as read); the yaw angle predicted."""
        if self.fe.paper:
            return gyro_z_radps
        if math.isnan(self.yaw.speed):
            self.yaw.set_speed(0.0)
        self.yaw.predict(gyro_z_radps, 0.0, self.dt)
        return gyro_z_radps - self.yaw.bias

    def _heading_update(self) -> None:
        """A fresh receiver heading (compass, clockwise from north) corrects the yaw angle
        and so the gyro's bias: ``ψ̇ = r_gyro − b`` (not paper)."""
        g = self.gnss
        if self.fe.paper or g is None or not math.isfinite(g.heading_rad):
            return
        yaw = math.pi / 2 - g.heading_rad
        if self.yaw.speed_var > 0.5:  # the first heading: the angle starts there
            self.yaw.set_speed(yaw, self.fe.heading_std_rad**2)
            return
        wrapped = (yaw - self.yaw.speed + math.pi) % (2 * math.pi) - math.pi
        self.yaw.update(self.yaw.speed + wrapped, self.fe.heading_std_rad**2)

    def _tilt_rate_step(self, gyro: FloatArray, yaw_rate: float) -> FloatArray:
        """The body's rates ``(p, q, r)`` (:func:`body_rates_radps`), the roll and pitch gyros
        less their biases, their angles predicted (paper: as read)."""
        if self.fe.paper:
            return body_rates_radps(gyro, yaw_rate)
        read = []
        for f, rate in ((self.roll_gyro, float(gyro[1])), (self.pitch_gyro, float(gyro[0]))):
            if math.isnan(f.speed):
                f.set_speed(0.0)
            f.predict(rate, 0.0, self.dt)
            read.append(rate - f.bias)
        return body_rates_radps(np.array([read[1], read[0], 0.0]), yaw_rate)

    def _attitude_update(self) -> None:
        """A fresh receiver roll and pitch (where it gives them) correct the angles and so the
        roll and pitch gyros' biases, as the heading does the yaw's (not paper)."""
        g = self.gnss
        if self.fe.paper or g is None:
            return
        var = self.fe.attitude_std_rad**2
        for f, angle in ((self.roll_gyro, g.roll_rad), (self.pitch_gyro, g.pitch_rad)):
            if not math.isfinite(angle):
                continue
            if f.speed_var > 0.5:  # the first: the angle starts there
                f.set_speed(angle, var)
            else:
                f.update(angle, var)

    def _gnss_recent(self) -> bool:
        return self.gnss is not None and self.last_tick_ns - self.gnss.stamp_ns <= (
            self.fe.gnss_timeout_s * 1e9
        )

    def _detilt(self, ax: float, ay: float) -> tuple[float, float]:
        """The accelerations without the body's tilt, ``a_m − s ā_m`` with ``ā_m`` the reading
        lagged as the body follows it (``a_m (1 − s)`` when steady; paper: as read)."""
        if self.fe.paper:
            return ax, ay
        lag_x, lag_y = self.tilt_reading
        return ax - self.pitch.slope * float(lag_x), ay - self.roll.slope * float(lag_y)

    def _learn_tilt(self, ax_raw: float, ay_raw: float, fresh: bool) -> None:
        """Lag the raw accelerations as the body follows them (the load transfer's lag) and,
        at a fresh GNSS epoch with attitude, fit the gradients (not paper)."""
        if self.fe.paper:
            return
        lag = max(self.ch.load_transfer_lag_s, 1e-9)
        self.tilt_reading += (np.array([ax_raw, ay_raw]) - self.tilt_reading) * (
            1.0 - math.exp(-self.dt / lag)
        )
        g = self.gnss
        if not fresh or g is None:
            return
        self.pitch.fix(g.pitch_rad, float(self.tilt_reading[0]) / GRAVITY_MPS2, g.stamp_ns)
        self.roll.fix(g.roll_rad, float(self.tilt_reading[1]) / GRAVITY_MPS2, g.stamp_ns)

    def _side_slip_step(self, ay: float, yaw_rate: float, gnss: tuple[float, float] | None) -> None:
        """Lateral speed: ``v̇_y = a_y − b − r v_x`` corrected by GNSS (the paper reading: no
        bias, no GNSS, a slow leak to zero)."""
        if self.fe.paper:
            vy = self.vy.speed + (ay - yaw_rate * self.vx.speed) * self.dt
            self.vy.set_speed(vy * math.exp(-self.dt / self.fe.side_slip_leak_s))
            return
        self.vy.predict(ay, -yaw_rate * self.vx.speed, self.dt)
        if gnss is not None:
            self.vy.update(gnss[1], 0.04**2)

    def _loads(self, ax: float, ay: float) -> FloatArray:
        ch = self.ch
        wheelbase = ch.cg_to_front_axle_m + ch.cg_to_rear_axle_m
        m_h = ch.mass_kg * ch.cg_height_m
        share = ch.cg_to_rear_axle_m / wheelbase if self.fe.paper else ch.roll_stiffness_front_share
        target = np.array(
            [
                m_h * ax / wheelbase,
                share * m_h * ay / ch.front_track_m,
                (1 - share) * m_h * ay / ch.rear_track_m,
            ]
        )
        lag = 0.0 if self.fe.paper else ch.load_transfer_lag_s
        self.transfer += (target - self.transfer) * (1.0 - math.exp(-self.dt / max(lag, 1e-9)))
        lx, lf, lr = self.transfer
        fz = self.fz_static + np.array([-lx / 2 - lf, -lx / 2 + lf, lx / 2 - lr, lx / 2 + lr])
        return np.maximum(fz, 0.0)

    def _wheel_velocity(
        self, vx: float, vy: float, yaw_rate: float, delta: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """Each wheel centre's velocity along and across its heading (source eq. 11-13)."""
        u = vx - self.wheel_y * yaw_rate
        w = vy + self.wheel_x * yaw_rate
        return u * np.cos(delta) + w * np.sin(delta), -u * np.sin(delta) + w * np.cos(delta)

    def _slips(
        self, fz: FloatArray, delta: FloatArray, yaw_rate: float
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
        """κ, α, their 1-σ and α's lag (relaxed − kinematic) per wheel (source eq. 8-14),
        relaxed (not paper). κ's 1-σ here is each wheel's own (its radius, the rim speed's
        resolution); the speed's error moves all four κ together and is given apart
        (``FrontEndTick.kappa_common_std``). The relaxation length is the config's, the tyre's
        may be half or twice it: while the slip moves, half the distance between the
        kinematic and the relaxed slip is added to its 1-σ, and what the wheel moved between
        readings beyond their rounding (:func:`ringing_slip_std`). A wheel whose ``δ`` is
        unknown (NaN) has NaN slips; at its next known ``δ`` its relaxed slip restarts from the
        kinematic one and its ring from 0 (what the tyre did meanwhile is unknown)."""
        v_long, v_lat = self._wheel_velocity(self.vx.speed, self.vy.speed, yaw_rate, delta)
        denom = np.maximum(np.abs(v_long), 1.0)
        radius = self._radius_now(fz)
        kappa = (self.omega * radius - v_long) / denom
        alpha = -np.arctan2(v_lat, np.maximum(np.abs(v_long), 0.5))
        k_std = self.omega * self.radius_std / denom + 2e-4
        a_std = np.full(4, math.sqrt(max(self.vy.speed_var, 0.0))) / denom + 1e-3
        lag = np.zeros(4)
        if not self.fe.paper:
            rate = (np.abs(v_long) + 1.0) / max(self.ty.relaxation_length_m, 1e-3)
            gain = 1.0 - np.exp(-self.dt * rate)
            kinematic = np.stack([kappa, alpha])
            self.slip_lag = np.where(np.isnan(self.slip_lag), kinematic, self.slip_lag)
            self.kappa_ring = np.where(np.isnan(self.kappa_ring), 0.0, self.kappa_ring)
            self.slip_lag += gain * (kinematic - self.slip_lag)
            rounding = self.fe.wheel_speed_resolution_radps * radius / denom
            self.kappa_ring = ringing_slip_std(
                kappa, self.kappa_prev, self.kappa_ring, gain, rounding
            )
            self.kappa_prev = kappa.copy()
            k_std = k_std + 0.5 * np.abs(kappa - self.slip_lag[0]) + self.kappa_ring
            a_std = a_std + 0.5 * np.abs(alpha - self.slip_lag[1])
            lag = self.slip_lag[1] - alpha
            kappa, alpha = self.slip_lag
        return kappa.copy(), alpha.copy(), k_std, a_std, lag

    def _radius_now(self, fz: FloatArray) -> FloatArray:
        """Effective radius per wheel: the calibrated one, falling by ``ρ`` of the change of
        deflection since (paper: the statically loaded radius)."""
        if self.fe.paper:
            return self.radius
        return self.radius - self.radius_drop * (fz - self.fz_cal) / self.kz_wheel

    def _learn_tyres(self) -> None:
        """``ρ`` and each wheel's ``kz`` from the calibrated radii (``method.md`` §5, eq. 18):
        ``ρ_i = (r_u − r_e,i)·kz/Fz_i``, ``ρ`` their median (one soft tyre does not move it)
        within ``radius_drop_range``; a wheel whose ``ρ_i`` is off ``ρ`` by more than
        ``kz_tolerance`` is suspect and gets its own ``kz_i = ρ Fz_i/(r_u − r_e,i)``."""
        if not self.calibrated:
            return
        fz_n = np.maximum(self.fz_cal, 1.0)
        sink_m = self.ty.unloaded_radius_m - self.radius
        lo, hi = self.fe.radius_drop_range
        implied = sink_m * self.ty.kz_npm / fz_n
        self.radius_drop = float(np.clip(np.median(implied), lo, hi))
        self.suspect = np.abs(implied / self.radius_drop - 1.0) > self.fe.kz_tolerance
        own = self.radius_drop * fz_n / np.maximum(sink_m, 1e-4)
        kz = np.clip(own, 0.05 * self.ty.kz_npm, 20.0 * self.ty.kz_npm)
        self.kz_wheel = np.where(self.suspect, kz, self.ty.kz_npm)

    def _calibrate(
        self,
        gnss: tuple[float, float] | None,
        fz: FloatArray,
        delta: FloatArray,
        yaw_rate: float,
        accel: tuple[float, float],
    ) -> None:
        """Per-wheel radius from GNSS speed while straight and steady (running mean, then a
        ``calib_time_s`` average), allowing for the slip the resistances need. The GNSS
        speed's error (~0.03 m/s an epoch, 0.3 % at 10 m/s) enters the four radii alike: it is
        kept apart from each wheel's own error (``radius_std``: rim-speed resolution and the
        load model, 2e-4 of the radius), since a shared scale error of the radii cancels in κ
        where the speed comes from the same rims.

        Without a steering angle (``δ`` NaN) the front pair's is :func:`free_rolling_steer`'s
        while ``|a_y|`` is small too (``accel``: the bias-free ``a_x``, ``a_y``)."""
        ax, ay = accel
        if self.fe.paper or gnss is None or gnss[0] < 5.0:
            return
        if math.isnan(delta[0]):
            if abs(ay) >= 0.3:
                return
            u, w = self._wheel_velocity(gnss[0], gnss[1], yaw_rate, np.zeros(4))
            delta = free_rolling_steer(u, w)
        if not (abs(ax) < 0.3 and abs(yaw_rate) < 0.02 and abs(delta[0]) < 0.01):
            return
        v_long, _ = self._wheel_velocity(gnss[0], gnss[1], yaw_rate, delta)
        resist = self.ch.rolling_resistance * fz.sum() + 0.5 * AIR_DENSITY_KGPM3 * (
            self.ch.drag_area_m2 * gnss[0] ** 2
        )
        c_x = load_adaptive_stiffness_n(
            fz, self.kz_wheel, self.ty.unloaded_radius_m, self.ty.c_px_npm2
        )
        expect = resist * self.drive_share / np.maximum(c_x, 1.0)
        measured = v_long * (1.0 + expect) / np.maximum(self.omega, 1e-3)
        self.calib_n += 1
        gain = max(0.1 / self.fe.calib_time_s, 1.0 / self.calib_n)  # GNSS at about 10 Hz
        self.radius += gain * (measured - self.radius)
        self.fz_cal += gain * (fz - self.fz_cal)
        self.radius_common_rel = 0.003 / math.sqrt(self.calib_n)
        self.radius_scale_var = float(calibration_scale_var(self.radius_scale_var, gain, gnss[0]))
        self.radius_std = 2e-4 * self.radius
        self._learn_tyres()

    @property
    def tyre_suspect(self) -> bool:
        """A calibrated radius sinks more (or less) under its load than the config's ``kz``
        and the learnt ``ρ`` give: that tyre's vertical stiffness is not the config's (a soft or
        damaged tyre deflects more and rolls smaller); ``kz_wheel`` holds the learnt one."""
        return bool(self.suspect.any())

    @property
    def calibrated(self) -> bool:
        return self.calib_n >= self.fe.calib_samples
