"""Per-vehicle constants as arrays ``(k,)``, so one batched call serves vehicles of different
geometry (gauge, contact length, the source's ratios and thresholds, lever arm, noises, the
gyro fitted). ``accel_std_mps2`` is the accelerometer's white noise per sample."""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from estimator._arrays import FloatArray
from estimator.config import TrackedConfig

__all__ = ["VehicleParams"]


@dataclass(frozen=True, slots=True)
class VehicleParams:
    """Each field shape ``(k,)`` (``antenna_xy_m``: ``(k, 2)``, x right, y forward;
    ``antenna_up_m`` its height over the hull centre's ground point;
    ``gyro_noise_measured`` 1 where the config measures the gyro's noise standing, else 0)."""

    gauge_m: FloatArray
    length_m: FloatArray
    lateral_resistance: FloatArray
    low_gear_ratio: FloatArray
    arc_ratio: FloatArray
    pivot_radius_m: FloatArray
    separated_radius_m: FloatArray
    straight_radius_m: FloatArray
    heading_jump_rad: FloatArray
    stop_speed_mps: FloatArray
    min_slip_speed_mps: FloatArray
    gnss_pos_std_m: FloatArray
    gnss_vel_std_mps: FloatArray
    accel_std_mps2: FloatArray
    sprocket_pitch_m: FloatArray
    odometer_pitch_m: FloatArray
    odometer_scale_std: FloatArray
    gyro_arw_rad_rt_s: FloatArray
    gyro_bias_walk_radps_rt_s: FloatArray
    gyro_noise_measured: FloatArray
    antenna_up_m: FloatArray
    antenna_xy_m: FloatArray

    @classmethod
    def of(cls, c: TrackedConfig) -> VehicleParams:
        """One vehicle's constants, each an array of one."""
        g, m, gyro = c.geometry, c.motion, c.gyro.resolved()
        values = {
            "gauge_m": g.track_gauge_m,
            "length_m": g.contact_length_m,
            "lateral_resistance": m.lateral_resistance,
            "low_gear_ratio": m.low_gear_ratio,
            "arc_ratio": m.arc_odometer_ratio,
            "pivot_radius_m": m.pivot_radius_per_half_gauge * 0.5 * g.track_gauge_m,
            "separated_radius_m": m.separated_radius_per_gauge * g.track_gauge_m,
            "straight_radius_m": m.straight_radius_m,
            "heading_jump_rad": m.heading_jump_rad,
            "stop_speed_mps": m.stop_speed_mps,
            "min_slip_speed_mps": c.slip.min_ground_speed_mps,
            "gnss_pos_std_m": c.noise.gnss_pos_std_m,
            "gnss_vel_std_mps": c.noise.gnss_vel_std_mps,
            "accel_std_mps2": c.noise.accel_std_mps2,
            "sprocket_pitch_m": 2.0 * np.pi * c.sprocket.pitch_radius_m / c.sprocket.teeth_per_rev,
            "odometer_pitch_m": c.odometer.distance_per_edge_m,
            "odometer_scale_std": c.odometer.scale_std_pct / 100.0,
            "gyro_arw_rad_rt_s": gyro.arw_rad_rt_s,
            "gyro_bias_walk_radps_rt_s": gyro.bias_walk_radps_rt_s,
            "gyro_noise_measured": 1.0 if c.calibration.gyro_noise else 0.0,
            "antenna_up_m": g.antenna_lever_arm_m[2],
        }
        arrays = {k: np.array([v], dtype=np.float64) for k, v in values.items()}
        return cls(**arrays, antenna_xy_m=np.array([g.antenna_lever_arm_m[:2]], dtype=np.float64))

    @classmethod
    def stack(cls, parts: list[VehicleParams]) -> VehicleParams:
        """The vehicles' constants side by side, in order."""
        if len(parts) == 1:
            return parts[0]
        return cls(
            **{f.name: np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(cls)}
        )
