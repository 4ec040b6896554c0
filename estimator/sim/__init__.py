"""Simulated rear-wheel-driven tractor: ground truth and raw sensor streams for named scenarios.

Pure: numpy only, every random draw from the seeded generator handed in, no I/O, no clock.

>>> run = simulate("figure_eight", seed=1, start_ns=1_700_000_000_000_000_000)
>>> run.measurements[0]            # GnssSample / ImuBatch / WheelEdges, in sensor order
>>> run.truth["slip_left_pct"]     # 100 Hz truth table (TRUTH_DTYPE)

How it works: the scenario (:mod:`estimator.sim.scenarios`) prescribes speed, yaw rate,
terrain and a traction model; :mod:`estimator.sim.kinematics` integrates the rigid-body truth on
a fine grid (500 Hz) and inverts eq. (8)(9) for the wheel speeds; :mod:`estimator.sim.sensors`
samples GNSS (10 Hz, 5 Hz in the paper scenarios), IMU (100 Hz, batches of 10) and encoder
edges (per wheel, 100 ms packets) with their imperfections.

Cost (one core, measured on the development machine): about 0.05-0.1 s per simulated minute,
dominated by the truth grid and the per-epoch ``GnssSample`` objects. A 5-minute ``field_work``
run takes ≈ 0.25 s and holds ≈ 12 k measurement objects (≈ 30 k encoder edges, a few MB); a
10-minute run ≈ 0.5 s. A fleet publisher can pre-generate a few minutes for a handful of vehicles
in about a second; give each vehicle its own ``seed`` (and, if wanted, ``heading0_deg``, origin
or ``config``). Memory peaks at ≈ 0.25 MB per simulated second while the fine grid is alive
(≈ 150 MB for a 10-minute run); the finished run keeps ≈ 40 kB per second (≈ 24 MB for 10 min).

Estimators should be configured with the sensors' noise figures:
``dataclasses.replace(run.config, noise=run.sensor_noise)``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from estimator.base import Measurement
from estimator.config import NoiseConfig, WheeledRearDriveConfig
from estimator.geo import EnuFrame
from estimator.sim.kinematics import (
    GRAVITY_MPS2,
    FineTruth,
    MotionPlan,
    TractionModel,
    integrate_plan,
    rim_speed_from_slip,
    slip_from_speeds,
)
from estimator.sim.scenarios import SCENARIOS, Scenario, scenario_names
from estimator.sim.sensors import (
    NO_EDGES,
    Emission,
    SensorSpec,
    antenna_point_m,
    gnss_emissions,
    imu_emissions,
    imu_point_m,
    wheel_emissions,
    wheel_heartbeats,
)
from estimator.sim.stream import (
    completion_ns,
    first_ns,
    in_arrival_order,
    replay,
    replay_arrivals,
)

__all__ = [
    "GRAVITY_MPS2",
    "SCENARIOS",
    "TRUTH_DTYPE",
    "TRUTH_FIELDS",
    "FineTruth",
    "MotionPlan",
    "Scenario",
    "SensorSpec",
    "SimRun",
    "TractionModel",
    "completion_ns",
    "first_ns",
    "in_arrival_order",
    "replay",
    "replay_arrivals",
    "rim_speed_from_slip",
    "scenario_names",
    "simulate",
    "slip_from_speeds",
    "truth_at",
]

#: Fields of the truth table, units in the names; slip in percent like ``ESTIMATE_DTYPE``.
TRUTH_FIELDS: tuple[tuple[str, str], ...] = (
    ("stamp_ns", "i8"),
    ("v0_mps", "f8"),  # forward speed of O (rear-axle midpoint's ground projection)
    ("v1_mps", "f8"),  # forward speed of the IMU point, eq. (2)
    ("vg_mps", "f8"),  # forward speed of the antenna point, eq. (1)
    ("vl_mps", "f8"),  # left wheel contact-point forward speed, eq. (4)
    ("vr_mps", "f8"),  # right, eq. (5)
    ("rim_left_mps", "f8"),  # r·W with the true radius
    ("rim_right_mps", "f8"),
    ("omega_left_radps", "f8"),
    ("omega_right_radps", "f8"),
    ("slip_left_pct", "f8"),  # eq. (8)(9); NaN when the wheel stands
    ("slip_right_pct", "f8"),
    ("a0_mps2", "f8"),  # dV0/dt
    ("a1_mps2", "f8"),  # forward inertial acceleration of the IMU point (no gravity)
    ("pitch_rate_radps", "f8"),  # ωx
    ("roll_rate_radps", "f8"),  # ωy
    ("yaw_rate_radps", "f8"),  # ωz, CCW +
    ("east_m", "f8"),  # antenna position, local ENU of the run's origin
    ("north_m", "f8"),
    ("up_m", "f8"),
    ("heading_rad", "f8"),  # from north, clockwise, in [0, 2π)
    ("pitch_rad", "f8"),
    ("roll_rad", "f8"),
    ("dist_m", "f8"),  # distance travelled by O
    ("mu_max", "f8"),  # ground's peak traction coefficient under the vehicle
    ("gnss_valid", "?"),  # a GNSS velocity is available at this time (not in an outage)
)

TRUTH_DTYPE = np.dtype(list(TRUTH_FIELDS))

_COMMON_KEYS = ("origin_lat_deg", "origin_lon_deg", "origin_height_m")
_ORIGIN_DEFAULT = (52.0, 5.6, 10.0)


@dataclass(frozen=True, slots=True)
class SimRun:
    """One simulated run.

    Attributes
    ----------
    name : str
        Scenario name.
    params : Mapping[str, Any]
        Scenario parameters actually used (defaults merged with overrides).
    sensors : SensorSpec
        Sensor settings actually used.
    config : WheeledRearDriveConfig
        The vehicle configuration the run was simulated for (as given).
    sensor_noise : NoiseConfig
        Noise figures of the simulated sensors, for tuning an estimator to this run
        (``dataclasses.replace(run.config, noise=run.sensor_noise)``).
    start_ns, end_ns : int
        Stamp of the first grid instant and of the last.
    measurements : list
        ``GnssSample | ImuBatch | WheelEdges`` in sensor order (see :mod:`estimator.sim.stream`).
    arrival_ns : ndarray, shape (len(measurements),), int64
        When each measurement reaches the server (latency included).
    until_ns : ndarray, shape (len(measurements),), int64
        Sensor time the stream is complete up to once each measurement is sent (the wire
        protocol's ``until_ns``: the end of a batch window, the next GNSS epoch − 1 ns).
    heartbeat_ns : ndarray, shape (k, 2), int64
        ``(arrival_ns, until_ns)`` of each wheel window without an edge on either wheel (see
        :func:`estimator.sim.sensors.wheel_heartbeats`); not measurements, only sent.
    truth : ndarray of TRUTH_DTYPE
        Truth at ``sensors.truth_rate_hz``.
    frame : EnuFrame
        Local frame of the run (``east_m``... of the truth are in it).
    """

    name: str
    params: Mapping[str, Any]
    sensors: SensorSpec
    config: WheeledRearDriveConfig
    sensor_noise: NoiseConfig
    start_ns: int
    end_ns: int
    measurements: list[Measurement]
    arrival_ns: npt.NDArray[np.int64]
    until_ns: npt.NDArray[np.int64]
    heartbeat_ns: npt.NDArray[np.int64]
    truth: np.ndarray
    frame: EnuFrame

    def in_arrival_order(self) -> list[tuple[int, Measurement]]:
        """``(arrival_ns, measurement)`` pairs in the order a live link would deliver them."""
        return list(in_arrival_order(self.measurements, self.arrival_ns))

    def sent_in_arrival_order(self) -> list[tuple[int, Measurement, int]]:
        """``(arrival_ns, measurement, until_ns)`` in the order a live link would deliver them,
        wheel heartbeats included (as edges of no stamps: nothing on either wheel)."""
        sent = [
            (int(a), m, int(u))
            for a, m, u in zip(self.arrival_ns, self.measurements, self.until_ns, strict=True)
        ]
        sent += [(int(a), NO_EDGES, int(u)) for a, u in self.heartbeat_ns]
        order = np.argsort([a for a, _, _ in sent], kind="stable")
        return [sent[int(i)] for i in order]

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) * 1e-9


def truth_at(truth: np.ndarray, stamp_ns: npt.ArrayLike, field: str) -> npt.NDArray[np.float64]:
    """Linear interpolation of one truth ``field`` at ``stamp_ns`` (NaN outside the table).

    Headings are unwrapped before interpolating and wrapped back to ``[0, 2π)``.
    """
    ts = np.asarray(truth["stamp_ns"], dtype=np.int64)
    q = np.asarray(stamp_ns, dtype=np.int64)
    x = (ts - ts[0]).astype(np.float64)
    xq = (q - ts[0]).astype(np.float64)
    y = np.asarray(truth[field], dtype=np.float64)
    if field == "heading_rad":
        y = np.unwrap(y)
    out = np.interp(xq, x, y, left=np.nan, right=np.nan)
    if field == "heading_rad":
        out = np.mod(out, 2 * math.pi)
    return out


def _resolve(
    scenario: Scenario, overrides: Mapping[str, Any]
) -> tuple[dict[str, Any], dict[str, Any], dict[str, Any]]:
    params = dict(scenario.defaults)
    sensor_kw: dict[str, Any] = {}
    common: dict[str, Any] = dict(zip(_COMMON_KEYS, _ORIGIN_DEFAULT, strict=True))
    sensor_names = SensorSpec.field_names()
    unknown = []
    for key, value in overrides.items():
        if key in params:
            params[key] = value
        elif key in sensor_names:
            sensor_kw[key] = value
        elif key in common:
            common[key] = value
        else:
            unknown.append(key)
    if unknown:
        allowed = sorted({*params, *sensor_names, *common})
        raise TypeError(
            f"{scenario.name}: unknown parameter(s) {sorted(unknown)}; allowed: {allowed}"
        )
    sensors: dict[str, Any] = {}
    for key, value in scenario.sensor_defaults.items():
        sensors[key] = value(params) if callable(value) else value
    sensors.update(sensor_kw)
    return params, sensors, common


def _noise_figures(
    spec: SensorSpec, truth: FineTruth, config: WheeledRearDriveConfig
) -> NoiseConfig:
    """RMS noise figures of the simulated sensors over the run (relative parts included)."""
    speed = float(np.sqrt(np.mean(truth.v0_mps**2)))
    gnss = math.hypot(spec.gnss_vel_std_mps, spec.gnss_speed_noise_rel * speed / math.sqrt(3.0))
    accel_rms = float(np.sqrt(np.mean(truth.point_accel_body(imu_point_m(config))[:, 1] ** 2)))
    rate_rms = float(np.sqrt(np.mean(truth.omega_radps[:, 2] ** 2)))
    accel = math.hypot(spec.accel_std_mps2, spec.accel_noise_rel * accel_rms)
    gyro = math.hypot(spec.gyro_std_radps, spec.gyro_noise_rel * rate_rms)
    tiny = 1e-6
    return NoiseConfig(
        gnss_vel_std_mps=max(gnss, tiny),
        accel_std_mps2=max(accel, tiny),
        gyro_std_radps=max(gyro, tiny),
        accel_bias_walk_mps2=max(spec.accel_bias_walk_mps2, tiny),
        gnss_pos_std_m=max(spec.gnss_pos_std_m, tiny),
    )


def _truth_table(
    fine: FineTruth, spec: SensorSpec, config: WheeledRearDriveConfig, start_ns: int
) -> np.ndarray:
    step = round(spec.fine_rate_hz / spec.truth_rate_hz)
    idx = np.arange(0, fine.t_s.size, step)
    out = np.zeros(idx.size, dtype=TRUTH_DTYPE)
    out["stamp_ns"] = start_ns + np.round(fine.t_s[idx] * 1e9).astype(np.int64)
    p_imu, p_ant = imu_point_m(config), antenna_point_m(config)
    out["v0_mps"] = fine.v0_mps[idx]
    out["v1_mps"] = fine.point_velocity_body(p_imu)[idx, 1]
    out["vg_mps"] = fine.point_velocity_body(p_ant)[idx, 1]
    out["vl_mps"] = fine.ground_mps[idx, 0]
    out["vr_mps"] = fine.ground_mps[idx, 1]
    out["rim_left_mps"] = fine.rim_mps[idx, 0]
    out["rim_right_mps"] = fine.rim_mps[idx, 1]
    out["omega_left_radps"] = fine.wheel_radps[idx, 0]
    out["omega_right_radps"] = fine.wheel_radps[idx, 1]
    out["slip_left_pct"] = 100.0 * fine.slip[idx, 0]
    out["slip_right_pct"] = 100.0 * fine.slip[idx, 1]
    out["a0_mps2"] = fine.a0_mps2[idx]
    out["a1_mps2"] = fine.point_accel_body(p_imu)[idx, 1]
    out["pitch_rate_radps"] = fine.omega_radps[idx, 0]
    out["roll_rate_radps"] = fine.omega_radps[idx, 1]
    out["yaw_rate_radps"] = fine.omega_radps[idx, 2]
    ant = fine.pos_enu_m[idx] + fine.rot[idx] @ p_ant
    out["east_m"], out["north_m"], out["up_m"] = ant[:, 0], ant[:, 1], ant[:, 2]
    out["heading_rad"] = np.mod(fine.psi_rad[idx], 2 * math.pi)
    out["pitch_rad"] = fine.theta_rad[idx]
    out["roll_rad"] = fine.phi_rad[idx]
    out["dist_m"] = fine.dist_m[idx]
    out["mu_max"] = fine.mu_max[idx]
    t = fine.t_s[idx]
    valid = np.ones(idx.size, dtype=bool)
    for t0, t1 in spec.gnss_outages:
        valid &= ~((t >= t0) & (t < t1))
    out["gnss_valid"] = valid
    return out


def simulate(
    name: str,
    *,
    seed: int | np.random.Generator,
    start_ns: int,
    config: WheeledRearDriveConfig | None = None,
    **overrides: Any,
) -> SimRun:
    """Simulate scenario ``name``.

    Parameters
    ----------
    name : str
        A key of :data:`SCENARIOS`.
    seed : int or numpy.random.Generator
        Everything random (wobbles, slip texture, sensor noise, tooth pattern) comes from it; the
        same seed gives bit-identical output.
    start_ns : int
        Stamp of t = 0 (UTC ns).
    config : WheeledRearDriveConfig, optional
        Vehicle geometry and encoder (default ``WheeledRearDriveConfig()``).
    **overrides
        Scenario parameters (``SCENARIOS[name].defaults``), :class:`SensorSpec` fields, or the
        run's origin ``origin_lat_deg``, ``origin_lon_deg``, ``origin_height_m``.

    Raises
    ------
    KeyError
        Unknown scenario.
    TypeError
        Unknown override.
    ValueError
        Inconsistent settings (rates, a wheel rolling backwards).
    """
    scenario, cfg, params, spec, common = _setup(name, config, overrides)
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    r_plan, r_truth, r_gnss, r_imu, r_wheel = rng.spawn(5)
    fine = _fine_truth(scenario.build(params, r_plan), spec, cfg, r_truth)
    frame = _origin_frame(common)
    span = (start_ns, start_ns + round(fine.t_s[-1] * 1e9))
    emitted = _sensor_emissions(fine, spec, cfg, frame, span, (r_gnss, r_imu, r_wheel))
    return _sim_run(name, params, (spec, cfg), fine, frame, span, emitted)


def _setup(
    name: str, config: WheeledRearDriveConfig | None, overrides: Mapping[str, Any]
) -> tuple[Scenario, WheeledRearDriveConfig, dict[str, Any], SensorSpec, dict[str, Any]]:
    """:func:`simulate`'s scenario, vehicle, parameters, sensors and origin settings."""
    if name not in SCENARIOS:
        raise KeyError(f"unknown scenario {name!r}; known: {scenario_names()}")
    scenario = SCENARIOS[name]
    cfg = config if config is not None else WheeledRearDriveConfig()
    params, sensor_kw, common = _resolve(scenario, overrides)
    return scenario, cfg, params, SensorSpec(**sensor_kw), common


def _origin_frame(common: Mapping[str, Any]) -> EnuFrame:
    """The run's ENU frame at its origin (``origin_lat_deg``, ``origin_lon_deg``,
    ``origin_height_m``)."""
    return EnuFrame(
        float(common["origin_lat_deg"]),
        float(common["origin_lon_deg"]),
        float(common["origin_height_m"]),
    )


def _sim_run(
    name: str,
    params: Mapping[str, Any],
    sensors: tuple[SensorSpec, WheeledRearDriveConfig],
    fine: FineTruth,
    frame: EnuFrame,
    span: tuple[int, int],
    emitted: tuple[list[Emission], npt.NDArray[np.int64]],
) -> SimRun:
    """The :class:`SimRun` of the emitted packets (and heartbeats ``(k, 2)``) over ``span``
    (start, end ns), its truth table from the fine grid ``fine``."""
    spec, cfg = sensors
    start_ns, end_ns = span
    emissions, heartbeats = emitted
    truth = _truth_table(fine, spec, cfg, start_ns)
    return SimRun(
        name=name,
        params=dict(params),
        sensors=spec,
        config=cfg,
        sensor_noise=_noise_figures(spec, fine, cfg),
        start_ns=start_ns,
        end_ns=end_ns,
        measurements=[e.measurement for e in emissions],
        arrival_ns=np.array([e.arrival_ns for e in emissions], dtype=np.int64),
        until_ns=np.array([e.until_ns for e in emissions], dtype=np.int64),
        heartbeat_ns=heartbeats,
        truth=truth,
        frame=frame,
    )


def _fine_truth(
    plan: MotionPlan, spec: SensorSpec, cfg: WheeledRearDriveConfig, rng: np.random.Generator
) -> FineTruth:
    """The plan integrated on the fine grid, with the wheels' radii as the spec mis-states them."""
    g = cfg.geometry
    radii = (
        g.wheel_radius_left_m * (1.0 + spec.wheel_radius_error_rel[0]),
        g.wheel_radius_right_m * (1.0 + spec.wheel_radius_error_rel[1]),
    )
    return integrate_plan(
        plan,
        fine_rate_hz=spec.fine_rate_hz,
        track_width_m=g.track_width_m,
        wheel_radius_m=radii,
        rng=rng,
    )


def _sensor_emissions(
    fine: FineTruth,
    spec: SensorSpec,
    cfg: WheeledRearDriveConfig,
    frame: EnuFrame,
    span_ns: tuple[int, int],
    rngs: tuple[np.random.Generator, np.random.Generator, np.random.Generator],
) -> tuple[list[Emission], npt.NDArray[np.int64]]:
    """GNSS, IMU and wheel emissions in sending order, and the wheels' heartbeats."""
    start_ns, end_ns = span_ns
    r_gnss, r_imu, r_wheel = rngs
    emissions: list[Emission] = []
    emissions += gnss_emissions(fine, spec, cfg, frame, start_ns, r_gnss)
    emissions += imu_emissions(fine, spec, cfg, start_ns, r_imu)
    wheels = wheel_emissions(fine, spec, cfg, start_ns, r_wheel)
    heartbeats = wheel_heartbeats(wheels, spec, start_ns, end_ns)
    emissions += wheels
    emissions.sort(key=lambda e: (e.key_ns, e.rank))
    return emissions, heartbeats
