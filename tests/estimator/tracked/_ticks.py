"""Hand-built inputs of one tracked tick, for the tests of the tick's equations."""

from __future__ import annotations

from typing import Any

import numpy as np

from estimator.sim.tracked import TrackedRun
from estimator.tracked import TrackedEstimatorConfig, TrackedFleet
from estimator.tracked.vehicle import TickInputs


def quiet_tick(n: int, tick_ns: int, **fields: Any) -> TickInputs:
    """One tick of ``n`` vehicles with the IMU alone: nothing moves or turns, ten IMU
    samples, no odometer, sprockets or GNSS (NaN or missing); ``fields`` replace any of it.

    Every array has the vehicle axis first (shape ``(n,)``, pairs ``(n, 2)``).
    """
    zero = np.zeros(n)
    nan = np.full(n, np.nan)
    base: dict[str, Any] = {
        "ticks_ns": np.full(n, tick_ns),
        "accel_mps2": zero,
        "gyro_radps": zero,
        "pitch_rate_radps": zero,
        "roll_rate_radps": zero,
        "lateral_accel_mps2": nan,  # no roll measurement
        "imu_samples": np.full(n, 10),
        "imu_age_s": np.full(n, 0.05),  # centred on the tick's middle: the state at the tick
        "yaw_accel_radps2": zero,
        "odometer_mps": nan,
        "odometer_lag_s": zero,
        "sprocket_pair_mps": np.full((n, 2), np.nan),
        "sprocket_missing": np.ones(n, dtype=bool),
        "sprocket_settling_pair": np.zeros((n, 2), dtype=bool),
        "sprocket_starting_pair": np.zeros((n, 2), dtype=bool),
        "gear_ratio": nan,
        "sprocket_before_pair_mps": np.full((n, 2), np.nan),
        "gear_ratio_before": nan,
        "gearbox_accel_mps2": zero,
        "steady_s": zero,
        "odometer_edges": np.zeros(n, dtype=np.int64),
        "odometer_gap_s": zero,
        "gnss_pos_pair_m": np.full((n, 2), np.nan),
        "gnss_vel_pair_mps": np.full((n, 2), np.nan),
        "gnss_vel_std_mps": nan,
        "gnss_age_s": zero,
        "gnss_vel_up_mps": nan,
    }
    return TickInputs(**{**base, **fields})


def run_to_first_outage(run: TrackedRun) -> tuple[TrackedFleet, list[tuple[str, np.ndarray]]]:
    """A default-configured :class:`~estimator.tracked.TrackedFleet` fed a simulated run
    (``simulate_tracked``) up to its first GNSS outage; returns the fleet (vehicle ``"v"``)
    and the rows it gave, as ``advance`` returns them."""
    fleet = TrackedFleet(TrackedEstimatorConfig())
    fleet.add_vehicle("v", run.config)
    loss_ns = run.outages_ns[0][0]
    for key_ns, m in run.measurements:
        if key_ns > loss_ns:
            break
        fleet.push("v", m)
    return fleet, fleet.advance({"v": loss_ns})


def rows_over(run: TrackedRun, cfg: TrackedEstimatorConfig, seconds: float) -> np.ndarray:
    """The rows a :class:`~estimator.tracked.TrackedFleet` of ``cfg`` gives for the first
    ``seconds`` of a simulated run (vehicle ``"v"``), advanced every second of sensor time."""
    fleet = TrackedFleet(cfg)
    fleet.add_vehicle("v", run.config)
    ms, i, t, parts = run.measurements, 0, run.start_ns, []
    while t < run.start_ns + seconds * 1_000_000_000:
        t += 1_000_000_000
        while i < len(ms) and ms[i][0] <= t:
            fleet.push("v", ms[i][1])
            i += 1
        parts += [rows for _, rows in fleet.advance({"v": t})]
    return np.concatenate(parts)
