"""The MDSF fleet estimator the server drives (``name = "mdsf"``).

:class:`MdsfFleet` implements :class:`estimator.base.FleetEstimator`. Its front end
(:class:`~estimator.mdsf.frontend.FleetFrontEnd`) buffers every vehicle's measurements and, on
:meth:`MdsfFleet.advance`, turns those of all due vehicles into per-tick filter inputs; the
engine (:class:`~estimator.mdsf.engine.MdsfEngine`) steps them round by round (round ``r`` is
the ``r``-th due tick of every vehicle that has one, all in one batched call). Slip (eq. (8)(9)),
positions (dead-reckoned through GNSS outages) and attitude follow for all rows at once.

Ticks sit on a grid of ``tick_ns``: multiples of it since the epoch by default, or moved by
:meth:`MdsfFleet.align_ticks` (the server puts a vehicle's ticks on the end of its first IMU
batch, so a tick is computed as soon as the batch holding it arrives). A row at ``t`` uses only
measurements stamped at or before ``t``: rows depend neither on how data was batched nor on the
other vehicles of a call. A vehicle's first row is the first tick with a usable GNSS speed (or,
after ``gnss_timeout_s`` without GNSS, with wheel speeds, flagged DEGRADED). Bad input is
skipped and counted (:meth:`MdsfFleet.counters`), never raised on. A wheel's slip has a value
and its valid flag only above the standstill speed, once its fit has settled (SETTLING) and
in product mode, while its std is within ``MdsfConfig.valid_slip_std_max_pct``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Mapping
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from estimator._arrays import BoolArray, FloatArray, IntArray, nan_to_num
from estimator._slots import grow_slot_array
from estimator.base import Pushed
from estimator.config import VehicleConfig, WheeledRearDriveConfig, expect_kind
from estimator.dead_reckoning import DeadReckoning, DeadReckoningConfig
from estimator.mdsf.calibration import CalibrationBank, MdsfCalibration
from estimator.mdsf.clock_shift import FixRates
from estimator.mdsf.engine import Counter, MdsfEngine, StepOutput, shrunk_lever_accel
from estimator.mdsf.frontend import FleetFrontEnd, FleetTicks, TickInputs
from estimator.mdsf.model import GRAVITY_MPS2, MdsfConfig, MdsfMode, MdsfObs
from estimator.mdsf_spec import MDSF_SPEC
from estimator.reference_speed import ReferenceSpeedConfig
from estimator.slip import fit_span_s, slip_pct, unsettled
from estimator.types import ESTIMATE_DTYPE, EstimateFlag, empty_estimates
from estimator.wheel_speed import WheelSpeedConfig

__all__ = ["MdsfFleet"]

_F = EstimateFlag
_NEVER = np.iinfo(np.int64).min
"""``_still_ns`` of a vehicle before its first tick."""
_START_SPANS = 1.0
_SETTLE_OFF = 1e9
"""``SlipConfig.settle_max_change`` at which the settling rule, this start wait included, is off."""
"""Fit spans a wheel must run after a standstill before its slip counts (the fit's window then
lies in the motion, past the first edge, whose phase is unknown)."""

# counters(): each counter's key and column, in declaration order
_COUNTER_KEYS = tuple(c.name.lower() for c in Counter)
_COUNTER_COLUMNS = np.array(list(Counter), dtype=np.intp)

_TICK_FIELDS = TickInputs.__slots__
_STEP_COLS = (
    "vg",
    "v1",
    "v0",
    "vl",
    "vr",
    "vg_std",
    "vl_std",
    "vr_std",
    "accel",
    "pitch_rate",
    "yaw_rate",
)
"""Per-row outputs of :class:`StepOutput` that go into the estimate rows."""
_CAL_FIELDS = (
    "gnss_clock_offset_s",
    "gnss_clock_offset_std_s",
    "wheel_clock_offset_s",
    "wheel_clock_offset_std_s",
    "radius_left_m",
    "radius_left_std_m",
    "radius_right_m",
    "radius_right_std_m",
    "imu_pitch_mount_rad",
    "imu_pitch_mount_std_rad",
)
"""Row fields of the online calibration (:meth:`CalibrationBank.row_fields`)."""


def _rounds(lengths: IntArray, offsets: IntArray) -> Iterator[tuple[int, IntArray]]:
    """Round ``r`` of a call's ticks: the ``r``-th tick of every vehicle that has one, as
    ``(c, rows)`` (the first ``c`` vehicles: ``lengths`` decrease), for steps that must see a
    vehicle's ticks in order."""
    for r in range(int(lengths[0]) if lengths.shape[0] else 0):
        c = int(np.count_nonzero(lengths > r))
        yield c, offsets[:c] + r


