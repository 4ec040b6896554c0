"""The friction front end for many vehicles at once: one numpy pass per round.

:class:`FleetFrontEnd` holds every vehicle's front-end state in arrays indexed by a slot
(``(N,)`` per vehicle, ``(N, 4)`` per wheel) and steps the vehicles due in a round together
from their :class:`~.sensors.SensedTicks`: the forward, lateral and yaw speed/bias filters,
the tilt gradients, the loads, the radius calibration, the slips and the measurement vector.
The equations, their reasons and the paper reading are :mod:`.frontend`'s (its
:class:`~.frontend.FrontEnd` is the per-vehicle reference the tests hold this one to, 1e-9):
here each stage runs on all vehicles of the round, a stage that applies to some only (a
fresh GNSS epoch, a steady straight for the calibration) on that subset.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from estimator._arrays import BoolArray, FloatArray, IntArray
from estimator.config import Wheeled4wdSteeredConfig
from estimator.friction.brush import load_adaptive_stiffness_n
from estimator.friction.frontend import (
    AIR_DENSITY_KGPM3,
    DRIVE_SHARE,
    GNSS_SPEED_STD_MPS,
    UNDRIVEN,
    FrontEndConfig,
    antenna_arm_m,
    antenna_velocity_at_cg,
    body_rates_radps,
    brake_slip_std,
    calibration_scale_var,
    consider_step,
    free_rolling_steer,
    rim_persistent_std_mps,
    ringing_slip_std,
    spin_up_slip,
    tilted_arm_m,
)
from estimator.friction.model import GRAVITY_MPS2
from estimator.friction.sensors import SensedTicks

__all__ = ["FleetFrontEnd", "FrontEndTicks"]


@dataclass(frozen=True, slots=True)
class FrontEndTicks:
    """One round's front-end output, one row per vehicle: :class:`~.frontend.FrontEndTick`'s
    fields batched (``(B, 4)`` per wheel, ``(B,)`` per vehicle, ``z`` ``(B, 3)``)."""

    fz_n: FloatArray
    kz_npm: FloatArray
    alpha_rad: FloatArray
    delta_rad: FloatArray
    kappa: FloatArray
    kappa_std: FloatArray
    kappa_common_std: FloatArray
    alpha_std_rad: FloatArray
    alpha_lag_rad: FloatArray
    z: FloatArray
    vx_mps: FloatArray
    vx_std_mps: FloatArray
    vy_mps: FloatArray
    yaw_rate_radps: FloatArray
    roll_pitch_rate_radps: FloatArray
    vy_gnss_mps: FloatArray
    gnss: BoolArray
    steering: BoolArray
    valid: BoolArray
    tyre_suspect: BoolArray


class _Arrays:
    """Per-slot arrays that grow with the fleet (first axis the slot)."""

    def _grow(self, capacity: int) -> None:
        for name, value in list(vars(self).items()):
            if isinstance(value, np.ndarray) and value.shape[0] < capacity:
                more = np.zeros((capacity - value.shape[0], *value.shape[1:]), value.dtype)
                setattr(self, name, np.concatenate([value, more]))


class _AxisFilters(_Arrays):
    """:class:`~.frontend._AxisFilter` for every slot: speed ``v`` and bias ``b`` with
    ``v̇ = a − b + c``, ``ḃ = w``; covariance ``[[var, p_vb], [p_vb, p_bb]]``."""

    def __init__(self, speed_walk: float, bias_walk: float) -> None:
        self.speed_walk, self.bias_walk = speed_walk, bias_walk
        self.speed = np.zeros(0)
        self.bias = np.zeros(0)
        self.var = np.zeros(0)
        self.p_vb = np.zeros(0)
        self.p_bb = np.zeros(0)

    def reset(self, slot: int, speed: float, bias0_std: float) -> None:
        self.speed[slot], self.bias[slot] = speed, 0.0
        self.var[slot], self.p_vb[slot], self.p_bb[slot] = 1.0, 0.0, bias0_std**2

    def predict(self, s: IntArray, accel: FloatArray, coupling: FloatArray, dt: float) -> None:
        """``x ← F x + [a + c, 0] dt``, ``P ← F P Fᵀ + Q``, ``F = [[1, −dt], [0, 1]]``."""
        p_vb, p_bb = self.p_vb[s], self.p_bb[s]
        self.speed[s] += (accel - self.bias[s] + coupling) * dt
        self.var[s] += -2.0 * dt * p_vb + dt * dt * p_bb + (self.speed_walk * dt) ** 2
        self.p_vb[s] = p_vb - dt * p_bb
        self.p_bb[s] = p_bb + self.bias_walk**2 * dt

    def update(self, s: IntArray, z: FloatArray, var: FloatArray | float) -> None:
        """Readings ``z`` ``(len(s),)`` of the speeds with variance ``var``."""
        v_var, p_vb = self.var[s], self.p_vb[s]
        total = v_var + var
        k_v, k_b = v_var / total, p_vb / total
        innovation = z - self.speed[s]
        self.speed[s] += k_v * innovation
        self.bias[s] += k_b * innovation
        self.p_bb[s] -= k_b * p_vb
        self.p_vb[s] = p_vb - k_v * p_vb
        self.var[s] = v_var - k_v * v_var


class _TiltFits(_Arrays):
    """:class:`~.frontend._TiltGradient` for every slot (one of pitch or roll)."""

    def __init__(self, prior_weight: float, highpass_s: float) -> None:
        self.prior_weight, self.highpass_s = prior_weight, highpass_s
        self.s0 = np.zeros(0)
        self.sxy = np.zeros(0)
        self.sxx = np.zeros(0)
        self.mean_x = np.zeros(0)
        self.mean_angle = np.zeros(0)
        self.last_ns = np.zeros(0, dtype=np.int64)

    def reset(self, slot: int, gradient_rad_per_g: float) -> None:
        s0 = gradient_rad_per_g / (1.0 + gradient_rad_per_g)
        self.s0[slot], self.sxy[slot], self.sxx[slot] = (
            s0,
            self.prior_weight * s0,
            self.prior_weight,
        )
        self.mean_x[slot] = self.mean_angle[slot] = math.nan
        self.last_ns[slot] = 0

    def slope(self, s: IntArray) -> FloatArray:
        """The fitted slope, held within a quarter and four times the prior (0.1 at least)."""
        s0 = self.s0[s]
        return np.clip(self.sxy[s] / self.sxx[s], 0.25 * s0, np.maximum(4.0 * s0, 0.1))

    def fix(
        self, s: IntArray, angle_rad: FloatArray, reading_g: FloatArray, t_ns: IntArray
    ) -> None:
        """Receiver angles with the lagged readings (in g) at their times."""
        ok = np.isfinite(angle_rad) & np.isfinite(reading_g)
        first = ok & np.isnan(self.mean_x[s])
        f = s[first]
        self.mean_x[f], self.mean_angle[f], self.last_ns[f] = (
            reading_g[first],
            angle_rad[first],
            t_ns[first],
        )
        more = ok & ~first
        m, x, y, t = s[more], reading_g[more], angle_rad[more], t_ns[more]
        age_s = np.maximum(t - self.last_ns[m], 0) * 1e-9
        gain = 1.0 - np.exp(-age_s / self.highpass_s)
        self.last_ns[m] = t
        self.mean_x[m] += gain * (x - self.mean_x[m])
        self.mean_angle[m] += gain * (y - self.mean_angle[m])
        dx, dy = x - self.mean_x[m], y - self.mean_angle[m]
        self.sxy[m] += dx * dy
        self.sxx[m] += dx * dx


class _Vehicles(_Arrays):
    """Each slot's constants from its config: geometry, loads, tyre, lags as gains."""

    def __init__(self) -> None:
        self.wheel_x = np.zeros((0, 4))
        self.wheel_y = np.zeros((0, 4))
        self.fz_static = np.zeros((0, 4))
        self.free = np.zeros((0, 4), dtype=bool)  # undriven wheels
        self.n_free = np.zeros(0)
        self.drive_share = np.zeros((0, 4))
        self.mass = np.zeros(0)
        self.m_h = np.zeros(0)  # mass × CG height
        self.wheelbase = np.zeros(0)
        self.share = np.zeros(0)  # lateral transfer's front share
        self.tracks = np.zeros((0, 2))  # front, rear
        self.load_gain = np.zeros(0)  # 1 − exp(−dt/lag) of the load transfer
        self.tilt_gain = np.zeros(0)  # the same for the tilting body (never lag-free)
        self.steering_ratio = np.zeros(0)
        self.drag_area = np.zeros(0)
        self.rolling = np.zeros(0)
        self.relax = np.zeros(0)
        self.r_u = np.zeros(0)
        self.kz = np.zeros(0)
        self.c_px = np.zeros(0)
        self.antenna_arm = np.zeros((0, 3))  # ahead, left of the CG, up from the tilt axis [m]

    def set(
        self, slot: int, config: Wheeled4wdSteeredConfig, fe: FrontEndConfig, dt: float
    ) -> None:
        ch, ty = config.chassis, config.tyre
        lf, lr = ch.cg_to_front_axle_m, ch.cg_to_rear_axle_m
        wheelbase = lf + lr
        self.wheel_x[slot] = [lf, lf, -lr, -lr]
        self.wheel_y[slot] = (
            np.array([ch.front_track_m, -ch.front_track_m, ch.rear_track_m, -ch.rear_track_m]) / 2
        )
        mg = ch.mass_kg * GRAVITY_MPS2
        self.fz_static[slot] = mg * np.array([lr, lr, lf, lf]) / (2 * wheelbase)
        self.free[slot] = UNDRIVEN[ch.driven_axle]
        self.n_free[slot] = float(self.free[slot].sum())
        self.drive_share[slot] = DRIVE_SHARE[ch.driven_axle]
        self.mass[slot] = ch.mass_kg
        self.m_h[slot] = ch.mass_kg * ch.cg_height_m
        self.wheelbase[slot] = wheelbase
        self.share[slot] = lr / wheelbase if fe.paper else ch.roll_stiffness_front_share
        self.tracks[slot] = ch.front_track_m, ch.rear_track_m
        lag = 0.0 if fe.paper else ch.load_transfer_lag_s
        self.load_gain[slot] = 1.0 - math.exp(-dt / max(lag, 1e-9))
        self.tilt_gain[slot] = 1.0 - math.exp(-dt / max(ch.load_transfer_lag_s, 1e-9))
        self.steering_ratio[slot] = ch.steering_ratio
        self.drag_area[slot] = ch.drag_area_m2
        self.rolling[slot] = ch.rolling_resistance
        self.relax[slot] = max(ty.relaxation_length_m, 1e-3)
        self.r_u[slot] = ty.unloaded_radius_m
        self.kz[slot] = ty.kz_npm
        self.c_px[slot] = ty.c_px_npm2
        self.antenna_arm[slot] = antenna_arm_m(ch)


