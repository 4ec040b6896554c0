"""Four-wheel vehicle truth, batched over runs: a model the friction estimator does not share.

Frame x forward, y left, z up at the centre of gravity; wheels in Corner order (FL, FR, RL,
RR). What it has that the estimator's model has not:

* brush tyres (the same law, :func:`estimator.friction.brush.brush_forces`) acting on
  *relaxed* slips: ``dκ'/dt = (|v|+1)/σx · (κ − κ')`` and the same for ``α'`` with ``σy``;
* wheel spin ``I_w ω̇ = T − Fx r_e`` with open differentials (the same torque left and right
  whatever their radii, split ``0.5 (1 ± b)`` by the differential's friction; ``all``: a centre
  split), brakes front-biased with the same torque left and right, traction control cutting a
  wheel's torque above a combined slip ``hypot(κ, tan α)`` of ``tc_slip``;
* effective radius falling with load, ``r_e = r_u − ρ Fz/kz`` (ρ per run);
* load transfer through first-order lags, its lateral part split between the axles by the
  roll-stiffness share ``ζ`` (not the geometric ``lr/L`` of the static formula);
* body roll and pitch (gradients and lag per run) that tilt the accelerometers;
* Ackermann toe on the front wheels, drag ``½ρ_air·CdA·v²`` and rolling resistance.

A driver holds the manoeuvre's target speed with a feed-forward + PI torque and turns the
steering wheel to its profile, counter-steering yaw rate beyond the kinematic one
(1 rad of road-wheel angle per rad/s; the reference kept within ``(|a_y| + 0.5)/v``, as a
stability control would). RK4 on a 2 ms grid.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from estimator._arrays import FloatArray
from estimator.config import DrivenAxle, Wheeled4wdSteeredConfig
from estimator.friction.brush import brush_forces, load_adaptive_stiffness_n

__all__ = ["AIR_DENSITY_KGPM3", "GRAVITY_MPS2", "Truth", "TruthParams", "integrate"]

GRAVITY_MPS2 = 9.80665
AIR_DENSITY_KGPM3 = 1.2
DT_S = 2e-3


@dataclass(frozen=True, slots=True)
class TruthParams:
    """Per-run physical numbers, each ``(R,)`` or ``(R, 4)`` per wheel."""

    mass_kg: FloatArray
    yaw_inertia_kgm2: FloatArray
    lf_m: FloatArray
    lr_m: FloatArray
    half_track_f_m: FloatArray
    half_track_r_m: FloatArray
    cg_height_m: FloatArray
    steering_ratio: FloatArray
    drag_area_m2: FloatArray
    rolling_resistance: FloatArray
    c_px_npm2: FloatArray  # (R, 4)
    c_py_npm2: FloatArray  # (R, 4)
    kz_npm: FloatArray  # (R, 4)
    radius_m: FloatArray  # (R, 4) unloaded
    radius_drop: FloatArray  # ρ in r_e = r_u − ρ Fz/kz
    relax_x_m: FloatArray
    relax_y_m: FloatArray
    roll_front_share: FloatArray
    load_lag_s: FloatArray
    roll_rad_per_g: FloatArray
    pitch_rad_per_g: FloatArray
    tilt_lag_s: FloatArray
    wheel_inertia_kgm2: FloatArray
    drive_share: FloatArray  # (R, 4) share of drive torque per wheel
    diff_bias: FloatArray  # b: the left wheel of each axle gets 1 + b of the even split
    ackermann: FloatArray
    tc_slip: FloatArray

    @staticmethod
    def draw(
        configs: list[Wheeled4wdSteeredConfig], rngs: list[np.random.Generator], kz_npm: FloatArray
    ) -> TruthParams:
        """The runs' truths: the configs' numbers (``kz_npm`` ``(R, 4)`` per wheel, to damage
        one) and per-run draws (uniform) of what the config does not say: c_p ×0.97-1.03,
        ρ 0.25-0.4, σx 0.2-0.5 m, σy 0.3-0.7 m, ζ 0.5-0.7, load lag 0.05-0.2 s, roll and
        pitch gradients ×0.7-1.3 of the config's, tilt lag 0.1-0.3 s, I_w 0.8-2 kg·m²,
        Ackermann 0-0.08, traction control above κ 0.03-0.08, differential bias b −0.02..0.02."""
        r = len(configs)
        ch = [c.chassis for c in configs]
        ty = [c.tyre for c in configs]

        def col(xs: list[float]) -> FloatArray:
            return np.array(xs, dtype=np.float64)

        def u(lo: float, hi: float, shape: tuple[int, ...] = (r,)) -> FloatArray:
            """One draw per run, each from its run's generator."""
            return np.stack([g.uniform(lo, hi, shape[1:]) for g in rngs])

        share = np.zeros((r, 4))
        for i, c in enumerate(ch):
            share[i] = {
                DrivenAxle.FRONT: (0.5, 0.5, 0, 0),
                DrivenAxle.REAR: (0, 0, 0.5, 0.5),
                DrivenAxle.ALL: (0.25, 0.25, 0.25, 0.25),
            }[c.driven_axle]
        return TruthParams(
            mass_kg=col([c.mass_kg for c in ch]),
            yaw_inertia_kgm2=col([c.yaw_inertia_kgm2 for c in ch]),
            lf_m=col([c.cg_to_front_axle_m for c in ch]),
            lr_m=col([c.cg_to_rear_axle_m for c in ch]),
            half_track_f_m=col([c.front_track_m / 2 for c in ch]),
            half_track_r_m=col([c.rear_track_m / 2 for c in ch]),
            cg_height_m=col([c.cg_height_m for c in ch]),
            steering_ratio=col([c.steering_ratio for c in ch]),
            drag_area_m2=col([c.drag_area_m2 for c in ch]),
            rolling_resistance=col([c.rolling_resistance for c in ch]),
            c_px_npm2=col([t.c_px_npm2 for t in ty])[:, None] * u(0.97, 1.03, (r, 4)),
            c_py_npm2=col([t.c_py_npm2 for t in ty])[:, None] * u(0.97, 1.03, (r, 4)),
            kz_npm=np.asarray(kz_npm, dtype=np.float64),
            radius_m=np.repeat(col([t.unloaded_radius_m for t in ty])[:, None], 4, axis=1),
            radius_drop=u(0.25, 0.4),
            relax_x_m=u(0.2, 0.5),
            relax_y_m=u(0.3, 0.7),
            roll_front_share=u(0.5, 0.7),
            load_lag_s=u(0.05, 0.2),
            roll_rad_per_g=np.radians(col([c.roll_gradient_deg_per_g for c in ch])) * u(0.7, 1.3),
            pitch_rad_per_g=np.radians(col([c.pitch_gradient_deg_per_g for c in ch])) * u(0.7, 1.3),
            tilt_lag_s=u(0.1, 0.3),
            wheel_inertia_kgm2=u(0.8, 2.0),
            drive_share=share,
            ackermann=u(0.0, 0.08),
            tc_slip=u(0.03, 0.08),
            diff_bias=u(-0.02, 0.02),
        )

    def wheel_xy(self) -> tuple[FloatArray, FloatArray]:
        """Wheel positions from the CG, ``(R, 4)`` each."""
        x = np.stack([self.lf_m, self.lf_m, -self.lr_m, -self.lr_m], axis=-1)
        y = np.stack(
            [self.half_track_f_m, -self.half_track_f_m, self.half_track_r_m, -self.half_track_r_m],
            axis=-1,
        )
        return x, y


