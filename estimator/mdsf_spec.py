"""The MDSF estimator's spec (``method.md`` §2): rear-wheel slip of a wheeled rear-drive vehicle.

Rows are :data:`estimator.types.ESTIMATE_DTYPE`; flags :class:`estimator.types.EstimateFlag`.
This module only describes them for the rest of the product (units, labels, channels).
"""

from __future__ import annotations

import math

from estimator.spec import (
    CalibrationChannel,
    ChartSpec,
    CommandSpec,
    EstimatorSpec,
    FieldSpec,
    PositionChannel,
    SlipChannel,
    SpeedChannel,
    WheelPosition,
    flags_from,
    gnss_clock_channel,
)
from estimator.types import ESTIMATE_DTYPE, ESTIMATE_FIELDS, EstimateFlag

__all__ = ["MDSF_SPEC"]

# name -> (unit, label, description)
_FIELD_TEXT: dict[str, tuple[str, str, str]] = {
    "stamp_ns": ("ns", "time", "tick time, ns since the Unix epoch (UTC, vehicle clock)"),
    "vg_mps": ("m/s", "ground speed", "vehicle-direction speed at the antenna, eq. (1), filtered"),
    "v1_mps": ("m/s", "speed at IMU", "forward speed at the IMU, eq. (2)"),
    "v0_mps": ("m/s", "axle speed", "forward speed of the rear-axle midpoint, eq. (3)"),
    "vl_mps": ("m/s", "left ground", "left wheel ground speed, eq. (4)"),
    "vr_mps": ("m/s", "right ground", "right wheel ground speed, eq. (5)"),
    "rim_left_mps": ("m/s", "left rim", "left wheel rim speed r·W"),
    "rim_right_mps": ("m/s", "right rim", "right wheel rim speed r·W"),
    "omega_left_radps": ("rad/s", "left wheel rate", "left wheel angular speed W"),
    "omega_right_radps": ("rad/s", "right wheel rate", "right wheel angular speed W"),
    "slip_left_pct": ("%", "slip rear left", "left wheel slip, eq. (8)(9); NaN when not valid"),
    "slip_right_pct": ("%", "slip rear right", "right wheel slip, eq. (8)(9); NaN when not valid"),
    "vg_std_mps": ("m/s", "ground speed σ", "1-sigma of vg_mps"),
    "vl_std_mps": ("m/s", "left ground σ", "1-sigma of vl_mps"),
    "vr_std_mps": ("m/s", "right ground σ", "1-sigma of vr_mps"),
    "slip_left_std_pct": ("%", "slip left σ", "1-sigma of slip_left_pct"),
    "slip_right_std_pct": ("%", "slip right σ", "1-sigma of slip_right_pct"),
    "accel_mps2": ("m/s²", "acceleration", "forward acceleration a1 (gravity removed)"),
    "pitch_rate_radps": ("rad/s", "pitch rate", "body pitch rate ωx"),
    "yaw_rate_radps": ("rad/s", "yaw rate", "body yaw rate ωz, counter-clockwise positive"),
    "east_m": ("m", "east", "antenna east of the vehicle's anchor"),
    "north_m": ("m", "north", "antenna north of the vehicle's anchor"),
    "up_m": ("m", "up", "antenna height above the vehicle's anchor"),
    "heading_rad": ("rad", "heading", "heading from north, clockwise"),
    "pitch_rad": ("rad", "pitch", "pitch, nose up positive"),
    "roll_rad": ("rad", "roll", "roll, right side down positive"),
    "flags": ("", "flags", "EstimateFlag bits"),
    "gnss_clock_offset_s": (
        "s",
        "GNSS clock offset",
        "a GNSS sample stamped t describes the IMU clock's t − offset (online calibration)",
    ),
    "gnss_clock_offset_std_s": ("s", "GNSS clock offset σ", "1-sigma of gnss_clock_offset_s"),
    "wheel_clock_offset_s": (
        "s",
        "wheel clock offset",
        "a wheel sample stamped t describes the IMU clock's t − offset (online calibration)",
    ),
    "wheel_clock_offset_std_s": ("s", "wheel clock offset σ", "1-sigma of wheel_clock_offset_s"),
    "radius_left_m": ("m", "left rolling radius", "left wheel's rolling radius, calibrated"),
    "radius_left_std_m": ("m", "left rolling radius σ", "1-sigma of radius_left_m"),
    "radius_right_m": ("m", "right rolling radius", "right wheel's rolling radius, calibrated"),
    "radius_right_std_m": ("m", "right rolling radius σ", "1-sigma of radius_right_m"),
    "imu_pitch_mount_rad": (
        "rad",
        "IMU mounting pitch",
        "the IMU's forward axis pitched up against the body's (online calibration)",
    ),
    "imu_pitch_mount_std_rad": ("rad", "IMU mounting pitch σ", "1-sigma of imu_pitch_mount_rad"),
}


def _fields() -> tuple[FieldSpec, ...]:
    return tuple(FieldSpec(name, kind, *_FIELD_TEXT[name]) for name, kind in ESTIMATE_FIELDS)