def _estimate_rows(
    flat: TickInputs,
    res: dict[str, np.ndarray],
    rim: np.ndarray,
    radius: np.ndarray,
    slip: np.ndarray,
    slip_std: np.ndarray,
    enu: np.ndarray,
    heading: np.ndarray,
) -> np.ndarray:
    """The rows of a call (``ESTIMATE_DTYPE``, one per tick of ``flat``) from the step's outputs
    ``res``, the rims and radii ``(m, 2)``, slip and its std ``(m, 2)`` (NaN where not valid),
    position ``(m, 3)`` and heading; ``flags`` and the calibration fields are the caller's."""
    out = empty_estimates(flat.m)
    out["stamp_ns"] = flat.stamp_ns
    out["vg_mps"] = res["vg"]
    out["v1_mps"] = res["v1"]
    out["v0_mps"] = res["v0"]
    out["vl_mps"] = res["vl"]
    out["vr_mps"] = res["vr"]
    out["rim_left_mps"] = rim[:, 0]
    out["rim_right_mps"] = rim[:, 1]
    out["omega_left_radps"] = rim[:, 0] / radius[:, 0]
    out["omega_right_radps"] = rim[:, 1] / radius[:, 1]
    out["slip_left_pct"] = slip[:, 0]
    out["slip_right_pct"] = slip[:, 1]
    out["vg_std_mps"] = res["vg_std"]
    out["vl_std_mps"] = res["vl_std"]
    out["vr_std_mps"] = res["vr_std"]
    out["slip_left_std_pct"] = slip_std[:, 0]
    out["slip_right_std_pct"] = slip_std[:, 1]
    out["accel_mps2"] = res["accel"]
    out["pitch_rate_radps"] = res["pitch_rate"]
    out["yaw_rate_radps"] = res["yaw_rate"]
    out["east_m"] = enu[:, 0]
    out["north_m"] = enu[:, 1]
    out["up_m"] = enu[:, 2]
    out["heading_rad"] = heading
    out["pitch_rad"] = flat.attitude[:, 1]
    out["roll_rad"] = flat.attitude[:, 2]
    return out