class _State(_Arrays):
    """Each slot's learnt radii and tyres, lags and the previous yaw rate."""

    def __init__(self) -> None:
        self.radius = np.zeros((0, 4))
        self.radius_std = np.zeros((0, 4))
        self.radius_common_rel = np.zeros(0)
        self.radius_scale_var = np.zeros(0)  # the radii's shared relative scale variance
        self.speed_persist = np.zeros(0)  # the speed's considered persistent 1-σ [m/s]
        self.radius_drop = np.zeros(0)
        self.calib_n = np.zeros(0, dtype=np.int64)
        self.kz_wheel = np.zeros((0, 4))
        self.suspect = np.zeros((0, 4), dtype=bool)
        self.fz_cal = np.zeros((0, 4))
        self.transfer = np.zeros((0, 3))  # lagged [long, lat front, lat rear] [N]
        self.tilt_reading = np.zeros((0, 2))  # lagged raw [a_x, a_y] [m/s²]
        self.yaw_prev = np.zeros(0)
        self.accel_prev = np.zeros((0, 2))  # the last tick's [a_x, a_y] [m/s²]
        self.slip_lag = np.zeros((0, 2, 4))
        self.kappa_prev = np.zeros((0, 4))  # the last tick's kinematic κ
        self.kappa_ring = np.zeros((0, 4))  # the relaxed κ's 1-σ from a ringing wheel

    def reset(self, slot: int, car: _Vehicles, fe: FrontEndConfig) -> None:
        fz = car.fz_static[slot]
        self.radius[slot] = car.r_u[slot] - fz / car.kz[slot] * (1.0 if fe.paper else 1 / 3)
        self.radius_std[slot] = 0.01 * car.r_u[slot]
        self.radius_common_rel[slot] = 0.0
        self.radius_scale_var[slot] = 0.01**2
        self.speed_persist[slot] = 0.0
        self.radius_drop[slot] = fe.radius_drop0
        self.calib_n[slot] = 0
        self.kz_wheel[slot] = car.kz[slot]
        self.suspect[slot] = False
        self.fz_cal[slot] = fz
        self.transfer[slot] = 0.0
        self.tilt_reading[slot] = 0.0
        self.yaw_prev[slot] = math.nan
        self.accel_prev[slot] = math.nan
        self.slip_lag[slot] = 0.0
        self.kappa_prev[slot] = math.nan
        self.kappa_ring[slot] = 0.0