class S:
    """Columns of the state matrix ``(R, N_STATE)``."""

    VX, VY, R, YAW, EAST, NORTH = range(6)
    OMEGA = slice(6, 10)
    KAPPA = slice(10, 14)
    ALPHA = slice(14, 18)
    LOAD_X = 18  # longitudinal load transfer to the rear axle [N]
    LOAD_YF, LOAD_YR = 19, 20  # lateral transfer to the right wheels, per axle [N]
    ROLL, PITCH = 21, 22
    SPEED_INT = 23  # driver's integral of speed error [m]
    ANGLE = slice(24, 28)  # wheel angles [rad], ``θ̇ = ω`` (read by the tone rings only)


N_STATE = 28


@dataclass(frozen=True, slots=True)
class Truth:
    """What the run did, sampled every ``every`` grid steps: arrays ``(R, T)`` or ``(R, T, 4)``."""

    t_s: FloatArray
    mu: FloatArray
    vx_mps: FloatArray
    vy_mps: FloatArray
    yaw_rate_radps: FloatArray
    yaw_rad: FloatArray
    east_m: FloatArray
    north_m: FloatArray
    ax_mps2: FloatArray
    ay_mps2: FloatArray
    yaw_accel_radps2: FloatArray
    roll_rad: FloatArray
    pitch_rad: FloatArray
    roll_rate_radps: FloatArray
    pitch_rate_radps: FloatArray
    steer_wheel_rad: FloatArray
    omega_radps: FloatArray
    kappa: FloatArray
    alpha_rad: FloatArray
    delta_rad: FloatArray
    fz_n: FloatArray
    fx_n: FloatArray
    fy_n: FloatArray
    angle_sub_rad: FloatArray  # (R, T, every, 4): wheel angles at each grid step of a row

    def take(self, run: int) -> Truth:
        """One run's rows (a leading axis of 1 dropped)."""
        return Truth(*(getattr(self, f.name)[run] for f in fields(self)))