_FLAG_TEXT: dict[str, str] = {
    "GNSS_OK": "a GNSS velocity was fused on this tick or recently enough to trust the speed",
    "DEGRADED": "GNSS lost: speed carried by IMU and wheel speed",
    "STANDSTILL": "below the standstill threshold: no slip value",
    "GATED": "a GNSS velocity was rejected by the innovation gate on this tick",
    "SLIP_LEFT_VALID": "the left wheel's slip is valid",
    "SLIP_RIGHT_VALID": "the right wheel's slip is valid",
    "WHEEL_PERIOD_METHOD": "wheel speed from the k-tooth period method (else frequency method)",
    "WHEEL_DIRECT": "wheel speed given directly (CAN), not from pulses",
    "RESET": "the filter was reset on this tick",
    "SETTLING": "starting or stopping too fast for the wheel-speed fit: no slip value",
    "WHEEL_GAP": "wheel data was lost: no wheel speed until the fits hold enough new edges",
    "DEAD_RECKONED": "no GNSS position: position and heading carried by speed and gyro",
    "UNCALIBRATED": "a calibration the slip depends on (clocks, radius, IMU mounting) has not "
    "converged yet",
}


_MS = 1e-3
_PCT = 1e-2
_DEG = math.pi / 180.0

_CALIBRATIONS = (
    gnss_clock_channel(enabled_config="calibration.clock_offsets"),
    CalibrationChannel(
        "wheel_clock_offset",
        "wheel clock offset",
        "wheel_clock_offset_s",
        "wheel_clock_offset_std_s",
        "calibration.clock_offset_converged_ms",
        _MS,
        enabled_config="calibration.clock_offsets",
    ),
    CalibrationChannel(
        "radius_left",
        "left rolling radius",
        "radius_left_m",
        "radius_left_std_m",
        "calibration.radius_converged_pct",
        _PCT,
        relative=True,
        enabled_config="calibration.wheel_radius",
    ),
    CalibrationChannel(
        "radius_right",
        "right rolling radius",
        "radius_right_m",
        "radius_right_std_m",
        "calibration.radius_converged_pct",
        _PCT,
        relative=True,
        enabled_config="calibration.wheel_radius",
    ),
    CalibrationChannel(
        "imu_pitch_mount",
        "IMU mounting pitch",
        "imu_pitch_mount_rad",
        "imu_pitch_mount_std_rad",
        "calibration.imu_pitch_converged_deg",
        _DEG,
        enabled_config="calibration.imu_mounting",
    ),
)
"""The online calibration (:mod:`estimator.mdsf.calibration`) as the rows carry it, each
converged below its ``CalibrationConfig`` threshold."""


MDSF_SPEC = EstimatorSpec(
    name="mdsf",
    title="MDSF wheel slip",
    description=(
        "Per-wheel ground speed and slip of the driven rear wheels from GNSS, IMU and wheel "
        "encoders (multi-source data structured fusion); slip S = (r·W − V) / max(r·W, V)."
    ),
    kinds=("wheeled_rear_drive",),
    inputs=("gnss", "imu", "wheels"),
    fields=_fields(),
    flags=flags_from(EstimateFlag, _FLAG_TEXT),
    slips=(
        SlipChannel(
            "left",
            "rear left wheel",
            "slip_left_pct",
            WheelPosition.REAR_LEFT,
            valid_flag="SLIP_LEFT_VALID",
            std_field="slip_left_std_pct",
        ),
        SlipChannel(
            "right",
            "rear right wheel",
            "slip_right_pct",
            WheelPosition.REAR_RIGHT,
            valid_flag="SLIP_RIGHT_VALID",
            std_field="slip_right_std_pct",
        ),
    ),
    speeds=(
        SpeedChannel("ground", "ground speed", "vg_mps", std_field="vg_std_mps"),
        SpeedChannel("left", "left wheel ground speed", "vl_mps", std_field="vl_std_mps"),
        SpeedChannel("right", "right wheel ground speed", "vr_mps", std_field="vr_std_mps"),
        SpeedChannel("rim_left", "left rim speed", "rim_left_mps"),
        SpeedChannel("rim_right", "right rim speed", "rim_right_mps"),
    ),
    motion="ground",
    position=PositionChannel(
        "east_m",
        "north_m",
        "up_m",
        "heading_rad",
        carried_flag="DEAD_RECKONED",
        pitch_field="pitch_rad",
        roll_field="roll_rad",
    ),
    charts=(
        ChartSpec("slip", "Wheel slip", "%", ("slip_left_pct", "slip_right_pct")),
        ChartSpec(
            "speed",
            "Speeds",
            "m/s",
            ("vg_mps", "vl_mps", "vr_mps", "rim_left_mps", "rim_right_mps"),
        ),
    ),
    ok_flag="GNSS_OK",
    degraded_flags=("DEGRADED",),
    commands=(
        CommandSpec(
            "calibration_drive",
            "calibration drive",
            "while on, the wheels are taken to roll without slip (drive on firm ground, nothing "
            "in tow, gently) and every wheel's rolling radius and clock are learnt",
        ),
    ),
    calibrations=_CALIBRATIONS,
    uncalibrated_flag="UNCALIBRATED",
    row_dtype=ESTIMATE_DTYPE,
)
