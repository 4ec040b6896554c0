"""The reference-speed estimator on its own: a GNSS-free forward speed, batched over vehicles.

``method.md`` §3 (source 001): state ``[v, a0]`` driven by the forward accelerometer, corrected
by the driven wheels' mean rim speed ``r·W`` (:func:`estimator.reference_speed.reference_step`
with no GNSS reference). Without GNSS the ground/rim ratio cannot be learnt, so the rim speed
is taken as it is, with the filter's relative wheel error: a slipping wheel reads fast, and the
speed follows it within that error. The accelerometer's bias state also holds the slope's
``g·sin θ`` (no attitude without GNSS). Beside MDSF's GNSS-fused speed the difference shows a
GNSS or slip problem at a glance. Rows: :data:`REFERENCE_SPEED_SPEC`.

Ticks lie on ``origin + k·tick_s`` (``align_ticks``); a tick is computed once the IMU covers
it. Each advance steps the vehicles' r-th due ticks together (one numpy step per round).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from estimator._arrays import FloatArray, IntArray, due_ticks
from estimator.base import Pushed
from estimator.config import ConfigError, VehicleConfig, WheeledRearDriveConfig, expect_kind
from estimator.reference_speed import RefAux, ReferenceSpeedConfig, RefState, reference_step
from estimator.reference_speed_spec import REFERENCE_SPEED_SPEC, ReferenceFlag
from estimator.types import ImuBatch, WheelEdges, WheelGap, WheelSpeeds
from estimator.wheel_speed import DirectWheelSpeed, WheelSpeedConfig, WheelTracker

__all__ = ["ReferenceFleetConfig", "ReferenceSpeedFleet"]

_FORWARD = 1  # body Y: forward axis of accel_mps2


@dataclass(frozen=True, slots=True)
class ReferenceFleetConfig:
    """Settings of the standalone reference-speed estimator.

    Attributes
    ----------
    tick_s : float
        Output interval [s].
    standstill_mps : float
        Below this |rim speed| (and |speed|) a row is flagged STANDSTILL [m/s].
    initial_speed_std_mps, initial_bias_std_mps2 : float
        Prior 1-sigma of the state at the first tick.
    filter : ReferenceSpeedConfig
        The filter's noise settings.
    """

    tick_s: float = 0.1
    standstill_mps: float = 0.05
    initial_speed_std_mps: float = 1.0
    initial_bias_std_mps2: float = 0.1
    filter: ReferenceSpeedConfig = field(default_factory=ReferenceSpeedConfig)

    def __post_init__(self) -> None:
        if not 0.005 <= self.tick_s <= 1.0:
            raise ConfigError(f"tick_s must be within 0.005..1 s, got {self.tick_s!r}")
        for name in ("standstill_mps", "initial_speed_std_mps", "initial_bias_std_mps2"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"{name} must be a finite number > 0, got {value!r}")


class _Vehicle:
    """One vehicle's inputs and filter state."""

    def __init__(
        self, config: WheeledRearDriveConfig, wheel: WheelSpeedConfig, tick_ns: int
    ) -> None:
        wcfg = dataclasses.replace(wheel, teeth_per_rev=config.encoder.teeth_per_rev)
        self.wheel_cfg = wcfg
        self.radius_m = np.array(
            [config.geometry.wheel_radius_left_m, config.geometry.wheel_radius_right_m]
        )
        self.trackers = (WheelTracker(wcfg), WheelTracker(wcfg))
        self.direct = DirectWheelSpeed(std_radps=0.01)
        self.has_direction = config.encoder.has_direction
        self.imu_ns = np.zeros(0, dtype=np.int64)
        self.imu_fwd = np.zeros(0)
        self.tick_ns = tick_ns
        self.next_ns: int | None = None  # next tick; None before the grid is set
        self.wheel_hold_until_ns = -(2**63)  # ticks up to here get no rim speed (WheelGap)
        self.wheel_resume_ns = -(2**63)  # after lost wheel data: no rim speed before this
        self.wheel_need: list[int] = [0, 0]  # edges each wheel still needs after a loss
        self.x = np.zeros(2)
        self.P = np.eye(2)
        self.aux = np.array([0.0, 1.0, 0.0])
        self.started = False

    def push_imu(self, batch: ImuBatch) -> None:
        t = np.asarray(batch.stamp_ns, dtype=np.int64)
        a = np.asarray(batch.accel_mps2, dtype=np.float64).reshape(-1, 3)[:, _FORWARD]
        keep = np.isfinite(a)
        if self.imu_ns.size:
            keep &= t > self.imu_ns[-1]
        self.imu_ns = np.concatenate([self.imu_ns, t[keep]])
        self.imu_fwd = np.concatenate([self.imu_fwd, a[keep]])
        if self.next_ns is None and self.imu_ns.size:
            self.next_ns = int(self.imu_ns[0]) + self.tick_ns

    def push_wheels(self, m: WheelEdges | WheelSpeeds | WheelGap) -> None:
        if isinstance(m, WheelEdges):
            direction = m.direction if self.has_direction else None
            self.trackers[int(m.wheel)].push(m.stamp_ns, direction)
            need = self.wheel_need[int(m.wheel)]
            if need and m.stamp_ns.size:
                got = min(need, int(m.stamp_ns.size))
                self.wheel_need[int(m.wheel)] -= got
                self.wheel_resume_ns = max(self.wheel_resume_ns, int(m.stamp_ns[got - 1]))
        elif isinstance(m, WheelSpeeds):
            self.direct.push(m.stamp_ns, m.omega_radps)
        elif m.until_ns is not None:
            self.wheel_hold_until_ns = max(self.wheel_hold_until_ns, m.until_ns)
        else:  # wheel data lost: fits start afresh, no rim speed until each has min_edges
            self.trackers = (WheelTracker(self.wheel_cfg), WheelTracker(self.wheel_cfg))
            self.wheel_need = [self.wheel_cfg.min_edges] * 2
            self.wheel_resume_ns = m.after_ns

    def due(self, until_ns: int) -> IntArray:
        """Ticks ``<= until_ns`` the IMU already covers, oldest first."""
        return due_ticks(self.next_ns, self.imu_ns, self.tick_ns, until_ns)

    def inputs(self, ticks: IntArray) -> tuple[FloatArray, FloatArray]:
        """Mean forward specific force over each tick ``(t − tick, t]`` and the mean rim speed
        at each tick (NaN where unknown), shapes ``(m,)``; drops IMU samples no longer needed."""
        edges = np.searchsorted(
            self.imu_ns, np.concatenate([ticks[:1] - self.tick_ns, ticks]), side="right"
        )
        count = np.diff(edges)
        # each tick's own samples summed in order: the same sum however calls were batched
        tick_of = np.repeat(np.arange(ticks.size), count)
        sums = np.bincount(tick_of, self.imu_fwd[edges[0] : edges[-1]], minlength=ticks.size)
        with np.errstate(invalid="ignore", divide="ignore"):
            accel = np.where(count > 0, sums / count, np.nan)
        cut = int(edges[-1])
        self.imu_ns, self.imu_fwd = self.imu_ns[cut:], self.imu_fwd[cut:]
        if self.direct.has_data:
            omega, _ = self.direct.query(ticks)
        else:
            omega = np.stack([tr.query(ticks).omega_radps for tr in self.trackers], axis=1)
        rim = (omega * self.radius_m).mean(axis=1)
        rim[ticks <= self.wheel_hold_until_ns] = np.nan
        if any(self.wheel_need) and not self.direct.has_data:
            rim[:] = np.nan
        else:
            rim[ticks < self.wheel_resume_ns] = np.nan
        return accel, rim