def _filtered_rims(
    so: StepOutput, rim: FloatArray, rim_std: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Rim speeds (k, 2), their std and covariance with the wheel's ground speed for the slip:
    the filtered ones where the step has them (product mode, emitted rows, measured rim
    speed), else the measured ones with no covariance."""
    if so.rim is None or so.rim_std is None or so.rim_ground_cov is None:
        return rim, rim_std, np.zeros(rim.shape)
    use = (so.emit & np.isfinite(so.rim).all(axis=1))[:, None] & np.isfinite(rim)
    return (
        np.where(use, so.rim, rim),
        np.where(use, so.rim_std, rim_std),
        np.where(use, so.rim_ground_cov, 0.0),
    )


@dataclass(slots=True)
class _Calibrated:
    """A round's wheel inputs as the filter took them, shapes (k, 2): rim speeds with the
    calibrated radius and clock, their std, the radius ratios and which wheels are not
    calibrated yet."""

    rim: FloatArray
    rim_std: FloatArray
    scale: FloatArray
    uncalibrated: BoolArray
    fields: dict[str, FloatArray]
    """The calibration's row fields (``CALIBRATION_FIELDS``), shape (k,) each; NaN in paper
    mode."""


@dataclass(slots=True)
class _Stepped:
    """A call's step results per row (m rows): emitted, flags, the :data:`_STEP_COLS` outputs
    (m,) each, rim speeds, their std and covariance with the ground speed (m, 2), the radius
    ratios and uncalibrated wheels (m, 2) and the calibration's row fields (m,) each."""

    emit: BoolArray
    flags: npt.NDArray[np.int32]
    res: dict[str, np.ndarray]
    rim: FloatArray
    rim_std: FloatArray
    rim_cov: FloatArray
    scale: FloatArray
    uncal: BoolArray
    cal_out: dict[str, FloatArray]


class MdsfFleet:
    """MDSF for a fleet of wheeled vehicles; implements :class:`estimator.base.FleetEstimator`.

    Parameters
    ----------
    config : MdsfConfig, optional
        Filter settings (default: product mode).
    wheel : WheelSpeedConfig, optional
        Wheel-speed front-end settings (``teeth_per_rev`` comes from each vehicle's encoder).
    reference : ReferenceSpeedConfig, optional
        Settings of the speed filter used while GNSS is lost.
    dead_reckoning : DeadReckoningConfig, optional
        How the position is carried while GNSS gives none (:mod:`estimator.dead_reckoning`).

    Examples
    --------
    >>> fleet = MdsfFleet()
    >>> fleet.add_vehicle("t1", WheeledRearDriveConfig())  # doctest: +SKIP
    >>> fleet.push("t1", imu_batch); fleet.push("t1", gnss_sample)   # doctest: +SKIP
    >>> for vid, rows in fleet.advance({"t1": now_ns}): ...          # doctest: +SKIP
    """

    name = "mdsf"
    spec = MDSF_SPEC
    output_dtype = ESTIMATE_DTYPE

    def __init__(
        self,
        config: MdsfConfig | None = None,
        wheel: WheelSpeedConfig | None = None,
        reference: ReferenceSpeedConfig | None = None,
        dead_reckoning: DeadReckoningConfig | None = None,
    ) -> None:
        self.config = config or MdsfConfig()
        self.wheel = wheel or WheelSpeedConfig()
        self.engine = MdsfEngine(self.config, reference)
        self.front = FleetFrontEnd(self.config, self.wheel)
        self.carry = DeadReckoning(dead_reckoning or DeadReckoningConfig(), self.config.dt_s)
        self.calibration_bank = CalibrationBank(self.config)
        """Online calibration of every vehicle (product mode; :mod:`estimator.mdsf.calibration`)."""
        self._product = self.config.mode is MdsfMode.PRODUCT
        self._slot: dict[str, int] = {}
        self._configs: dict[str, WheeledRearDriveConfig] = {}  # reset_calibration's priors
        # per slot: wheel radii and rim travel per encoder tooth (left, right) [m], the slip's
        # minimum ground speed [m/s] and settling limit (SlipConfig)
        self._radius_m = np.zeros((0, 2))
        self._tooth_arc_m = np.zeros((0, 2))
        self._min_speed_mps = np.zeros(0)
        self._settle_max_change = np.zeros(0)
        # per slot: the GNSS clock offset's share of the RTK distance since its chain began [m]
        self._dist_shift_m = np.zeros(0)
        # per slot and wheel: stamp of the last tick whose measured rim speed was a standstill
        # (or unknown); _NEVER until the vehicle's first tick
        self._still_ns = np.zeros((0, 2), dtype=np.int64)
        # per slot and wheel: the last emitted tick's filtered ground speed [m/s] (NaN: none)
        # and its low-passed rate [m/s²] (_wheel_accel)
        self._wheel_prev_mps = np.zeros((0, 2))
        self._wheel_accel_mps2 = np.zeros((0, 2))

    def add_vehicle(self, vehicle_id: str, config: VehicleConfig) -> None:
        """Start estimating ``vehicle_id`` (replaces its config and state if already there)."""
        config = expect_kind(config, WheeledRearDriveConfig, "mdsf")
        self.remove_vehicle(vehicle_id)
        slot = self.engine.add(config)
        self._slot[vehicle_id] = slot
        self._configs[vehicle_id] = config
        self.front.add(slot, config)
        self.carry.add(slot, config.geometry.antenna_offset_m)
        self.calibration_bank.add(slot, config)
        if slot >= self._min_speed_mps.shape[0]:
            cap = max(2 * self._min_speed_mps.shape[0], slot + 1)
            grow_slot_array(self, "_radius_m", cap, (2,), 0.0)
            grow_slot_array(self, "_tooth_arc_m", cap, (2,), 0.0)
            grow_slot_array(self, "_min_speed_mps", cap, (), 0.0)
            grow_slot_array(self, "_settle_max_change", cap, (), 0.0)
            grow_slot_array(self, "_still_ns", cap, (2,), _NEVER)
            grow_slot_array(self, "_dist_shift_m", cap, (), 0.0)
            grow_slot_array(self, "_wheel_prev_mps", cap, (2,), np.nan)
            grow_slot_array(self, "_wheel_accel_mps2", cap, (2,), 0.0)
        geo = config.geometry
        self._radius_m[slot] = (geo.wheel_radius_left_m, geo.wheel_radius_right_m)
        teeth = config.encoder.teeth_per_rev
        self._tooth_arc_m[slot] = self._radius_m[slot] * (2.0 * np.pi / teeth)
        self._min_speed_mps[slot] = config.slip.min_ground_speed_mps
        self._settle_max_change[slot] = config.slip.settle_max_change
        self._still_ns[slot] = _NEVER
        self._dist_shift_m[slot] = 0.0
        self._wheel_prev_mps[slot] = np.nan
        self._wheel_accel_mps2[slot] = 0.0

    def remove_vehicle(self, vehicle_id: str) -> None:
        """Forget ``vehicle_id`` (no error if unknown)."""
        slot = self._slot.pop(vehicle_id, None)
        self._configs.pop(vehicle_id, None)
        if slot is not None:
            self.engine.release(slot)
            self.front.release(slot)

    def vehicle_ids(self) -> list[str]:
        return list(self._slot)

    def push(self, vehicle_id: str, measurement: Pushed) -> None:
        """Buffer one measurement (sensor-time order per vehicle); ``KeyError`` if unknown."""
        self.front.push(self._slot[vehicle_id], measurement)

    def align_ticks(self, vehicle_id: str, stamp_ns: int) -> None:
        """Ticks of ``vehicle_id`` fall on ``stamp_ns + k·tick`` (call before its first push;
        see :meth:`estimator.mdsf.frontend.FleetFrontEnd.align_ticks`); ``KeyError`` if unknown."""
        self.front.align_ticks(self._slot[vehicle_id], stamp_ns)

    def anchor(self, vehicle_id: str) -> tuple[float, float, float] | None:
        """``(lat_deg, lon_deg, height_m)`` of the vehicle's local ENU frame (its first GNSS
        fix), to which ``east_m``/``north_m``/``up_m`` of its rows refer; None before that fix."""
        slot = self._slot.get(vehicle_id)
        return None if slot is None else self.front.anchor(slot)

    def set_anchor(self, vehicle_id: str, lat_deg: float, lon_deg: float, height_m: float) -> None:
        """Give the vehicle's ENU frame this origin (e.g. the anchor its stored estimates were
        given in before a restart) instead of its next first fix; ``KeyError`` if unknown,
        ``ValueError`` if not a geodetic position. Later fixes do not move it."""
        self.front.set_anchor(self._slot[vehicle_id], lat_deg, lon_deg, height_m)

    def calibration(self, vehicle_id: str) -> MdsfCalibration:
        """The vehicle's online calibration, each value with its std (state out: the server
        stores it); ``KeyError`` if unknown."""
        return self.calibration_bank.state(self._slot[vehicle_id])

    def restore_calibration(self, vehicle_id: str, calibration: MdsfCalibration) -> None:
        """Start the vehicle from a stored calibration (state in: call after
        :meth:`add_vehicle`, before its data); ``KeyError`` if unknown."""
        self.calibration_bank.restore(self._slot[vehicle_id], calibration)

    def calibration_drive(self, vehicle_id: str, on: bool) -> None:
        """The operator starts (``on``) or stops a calibration drive: while on, every wheel's
        slip is taken as ~0 and its rolling radius is learnt; ``KeyError`` if unknown."""
        self.calibration_bank.set_drive(self._slot[vehicle_id], on)

    def calibration_drive_on(self, vehicle_id: str) -> bool:
        """Whether the vehicle's calibration drive is on; ``KeyError`` if unknown."""
        return bool(self.calibration_bank.drive[self._slot[vehicle_id]])

    def command(self, vehicle_id: str, key: str, on: bool) -> None:
        """An operator's switch of :data:`MDSF_SPEC` ``commands`` (``calibration_drive``);
        ``KeyError`` for an unknown vehicle or command."""
        if key != "calibration_drive":
            raise KeyError(f"mdsf has no command {key!r}")
        self.calibration_drive(vehicle_id, on)

    def calibration_fields(self, vehicle_id: str) -> dict[str, float]:
        """The calibration as its row fields (``MDSF_SPEC.calibrations``: values and stds, the
        radii in metres); ``KeyError`` if unknown."""
        slots = np.array([self._slot[vehicle_id]])
        fields = self.calibration_bank.row_fields(slots, self._radius_m[slots])
        return {name: float(v[0]) for name, v in fields.items()}

    def restore_calibration_fields(self, vehicle_id: str, values: Mapping[str, float]) -> None:
        """Start the vehicle from its calibration's row fields (:meth:`calibration_fields`, a
        stored row's); ``KeyError`` if unknown or a field is missing."""
        radius = self._radius_m[self._slot[vehicle_id]]
        self.restore_calibration(
            vehicle_id,
            MdsfCalibration(
                gnss_clock_offset_s=values["gnss_clock_offset_s"],
                gnss_clock_offset_std_s=values["gnss_clock_offset_std_s"],
                wheel_clock_offset_s=values["wheel_clock_offset_s"],
                wheel_clock_offset_std_s=values["wheel_clock_offset_std_s"],
                radius_scale_left=values["radius_left_m"] / radius[0],
                radius_scale_left_std=values["radius_left_std_m"] / radius[0],
                radius_scale_right=values["radius_right_m"] / radius[1],
                radius_scale_right_std=values["radius_right_std_m"] / radius[1],
                imu_pitch_rad=values["imu_pitch_mount_rad"],
                imu_pitch_std_rad=values["imu_pitch_mount_std_rad"],
            ),
        )

    def reset_calibration(self, vehicle_id: str) -> None:
        """Forget the vehicle's calibration: back to its config's priors, learnt anew (a
        calibration drive that is on stays on); ``KeyError`` if unknown."""
        slot = self._slot[vehicle_id]
        drive = bool(self.calibration_bank.drive[slot])
        self.calibration_bank.add(slot, self._configs[vehicle_id])
        self.calibration_bank.set_drive(slot, drive)

    def counters(self, vehicle_id: str) -> dict[str, int]:
        """Event counters of one vehicle: ticks, GNSS fused/gated/re-acquired, resets,
        degraded ticks, skipped (non-finite or out-of-order) GNSS/IMU/edges/wheel speeds."""
        slot = self._slot[vehicle_id]
        out = dict(
            zip(_COUNTER_KEYS, self.engine.counts[slot, _COUNTER_COLUMNS].tolist(), strict=True)
        )
        for k, v in self.front.counts(slot).items():
            out[k] = out.get(k, 0) + v
        return out

    def advance(self, until_ns: Mapping[str, int]) -> list[tuple[str, np.ndarray]]:
        """Emit every due tick (``stamp_ns <= until_ns[id]``), vehicles stepped together."""
        ids = [vid for vid in until_ns if vid in self._slot]
        if not ids:
            return []
        slots = np.fromiter(map(self._slot.__getitem__, ids), dtype=np.int64, count=len(ids))
        until = np.fromiter(map(until_ns.__getitem__, ids), dtype=np.int64, count=len(ids))
        due = self.front.assemble(slots, until)
        if due is None:
            return []
        flat = due.inputs
        row_slot = np.repeat(due.slots, due.lengths)
        radius = self._radius_m[row_slot]
        min_speed = self._min_speed_mps[row_slot]
        rim = flat.omega * radius
        still_ns = self._last_still(due, rim, min_speed)
        rim_std = flat.omega_std * radius
        # Slip from the filtered rim speeds where the filter has them (product mode), so the
        # wheel fit's noise is weighed against the accelerometer; the measured ones otherwise.
        if int(due.lengths[0]) == 1:
            stepped = self._step_once(due, rim, rim_std, min_speed)
        else:
            stepped = self._step_rounds(due, rim, rim_std, min_speed)
        out = self._slip_rows(due, row_slot, stepped, radius * stepped.scale, min_speed, still_ns)
        return _by_vehicle([ids[i] for i in due.index.tolist()], out, stepped.emit, due.offsets)

    def _step_once(
        self, due: FleetTicks, rim: FloatArray, rim_std: FloatArray, min_speed: FloatArray
    ) -> _Stepped:
        """One tick per vehicle (the usual call): the step's rows are the call's rows, its
        outputs are used as they are (``rim``, ``rim_std`` (m, 2), ``min_speed`` (m,))."""
        so, cal = self._calibrated_step(due.slots, due.inputs, rim, rim_std, min_speed)
        res = {name: getattr(so, name) for name in _STEP_COLS}
        rim, rim_std, rim_cov = _filtered_rims(so, cal.rim, cal.rim_std)
        return _Stepped(
            so.emit, so.flags, res, rim, rim_std, rim_cov, cal.scale, cal.uncalibrated, cal.fields
        )

    def _step_rounds(
        self, due: FleetTicks, rim: FloatArray, rim_std: FloatArray, min_speed: FloatArray
    ) -> _Stepped:
        """Several ticks per vehicle: stepped round by round (:func:`_rounds`), each round's
        results written to its rows of the call (``rim``, ``rim_std`` (m, 2) in place)."""
        total, flat = due.inputs.m, due.inputs
        emit = np.zeros(total, dtype=bool)
        flags = np.zeros(total, dtype=np.int32)
        res = {c: np.full(total, np.nan) for c in _STEP_COLS}
        rim_cov = np.zeros((total, 2))
        scale = np.ones((total, 2))
        uncal = np.zeros((total, 2), dtype=bool)
        cal_out = {c: np.full(total, np.nan) for c in _CAL_FIELDS}
        for c, fi in _rounds(due.lengths, due.offsets):
            tin = TickInputs(*(getattr(flat, f)[fi] for f in _TICK_FIELDS))
            so, cal = self._calibrated_step(due.slots[:c], tin, rim[fi], rim_std[fi], min_speed[fi])
            emit[fi] = so.emit
            for name in _STEP_COLS:
                res[name][fi] = getattr(so, name)
            flags[fi] = so.flags
            rim[fi], rim_std[fi], rim_cov[fi] = _filtered_rims(so, cal.rim, cal.rim_std)
            scale[fi], uncal[fi] = cal.scale, cal.uncalibrated
            for name in _CAL_FIELDS:
                cal_out[name][fi] = cal.fields[name]
        return _Stepped(emit, flags, res, rim, rim_std, rim_cov, scale, uncal, cal_out)

    def _slip_rows(
        self,
        due: FleetTicks,
        row_slot: IntArray,
        st: _Stepped,
        radius: FloatArray,
        min_speed: FloatArray,
        still_ns: IntArray,
    ) -> np.ndarray:
        """The call's rows (``ESTIMATE_DTYPE``, m): slip from the stepped rims and ground
        speeds (``radius`` (m, 2) calibrated), its validity and flags, position, calibration."""
        flat, res = due.inputs, st.res
        # Slip for all rows and both wheels at once (eq. (8)(9); element-wise: columns left, right).
        ground = np.stack([res["vl"], res["vr"]], axis=1)
        sp = slip_pct(
            st.rim,
            ground,
            min_speed[:, None],
            st.rim_std,
            np.stack([res["vl_std"], res["vr_std"]], axis=1),
            st.rim_cov,
        )
        settling = sp.valid & self._settling(flat, row_slot, ground, res["accel"], still_ns)
        # product mode: a slip whose std is beyond the bound (or unknown) is no reading, not
        # valid (paper mode keeps the source's rule: any slip above the standstill speed)
        certain = (sp.std_pct <= self.config.valid_slip_std_max_pct) | (not self._product)
        valid = sp.valid & ~settling & certain
        enu, heading, carried = self._carry(due, res)
        slip_out = np.where(valid, sp.slip_pct, np.nan)
        slip_std_out = np.where(valid, sp.std_pct, np.nan)
        flags = (
            st.flags
            | _slip_flags(valid, sp.standstill, settling, carried, st.uncal)
            | flat.wheel_flags
        )
        out = _estimate_rows(flat, res, st.rim, radius, slip_out, slip_std_out, enu, heading)
        out["flags"] = flags
        for name in _CAL_FIELDS:
            out[name] = st.cal_out[name]
        return out

    def _settling(
        self,
        flat: TickInputs,
        row_slot: IntArray,
        ground: FloatArray,
        accel: FloatArray,
        still_ns: IntArray,
    ) -> BoolArray:
        """Rows ``(m, 2)`` starting or stopping faster than the wheel fit follows (``SETTLING``:
        no slip value): the ground speed changing by more than the settle bound over the fit's
        span, or a start from standstill less than ``_START_SPANS`` spans ago. The change is
        judged on the axle's acceleration: the filter's ``a1`` (the IMU's) plus the tick's
        ``lever_accel_fwd_mps2``, shrunk towards 0 by two of its std (a soft threshold: on a
        cab without sway the term is the gyro's noise, about 0.07 m/s², where a crawl's bound
        is 0.1-0.3 m/s²; under sway it is metres per second squared)."""
        fitted = (flat.wheel_flags & int(_F.WHEEL_DIRECT)) == 0
        span = np.where(
            fitted[:, None],
            fit_span_s(ground, self._tooth_arc_m[row_slot], self.wheel.min_edges),
            0.0,
        )
        max_change = self._settle_max_change[row_slot]
        # the axle's acceleration, not the IMU's: a swaying cab's h0·ω̇x is no start; the term
        # counts beyond two of its std only (its gyro noise is a crawl's bound)
        accel = accel + shrunk_lever_accel(flat)
        starting = ((flat.stamp_ns[:, None] - still_ns) * 1e-9 < _START_SPANS * span) & (
            max_change < _SETTLE_OFF
        )[:, None]
        settling: BoolArray = (
            unsettled(ground, accel[:, None], span, max_change[:, None]) | starting
        )
        return settling

    def _calibrated_step(
        self,
        slots: IntArray,
        tin: TickInputs,
        rim: FloatArray,
        rim_std: FloatArray,
        min_speed: FloatArray,
    ) -> tuple[StepOutput, _Calibrated]:
        """One round: the tick inputs and rim speeds corrected by the calibration so far, the
        filter stepped, then the calibration learns from the round (product mode; paper mode
        steps the inputs as they are)."""
        bank = self.calibration_bank
        if not self._product:
            so = self.engine.step(slots, tin, rim, rim_std)
            nan = {name: np.full(slots.shape[0], np.nan) for name in _CAL_FIELDS}
            ones, no = np.ones(rim.shape), np.zeros(rim.shape, bool)
            return so, _Calibrated(rim, rim_std, ones, no, nan)
        fix = self._record_inputs(slots, tin)
        fixed = self._apply_calibration(slots, tin, fix)
        scale, wheel_offset_s = bank.wheel_correction(slots)
        rim_c = scale * (rim + wheel_offset_s[:, None] * self._wheel_accel_mps2[slots])
        rim_std_c = scale * rim_std
        so = self.engine.step(slots, fixed, rim_c, rim_std_c)
        bank.shift.record_speed(slots, so.v0, so.emit)
        self._wheel_accel(slots, so)
        self._learn_calibration(slots, tin, fixed, so, rim, rim_std, min_speed)
        fields = bank.row_fields(slots, self._radius_m[slots])
        return so, _Calibrated(rim_c, rim_std_c, scale, bank.uncalibrated(slots), fields)

    def _wheel_accel(self, slots: IntArray, so: StepOutput) -> None:
        """Each wheel's ground acceleration ``a_w`` (slots, 2) after a round: the rate of its
        filtered ground speed (``vl``, ``vr``: GNSS-anchored, at the axle, so without the
        IMU's sway) over the tick, low-passed, ``a ← a + α·((V − V_prev)/dt − a)`` with
        ``α = dt/(τ + dt)``, ``τ`` = ``wheel_clock_accel_tau_s``. A wheel clock offset
        ``δ_w`` moves a rim by ``δ_w·a_w`` (rims read ``δ_w`` late); ``a_w`` is what the rims
        feel, not the accelerometer's vibration and leftover gravity. Kept through ticks
        without a row; the rate restarts after them."""
        dt = self.config.dt_s
        ground = np.stack([so.vl, so.vr], axis=1)
        ok = so.emit[:, None] & np.isfinite(ground)
        rate = (ground - self._wheel_prev_mps[slots]) / dt
        acc = self._wheel_accel_mps2[slots]
        alpha = dt / (self.config.wheel_clock_accel_tau_s + dt)
        step = ok & np.isfinite(rate)
        self._wheel_accel_mps2[slots] = np.where(step, acc + alpha * (rate - acc), acc)
        self._wheel_prev_mps[slots] = np.where(ok, ground, np.nan)

    def _record_inputs(self, slots: IntArray, tin: TickInputs) -> FixRates:
        """The state a round's inputs move before the filter's step: the tick's body rates
        become the GNSS clock shift's newest, the running powers of its sway part step and,
        once the offset has converged, the RTK distance's clock share grows by
        ``δ_g·ΔV1`` (restarted with its chain). Returns the rates at the instants the
        round's fixes describe (:meth:`GnssClockShift.fix_rates`)."""
        bank = self.calibration_bank
        shift = bank.shift
        rates = tin.z[:, (MdsfObs.OMEGA_X, MdsfObs.OMEGA_Z)]
        shift.record_rates(slots, tin.stamp_ns, rates, tin.gyro_var)
        fix = shift.fix_rates(slots, bank.gnss_offset_s(slots), tin.fix_age_s, self.front)
        shift.record_sway(slots, fix)
        # the distance's error δ·V as its growth since the chain began, Σδ·ΔV1, once δ has
        # converged: the chain's origin is arbitrary, an estimate still moving would leave its
        # error in the distance, and a step of it must not make the distance jump; ΔV1 from
        # the filter's GNSS-anchored speed (∫a1·dt carries the accelerometer's bias)
        restart = tin.dist_ok & tin.dist_restart
        rate = np.where(bank.gnss_offset_converged(slots), fix.offset_s, 0.0)
        moved = rate * shift.imu_speed_step_mps(slots, self.front)
        self._dist_shift_m[slots] = np.where(restart, 0.0, self._dist_shift_m[slots] + moved)
        return fix

    def _apply_calibration(self, slots: IntArray, tin: TickInputs, fix: FixRates) -> TickInputs:
        """Tick inputs with the calibrations applied (no state changes): the mounting pitch's
        gravity share ``g·(sin(θ + β) − sin θ)`` taken off the forward acceleration and force
        and the mounting yaw's lateral share ``γ·f_x`` put back, the GNSS speed moved by what
        its clock offset makes of the antenna's speed (the filter's own speed rate and the
        body rates ``fix`` at the instant the fix describes,
        :class:`~estimator.mdsf.clock_shift.GnssClockShift`; the offset's std and the rates'
        guess into its variance) and, once the offset has converged, the RTK distance by its
        clock share (:meth:`_record_inputs`) and the mast's turn over the offset
        (``docs/perf/estimator.md``)."""
        bank = self.calibration_bank
        z = tin.z.copy()
        theta = np.nan_to_num(tin.attitude[:, 1])
        tilt = GRAVITY_MPS2 * (np.sin(theta + bank.mount_pitch_rad(slots)) - np.sin(theta))
        if tin.force_lat is not None:
            tilt = tilt - bank.mount_yaw_rad(slots) * np.nan_to_num(tin.force_lat)
        z[:, MdsfObs.A1] -= tilt
        shift, shift_var = bank.shift.shift_mps(slots, fix, bank.gnss_offset_std_s(slots))
        z[:, MdsfObs.VG] += shift
        converged = bank.gnss_offset_converged(slots)
        mast = bank.shift.mast_shift_m(slots, fix, converged, self.front)
        dist_m = tin.dist_m + self._dist_shift_m[slots] + mast
        return dataclasses.replace(
            tin,
            z=z,
            gnss_var=tin.gnss_var + shift_var,
            force_fwd=tin.force_fwd - tilt,
            dist_m=dist_m,
        )

    def _learn_calibration(
        self,
        slots: IntArray,
        tin: TickInputs,
        fixed: TickInputs,
        so: StepOutput,
        rim: FloatArray,
        rim_std: FloatArray,
        min_speed: FloatArray,
    ) -> None:
        """The calibration filters learn from one round: raw GNSS speed (at the IMU: the
        antenna's lever-arm terms taken off) against the corrected acceleration, raw rim
        speeds against the filter's wheel ground speeds (emitted, GNSS-anchored rows), the
        raw forward force at standstill, the raw lateral force at ``O`` (lever-arm term off)
        against the centripetal and gravity's share and the raw forward force at ``O`` (the
        forward lever term on)."""
        bank = self.calibration_bank
        accel = fixed.z[:, MdsfObs.A1]
        vg_raw = np.where(tin.gnss_ok, tin.z[:, MdsfObs.VG], np.nan)
        # the antenna's lever-arm terms taken off: eq. (2) with the rates at the tick
        wx, wz = (np.nan_to_num(tin.z[:, c]) for c in (MdsfObs.OMEGA_X, MdsfObs.OMEGA_Z))
        lever = self.front.ant_x_m[slots] * wz - self.front.h1_m[slots] * wx
        spans = None
        if tin.gnss_age_span_s is not None and tin.accel_span_end_s is not None:
            spans = (tin.gnss_age_span_s, tin.accel_span_end_s)
        bank.observe_gnss(slots, accel, tin.accel_var, vg_raw - lever, tin.gnss_var, lever, spans)
        usable = so.emit & ((so.flags & int(_F.GNSS_OK)) != 0)
        ground = np.stack([so.vl, so.vr], axis=1)
        ground_var = np.stack([so.vl_std, so.vr_std], axis=1) ** 2
        wheel_accel = self._wheel_accel_mps2[slots]
        bank.observe_wheels(slots, rim, rim_std**2, ground, ground_var, wheel_accel, usable)
        still = bank.still_pitch_rows(slots, vg_raw, rim, min_speed)
        bank.observe_still(slots, tin.force_fwd, tin.accel_var, tin.attitude[:, 1], still)
        if tin.force_lat is None or tin.lever_force_lat is None:
            return
        lever_fwd = tin.lever_accel_fwd_mps2
        if lever_fwd is None:  # a caller without the forward lever term: predicted only
            lever_fwd = np.full(tin.force_fwd.shape, np.nan)
        bank.observe_yaw(
            slots,
            (tin.force_fwd + lever_fwd, tin.force_lat - tin.lever_force_lat),
            tin.accel_var,
            so.v0,
            tin.z[:, MdsfObs.OMEGA_Z],
            (tin.attitude[:, 1], tin.attitude[:, 2]),
            (lever_fwd, tin.lever_force_lat),
        )

    def _last_still(self, due: FleetTicks, rim: FloatArray, min_speed: FloatArray) -> IntArray:
        """Per row and wheel, the stamp of the latest tick at or before it whose measured rim
        speed was unknown or below the standstill speed (this call's rows, else the stored one;
        a vehicle's first tick counts as one), shape (rows, 2); stores each vehicle's last.

        A wheel starting from rest has its first fits over edges from before the start (a fit
        of 30 % low read as valid slip): slip waits until the wheel has run ``_START_SPANS``
        fit spans since (:func:`estimator.slip.fit_span_s`), so no value comes before the
        wheel's first fit or from a zero-edge start. Part of the settling rule (flag SETTLING;
        off with it at ``settle_max_change`` 1e9)."""
        flat = due.inputs
        stamps = flat.stamp_ns
        n = stamps.shape[0]
        still = ~np.isfinite(rim) | (np.abs(nan_to_num(rim)) < min_speed[:, None])
        idx = np.where(still, np.arange(n)[:, None], -1)
        last = np.maximum.accumulate(idx, axis=0)
        seg_start = np.repeat(due.offsets, due.lengths)
        stored = self._still_ns[np.repeat(due.slots, due.lengths)]
        stored = np.where(
            stored == _NEVER, np.repeat(stamps[due.offsets], due.lengths)[:, None], stored
        )
        out = np.where(last >= seg_start[:, None], stamps[np.maximum(last, 0)], stored)
        ends = due.offsets + due.lengths - 1
        self._still_ns[due.slots] = out[ends]
        return out

    def _carry(
        self, due: FleetTicks, res: dict[str, FloatArray]
    ) -> tuple[FloatArray, FloatArray, npt.NDArray[np.bool_]]:
        """Positions and headings of the call's ticks with GNSS outages dead-reckoned, and which
        ticks were (a vehicle's ticks in order: one round per tick, as the filter's steps)."""
        flat, lengths, offsets = due.inputs, due.lengths, due.offsets
        enu, heading = flat.enu, flat.attitude[:, 0]
        carried = np.zeros(flat.m, dtype=bool)
        copied = False
        for c, fi in _rounds(lengths, offsets):
            e, h, k = self.carry.step(
                due.slots[:c],
                flat.enu[fi],
                flat.fix_age_s[fi],
                flat.attitude[fi, 0],
                res["v0"][fi],
                res["yaw_rate"][fi],
                flat.attitude[fi, 1],
            )
            if k.any():  # outputs copied only when some tick is carried (rare)
                if not copied:
                    enu, heading, copied = enu.copy(), heading.copy(), True
                enu[fi], heading[fi], carried[fi] = e, h, k
        return enu, heading, carried


def _by_vehicle(
    ids: list[str], out: np.ndarray, emit: BoolArray, offsets: IntArray
) -> list[tuple[str, np.ndarray]]:
    """The emitted rows of ``out`` split by vehicle (``ids`` in the order of the call's rows,
    ``offsets`` their first rows), vehicles without an emitted row left out. One row each, all
    emitted (the usual call): the rows as they lie, one view per row."""
    if emit.all() and out.shape[0] == len(ids):
        return list(zip(ids, out[:, None], strict=True))
    kept = out if emit.all() else out[emit]
    ends = np.cumsum(np.add.reduceat(emit, offsets)).tolist()
    return [(vid, kept[a:b]) for vid, a, b in zip(ids, [0, *ends[:-1]], ends, strict=True) if b > a]


def _slip_flags(
    valid: BoolArray,
    standstill: BoolArray,
    settling: BoolArray,
    carried: BoolArray,
    uncalibrated: BoolArray,
) -> IntArray:
    """The slip's flags per row ``(m,)`` from per-wheel ``(m, 2)`` masks (``carried``
    ``(m,)``): valid per side, standstill on both, settling or uncalibrated on either."""
    return (
        np.where(valid[:, 0], int(_F.SLIP_LEFT_VALID), 0)
        | np.where(valid[:, 1], int(_F.SLIP_RIGHT_VALID), 0)
        | np.where(standstill.all(axis=1), int(_F.STANDSTILL), 0)
        | np.where(settling.any(axis=1), int(_F.SETTLING), 0)
        | np.where(carried, int(_F.DEAD_RECKONED), 0)
        | np.where((valid & uncalibrated).any(axis=1), int(_F.UNCALIBRATED), 0)
    ).astype(np.int32)