@dataclass(frozen=True, slots=True)
class _Drive:
    """Profiles on the grid, ``(R, K)``: target speed, its slope, steering-wheel angle, μ."""

    speed_mps: FloatArray
    accel_mps2: FloatArray
    steer_rad: FloatArray
    mu: FloatArray


def _deriv(
    x: FloatArray, k: int, p: TruthParams, d: _Drive, acc: FloatArray
) -> tuple[FloatArray, dict[str, FloatArray]]:
    """State derivative at grid step ``k`` and what the sensors read; ``acc`` ``(R, 2)`` is the
    last step's body acceleration (what the lagged load transfer and tilt follow)."""
    vx, vy, r = x[:, S.VX], x[:, S.VY], x[:, S.R]
    wx, wy = p.wheel_xy()
    wheelbase = p.lf_m + p.lr_m
    delta_f, delta = _steer_angles(x, d.steer_rad[:, k] / p.steering_ratio, p, acc, wheelbase)
    u = vx[:, None] - wy * r[:, None]
    w = vy[:, None] + wx * r[:, None]
    cos_d, sin_d = np.cos(delta), np.sin(delta)
    v_long = u * cos_d + w * sin_d
    v_lat = -u * sin_d + w * cos_d
    fz = _wheel_loads(x, p, wheelbase)
    r_eff = p.radius_m - p.radius_drop[:, None] * fz / p.kz_npm
    omega = x[:, S.OMEGA]
    kappa = (omega * r_eff - v_long) / np.maximum(np.abs(v_long), 1.0)
    alpha = -np.arctan2(v_lat, np.maximum(np.abs(v_long), 0.5))
    speed = np.abs(v_long) + 1.0
    kr, ar = x[:, S.KAPPA], x[:, S.ALPHA]
    mu = d.mu[:, k][:, None]
    cx = load_adaptive_stiffness_n(fz, p.kz_npm, p.radius_m, p.c_px_npm2)
    cy = load_adaptive_stiffness_n(fz, p.kz_npm, p.radius_m, p.c_py_npm2)
    fx, fy = brush_forces(kr, ar, fz, mu, cx, cy)
    fxb = fx * cos_d - fy * sin_d
    fyb = fx * sin_d + fy * cos_d
    ax, ay, r_dot = _body_accelerations(vx, fxb, fyb, fz, (wx, wy), p)
    torque = _torques(x, k, p, d, r_eff, np.hypot(kappa, np.tan(ar)))
    dx = np.zeros_like(x)
    dx[:, S.VX] = ax + r * vy
    dx[:, S.VY] = ay - r * vx
    dx[:, S.R] = r_dot
    dx[:, S.YAW] = r
    yaw = x[:, S.YAW]
    dx[:, S.EAST] = vx * np.cos(yaw) - vy * np.sin(yaw)
    dx[:, S.NORTH] = vx * np.sin(yaw) + vy * np.cos(yaw)
    dx[:, S.OMEGA] = (torque - fx * r_eff) / p.wheel_inertia_kgm2[:, None]
    dx[:, S.KAPPA] = speed / p.relax_x_m[:, None] * (kappa - kr)
    dx[:, S.ALPHA] = speed / p.relax_y_m[:, None] * (alpha - ar)
    _lagged_load_and_tilt(dx, x, p, acc, wheelbase)
    dx[:, S.SPEED_INT] = d.speed_mps[:, k] - vx
    dx[:, S.ANGLE] = omega
    out = {
        "ax": ax,
        "ay": ay,
        "r_dot": r_dot,
        "fx": fx,
        "fy": fy,
        "fz": fz,
        "delta": delta,
        "steer": delta_f * p.steering_ratio,
        "kappa": kr,
        "alpha": ar,
    }
    return dx, out