class ReferenceSpeedFleet:
    """Many vehicles' reference-speed filters behind one batched step (a ``FleetEstimator``)."""

    name = "reference_speed"
    spec = REFERENCE_SPEED_SPEC
    output_dtype = REFERENCE_SPEED_SPEC.dtype

    def __init__(
        self, config: ReferenceFleetConfig | None = None, wheel: WheelSpeedConfig | None = None
    ) -> None:
        self.config = config or ReferenceFleetConfig()
        self.wheel = wheel or WheelSpeedConfig()
        self._tick_ns = round(self.config.tick_s * 1e9)
        self._vehicles: dict[str, _Vehicle] = {}

    def add_vehicle(self, vehicle_id: str, config: VehicleConfig) -> None:
        wheeled = expect_kind(config, WheeledRearDriveConfig, self.name)
        self._vehicles[vehicle_id] = _Vehicle(wheeled, self.wheel, self._tick_ns)

    def remove_vehicle(self, vehicle_id: str) -> None:
        self._vehicles.pop(vehicle_id, None)

    def vehicle_ids(self) -> list[str]:
        return list(self._vehicles)

    def push(self, vehicle_id: str, measurement: Pushed) -> None:
        v = self._vehicles[vehicle_id]
        if isinstance(measurement, ImuBatch):
            v.push_imu(measurement)
        elif isinstance(measurement, WheelEdges | WheelSpeeds | WheelGap):
            v.push_wheels(measurement)
        # GNSS is not an input of this estimator (its point is to go without it)

    def align_ticks(self, vehicle_id: str, stamp_ns: int) -> None:
        v = self._vehicles[vehicle_id]
        if v.next_ns is None:
            v.next_ns = int(stamp_ns)

    def advance(self, until_ns: Mapping[str, int]) -> list[tuple[str, np.ndarray]]:
        """Emit every tick with ``stamp_ns <= until_ns[vehicle_id]`` the IMU covers."""
        work = []
        for vid, until in until_ns.items():
            v = self._vehicles.get(vid)
            if v is None:
                continue
            ticks = v.due(int(until))
            if ticks.size:
                work.append((vid, v, ticks, *v.inputs(ticks)))
                v.next_ns = int(ticks[-1]) + v.tick_ns
        if not work:
            return []
        out = [REFERENCE_SPEED_SPEC.empty_rows(w[2].size) for w in work]
        for r in range(max(w[2].size for w in work)):
            self._round([(k, w) for k, w in enumerate(work) if w[2].size > r], r, out)
        return [(w[0], rows) for w, rows in zip(work, out, strict=True)]

    def _round(self, part: list, r: int, out: list[np.ndarray]) -> None:
        """Step the r-th due tick of every vehicle in ``part`` together."""
        vs = [w[1] for _, w in part]
        accel = np.array([w[3][r] for _, w in part])
        rim = np.array([w[4][r] for _, w in part])
        fresh = np.array([not v.started for v in vs])
        x = np.stack([v.x for v in vs])
        P = np.stack([v.P for v in vs])
        aux = np.stack([v.aux for v in vs])
        cfg = self.config
        if fresh.any():
            x[fresh, RefState.V] = np.where(np.isfinite(rim[fresh]), rim[fresh], 0.0)
            x[fresh, RefState.A0] = 0.0
            P[fresh] = np.diag([cfg.initial_speed_std_mps**2, cfg.initial_bias_std_mps2**2])
        aux[:, RefAux.LOST_S] = 0.0  # the rim speed is the reference itself, never "lost"
        aux[:, RefAux.WHEEL_RATIO] = 1.0
        nan = np.full(len(vs), np.nan)
        x, P, aux, used = reference_step(x, P, aux, accel, cfg.tick_s, nan, nan, rim, cfg.filter)
        flags = np.where(used, int(ReferenceFlag.WHEEL_OK), int(ReferenceFlag.NO_WHEEL))
        flags |= np.where(fresh, int(ReferenceFlag.RESET), 0)
        still = (np.abs(np.nan_to_num(rim, nan=np.inf)) < cfg.standstill_mps) & (
            np.abs(x[:, RefState.V]) < cfg.standstill_mps
        )
        flags |= np.where(still, int(ReferenceFlag.STANDSTILL), 0)
        for i, ((k, w), v) in enumerate(zip(part, vs, strict=True)):
            v.x, v.P, v.aux, v.started = x[i], P[i], aux[i], True
            row = out[k][r]
            row["stamp_ns"] = w[2][r]
            row["speed_mps"] = x[i, RefState.V]
            row["speed_std_mps"] = math.sqrt(max(P[i, RefState.V, RefState.V], 0.0))
            row["rim_mps"] = rim[i]
            row["accel_mps2"] = accel[i]
            row["accel_bias_mps2"] = x[i, RefState.A0]
            row["flags"] = flags[i]
