"""Measurement and output types shared by every estimator.

Frames and conventions (``../shared/docs/method.md`` section 1):

* Vehicle body frame: **X right (pitch axis), Y forward, Z up**.
* ``gyro_radps[:, 0]`` is the pitch rate ``ωx``; ``gyro_radps[:, 2]`` the yaw rate ``ωz``,
  positive counter-clockwise seen from above.
* ``accel_mps2`` is *specific force* as a MEMS accelerometer measures it: it includes gravity,
  so a level vehicle at rest reads ``(0, 0, +9.81)``; climbing a slope of pitch ``θ`` (nose up
  positive) the forward axis reads ``dv/dt + g·sin θ``.
* GNSS velocity is ENU (east, north, up) in m/s; heading ``ψ`` is from north, clockwise, in
  radians; pitch ``θ`` nose up positive; roll ``φ`` right side down positive.
* Every timestamp is an ``int`` (or ``int64`` array) of nanoseconds since the Unix epoch, UTC,
  from the vehicle clock.

Arrays are batches: an IMU packet carries ``n`` samples, a wheel packet ``n`` edges. Nothing
here copies per sample, so a decoder can hand over views of its buffers.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass
from enum import IntEnum, IntFlag
from typing import overload

import numpy as np
import numpy.typing as npt

from estimator._arrays import FloatArray, IntArray
from estimator.spec import EstimatorSpec

__all__ = [
    "ESTIMATE_DTYPE",
    "ESTIMATE_FIELDS",
    "Corner",
    "EstimateBatch",
    "EstimateFlag",
    "GnssFix",
    "GnssSample",
    "ImuBatch",
    "OdometerEdges",
    "SprocketEdges",
    "SteeringAngles",
    "TrackSide",
    "Wheel",
    "WheelEdges",
    "WheelGap",
    "WheelSpeeds",
    "WheelSpeeds4",
    "concat_estimates",
    "empty_estimates",
]


class Wheel(IntEnum):
    """Index of a driven wheel (or track) in every per-wheel array."""

    LEFT = 0
    RIGHT = 1


class GnssFix(IntEnum):
    """GNSS solution quality, as receivers report it (NMEA GGA quality, simplified)."""

    NONE = 0
    SINGLE = 1
    DGNSS = 2
    RTK_FLOAT = 5
    RTK_FIXED = 4


@dataclass(frozen=True, slots=True)
class GnssSample:
    """One GNSS epoch.

    Attributes
    ----------
    stamp_ns : int
        Epoch time of the solution (not the arrival time).
    vel_enu_mps : tuple[float, float, float]
        Velocity ``(Ve, Vn, Vu)`` of the antenna.
    heading_rad, pitch_rad, roll_rad : float
        Attitude from a dual-antenna receiver (or NaN when not available).
    lat_deg, lon_deg, height_m : float
        WGS-84 position of the antenna.
    fix : GnssFix
        Solution type.
    vel_std_mps : float
        Receiver-reported 1-sigma velocity accuracy per axis, or NaN if unknown.
    """

    stamp_ns: int
    vel_enu_mps: tuple[float, float, float]
    heading_rad: float
    pitch_rad: float
    roll_rad: float
    lat_deg: float
    lon_deg: float
    height_m: float
    fix: GnssFix = GnssFix.RTK_FIXED
    vel_std_mps: float = float("nan")


@dataclass(frozen=True, slots=True)
class ImuBatch:
    """A batch of IMU samples.

    Attributes
    ----------
    stamp_ns : ndarray, shape (n,), int64
        Sample times, strictly increasing.
    accel_mps2 : ndarray, shape (n, 3)
        Specific force in the body frame (X right, Y forward, Z up), gravity included.
    gyro_radps : ndarray, shape (n, 3)
        Angular rate in the body frame: ``[:, 0]`` pitch rate ωx, ``[:, 2]`` yaw rate ωz (CCW +).
    """

    stamp_ns: IntArray
    accel_mps2: FloatArray
    gyro_radps: FloatArray


@dataclass(frozen=True, slots=True)
class WheelEdges:
    """Rising edges of one wheel's encoder (toothed ring with ``teeth_per_rev`` teeth).

    Attributes
    ----------
    wheel : Wheel
        Which wheel.
    stamp_ns : ndarray, shape (n,), int64
        Edge times, non-decreasing.
    direction : ndarray, shape (n,), int8, or None
        +1 forward, -1 reverse, when the encoder is quadrature; None if it cannot tell.
    """

    wheel: Wheel
    stamp_ns: IntArray
    direction: npt.NDArray[np.int8] | None = None


@dataclass(frozen=True, slots=True)
class WheelGap:
    """Wheel edges missing where the estimator is about to go on without them.

    The server sends one before the first data it feeds after ``after_ns``, the time a
    vehicle's wheel data is complete up to, in two cases:

    * ``until_ns`` given: the ticks up to ``until_ns`` are due while the wheel data after
      ``after_ns`` has not come (the wheel stream later than the reorder window). No edge up
      to a tick reads as a wheel turning slower than one tooth since the last, which is only
      true if none is on its way, so those ticks get no wheel speed; the fits go on.
    * ``until_ns`` None: wheel data after ``after_ns`` is lost (a packet that never came, or
      came too late to be fed). Edges count wheel angle and a fit across the loss would read a
      slower wheel, so the wheels' fits start afresh and no tick gets a wheel speed until each
      holds enough edges again.

    Attributes
    ----------
    after_ns : int
        Sensor time up to which the wheel stream is complete.
    until_ns : int or None
        End of the span of ticks due without wheel data; None: the data is lost.
    """

    after_ns: int
    until_ns: int | None = None


@dataclass(frozen=True, slots=True)
class WheelSpeeds:
    """Wheel angular speeds given directly (for example from the CAN bus).

    Attributes
    ----------
    stamp_ns : ndarray, shape (n,), int64
    omega_radps : ndarray, shape (n, 2)
        Signed angular speed of the left and right wheel (forward positive).
    """

    stamp_ns: IntArray
    omega_radps: FloatArray


class TrackSide(IntEnum):
    """Which track a sprocket drives (crawlers)."""

    TRACK_LEFT = 0
    TRACK_RIGHT = 1


class Corner(IntEnum):
    """Column of a wheel in a four-wheel array (:class:`WheelSpeeds4`)."""

    FRONT_LEFT = 0
    FRONT_RIGHT = 1
    REAR_LEFT = 2
    REAR_RIGHT = 3


@dataclass(frozen=True, slots=True)
class OdometerEdges:
    """Edges of the transmission's odometer sensor (a toothed output shaft).

    Attributes
    ----------
    stamp_ns : ndarray, shape (n,), int64
        Edge times, non-decreasing.
    direction : ndarray, shape (n,), int8, or None
        +1 forward, -1 reverse, when the sensor tells; None if it cannot.
    """

    stamp_ns: IntArray
    direction: npt.NDArray[np.int8] | None = None


@dataclass(frozen=True, slots=True)
class SprocketEdges:
    """Rising edges of one track's sprocket encoder (like :class:`WheelEdges`, per track).

    Attributes
    ----------
    side : TrackSide
    stamp_ns : ndarray, shape (n,), int64
        Edge times, non-decreasing.
    direction : ndarray, shape (n,), int8, or None
        +1 forward, -1 reverse, when the encoder is quadrature; None if it cannot tell.
    """

    side: TrackSide
    stamp_ns: IntArray
    direction: npt.NDArray[np.int8] | None = None


@dataclass(frozen=True, slots=True)
class SteeringAngles:
    """Steering-wheel angle samples.

    Attributes
    ----------
    stamp_ns : ndarray, shape (n,), int64
        Sample times, strictly increasing.
    angle_rad : ndarray, shape (n,), float64
        Steering-wheel angle from straight ahead, counter-clockwise (a left turn) positive;
        NaN when not available.
    """

    stamp_ns: IntArray
    angle_rad: FloatArray


@dataclass(frozen=True, slots=True)
class WheelSpeeds4:
    """Angular speeds of four wheels from the CAN bus.

    Attributes
    ----------
    stamp_ns : ndarray, shape (n,), int64
        Sample times, strictly increasing.
    omega_radps : ndarray, shape (n, 4)
        Signed angular speed (forward positive), columns in :class:`Corner` order: front left,
        front right, rear left, rear right.
    """

    stamp_ns: IntArray
    omega_radps: FloatArray


class EstimateFlag(IntFlag):
    """Quality flags of one estimate (bit field stored with every row)."""

    NONE = 0
    GNSS_OK = 1 << 0
    """A GNSS velocity was fused on this tick or recently enough to trust the speed."""
    DEGRADED = 1 << 1
    """GNSS lost: speed carried by IMU + wheel speed (reference-speed filter)."""
    STANDSTILL = 1 << 2
    """Below the standstill threshold: no slip value."""
    GATED = 1 << 3
    """A GNSS velocity was rejected by the innovation gate on this tick."""
    SLIP_LEFT_VALID = 1 << 4
    SLIP_RIGHT_VALID = 1 << 5
    WHEEL_PERIOD_METHOD = 1 << 6
    """Wheel speed came from the (k-tooth) period method; otherwise the frequency method."""
    WHEEL_DIRECT = 1 << 7
    """Wheel speed was given directly (CAN), not from pulses."""
    RESET = 1 << 8
    """The filter was reset on this tick (divergence or re-initialisation)."""
    SETTLING = 1 << 9
    """Starting or stopping: the speed changes too fast for the wheel-speed fit at this low
    speed (``SlipConfig.settle_max_change``); no slip value for a wheel so judged."""
    WHEEL_GAP = 1 << 10
    """Wheel data was missing (:class:`WheelGap`): a wheel's fit starts afresh and has no
    speed, hence no slip, until it holds enough new edges."""
    DEAD_RECKONED = 1 << 11
    """No GNSS position for longer than ``DeadReckoningConfig.after_s``: position and heading
    are carried from the last fix by the speed and the gyro (:mod:`estimator.dead_reckoning`)."""
    UNCALIBRATED = 1 << 12
    """A calibration a valid slip depends on (clock offsets, the wheel's rolling radius, the
    IMU's mounting) has not converged yet (:mod:`estimator.mdsf.calibration`)."""


#: Fields of one estimate row, in storage order. Units are in the names; slip is in percent.
ESTIMATE_FIELDS: tuple[tuple[str, str], ...] = (
    ("stamp_ns", "i8"),
    ("vg_mps", "f8"),  # vehicle-direction speed at the antenna, eq. (1) / filtered
    ("v1_mps", "f8"),  # forward speed at the IMU, eq. (2)
    ("v0_mps", "f8"),  # forward speed of the rear-axle midpoint's ground projection, eq. (3)
    ("vl_mps", "f8"),  # left wheel ground speed, eq. (4)
    ("vr_mps", "f8"),  # right wheel ground speed, eq. (5)
    ("rim_left_mps", "f8"),  # r·W left
    ("rim_right_mps", "f8"),  # r·W right
    ("omega_left_radps", "f8"),
    ("omega_right_radps", "f8"),
    ("slip_left_pct", "f8"),  # eq. (8)(9); NaN when not valid
    ("slip_right_pct", "f8"),
    ("vg_std_mps", "f8"),
    ("vl_std_mps", "f8"),
    ("vr_std_mps", "f8"),
    ("slip_left_std_pct", "f8"),
    ("slip_right_std_pct", "f8"),
    ("accel_mps2", "f8"),  # forward acceleration a1 (gravity removed in product mode)
    ("pitch_rate_radps", "f8"),
    ("yaw_rate_radps", "f8"),
    ("east_m", "f8"),  # antenna position in the vehicle's local ENU frame
    ("north_m", "f8"),
    ("up_m", "f8"),
    ("heading_rad", "f8"),
    ("pitch_rad", "f8"),
    ("roll_rad", "f8"),
    ("flags", "i4"),  # EstimateFlag bits
    # online calibration in force at the row (estimator.mdsf.calibration), each with its std
    ("gnss_clock_offset_s", "f8"),
    ("gnss_clock_offset_std_s", "f8"),
    ("wheel_clock_offset_s", "f8"),
    ("wheel_clock_offset_std_s", "f8"),
    ("radius_left_m", "f8"),
    ("radius_left_std_m", "f8"),
    ("radius_right_m", "f8"),
    ("radius_right_std_m", "f8"),
    ("imu_pitch_mount_rad", "f8"),
    ("imu_pitch_mount_std_rad", "f8"),
)

ESTIMATE_DTYPE = np.dtype(list(ESTIMATE_FIELDS))


def _empty_row() -> np.ndarray:
    out = np.zeros(1, dtype=ESTIMATE_DTYPE)
    for name, kind in ESTIMATE_FIELDS:
        if kind == "f8":
            out[name] = np.nan
    return out


_EMPTY_ROW = _empty_row()


def empty_estimates(n: int = 0) -> np.ndarray:
    """Return ``n`` estimate rows, floats NaN, ints zero (structured array of ESTIMATE_DTYPE)."""
    return np.repeat(_EMPTY_ROW, n)  # one copy, not one fill per field (the estimator's hot path)


def concat_estimates(parts: Sequence[np.ndarray]) -> np.ndarray:
    """Concatenate row arrays of one structured dtype into one array.

    ``np.concatenate`` of structured arrays promotes their dtypes in Python code (~50 µs per
    array: ~5 µs per row for a batch of small packets); viewed as fixed-size void rows they
    concatenate as one copy. One part is returned as it is; parts of different dtypes raise
    ``TypeError`` (rows of two estimators never mix).
    """
    if len(parts) == 1:
        return parts[0]
    dtype = parts[0].dtype
    if any(p.dtype != dtype for p in parts):
        raise TypeError(f"rows of different dtypes cannot be joined: {[p.dtype for p in parts]}")
    void = np.dtype((np.void, dtype.itemsize))
    return np.concatenate([p.view(void) for p in parts]).view(dtype)


class EstimateBatch(Sequence[tuple[str, np.ndarray]]):
    """One estimator's rows of several vehicles in one array, grouped by vehicle.

    A sequence of ``(vehicle_id, rows)`` like the list an estimator call returns, whose items
    are views of one joined array: consumers that work on all rows at once read :attr:`rows`
    instead of joining the parts again, each of them. :attr:`spec` says what the rows are
    (every sink reads them through it, never by one estimator's field names).

    Parameters
    ----------
    ids : list of str, length k
        The vehicles, in the order of their rows.
    counts : list of int, length k
        Rows of each vehicle (> 0).
    rows : ndarray, shape (sum(counts),), ``spec.dtype``
        ``counts[0]`` rows of ``ids[0]``, then ``counts[1]`` of ``ids[1]`` …
    spec : EstimatorSpec
        The estimator that produced them.
    """

    __slots__ = ("_bounds", "counts", "ids", "rows", "spec")

    def __init__(
        self, ids: list[str], counts: list[int], rows: np.ndarray, spec: EstimatorSpec
    ) -> None:
        if len(ids) != len(counts) or sum(counts) != rows.shape[0]:
            raise ValueError("ids, counts and rows disagree")
        if rows.dtype is not spec.dtype and rows.dtype != spec.dtype:
            raise TypeError(f"rows of {spec.name!r} must have its dtype, got {rows.dtype}")
        self.ids = ids
        self.counts = counts
        self.rows = rows
        self.spec = spec
        self._bounds = [0, *itertools.accumulate(counts)]

    @property
    def estimator(self) -> str:
        """Name of the estimator whose rows these are."""
        return self.spec.name

    @classmethod
    def of(cls, batch: Sequence[tuple[str, np.ndarray]], spec: EstimatorSpec) -> EstimateBatch:
        """``batch`` itself when it is one of ``spec``, else its non-empty parts joined (one
        copy); ``TypeError`` for rows of another dtype."""
        if isinstance(batch, EstimateBatch) and batch.spec is spec:
            return batch
        parts = [(vid, spec.check_rows(rows)) for vid, rows in batch if rows.shape[0] > 0]
        if not parts:
            return cls([], [], spec.empty_rows(0), spec)
        return cls(
            [vid for vid, _ in parts],
            [rows.shape[0] for _, rows in parts],
            concat_estimates([rows for _, rows in parts]),
            spec,
        )

    def grouped(self, keys: npt.NDArray[np.int64]) -> tuple[np.ndarray, npt.NDArray[np.int64]]:
        """The rows with each vehicle's rows as one run, and each row's key.

        ``keys`` (shape ``(len(ids),)``) is a number per vehicle (a consumer's slot); returns
        ``(rows, key per row)``. A vehicle is listed once per estimator call, so its rows are
        one run already; only a batch naming a vehicle twice is reordered (stable: time order
        within a vehicle kept).
        """
        key = np.repeat(keys, self.counts)
        if len(set(self.ids)) == len(self.ids):
            return self.rows, key
        order = np.argsort(key, kind="stable")
        return self.rows[order], key[order]

    def __len__(self) -> int:
        return len(self.ids)

    @overload
    def __getitem__(self, i: int) -> tuple[str, np.ndarray]: ...
    @overload
    def __getitem__(self, i: slice) -> list[tuple[str, np.ndarray]]: ...
    def __getitem__(self, i: int | slice) -> tuple[str, np.ndarray] | list[tuple[str, np.ndarray]]:
        if isinstance(i, slice):
            return [self[k] for k in range(*i.indices(len(self)))]
        k = range(len(self.ids))[i]  # negative indices, IndexError
        return self.ids[k], self.rows[self._bounds[k] : self._bounds[k + 1]]
