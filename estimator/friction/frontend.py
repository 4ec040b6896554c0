"""Per-wheel slip, slip angle, steer angle and load from the sensors, with their uncertainty.

One :class:`FrontEnd` per vehicle turns IMU, CAN wheel speeds, steering-wheel angle and
(optional) GNSS into the μ filter's inputs each tick (``method.md`` §5, source eq. 7-15):

* speed ``v_x`` and the forward accelerometer's bias from a two-state Kalman filter driven by
  the accelerometer and corrected by GNSS forward speed (or, without GNSS, the undriven
  wheels' mean rim speed);
* side-slip ``v_y``: ``v̇_y = a_y − r v_x`` corrected by GNSS (velocity across the heading);
  the source's reading (``FrontEndConfig.paper``) integrates it with a slow leak to zero;
* tilt: body roll and pitch follow the accelerations (``φ = k_φ a_y/g``, ``θ = k_θ a_x/g``,
  the config's gradients), so the accelerometers read ``a(1 + k)``: divided out (not in the
  paper reading);
* loads: static + longitudinal ``m a_x h/L`` + lateral ``m a_y h/b`` split between the axles
  by the roll-stiffness share, through a first-order lag (paper: the static formula, lateral
  split ``lr/L``, no lag);
* radius: calibrated per wheel while driving straight and steady (the slip there is what the
  resistances need), then falling by a third of the deflection change with load (paper: the
  statically loaded radius ``r_u − Fz/kz``);
* relaxation: κ and α pass a first-order lag over the tyre's relaxation length (not paper).

Frame: x forward, y left (the IMU's X right, Y forward: ``a_y = −accel[:, 0]``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from estimator._arrays import FloatArray
from estimator.config import DrivenAxle, Wheeled4wdSteeredConfig
from estimator.friction.model import GRAVITY_MPS2
from estimator.types import GnssSample, ImuBatch, SteeringAngles, WheelSpeeds4

__all__ = ["FrontEnd", "FrontEndConfig", "FrontEndTick"]

AIR_DENSITY_KGPM3 = 1.2
_UNDRIVEN = {
    DrivenAxle.FRONT: np.array([False, False, True, True]),
    DrivenAxle.REAR: np.array([True, True, False, False]),
    DrivenAxle.ALL: np.zeros(4, dtype=bool),
}
_DRIVE_SHARE = {
    DrivenAxle.FRONT: np.array([0.5, 0.5, 0.0, 0.0]),
    DrivenAxle.REAR: np.array([0.0, 0.0, 0.5, 0.5]),
    DrivenAxle.ALL: np.full(4, 0.25),
}


@dataclass(frozen=True, slots=True)
class FrontEndConfig:
    """Front-end settings: ``paper`` the source's reading (see the module docstring).

    ``min_speed_mps``: no μ update below it; ``gnss_timeout_s``: GNSS older than this is
    not used; ``calib_time_s``: time constant of the radius calibration.
    """

    paper: bool = False
    min_speed_mps: float = 3.0
    gnss_timeout_s: float = 0.5
    calib_time_s: float = 1.0
    speed_walk_mps2: float = 0.3
    bias_walk_mps2_per_sqrt_s: float = 0.005
    side_slip_leak_s: float = 5.0


@dataclass(frozen=True, slots=True)
class FrontEndTick:
    """One tick's inputs (per wheel ``(4,)``) and measurements, with 1-σ where the filter uses it."""

    fz_n: FloatArray
    alpha_rad: FloatArray
    delta_rad: FloatArray
    kappa: FloatArray
    kappa_std: FloatArray
    alpha_std_rad: FloatArray
    z: FloatArray  # [a_x + resistances/m, a_y, ṙ]
    vx_mps: float
    vy_mps: float
    gnss: bool
    valid: bool