class FleetFrontEnd:
    """Every vehicle's front-end state by slot, stepped a round at a time (:meth:`step`)."""

    def __init__(self, fe: FrontEndConfig, tick_s: float) -> None:
        self.fe, self.dt = fe, tick_s
        walk, bias_walk = fe.speed_walk_mps2, fe.bias_walk_mps2_per_sqrt_s
        self.vx = _AxisFilters(walk, bias_walk)
        self.vy = _AxisFilters(walk, bias_walk)
        self.yaw = _AxisFilters(fe.yaw_walk_radps, fe.gyro_bias_walk_radps_per_sqrt_s)
        self.roll_gyro = _AxisFilters(fe.yaw_walk_radps, fe.gyro_bias_walk_radps_per_sqrt_s)
        self.pitch_gyro = _AxisFilters(fe.yaw_walk_radps, fe.gyro_bias_walk_radps_per_sqrt_s)
        self.pitch = _TiltFits(fe.tilt_prior_weight, fe.tilt_highpass_s)
        self.roll = _TiltFits(fe.tilt_prior_weight, fe.tilt_highpass_s)
        self.car = _Vehicles()
        self.state = _State()
        self._parts: tuple[_Arrays, ...] = (
            self.vx,
            self.vy,
            self.yaw,
            self.roll_gyro,
            self.pitch_gyro,
            self.pitch,
            self.roll,
            self.car,
            self.state,
        )
        self.capacity = 0

    def add(self, slot: int, config: Wheeled4wdSteeredConfig) -> None:
        """Start slot ``slot``'s front end afresh for a vehicle of ``config``."""
        if slot >= self.capacity:
            self.capacity = max(2 * self.capacity, slot + 1, 16)
            for part in self._parts:
                part._grow(self.capacity)
        ch = config.chassis
        self.car.set(slot, config, self.fe, self.dt)
        self.state.reset(slot, self.car, self.fe)
        self.vx.reset(slot, math.nan, 0.1)
        self.vy.reset(slot, 0.0, 0.1)
        self.yaw.reset(slot, math.nan, 0.005)
        self.roll_gyro.reset(slot, math.nan, 0.005)
        self.pitch_gyro.reset(slot, math.nan, 0.005)
        self.pitch.reset(slot, math.radians(ch.pitch_gradient_deg_per_g))
        self.roll.reset(slot, math.radians(ch.roll_gradient_deg_per_g))

    def calibrated(self, s: IntArray) -> BoolArray:
        return self.state.calib_n[s] >= self.fe.calib_samples

    def radius_drop(self, slot: int) -> float:
        """Slot ``slot``'s learnt ``ρ`` (the radius's fall per unit of deflection)."""
        return float(self.state.radius_drop[slot])

    def kz_wheel(self, slot: int) -> FloatArray:
        """Slot ``slot``'s per-wheel vertical stiffness (config's, or learnt if suspect)."""
        return self.state.kz_wheel[slot].copy()

    def step(self, s: IntArray, sensed: SensedTicks) -> FrontEndTicks:
        """One tick of the slots ``s`` ``(B,)`` (distinct) from their sensed rows ``(B, …)``."""
        paper, dt = self.fe.paper, self.dt
        ax_raw, ay_raw = sensed.accel_mps2[:, 1], -sensed.accel_mps2[:, 0]
        g = np.flatnonzero(np.isfinite(sensed.gnss_vel_mps[:, 0]))  # a fresh GNSS velocity
        yaw_rate = self._yaw_step(s, sensed.gyro_radps[:, 2], g, sensed)
        rates = self._tilt_rate_step(s, sensed.gyro_radps, yaw_rate, g, sensed)
        ax_tilt, ay_tilt = self._tilt_step(s, ax_raw, ay_raw, g, sensed)
        gnss_v = sensed.gnss_vel_mps
        if not paper:  # the CG's, moved from the antenna (FrontEnd._gnss_at_cg)
            reading = self.state.tilt_reading[s] / GRAVITY_MPS2
            roll, pitch = self.roll.slope(s) * reading[:, 1], self.pitch.slope(s) * reading[:, 0]
            arm = tilted_arm_m(self.car.antenna_arm[s], roll, pitch)
            gnss_v = antenna_velocity_at_cg(gnss_v, rates, arm)
        ax, ay = ax_tilt - self.vx.bias[s], ay_tilt - self.vy.bias[s]
        fz = self._loads(s, ax, ay)
        steering, delta = self._steer_angles(s, sensed.steer_rad)
        if not paper:
            self._calibrate(s, g, gnss_v, fz, delta, yaw_rate, (ax, ay), sensed.omega_radps)
        self._speed_step(s, ax_tilt, yaw_rate, g, gnss_v, fz, delta, sensed)
        self._side_slip_step(s, ay_tilt, yaw_rate, g, gnss_v)
        st = self.state
        prev = st.yaw_prev[s]
        yaw_accel = np.where(np.isnan(prev), 0.0, (yaw_rate - prev) / dt)
        st.yaw_prev[s] = yaw_rate
        slips = self._slips(s, fz, delta, yaw_rate, sensed.omega_radps)
        vx, vx_var = self.vx.speed[s], self.vx.var[s]
        ax_now, ay_now = self._at_tick(s, ax, ay, sensed.imu_lag_s)
        z = np.stack([ax_now + self._resistance(s, vx, fz), ay_now, yaw_accel], axis=1)
        valid = (vx >= self.fe.min_speed_mps) & ~np.isnan(yaw_rate) & steering
        if not paper:
            valid &= self.calibrated(s)
        return FrontEndTicks(
            fz_n=fz,
            kz_npm=st.kz_wheel[s],
            delta_rad=delta,
            kappa_common_std=np.sqrt(np.maximum(vx_var, 0.0)) / np.maximum(np.abs(vx), 1.0),
            z=z,
            vx_mps=vx,
            vx_std_mps=np.hypot(np.sqrt(np.maximum(vx_var, 0.0)), st.speed_persist[s]),
            vy_mps=self.vy.speed[s],
            yaw_rate_radps=yaw_rate,
            roll_pitch_rate_radps=rates[:, :2],
            vy_gnss_mps=gnss_v[:, 1],
            gnss=np.isfinite(gnss_v[:, 0]),
            steering=steering,
            valid=valid,
            tyre_suspect=np.any(st.suspect[s], axis=1),
            **slips,
        )

    # --- stages ---------------------------------------------------------------------------
    def _steer_angles(self, s: IntArray, steer_rad: FloatArray) -> tuple[BoolArray, FloatArray]:
        """Which rows have a steering-wheel angle ``(B,)`` (none yet, or stale: NaN from the
        sensors), and the wheels' steer angles ``(B, 4)``, the front pair's NaN without one
        (``FrontEnd._steer_angles``)."""
        delta = np.zeros((s.size, 4))
        delta[:, :2] = (steer_rad / self.car.steering_ratio[s])[:, None]
        return np.isfinite(steer_rad), delta

    def _yaw_step(
        self, s: IntArray, gyro_z: FloatArray, g: IntArray, sensed: SensedTicks
    ) -> FloatArray:
        """Yaw rate less the gyro's bias, the yaw angle predicted and, at a fresh receiver
        heading, corrected (``FrontEnd._yaw_step``, ``_heading_update``; paper: as read)."""
        if self.fe.paper:
            return gyro_z
        yaw = self.yaw
        yaw.speed[s] = np.where(np.isnan(yaw.speed[s]), 0.0, yaw.speed[s])
        yaw.predict(s, gyro_z, np.zeros(s.size), self.dt)
        rate = gyro_z - yaw.bias[s]
        if g.size:
            h_var = self.fe.heading_std_rad**2
            sg = s[g]
            angle = math.pi / 2 - sensed.gnss_attitude[g, 0]
            first = yaw.var[sg] > 0.5
            yaw.speed[sg[first]], yaw.var[sg[first]] = angle[first], h_var
            rest = sg[~first]
            wrapped = (angle[~first] - yaw.speed[rest] + math.pi) % (2 * math.pi) - math.pi
            yaw.update(rest, yaw.speed[rest] + wrapped, h_var)
        return rate

    def _tilt_rate_step(
        self, s: IntArray, gyro: FloatArray, yaw_rate: FloatArray, g: IntArray, sensed: SensedTicks
    ) -> FloatArray:
        """The body's rates ``(B, 3)``: the roll and pitch gyros less their biases, their angles
        predicted and, at a fresh receiver roll and pitch, corrected
        (``FrontEnd._tilt_rate_step``, ``_attitude_update``; paper: as read)."""
        if self.fe.paper:
            return body_rates_radps(gyro, yaw_rate)
        read = []
        for f, rate, col in ((self.roll_gyro, gyro[:, 1], 2), (self.pitch_gyro, gyro[:, 0], 1)):
            f.speed[s] = np.where(np.isnan(f.speed[s]), 0.0, f.speed[s])
            f.predict(s, rate, np.zeros(s.size), self.dt)
            read.append(rate - f.bias[s])
            if g.size:
                angle = sensed.gnss_attitude[g, col]
                ok = np.isfinite(angle)
                sg, angle = s[g][ok], angle[ok]
                first = f.var[sg] > 0.5
                var = self.fe.attitude_std_rad**2
                f.speed[sg[first]], f.var[sg[first]] = angle[first], var
                f.update(sg[~first], angle[~first], var)
        return body_rates_radps(np.stack([read[1], read[0], np.zeros(s.size)], axis=1), yaw_rate)

    def _at_tick(
        self, s: IntArray, ax: FloatArray, ay: FloatArray, lag_s: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """The accelerations carried to the tick (``FrontEnd._at_tick``)."""
        st = self.state
        prev = st.accel_prev[s]
        st.accel_prev[s] = np.stack([ax, ay], axis=1)
        if self.fe.paper:
            return ax, ay
        step = np.where(np.isnan(prev[:, 0]), 0.0, lag_s / self.dt)
        ax_prev, ay_prev = np.where(np.isnan(prev), 0.0, prev).T
        return ax + (ax - ax_prev) * step, ay + (ay - ay_prev) * step

    def _tilt_step(
        self, s: IntArray, ax_raw: FloatArray, ay_raw: FloatArray, g: IntArray, sensed: SensedTicks
    ) -> tuple[FloatArray, FloatArray]:
        """Lag the raw readings, fit the gradients at fresh epochs, and the accelerations
        without the body's tilt ``a_m − s ā_m`` (``FrontEnd._learn_tilt``, ``_detilt``)."""
        if self.fe.paper:
            return ax_raw, ay_raw
        st = self.state
        raw = np.stack([ax_raw, ay_raw], axis=1)
        reading = st.tilt_reading[s]
        reading += (raw - reading) * self.car.tilt_gain[s][:, None]
        st.tilt_reading[s] = reading
        if g.size:
            stamp = sensed.gnss_stamp_ns[g]
            att = sensed.gnss_attitude[g]
            self.pitch.fix(s[g], att[:, 1], reading[g, 0] / GRAVITY_MPS2, stamp)
            self.roll.fix(s[g], att[:, 2], reading[g, 1] / GRAVITY_MPS2, stamp)
        ax = ax_raw - self.pitch.slope(s) * reading[:, 0]
        return ax, ay_raw - self.roll.slope(s) * reading[:, 1]

    def _loads(self, s: IntArray, ax: FloatArray, ay: FloatArray) -> FloatArray:
        """Static loads plus the lagged transfer ``(B, 4)`` (``FrontEnd._loads``)."""
        car, st = self.car, self.state
        m_h, share, tracks = car.m_h[s], car.share[s], car.tracks[s]
        target = np.stack(
            [
                m_h * ax / car.wheelbase[s],
                share * m_h * ay / tracks[:, 0],
                (1 - share) * m_h * ay / tracks[:, 1],
            ],
            axis=1,
        )
        transfer = st.transfer[s]
        transfer += (target - transfer) * car.load_gain[s][:, None]
        st.transfer[s] = transfer
        lx, lf, lr = transfer.T
        moved = np.stack([-lx / 2 - lf, -lx / 2 + lf, lx / 2 - lr, lx / 2 + lr], axis=1)
        return np.maximum(car.fz_static[s] + moved, 0.0)

    def _wheel_velocity(
        self, s: IntArray, vx: FloatArray, vy: FloatArray, yaw_rate: FloatArray, delta: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """Each wheel centre's velocity along and across its heading ``(B, 4)`` each."""
        u = vx[:, None] - self.car.wheel_y[s] * yaw_rate[:, None]
        w = vy[:, None] + self.car.wheel_x[s] * yaw_rate[:, None]
        cos, sin = np.cos(delta), np.sin(delta)
        return u * cos + w * sin, -u * sin + w * cos

    def _radius_now(self, s: IntArray, fz: FloatArray) -> FloatArray:
        """Effective radius per wheel (``FrontEnd._radius_now``)."""
        st = self.state
        if self.fe.paper:
            return st.radius[s]
        return st.radius[s] - st.radius_drop[s][:, None] * (fz - st.fz_cal[s]) / st.kz_wheel[s]

    def _calibrate(
        self,
        s: IntArray,
        g: IntArray,
        gnss_v: FloatArray,
        fz: FloatArray,
        delta: FloatArray,
        yaw_rate: FloatArray,
        accel: tuple[FloatArray, FloatArray],
        omega: FloatArray,
    ) -> None:
        """Radius calibration on the rows with a fresh epoch, straight and steady at 5 m/s or
        more, without a steering angle at the front pair's free-rolling one while ``|a_y|`` is
        small too (``FrontEnd._calibrate``), then ``ρ`` and the tyres learnt."""
        ax, ay = accel
        unknown = np.isnan(delta[g, 0]) & (np.abs(ay[g]) >= 0.3)
        delta = self._calibration_steer(s, g, gnss_v, delta, yaw_rate)
        steady = (np.abs(ax[g]) < 0.3) & (np.abs(yaw_rate[g]) < 0.02) & (np.abs(delta[g, 0]) < 0.01)
        rows = g[steady & ~unknown & (gnss_v[g, 0] >= 5.0)]
        if not rows.size:
            return
        c, car, st = s[rows], self.car, self.state
        v = gnss_v[rows]
        v_long, _ = self._wheel_velocity(c, v[:, 0], v[:, 1], yaw_rate[rows], delta[rows])
        f = fz[rows]
        resist = car.rolling[c] * f.sum(axis=1) + 0.5 * AIR_DENSITY_KGPM3 * (
            car.drag_area[c] * v[:, 0] ** 2
        )
        c_x = load_adaptive_stiffness_n(
            f, st.kz_wheel[c], car.r_u[c][:, None], car.c_px[c][:, None]
        )
        expect = resist[:, None] * car.drive_share[c] / np.maximum(c_x, 1.0)
        measured = v_long * (1.0 + expect) / np.maximum(omega[rows], 1e-3)
        st.calib_n[c] += 1
        n = st.calib_n[c]
        gain = np.maximum(0.1 / self.fe.calib_time_s, 1.0 / n)[:, None]
        radius = st.radius[c]
        radius += gain * (measured - radius)
        st.radius[c] = radius
        st.fz_cal[c] += gain * (f - st.fz_cal[c])
        st.radius_common_rel[c] = 0.003 / np.sqrt(n)
        st.radius_scale_var[c] = calibration_scale_var(st.radius_scale_var[c], gain[:, 0], v[:, 0])
        st.radius_std[c] = 2e-4 * radius
        self._learn_tyres(c[n >= self.fe.calib_samples])

    def _calibration_steer(
        self, s: IntArray, g: IntArray, gnss_v: FloatArray, delta: FloatArray, r: FloatArray
    ) -> FloatArray:
        """``delta`` ``(B, 4)`` with the rows ``g`` (a fresh epoch) that have no steering angle
        at :func:`~.frontend.free_rolling_steer`'s, along the front wheels' travel."""
        rows = g[np.isnan(delta[g, 0])]
        if not rows.size:
            return delta
        v = gnss_v[rows]
        u, w = self._wheel_velocity(s[rows], v[:, 0], v[:, 1], r[rows], np.zeros((rows.size, 4)))
        out = delta.copy()
        out[rows] = free_rolling_steer(u, w)
        return out

    def _learn_tyres(self, c: IntArray) -> None:
        """``ρ`` and each wheel's ``kz`` from the calibrated radii (``FrontEnd._learn_tyres``)."""
        if not c.size:
            return
        car, st, fe = self.car, self.state, self.fe
        kz = car.kz[c][:, None]
        fz_n = np.maximum(st.fz_cal[c], 1.0)
        sink_m = car.r_u[c][:, None] - st.radius[c]
        implied = sink_m * kz / fz_n
        lo, hi = fe.radius_drop_range
        drop = np.clip(np.median(implied, axis=1), lo, hi)
        st.radius_drop[c] = drop
        suspect = np.abs(implied / drop[:, None] - 1.0) > fe.kz_tolerance
        st.suspect[c] = suspect
        own = drop[:, None] * fz_n / np.maximum(sink_m, 1e-4)
        st.kz_wheel[c] = np.where(suspect, np.clip(own, 0.05 * kz, 20.0 * kz), kz)

    def _speed_step(
        self,
        s: IntArray,
        ax_tilt: FloatArray,
        yaw_rate: FloatArray,
        g: IntArray,
        gnss_v: FloatArray,
        fz: FloatArray,
        delta: FloatArray,
        sensed: SensedTicks,
    ) -> None:
        """Forward speed: started at the first tick, predicted, corrected by GNSS and, on
        the calibrated vehicles with undriven wheels, by their rims while their steer angles are
        known (``FrontEnd._speed_step``)."""
        vx, st = self.vx, self.state
        omega = sensed.omega_radps
        unset = np.isnan(vx.speed[s])
        if unset.any():
            rim = (omega[unset] * st.radius[s[unset]]).mean(axis=1)
            vx.speed[s[unset]] = np.where(np.isfinite(gnss_v[unset, 0]), gnss_v[unset, 0], rim)
        vx.predict(s, ax_tilt, yaw_rate * self.vy.speed[s], self.dt)
        if g.size:
            sg, r_gnss = s[g], GNSS_SPEED_STD_MPS**2
            gain = vx.var[sg] / (vx.var[sg] + r_gnss)
            st.speed_persist[sg] = consider_step(st.speed_persist[sg], gain, 0.0)
            vx.update(sg, gnss_v[g, 0], r_gnss)
        if self.fe.paper:
            return
        use = (self.car.n_free[s] > 0) & (self.calibrated(s) | ~sensed.gnss_recent)
        use &= ~(self.car.free[s] & np.isnan(delta)).any(axis=1)
        rows = np.flatnonzero(use)
        if rows.size:
            ax = ax_tilt[rows] - self.vx.bias[s[rows]]
            self._rim_update(s[rows], omega[rows], fz[rows], delta[rows], (yaw_rate[rows], ax))

    def _rim_update(
        self,
        c: IntArray,
        omega: FloatArray,
        fz: FloatArray,
        delta: FloatArray,
        rates: tuple[FloatArray, FloatArray],
    ) -> None:
        """The undriven wheels' mean rim speed, less their spin-up slip, as a reading of
        ``v_x`` (``rates``: yaw rate and the bias-free ``a_x``; ``FrontEnd._speed_step``)."""
        car, st, fe = self.car, self.state, self.fe
        r, ax = rates
        radius = self._radius_now(c, fz)
        c_x = load_adaptive_stiffness_n(
            fz, st.kz_wheel[c], car.r_u[c][:, None], car.c_px[c][:, None]
        )
        spin = spin_up_slip(ax[:, None], radius, c_x, fe.wheel_inertia_kgm2)
        brake = -(ax + self._resistance(c, self.vx.speed[c], fz))
        braked = fe.brake_share_std * brake_slip_std(brake[:, None], car.mass[c][:, None], c_x)
        rim = omega * radius / (1.0 + spin)
        w = self.vy.speed[c][:, None] + car.wheel_x[c] * r[:, None]
        vx_rim = (rim - w * np.sin(delta)) / np.cos(delta) + car.wheel_y[c] * r[:, None]
        free, n_free = car.free[c], car.n_free[c]
        v = np.where(free, vx_rim, 0.0).sum(axis=1) / n_free
        own = np.where(free, st.radius_std[c] / st.radius[c], 0.0).sum(axis=1) / n_free
        spin_mean = np.where(free, spin, 0.0).sum(axis=1) / n_free
        rel = np.hypot(np.hypot(own, st.radius_common_rel[c]), fe.wheel_inertia_rel_std * spin_mean)
        braked_mean = np.where(free, braked, 0.0).sum(axis=1) / n_free
        ok = braked_mean <= np.hypot(rel, 5e-4)  # a brake slip is a bias, not noise
        var = ((rel * v) ** 2 + (5e-4 * v) ** 2)[ok]
        persist = self._rim_persistent(c, delta, rates, spin_mean, v)
        co = c[ok]
        k = self.vx.var[co] / (self.vx.var[co] + var)
        st.speed_persist[co] = consider_step(st.speed_persist[co], k, persist[ok])
        self.vx.update(co, v[ok], var)

    def _rim_persistent(
        self,
        c: IntArray,
        delta: FloatArray,
        rates: tuple[FloatArray, FloatArray],
        spin: FloatArray,
        v: FloatArray,
    ) -> FloatArray:
        """1-σ of the rim reading's persistent error ``(len(c),)`` [m/s]
        (:func:`~.frontend.rim_persistent_std_mps`): the window's lag of ``v̇ = a_x + r v_y``,
        the radii's shared scale, the lateral speed's 1-σ through the steered rims and the
        spin-up slip ``spin`` (the rims' mean) of a wheel inertia known to
        ``wheel_inertia_rel_std``: each is held while the acceleration, the steering or the
        radii are."""
        car, fe = self.car, self.fe
        r, ax = rates
        v_dot = ax + r * self.vy.speed[c]
        free, n_free = car.free[c], car.n_free[c]
        tan = np.where(free, np.abs(np.tan(delta)), 0.0).sum(axis=1) / n_free
        cross = np.hypot(tan * np.sqrt(self.vy.var[c]), fe.wheel_inertia_rel_std * spin * v)
        scale = np.sqrt(self.state.radius_scale_var[c])
        return rim_persistent_std_mps(v_dot, v, scale, cross, fe.wheel_speed_window_s)

    def _side_slip_step(
        self, s: IntArray, ay: FloatArray, yaw_rate: FloatArray, g: IntArray, gnss_v: FloatArray
    ) -> None:
        """Lateral speed (``FrontEnd._side_slip_step``)."""
        vy, dt = self.vy, self.dt
        if self.fe.paper:
            speed = vy.speed[s] + (ay - yaw_rate * self.vx.speed[s]) * dt
            vy.speed[s] = speed * math.exp(-dt / self.fe.side_slip_leak_s)
            return
        vy.predict(s, ay, -yaw_rate * self.vx.speed[s], dt)
        if g.size:
            vy.update(s[g], gnss_v[g, 1], 0.04**2)

    def _slips(
        self,
        s: IntArray,
        fz: FloatArray,
        delta: FloatArray,
        yaw_rate: FloatArray,
        omega: FloatArray,
    ) -> dict[str, FloatArray]:
        """κ, α, their 1-σ and α's lag per wheel ``(B, 4)``, NaN where ``δ`` is
        (``FrontEnd._slips``)."""
        st, vx, vy = self.state, self.vx.speed[s], self.vy
        v_long, v_lat = self._wheel_velocity(s, vx, vy.speed[s], yaw_rate, delta)
        speed = np.abs(v_long)
        denom = np.maximum(speed, 1.0)
        radius = self._radius_now(s, fz)
        kappa = (omega * radius - v_long) / denom
        alpha = -np.arctan2(v_lat, np.maximum(speed, 0.5))
        k_std = omega * st.radius_std[s] / denom + 2e-4
        a_std = np.sqrt(np.maximum(vy.var[s], 0.0))[:, None] / denom + 1e-3
        if self.fe.paper:
            lag = np.zeros_like(alpha)
        else:
            rate = (speed + 1.0) / self.car.relax[s][:, None]
            gain = 1.0 - np.exp(-self.dt * rate)
            kinematic = np.stack([kappa, alpha], axis=1)
            slip_lag = st.slip_lag[s]
            slip_lag = np.where(np.isnan(slip_lag), kinematic, slip_lag)
            slip_lag += gain[:, None] * (kinematic - slip_lag)
            st.slip_lag[s] = slip_lag
            rounding = self.fe.wheel_speed_resolution_radps * radius / denom
            ring = np.nan_to_num(st.kappa_ring[s], nan=0.0)
            ring = ringing_slip_std(kappa, st.kappa_prev[s], ring, gain, rounding)
            st.kappa_ring[s] = ring
            st.kappa_prev[s] = kappa
            k_std = k_std + 0.5 * np.abs(kappa - slip_lag[:, 0]) + ring
            a_std = a_std + 0.5 * np.abs(alpha - slip_lag[:, 1])
            lag = slip_lag[:, 1] - alpha
            kappa, alpha = slip_lag[:, 0], slip_lag[:, 1]
        return {
            "kappa": kappa,
            "alpha_rad": alpha,
            "kappa_std": k_std,
            "alpha_std_rad": a_std,
            "alpha_lag_rad": lag,
        }

    def _resistance(self, s: IntArray, vx: FloatArray, fz: FloatArray) -> FloatArray:
        """Drag and rolling resistance over the mass [m/s²] (0 in the paper reading)."""
        if self.fe.paper:
            return np.zeros(s.size)
        car = self.car
        drag = 0.5 * AIR_DENSITY_KGPM3 * car.drag_area[s] * vx * np.abs(vx)
        rolling = car.rolling[s] * fz.sum(axis=1) * np.tanh(vx)
        return (drag + rolling) / car.mass[s]
