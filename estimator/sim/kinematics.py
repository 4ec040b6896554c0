"""Ground truth of a rear-wheel-driven tractor on a fine time grid.

Model (``../shared/docs/method.md`` section 1, frames of :mod:`estimator.types`):

* The body frame is X right, Y forward, Z up. Its attitude is heading ``ψ`` (from north,
  clockwise), pitch ``θ`` (nose up +) and roll ``φ`` (right side down +), composed as
  ``R = Rz(−ψ)·Rx(θ)·Ry(φ)`` (body → ENU). The body forward axis in ENU is
  ``(sinψ·cosθ, cosψ·cosθ, sinθ)``, the direction eq. (1) projects the GNSS velocity on.
* The origin ``O`` (ground projection of the rear-axle midpoint) moves along the body Y axis
  only: ``v_O = V0·e_Y`` (no side slip). Every rigid-body point ``p`` (body coordinates, from
  ``O``) then moves at ``v_p = V0·e_Y + ω × p``. For a point on the vertical through ``O`` at
  height ``h`` the forward component is ``V0 − ωx·h``, which is eq. (2)(3) of the method; for the
  wheel contact points ``(∓b/2, 0, 0)`` it is ``V0 ∓ ωz·b/2``, eq. (4)(5). The truth therefore
  satisfies the source's structure exactly; lever arms (horizontal offsets) add ``ωz·x`` terms.
* The scenario gives the body yaw rate ``ωz`` (what the gyro's Z axis reads) and the attitude
  ``θ, φ`` (terrain under the wheels, which is a function of the distance travelled, plus a body
  wobble, plus a pitch sway of the body about the rear axle). The heading rate follows from
  the Euler kinematics ``ωz = −ψ̇·cosθ·cosφ + θ̇·sinφ``, and ``ωx = θ̇·cosφ + ψ̇·cosθ·sinφ``,
  ``ωy = φ̇ − ψ̇·sinθ``.
* Acceleration of ``O`` in the body frame: ``(−V0·ωz, V̇0, V0·ωx)``; of a point ``p``:
  ``a_O + ω̇ × p + ω × (ω × p)``. Specific force (what an accelerometer reads) adds gravity's
  reaction ``g·(−sinφ·cosθ, sinθ, cosφ·cosθ)``: at rest on a slope ``θ`` the forward axis reads
  ``g·sinθ``.
* Slip ``s`` per driven wheel comes from a traction model (:class:`TractionModel`) on the grade
  under the axle, ``θ`` less the sway (the body swings about the axle; the ground does not),
  and is turned into a rim speed by inverting eq. (8)(9) exactly: driving (``s ≥ 0``)
  ``r·W = V/(1 − s)``, braking (``s < 0``) ``r·W = V·(1 + s)``.

Derivatives on the grid are second-order central differences (``numpy.gradient``); integrals are
cumulative trapezoids. All profiles are smooth at the grid scale (the default grid is 500 Hz).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from estimator._arrays import FloatArray
from estimator.sim._signals import Profile, cumtrapz, ou_process

__all__ = [
    "GRAVITY_MPS2",
    "FineTruth",
    "MotionPlan",
    "TractionModel",
    "integrate_plan",
    "rim_speed_from_slip",
    "rotation_body_to_enu",
    "slip_from_speeds",
]

GRAVITY_MPS2 = 9.80665
"""Standard gravity; the simulator's accelerometers read this at rest on level ground."""

TimeSpeedProfile = Callable[[FloatArray, FloatArray], FloatArray]


def _zero_ts(t: FloatArray, v0: FloatArray) -> FloatArray:
    return np.zeros_like(t)


def _zero(x: FloatArray) -> FloatArray:
    return np.zeros_like(np.asarray(x, dtype=np.float64))


def _firm_soil(x: FloatArray) -> FloatArray:
    return np.full_like(np.asarray(x, dtype=np.float64), 0.6)