class FrontEnd:
    """One vehicle's sensor buffers and the small filters between them and the μ filter."""

    def __init__(self, config: Wheeled4wdSteeredConfig, fe: FrontEndConfig, tick_s: float) -> None:
        ch, ty = config.chassis, config.tyre
        self.ch, self.ty, self.fe, self.dt = ch, ty, fe, tick_s
        self.wheel_x = np.array([1, 1, -1, -1]) * np.array(
            [ch.cg_to_front_axle_m] * 2 + [ch.cg_to_rear_axle_m] * 2
        )
        self.wheel_y = np.array([ch.front_track_m, -ch.front_track_m, ch.rear_track_m,
                                 -ch.rear_track_m]) / 2
        wheelbase = ch.cg_to_front_axle_m + ch.cg_to_rear_axle_m
        mg = ch.mass_kg * GRAVITY_MPS2
        self.fz_static = mg * np.array([ch.cg_to_rear_axle_m] * 2 + [ch.cg_to_front_axle_m] * 2) / (
            2 * wheelbase
        )
        self.undriven = _UNDRIVEN[ch.driven_axle]
        self.drive_share = _DRIVE_SHARE[ch.driven_axle]
        self.radius = ty.unloaded_radius_m - self.fz_static / ty.kz_npm
        self.radius_std = np.full(4, 0.01 * ty.unloaded_radius_m)
        self.fz_cal = self.fz_static.copy()
        self.imu: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.omega = np.full(4, np.nan)
        self.steer_rad = math.nan
        self.gnss: GnssSample | None = None
        self.gnss_fresh = False
        self.v = np.array([math.nan, 0.0])  # [v_x, accelerometer bias]
        self.pv = np.diag([1.0, 0.1**2])
        self.vy, self.vy_var = 0.0, 0.5**2
        self.transfer = np.zeros(3)  # lagged [long, lat front, lat rear] [N]
        self.yaw_prev = math.nan
        self.slip_lag = np.zeros((2, 4))

    # --- input ------------------------------------------------------------------------------
    def push_imu(self, m: ImuBatch) -> None:
        self.imu.append((np.asarray(m.stamp_ns), np.asarray(m.accel_mps2), np.asarray(m.gyro_radps)))

    def push_wheels(self, m: WheelSpeeds4, until_ns: int | None = None) -> None:
        self._wheels = getattr(self, "_wheels", [])
        self._wheels.append((np.asarray(m.stamp_ns), np.asarray(m.omega_radps)))

    def push_steering(self, m: SteeringAngles) -> None:
        self._steer = getattr(self, "_steer", [])
        self._steer.append((np.asarray(m.stamp_ns), np.asarray(m.angle_rad)))

    def push_gnss(self, m: GnssSample) -> None:
        self._gnss = getattr(self, "_gnss", [])
        self._gnss.append(m)

    def imu_until_ns(self) -> int | None:
        """The last IMU sample time held (ticks up to it can be computed)."""
        return int(self.imu[-1][0][-1]) if self.imu and self.imu[-1][0].size else None

    # --- one tick ----------------------------------------------------------------------------
    def _imu_window(self, t_ns: int) -> tuple[FloatArray, FloatArray] | None:
        """Mean specific force and rate over ``(t − tick, t]``; drops samples before it."""
        lo = t_ns - round(self.dt * 1e9)
        acc, gyr = [], []
        keep = []
        for stamps, a, g in self.imu:
            sel = (stamps > lo) & (stamps <= t_ns)
            acc.append(a[sel])
            gyr.append(g[sel])
            if stamps.size and stamps[-1] > t_ns:
                keep.append((stamps, a, g))
        self.imu = keep
        a = np.concatenate(acc) if acc else np.zeros((0, 3))
        g = np.concatenate(gyr) if gyr else np.zeros((0, 3))
        if not a.size:
            return None
        return a.mean(axis=0), g.mean(axis=0)

    def _latest(self, t_ns: int) -> None:
        """Latest wheel speeds, steering angle and GNSS sample at or before ``t_ns``."""
        for name in ("_wheels", "_steer"):
            buf = getattr(self, name, [])
            rest = []
            for stamps, vals in buf:
                sel = np.flatnonzero(stamps <= t_ns)
                if sel.size:
                    if name == "_wheels":
                        self.omega = vals[sel[-1]]
                    else:
                        self.steer_rad = float(vals[sel[-1]])
                if stamps.size and stamps[-1] > t_ns:
                    rest.append((stamps, vals))
            setattr(self, name, rest)
        gbuf = getattr(self, "_gnss", [])
        while gbuf and gbuf[0].stamp_ns <= t_ns:
            self.gnss = gbuf.pop(0)
            self.gnss_fresh = True

    def tick(self, t_ns: int) -> FrontEndTick | None:
        """The inputs at tick ``t_ns`` (None until the IMU covers it and wheels are known)."""
        window = self._imu_window(t_ns)
        self._latest(t_ns)
        if window is None or not np.all(np.isfinite(self.omega)):
            return None
        accel, gyro = window
        ax_raw, ay_raw, yaw_rate = float(accel[1]), float(-accel[0]), float(gyro[2])
        gnss = self._gnss_velocity(t_ns)
        self._speed_step(ax_raw, yaw_rate, gnss)
        ax, ay = self._detilt(ax_raw - self.v[1], ay_raw)
        self._side_slip_step(ay, yaw_rate, gnss)
        fz = self._loads(ax, ay)
        delta = np.zeros(4)
        steer = self.steer_rad if math.isfinite(self.steer_rad) else 0.0
        delta[:2] = steer / self.ch.steering_ratio
        yaw_accel = 0.0 if math.isnan(self.yaw_prev) else (yaw_rate - self.yaw_prev) / self.dt
        self.yaw_prev = yaw_rate
        kappa, alpha, k_std, a_std = self._slips(fz, delta, yaw_rate, ax)
        resist = 0.0
        vx = float(self.v[0])
        if not self.fe.paper:
            resist = (0.5 * AIR_DENSITY_KGPM3 * self.ch.drag_area_m2 * vx * abs(vx)
                      + self.ch.rolling_resistance * float(fz.sum()) * math.tanh(vx)) / self.ch.mass_kg
        z = np.array([ax + resist, ay, yaw_accel])
        valid = vx >= self.fe.min_speed_mps and math.isfinite(steer) and not math.isnan(
            self.yaw_prev
        )
        return FrontEndTick(fz, alpha, delta, kappa, k_std, a_std, z, vx, self.vy, gnss is not None,
                            bool(valid))

    # --- the small filters --------------------------------------------------------------------
    def _gnss_velocity(self, t_ns: int) -> tuple[float, float] | None:
        """GNSS ``(v_x, v_y)`` in the body frame when a fresh sample arrived, else None."""
        g = self.gnss
        if not self.gnss_fresh or g is None:
            return None
        self.gnss_fresh = False
        if t_ns - g.stamp_ns > self.fe.gnss_timeout_s * 1e9 or not math.isfinite(g.heading_rad):
            return None
        ve, vn, _ = g.vel_enu_mps
        h = g.heading_rad
        return ve * math.sin(h) + vn * math.cos(h), -ve * math.cos(h) + vn * math.sin(h)

    def _speed_step(self, ax_raw: float, yaw_rate: float, gnss: tuple[float, float] | None) -> None:
        """``[v_x, b]``: ``v̇ = a_x − b + r v_y``; GNSS forward speed, else undriven rims."""
        dt = self.dt
        if math.isnan(self.v[0]):
            rims = self.omega * self.radius
            self.v[0] = gnss[0] if gnss else float(np.mean(rims))
        f = np.array([[1.0, -dt], [0.0, 1.0]])
        self.v = np.array([self.v[0] + (ax_raw - self.v[1] + yaw_rate * self.vy) * dt, self.v[1]])
        q = np.diag([(self.fe.speed_walk_mps2 * dt) ** 2, self.fe.bias_walk_mps2_per_sqrt_s**2 * dt])
        self.pv = f @ self.pv @ f.T + q
        if gnss is not None:
            self._speed_update(gnss[0], 0.03**2)
        elif self.undriven.any():
            rim = float(np.mean((self.omega * self.radius)[self.undriven]))
            self._speed_update(rim, 0.05**2 + (0.003 * rim) ** 2)

    def _speed_update(self, z: float, var: float) -> None:
        s = self.pv[0, 0] + var
        k = self.pv[:, 0] / s
        self.v = self.v + k * (z - self.v[0])
        self.pv = self.pv - np.outer(k, self.pv[0])

    def _detilt(self, ax: float, ay: float) -> tuple[float, float]:
        if self.fe.paper:
            return ax, ay
        k_pitch = math.radians(self.ch.pitch_gradient_deg_per_g)
        k_roll = math.radians(self.ch.roll_gradient_deg_per_g)
        return ax / (1.0 + k_pitch), ay / (1.0 + k_roll)

    def _side_slip_step(self, ay: float, yaw_rate: float, gnss: tuple[float, float] | None) -> None:
        dt = self.dt
        self.vy += (ay - yaw_rate * float(self.v[0])) * dt
        self.vy_var += (0.05**2) * dt
        if self.fe.paper:
            self.vy *= math.exp(-dt / self.fe.side_slip_leak_s)
            return
        if gnss is not None:
            k = self.vy_var / (self.vy_var + 0.04**2)
            self.vy += k * (gnss[1] - self.vy)
            self.vy_var *= 1.0 - k

    def _loads(self, ax: float, ay: float) -> FloatArray:
        ch = self.ch
        wheelbase = ch.cg_to_front_axle_m + ch.cg_to_rear_axle_m
        m_h = ch.mass_kg * ch.cg_height_m
        share = (ch.cg_to_rear_axle_m / wheelbase if self.fe.paper
                 else ch.roll_stiffness_front_share)
        target = np.array([m_h * ax / wheelbase, share * m_h * ay / ch.front_track_m,
                           (1 - share) * m_h * ay / ch.rear_track_m])
        lag = 0.0 if self.fe.paper else ch.load_transfer_lag_s
        self.transfer += (target - self.transfer) * (1.0 - math.exp(-self.dt / max(lag, 1e-9)))
        lx, lf, lr = self.transfer
        fz = self.fz_static + np.array([-lx / 2 - lf, -lx / 2 + lf, lx / 2 - lr, lx / 2 + lr])
        return np.maximum(fz, 0.0)

    def _slips(
        self, fz: FloatArray, delta: FloatArray, yaw_rate: float, ax: float
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """κ, α and their 1-σ per wheel (source eq. 8-14)."""
        vx, vy = float(self.v[0]), self.vy
        u = vx - self.wheel_y * yaw_rate
        w = vy + self.wheel_x * yaw_rate
        v_long = u * np.cos(delta) + w * np.sin(delta)
        v_lat = -u * np.sin(delta) + w * np.cos(delta)
        radius = self._radius(fz, v_long, delta, yaw_rate, ax)
        denom = np.maximum(np.abs(v_long), 1.0)
        kappa = (self.omega * radius - v_long) / denom
        alpha = -np.arctan2(v_lat, np.maximum(np.abs(v_long), 0.5))
        v_std = math.sqrt(max(self.pv[0, 0], 0.0))
        k_std = np.hypot(v_std, self.omega * self.radius_std) / denom + 2e-4
        a_std = np.full(4, math.sqrt(self.vy_var)) / denom + 1e-3
        if not self.fe.paper:
            gain = 1.0 - np.exp(-self.dt * (np.abs(v_long) + 1.0) / max(self.ty.relaxation_length_m, 1e-3))
            self.slip_lag += gain * (np.stack([kappa, alpha]) - self.slip_lag)
            kappa, alpha = self.slip_lag
        return kappa.copy(), alpha.copy(), k_std, a_std

    def _radius(
        self, fz: FloatArray, v_long: FloatArray, delta: FloatArray, yaw_rate: float, ax: float
    ) -> FloatArray:
        """Effective radius per wheel; calibrated while straight and steady (not paper)."""
        if self.fe.paper:
            return self.radius
        steady = (abs(ax) < 0.3 and abs(yaw_rate) < 0.02 and abs(delta[0]) < 0.01
                  and float(self.v[0]) > 5.0 and self.pv[0, 0] < 0.05**2)
        drop = (fz - self.fz_cal) / (3.0 * self.ty.kz_npm)
        if steady:
            resist = self.ch.rolling_resistance * fz.sum() + 0.5 * AIR_DENSITY_KGPM3 * (
                self.ch.drag_area_m2 * float(self.v[0]) ** 2)
            c_x = 2.0 * self.ty.c_px_npm2 * (2 * self.ty.unloaded_radius_m * fz / self.ty.kz_npm)
            expect = resist * self.drive_share / np.maximum(c_x, 1.0)
            measured = v_long * (1.0 + expect) / np.maximum(self.omega, 1e-3)
            gain = self.dt / self.fe.calib_time_s
            self.radius += gain * (measured - self.radius)
            self.fz_cal += gain * (fz - self.fz_cal)
            self.radius_std = np.maximum(self.radius_std * (1 - gain), 2e-4 * self.radius)
            drop = np.zeros(4)
        return self.radius - drop
