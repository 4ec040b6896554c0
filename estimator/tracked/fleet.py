"""The tracked estimator as the server drives it: :class:`TrackedFleet`, every vehicle's tick
stepped together (a ``FleetEstimator``), and :class:`TrackedEstimator`, one vehicle alone (the
per-vehicle reference the fleet equals to 1e-9).

Ticks every ``tick_s`` on the vehicle's IMU grid; a tick is due once the IMU covers it (the
server releases every stream in sensor order, so the edges and fixes up to it are in).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence

import numpy as np

from estimator._arrays import BoolArray, FloatArray, IntArray
from estimator.base import Pushed
from estimator.config import TrackedConfig, VehicleConfig, expect_kind
from estimator.geo import geodetic_from_enu
from estimator.tracked.clock_cal import clock_fields, reset_clock, restore_clock
from estimator.tracked.fleet_inputs import take_fleet
from estimator.tracked.gyro_noise import arw_fields, initial_stats, stats_from_fields
from estimator.tracked.lag import BRAKED_BITS, HeldRows
from estimator.tracked.model import TrackedState as S
from estimator.tracked.params import VehicleParams
from estimator.tracked.settings import TrackedEstimatorConfig
from estimator.tracked.step import Filter, TickOut, initial_filter, tick_step
from estimator.tracked.vehicle import TickInputs, VehicleInputs
from estimator.tracked_spec import TRACKED_SPEC, TrackedFlag
from estimator.types import GnssSample, ImuBatch, OdometerEdges, SprocketEdges

__all__ = ["TrackedEstimator", "TrackedFleet"]

_F = TrackedFlag
_GNSS_OK_S = 1.0
_STACKED_SETS = 8
"""Sets of vehicles whose stacked constants :class:`TrackedFleet` keeps."""


class _Slot:
    """One vehicle: its inputs, its filter (arrays of one) and its counters."""

    __slots__ = ("counts", "filter", "held", "inputs", "nis")

    def __init__(self, config: TrackedConfig, cfg: TrackedEstimatorConfig) -> None:
        self.inputs = VehicleInputs(config, cfg)
        self.filter = initial_filter(cfg)
        self.counts = {
            "ticks": 0,
            "gnss_fused": 0,
            "gnss_gated": 0,
            "odometer_fused": 0,
        }
        self.nis: list[float] = []
        self.held = HeldRows()

    def push(self, m: Pushed) -> None:
        if isinstance(m, ImuBatch):
            self.inputs.push_imu(m)
        elif isinstance(m, GnssSample):
            self.inputs.push_gnss(m)
        elif isinstance(m, OdometerEdges | SprocketEdges):
            self.inputs.push_edges(m)


def _select(inp: TickInputs, rows: IntArray) -> TickInputs:
    """The ``rows`` of ``inp``, in that order."""
    return TickInputs(**{f.name: getattr(inp, f.name)[rows] for f in dataclasses.fields(inp)})


def _params_of(p: VehicleParams, vehicles: IntArray) -> VehicleParams:
    """The constants of ``vehicles`` (indices into ``p``'s, in that order)."""
    if vehicles.size == p.gauge_m.size:
        return p
    return VehicleParams(**{f.name: getattr(p, f.name)[vehicles] for f in dataclasses.fields(p)})


def _stack_filters(filters: list[Filter]) -> Filter:
    return Filter(
        np.concatenate([f.x for f in filters]),
        np.concatenate([f.P for f in filters]),
        np.concatenate([f.started for f in filters]),
        np.concatenate([f.since_gnss_s for f in filters]),
        np.concatenate([f.gated_s for f in filters]),
        np.concatenate([f.since_gnss_m for f in filters]),
        np.concatenate([f.odometer_gain for f in filters]),
        np.concatenate([f.fix_learnt_cov for f in filters]),
        np.concatenate([f.gyro_standing for f in filters]),
        np.concatenate([f.accel_steady_s for f in filters]),
    )


def _flags(f: Filter, out: TickOut, conf_min: float, inp: TickInputs) -> IntArray:
    bits = np.zeros(f.x.shape[0], dtype=np.int64)
    ok = f.since_gnss_s <= _GNSS_OK_S
    for mask, flag in (
        (ok, _F.GNSS_OK),
        (f.started & ~ok, _F.DEAD_RECKONING),
        (out.confidence < conf_min, _F.STATE_UNCERTAIN),
        (out.standstill, _F.STANDSTILL),
        (out.slip_valid_pair[:, 0], _F.SLIP_LEFT_VALID),
        (out.slip_valid_pair[:, 1], _F.SLIP_RIGHT_VALID),
        (out.braked_pair[:, 0], _F.BRAKED_LEFT),
        (out.braked_pair[:, 1], _F.BRAKED_RIGHT),
        (out.odometer_used, _F.ODOMETER_USED),
        (out.gnss_gated, _F.GNSS_GATED),
        (inp.sprocket_missing, _F.SPROCKET_MISSING),
        (~f.started, _F.NOT_STARTED),
        (inp.sprocket_settling_pair.any(axis=1), _F.SLIP_SETTLING),
    ):
        bits |= np.where(mask, int(flag), 0)
    return bits


def _rows(f: Filter, out: TickOut, inp: TickInputs, cfg: TrackedEstimatorConfig) -> np.ndarray:
    """Rows of one tick for the ``k`` vehicles of ``f`` (``lat_deg``/``lon_deg`` left NaN)."""
    x, P = f.x, f.P
    rows = TRACKED_SPEC.empty_rows(x.shape[0])
    started = f.started
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = np.where(
            np.abs(out.yaw_rate_radps) > 1e-3, x[:, S.SPEED] / out.yaw_rate_radps, np.nan
        )
    cols: dict[str, object] = {
        "stamp_ns": inp.ticks_ns,
        "motion_state": out.state,
        "state_confidence": out.confidence,
        "speed_mps": x[:, S.SPEED],
        "speed_std_mps": np.sqrt(np.maximum(P[:, S.SPEED, S.SPEED], 0.0)),
        "lateral_mps": out.lateral_mps,
        "yaw_rate_radps": out.yaw_rate_radps,
        "turn_radius_m": rho,
        "track_left_mps": out.track_pair_mps[:, 0],
        "track_right_mps": out.track_pair_mps[:, 1],
        "track_std_mps": out.track_std_mps,
        "sprocket_left_mps": inp.sprocket_pair_mps[:, 0],
        "sprocket_right_mps": inp.sprocket_pair_mps[:, 1],
        "slip_left_pct": out.slip_pair_pct[:, 0],
        "slip_right_pct": out.slip_pair_pct[:, 1],
        "slip_left_std_pct": out.slip_std_pair_pct[:, 0],
        "slip_right_std_pct": out.slip_std_pair_pct[:, 1],
        "odometer_raw_mps": inp.odometer_mps,
        "odometer_mps": out.odometer_mps,
        "odometer_scale": x[:, S.F_STRAIGHT],
        "gyro_bias_radps": x[:, S.GYRO_BIAS],
        "east_m": np.where(started, x[:, S.EAST], np.nan),
        "north_m": np.where(started, x[:, S.NORTH], np.nan),
        "heading_rad": np.where(started, x[:, S.HEADING], np.nan),
        "east_std_m": np.where(started, np.sqrt(np.maximum(P[:, S.EAST, S.EAST], 0.0)), np.nan),
        "north_std_m": np.where(started, np.sqrt(np.maximum(P[:, S.NORTH, S.NORTH], 0.0)), np.nan),
        "east_north_cov_m2": np.where(started, P[:, S.EAST, S.NORTH], np.nan),
        "flags": _flags(f, out, cfg.uncertain_below, inp),
    }
    cols["gyro_arw_deg_rt_h"], cols["gyro_arw_std_deg_rt_h"] = arw_fields(f.gyro_standing, cfg)
    cols["gnss_clock_offset_s"], cols["gnss_clock_offset_std_s"] = clock_fields(f, cfg)
    for name, index in (("pitch", S.PITCH), ("roll", S.ROLL)):
        std = np.sqrt(np.maximum(P[:, index, index], 0.0))
        known = std <= cfg.tilt_reported_std_rad
        cols[f"{name}_rad"] = np.where(known, x[:, index], np.nan)
        cols[f"{name}_std_rad"] = np.where(known, std, np.nan)
    for name, value in cols.items():
        rows[name] = value
    return rows


def _geodetic(slots: Sequence[_Slot], sizes: Sequence[int], rows: np.ndarray) -> None:
    """Fill ``up_m``, ``lat_deg``, ``lon_deg`` of rows laid out vehicle after vehicle
    (``sizes[k]`` rows of ``slots[k]``), each from its vehicle's anchor, in one conversion;
    a vehicle without an anchor yet keeps its rows as they are."""
    frames = [s.inputs.frame for s in slots]
    has = np.repeat([f is not None for f in frames], sizes)
    if not has.any():
        return
    anchor = np.repeat(
        [(f.lat0_deg, f.lon0_deg, f.h0_m) if f is not None else (0.0, 0.0, 0.0) for f in frames],
        sizes,
        axis=0,
    )
    up = np.repeat([-s.inputs.config.geometry.antenna_lever_arm_m[2] for s in slots], sizes)
    known = has & np.isfinite(rows["east_m"])
    rows["up_m"] = np.where(has, np.where(known, up, np.nan), rows["up_m"])
    if known.any():
        a = anchor[known]
        lat, lon, _ = geodetic_from_enu(
            rows["east_m"][known], rows["north_m"][known], up[known], a[:, 0], a[:, 1], a[:, 2]
        )
        rows["lat_deg"][known] = lat
        rows["lon_deg"][known] = lon


def _may_be_due(inputs: VehicleInputs, until_ns: int) -> bool:
    """False when the vehicle's next tick is after ``until_ns`` (about half the fleet at every
    call): nothing is due and :meth:`VehicleInputs.due` need not build an empty array."""
    return inputs.next_ns is None or inputs.next_ns <= until_ns


def _count(slots: Sequence[_Slot], out: TickOut) -> None:
    """Each slot's counters and NIS after its tick (``slots[i]`` is row ``i`` of ``out``)."""
    columns = (out.gnss_used, out.gnss_gated, out.odometer_used, out.gnss_nis)
    for slot, gnss, gated, odometer, nis in zip(slots, *(c.tolist() for c in columns), strict=True):
        c = slot.counts
        c["ticks"] += 1
        c["gnss_fused"] += gnss
        c["gnss_gated"] += gated
        c["odometer_fused"] += odometer
        if gnss and math.isfinite(nis):
            slot.nis.append(nis)


class _Base:
    """What the fleet and the single-vehicle reference share: slots, pushing, anchors."""

    name = "tracked"
    spec = TRACKED_SPEC
    output_dtype = TRACKED_SPEC.dtype

    def __init__(self, config: TrackedEstimatorConfig | None = None) -> None:
        self.config = config or TrackedEstimatorConfig()
        self._slots: dict[str, _Slot] = {}

    @property
    def _conf_min(self) -> float:
        return self.config.uncertain_below

    @property
    def _reach(self) -> int:
        return self.config.release_reach_ticks

    def add_vehicle(self, vehicle_id: str, config: VehicleConfig) -> None:
        tracked = expect_kind(config, TrackedConfig, self.name)
        self._slots[vehicle_id] = _Slot(tracked, self.config)

    def remove_vehicle(self, vehicle_id: str) -> None:
        self._slots.pop(vehicle_id, None)

    def vehicle_ids(self) -> list[str]:
        return list(self._slots)

    def flush(self, vehicle_id: str) -> np.ndarray:
        """The vehicle's rows still held by the fixed lag (:mod:`estimator.tracked.lag`), given
        now as they stand (``HoldsRows``): the registry takes them before a new config starts
        the vehicle afresh. Empty for an unknown vehicle."""
        slot = self._slots.get(vehicle_id)
        return TRACKED_SPEC.empty_rows(0) if slot is None else slot.held.flush()

    def push(self, vehicle_id: str, measurement: Pushed) -> None:
        self._slots[vehicle_id].push(measurement)

    def align_ticks(self, vehicle_id: str, stamp_ns: int) -> None:
        inputs = self._slots[vehicle_id].inputs
        if inputs.next_ns is None:
            inputs.next_ns = int(stamp_ns)

    def anchor(self, vehicle_id: str) -> tuple[float, float, float] | None:
        """``(lat_deg, lon_deg, height_m)`` of the vehicle's ENU frame (its first fix's
        antenna), None before it."""
        frame = self._slots[vehicle_id].inputs.frame
        return None if frame is None else (frame.lat0_deg, frame.lon0_deg, frame.h0_m)

    def set_anchor(self, vehicle_id: str, lat_deg: float, lon_deg: float, height_m: float) -> None:
        """Give the vehicle's ENU frame this origin instead of its first fix."""
        from estimator.geo import EnuFrame

        if not all(np.isfinite([lat_deg, lon_deg, height_m])) or abs(lat_deg) > 90:
            raise ValueError("not a geodetic position")
        self._slots[vehicle_id].inputs.frame = EnuFrame(lat_deg, lon_deg, height_m)

    def counters(self, vehicle_id: str) -> dict[str, int]:
        """Ticks, fixes fused and gated, odometer updates, and the bad input counted
        and dropped (IMU samples, fixes, edges going backwards, ticks without a sprocket)."""
        slot = self._slots[vehicle_id]
        inputs = slot.inputs
        return {
            **slot.counts,
            **inputs.counts,
            "odometer_backwards": inputs.odometer.backwards,
            "sprocket_backwards": sum(b.backwards for b in inputs.sprockets),
        }

    def calibration_fields(self, vehicle_id: str) -> dict[str, float]:
        """The vehicle's calibration as its row fields (``TRACKED_SPEC.calibrations``): the
        gyro's noise measured standing (ARW and its 1-sigma, °/√h; NaN before a pair) and the
        receiver's clock (s, and its 1-sigma; NaN outside the product mode); ``KeyError`` if
        unknown."""
        f = self._slots[vehicle_id].filter
        arw, std = arw_fields(f.gyro_standing, self.config)
        clock, clock_std = clock_fields(f, self.config)
        return {
            "gyro_arw_deg_rt_h": float(arw[0]),
            "gyro_arw_std_deg_rt_h": float(std[0]),
            "gnss_clock_offset_s": float(clock[0]),
            "gnss_clock_offset_std_s": float(clock_std[0]),
        }

    def restore_calibration_fields(self, vehicle_id: str, values: Mapping[str, float]) -> None:
        """Go on from a calibration's row fields (:meth:`calibration_fields`, a stored row's),
        each calibration whose two fields ``values`` holds (the others start as they do):
        the gyro's measured pairs and their squared changes (``gyro_noise.stats_from_fields``),
        against the part the config names now, nothing where the config turns the measurement
        off; the receiver's clock as its state's prior mean and 1-sigma
        (:func:`~estimator.tracked.clock_cal.restore_clock`). ``KeyError`` if unknown."""
        slot = self._slots[vehicle_id]
        if {"gyro_arw_deg_rt_h", "gyro_arw_std_deg_rt_h"} <= values.keys():
            arw = np.array([values["gyro_arw_deg_rt_h"]])
            std = np.array([values["gyro_arw_std_deg_rt_h"]])
            if slot.inputs.config.calibration.gyro_noise:
                slot.filter.gyro_standing = stats_from_fields(arw, std, self.config)
        if {"gnss_clock_offset_s", "gnss_clock_offset_std_s"} <= values.keys():
            restore_clock(
                slot.filter,
                self.config,
                values["gnss_clock_offset_s"],
                values["gnss_clock_offset_std_s"],
            )

    def reset_calibration(self, vehicle_id: str) -> None:
        """Forget the vehicle's calibration: the gyro's noise the data sheet's again, measured
        anew, and the receiver's clock back to its prior, learnt anew; ``KeyError`` if
        unknown."""
        f = self._slots[vehicle_id].filter
        f.gyro_standing = initial_stats(1)
        reset_clock(f, self.config)

    def gnss_nis(self, vehicle_id: str) -> FloatArray:
        """NIS of every GNSS position fused so far (2 degrees of freedom; consistency checks)."""
        return np.asarray(self._slots[vehicle_id].nis, dtype=np.float64)

    def filter_state(self, vehicle_id: str) -> tuple[FloatArray, FloatArray]:
        """``(x (n,), P (n, n))`` of the vehicle's filter (diagnostics and tests)."""
        f = self._slots[vehicle_id].filter
        return f.x[0].copy(), f.P[0].copy()


class TrackedFleet(_Base):
    """Every vehicle's tracked estimator behind one batched step (a ``FleetEstimator``)."""

    def __init__(self, config: TrackedEstimatorConfig | None = None) -> None:
        super().__init__(config)
        self._stacked: dict[tuple[int, ...], tuple[list[VehicleParams], VehicleParams]] = {}

    def _params(self, work: list[tuple[str, _Slot, IntArray]]) -> VehicleParams:
        """The constants of the vehicles in ``work``, stacked once per set of vehicles (the
        same few sets come back call after call, each vehicle on its tick's phase). An entry
        holds its parts, so no other object can take their ids while it stands."""
        parts = [w[1].inputs.params for w in work]
        key = tuple(map(id, parts))
        hit = self._stacked.get(key)
        if hit is None:
            if len(self._stacked) >= _STACKED_SETS:
                self._stacked.clear()
            hit = self._stacked[key] = (parts, VehicleParams.stack(parts))
        return hit[1]

    def advance(self, until_ns: Mapping[str, int]) -> list[tuple[str, np.ndarray]]:
        """Emit every due tick ``<= until_ns[vehicle_id]``; the inputs of all are taken at
        once (:func:`take_fleet`) and the r-th due tick of every vehicle is stepped in one
        batched call."""
        work: list[tuple[str, _Slot, IntArray]] = []
        for vid, until in until_ns.items():
            slot = self._slots.get(vid)
            if slot is None or not _may_be_due(slot.inputs, until):
                continue
            ticks = slot.inputs.due(int(until))
            if ticks.size:
                work.append((vid, slot, ticks))
        if not work:
            return []
        inp, starts = take_fleet([w[1].inputs for w in work], [w[2] for w in work])
        params = self._params(work)
        sizes = np.diff(starts)
        out = TRACKED_SPEC.empty_rows(int(starts[-1]))
        onset = np.zeros(out.size, dtype=bool)
        for r in range(int(sizes.max())):
            part = np.flatnonzero(sizes > r)
            rows = starts[part] + r
            slots = [work[k][1] for k in part]
            out[rows], onset[rows] = self._round(
                slots, _select(inp, rows), _params_of(params, part)
            )
        _geodetic([slot for _, slot, _ in work], np.diff(starts).tolist(), out)
        result = []
        braked = np.add.reduceat((out["flags"] & BRAKED_BITS) != 0, starts[:-1]) > 0
        for (vid, slot, _), a, b, any_braked in zip(
            work, starts[:-1].tolist(), starts[1:].tolist(), braked.tolist(), strict=True
        ):
            given = slot.held.give(
                out[a:b], onset[a:b], self.config.lag_ticks, self._conf_min, self._reach, any_braked
            )
            if given.size:
                result.append((vid, given))
        return result

    def _round(
        self, slots: list[_Slot], inp: TickInputs, p: VehicleParams
    ) -> tuple[np.ndarray, BoolArray]:
        """One tick of each of ``slots`` (their filters stepped); its rows and onsets."""
        f = _stack_filters([s.filter for s in slots])
        got = tick_step(f, inp, p, self.config)
        rows = _rows(f, got, inp, self.config)
        for i, slot in enumerate(slots):
            slot.filter = Filter(
                f.x[i : i + 1],
                f.P[i : i + 1],
                f.started[i : i + 1],
                f.since_gnss_s[i : i + 1],
                f.gated_s[i : i + 1],
                f.since_gnss_m[i : i + 1],
                f.odometer_gain[i : i + 1],
                f.fix_learnt_cov[i : i + 1],
                f.gyro_standing[i : i + 1],
                f.accel_steady_s[i : i + 1],
            )
        _count(slots, got)
        return rows, got.onset


class TrackedEstimator(_Base):
    """The same estimator stepping each vehicle on its own, tick by tick (the reference)."""

    def advance(self, until_ns: Mapping[str, int]) -> list[tuple[str, np.ndarray]]:
        result = []
        for vid, until in until_ns.items():
            slot = self._slots.get(vid)
            if slot is None:
                continue
            ticks = slot.inputs.due(int(until))
            if not ticks.size:
                continue
            inputs = slot.inputs.take(ticks)
            rows = TRACKED_SPEC.empty_rows(ticks.size)
            onset = np.zeros(ticks.size, dtype=bool)
            for r in range(ticks.size):
                one = _select(inputs, np.array([r]))
                got = tick_step(slot.filter, one, slot.inputs.params, self.config)
                rows[r] = _rows(slot.filter, got, one, self.config)[0]
                onset[r] = got.onset[0]
                _count([slot], got)
            _geodetic([slot], [ticks.size], rows)
            given = slot.held.give(rows, onset, self.config.lag_ticks, self._conf_min, self._reach)
            if given.size:
                result.append((vid, given))
        return result