@dataclass(frozen=True, slots=True)
class TractionModel:
    """Slip of the driven (rear) wheels from the traction they must transmit.

    Traction demand as a share of the rear axle's load::

        d = (V̇0/g + sinθ + c_rr + drawbar) / rear_load_fraction

    A saturating tyre curve ``μ(s) = μ_max·(1 − exp(−|s|/s0))·sign(s)`` is inverted for the
    slip: ``s = −sign(d)·s0·ln(1 − min(|d|/μ_max, max_utilisation))``. Turning adds
    ``±turn_gain·V0·ωz/g`` (the outer wheel slips slightly more, as observed in the field runs of
    method.md section 1) and each wheel gets a slow Ornstein-Uhlenbeck "soil texture" term.

    Attributes
    ----------
    s0 : float
        Slip scale of the tyre curve (fraction); slope at the origin is ``μ_max/s0``.
    rolling_resistance : float
        Rolling resistance coefficient ``c_rr``.
    rear_load_fraction : float
        Share of the vehicle's weight on the driven rear axle.
    turn_gain : float
        Extra slip of the outer wheel (and less of the inner) per g of lateral acceleration.
    max_utilisation : float
        Cap of ``|d|/μ_max`` (keeps the slip finite: at most ``s0·ln(1/(1−cap))``).
    texture_std : float
        Standard deviation of the per-wheel texture term (fraction).
    texture_tau_s : float
        Its correlation time.
    """

    s0: float = 0.15
    rolling_resistance: float = 0.05
    rear_load_fraction: float = 0.6
    turn_gain: float = 0.1
    max_utilisation: float = 0.95
    texture_std: float = 0.003
    texture_tau_s: float = 1.5

    def slip(
        self,
        accel_mps2: FloatArray,
        pitch_rad: FloatArray,
        drawbar: FloatArray,
        mu_max: FloatArray,
    ) -> FloatArray:
        """Slip (fraction, shape (n,)) of a wheel pair before the turn and texture terms."""
        demand = (
            accel_mps2 / GRAVITY_MPS2 + np.sin(pitch_rad) + self.rolling_resistance + drawbar
        ) / self.rear_load_fraction
        ratio = np.minimum(np.abs(demand) / mu_max, self.max_utilisation)
        return -np.sign(demand) * self.s0 * np.log1p(-ratio)


@dataclass(frozen=True, slots=True)
class MotionPlan:
    """What a scenario prescribes; :func:`integrate_plan` turns it into truth.

    Time profiles take seconds from the start; ``*_ts`` profiles take ``(t_s, v0_mps)`` so they
    can fade with speed (no yaw rate at standstill); terrain profiles take metres travelled.

    Attributes
    ----------
    duration_s : float
    speed_mps : Profile
        ``V0(t) ≥ 0``, forward speed of ``O``.
    yaw_rate_ts : callable
        Body yaw rate ``ωz(t, V0)`` (CCW +), rad/s.
    pitch_wobble_ts, roll_wobble_ts : callable
        Body pitch/roll (rad) on top of the terrain's.
    pitch_sway_ts : callable
        Body pitch (rad) about the rear axle on top of both (a cab swaying): the body and what
        it carries pitch, the grade under the axle, which the traction model reads, does not.
    terrain_pitch_rad, terrain_roll_rad : Profile
        Slope under the vehicle as a function of distance (m).
    mu_max : Profile
        Peak traction coefficient of the ground as a function of distance (wet patch: lower).
    drawbar : Profile
        Drawbar pull of an implement, as a share of the vehicle's weight, function of time.
    heading0_rad : float
        Initial heading (from north, clockwise).
    traction : TractionModel
    slip_offset : Profile
        Slip (fraction) added to both driven wheels as a function of time, on top of the
        traction model's (steps and ramps: a wet patch, an implement lowered or lifted).
    free_rolling : (bool, bool)
        Wheels (left, right) that are not driven: they roll without slip (a front-drive car's
        rear wheels).
    """

    duration_s: float
    speed_mps: Profile
    yaw_rate_ts: TimeSpeedProfile = _zero_ts
    pitch_wobble_ts: TimeSpeedProfile = _zero_ts
    roll_wobble_ts: TimeSpeedProfile = _zero_ts
    pitch_sway_ts: TimeSpeedProfile = _zero_ts
    terrain_pitch_rad: Profile = _zero
    terrain_roll_rad: Profile = _zero
    mu_max: Profile = _firm_soil
    drawbar: Profile = _zero
    heading0_rad: float = 0.0
    traction: TractionModel = field(default_factory=TractionModel)
    slip_offset: Profile = _zero
    free_rolling: tuple[bool, bool] = (False, False)


def rotation_body_to_enu(psi: FloatArray, theta: FloatArray, phi: FloatArray) -> FloatArray:
    """``R = Rz(−ψ)·Rx(θ)·Ry(φ)`` for arrays of angles; shape (n, 3, 3), body → ENU."""
    cps, sps = np.cos(psi), np.sin(psi)
    cth, sth = np.cos(theta), np.sin(theta)
    cph, sph = np.cos(phi), np.sin(phi)
    r = np.empty((np.size(psi), 3, 3))
    # columns: images of body X, Y, Z
    r[:, 0, 0] = cps * cph + sps * sth * sph
    r[:, 1, 0] = -sps * cph + cps * sth * sph
    r[:, 2, 0] = -cth * sph
    r[:, 0, 1] = sps * cth
    r[:, 1, 1] = cps * cth
    r[:, 2, 1] = sth
    r[:, 0, 2] = cps * sph - sps * sth * cph
    r[:, 1, 2] = -sps * sph - cps * sth * cph
    r[:, 2, 2] = cth * cph
    return r


