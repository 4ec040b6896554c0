"""The reference-speed estimator's spec (``method.md`` §3, source 001): a GNSS-free speed.

Speed and accelerometer bias from the IMU's forward acceleration and the driven wheels' rim
speed, without GNSS. Beside MDSF's GNSS-fused speed it shows a GNSS problem at a glance.
"""

from __future__ import annotations

from enum import IntFlag

from estimator.spec import ChartSpec, EstimatorSpec, FieldSpec, SpeedChannel, flags_from

__all__ = ["REFERENCE_SPEED_SPEC", "ReferenceFlag"]


class ReferenceFlag(IntFlag):
    """Bits of a reference-speed row's ``flags``."""

    NONE = 0
    WHEEL_OK = 1 << 0
    """The rim speed was fused on this tick."""
    NO_WHEEL = 1 << 1
    """No rim speed (no edges yet, or wheel data lost): the speed is the accelerometer's alone."""
    STANDSTILL = 1 << 2
    """Below the standstill threshold."""
    RESET = 1 << 3
    """The filter was (re)initialised on this tick."""


REFERENCE_SPEED_SPEC = EstimatorSpec(
    name="reference_speed",
    title="Reference speed (GNSS-free)",
    description=(
        "Forward speed and accelerometer bias from the IMU and the driven wheels' rim speed, "
        "without GNSS (Kalman filter of method.md §3)."
    ),
    kinds=("wheeled_rear_drive",),
    inputs=("imu", "wheels"),
    fields=(
        FieldSpec("stamp_ns", "i8", "ns", "time", "tick time, ns since the Unix epoch (UTC)"),
        FieldSpec("speed_mps", "f8", "m/s", "reference speed", "filtered forward speed"),
        FieldSpec("speed_std_mps", "f8", "m/s", "reference speed σ", "1-sigma of speed_mps"),
        FieldSpec("rim_mps", "f8", "m/s", "mean rim speed", "mean of the driven wheels' r·W"),
        FieldSpec(
            "accel_mps2",
            "f8",
            "m/s²",
            "acceleration",
            "forward specific force over the tick, bias not removed",
        ),
        FieldSpec(
            "accel_bias_mps2",
            "f8",
            "m/s²",
            "accelerometer bias",
            "estimated forward accelerometer bias (slope included)",
        ),
        FieldSpec("flags", "i4", "", "flags", "ReferenceFlag bits"),
    ),
    flags=flags_from(
        ReferenceFlag,
        {
            "WHEEL_OK": "the rim speed was fused on this tick",
            "NO_WHEEL": "no rim speed: the speed is the accelerometer's alone",
            "STANDSTILL": "below the standstill threshold",
            "RESET": "the filter was (re)initialised on this tick",
        },
    ),
    speeds=(
        SpeedChannel("reference", "reference speed", "speed_mps", std_field="speed_std_mps"),
        SpeedChannel("rim", "mean rim speed", "rim_mps"),
    ),
    motion="reference",
    charts=(
        ChartSpec("speed", "Reference speed", "m/s", ("speed_mps", "rim_mps")),
        ChartSpec("bias", "Accelerometer bias", "m/s²", ("accel_bias_mps2",)),
    ),
    ok_flag="WHEEL_OK",
    degraded_flags=("NO_WHEEL",),
)
