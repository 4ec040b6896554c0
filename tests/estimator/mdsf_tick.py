"""One vehicle's MDSF tick inputs for engine-level tests."""

from __future__ import annotations

import numpy as np

from estimator.mdsf import TickInputs


def one_vehicle_inputs(**fields: np.ndarray) -> TickInputs:
    """One vehicle's tick inputs: zeros, GNSS and IMU fused with unit variances, no wheel or
    distance; ``fields`` replace any of them (arrays of the field's shape)."""
    base: dict[str, np.ndarray] = {
        "stamp_ns": np.array([0]),
        "z": np.zeros((1, 4)),
        "gnss_ok": np.array([True]),
        "gnss_var": np.ones(1),
        "imu_ok": np.array([True]),
        "accel_var": np.ones(1),
        "gyro_var": np.ones(1),
        "force_fwd": np.zeros(1),
        "omega": np.zeros((1, 2)),
        "omega_std": np.zeros((1, 2)),
        "wheel_flags": np.zeros(1, dtype=np.int32),
        "enu": np.zeros((1, 3)),
        "attitude": np.zeros((1, 3)),
        "dist_ok": np.zeros(1, bool),
        "dist_m": np.zeros(1),
        "dist_var": np.zeros(1),
        "dist_restart": np.zeros(1, bool),
        "fix_age_s": np.zeros(1),
    }
    return TickInputs(**{**base, **fields})