def rim_speed_from_slip(ground_mps: FloatArray, slip: FloatArray) -> FloatArray:
    """Invert eq. (8)(9): rim speed ``r·W`` from ground speed ``V ≥ 0`` and slip (fraction).

    Driving ``s ≥ 0``: ``S = (rW − V)/rW`` so ``rW = V/(1 − s)``; braking ``s < 0``:
    ``S = (rW − V)/V`` so ``rW = V·(1 + s)``. Slip must be in ``(−1, 1)``.
    """
    s = np.asarray(slip, dtype=np.float64)
    v = np.asarray(ground_mps, dtype=np.float64)
    return np.where(s >= 0.0, v / (1.0 - np.maximum(s, 0.0)), v * (1.0 + np.minimum(s, 0.0)))


def slip_from_speeds(rim_mps: FloatArray, ground_mps: FloatArray) -> FloatArray:
    """Eq. (8)(9): ``S = (rW − V)/max(rW, V)`` as a fraction; NaN where both are ≤ 0."""
    rim = np.asarray(rim_mps, dtype=np.float64)
    v = np.asarray(ground_mps, dtype=np.float64)
    den = np.maximum(rim, v)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0.0, (rim - v) / np.where(den > 0.0, den, 1.0), np.nan)


@dataclass(frozen=True, slots=True)
class FineTruth:
    """Truth on the fine grid; every array has ``n`` rows.

    Attributes
    ----------
    t_s : (n,)
        Seconds from the start.
    v0_mps, a0_mps2, dist_m : (n,)
        Forward speed of ``O``, its time derivative, distance travelled.
    psi_rad, theta_rad, phi_rad : (n,)
        Heading, pitch, roll.
    omega_radps, alpha_radps2 : (n, 3)
        Body angular rate (ωx, ωy, ωz) and its derivative.
    pos_enu_m : (n, 3)
        Position of ``O`` in the local ENU frame.
    rot : (n, 3, 3)
        Body → ENU rotation.
    ground_mps, slip, rim_mps, wheel_radps, wheel_angle_rad : (n, 2)
        Per driven wheel (left, right): contact-point forward speed (eq. 4/5), slip (fraction,
        NaN at standstill), rim speed ``r·W``, angular speed ``W``, integrated angle.
    mu_max : (n,)
        Ground's peak traction coefficient under the vehicle.
    """

    t_s: FloatArray
    v0_mps: FloatArray
    a0_mps2: FloatArray
    dist_m: FloatArray
    psi_rad: FloatArray
    theta_rad: FloatArray
    phi_rad: FloatArray
    omega_radps: FloatArray
    alpha_radps2: FloatArray
    pos_enu_m: FloatArray
    rot: FloatArray
    ground_mps: FloatArray
    slip: FloatArray
    rim_mps: FloatArray
    wheel_radps: FloatArray
    wheel_angle_rad: FloatArray
    mu_max: FloatArray

    def point_velocity_body(self, p: FloatArray) -> FloatArray:
        """Velocity (body frame, shape (n, 3)) of the body-fixed point ``p`` = (x, y, z) from O."""
        v = np.cross(self.omega_radps, np.asarray(p, dtype=np.float64)[None, :])
        v[:, 1] += self.v0_mps
        return v

    def point_accel_body(self, p: FloatArray) -> FloatArray:
        """Inertial acceleration of point ``p`` expressed in the body frame, shape (n, 3)."""
        pp = np.asarray(p, dtype=np.float64)[None, :]
        w = self.omega_radps
        a = np.cross(self.alpha_radps2, pp) + np.cross(w, np.cross(w, pp))
        a[:, 0] += -self.v0_mps * w[:, 2]
        a[:, 1] += self.a0_mps2
        a[:, 2] += self.v0_mps * w[:, 0]
        return a

    def specific_force_body(self, p: FloatArray) -> FloatArray:
        """What an ideal accelerometer at ``p`` reads (body frame, gravity included), (n, 3)."""
        f = self.point_accel_body(p)
        # gravity's reaction, +g along ENU up, seen in the body frame: third row of R
        f += GRAVITY_MPS2 * self.rot[:, 2, :]
        return f