def _body_accelerations(
    vx: FloatArray,
    fxb: FloatArray,
    fyb: FloatArray,
    fz: FloatArray,
    wheel_xy: tuple[FloatArray, FloatArray],
    p: TruthParams,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``(a_x, a_y, ṙ)`` of the body from the tyres' body-frame forces, drag and rolling."""
    wx, wy = wheel_xy
    resist = 0.5 * AIR_DENSITY_KGPM3 * p.drag_area_m2 * vx * np.abs(vx) + (
        p.rolling_resistance * fz.sum(axis=-1) * np.tanh(vx)
    )
    ax = (fxb.sum(axis=-1) - resist) / p.mass_kg
    ay = fyb.sum(axis=-1) / p.mass_kg
    r_dot = (wx * fyb - wy * fxb).sum(axis=-1) / p.yaw_inertia_kgm2
    return ax, ay, r_dot


def _steer_angles(
    x: FloatArray, delta_f: FloatArray, p: TruthParams, acc: FloatArray, wheelbase: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Front steer (yaw-rate limited by the grip) and the four wheels' angles with Ackermann."""
    vx, r = x[:, S.VX], x[:, S.R]
    r_ref = vx * np.tan(delta_f) / wheelbase / (1.0 + (vx / 20.0) ** 2)
    r_max = (np.abs(acc[:, 1]) + 0.5) / np.maximum(np.abs(vx), 1.0)
    delta_f = delta_f - 1.0 * (r - np.clip(r_ref, -r_max, r_max))
    toe = p.ackermann * np.abs(delta_f)
    delta = np.stack(
        [
            delta_f * (1 + toe * np.sign(delta_f)),
            delta_f * (1 - toe * np.sign(delta_f)),
            0 * delta_f,
            0 * delta_f,
        ],
        axis=-1,
    )
    return delta_f, delta


def _wheel_loads(x: FloatArray, p: TruthParams, wheelbase: FloatArray) -> FloatArray:
    """Normal loads ``(R, 4)``: static share plus the lagged transfers, never negative."""
    mg = p.mass_kg * GRAVITY_MPS2
    static = np.stack([mg * p.lr_m, mg * p.lr_m, mg * p.lf_m, mg * p.lf_m], axis=-1) / (
        2 * wheelbase[:, None]
    )
    lx, lyf, lyr = x[:, S.LOAD_X], x[:, S.LOAD_YF], x[:, S.LOAD_YR]
    fz = static + np.stack([-lx / 2 - lyf, -lx / 2 + lyf, lx / 2 - lyr, lx / 2 + lyr], axis=-1)
    return np.maximum(fz, 0.0)


def _lagged_load_and_tilt(
    dx: FloatArray, x: FloatArray, p: TruthParams, acc: FloatArray, wheelbase: FloatArray
) -> None:
    """Rates of the load transfers and of roll and pitch, first-order lags behind ``acc``."""
    m_h = p.mass_kg * p.cg_height_m
    z = p.roll_front_share
    targets = (
        m_h * acc[:, 0] / wheelbase,
        z * m_h * acc[:, 1] / (2 * p.half_track_f_m),
        (1 - z) * m_h * acc[:, 1] / (2 * p.half_track_r_m),
    )
    for col, target in zip((S.LOAD_X, S.LOAD_YF, S.LOAD_YR), targets, strict=True):
        dx[:, col] = (target - x[:, col]) / p.load_lag_s
    dx[:, S.ROLL] = (p.roll_rad_per_g * acc[:, 1] / GRAVITY_MPS2 - x[:, S.ROLL]) / p.tilt_lag_s
    dx[:, S.PITCH] = (p.pitch_rad_per_g * acc[:, 0] / GRAVITY_MPS2 - x[:, S.PITCH]) / p.tilt_lag_s


def _torques(
    x: FloatArray, k: int, p: TruthParams, d: _Drive, r_eff: FloatArray, slip: FloatArray
) -> FloatArray:
    """Wheel torques ``(R, 4)``: the driver's feed-forward + PI force through the differentials
    (drive) or the brakes (60 % front), cut per wheel by traction control above a combined slip
    ``hypot(κ, tan α)`` of ``tc_slip``.

    An open differential (and a brake at one pressure) gives both wheels of an axle the same
    torque, not the same force: ``T_i = F · share_i · r̄ · (1 ± b)`` with ``r̄`` the mean
    effective radius of the wheels it drives, so a wheel on a smaller radius pushes harder
    (``F_L r_L = F_R r_R`` at steady spin)."""
    vx = x[:, S.VX]
    err = d.speed_mps[:, k] - vx
    force = p.mass_kg * (d.accel_mps2[:, k] + 1.5 * err + 0.3 * x[:, S.SPEED_INT])
    force += 0.5 * AIR_DENSITY_KGPM3 * p.drag_area_m2 * vx * vx
    force += p.rolling_resistance * p.mass_kg * GRAVITY_MPS2
    brake_share = np.array([0.3, 0.3, 0.2, 0.2])
    share = np.where(force[:, None] >= 0.0, p.drive_share, brake_share)
    weight = (share > 0.0).astype(np.float64)
    r_mean = (r_eff * weight).sum(axis=-1) / np.maximum(weight.sum(axis=-1), 1.0)
    split = 1.0 + p.diff_bias[:, None] * np.array([1.0, -1.0, 1.0, -1.0])
    torque = force[:, None] * share * split * r_mean[:, None]
    cut = np.clip(1.0 - (slip - p.tc_slip[:, None]) / 0.05, 0.0, 1.0)
    return torque * cut


def _rk4(
    x: FloatArray, k: int, p: TruthParams, d: _Drive, acc: FloatArray
) -> tuple[FloatArray, dict]:
    k1, out = _deriv(x, k, p, d, acc)
    k2, _ = _deriv(x + 0.5 * DT_S * k1, k, p, d, acc)
    k3, _ = _deriv(x + 0.5 * DT_S * k2, k, p, d, acc)
    k4, _ = _deriv(x + DT_S * k3, k, p, d, acc)
    return x + DT_S / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4), out


def integrate(
    p: TruthParams,
    speed_mps: FloatArray,
    steer_rad: FloatArray,
    mu: FloatArray,
    every: int = 10,
) -> Truth:
    """Run the truth over the grid ``k·DT_S`` of the profiles ``(R, K)``; rows every ``every``,
    the wheel angles at every grid step (``Truth.angle_sub_rad``)."""
    n_runs, steps = speed_mps.shape
    accel = np.gradient(speed_mps, DT_S, axis=1)
    drive = _Drive(speed_mps, accel, steer_rad, mu)
    x = np.zeros((n_runs, N_STATE))
    x[:, S.VX] = speed_mps[:, 0]
    x[:, S.OMEGA] = (speed_mps[:, 0] / p.radius_m[:, 0])[:, None]
    acc = np.zeros((n_runs, 2))
    x = _settle_wheels(x, p, drive)
    rows: list[tuple[FloatArray, dict]] = []
    angles = np.zeros((n_runs, -(-steps // every) * every, 4))
    for k in range(steps):
        x_new, out = _rk4(x, k, p, drive, acc)
        acc = np.stack([out["ax"], out["ay"]], axis=-1)
        angles[:, k] = x[:, S.ANGLE]
        if k % every == 0:
            rows.append((x.copy(), out))
        x = x_new
    angles[:, steps:] = x[:, None, S.ANGLE]
    return _truth(rows, drive, every, angles.reshape(n_runs, -1, every, 4))


def _settle_wheels(x: FloatArray, p: TruthParams, d: _Drive) -> FloatArray:
    """Start each wheel at its free-rolling speed under static load (no start-up transient)."""
    _, out = _deriv(x, 0, p, d, np.zeros((x.shape[0], 2)))
    r_eff = p.radius_m - p.radius_drop[:, None] * out["fz"] / p.kz_npm
    x[:, S.OMEGA] = x[:, [S.VX]] / r_eff
    return x


def _truth(rows: list[tuple[FloatArray, dict]], d: _Drive, every: int, angles: FloatArray) -> Truth:
    xs = np.stack([r[0] for r in rows], axis=1)

    def o(key: str) -> FloatArray:
        return np.stack([r[1][key] for r in rows], axis=1)

    idx = np.arange(len(rows)) * every
    roll, pitch = xs[..., S.ROLL], xs[..., S.PITCH]
    dt = every * DT_S
    return Truth(
        t_s=np.broadcast_to(idx * DT_S, xs.shape[:2]).copy(),
        mu=d.mu[:, idx],
        vx_mps=xs[..., S.VX],
        vy_mps=xs[..., S.VY],
        yaw_rate_radps=xs[..., S.R],
        yaw_rad=xs[..., S.YAW],
        east_m=xs[..., S.EAST],
        north_m=xs[..., S.NORTH],
        ax_mps2=o("ax"),
        ay_mps2=o("ay"),
        yaw_accel_radps2=o("r_dot"),
        roll_rad=roll,
        pitch_rad=pitch,
        roll_rate_radps=np.gradient(roll, dt, axis=1),
        pitch_rate_radps=np.gradient(pitch, dt, axis=1),
        steer_wheel_rad=o("steer"),
        omega_radps=xs[..., S.OMEGA],
        kappa=o("kappa"),
        alpha_rad=o("alpha"),
        delta_rad=o("delta"),
        fz_n=o("fz"),
        fx_n=o("fx"),
        fy_n=o("fy"),
        angle_sub_rad=angles,
    )