def integrate_plan(
    plan: MotionPlan,
    *,
    fine_rate_hz: float,
    track_width_m: float,
    wheel_radius_m: tuple[float, float],
    rng: np.random.Generator,
) -> FineTruth:
    """Evaluate ``plan`` on a grid of ``fine_rate_hz`` from 0 to ``plan.duration_s`` inclusive.

    ``wheel_radius_m`` are the *true* rolling radii (they may differ from the configured ones).
    ``rng`` draws the slip texture. Raises ``ValueError`` if a wheel would roll backwards.
    """
    dt = 1.0 / fine_rate_hz
    n = round(plan.duration_s * fine_rate_hz) + 1
    t: FloatArray = np.asarray(np.arange(n) * dt, dtype=np.float64)
    v0: FloatArray = np.asarray(np.maximum(plan.speed_mps(t), 0.0), dtype=np.float64)
    a0: FloatArray = np.asarray(np.gradient(v0, dt), dtype=np.float64)
    dist = cumtrapz(v0, dt)

    sway = np.asarray(plan.pitch_sway_ts(t, v0), dtype=np.float64)
    psi, theta, phi, wz, omega = _attitude(plan, t, v0, dist, dt, sway)
    alpha = np.gradient(omega, dt, axis=0)

    rot = rotation_body_to_enu(psi, theta, phi)
    vel_enu = v0[:, None] * rot[:, :, 1]
    pos = np.stack([cumtrapz(vel_enu[:, k], dt) for k in range(3)], axis=1)

    half_b = 0.5 * track_width_m
    ground = np.stack([v0 - wz * half_b, v0 + wz * half_b], axis=1)
    if np.any(ground < -1e-9):
        raise ValueError("scenario makes a driven wheel roll backwards; lower the yaw rate")
    ground = np.maximum(ground, 0.0)

    mu = np.asarray(plan.mu_max(dist), dtype=np.float64)
    slip = _wheel_slip(plan, t, (v0, a0, wz), theta - sway, mu, rng)
    rim = rim_speed_from_slip(ground, slip)
    radius = np.asarray(wheel_radius_m, dtype=np.float64)[None, :]
    wheel = rim / radius
    angle = np.stack([cumtrapz(wheel[:, k], dt) for k in range(2)], axis=1)
    slip = np.where(ground > 0.0, slip, np.nan)
    return FineTruth(
        t_s=t,
        v0_mps=v0,
        a0_mps2=a0,
        dist_m=dist,
        psi_rad=psi,
        theta_rad=theta,
        phi_rad=phi,
        omega_radps=omega,
        alpha_radps2=alpha,
        pos_enu_m=pos,
        rot=rot,
        ground_mps=ground,
        slip=slip,
        rim_mps=rim,
        wheel_radps=wheel,
        wheel_angle_rad=angle,
        mu_max=mu,
    )


def _attitude(
    plan: MotionPlan, t: FloatArray, v0: FloatArray, dist: FloatArray, dt: float, sway: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """``(ψ, θ, φ, ω_z, ω (n, 3))``: terrain, wobble and sway tilt, the heading giving the yaw
    rate."""
    theta = plan.terrain_pitch_rad(dist) + plan.pitch_wobble_ts(t, v0) + sway
    phi = plan.terrain_roll_rad(dist) + plan.roll_wobble_ts(t, v0)
    wz = np.asarray(plan.yaw_rate_ts(t, v0), dtype=np.float64)
    theta_dot = np.gradient(theta, dt)
    phi_dot = np.gradient(phi, dt)
    psi_dot = (theta_dot * np.sin(phi) - wz) / (np.cos(theta) * np.cos(phi))
    psi = plan.heading0_rad + cumtrapz(psi_dot, dt)
    wx = theta_dot * np.cos(phi) + psi_dot * np.cos(theta) * np.sin(phi)
    wy = phi_dot - psi_dot * np.sin(theta)
    return psi, theta, phi, wz, np.stack([wx, wy, wz], axis=1)


def _wheel_slip(
    plan: MotionPlan,
    t: FloatArray,
    motion: tuple[FloatArray, FloatArray, FloatArray],
    theta: FloatArray,
    mu: FloatArray,
    rng: np.random.Generator,
) -> FloatArray:
    """Slip of both driven wheels ``(n, 2)``: traction, turn, texture and offset, clipped."""
    v0, a0, wz = motion
    base = plan.traction.slip(a0, theta, plan.drawbar(t), mu)
    turn = plan.traction.turn_gain * v0 * wz / GRAVITY_MPS2
    moving = np.clip(v0 / 0.5, 0.0, 1.0)
    tex = np.stack(
        [
            ou_process(rng, t, plan.traction.texture_std, plan.traction.texture_tau_s) * moving,
            ou_process(rng, t, plan.traction.texture_std, plan.traction.texture_tau_s) * moving,
        ],
        axis=1,
    )
    base = base + np.asarray(plan.slip_offset(t), dtype=np.float64) * moving
    slip = np.stack([base - turn, base + turn], axis=1) + tex
    slip = np.clip(slip, -0.9, 0.9)
    if any(plan.free_rolling):
        slip = np.where(np.asarray(plan.free_rolling)[None, :], 0.0, slip)
    return slip
