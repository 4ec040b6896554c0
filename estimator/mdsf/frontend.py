"""Fleet front end of the MDSF estimator: buffered measurements of many vehicles → tick inputs.

:class:`FleetFrontEnd` holds every vehicle's front-end state in arrays indexed by the
:class:`~estimator.mdsf.engine.MdsfEngine` slot and turns the buffered measurements of all vehicles
due in one :meth:`~estimator.mdsf.MdsfFleet.advance` into :class:`TickInputs` with a number
of numpy calls that does not grow with the fleet (ticks are ``MdsfConfig.tick_ns`` of sensor
time on a fleet-wide grid):

* IMU samples of all vehicles wait in one queue (push order); an assembly takes those of the
  due vehicles, sorted stably by vehicle. Per tick: the mean forward acceleration (gravity
  removed with the tracked pitch, product mode), ``ωx`` and ``ωz`` (gyro biases removed),
  binned with ``np.bincount`` over (vehicle row, tick) ids.
* A tilt track (pitch and roll as ``θ + iφ``, :mod:`estimator.tilt`, run for the batch by
  :meth:`_Batch._pitch_track`): the body rates integrated with the yaw rate turning the tilt;
  at each fix a Kalman update of pitch and pitch-gyro bias with the GNSS pitch or, from a
  receiver without attitude, the GNSS velocity's elevation, the same update of roll and
  roll-gyro bias with the GNSS roll, and zero-rate updates of the biases when the vehicle
  stood since the previous fix (:func:`~estimator.tilt.pitch_kf_update`); and a yaw-gyro-bias
  track (heading integrated from ``ωz``, pulled to the GNSS heading,
  :func:`~estimator.tilt.yaw_fix_update`), product mode. Paper mode takes each GNSS pitch as
  it is (:func:`~estimator.tilt.pitch_fix_update`). The integrals are segmented cumulative
  sums; the sequential updates at the fixes run for all vehicles at once, one loop pass per
  "k-th fix of this batch" (a handful of passes).
* GNSS speed per tick: eq. (1) (``method.md`` §1) with the pitch in force, moved to the tick
  with the tick-mean acceleration and averaged (product), or the latest (paper).
* Position (ENU of each vehicle's first fix, :func:`estimator.geo.enu_from_geodetic`, moved to
  the tick with the GNSS velocity in product mode) and attitude held from the latest fix at or
  before each tick.
* Wheel speeds: encoder trackers of all vehicles that share the ticks queried in one
  :meth:`~estimator.wheel_speed.WheelBank.query`; direct (CAN) speeds per vehicle (no batched
  query exists for them).

Within one vehicle, measurements are expected in sensor order (the pipeline's reorder buffer
releases them so); IMU samples and fixes that go back in time are skipped or, for fixes,
taken in push order.

"Latest entry at or before ``t`` for the same vehicle" lookups are one stable sort of the
combined (vehicle, time) keys (:func:`_asof`).

Bad input is skipped and counted (:data:`COUNT_NAMES`), never raised on (a malformed array
shape still raises in :meth:`FleetFrontEnd.push`, as ``reshape`` does). IMU samples and GNSS
fixes are checked when the next :meth:`FleetFrontEnd.assemble` (or :meth:`FleetFrontEnd.counts`)
takes them, against the state of their push time (nothing changes that state in between), so
counts and rows equal a check at push time.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
import numpy.typing as npt

from estimator._arrays import (
    BoolArray,
    CArray,
    FloatArray,
    IntArray,
    as_rows,
    as_stamps,
    nan_to_num,
    seg_cumsum,
)
from estimator._slots import grow_slot_array
from estimator.base import Pushed
from estimator.config import WheeledRearDriveConfig
from estimator.geo import enu_from_geodetic
from estimator.mdsf.model import (
    GRAVITY_MPS2,
    N_OBS_PAPER,
    MdsfConfig,
    MdsfMode,
    MdsfObs,
    gnss_vehicle_speed,
)
from estimator.tilt import (
    PITCH_SUM_OF,
    ROLL_SUM_OF,
    AngleCov,
    Integral,
    PitchSum,
    RollSum,
    angle_var_after,
    pitch_fix_update,
    pitch_kf_update,
    shrunk_roll,
    tilt_at,
    tilt_integrals,
    yaw_fix_update,
)
from estimator.types import (
    EstimateFlag,
    GnssFix,
    GnssSample,
    ImuBatch,
    Wheel,
    WheelEdges,
    WheelGap,
    WheelSpeeds,
)
from estimator.wheel_speed import (
    DirectWheelSpeed,
    WheelBank,
    WheelSpeedConfig,
    WheelSpeedMethod,
    WheelSpeedResult,
    WheelTracker,
    gather_bank,
)

__all__ = [
    "COUNT_NAMES",
    "FleetFrontEnd",
    "FleetTicks",
    "TickInputs",
]

_NS = 1e-9
_NONE_NS = np.iinfo(np.int64).min
_PENDING_NS = np.iinfo(np.int64).max
"""Time stamp meaning "not yet" in the slot arrays."""
_F = EstimateFlag

COUNT_NAMES = (
    "skipped_gnss",
    "skipped_imu",
    "skipped_edges",
    "skipped_wheel_speeds",
    "skipped_late",
    "ticks_without_wheel_data",
)
"""Per-vehicle counters kept by the front end (columns of ``FleetFrontEnd.count``); the last
counts ticks that had no wheel speed for missing wheel data (:class:`WheelGap`)."""
_GNSS, _IMU, _EDGES, _SPEEDS, _LATE, _NO_WHEEL_DATA = range(len(COUNT_NAMES))

# Columns of a GNSS fix's float record (as pushed) and of a held output row.
_G_VE, _G_VN, _G_VU, _G_HEAD, _G_PITCH, _G_ROLL, _G_LAT, _G_LON, _G_H, _G_VSTD, _G_FIX = range(11)
_H_STAMP, _H_E, _H_N, _H_U, _H_VE, _H_VN, _H_VU, _H_HEAD, _H_PITCH, _H_ROLL = range(10)


@dataclass(slots=True)
class TickInputs:
    """Inputs of ``m`` ticks (rows): one vehicle's consecutive ticks, or several vehicles' flat.

    Attributes
    ----------
    stamp_ns : ndarray, shape (m,), int64
    z : ndarray, shape (m, 4)
        ``[Vg, a1, ωx, ωz]`` (eq. (6) observation); Vg aligned to the tick in product mode.
    gnss_ok : ndarray, shape (m,), bool
        A GNSS speed is in ``z[:, VG]``.
    gnss_var : ndarray, shape (m,)
        Its variance [(m/s)²].
    imu_ok : ndarray, shape (m,), bool
        The tick window held IMU samples.
    accel_var, gyro_var : ndarray, shape (m,)
        Variance of the tick-mean acceleration and rates.
    force_fwd : ndarray, shape (m,)
        Tick-mean forward specific force as measured (gravity included) [m/s²]: the traction
        demand the tyres see.
    omega : ndarray, shape (m, 2)
        Wheel angular speeds (left, right) at the tick [rad/s]; NaN when unknown.
    omega_std : ndarray, shape (m, 2)
    wheel_flags : ndarray, shape (m,), int32
        ``WHEEL_PERIOD_METHOD`` / ``WHEEL_DIRECT`` bits.
    enu : ndarray, shape (m, 3)
        Antenna position in the vehicle's ENU frame (NaN before the first fix).
    attitude : ndarray, shape (m, 3)
        Heading, pitch, roll [rad].
    dist_ok : ndarray, shape (m,), bool
        An RTK-fixed position gave the along-track distance of this tick (product mode).
    dist_m : ndarray, shape (m,)
        Along-track distance of the IMU point from the RTK positions, moved to the tick
        (:meth:`_Batch._gnss_distance`); an arbitrary offset per chain [m].
    dist_var : ndarray, shape (m,)
        Its variance [m²].
    dist_restart : ndarray, shape (m,), bool
        A new chain of positions starts at this tick (first fix, or a gap): the distance has a
        new offset.
    fix_age_s : ndarray, shape (m,)
        Age of the fix ``enu`` and ``attitude`` were moved to the tick from (``inf``: none yet)
        [s]; :mod:`estimator.dead_reckoning` carries the position past a stale one.
    force_lat : ndarray, shape (m,), or None
        Tick-mean lateral specific force as measured (IMU x axis) [m/s²]: with ``force_fwd``
        the mounting yaw's observation and correction (:mod:`estimator.mdsf.calibration`);
        None from a caller without one.
    lever_force_lat : ndarray, shape (m,), or None
        What the IMU's lever arm adds to the lateral force by the angular acceleration
        (:func:`_lever_force_lat`) [m/s²]: the lateral force at ``O`` is ``force_lat`` less it.
    lever_accel_fwd_mps2 : ndarray, shape (m,), or None
        What the IMU's height takes off the axle's tick-mean forward acceleration by the pitch
        acceleration, ``h0·(ωx(t) − ωx(t − Δt))/Δt`` (:meth:`_Batch._lever_accel_fwd`): the
        axle's is ``a1`` plus it; NaN where a rate at either end of the tick is unknown.
    lever_accel_fwd_var : ndarray, shape (m,), or None
        Its variance under the gyro's white noise [(m/s²)²].
    tilt_var : ndarray, shape (m, 2), or None
        Variance of the tilt track's pitch and roll at the tick, carried from their last fix
        by the gyro biases' uncertainty (:func:`~estimator.tilt.angle_var_after`): small with a
        receiver's attitude, growing through an outage with one antenna [rad²].
    gnss_age_span_s : ndarray, shape (m,), or None
        Mean age before the tick of the fixes averaged into ``z[:, VG]`` (NaN: none) [s]:
        where the GNSS clock learner takes the antenna's acceleration
        (:mod:`estimator.mdsf.calibration`).
    accel_span_end_s : ndarray, shape (m,), or None
        Where the tick-mean acceleration's span ends, relative to the tick [s]: the mean of
        point samples in ``(tick − dt, tick]`` is the acceleration at their mean instant
        ``tick + τ̄``, so their sum times ``dt`` integrates ``(tick − dt + e, tick + e]`` with
        ``e = τ̄ + dt/2`` (half a sample interval past the tick for a regular IMU; NaN: no
        sample).
    """

    stamp_ns: IntArray
    z: FloatArray
    gnss_ok: BoolArray
    gnss_var: FloatArray
    imu_ok: BoolArray
    accel_var: FloatArray
    gyro_var: FloatArray
    force_fwd: FloatArray
    omega: FloatArray
    omega_std: FloatArray
    wheel_flags: npt.NDArray[np.int32]
    enu: FloatArray
    attitude: FloatArray
    dist_ok: BoolArray
    dist_m: FloatArray
    dist_var: FloatArray
    dist_restart: BoolArray
    fix_age_s: FloatArray
    force_lat: FloatArray | None = None
    lever_force_lat: FloatArray | None = None
    lever_accel_fwd_mps2: FloatArray | None = None
    lever_accel_fwd_var: FloatArray | None = None
    tilt_var: FloatArray | None = None
    gnss_age_span_s: FloatArray | None = None
    accel_span_end_s: FloatArray | None = None

    @property
    def m(self) -> int:
        return int(self.stamp_ns.shape[0])


@dataclass(slots=True)
class FleetTicks:
    """Due ticks of several vehicles, flat: vehicle ``i``'s rows are
    ``inputs[offsets[i] : offsets[i] + lengths[i]]``; vehicles by decreasing ``lengths``.

    Attributes
    ----------
    index : ndarray, shape (k,), int
        Position of each vehicle in the ``slots`` given to :meth:`FleetFrontEnd.assemble`.
    slots : ndarray, shape (k,), int
    lengths, offsets : ndarray, shape (k,), int
    inputs : TickInputs
        ``lengths.sum()`` rows.
    """

    index: IntArray
    slots: IntArray
    lengths: IntArray
    offsets: IntArray
    inputs: TickInputs


# ---------------------------------------------------------------------------------------------
# Array helpers
# ---------------------------------------------------------------------------------------------


def _asof(
    row_a: IntArray, key_a: npt.NDArray[np.generic], row_b: IntArray, key_b: npt.NDArray[np.generic]
) -> IntArray:
    """For each ``b``: index of the last ``a`` of the same row with ``key_a <= key_b``, else -1.

    "Last" in (row, key) order, ties in index order: what ``searchsorted(..., side="right") - 1``
    gives on each row's sorted keys. Integer keys with ``a`` already in (row, key) order (the
    front end's queues) take one ``searchsorted`` over combined ``row·span + key`` keys;
    otherwise one stable sort of both sets. Shape ``(len(row_b),)``.
    """
    na, nb = row_a.shape[0], row_b.shape[0]
    if nb == 0 or na == 0:
        return np.full(nb, -1, dtype=np.int64)
    combined = _combined_keys(row_a, key_a, row_b, key_b)
    if combined is not None:
        comp_a, comp_b = combined
        if na == 1 or bool((comp_a[1:] >= comp_a[:-1]).all()):
            i = np.searchsorted(comp_a, comp_b, side="right") - 1
            ok = i >= 0
            return np.where(ok & (row_a[np.maximum(i, 0)] == row_b), i, -1)
    rows = np.concatenate([row_a, row_b])
    keys = np.concatenate([key_a, key_b])
    kind = np.concatenate([np.zeros(na, dtype=np.int8), np.ones(nb, dtype=np.int8)])
    order = np.lexsort((kind, keys, rows))
    is_a = order < na
    last = np.maximum.accumulate(np.where(is_a, np.arange(order.shape[0]), -1))
    hit = np.where(last >= 0, order[np.maximum(last, 0)], -1)
    at_b = ~is_a
    out = np.empty(nb, dtype=np.int64)
    out[order[at_b] - na] = hit[at_b]
    ok = out >= 0
    ok[ok] = row_a[out[ok]] == row_b[ok]
    return np.where(ok, out, -1)


def _combined_keys(
    row_a: IntArray, key_a: npt.NDArray[np.generic], row_b: IntArray, key_b: npt.NDArray[np.generic]
) -> tuple[IntArray, IntArray] | None:
    """``row·span + (key − lo)`` of both sets (int64), ordered as ``(row, key)``; None for
    non-integer keys, negative rows or where it could overflow."""
    if key_a.dtype != np.int64 or key_b.dtype != np.int64:
        return None
    lo = min(int(key_a.min()), int(key_b.min()))
    span = max(int(key_a.max()), int(key_b.max())) - lo + 1
    n_rows = max(int(row_a.max()), int(row_b.max())) + 1
    if min(int(row_a.min()), int(row_b.min())) < 0 or n_rows * span >= 2**62:
        return None
    ka, kb = key_a.astype(np.int64, copy=False), key_b.astype(np.int64, copy=False)
    return row_a * span + (ka - lo), row_b * span + (kb - lo)


_PITCH_PRIOR_STD_RAD = 0.1
"""Pitch before any measurement: level ± 0.1 rad (6°; field slopes rarely pass 15°)."""
_VEL_PITCH_MIN_SPEED_MPS = 0.5
"""Horizontal speed from which the GNSS velocity's elevation is a pitch measurement."""
_COURSE_MIN_SPEED_MPS = 0.2
"""Horizontal speed of ``O`` from which the GNSS velocity's direction pulls the course."""
_FIRST_COURSE_LEVER_SHARE = 0.3
"""Largest lever-arm speed, over the antenna's, at which a course starts (``_course_update``)."""
_COURSE_LEVER_SHARE = 0.1
"""Lever-arm speed, over the antenna's (RMS each, :data:`_COURSE_LP_TAU_S`), from which
``O``'s course stands for the heading."""
_COURSE_LP_TAU_S = 2.0
"""Time constant [s] of what ``_TiltTrack._course_lowpass`` low-passes: longer than a sway's
period (0.3-3 Hz), so the lever arm's share is the sway's size, not its phase at a fix, and
the antenna's mean velocity is ``O``'s (the lever arm's moves it by its travel, centimetres,
over the time constant)."""
_COURSE_LP_SHARE = slice(0, 2)
"""Columns of the course low-pass (``course_lp``): the lever arm's and the antenna's squared
speeds [m²/s²]."""
_COURSE_LP_VEL = slice(2, 4)
"""Columns of the course low-pass: the antenna's east and north velocity [m/s]."""


def _pick(i: IntArray, values: FloatArray, otherwise: FloatArray) -> FloatArray:
    """``values[i]`` where ``i >= 0``, else ``otherwise`` (shapes of ``i``)."""
    if values.shape[0] == 0:
        return otherwise
    return np.where(i >= 0, values[np.maximum(i, 0)], otherwise)


def _ranks(group: IntArray) -> IntArray:
    """Position of each element within its run of equal ``group`` values (groups contiguous)."""
    n = group.shape[0]
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    new = np.ones(n, dtype=bool)
    new[1:] = group[1:] != group[:-1]
    index = np.arange(n)
    return index - np.maximum.accumulate(np.where(new, index, 0))  # minus its run's start


def _rank_passes(rank: IntArray) -> list[IntArray]:
    """Indices grouped by rank (0, 1, …), each group in index order."""
    if rank.shape[0] == 0:
        return []
    order = np.argsort(rank, kind="stable")
    bounds = np.cumsum(np.bincount(rank)).tolist()
    return [order[a:b] for a, b in zip([0, *bounds[:-1]], bounds, strict=True)]


def _fill_segments(
    n: int, lo: list[IntArray], values: list[FloatArray]
) -> tuple[IntArray, FloatArray]:
    """Segment of each of ``n`` elements from segment starts ``lo`` (segments tile 0..n) and
    the segments' value rows: returns ``(segment index per element, values (n_seg, k))``."""
    starts = np.concatenate(lo) if lo else np.zeros(0, dtype=np.int64)
    vals = np.concatenate(values) if values else np.zeros((0, 1))
    order = np.argsort(starts, kind="stable")
    seg = np.searchsorted(starts[order], np.arange(n), side="right") - 1
    return order[seg], vals


def _shift_in(x: npt.NDArray[Any], first: BoolArray, carried: npt.NDArray[Any]) -> npt.NDArray[Any]:
    """``x`` (k, ...) shifted down one row: each row's predecessor, ``carried`` at the rows
    ``first`` (a vehicle's first, taking what its previous call left)."""
    prev = np.empty_like(x)
    prev[1:] = x[:-1]
    prev[first] = carried
    return prev


def _sample_weights(
    t_ns: IntArray,
    T: IntArray,
    j: IntArray,
    span: tuple[IntArray, IntArray],
    prev_ns: IntArray,
    prev_ok: BoolArray,
) -> tuple[BoolArray, BoolArray, IntArray, IntArray, FloatArray]:
    """Where stamps ``t_ns`` fall among their rows' IMU samples, for a value at the stamps
    interpolated linearly (:func:`_lerp_at`).

    ``T`` the samples' times, ``span`` each stamp's row's ``(begin, end)`` in them, ``j`` the
    last sample at or before each stamp. A stamp before its row's first sample (a fix that
    arrives in the call after the samples before it) falls after the vehicle's newest
    sample integrated by the previous call, at ``prev_ns``, where ``prev_ok`` says its value
    is kept. Returns ``own`` (``j`` is the row's), ``carried`` (the kept sample stands in),
    the samples ``jj`` and ``nxt`` either side and the weight ``u`` of ``nxt`` (0 without
    one), each shape ``(len(t_ns),)``.
    """
    begin, end = span
    own = (j >= begin) & (j >= 0)
    carried = ~own & (prev_ns != _NONE_NS) & prev_ok
    last = T.shape[0] - 1
    jj = np.clip(j, 0, last)
    nxt = np.clip(np.where(own, j + 1, begin), 0, last)
    after = np.where(own, j + 1 < end, carried & (end > begin))
    t0 = np.where(own, T[jj], prev_ns)
    dt = np.where(after, (T[nxt] - t0).astype(np.float64), 1.0)
    u = np.where(after & (dt > 0), (t_ns - t0) / np.where(dt > 0, dt, 1.0), 0.0)
    return own, carried, jj, nxt, np.clip(u, 0.0, 1.0)


def _lerp_at(
    w: FloatArray,
    prev: FloatArray,
    weights: tuple[BoolArray, BoolArray, IntArray, IntArray, FloatArray],
) -> FloatArray:
    """Samples ``w`` interpolated at the stamps :func:`_sample_weights` placed (``prev`` the
    kept sample's value per stamp); 0 where the stamp has neither its row's sample nor a
    kept one."""
    own, carried, jj, nxt, u = weights
    w0 = np.where(own, w[jj], np.where(carried, prev, 0.0))
    return np.asarray(w0 + u * (w[nxt] - w0))


def _lever_share_lat(
    rate_y: FloatArray, rate_z: FloatArray, up_m: FloatArray, fwd_m: FloatArray
) -> FloatArray:
    """Lateral specific force the IMU's lever arm adds to ``O``'s, ``(ω̇ × p)_x = ω̇y·h0 −
    ω̇z·y`` (``p = (x, y, h0)`` the IMU's point), from the angular accelerations ``rate_y``,
    ``rate_z`` [rad/s²] (or their changes over a span [rad/s], giving the force times the span).

    A body swaying in roll on its axle shakes a raised IMU sideways by metres per second
    squared; whatever reads the lateral force at ``O`` (the mounting yaw's observation, the
    tilt track's accelerometer roll) takes this off. Arrays broadcast; returns their shape.
    """
    return np.asarray(rate_y * up_m - rate_z * fwd_m)


def _lever_force_lat(
    tick_id: IntArray,
    tau_s: FloatArray,
    rates: tuple[FloatArray, FloatArray],
    n: IntArray,
    lever_m: tuple[FloatArray, FloatArray],
) -> FloatArray:
    """Tick-mean lateral specific force the IMU's lever arm adds to ``O``'s
    (:func:`_lever_share_lat`), for the mounting yaw's observation (lateral force at ``O``,
    :mod:`estimator.mdsf.calibration`).

    The tick-mean angular accelerations are the slopes of a least-squares line through the
    window's gyro samples (0 with fewer than two): a tick's window alone, without the sample
    before it. ``rates`` are ``(ω_y, ω_z)`` per sample, ``lever_m`` ``(h0, y)`` per tick;
    returns shape ``(m,)``.
    """
    m = n.shape[0]
    s_t, s_tt = (np.bincount(tick_id, weights=tau_s**k, minlength=m) for k in (1, 2))
    det = n * s_tt - s_t * s_t
    ok = (n >= 2) & (det > 0)
    det = np.where(ok, det, 1.0)

    def slope(w: FloatArray) -> FloatArray:
        s_w = np.bincount(tick_id, weights=w, minlength=m)
        s_tw = np.bincount(tick_id, weights=tau_s * w, minlength=m)
        return np.where(ok, (n * s_tw - s_t * s_w) / det, 0.0)

    up_m, fwd_m = lever_m
    return _lever_share_lat(slope(rates[0]), slope(rates[1]), up_m, fwd_m)


# ---------------------------------------------------------------------------------------------
# The front end
# ---------------------------------------------------------------------------------------------


def _quadratic_first_row(
    tick_id: IntArray, tau_s: FloatArray, tau2: FloatArray, n: IntArray
) -> tuple[tuple[FloatArray, FloatArray, FloatArray], BoolArray]:
    """First row of ``M⁻¹``, ``M = [Στ^(i+j)]`` (3, 3) the moment matrix of each tick's samples
    (:func:`_rates_at_tick`), from its cofactors over the determinant; and where the fit is
    made (at least three samples, a finite row with ``(M⁻¹)[0, 0] > 0``; the row is 0
    elsewhere). ``tick_id``, ``tau_s``, ``tau2 = τ²``: (s,); ``n``: (m,) samples per tick;
    each row entry (m,)."""
    m = n.shape[0]
    powers = (tau_s, tau2, tau2 * tau_s, tau2 * tau2)  # τ¹…τ⁴ by products: pow() is ~100× dearer
    m0 = n.astype(np.float64)
    m1, m2, m3, m4 = (np.bincount(tick_id, weights=p, minlength=m) for p in powers)
    # first row of M⁻¹ (M symmetric): cofactors over the determinant
    c0, c1, c2 = m2 * m4 - m3 * m3, m2 * m3 - m1 * m4, m1 * m3 - m2 * m2
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        det = m0 * c0 + m1 * c1 + m2 * c2
        row = (c0 / det, c1 / det, c2 / det)
    fit = (n >= 3) & np.isfinite(row[0]) & np.isfinite(row[1]) & np.isfinite(row[2])
    fit &= row[0] > 0
    i0, i1, i2 = (np.where(fit, c, 0.0) for c in row)
    return (i0, i1, i2), fit


def _rates_at_tick(
    tick_id: IntArray,
    tau_s: FloatArray,
    rates: tuple[FloatArray, ...],
    means: list[FloatArray],
    n: IntArray,
) -> tuple[tuple[FloatArray, ...], FloatArray]:
    """Body rates at each tick's instant: a least-squares quadratic in ``τ`` (sample time −
    tick time) through the tick window's samples, evaluated at ``τ = 0``.

    The lever-arm terms (``h1·ωx``, ``h0·ωx``, ``x·ωz``) correct the speeds *at the tick*; the
    window's mean rate is half a window older, which under a body sway of a few hertz on a tall
    mast is off by about ``ω̇·dt/2`` (metres per second at the antenna). With the moment matrix
    ``M = [Στ^(i+j)]`` (3, 3) and ``r = [Στ^i·ω]`` the value at ``τ = 0`` is ``(M⁻¹·r)[0]``,
    its white-noise variance factor ``(M⁻¹)[0, 0]`` (``1/n`` for the mean, about 0.6 for ten
    samples); the first row of ``M⁻¹`` is taken from its cofactors (a batched LAPACK inverse
    costs ~0.5 µs a tick). A window of fewer than three samples keeps its mean.

    Parameters
    ----------
    tick_id : (s,) int — tick of each sample; tau_s : (s,) — sample time − tick time [s]
    rates : arrays (s,) — per-sample rates; means : arrays (m,) — their tick means
    n : (m,) int — samples per tick

    Returns
    -------
    (rates at the ticks, each (m,)), variance factor (m,) on one sample's noise variance
    """
    m = n.shape[0]
    tau2 = tau_s * tau_s
    (i0, i1, i2), fit = _quadratic_first_row(tick_id, tau_s, tau2, n)
    out = []
    for w, mean in zip(rates, means, strict=True):
        r0, r1, r2 = (
            np.bincount(tick_id, weights=x, minlength=m) for x in (w, tau_s * w, tau2 * w)
        )
        out.append(np.where(fit, i0 * r0 + i1 * r1 + i2 * r2, mean))
    factor = np.where(fit, i0, 1.0 / np.maximum(n, 1))
    return tuple(out), factor


_SLOT_ARRAYS: tuple[tuple[str, tuple[int, ...], Any], ...] = (
    ("next_tick_ns", (), _NONE_NS),
    ("tick_phase_ns", (), np.int64(0)),  # the grid is tick_phase_ns + k·tick_ns
    ("done_ns", (), _NONE_NS),  # last tick emitted
    ("last_imu_ns", (), _NONE_NS),  # newest IMU sample accepted
    ("last_imu_used_ns", (), _NONE_NS),  # newest IMU sample integrated
    ("last_rates", (2,), np.nan),  # its bias-corrected (ωx, ωz) [rad/s]
    ("last_raw_rates", (3,), np.nan),  # its measured (ωx, ωy, ωz) [rad/s]
    ("pitch_rad", (), 0.0),
    ("pitch_known", (), False),
    ("pitch_gyro_bias", (), 0.0),
    ("pitch_fix_ns", (), np.int64(0)),
    ("pitch_var", (), 0.0),
    ("pitch_cov_tb", (), 0.0),  # covariance of pitch and pitch-gyro bias
    ("pitch_var_b", (), 0.0),  # variance of the pitch-gyro bias
    # since the last fix: angle noise var, ∫rate·dt, ∫dt, samples, ∫f_y·dt
    ("pitch_acc", (len(PitchSum),), 0.0),
    ("pitch_still", (), False),  # the last fix was standing
    ("roll_rad", (), 0.0),  # roll track (pitch_kf_update with the roll measured)
    ("roll_known", (), False),  # the track has had a roll (GNSS or accelerometer)
    ("roll_gyro_bias", (), 0.0),
    ("roll_fix_ns", (), np.int64(0)),
    ("roll_cov", (3,), 0.0),  # covariance of roll and roll-gyro bias
    ("roll_acc", (len(RollSum),), 0.0),  # since the last fix
    ("yaw_rad", (), np.nan),
    ("yaw_gyro_bias", (), 0.0),
    ("yaw_fix_ns", (), np.int64(0)),
    # course of O for a receiver without heading: yaw rate integrated, pulled to the GNSS
    # velocity less the antenna's lever-arm velocity (_TiltTrack._course_update)
    ("course_rad", (), np.nan),
    ("course_fix_ns", (), np.int64(0)),  # last fix whose velocity pulled it
    ("course_gyro_bias", (), 0.0),  # yaw-gyro bias learnt against that course
    # low-passed at the fixes (_COURSE_LP_TAU_S): the squared horizontal speeds of the
    # antenna's lever arm and of the antenna, the antenna's east and north velocity
    ("course_lp", (4,), np.nan),
    ("hold", (10,), np.nan),  # latest GNSS row: stamp, e, n, u, ve, vn, vu, ψ, θ, φ
    ("has_frame", (), False),
    ("origin", (3,), np.nan),  # lat_deg, lon_deg, height_m of the ENU frame
    ("has_edges", (), False),
    ("has_direction", (), False),
    ("has_speeds", (), False),  # direct (CAN) wheel speeds held
    ("gnss_var_cfg", (), 0.0),
    ("accel_var_cfg", (), 0.0),
    ("gyro_var_cfg", (), 0.0),
    ("imu_fwd_m", (), 0.0),
    ("imu_up_m", (), 0.0),  # IMU height above O (h0)
    # the last tick built: the pitch rate at the end of its sample mean's span, that
    # instant, and the tick (the next tick's rate at its start: _Batch._lever_accel_fwd)
    ("pitch_rate_end", (), np.nan),
    ("pitch_rate_end_ns", (), _NONE_NS),
    ("pitch_rate_end_tick_ns", (), _NONE_NS),
    ("ant_fwd_m", (), 0.0),
    ("lone_std", (), 0.0),
    ("wheel_cfg", (), np.int64(0)),
    ("wheel_bank", (), np.int64(-1)),  # index in _banks of the trackers' bank; -1: unknown
    ("wheel_slot", (len(Wheel),), np.int64(0)),  # their slots in it (left, right)
    # after lost wheel data (WheelGap): ticks before this have no wheel speed (the fit's
    # first min_edges edges after the gap; _PENDING_NS until they came, _NONE_NS: none)
    ("wheel_resume_ns", (len(Wheel),), _NONE_NS),
    ("wheel_need", (len(Wheel),), np.int64(0)),  # edges still to come before that
    # ticks in (from, to] are due without the wheel data (WheelGap with until_ns): none
    # get a wheel speed (_NONE_NS: no such span)
    ("wheel_wait_from_ns", (), _NONE_NS),
    ("wheel_wait_to_ns", (), _NONE_NS),
    ("count", (len(COUNT_NAMES),), np.int64(0)),
    # last RTK-fixed position of the along-track distance chain: stamp, ENU, heading,
    # pitch, and the chain's distance there
    ("chain_ns", (), _NONE_NS),
    ("chain_enu", (3,), 0.0),
    ("chain_att", (2,), 0.0),
    ("chain_m", (), 0.0),
    ("chain_yaw_rad", (), 0.0),  # heading unwrapped along the chain
    ("chain_turn_rad", (), 0.0),  # Σ Δψ·cos θ·sin φ along the chain (∫ωx beyond θ)
    ("h1_m", (), 0.0),
    ("ant_x_m", (), 0.0),  # antenna's lateral offset from the IMU, x_a − x_i
    ("ant_lat_m", (), 0.0),  # antenna's lateral offset from O, x_a
    ("imu_lat_m", (), 0.0),  # IMU's lateral offset from O, x_i
    ("pos_var_cfg", (), 0.0),
)
"""Per-vehicle arrays of :class:`FleetFrontEnd` (name, shape of a slot's row, fill of a new
row), grown by :meth:`FleetFrontEnd._alloc`."""


class FleetFrontEnd:
    """Buffers the measurements of many vehicles (by slot) and builds their tick inputs.

    Parameters
    ----------
    config : MdsfConfig
    wheel : WheelSpeedConfig
        Wheel-speed settings (``teeth_per_rev`` comes from each vehicle's encoder).
    capacity : int
        Initial number of slots (grows as needed).
    """

    def __init__(self, config: MdsfConfig, wheel: WheelSpeedConfig, capacity: int = 16) -> None:
        self.config = config
        self.wheel = wheel
        self.product = config.mode is MdsfMode.PRODUCT
        self.tick_ns = config.tick_ns
        self.fit_wheels: Callable[[WheelBank, IntArray, IntArray], WheelSpeedResult]
        self.fit_wheels = WheelBank.query
        """Batched wheel-speed fit of encoder wheels in one bank
        (:meth:`~estimator.wheel_speed.WheelBank.query`)."""
        self._cap = 0
        self._seq = 0  # push counter: which measurement of a vehicle came first
        self.trackers: list[tuple[WheelTracker, ...]] = []  # (left, right); () if free
        # Banks that held the trackers of a whole wheel query (index: wheel_bank), and where:
        # the trackers stay there until the next gather_bank of them (in _wheels).
        self._banks: list[WheelBank] = []
        self.direct: list[DirectWheelSpeed | None] = []
        self._wheel_cfgs: list[WheelSpeedConfig] = []
        self._alloc(max(capacity, 1))
        # Pushed since the last check: IMU (slot, seq, t, accel, gyro); GNSS (slot, seq, stamp)
        # and the float record of _G_* columns.
        self._imu_new_slot: list[int] = []
        self._imu_new_seq: list[int] = []
        self._imu_new_t: list[IntArray] = []
        self._imu_new_f: list[FloatArray] = []
        self._imu_new_w: list[FloatArray] = []
        # Vehicles without a tick grid yet, and the first wheel data (seq, stamp) of such.
        self._gridless: set[int] = set()
        self._first_wheel: dict[int, tuple[int, int]] = {}
        self._gnss_new_id: list[int] = []  # slot, seq, stamp of each fix, flat
        self._gnss_new_val: list[float] = []  # the _G_* columns of each fix, flat
        # Checked and waiting for their tick, in push order.
        self._imu_slot = np.zeros(0, dtype=np.int64)
        self._imu_t = np.zeros(0, dtype=np.int64)
        self._imu_v = np.zeros((0, 5))  # forward specific force, ωx, ωz, ωy, lateral force
        self._gnss_slot = np.zeros(0, dtype=np.int64)
        self._gnss_t = np.zeros(0, dtype=np.int64)
        self._gnss_v = np.zeros((0, 11))

    # -- slots -------------------------------------------------------------------------------
    def _alloc(self, cap: int) -> None:
        """Grow every slot array (:data:`_SLOT_ARRAYS`) and slot list to ``cap`` slots."""
        old = self._cap
        for name, shape, fill in _SLOT_ARRAYS:
            grow_slot_array(self, name, cap, shape, fill)
        self.trackers.extend([()] * (cap - old))
        self.direct.extend([None] * (cap - old))
        self._cap = cap

    next_tick_ns: IntArray
    tick_phase_ns: IntArray
    done_ns: IntArray
    last_imu_ns: IntArray
    last_imu_used_ns: IntArray
    last_rates: FloatArray
    last_raw_rates: FloatArray
    pitch_rad: FloatArray
    pitch_known: BoolArray
    pitch_gyro_bias: FloatArray
    pitch_fix_ns: IntArray
    pitch_var: FloatArray
    pitch_cov_tb: FloatArray
    pitch_var_b: FloatArray
    pitch_acc: FloatArray
    pitch_still: BoolArray
    roll_rad: FloatArray
    roll_known: BoolArray
    roll_gyro_bias: FloatArray
    roll_fix_ns: IntArray
    roll_cov: FloatArray
    roll_acc: FloatArray
    yaw_rad: FloatArray
    yaw_gyro_bias: FloatArray
    yaw_fix_ns: IntArray
    course_rad: FloatArray
    course_fix_ns: IntArray
    course_gyro_bias: FloatArray
    course_lp: FloatArray
    hold: FloatArray
    has_frame: BoolArray
    origin: FloatArray
    has_edges: BoolArray
    has_direction: BoolArray
    has_speeds: BoolArray
    gnss_var_cfg: FloatArray
    accel_var_cfg: FloatArray
    gyro_var_cfg: FloatArray
    imu_fwd_m: FloatArray
    imu_up_m: FloatArray
    pitch_rate_end: FloatArray
    pitch_rate_end_ns: IntArray
    pitch_rate_end_tick_ns: IntArray
    ant_fwd_m: FloatArray
    lone_std: FloatArray
    wheel_cfg: IntArray
    wheel_bank: IntArray
    wheel_slot: IntArray
    wheel_resume_ns: IntArray
    wheel_need: IntArray
    wheel_wait_from_ns: IntArray
    wheel_wait_to_ns: IntArray
    count: IntArray
    chain_ns: IntArray
    chain_enu: FloatArray
    chain_att: FloatArray
    chain_m: FloatArray
    chain_yaw_rad: FloatArray
    chain_turn_rad: FloatArray
    h1_m: FloatArray
    ant_x_m: FloatArray
    ant_lat_m: FloatArray
    imu_lat_m: FloatArray
    pos_var_cfg: FloatArray

    def add(self, slot: int, vehicle: WheeledRearDriveConfig) -> None:
        """Start a vehicle in ``slot`` (fresh state)."""
        if slot >= self._cap:
            self._alloc(max(2 * self._cap, slot + 1))
        self._drop(slot)
        wcfg = self._add_wheels(slot, vehicle)
        for name in (
            "next_tick_ns",
            "done_ns",
            "last_imu_ns",
            "last_imu_used_ns",
            "pitch_rate_end_tick_ns",
        ):
            getattr(self, name)[slot] = _NONE_NS
        self.tick_phase_ns[slot] = 0
        self.last_rates[slot] = np.nan
        self.last_raw_rates[slot] = np.nan
        self._gridless.add(slot)
        self._reset_tilt(slot)
        self.hold[slot] = np.nan
        self.has_frame[slot] = False
        self.origin[slot] = np.nan
        self.has_edges[slot] = False
        self.has_speeds[slot] = False
        self._set_vehicle(slot, vehicle, wcfg)
        self.count[slot] = 0
        self._reset_chain(slot)

    def _add_wheels(self, slot: int, vehicle: WheeledRearDriveConfig) -> WheelSpeedConfig:
        """Fresh encoder trackers and direct-speed store for ``slot``, no wheel gap pending;
        returns the wheel settings with the vehicle's teeth."""
        wcfg = dataclasses.replace(self.wheel, teeth_per_rev=vehicle.encoder.teeth_per_rev)
        if wcfg not in self._wheel_cfgs:
            self._wheel_cfgs.append(wcfg)
        self.trackers[slot] = (WheelTracker(wcfg), WheelTracker(wcfg))
        self.wheel_bank[slot] = -1
        self.wheel_resume_ns[slot] = _NONE_NS
        self.wheel_need[slot] = 0
        self.wheel_wait_from_ns[slot] = self.wheel_wait_to_ns[slot] = _NONE_NS
        self.direct[slot] = DirectWheelSpeed(std_radps=0.01)
        self.has_direction[slot] = vehicle.encoder.has_direction
        return wcfg

    def _reset_tilt(self, slot: int) -> None:
        """The pitch, roll, yaw-bias and course tracks of ``slot`` back to their priors."""
        self.pitch_rad[slot] = 0.0
        self.pitch_known[slot] = False
        self.pitch_gyro_bias[slot] = 0.0
        self.pitch_fix_ns[slot] = 0
        self.pitch_var[slot] = _PITCH_PRIOR_STD_RAD**2  # unknown before a fix
        self.pitch_cov_tb[slot] = 0.0
        self.pitch_var_b[slot] = self.config.gyro_bias_std_radps**2
        self.pitch_acc[slot] = 0.0
        self.pitch_still[slot] = False
        self.roll_rad[slot] = 0.0
        self.roll_known[slot] = False
        self.roll_gyro_bias[slot] = 0.0
        self.roll_fix_ns[slot] = 0
        self.roll_cov[slot] = (_PITCH_PRIOR_STD_RAD**2, 0.0, self.config.gyro_bias_std_radps**2)
        self.roll_acc[slot] = 0.0
        self.yaw_rad[slot] = np.nan
        self.yaw_gyro_bias[slot] = 0.0
        self.yaw_fix_ns[slot] = 0
        self.course_rad[slot] = np.nan
        self.course_fix_ns[slot] = 0
        self.course_gyro_bias[slot] = 0.0
        self.course_lp[slot] = np.nan

    def _set_vehicle(
        self, slot: int, vehicle: WheeledRearDriveConfig, wcfg: WheelSpeedConfig
    ) -> None:
        """The vehicle's sensor noise, lever arms and wheel settings into ``slot``."""
        n = vehicle.noise
        self.gnss_var_cfg[slot] = n.gnss_vel_std_mps**2
        self.accel_var_cfg[slot] = n.accel_std_mps2**2
        self.gyro_var_cfg[slot] = n.gyro_std_radps**2
        self.imu_fwd_m[slot] = vehicle.geometry.imu_offset_m[1]
        self.imu_up_m[slot] = vehicle.geometry.h0_m
        self.ant_fwd_m[slot] = vehicle.geometry.antenna_offset_m[1]
        self.lone_std[slot] = 2 * np.pi / (vehicle.encoder.teeth_per_rev * 2.0)
        self.wheel_cfg[slot] = self._wheel_cfgs.index(wcfg)
        geo = vehicle.geometry
        self.h1_m[slot] = geo.h1_m
        self.ant_x_m[slot] = geo.antenna_offset_m[0] - geo.imu_offset_m[0]
        self.ant_lat_m[slot] = geo.antenna_offset_m[0]
        self.imu_lat_m[slot] = geo.imu_offset_m[0]
        self.pos_var_cfg[slot] = n.gnss_pos_std_m**2

    def _reset_chain(self, slot: int) -> None:
        """No along-track distance chain for ``slot`` (:meth:`_Batch._gnss_distance`)."""
        self.chain_ns[slot] = _NONE_NS
        self.chain_enu[slot] = 0.0
        self.chain_att[slot] = 0.0
        self.chain_m[slot] = 0.0
        self.chain_yaw_rad[slot] = 0.0
        self.chain_turn_rad[slot] = 0.0

    def align_ticks(self, slot: int, stamp_ns: int) -> None:
        """Put the vehicle's tick grid on ``stamp_ns + k·tick_ns`` (default: multiples of
        ``tick_ns``). Takes effect when the grid opens, at the vehicle's first measurement (or
        the first after :meth:`add`); a grid already open keeps its phase."""
        self.tick_phase_ns[slot] = int(stamp_ns) % self.tick_ns

    def release(self, slot: int) -> None:
        """Forget the vehicle in ``slot`` and whatever it has buffered."""
        self._drop(slot)
        self._gridless.discard(slot)
        self.trackers[slot] = ()
        self.wheel_bank[slot] = -1
        self.direct[slot] = None

    def _drop(self, slot: int) -> None:
        self._check_new()
        keep = self._imu_slot != slot
        self._imu_slot, self._imu_t, self._imu_v = (
            self._imu_slot[keep],
            self._imu_t[keep],
            self._imu_v[keep],
        )
        keep = self._gnss_slot != slot
        self._gnss_slot, self._gnss_t, self._gnss_v = (
            self._gnss_slot[keep],
            self._gnss_t[keep],
            self._gnss_v[keep],
        )

    def counts(self, slot: int) -> dict[str, int]:
        """The vehicle's skip counters (:data:`COUNT_NAMES`)."""
        self._check_new()
        return dict(zip(COUNT_NAMES, self.count[slot, : len(COUNT_NAMES)].tolist(), strict=True))

    def anchor(self, slot: int) -> tuple[float, float, float] | None:
        """``(lat_deg, lon_deg, height_m)`` of the vehicle's ENU frame; None before a fix."""
        if not self.has_frame[slot]:
            return None
        lat, lon, h = self.origin[slot]
        return (float(lat), float(lon), float(h))

    def set_anchor(self, slot: int, lat_deg: float, lon_deg: float, height_m: float) -> None:
        """Anchor the vehicle's ENU frame at a given origin instead of its first fix (a frame
        its earlier estimates were given in: see ``MdsfFleet.set_anchor``)."""
        origin = np.array([lat_deg, lon_deg, height_m], dtype=np.float64)
        if not (np.all(np.isfinite(origin)) and abs(lat_deg) <= 90.0 and abs(lon_deg) <= 180.0):
            raise ValueError(f"not a geodetic anchor: {(lat_deg, lon_deg, height_m)}")
        self.origin[slot] = origin
        self.has_frame[slot] = True

    # -- push --------------------------------------------------------------------------------
    def _first_seen(self, slot: int, stamp_ns: int) -> None:
        # Wheel data that may open the vehicle's tick grid (unless earlier IMU/GNSS did).
        if slot in self._gridless and slot not in self._first_wheel:
            self._seq += 1
            self._first_wheel[slot] = (self._seq, stamp_ns)

    def push(self, slot: int, m: Pushed) -> None:
        """Buffer one measurement of the vehicle in ``slot`` (sensor-time order)."""
        if isinstance(m, GnssSample):
            self._push_gnss(slot, m)
        elif isinstance(m, ImuBatch):
            self._push_imu(slot, m)
        elif isinstance(m, WheelEdges):
            self._push_edges(slot, m)
        elif isinstance(m, WheelGap):
            if m.until_ns is None:
                self._restart_wheels(slot)
            else:
                self._wait_wheels(slot, int(m.after_ns), int(m.until_ns))
        elif isinstance(m, WheelSpeeds):
            self._push_speeds(slot, m)

    def _push_gnss(self, slot: int, m: GnssSample) -> None:
        """Queue a fix as its id (slot, push order, stamp) and its ``_G_*`` record, unchecked
        (:meth:`_check_gnss`); a malformed one is counted."""
        if not isinstance(m.stamp_ns, int | np.integer) or len(m.vel_enu_mps) != 3:
            self.count[slot, _GNSS] += 1
            return
        self._seq += 1
        self._gnss_new_id.extend((slot, self._seq, int(m.stamp_ns)))
        self._gnss_new_val.extend(
            (
                *m.vel_enu_mps,
                m.heading_rad,
                m.pitch_rad,
                m.roll_rad,
                m.lat_deg,
                m.lon_deg,
                m.height_m,
                m.vel_std_mps,
                float(int(m.fix)),
            )
        )

    def _push_imu(self, slot: int, m: ImuBatch) -> None:
        """Queue a batch of IMU samples unchecked (:meth:`_check_imu`); a batch whose arrays
        differ in length is counted."""
        t = as_stamps(m.stamp_ns)
        f = as_rows(m.accel_mps2, 3)
        w = as_rows(m.gyro_radps, 3)
        if f.shape[0] != t.shape[0] or w.shape[0] != t.shape[0]:
            self.count[slot, _IMU] += t.shape[0]
            return
        if t.shape[0]:
            self._seq += 1
            self._imu_new_slot.append(slot)
            self._imu_new_seq.append(self._seq)
            self._imu_new_t.append(t)
            self._imu_new_f.append(f)
            self._imu_new_w.append(w)

    def _push_edges(self, slot: int, m: WheelEdges) -> None:
        """Encoder edges into the wheel's tracker (with their directions where the encoder has
        them); skipped edges counted, a wheel waiting after a gap counts them down."""
        t = as_stamps(m.stamp_ns)
        if t.shape[0] == 0:
            return
        try:
            tracker = self.trackers[slot][int(m.wheel)]
        except (IndexError, ValueError):
            self.count[slot, _EDGES] += t.shape[0]
            return
        d = None
        if m.direction is not None and self.has_direction[slot]:
            d = np.asarray(m.direction).reshape(-1)
            if d.shape[0] != t.shape[0]:
                d = None
        skipped = tracker.push(t, d)
        if skipped:
            self.count[slot, _EDGES] += skipped
        if self.wheel_need[slot, int(m.wheel)]:
            self._count_resume(slot, int(m.wheel), t)
        self.has_edges[slot] = True
        if slot in self._gridless:
            self._first_seen(slot, int(t[0]))

    def _push_speeds(self, slot: int, m: WheelSpeeds) -> None:
        """Direct (CAN) wheel speeds into the vehicle's store; skipped ones counted."""
        t = as_stamps(m.stamp_ns)
        direct = self.direct[slot]
        assert direct is not None
        before = direct.skipped
        direct.push(t, m.omega_radps)
        self.count[slot, _SPEEDS] += direct.skipped - before
        self.has_speeds[slot] = direct.has_data  # stays true once true
        if t.shape[0]:
            self._first_seen(slot, int(t[0]))

    def _restart_wheels(self, slot: int) -> None:
        """Start the vehicle's encoder fits afresh after lost wheel data (:class:`WheelGap`).

        The edges before the gap are dropped with their trackers (a fit across the gap would
        count its missing edges as wheel angle not turned, and the tooth calibration's phase is
        lost with them). No tick gets a wheel speed until each wheel's fit holds ``min_edges``
        edges after the gap (``wheel_resume_ns``): without edges a fresh tracker reads as a
        wheel standing still. The pipeline computes the ticks before the gap first.
        """
        wcfg = self._wheel_cfgs[int(self.wheel_cfg[slot])]
        self.trackers[slot] = (WheelTracker(wcfg), WheelTracker(wcfg))
        self.wheel_bank[slot] = -1
        self.wheel_resume_ns[slot] = _PENDING_NS
        self.wheel_need[slot] = wcfg.min_edges

    def _wait_wheels(self, slot: int, after_ns: int, until_ns: int) -> None:
        """Ticks in ``(after_ns, until_ns]`` are due without the wheel data: no wheel speed
        for them (a span not yet computed is widened)."""
        if self.wheel_wait_from_ns[slot] == _NONE_NS:
            self.wheel_wait_from_ns[slot] = after_ns
            self.wheel_wait_to_ns[slot] = until_ns
        else:
            self.wheel_wait_from_ns[slot] = min(int(self.wheel_wait_from_ns[slot]), after_ns)
            self.wheel_wait_to_ns[slot] = max(int(self.wheel_wait_to_ns[slot]), until_ns)

    def _count_resume(self, slot: int, wheel: int, t: IntArray) -> None:
        """Count edges ``t`` of a wheel waiting to resume after a gap; the stamp of the last
        one its fit needs ends the wait."""
        need = int(self.wheel_need[slot, wheel])
        if t.shape[0] >= need:
            self.wheel_resume_ns[slot, wheel] = t[need - 1]
            self.wheel_need[slot, wheel] = 0
        else:
            self.wheel_need[slot, wheel] = need - t.shape[0]

    # -- checks of what was pushed -----------------------------------------------------------
    def _check_new(self) -> None:
        """Check the IMU samples and GNSS fixes pushed since the last call, count the bad
        ones, queue the good ones and open the tick grid of vehicles seen for the first time."""
        seen: list[tuple[IntArray, IntArray, IntArray]] = []
        if self._imu_new_slot:
            seen.append(self._check_imu())
        if self._gnss_new_id:
            seen.append(self._check_gnss())
        if self._first_wheel:
            w = np.array([(k, q, t) for k, (q, t) in self._first_wheel.items()], dtype=np.int64)
            seen.append((w[:, 0], w[:, 1], w[:, 2]))
            self._first_wheel = {}
        if not seen:
            return
        slot = np.concatenate([s for s, _, _ in seen])
        seq = np.concatenate([q for _, q, _ in seen])
        stamp = np.concatenate([t for _, _, t in seen])
        new = self.next_tick_ns[slot] == _NONE_NS
        slot, seq, stamp = slot[new], seq[new], stamp[new]
        order = np.lexsort((seq, slot))
        slot, stamp = slot[order], stamp[order]
        first = np.ones(slot.shape[0], dtype=bool)
        first[1:] = slot[1:] != slot[:-1]
        tn = self.tick_ns
        opened, phase = slot[first], self.tick_phase_ns[slot[first]]
        self.next_tick_ns[opened] = phase - (-(stamp[first] - phase) // tn) * tn
        self._gridless.difference_update(opened.tolist())

    def _check_imu(self) -> tuple[IntArray, IntArray, IntArray]:
        """IMU: non-finite, not after the last accepted sample or the last tick, or not
        increasing within the batch → skipped. Returns (slot, seq, first stamp) of the
        batches that kept samples."""
        c_slot = np.array(self._imu_new_slot, dtype=np.int64)
        c_seq = np.array(self._imu_new_seq, dtype=np.int64)
        ts = self._imu_new_t
        lens = np.array([a.shape[0] for a in ts], dtype=np.int64)
        t = np.concatenate(ts)
        f = np.concatenate(self._imu_new_f)
        w = np.concatenate(self._imu_new_w)
        n_chunks = c_slot.shape[0]
        one_each = len(set(self._imu_new_slot)) == n_chunks  # one batch per vehicle
        self._imu_new_slot, self._imu_new_seq = [], []
        self._imu_new_t, self._imu_new_f, self._imu_new_w = [], [], []
        chunk = np.repeat(np.arange(n_chunks), lens)
        c_start = np.cumsum(lens) - lens
        # a NaN roll rate alone keeps the sample, read as no roll rate (the roll then moves
        # only with the yaw rate and the fixes)
        ok = np.isfinite(f[:, 1]) & np.isfinite(w[:, 0]) & np.isfinite(w[:, 2])
        ok &= t > self.done_ns[c_slot][chunk]
        inc = np.ones(t.shape[0], dtype=bool)
        inc[1:] = t[1:] > t[:-1]
        inc[c_start] = True
        ok &= inc
        self._imu_after_last(ok, t, c_slot, chunk, one_each)
        bad = ~ok
        if bad.any():
            self.count[:, _IMU] += np.bincount(c_slot[chunk[bad]], minlength=self._cap)[: self._cap]
        return self._queue_imu(ok, t, (f, w), (c_slot, c_seq, chunk))

    def _imu_after_last(
        self, ok: BoolArray, t: IntArray, c_slot: IntArray, chunk: IntArray, one_each: bool
    ) -> None:
        """Clear ``ok`` (shape ``(n,)``, in place) of samples ``t`` not after their vehicle's
        last accepted one, and move each vehicle's ``last_imu_ns`` to its newest kept sample.
        ``c_slot`` is each batch's slot, ``chunk`` (n,) each sample's batch."""
        n_chunks = c_slot.shape[0]
        # The floor "after the last accepted sample" chains the batches of one vehicle: one pass
        # per k-th batch of each vehicle in this lot (one pass when each vehicle sent one).
        if one_each:
            passes = [np.arange(t.shape[0])]
        else:
            by_slot = np.argsort(c_slot, kind="stable")
            rank = np.empty(n_chunks, dtype=np.int64)
            rank[by_slot] = _ranks(c_slot[by_slot])
            passes = _rank_passes(rank[chunk])
        for idx in passes:
            owner = c_slot[chunk[idx]]
            ok[idx] &= t[idx] > self.last_imu_ns[owner]
            kept = idx[ok[idx]]
            # last kept sample of each batch: the newest accepted stamp of its vehicle
            last = np.full(n_chunks, -1, dtype=np.int64)
            np.maximum.at(last, chunk[kept], kept)
            has = np.flatnonzero(last >= 0)
            self.last_imu_ns[c_slot[has]] = t[last[has]]

    def _queue_imu(
        self,
        ok: BoolArray,
        t: IntArray,
        fw: tuple[FloatArray, FloatArray],
        batches: tuple[IntArray, IntArray, IntArray],
    ) -> tuple[IntArray, IntArray, IntArray]:
        """Append the kept samples (``ok``; ``fw`` their forces and rates, (n, 3) each) to the
        checked queue as ``_imu_v``'s columns. ``batches`` is each batch's slot and push order
        and each sample's batch; returns (slot, seq, first kept stamp) of batches that kept
        samples."""
        f, w = fw
        c_slot, c_seq, chunk = batches
        n_chunks = c_slot.shape[0]
        keep = np.flatnonzero(ok)
        # a NaN lateral force alone keeps the sample too (no accelerometer roll from it)
        fk, wk = np.take(f, keep, axis=0), np.take(w, keep, axis=0)
        roll_rate = np.where(np.isfinite(wk[:, 1]), wk[:, 1], 0.0)
        vals = np.stack([fk[:, 1], wk[:, 0], wk[:, 2], roll_rate, fk[:, 0]], axis=1)
        slots = c_slot[chunk[keep]]
        self._imu_slot = np.concatenate([self._imu_slot, slots])
        self._imu_t = np.concatenate([self._imu_t, np.take(t, keep)])
        self._imu_v = np.concatenate([self._imu_v, vals])
        # first kept sample of each batch
        first = np.full(n_chunks, t.shape[0], dtype=np.int64)
        np.minimum.at(first, chunk[keep], keep)
        has = first < t.shape[0]
        return c_slot[has], c_seq[has], t[first[has]]

    def _check_gnss(self) -> tuple[IntArray, IntArray, IntArray]:
        """GNSS: stamped at or before the last tick emitted → skipped as late."""
        ids = np.array(self._gnss_new_id, dtype=np.int64).reshape(-1, 3)
        vals = np.array(self._gnss_new_val, dtype=np.float64).reshape(-1, 11)
        self._gnss_new_id = []
        self._gnss_new_val = []
        slot, seq, stamp = ids[:, 0], ids[:, 1], ids[:, 2]
        done = self.done_ns[slot]
        late = (done != _NONE_NS) & (stamp <= done)
        if late.any():
            self.count[:, _LATE] += np.bincount(slot[late], minlength=self._cap)[: self._cap]
        ok = ~late
        self._gnss_slot = np.concatenate([self._gnss_slot, slot[ok]])
        self._gnss_t = np.concatenate([self._gnss_t, stamp[ok]])
        self._gnss_v = np.concatenate([self._gnss_v, vals[ok]])
        return slot[ok], seq[ok], stamp[ok]

    # -- tick assembly -----------------------------------------------------------------------
    def assemble(self, slots: IntArray, until_ns: IntArray) -> FleetTicks | None:
        """Tick inputs of every vehicle in ``slots`` (distinct) with ticks due at ``until_ns``.

        A vehicle's ticks are due from its next tick up to ``until_ns``; each tick uses only
        measurements stamped at or before it. Returns None when no vehicle has a due tick.
        """
        self._check_new()
        slots = np.asarray(slots, dtype=np.int64)
        until_ns = np.asarray(until_ns, dtype=np.int64)
        nxt = self.next_tick_ns[slots]
        cand = np.flatnonzero((nxt != _NONE_NS) & (until_ns >= nxt))
        if cand.size == 0:
            return None
        tn = self.tick_ns
        m_all = (until_ns[cand] - nxt[cand]) // tn + 1
        order = np.argsort(-m_all, kind="stable")
        index = cand[order]
        v = _Batch(self, slots[index], nxt[index], m_all[order])
        self.next_tick_ns[v.slots] = v.t_end + tn
        self.done_ns[v.slots] = v.t_end
        inputs = v.build()
        return FleetTicks(index, v.slots, v.m, v.offsets, inputs)


class _ImuTicks(NamedTuple):
    """The IMU's part of one assembly's tick inputs (:meth:`_Batch._imu_ticks`), named as in
    :class:`TickInputs`: each shape ``(m,)`` but ``z`` (m, 4)."""

    z: FloatArray
    imu_ok: BoolArray
    accel_var: FloatArray
    gyro_var: FloatArray
    force_fwd: FloatArray
    force_lat: FloatArray
    lever_force_lat: FloatArray
    lever_accel_fwd_mps2: FloatArray
    lever_accel_fwd_var: FloatArray
    accel_span_end_s: FloatArray


class _Batch:
    """One assembly: the due vehicles (rows, in output order), their ticks, samples, fixes."""

    def __init__(self, fe: FleetFrontEnd, slots: IntArray, first: IntArray, m: IntArray) -> None:
        self.fe = fe
        self.config = fe.config
        self.product = fe.product
        tn = fe.tick_ns
        self.slots = slots
        self.m = m
        n_rows = slots.shape[0]
        self.n_rows = n_rows
        self.first = first
        self.t_end = first + (m - 1) * tn
        self.offsets = np.cumsum(m) - m
        self.n_ticks = int(m.sum())
        self.tick_row = np.repeat(np.arange(n_rows), m)
        self.ticks = first[self.tick_row] + tn * (
            np.arange(self.n_ticks) - self.offsets[self.tick_row]
        )
        self.row_of_slot = np.full(fe._cap, -1, dtype=np.int64)
        self.row_of_slot[slots] = np.arange(n_rows)
        self._fix_of_sample_cache: IntArray | None = None
        self._take_imu()
        self._take_gnss()

    # -- what this assembly uses -------------------------------------------------------------
    def _take_imu(self) -> None:
        """IMU samples of the due vehicles up to their last tick, grouped by row."""
        fe = self.fe
        row = self.row_of_slot[fe._imu_slot]
        use = row >= 0
        use[use] = fe._imu_t[use] <= self.t_end[row[use]]
        idx = np.flatnonzero(use)
        idx = idx[np.argsort(row[idx], kind="stable")]
        # np.take / np.compress: the same gathers at a third of the cost of indexing
        self.T = np.take(fe._imu_t, idx)
        vals = np.take(fe._imu_v, idx, axis=0)
        self.fy, self.wx, self.wz, self.wy, self.fx = (vals[:, c] for c in range(5))
        self.s_row = np.take(row, idx)
        keep = ~use
        fe._imu_slot, fe._imu_t = np.compress(keep, fe._imu_slot), np.compress(keep, fe._imu_t)
        fe._imu_v = np.compress(keep, fe._imu_v, axis=0)
        self.n_s = np.bincount(self.s_row, minlength=self.n_rows)
        self.s_begin = np.cumsum(self.n_s) - self.n_s  # first sample of each row
        self.s_end = self.s_begin + self.n_s

    def _take_gnss(self) -> None:
        """GNSS fixes of the due vehicles in push order while stamped at or before the last
        tick (a later-stamped fix waits, with everything pushed after it)."""
        fe = self.fe
        row = self.row_of_slot[fe._gnss_slot]
        mine = row >= 0
        after = np.zeros(row.shape[0], dtype=bool)
        after[mine] = fe._gnss_t[mine] > self.t_end[row[mine]]
        # the first fix of each vehicle stamped after its last tick (queue in push order)
        stop = np.full(self.n_rows, row.shape[0], dtype=np.int64)
        np.minimum.at(stop, row[after], np.flatnonzero(after))
        take = mine & (np.arange(row.shape[0]) < stop[row])
        idx = np.flatnonzero(take)
        idx = idx[np.argsort(row[idx], kind="stable")]
        self.g_row = row[idx]
        self.g_t = fe._gnss_t[idx]
        g = np.take(fe._gnss_v, idx, axis=0)
        keep = ~take
        fe._gnss_slot, fe._gnss_t = np.compress(keep, fe._gnss_slot), np.compress(keep, fe._gnss_t)
        fe._gnss_v = np.compress(keep, fe._gnss_v, axis=0)
        self.g_rank = _ranks(self.g_row)
        ve, vn = g[:, _G_VE], g[:, _G_VN]
        fix_ok = g[:, _G_FIX] != float(GnssFix.NONE)
        v3 = g[:, _G_VE : _G_VU + 1]
        self.g_vel_ok = np.isfinite(v3).all(axis=1) & fix_ok & (np.abs(v3) < 200).all(axis=1)
        bad = ~self.g_vel_ok
        if bad.any():
            fe.count[:, _GNSS] += np.bincount(self.slots[self.g_row[bad]], minlength=fe._cap)[
                : fe._cap
            ]
        self.g = g
        self.g_heading = np.where(np.isfinite(g[:, _G_HEAD]), g[:, _G_HEAD], np.arctan2(ve, vn))
        self.g_pos_ok = np.isfinite(g[:, _G_LAT : _G_H + 1]).all(axis=1) & fix_ok
        std = g[:, _G_VSTD]
        with np.errstate(invalid="ignore"):
            good_std = np.isfinite(std) & (std > 0)
        self.g_var = np.where(good_std, std**2, fe.gnss_var_cfg[self.slots[self.g_row]])
        # samples at or before each fix (global index one past the last)
        last = _asof(self.s_row, self.T, self.g_row, self.g_t)
        self.g_j = np.where(last >= 0, last + 1, self.s_begin[self.g_row])

    # -- the build ---------------------------------------------------------------------------
    def build(self) -> TickInputs:
        """The inputs of every due tick, ``n_ticks`` rows (:class:`TickInputs`): the IMU's
        tick means and rates (:meth:`_imu_ticks`), the GNSS speed, the held position and
        attitude, the along-track distance and the wheel speeds, in that order (each step
        carries its vehicles' state to the next call)."""
        imu, (wz_mean, theta_tick, phi_tick) = self._imu_ticks()
        gnss_ok, gnss_var, gnss_age = self._gnss_speed(imu.z, imu.lever_accel_fwd_mps2)
        enu, att, fix_age_s = self._hold_outputs(wz_mean, theta_tick, phi_tick)
        dist_ok, dist_m, dist_var, dist_restart = self._gnss_distance()
        omega, omega_std, wflags = self._wheels()
        return TickInputs(
            stamp_ns=self.ticks,
            gnss_ok=gnss_ok,
            gnss_var=gnss_var,
            omega=omega,
            omega_std=omega_std,
            wheel_flags=wflags,
            enu=enu,
            attitude=att,
            dist_ok=dist_ok,
            dist_m=dist_m,
            dist_var=dist_var,
            dist_restart=dist_restart,
            fix_age_s=fix_age_s,
            tilt_var=self._tilt_var_at_ticks(),
            gnss_age_span_s=gnss_age,
            **imu._asdict(),
        )

    def _imu_ticks(self) -> tuple[_ImuTicks, tuple[FloatArray, FloatArray, FloatArray]]:
        """The IMU's part of the ticks (:class:`_ImuTicks`): the samples' tilt track and
        bias-corrected rates, binned to the ticks (a sample in ``(tick − tn, tick]``). Also
        returns what the held outputs use: the tick-mean ``ωz`` and the tilt track's pitch and
        roll at the ticks, shape ``(m,)`` each."""
        n = self._sample_dts()
        theta = self._pitch_track()
        a_fwd, wx, wz = self._imu_at_samples(theta)
        tick_id, inb, tau, n_imu = self._tick_bins()
        imu_ok = n_imu > 0
        means = self._tick_means(
            tick_id, n_imu, [x[inb] for x in (a_fwd, wx, wz, self.fy, self.fx)]
        )
        lever_lat = self._lever_lat_at_ticks(tick_id, tau, inb, n_imu)
        (wx_tick, wz_tick), rate_var_factor = _rates_at_tick(
            tick_id, tau, (wx[inb], wz[inb]), means[1:3], n_imu
        )
        at_tick = self._last_sample_of_tick(inb, n_imu)
        tilt_tick = [
            np.where(imu_ok, x[at_tick] if n else np.nan, np.nan) for x in (theta, self.phi)
        ]
        variances = self._tick_variances(n_imu, rate_var_factor)
        z = np.full((self.n_ticks, N_OBS_PAPER), np.nan)
        z[:, MdsfObs.A1] = means[0]
        z[:, MdsfObs.OMEGA_X] = wx_tick
        z[:, MdsfObs.OMEGA_Z] = wz_tick
        self._carry_rates(wx, wz)
        lever_fwd = self._lever_accel_fwd(tick_id, tau, wx[inb], means[1], n_imu, at_tick)
        span_end = self._tick_means(tick_id, n_imu, [tau])[0] + self.config.dt_s / 2
        span_end = np.where(imu_ok, span_end, np.nan)
        imu = _ImuTicks(z, imu_ok, *variances, means[3], means[4], lever_lat, *lever_fwd, span_end)
        return imu, (means[2], tilt_tick[0], tilt_tick[1])

    def _lever_lat_at_ticks(
        self, tick_id: IntArray, tau_s: FloatArray, inb: BoolArray, n_imu: IntArray
    ) -> FloatArray:
        """:func:`_lever_force_lat` of the binned samples (``tick_id``, ``tau_s``: (s,);
        ``inb``: (n,)) with each tick's vehicle's IMU height and forward offset, shape (m,)."""
        fe = self.fe
        slot_t = self.slots[self.tick_row]
        return _lever_force_lat(
            tick_id,
            tau_s,
            (self.wy[inb], self.wz[inb]),
            n_imu,
            (fe.imu_up_m[slot_t], fe.imu_fwd_m[slot_t]),
        )

    def _sample_dts(self) -> int:
        """Each sample's interval ``dts`` [s], shape ``(n,)``: from the previous sample, the
        first of a row from the vehicle's last integrated sample (0 with none), clipped to
        [0, 0.1]. Keeps the vehicles' last integrated stamp and raw rates of before this call
        (``prev_used_ns``, ``prev_raw_rates``) and moves them to this call's last sample.
        Returns ``n``."""
        fe = self.fe
        n = self.T.shape[0]
        self.prev_used_ns = fe.last_imu_used_ns[self.slots].copy()
        self.prev_raw_rates = fe.last_raw_rates[self.slots].copy()
        dts = np.empty(n)
        if n:
            dts[1:] = np.diff(self.T) * _NS
            nz = self.n_s > 0
            b = self.s_begin[nz]
            prev = fe.last_imu_used_ns[self.slots[nz]]
            prev = np.where(prev != _NONE_NS, prev, self.T[b])  # none yet: dt 0
            dts[b] = (self.T[b] - prev) * _NS
            dts = np.clip(dts, 0.0, 0.1)
            ends = self.s_end[nz] - 1
            fe.last_imu_used_ns[self.slots[nz]] = self.T[ends]
            fe.last_raw_rates[self.slots[nz]] = np.stack(
                [self.wx[ends], self.wy[ends], self.wz[ends]], axis=1
            )
        self.dts = dts
        self.begin_of = self.s_begin[self.s_row]
        return n

    def _imu_at_samples(self, theta: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Forward acceleration, ``ωx`` and ``ωz`` per sample, shape ``(n,)`` each. Product
        mode: the rates less the tracked gyro biases, the acceleration less gravity at the
        tracked pitch ``theta`` and with the IMU's forward lever ``(ωx² + ωz²)·y_imu``; paper
        mode: as measured."""
        wx, wz = self.wx, self.wz
        if self.product:
            bx = self._pitch_bias_at_samples()
            bz = self._yaw_track(theta)
            wx = wx - bx
            wz = wz - bz
            a_fwd = self.fy - GRAVITY_MPS2 * np.sin(theta)
            a_fwd = a_fwd + (wx**2 + wz**2) * self.fe.imu_fwd_m[self.slots[self.s_row]]
        else:
            a_fwd = self.fy
        return a_fwd, wx, wz

    def _tick_bins(self) -> tuple[IntArray, BoolArray, FloatArray, IntArray]:
        """Tick bins: a sample in ``(tick − tn, tick]``; samples before the first tick's window
        count toward no tick. Returns each binned sample's tick (s,), which samples are binned
        ``inb`` (n,), their time from their tick ``tau`` [s] (s,), and samples per tick (m,)."""
        tn = self.fe.tick_ns
        k = -((self.first[self.s_row] - self.T) // tn)
        inb = k >= 0
        tick_id = self.offsets[self.s_row[inb]] + k[inb]
        n_imu = np.bincount(tick_id, minlength=self.n_ticks)
        tau = (self.T[inb] - self.ticks[tick_id]) * _NS
        return tick_id, inb, tau, n_imu

    def _tick_means(
        self, tick_id: IntArray, n_imu: IntArray, values: list[FloatArray]
    ) -> list[FloatArray]:
        """Tick means of the binned samples' ``values`` (each (s,) → (m,); NaN: no sample)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return [np.bincount(tick_id, weights=x, minlength=self.n_ticks) / n_imu for x in values]

    def _last_sample_of_tick(self, inb: BoolArray, n_imu: IntArray) -> IntArray:
        """Index of the last sample in each tick's window (or before it), shape ``(m,)``."""
        rows = self.tick_row
        before = np.bincount(self.s_row[~inb], minlength=self.n_rows)
        cum = np.cumsum(n_imu)
        hi = cum - (cum - n_imu)[self.offsets][rows] + self.s_begin[rows] + before[rows]
        return np.maximum(hi - 1, 0)

    def _tick_variances(
        self, n_imu: IntArray, rate_var_factor: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """Variance of each tick's mean acceleration (with the gravity leak in product mode)
        and of its rates, shape ``(m,)`` each."""
        fe, cfg = self.fe, self.config
        slot_t = self.slots[self.tick_row]
        nf = np.maximum(n_imu, 1).astype(np.float64)
        accel_var = fe.accel_var_cfg[slot_t] / nf
        if self.product:
            # the gravity leak g·δθ as white accelerometer noise over the pitch error's
            # assumed correlation time (pitch_leak_corr_s)
            pv = self._pitch_var_at_ticks()
            accel_var = accel_var + (GRAVITY_MPS2**2) * pv * (cfg.pitch_leak_corr_s / cfg.dt_s)
        gyro_var = fe.gyro_var_cfg[slot_t] * rate_var_factor
        return accel_var, gyro_var

    def _carry_rates(self, wx: FloatArray, wz: FloatArray) -> None:
        """Keep the bias-corrected rates ``rates_bc`` and the vehicles' last ones of before this
        call (``prev_rates``); move those to this call's last sample."""
        fe = self.fe
        self.rates_bc = (wx, wz)
        self.prev_rates = fe.last_rates[self.slots].copy()
        if self.T.shape[0]:
            nz = self.n_s > 0
            last = self.s_end[nz] - 1
            fe.last_rates[self.slots[nz]] = np.stack([wx[last], wz[last]], axis=1)

    def _lever_accel_fwd(
        self,
        tick_id: IntArray,
        tau_s: FloatArray,
        wx: FloatArray,
        wx_mean: FloatArray,
        n_imu: IntArray,
        at_tick: IntArray,
    ) -> tuple[FloatArray, FloatArray]:
        """What the IMU's height ``h0`` takes off the axle's tick-mean forward acceleration,
        shape ``(n_ticks,)`` [m/s²]: eq. (3) differentiated and averaged over the tick,

            ā0 = ā1 + h0·(ωx(t_e) − ωx(t_s))/(t_e − t_s)

        exact for a rigid body (``∫ω̇x dt`` is the change of the rate). ``ā1`` is a mean of
        samples, each standing for its own sample interval, so its span ends half an interval
        past the window's last sample: ``ωx(t_e)`` is the window's quadratic (as in
        :func:`_rates_at_tick`) evaluated there, and ``t_s`` the previous tick's ``t_e`` with
        its rate, carried per slot across assemblies. Under a body sway of a few hertz
        ``h0·ω̇x`` is metres per second squared. The centripetal term ``ωy·ωz·h0`` is left out
        (hundredths of m/s² under the simulator's sway). NaN where a rate is unknown (a tick
        without IMU samples, or after one, a vehicle's first tick). Also returns its variance
        under the gyro's white noise, both ends' taken as this window's end's (about
        ``(h0·σ_g·1.1/Δt)²``: 0.07 m/s² in std for 5 mrad/s a sample on a 1.2 m IMU).
        """
        fe = self.fe
        has = n_imu > 0
        tau_e = np.zeros(self.n_ticks)
        if self.T.shape[0]:
            last_s = (self.T[at_tick] - self.ticks) * _NS + 0.5 * self.dts[at_tick]
            tau_e = np.where(has, last_s, 0.0)
        (wx_e,), var_factor = _rates_at_tick(
            tick_id, tau_s - tau_e[tick_id], (wx,), [wx_mean], n_imu
        )
        wx_e = np.where(has, wx_e, np.nan)
        end_ns = self.ticks + np.round(tau_e * 1e9).astype(np.int64)
        prev, prev_ns = self._previous_rate_end(wx_e, end_ns)
        s = self.slots
        span_s = (end_ns - prev_ns) * _NS
        h0 = fe.imu_up_m[s[self.tick_row]]
        with np.errstate(invalid="ignore", divide="ignore"):
            lever = np.where(span_s > 0, h0 * (wx_e - prev) / span_s, np.nan)
            var = 2.0 * var_factor * fe.gyro_var_cfg[s[self.tick_row]] * (h0 / span_s) ** 2
        return np.asarray(lever), np.asarray(var)

    def _previous_rate_end(self, wx_e: FloatArray, end_ns: IntArray) -> tuple[FloatArray, IntArray]:
        """The pitch rate ``wx_e`` at each tick's span end ``end_ns`` (both (m,)) shifted by
        one tick: each tick's start. A vehicle's first tick takes the one carried from its
        previous call (NaN unless that was the tick before); this call's last is carried on."""
        fe, tn = self.fe, self.fe.tick_ns
        prev, prev_ns = np.empty_like(wx_e), np.empty_like(end_ns)
        prev[1:], prev_ns[1:] = wx_e[:-1], end_ns[:-1]
        s, first = self.slots, self.offsets
        carried = fe.pitch_rate_end_tick_ns[s] == self.first - tn
        prev[first] = np.where(carried, fe.pitch_rate_end[s], np.nan)
        prev_ns[first] = fe.pitch_rate_end_ns[s]
        last = first + self.m - 1
        fe.pitch_rate_end[s] = wx_e[last]
        fe.pitch_rate_end_ns[s] = end_ns[last]
        fe.pitch_rate_end_tick_ns[s] = self.ticks[last]
        return prev, prev_ns

    def _between_fixes(
        self,
        passes: list[IntArray],
        end_segment: Callable[[IntArray, IntArray], FloatArray],
        at_fix: Callable[[IntArray, IntArray], None],
    ) -> FloatArray:
        """Run a track that integrates the IMU samples between GNSS fixes, for all rows.

        For each pass (the k-th fix of each row that has one: fix indices ``fi``), the samples
        of those rows up to the fix (``g_j``) end a segment: ``end_segment(rows, j)`` returns
        the parameters the segment was integrated with, shape ``(len(rows), p)``, and moves
        the track to sample ``j − 1``; then ``at_fix(fi, rows)`` applies the fix. The samples
        after the last fix end the last segments. Returns each sample's segment parameters,
        shape ``(n, p)``.
        """
        start = self.s_begin.copy()
        lo: list[IntArray] = []
        params: list[FloatArray] = []

        def close(r: IntArray, j: IntArray) -> None:
            lo.append(start[r])
            params.append(end_segment(r, j))
            start[r] = j

        for fi in passes:
            r, j = self.g_row[fi], self.g_j[fi]
            adv = j > start[r]
            if adv.any():
                close(r[adv], j[adv])
            at_fix(fi, r)
        rest = np.flatnonzero(self.s_end > start)
        if rest.size:
            close(rest, self.s_end[rest])
        n = self.T.shape[0]
        if not params:
            return np.zeros((n, 1))
        which, values = _fill_segments(n, lo, params)
        return np.take(values, which, axis=0)

    def _pitch_track(self) -> FloatArray:
        """Pitch at each IMU sample: the body rates integrated, corrected at each GNSS fix.

        Paper mode: the pitch rate ``ωx − b_x`` integrated, each GNSS pitch taken as it is
        (:func:`~estimator.tilt.pitch_fix_update`).

        Product mode: pitch and roll as one tilt ``z = θ + iφ`` (:mod:`estimator.tilt`: the
        linearised Euler kinematics solved between fixes in closed form over the samples'
        integrals), so a turn on a side slope turns the bank's roll into pitch. At each fix a
        Kalman filter of pitch and pitch-gyro bias takes the GNSS pitch
        (:func:`~estimator.tilt.pitch_kf_update`; a receiver without attitude: the velocity's
        elevation, or standing, where that is too noisy, gravity's share of the forward
        specific force ``sin θ = f̄_y/g`` with variance ``σ_a²/(n·g²) + pitch_std_rad²``), and
        the same update of roll and roll-gyro bias the GNSS roll, so the roll gyro's bias
        learnt while the receiver gives roll holds the roll through an outage. The angle noise
        either adds between fixes is the gyro's white noise summed over the samples
        (``Σ σ²·dt²``) and the other angle's error carried by the yaw rate
        (``Σ ωz²·var·2·attitude_tau_s·dt``); a standing fix after a standing one gives both
        biases the interval's mean rate. A receiver without attitude gives no roll: the
        lateral accelerometer's stands in (:meth:`_accel_roll`), as the velocity's elevation
        does for the pitch. Until a vehicle's first roll its roll is 0 and its pitch rate
        ``ωx − b_x``.

        Also sets ``g_vg`` (eq. (1) with the GNSS pitch, or the tracked pitch if the receiver
        gives none), the pitch variance, bias and pitch after each fix (``g_var_after``,
        ``g_bias_after``, ``g_theta_after``), the roll after each fix shrunk by its noise
        (``g_roll_after``, :func:`~estimator.tilt.shrunk_roll`) and the roll at each sample
        (``phi``, NaN where unknown). Returns the pitch, shape ``(n,)``. The steps are
        :class:`_TiltTrack`'s.
        """
        track = _TiltTrack(self)
        self.var_before = track.st.var.copy()
        self.tilt_before = track.st.tilt_cov()
        self.bias_before = track.st.bx.copy()
        nf = self.g_row.shape[0]
        self.g_vg = np.zeros(nf)
        self.g_var_after = np.empty(nf)
        self.g_bias_after = np.empty(nf)
        self.g_theta_after = np.empty(nf)
        self.g_roll_after = np.zeros(nf)
        self.g_tilt_after = (np.zeros((nf, 2, 3)), np.zeros((nf, 2), dtype=np.int64))
        q = self._between_fixes(_rank_passes(self.g_rank), track.end_segment, track.at_fix)
        track.st.put(self.fe, self.slots)
        theta, self.phi = track.at_samples(q)
        return theta

    def _fix_of_sample(self) -> IntArray:
        """Index of the latest fix at or before each IMU sample of the same row (−1: none)."""
        if self._fix_of_sample_cache is None:
            self._fix_of_sample_cache = _asof(self.g_row, self.g_t, self.s_row, self.T)
        return self._fix_of_sample_cache

    def _velocity_pitch(self, fi: IntArray, r: IntArray) -> tuple[FloatArray, FloatArray]:
        """Pitch from the GNSS velocity's elevation at fixes ``fi`` (rows ``r``) and its variance.

        The body moves along its forward axis, so ``tan θ = v_up/v_fwd``: ``v_fwd`` the
        horizontal velocity along the heading, ``v_up`` the vertical velocity less the antenna's
        lever-arm term ``ωx·y_a`` (latest gyro sample). Variance ``(k·σ_v/v_fwd)² + floor²``:
        ``σ_v`` the velocity noise (``NoiseConfig.gnss_vel_std_mps``), ``k``
        ``gnss_vertical_vel_factor``, the floor ``velocity_pitch_floor_rad`` (the body pitching
        on its tyres against its path). NaN below ``_VEL_PITCH_MIN_SPEED_MPS``. Far noisier than
        a receiver's attitude (3 cm/s at 2.5 m/s: 18 mrad against 5), it stands in for one that
        gives none (single antenna), where the pitch would otherwise be the gyro's integral.
        """
        fe, g, cfg = self.fe, self.g, self.config
        slot = self.slots[r]
        vel_ok = self.g_vel_ok[fi] & np.isfinite(self.g_heading[fi])
        psi = np.where(vel_ok, self.g_heading[fi], 0.0)
        ve, vn, vu = (np.where(vel_ok, g[fi, c], 0.0) for c in (_G_VE, _G_VN, _G_VU))
        v_fwd = ve * np.sin(psi) + vn * np.cos(psi)
        wx = self._rates_at_fix(fi, r)[0]
        v_up = vu - wx * fe.ant_fwd_m[slot]
        ok = vel_ok & np.isfinite(v_up) & (np.abs(v_fwd) >= _VEL_PITCH_MIN_SPEED_MPS)
        safe = np.where(ok, v_fwd, 1.0)
        pitch = np.where(ok, np.arctan(np.where(ok, v_up, 0.0) / safe), np.nan)
        var = (
            fe.gnss_var_cfg[slot] * cfg.gnss_vertical_vel_factor**2 / (safe * safe)
            + cfg.velocity_pitch_floor_rad**2
        )
        return pitch, var

    def _rates_at_fix(self, fi: IntArray, r: IntArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Measured body rates ``(ωx, ωy, ωz)`` at the stamps of fixes ``fi`` (rows ``r``),
        interpolated between the IMU samples around each (:func:`_sample_weights`: a fix
        before the batch's first sample reads the vehicle's newest sample of the previous
        call); 0 where the row has neither. Under a sway of 1-2 Hz on a mast of metres the
        rates are the lever arm's metres per second: a fix between two calls must not read
        them as 0. Each shape ``(len(fi),)``."""
        k = fi.shape[0]
        if not self.wx.shape[0]:
            return np.zeros(k), np.zeros(k), np.zeros(k)
        prev = self.prev_raw_rates[r]
        weights = _sample_weights(
            self.g_t[fi],
            self.T,
            self.g_j[fi] - 1,
            (self.s_begin[r], self.s_end[r]),
            self.prev_used_ns[r],
            np.isfinite(prev[:, 0]),
        )
        wx, wy, wz = (
            _lerp_at(w, prev[:, c], weights) for c, w in enumerate((self.wx, self.wy, self.wz))
        )
        return wx, wy, wz

    def _antenna_lever(
        self, fi: IntArray, r: IntArray, heading_rad: FloatArray, pitch_rad: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """ENU velocity ``(e, n, u)`` of the antenna about ``O`` at fixes ``fi`` (rows ``r``).

        ``ω × p_a`` in the body frame (X right, Y forward, Z up; ``p_a = (x_a, y_a, h1)``):
        across ``ωy·h1 − ωz·y_a``, along ``ωz·x_a − ωx·h1``, up ``ωx·y_a − ωy·x_a``
        (:mod:`estimator.sim.kinematics`), turned into ENU with ``heading_rad`` and
        ``pitch_rad`` (roll neglected), rates from :meth:`_rates_at_fix`. Each shape ``(k,)``.
        """
        fe = self.fe
        slot = self.slots[r]
        wx, wy, wz = self._rates_at_fix(fi, r)
        xa, ya, h1 = fe.ant_lat_m[slot], fe.ant_fwd_m[slot], fe.h1_m[slot]
        across, along, up = wy * h1 - wz * ya, wz * xa - wx * h1, wx * ya - wy * xa
        ct, stt = np.cos(pitch_rad), np.sin(pitch_rad)
        flat = along * ct - up * stt
        sp, cp = np.sin(heading_rad), np.cos(heading_rad)
        return flat * sp + across * cp, flat * cp - across * sp, along * stt + up * ct

    def _accel_roll(
        self, fi: IntArray, r: IntArray, theta: FloatArray, acc: FloatArray, racc: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """Roll from the lateral accelerometer over the interval before fixes ``fi`` (rows
        ``r``, pitch ``theta``, the interval's sums ``acc``, ``racc``) and its variance.

        The body's lateral specific force is its centripetal acceleration less gravity's
        share, ``f_x = −v·ωz − g·sin φ·cos θ`` (:mod:`estimator.sim.kinematics`), so
        ``sin φ = −(f̄_x + v·ω̄z)/(g·cos θ)`` with the interval's mean force at ``O`` (the
        IMU's lever-arm share ``h0·ω̇y − y·ω̇z`` off, its mean from the rates' change over the
        interval), mean yaw rate and the GNSS velocity along the heading ``v``. Variance
        ``σ_a²/(n·g²) + floor²`` (``n`` samples, the floor ``accel_roll_floor_rad``: body
        sway, side slip, the sensor's bias). NaN without a GNSS velocity or a lateral force.
        It stands in for the roll of a receiver that gives none, where the roll would
        otherwise stay 0 and the yaw rate of a turn on a side slope would drive the pitch off.
        """
        g = self.g
        t_fx = racc[:, RollSum.FORCE_LAT_TIME]
        ok = self.g_vel_ok[fi] & (t_fx > 0) & (acc[:, PitchSum.TIME] > 0)
        psi = np.where(np.isfinite(self.g_heading[fi]), self.g_heading[fi], 0.0)
        v = np.where(ok, g[fi, _G_VE] * np.sin(psi) + g[fi, _G_VN] * np.cos(psi), 0.0)
        f_x = racc[:, RollSum.FORCE_LAT] / np.where(ok, t_fx, 1.0)
        span = np.where(ok, acc[:, PitchSum.TIME], 1.0)
        w_z = racc[:, RollSum.YAW] / span
        # the IMU's lever arm's share, its interval mean from the rates' change over the
        # interval (exact, telescoping across ticks): read as gravity's share, a cab rolling
        # at 1-2 Hz would make the roll tens of degrees
        slot = self.slots[r]
        f_x = (
            f_x
            - _lever_share_lat(
                racc[:, RollSum.RATE_Y_CHANGE],
                racc[:, RollSum.RATE_Z_CHANGE],
                self.fe.imu_up_m[slot],
                self.fe.imu_fwd_m[slot],
            )
            / span
        )
        force = -(f_x + v * w_z) / np.cos(theta)
        ok &= np.abs(force) < GRAVITY_MPS2
        n = acc[:, PitchSum.SAMPLES]
        roll, var = self._gravity_angle(r, force, n, self.config.accel_roll_floor_rad)
        return np.where(ok, roll, np.nan), var

    def _gravity_angle(
        self, r: IntArray, force_mps2: FloatArray, n: FloatArray, floor_rad: float
    ) -> tuple[FloatArray, FloatArray]:
        """Angle whose sine is gravity's share ``force_mps2/g`` of a mean specific force over
        ``n`` samples (rows ``r``; clipped to ±π/2), and its variance ``σ_a²/(n·g²) + floor²``
        (``σ_a`` the vehicle's accelerometer noise)."""
        angle = np.arcsin(np.clip(force_mps2 / GRAVITY_MPS2, -1.0, 1.0))
        var = self.fe.accel_var_cfg[self.slots[r]] / (np.maximum(n, 1.0) * GRAVITY_MPS2**2)
        return angle, var + floor_rad**2

    def _pitch_bias_at_samples(self) -> FloatArray:
        """Pitch-gyro bias in force at each IMU sample (the latest fix at or before it)."""
        return _pick(self._fix_of_sample(), self.g_bias_after, self.bias_before[self.s_row])

    def _pitch_var_at_ticks(self) -> FloatArray:
        """Pitch variance in force at each tick (the latest fix at or before it)."""
        i = _asof(self.g_row, self.g_t, self.tick_row, self.ticks)
        return _pick(i, self.g_var_after, self.var_before[self.tick_row])

    def _tilt_var_at_ticks(self) -> FloatArray:
        """Pitch and roll variance at each tick, shape ``(n_ticks, 2)`` [rad²]: the tracks'
        covariance after the latest fix at or before the tick (or the batch's start),
        carried to the tick (:func:`~estimator.tilt.angle_var_after`)."""
        i = _asof(self.g_row, self.g_t, self.tick_row, self.ticks)
        cov_b = self.tilt_before[0][self.tick_row]
        fix_b = self.tilt_before[1][self.tick_row]
        cov_a, fix_a = self.g_tilt_after
        if cov_a.shape[0]:
            j = np.maximum(i, 0)
            cov_b = np.where((i >= 0)[:, None, None], cov_a[j], cov_b)
            fix_b = np.where((i >= 0)[:, None], fix_a[j], fix_b)
        known = fix_b != _NONE_NS
        gap = np.where(known, np.maximum((self.ticks[:, None] - fix_b) * _NS, 0.0), 0.0)
        walk = self.config.gyro_bias_walk_radps_per_sqrt_s
        return angle_var_after(cov_b.reshape(-1, 3), gap.ravel(), walk).reshape(-1, 2)

    def _yaw_track(self, theta: FloatArray) -> FloatArray:
        """Yaw-gyro bias in force at each IMU sample, learnt against the GNSS heading.

        Heading is integrated from the yaw rate (``ψ̇ = −(ωz − b_z)/cos θ``) and pulled to each
        GNSS heading (:func:`~estimator.tilt.yaw_fix_update`). Returns shape ``(n,)``.
        """
        fe, cfg = self.fe, self.config
        s = self.slots
        cosf = np.maximum(np.cos(theta), 0.5)
        cr = seg_cumsum(-self.wz / cosf * self.dts, self.begin_of)
        ct = seg_cumsum(self.dts / cosf, self.begin_of)
        psi = fe.yaw_rad[s]  # copies (s is an index array)
        bias = fe.yaw_gyro_bias[s]
        fix_ns = fe.yaw_fix_ns[s]
        base_r = np.zeros(self.n_rows)
        base_t = np.zeros(self.n_rows)
        heads = self.g[:, _G_HEAD]

        def end_segment(r: IntArray, j: IntArray) -> FloatArray:
            used = bias[r][:, None]
            step = (cr[j - 1] - base_r[r]) + bias[r] * (ct[j - 1] - base_t[r])
            psi[r] = np.where(np.isfinite(psi[r]), psi[r] + step, psi[r])
            base_r[r], base_t[r] = cr[j - 1], ct[j - 1]
            return used

        def at_fix(fi: IntArray, r: IntArray) -> None:
            psi[r], bias[r], fix_ns[r] = yaw_fix_update(
                psi[r], bias[r], fix_ns[r], heads[fi], self.g_t[fi], cfg
            )

        with_head = np.flatnonzero(np.isfinite(heads))  # fixes without a heading: no update
        passes = [with_head[p] for p in _rank_passes(_ranks(self.g_row[with_head]))]
        b = self._between_fixes(passes, end_segment, at_fix)
        fe.yaw_rad[s] = psi
        fe.yaw_gyro_bias[s] = bias
        fe.yaw_fix_ns[s] = fix_ns
        return np.asarray(b[:, 0])

    def _gnss_speed(
        self, z: FloatArray, lever_fwd: FloatArray
    ) -> tuple[BoolArray, FloatArray, FloatArray]:
        """GNSS speed per tick into ``z[:, VG]``: eq. (1) moved to the tick and averaged
        (product), or the latest fix (paper). Moved with the axle's tick-mean acceleration
        ``ā1 + lever_fwd`` (``lever_fwd`` (n_ticks,), :meth:`_lever_accel_fwd`; ``ā1`` where
        it is NaN) and the lever change of the antenna about the axle at the fix's instant
        (:meth:`_lever_change`). Returns ``(gnss_ok, gnss_var, age)``, shape ``(n_ticks,)``,
        ``age`` the mean age of the tick's fixes before it (the latest's in paper mode; NaN:
        none) [s]."""
        fe = self.fe
        tn = fe.tick_ns
        n_ticks = self.n_ticks
        gnss_ok = np.zeros(n_ticks, dtype=bool)
        gnss_var = fe.gnss_var_cfg[self.slots[self.tick_row]].copy()
        age = np.full(n_ticks, np.nan)
        if self.g_row.shape[0] == 0:
            return gnss_ok, gnss_var, age
        # the tick whose window holds the fix
        j = np.maximum(-((self.first[self.g_row] - self.g_t) // tn), 0)
        tid = self.offsets[self.g_row] + j
        inside = self.g_vel_ok
        fix_age = (self.ticks[tid] - self.g_t) * _NS
        if self.product:
            axle = np.isfinite(lever_fwd[tid])
            a_t = nan_to_num(z[tid, MdsfObs.A1]) + np.where(axle, lever_fwd[tid], 0.0)
            vg_al = self.g_vg + a_t * (self.ticks[tid] - self.g_t) * _NS
            vg_al = vg_al + self._lever_change(tid, z, axle)
            ti = tid[inside]
            cnt = np.bincount(ti, minlength=n_ticks)
            s_vg = np.bincount(ti, weights=vg_al[inside], minlength=n_ticks)
            s_var = np.bincount(ti, weights=self.g_var[inside], minlength=n_ticks)
            has = cnt > 0
            s_age = np.bincount(ti, weights=fix_age[inside], minlength=n_ticks)
            z[has, MdsfObs.VG] = s_vg[has] / cnt[has]
            gnss_var[has] = s_var[has] / cnt[has] ** 2
            age[has] = s_age[has] / cnt[has]
            gnss_ok = has
        else:
            ti = tid[inside]
            z[ti, MdsfObs.VG] = self.g_vg[inside]  # later fixes overwrite: the latest wins
            gnss_var[ti] = self.g_var[inside]
            age[ti] = fix_age[inside]
            gnss_ok[ti] = True
        return gnss_ok, gnss_var, age

    def _lever_change(self, tid: IntArray, z: FloatArray, axle: BoolArray) -> FloatArray:
        """Change of the antenna's lever-arm terms from each fix's instant to its tick,
        ``−h·(ωx(tick) − ωx(t_g)) + (x_a − x_i)·(ωz(tick) − ωz(t_g))``, shape (fixes,):
        eq. (2) at the tick, not at the fix. ``h`` is the mast ``h1``, or ``h0 + h1`` where
        ``axle`` (fixes,) says the speed is moved with the axle's acceleration (eq. (3): the
        IMU's own sway then moves here, exactly). The rates at the fix
        (:meth:`_rates_at_fix_instant`); 0 where there are none, or the tick has no rate."""
        wx_g, wz_g, has = self._rates_at_fix_instant()
        if wx_g.shape[0] == 0 or self.rates_bc[0].shape[0] == 0:
            return np.zeros(tid.shape[0])
        d_wx = nan_to_num(z[tid, MdsfObs.OMEGA_X] - wx_g)
        d_wz = nan_to_num(z[tid, MdsfObs.OMEGA_Z] - wz_g)
        s = self.slots[self.g_row]
        up = self.fe.h1_m[s] + np.where(axle, self.fe.imu_up_m[s], 0.0)
        change = -up * d_wx + self.fe.ant_x_m[s] * d_wz
        return np.where(has, change, 0.0)

    def _rates_at_fix_instant(self) -> tuple[FloatArray, FloatArray, BoolArray]:
        """Bias-corrected ``(ωx, ωz)`` at each fix's stamp, interpolated between the IMU
        samples around it (:func:`_sample_weights`: before the batch's first sample, the
        vehicle's newest integrated one, carried). Under a sway of a few hertz a sample's
        10 ms is tenths of a metre per second on a tall mast. Returns the rates and where they
        are known (the row has samples in the batch: the tick has a rate), each (fixes,)."""
        wx, wz = self.rates_bc
        nf = self.g_row.shape[0]
        if wx.shape[0] == 0:
            return np.zeros(nf), np.zeros(nf), np.zeros(nf, dtype=bool)
        row = self.g_row
        begin, end = self.s_begin[row], self.s_end[row]
        prev = self.prev_rates[row]
        weights = _sample_weights(
            self.g_t,
            self.T,
            self.g_j - 1,
            (begin, end),
            self.prev_used_ns[row],
            np.isfinite(prev[:, 0]),
        )
        own, carried = weights[0], weights[1]
        wx_g, wz_g = (_lerp_at(w, prev[:, c], weights) for c, w in enumerate((wx, wz)))
        return wx_g, wz_g, own | (carried & (end > begin))

    def _gnss_distance(self) -> tuple[BoolArray, FloatArray, FloatArray, BoolArray]:
        """Along-track distance of the IMU point from RTK-fixed positions, per tick.

        Eq. (1) integrated: between consecutive RTK-fixed positions ``p`` of a vehicle the
        distance grows by ``(p_k − p_{k−1})·u`` with ``u = [sinψ·cosθ, cosψ·cosθ, sinθ]`` the
        body's forward axis at the mid heading and pitch of the two fixes (the GNSS speed's
        projection, eq. (1), applied to the displacement). The sum telescopes while ``u``
        barely turns, so each distance carries about one position's noise and no random walk:
        a speed reference over seconds with centimetre noise, where the Doppler speed has
        percent noise. The antenna's distance differs from the IMU point's by the integral of
        the lever-arm terms of the ``Vg`` row, ``−h1·ωx + (x_a − x_i)·ωz``, with
        ``∫ωx = θ + Σ Δψ·cos θ·sin φ`` (``ωx = θ̇·cos φ + ψ̇·cos θ·sin φ``: a turn on a side
        slope turns the antenna about the body's X axis) and ``∫ωz = −ψ``:
        ``D_imu = D_ant + h1·(θ + Σ Δψ·cos θ·sin φ) + (x_a − x_i)·ψ`` (``ψ`` unwrapped along
        the chain, ``φ`` the roll track; constant parts fall into the chain's offset). A fix
        taken more than ``gnss_distance_gap_s`` after the chain's last (outage, float spell,
        start) starts a new chain with a new offset (``dist_restart``). Each tick takes the
        latest fix in its window, moved to the tick with that fix's speed (eq. (1)). Product
        mode only.

        Returns ``(dist_ok, dist_m, dist_var, dist_restart)``, shape ``(n_ticks,)``.
        """
        n_ticks = self.n_ticks
        ok = np.zeros(n_ticks, dtype=bool)
        dist = np.full(n_ticks, np.nan)
        var = np.zeros(n_ticks)
        restart = np.zeros(n_ticks, dtype=bool)
        idx = self._distance_fixes()
        if idx.size == 0:
            return ok, dist, var, restart
        chain = self._distance_chain(idx)
        self._distance_to_ticks(idx, chain, (ok, dist, var, restart))
        return ok, dist, var, restart

    def _distance_fixes(self) -> IntArray:
        """The fixes the along-track distance uses (indices into this batch's fixes): RTK-fixed,
        with a position in the vehicle's frame, a heading and a good velocity; none outside
        product mode or with ``gnss_distance_gap_s`` ≤ 0."""
        if not self.product or self.config.gnss_distance_gap_s <= 0 or self.g_row.shape[0] == 0:
            return np.zeros(0, dtype=np.int64)
        g = self.g
        use = (
            self.g_pos_ok
            & (g[:, _G_FIX] == float(GnssFix.RTK_FIXED))
            & np.isfinite(self.g_enu).all(axis=1)
            & np.isfinite(self.g_heading)
            & self.g_vel_ok
        )
        return np.flatnonzero(use)

    def _distance_chain(
        self, idx: IntArray
    ) -> tuple[BoolArray, FloatArray, FloatArray, FloatArray]:
        """The chain through fixes ``idx`` (k,), each from the one before (a row's first from
        the vehicle's chain state): whether it continues the chain, the antenna's distance,
        the unwrapped heading and ``Σ Δψ·cos θ·sin φ``, each (k,). Carries each vehicle's
        chain state to its last fix."""
        fe, cfg = self.fe, self.config
        r = self.g_row[idx]
        s = self.slots[r]
        p = self.g_enu[idx]
        t = self.g_t[idx]
        att = np.stack([self.g_heading[idx], nan_to_num(self.g[idx, _G_PITCH])], axis=1)
        first = np.ones(idx.size, dtype=bool)
        first[1:] = r[1:] != r[:-1]
        p_prev = _shift_in(p, first, fe.chain_enu[s[first]])
        t_prev = _shift_in(t, first, fe.chain_ns[s[first]])
        a_prev = _shift_in(att, first, fe.chain_att[s[first]])
        gap_s = (t - t_prev) * _NS
        chained = (t_prev != _NONE_NS) & (gap_s > 0) & (gap_s <= cfg.gnss_distance_gap_s)
        d_head = np.mod(att[:, 0] - a_prev[:, 0] + np.pi, 2 * np.pi) - np.pi
        psi = a_prev[:, 0] + 0.5 * d_head
        th = 0.5 * (att[:, 1] + a_prev[:, 1])
        u = np.stack([np.sin(psi) * np.cos(th), np.cos(psi) * np.cos(th), np.sin(th)], axis=1)
        inc = np.where(chained, np.einsum("ni,ni->n", p - p_prev, u), 0.0)
        seg_start = np.maximum.accumulate(np.where(first, np.arange(idx.size), 0))
        d_ant = fe.chain_m[s] + seg_cumsum(inc, seg_start)
        step_yaw = np.where(chained, d_head, 0.0)
        yaw = fe.chain_yaw_rad[s] + seg_cumsum(step_yaw, seg_start)
        roll = self.g_roll_after[idx]
        turn = fe.chain_turn_rad[s] + seg_cumsum(step_yaw * np.cos(th) * np.sin(roll), seg_start)
        # the chain's state after this batch: its last fix per vehicle
        last = np.ones(idx.size, dtype=bool)
        last[:-1] = r[1:] != r[:-1]
        sl = s[last]
        fe.chain_ns[sl] = t[last]
        fe.chain_enu[sl] = p[last]
        fe.chain_att[sl] = att[last]
        fe.chain_m[sl] = d_ant[last]
        fe.chain_yaw_rad[sl] = yaw[last]
        fe.chain_turn_rad[sl] = turn[last]
        return chained, d_ant, yaw, turn

    def _distance_to_ticks(
        self,
        idx: IntArray,
        chain: tuple[BoolArray, FloatArray, FloatArray, FloatArray],
        out: tuple[BoolArray, FloatArray, FloatArray, BoolArray],
    ) -> None:
        """Into ``out`` (``dist_ok``, ``dist_m``, ``dist_var``, ``dist_restart``, each
        (n_ticks,)): the latest of fixes ``idx`` in each tick's window (the IMU point's
        distance from the ``chain`` of :meth:`_distance_chain`, moved to the tick with the
        fix's speed), a restart if any fix broke the chain."""
        fe = self.fe
        chained, d_ant, yaw, turn = chain
        ok, dist, var, restart = out
        r = self.g_row[idx]
        s = self.slots[r]
        t = self.g_t[idx]
        tn = fe.tick_ns
        tid = self.offsets[r] + np.maximum(-((self.first[r] - t) // tn), 0)
        ok[tid] = True
        dt_s = (self.ticks[tid] - t) * _NS
        vg = self.g_vg[idx]
        # the lever arm with the tracked pitch (gyro between fixes, smoother than the fix's)
        theta = self.g_theta_after[idx]
        d_imu = d_ant + fe.h1_m[s] * (theta + turn) + fe.ant_x_m[s] * yaw + vg * dt_s
        dist[tid] = d_imu  # later fixes overwrite: the latest wins
        lever_var = fe.h1_m[s] ** 2 * self.g_var_after[idx]
        var[tid] = fe.pos_var_cfg[s] + lever_var + self.g_var[idx] * dt_s**2
        np.logical_or.at(restart, tid, ~chained)

    def _hold_outputs(
        self, wz_tick: FloatArray, theta_tick: FloatArray, phi_tick: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Position (ENU, moved to the tick with the GNSS velocity), attitude and the age of the
        fix they come from (``inf``: none) per tick. Product mode: pitch and roll from the
        tracks at the tick (``theta_tick``, ``phi_tick``) where known."""
        table = self._fix_table()
        sel = self._held_at_ticks(table)
        age = (self.ticks - nan_to_num(sel[:, _H_STAMP])) * _NS
        fix_age_s = np.where(np.isfinite(sel[:, _H_STAMP]), age, np.inf)
        age = np.where(np.isfinite(sel[:, _H_STAMP]), age, 0.0)
        vel = nan_to_num(sel[:, _H_VE : _H_VU + 1])
        enu = sel[:, _H_E : _H_U + 1] + (vel * age[:, None] if self.product else 0.0)
        heading = sel[:, _H_HEAD] - (nan_to_num(wz_tick) * age if self.product else 0.0)
        heading = np.mod(heading, 2 * np.pi)
        pitch, roll = sel[:, _H_PITCH], sel[:, _H_ROLL]
        if self.product:
            pitch = np.where(np.isfinite(theta_tick), theta_tick, pitch)
            roll = np.where(np.isfinite(phi_tick), phi_tick, roll)
        att = np.stack([heading, pitch, roll], axis=1)
        if self.g_row.shape[0]:
            self._keep_held(table)
        return enu, att, fix_age_s

    def _fix_table(self) -> FloatArray:
        """This batch's fixes as held rows (``_H_*`` columns), shape ``(nf, 10)``; sets
        ``g_enu`` (nf, 3), their positions in their vehicle's frame (NaN: none), anchoring the
        frame of a vehicle without one at its first fix with a position."""
        g, rows = self.g, self.g_row
        if not rows.shape[0]:
            self.g_enu = np.zeros((0, 3))
            return np.zeros((0, 10))
        self.g_enu = self._fixes_enu()
        return np.column_stack(
            [
                self.g_t.astype(np.float64),
                self.g_enu,
                g[:, _G_VE : _G_VU + 1],
                self.g_heading,
                g[:, _G_PITCH],
                g[:, _G_ROLL],
            ]
        )

    def _fixes_enu(self) -> FloatArray:
        """Positions of the fixes in their vehicle's ENU frame, shape ``(nf, 3)`` (NaN: none);
        the frame of a vehicle is anchored at its first fix with a position."""
        fe, g, rows, s = self.fe, self.g, self.g_row, self.slots
        pos = np.flatnonzero(self.g_pos_ok)
        r_pos = rows[pos]
        new = np.ones(pos.shape[0], dtype=bool)
        new[1:] = r_pos[1:] != r_pos[:-1]
        first = pos[new]
        fresh = ~fe.has_frame[s[rows[first]]]
        anchor_at = first[fresh]
        fe.origin[s[rows[anchor_at]]] = g[anchor_at][:, _G_LAT : _G_H + 1]
        fe.has_frame[s[rows[anchor_at]]] = True
        e = np.full((rows.shape[0], 3), np.nan)
        if pos.size:
            o = fe.origin[s[r_pos]]
            e[pos] = np.stack(
                enu_from_geodetic(
                    g[pos, _G_LAT], g[pos, _G_LON], g[pos, _G_H], o[:, 0], o[:, 1], o[:, 2]
                ),
                axis=1,
            )
        return e

    def _held_at_ticks(self, table: FloatArray) -> FloatArray:
        """Each tick's held row, shape ``(n_ticks, 10)``: the latest fix of ``table`` at or
        before it (compared as float, as the stored stamps: whole numbers, so as integers
        exactly), else the row held from earlier batches."""
        fe, rows = self.fe, self.g_row
        t_tick = self.ticks.astype(np.float64).astype(np.int64)
        i = _asof(rows, table[:, _H_STAMP].astype(np.int64), self.tick_row, t_tick)
        sel = np.take(fe.hold, self.slots[self.tick_row], axis=0)
        if rows.shape[0]:
            sel = np.where((i >= 0)[:, None], np.take(table, np.maximum(i, 0), axis=0), sel)
        return sel

    def _keep_held(self, table: FloatArray) -> None:
        """Hold each vehicle's latest fix of ``table`` for later batches; its position, or the
        latest finite one of this batch."""
        rows = self.g_row
        n_fix = np.bincount(rows, minlength=self.n_rows)
        last_fix = np.cumsum(n_fix) - 1
        has = n_fix > 0
        held = table[last_fix[has]]
        fin = np.flatnonzero(np.isfinite(table[:, _H_E]))
        last_pos = np.full(self.n_rows, -1, dtype=np.int64)
        np.maximum.at(last_pos, rows[fin], fin)
        lp = last_pos[has]
        fix_pos = (lp >= 0) & ~np.isfinite(held[:, _H_E])
        held[fix_pos, _H_E : _H_U + 1] = table[lp[fix_pos], _H_E : _H_U + 1]
        self.fe.hold[self.slots[has]] = held

    def _no_wheel_data(
        self, vs: IntArray, tix2: IntArray, om: FloatArray, sd: FloatArray
    ) -> tuple[FloatArray, FloatArray, npt.NDArray[np.bool_]]:
        """Wheel speeds ``om``, ``sd`` (``(k·m, 2)``: vehicles ``vs``, ticks ``tix2`` of shape
        ``(k, m)``) with NaN where the wheel data is missing (:class:`WheelGap`): before a
        wheel's fit resumes after lost data, or in a span due without the data. Returns them
        and which ticks lack a wheel; spans and waits the ticks have passed are cleared."""
        fe = self.fe
        t = self.ticks[tix2]  # (k, m)
        resume = fe.wheel_resume_ns[vs]  # (k, 2)
        lo, hi = fe.wheel_wait_from_ns[vs], fe.wheel_wait_to_ns[vs]  # (k,)
        due = (lo != _NONE_NS)[:, None] & (t > lo[:, None]) & (t <= hi[:, None])
        missing = ((t[:, :, None] < resume[:, None, :]) | due[:, :, None]).reshape(-1, len(Wheel))
        last = t[:, -1]
        resumed = (resume != _PENDING_NS) & (resume <= last[:, None])
        fe.wheel_resume_ns[vs] = np.where(resumed, _NONE_NS, resume)
        passed = (lo != _NONE_NS) & (hi <= last)
        fe.wheel_wait_from_ns[vs] = np.where(passed, _NONE_NS, lo)
        fe.wheel_wait_to_ns[vs] = np.where(passed, _NONE_NS, hi)
        gap = missing.any(axis=1)
        fe.count[vs, _NO_WHEEL_DATA] += gap.reshape(t.shape).sum(axis=1)
        nan = np.nan
        return np.where(missing, nan, om), np.where(missing, nan, sd), gap

    def _wheels(self) -> tuple[FloatArray, FloatArray, npt.NDArray[np.int32]]:
        """Wheel speeds (left, right) at the ticks: encoder trackers of the vehicles with the
        same wheel settings and number of ticks fitted together (each at its own ticks), or
        direct (CAN) speeds. Returns ``omega``, ``omega_std`` (``(n_ticks, 2)``) and the wheel
        flags."""
        fe = self.fe
        n_ticks = self.n_ticks
        omega = np.full((n_ticks, 2), np.nan)
        omega_std = np.full((n_ticks, 2), np.nan)
        wflags = np.zeros(n_ticks, dtype=np.int32)
        # encoders, unless the vehicle sends direct speeds and no edges
        uses_enc = fe.has_edges[self.slots] | ~fe.has_speeds[self.slots]
        for r in np.flatnonzero(~uses_enc):  # CAN speeds: one query per such vehicle
            d = fe.direct[int(self.slots[r])]
            assert d is not None
            sl = slice(self.offsets[r], self.offsets[r] + self.m[r])
            omega[sl], omega_std[sl] = d.query(self.ticks[sl])
            wflags[sl] |= int(_F.WHEEL_DIRECT)
        enc = np.flatnonzero(uses_enc)
        if enc.size == 0:
            return omega, omega_std, wflags
        for members in self._wheel_groups(enc):
            self._fit_wheel_group(enc[members], (omega, omega_std, wflags))
        return omega, omega_std, wflags

    def _wheel_groups(self, enc: IntArray) -> list[IntArray]:
        """Groups (positions in ``enc``, the rows with encoders) of vehicles with the same
        wheel settings and the same number of ticks (often one group: every vehicle)."""
        fe = self.fe
        keys = (fe.wheel_cfg[self.slots[enc]], self.m[enc])
        if ((keys[0] == keys[0][0]) & (keys[1] == keys[1][0])).all():
            return [np.arange(enc.shape[0])]
        order = np.lexsort(keys[::-1])
        new = np.ones(enc.shape[0], dtype=bool)
        new[1:] = np.any([k[order][1:] != k[order][:-1] for k in keys], axis=0)
        group = np.empty(enc.shape[0], dtype=np.int64)
        group[order] = np.cumsum(new) - 1
        return _rank_passes(group)

    def _fit_wheel_group(
        self, rows: IntArray, out: tuple[FloatArray, FloatArray, npt.NDArray[np.int32]]
    ) -> None:
        """One bank query for the encoder wheels of ``rows`` (one group of
        :meth:`_wheel_groups`), each at its own ticks, into ``out`` (``omega``, ``omega_std``
        (n_ticks, 2), the wheel flags (n_ticks,)); no wheel speed where the data is missing."""
        fe = self.fe
        omega, omega_std, wflags = out
        mt = int(self.m[rows[0]])
        tix2 = self.offsets[rows][:, None] + np.arange(mt)
        tix = tix2.reshape(-1)
        # rows of the fit: left, right of the first vehicle, then of the next, …
        vs = self.slots[rows]
        bank = self._wheel_bank(vs)
        wheel_slots = fe.wheel_slot[vs].reshape(-1)
        fitted = fe.fit_wheels(bank, wheel_slots, np.repeat(self.ticks[tix2], 2, axis=0))
        lone = np.repeat(fe.lone_std[self.slots[rows]], mt)[:, None]
        # fit rows (vehicle, wheel) × ticks → (vehicle·tick, wheel), both wheels at once
        om, sd, method = (
            a.reshape(rows.shape[0], len(Wheel), mt).swapaxes(1, 2).reshape(-1, len(Wheel))
            for a in (fitted.omega_radps, fitted.std_radps, fitted.method)
        )
        none = method == WheelSpeedMethod.NONE
        om = np.where(none, 0.0, om).astype(np.float64, copy=False)
        sd = np.where(none, lone, sd).astype(np.float64, copy=False)
        resume = fe.wheel_resume_ns[vs]
        wait_from = fe.wheel_wait_from_ns[vs]
        if (resume != _NONE_NS).any() or (wait_from != _NONE_NS).any():
            om, sd, gap = self._no_wheel_data(vs, tix2, om, sd)
            wflags[tix] |= np.where(gap, int(_F.WHEEL_GAP), 0).astype(np.int32)
        omega[tix] = om
        omega_std[tix] = sd
        period = (method != WheelSpeedMethod.FREQUENCY).all(axis=1)
        wflags[tix] |= np.where(period, int(_F.WHEEL_PERIOD_METHOD), 0).astype(np.int32)

    def _wheel_bank(self, vs: IntArray) -> WheelBank:
        """The bank holding the trackers of vehicles ``vs`` (one wheel config); trackers new or
        spread over banks are gathered into one (as ``query_many``), noted per slot."""
        fe = self.fe
        bank_of = fe.wheel_bank[vs]
        if bank_of[0] < 0 or not (bank_of == bank_of[0]).all():
            trackers = [tr for s in vs.tolist() for tr in fe.trackers[s]]
            held = gather_bank(trackers)
            assert held is not None  # one wheel config
            bank, wheel_slots = held
            known = [i for i, b in enumerate(fe._banks) if b is bank]
            if not known:
                fe._banks.append(bank)
            fe.wheel_bank[vs] = known[0] if known else len(fe._banks) - 1
            fe.wheel_slot[vs] = wheel_slots.reshape(-1, len(Wheel))
        return fe._banks[int(fe.wheel_bank[vs[0]])]


@dataclass
class _TiltState:
    """The tilt tracks' state of one batch's vehicles (rows in batch order), copied from the
    front end's slot arrays and put back after the batch: pitch ``th``, its Kalman
    covariance (``var``, ``cov_tb``, ``var_b``), pitch-gyro bias ``bx``, last fix, whether it
    stood, the sums since it (``acc``, :class:`~estimator.tilt.PitchSum`); the same for roll
    (``ph``, ``by``, ``rcov`` as :class:`~estimator.tilt.AngleCov`, ``racc`` as
    :class:`~estimator.tilt.RollSum`); a receiver without heading's course and its yaw-gyro
    bias (``course``, ``cbias``, :meth:`_TiltTrack._course_update`) and what it low-passes
    (``clp``, shape ``(k, 4)``: :meth:`_TiltTrack._course_lowpass`)."""

    th: FloatArray
    var: FloatArray
    cov_tb: FloatArray
    var_b: FloatArray
    bx: FloatArray
    fix_ns: IntArray
    known: BoolArray
    still: BoolArray
    acc: FloatArray
    ph: FloatArray
    by: FloatArray
    rcov: FloatArray
    rfix_ns: IntArray
    rknown: BoolArray
    racc: FloatArray
    course: FloatArray
    cfix_ns: IntArray
    cbias: FloatArray
    clp: FloatArray

    @classmethod
    def take(cls, fe: FleetFrontEnd, s: IntArray) -> _TiltState:
        """Copies of slots ``s`` (an index array, so every field is a copy)."""
        return cls(
            th=fe.pitch_rad[s],
            var=fe.pitch_var[s],
            cov_tb=fe.pitch_cov_tb[s],
            var_b=fe.pitch_var_b[s],
            bx=fe.pitch_gyro_bias[s],
            fix_ns=fe.pitch_fix_ns[s],
            known=fe.pitch_known[s],
            still=fe.pitch_still[s],
            acc=fe.pitch_acc[s],
            ph=fe.roll_rad[s],
            by=fe.roll_gyro_bias[s],
            rcov=fe.roll_cov[s],
            rfix_ns=fe.roll_fix_ns[s],
            rknown=fe.roll_known[s],
            racc=fe.roll_acc[s],
            course=fe.course_rad[s],
            cfix_ns=fe.course_fix_ns[s],
            cbias=fe.course_gyro_bias[s],
            clp=fe.course_lp[s],
        )

    def tilt_cov(self) -> tuple[FloatArray, IntArray]:
        """Pitch's and roll's covariance with their gyro's bias, shape ``(k, 2, 3)``
        (:class:`~estimator.tilt.AngleCov`), and their last fix, ``(k, 2)``
        (``_NONE_NS`` where the angle is not known yet)."""
        cov = np.stack([np.stack([self.var, self.cov_tb, self.var_b], axis=1), self.rcov], axis=1)
        fix_ns = np.stack([self.fix_ns, self.rfix_ns], axis=1)
        return cov, np.where(np.stack([self.known, self.rknown], axis=1), fix_ns, _NONE_NS)

    def put(self, fe: FleetFrontEnd, s: IntArray) -> None:
        """Write the state back to slots ``s``."""
        fe.pitch_rad[s] = self.th
        fe.pitch_var[s] = self.var
        fe.pitch_cov_tb[s] = self.cov_tb
        fe.pitch_var_b[s] = self.var_b
        fe.pitch_acc[s] = self.acc
        fe.pitch_still[s] = self.still
        fe.pitch_gyro_bias[s] = self.bx
        fe.pitch_fix_ns[s] = self.fix_ns
        fe.pitch_known[s] = self.known
        fe.roll_rad[s] = self.ph
        fe.roll_gyro_bias[s] = self.by
        fe.roll_cov[s] = self.rcov
        fe.roll_fix_ns[s] = self.rfix_ns
        fe.roll_known[s] = self.rknown
        fe.roll_acc[s] = self.racc
        fe.course_rad[s] = self.course
        fe.course_fix_ns[s] = self.cfix_ns
        fe.course_gyro_bias[s] = self.cbias
        fe.course_lp[s] = self.clp


class _TiltTrack:
    """One batch's tilt track (:meth:`_Batch._pitch_track`): the samples' integrals
    (:func:`~estimator.tilt.tilt_integrals`), the state, and the two steps
    :meth:`_Batch._between_fixes` runs: :meth:`end_segment` (integrate up to a fix) and
    :meth:`at_fix` (the fix's update). Writes the per-fix outputs (``g_vg``, ``g_*_after``)
    into the batch."""

    def __init__(self, b: _Batch) -> None:
        self.b = b
        self.cfg = b.config
        self.product = b.product
        n = b.T.shape[0]
        gyro_var = b.fe.gyro_var_cfg[b.slots][b.s_row] if self.product else np.zeros(n)
        self.cum, self.psi, self.rot = tilt_integrals(
            b.dts, b.wx, b.wy, b.wz, b.fx, b.fy, gyro_var, b.begin_of, self.product
        )
        self.st = _TiltState.take(b.fe, b.slots)
        self.last = np.full(b.n_rows, -1, dtype=np.int64)  # last sample integrated, per row
        speed_mps = np.hypot(b.g[:, _G_VE], b.g[:, _G_VN])
        self.g_still = b.g_vel_ok & (speed_mps < self.cfg.standstill_speed_mps)

    # -- between fixes ---------------------------------------------------------------------
    def end_segment(self, r: IntArray, j: IntArray) -> FloatArray:
        """Integrate samples up to ``j − 1`` of rows ``r`` with the biases in force and move
        θ, φ there. Returns the segment's parameters ``[Re a, Im a, Re β, Im β, coupled]``
        (:func:`~estimator.tilt.tilt_at`), shape ``(len(r), 5)``."""
        st = self.st
        k, lk = j - 1, self.last[r]
        begun = lk >= 0
        c0 = np.where(begun[:, None], np.take(self.cum, np.maximum(lk, 0), axis=0), 0.0)  # at start
        d = np.take(self.cum, k, axis=0) - c0
        st.acc[r, PitchSum.RATE : PitchSum.SAMPLES + 1] += d[:, PITCH_SUM_OF]
        a, beta, coupled = self._segment_start(r, lk, begun, c0)
        if self.product:
            self._add_product_sums(r, k, lk, begun, d)
        z = tilt_at(self.cum, self.rot, k, a, beta, coupled, self.product)
        st.th[r], st.ph[r] = z.real, z.imag
        self.last[r] = k
        return np.stack([a.real, a.imag, beta.real, beta.imag, coupled], axis=1)

    def _segment_start(
        self, r: IntArray, lk: IntArray, begun: BoolArray, c0: FloatArray
    ) -> tuple[CArray, CArray, BoolArray]:
        """The segment's integration constant ``a``, biases ``β = b_x + i·b_y`` and whether
        pitch and roll are coupled (product mode, once the row has a roll); ``c0`` the
        integrals at the segment's start, ``lk`` its last sample (−1: none)."""
        st = self.st
        a = (st.th[r] - c0[:, Integral.RATE_X] + st.bx[r] * c0[:, Integral.TIME]) + 1j * st.ph[r]
        if not self.product:
            return a, st.bx[r] + 0j, np.zeros(r.shape[0], dtype=bool)
        coupled = st.rknown[r]
        beta = st.bx[r] + 1j * np.where(coupled, st.by[r], 0.0)
        turn0 = np.where(begun, self.rot[np.maximum(lk, 0)], 1.0)
        cz0 = c0[:, Integral.TURNED_RATE_RE] + 1j * c0[:, Integral.TURNED_RATE_IM]
        ez0 = c0[:, Integral.TURN_RE] + 1j * c0[:, Integral.TURN_IM]
        a = np.where(coupled, turn0 * (st.th[r] + 1j * st.ph[r]) - cz0 + beta * ez0, a)
        return a, beta, coupled

    def _add_product_sums(
        self, r: IntArray, k: IntArray, lk: IntArray, begun: BoolArray, d: FloatArray
    ) -> None:
        """Product mode's sums since the last fix: each angle's added variance (gyro noise and
        the other angle's error carried by the yaw rate), the roll's rates, lateral force and
        yaw, the forward force; ``d`` the segment's integrals, shape ``(len(r), len(Integral))``."""
        st = self.st
        tau2 = 2.0 * self.cfg.attitude_tau_s
        d_g, d_z2 = d[:, Integral.GYRO_VAR], d[:, Integral.YAW_RATE_SQ]
        roll_var = np.where(st.rknown[r], st.rcov[r, AngleCov.ANGLE], 0.0)
        st.acc[r, PitchSum.ANGLE_VAR] += d_g + tau2 * roll_var * d_z2
        st.racc[r, RollSum.ANGLE_VAR] += d_g + tau2 * st.var[r] * d_z2
        st.racc[r, RollSum.RATE : RollSum.FORCE_LAT_TIME + 1] += d[:, ROLL_SUM_OF]
        st.racc[r, RollSum.YAW] += self.psi[k] - np.where(begun, self.psi[np.maximum(lk, 0)], 0.0)
        # the rates' change over the segment (telescoping to the interval's): the mean angular
        # acceleration, whose lever arm the lateral force carries (_Batch._accel_roll); a row's
        # first segment in a call starts at the last sample summed before (kept in the sums)
        b = self.b
        first = b.s_begin[r]
        has = k >= first
        if b.wy.shape[0]:
            k_ = np.where(has, k, 0)
            held = st.racc[r, RollSum.HAS_LAST] > 0
            for col, last, w in (
                (RollSum.RATE_Y_CHANGE, RollSum.LAST_RATE_Y, b.wy),
                (RollSum.RATE_Z_CHANGE, RollSum.LAST_RATE_Z, b.wz),
            ):
                now = np.nan_to_num(w[k_])
                before = np.where(
                    begun,
                    np.nan_to_num(w[np.maximum(lk, 0)]),
                    np.where(held, st.racc[r, last], np.nan_to_num(w[np.where(has, first, 0)])),
                )
                st.racc[r, col] += np.where(has, now - before, 0.0)
                st.racc[r, last] = np.where(has, now, st.racc[r, last])
            st.racc[r, RollSum.HAS_LAST] = np.where(has, 1.0, st.racc[r, RollSum.HAS_LAST])
        st.acc[r, PitchSum.FORCE_FWD] += d[:, Integral.FORCE_FWD]

    # -- at a fix ----------------------------------------------------------------------------
    def at_fix(self, fi: IntArray, r: IntArray) -> None:
        """Update rows ``r`` with their fixes ``fi``: pitch (and roll, product mode) measured,
        the Kalman update, the fix's outputs."""
        st, b = self.st, self.b
        p = b.g[fi, _G_PITCH]
        # stood through the interval since the previous fix: the mean rates are the biases
        t_since = st.acc[r, PitchSum.TIME]
        stood = st.still[r] & self.g_still[fi] & (t_since > 0) & (self.cfg.standstill_speed_mps > 0)
        span = np.where(stood, t_since, 1.0)
        if self.product:
            self._course_update(fi, r)
            pm, pm_var = self._pitch_measured(fi, r, p, stood, span)
            roll_m, roll_var = self._roll_measured(fi, r)
            self._kalman_update(fi, r, (pm, pm_var), (roll_m, roll_var), stood, span)
        else:
            st.th[r], st.var[r], st.bx[r], st.fix_ns[r], st.known[r] = pitch_fix_update(
                st.th[r], st.var[r], st.bx[r], st.fix_ns[r], st.known[r], p, b.g_t[fi], self.cfg
            )
        self._fix_outputs(fi, r, p)

    def _course_update(self, fi: IntArray, r: IntArray) -> None:
        """Heading at fixes ``fi`` (rows ``r``) of a receiver without one: ``O``'s course.

        The antenna's velocity is ``O``'s plus the lever arm's ``ω × p_a``
        (:meth:`_Batch._antenna_lever`), whose horizontal part on a swaying mast is metres per
        second (``h1·ωy`` across, ``h1·ωx`` along): the antenna's own course swings by tens of
        degrees and turns round when ``h1·ωx`` outruns the speed, and eq. (1) projected on it
        reads ``|v|`` instead of the body's forward speed. So the course is integrated from the
        yaw rate between fixes (``ψ̇ = −(ωz − b_z)/cos θ``, ``b_z`` learnt against the course as
        the heading track learns it) and pulled, with time constant
        ``course_tau_s`` (:func:`~estimator.tilt.yaw_fix_update`), to the direction of the
        velocity less the lever arm's (turned into ENU with the course predicted), where that
        speed is at least ``_COURSE_MIN_SPEED_MPS``; the bias is learnt from
        ``_VEL_PITCH_MIN_SPEED_MPS`` on, fix to fix (a gap without a course would wind it up),
        and the pull is ``(v/_VEL_PITCH_MIN_SPEED_MPS)²`` of it below that (the direction's
        noise grows as ``1/v``). A course not pulled for ``reacquire_s`` (an outage, a stop)
        starts anew, from the antenna's mean velocity (:meth:`_course_lowpass`) where that
        is at least ``_COURSE_MIN_SPEED_MPS``. Replaces ``g_heading`` of those fixes where
        ``O``'s mean speed is at least ``_COURSE_MIN_SPEED_MPS`` (where the course is
        measured) and the lever arm's RMS horizontal speed at least ``_COURSE_LEVER_SHARE``
        of the antenna's; elsewhere the antenna's own course is ``O``'s to within that share
        and carries no integrated yaw-rate error. At a crawl the share is as large as at
        speed (the sway grows with the speed), so the course is used there too.
        """
        st, b = self.st, self.b
        own = ~np.isfinite(b.g[fi, _G_HEAD])
        if not own.any():
            return
        fi, r = fi[own], r[own]
        pred, mean_course = self._course_predicted(fi, r)
        course, speed, seen, share = self._course_measured(fi, r, pred)
        share = self._course_lowpass(fi, r, share)
        self._course_pull(fi, r, pred, (course, speed, seen))
        used = np.isfinite(st.course[r]) & (share >= _COURSE_LEVER_SHARE)
        used &= np.isfinite(mean_course)  # O's mean speed at least _COURSE_MIN_SPEED_MPS
        b.g_heading[fi] = np.where(used, st.course[r], b.g_heading[fi])

    def _course_predicted(self, fi: IntArray, r: IntArray) -> tuple[FloatArray, FloatArray]:
        """The course at fixes ``fi`` (rows ``r``) predicted by the yaw rate since the previous
        fix, less the learnt bias (NaN where stale); where there is none, the antenna's mean
        velocity's direction. Returns it and that direction (NaN under
        ``_COURSE_MIN_SPEED_MPS``), shape ``(len(r),)`` each."""
        st, b = self.st, self.b
        bz = st.cbias[r]
        turn = st.racc[r, RollSum.YAW] - bz * st.acc[r, PitchSum.TIME]
        pred = st.course[r] - turn / np.maximum(np.cos(st.th[r]), 0.5)
        stale = (b.g_t[fi] - st.cfix_ns[r]) * _NS > self.cfg.reacquire_s
        # a course that went stale (an outage, a stop) restarts from the velocity of now: the
        # antenna's mean velocity of before is as old as the outage, the vehicle may have
        # turned through it
        restart = stale & np.isfinite(pred)
        if restart.any():
            st.clp[r[restart], _COURSE_LP_VEL] = np.nan
        pred = np.where(stale, np.nan, pred)
        # none yet: the antenna's mean velocity's direction, the lever arm's swing averaged out
        mean_course = self._course_lowpass(fi, r)
        pred = np.where(np.isfinite(pred), pred, mean_course)
        return pred, mean_course

    def _course_pull(
        self,
        fi: IntArray,
        r: IntArray,
        pred: FloatArray,
        measured: tuple[FloatArray, FloatArray, BoolArray],
    ) -> None:
        """Pull the course ``pred`` at fixes ``fi`` (rows ``r``) to the ``measured`` course of
        :meth:`_course_measured` (course, speed, seen; :func:`~estimator.tilt.yaw_fix_update`
        over ``course_tau_s``, weaker below ``_VEL_PITCH_MIN_SPEED_MPS``) and learn its bias."""
        st, b = self.st, self.b
        course, speed, seen = measured
        bz = st.cbias[r]
        tau_cfg = dataclasses.replace(self.cfg, attitude_tau_s=self.cfg.course_tau_s)
        # the interval since the previous fix: the time its IMU samples span
        prev_ns = b.g_t[fi] - np.rint(st.acc[r, PitchSum.TIME] / _NS).astype(np.int64)
        new, bias, _ = yaw_fix_update(pred, bz, prev_ns, course, b.g_t[fi], tau_cfg)
        # the direction's noise grows as 1/speed: below _VEL_PITCH_MIN_SPEED_MPS a smaller pull
        w = np.where(np.isfinite(pred), np.minimum(speed / _VEL_PITCH_MIN_SPEED_MPS, 1.0) ** 2, 1.0)
        st.course[r] = np.where(
            seen, np.where(np.isfinite(pred), pred + w * (new - pred), new), pred
        )
        st.cbias[r] = np.where(seen & (speed >= _VEL_PITCH_MIN_SPEED_MPS), bias, bz)
        st.cfix_ns[r] = np.where(seen, b.g_t[fi], st.cfix_ns[r])

    def _course_lowpass(
        self, fi: IntArray, r: IntArray, share: FloatArray | None = None
    ) -> FloatArray:
        """Low-pass at fixes ``fi`` (rows ``r``) over ``_COURSE_LP_TAU_S``, the first value
        taken as it is: without ``share``, the antenna's east and north velocity, and returns
        its direction (NaN under ``_COURSE_MIN_SPEED_MPS``); with the fix's own lever-arm
        ``share`` (:meth:`_course_measured`), the squared speeds of the lever arm and the
        antenna, and returns the RMS share (the fix's own where there is none yet). A fix's
        own share follows the sway's phase, and with the GNSS clock not yet known its rates
        are a fraction of a sway off: near a zero of the rates a swaying mast read small."""
        st, b = self.st, self.b
        ve, vn = b.g[fi, _G_VE], b.g[fi, _G_VN]
        cols = _COURSE_LP_VEL if share is None else _COURSE_LP_SHARE
        if share is None:
            now = np.stack([ve, vn], axis=1)
        else:
            # a standing antenna's share: not a number; a speed beyond a float's square: inf;
            # either leaves the row out (``ok`` below)
            with np.errstate(invalid="ignore", over="ignore"):
                v2 = ve**2 + vn**2
                now = np.stack([share**2 * v2, v2], axis=1)
        ok = b.g_vel_ok[fi] & np.isfinite(now).all(axis=1)
        dt = st.acc[r, PitchSum.TIME]
        alpha = (dt / (_COURSE_LP_TAU_S + dt))[:, None]
        old = st.clp[r, cols]
        new = np.where(np.isfinite(old), old + alpha * (now - old), now)
        st.clp[r, cols] = np.where(ok[:, None], new, old)
        lp = st.clp[r, cols]
        with np.errstate(invalid="ignore", divide="ignore"):
            if share is None:
                moving = np.hypot(lp[:, 0], lp[:, 1]) >= _COURSE_MIN_SPEED_MPS
                return np.where(moving, np.arctan2(lp[:, 0], lp[:, 1]), np.nan)
            rms = np.sqrt(lp[:, 0] / lp[:, 1])
        return np.where(np.isfinite(rms), rms, share)

    def _course_measured(
        self, fi: IntArray, r: IntArray, pred: FloatArray
    ) -> tuple[FloatArray, FloatArray, BoolArray, FloatArray]:
        """Course of ``O`` at fixes ``fi`` (rows ``r``, course predicted ``pred``, NaN: none
        yet), its horizontal speed, whether it is used, and the lever arm's horizontal speed
        over the antenna's. Used: from ``_COURSE_MIN_SPEED_MPS`` on,
        a first course only while the lever arm's velocity is under
        ``_FIRST_COURSE_LEVER_SHARE`` of the antenna's (it is taken off in the antenna's own
        course)."""
        st, b = self.st, self.b
        frame = np.where(np.isfinite(pred), pred, b.g_heading[fi])
        lever_e, lever_n, _ = b._antenna_lever(fi, r, frame, st.th[r])
        ve, vn = b.g[fi, _G_VE] - lever_e, b.g[fi, _G_VN] - lever_n
        speed = np.hypot(ve, vn)
        seen = b.g_vel_ok[fi] & np.isfinite(speed) & (speed >= _COURSE_MIN_SPEED_MPS)
        with np.errstate(invalid="ignore", divide="ignore"):
            share = np.hypot(lever_e, lever_n) / np.hypot(b.g[fi, _G_VE], b.g[fi, _G_VN])
        seen &= np.isfinite(pred) | (share < _FIRST_COURSE_LEVER_SHARE)
        return np.where(seen, np.arctan2(ve, vn), pred), speed, seen, share

    def _pitch_measured(
        self, fi: IntArray, r: IntArray, p: FloatArray, stood: BoolArray, span: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """Pitch measured at fixes ``fi`` and its variance: the receiver's or, without one, the
        velocity's elevation or, standing, the forward accelerometer's gravity, chi-square
        gated (an outlying velocity is a wild pitch; before the first pitch against the prior,
        ±_PITCH_PRIOR_STD_RAD about level)."""
        st, cfg, b = self.st, self.cfg, self.b
        pm_var = np.full(p.shape[0], cfg.pitch_std_rad**2)
        need = np.flatnonzero(~np.isfinite(p))
        if not need.size:
            return p, pm_var
        rn = r[need]
        pv, pv_var = b._velocity_pitch(fi[need], rn)
        st_pitch, st_var = b._gravity_angle(
            rn,
            st.acc[rn, PitchSum.FORCE_FWD] / span[need],
            st.acc[rn, PitchSum.SAMPLES],
            cfg.pitch_std_rad,
        )
        standing = stood[need] & ~np.isfinite(pv)
        pv = np.where(standing, st_pitch, pv)
        pv_var = np.where(standing, st_var, pv_var)
        wild = (pv - st.th[rn]) ** 2 > cfg.gate_chi2 * (st.var[rn] + pv_var)
        pm = p.copy()
        pm[need] = np.where(wild, np.nan, pv)
        pm_var[need] = pv_var
        return pm, pm_var

    def _roll_measured(self, fi: IntArray, r: IntArray) -> tuple[FloatArray, FloatArray]:
        """Roll measured at fixes ``fi`` and its variance: the receiver's or, without one, the
        lateral accelerometer's (:meth:`_Batch._accel_roll`), chi-square gated."""
        st, cfg = self.st, self.cfg
        roll_var = np.full(r.shape[0], cfg.pitch_std_rad**2)
        roll_m = self.b.g[fi, _G_ROLL]
        need = np.flatnonzero(~np.isfinite(roll_m))
        if not need.size:
            return roll_m, roll_var
        rn = r[need]
        pa, pa_var = self.b._accel_roll(fi[need], rn, st.th[rn], st.acc[rn], st.racc[rn])
        gate = cfg.gate_chi2 * (st.rcov[rn, AngleCov.ANGLE] + pa_var)
        wild = st.rknown[rn] & ((pa - st.ph[rn]) ** 2 > gate)
        roll_m = roll_m.copy()
        roll_m[need] = np.where(wild, np.nan, pa)
        roll_var[need] = pa_var
        return roll_m, roll_var

    def _kalman_update(
        self,
        fi: IntArray,
        r: IntArray,
        pitch: tuple[FloatArray, FloatArray],
        roll: tuple[FloatArray, FloatArray],
        stood: BoolArray,
        span: FloatArray,
    ) -> None:
        """Product mode: pitch and roll (each ``(measured, variance)``) through one
        :func:`~estimator.tilt.pitch_kf_update` call (pitch the first ``len(r)``, roll the
        last), with the zero-rate update where the row stood; the sums restart."""
        st, b = self.st, self.b
        r_still = (
            b.fe.gyro_var_cfg[b.slots[r]] / np.maximum(st.acc[r, PitchSum.SAMPLES], 1.0)
            + self.cfg.standstill_rate_floor_radps**2
        )
        rates = np.concatenate([st.acc[r, PitchSum.RATE], st.racc[r, RollSum.RATE]])
        cov = np.stack([st.var[r], st.cov_tb[r], st.var_b[r]], axis=1)
        updated = pitch_kf_update(
            np.concatenate([st.th[r], st.ph[r]]),
            np.concatenate([cov, st.rcov[r]]),
            np.concatenate([st.bx[r], st.by[r]]),
            np.concatenate([st.fix_ns[r], st.rfix_ns[r]]),
            np.concatenate([st.known[r], st.rknown[r]]),
            np.concatenate([pitch[0], roll[0]]),
            np.concatenate([b.g_t[fi], b.g_t[fi]]),
            self.cfg,
            np.concatenate([pitch[1], roll[1]]),
            np.concatenate([st.acc[r, PitchSum.ANGLE_VAR], st.racc[r, RollSum.ANGLE_VAR]]),
            np.where(np.tile(stood, 2), rates / np.tile(span, 2), np.nan),
            np.concatenate([r_still, r_still]),
        )
        self._take_update(fi, r, updated)

    def _take_update(
        self,
        fi: IntArray,
        r: IntArray,
        updated: tuple[FloatArray, FloatArray, FloatArray, IntArray, BoolArray],
    ) -> None:
        """Rows ``r`` take :func:`~estimator.tilt.pitch_kf_update`'s ``updated`` (angle,
        covariance, bias, fix stamp, known; pitch the first ``len(r)``, roll the last) at
        fixes ``fi``; the sums restart, the roll after the fix is written to the batch."""
        st, b = self.st, self.b
        angle, cov2, bias2, fix2, known2 = updated
        kr = r.shape[0]
        st.th[r], st.ph[r] = angle[:kr], angle[kr:]
        st.var[r] = cov2[:kr, AngleCov.ANGLE]
        st.cov_tb[r] = cov2[:kr, AngleCov.CROSS]
        st.var_b[r] = cov2[:kr, AngleCov.BIAS]
        st.rcov[r] = cov2[kr:]
        st.bx[r], st.by[r] = bias2[:kr], bias2[kr:]
        st.fix_ns[r], st.rfix_ns[r] = fix2[:kr], fix2[kr:]
        st.known[r], st.rknown[r] = known2[:kr], known2[kr:]
        st.acc[r] = 0.0
        st.racc[r, : RollSum.LAST_RATE_Y] = 0.0  # the last sample's rates are kept
        st.still[r] = self.g_still[fi]
        roll_after = shrunk_roll(st.ph[r], st.rcov[r, AngleCov.ANGLE])
        b.g_roll_after[fi] = np.where(st.rknown[r], roll_after, 0.0)

    def _fix_outputs(self, fi: IntArray, r: IntArray, p: FloatArray) -> None:
        """The batch's per-fix outputs: pitch variance, bias and pitch after the fix, and the
        GNSS speed of eq. (1) with the receiver's pitch, or the tracked one without it."""
        st, b = self.st, self.b
        b.g_var_after[fi] = st.var[r]
        b.g_bias_after[fi] = st.bx[r]
        b.g_theta_after[fi] = st.th[r]
        cov, fix_ns = st.tilt_cov()
        b.g_tilt_after[0][fi], b.g_tilt_after[1][fi] = cov[r], fix_ns[r]
        ok = b.g_vel_ok[fi]
        used = np.where(np.isfinite(p), p, st.th[r])
        fo = fi[ok]
        b.g_vg[fo] = gnss_vehicle_speed(
            b.g[fo, _G_VE], b.g[fo, _G_VN], b.g[fo, _G_VU], b.g_heading[fo], used[ok]
        )

    # -- at the samples ----------------------------------------------------------------------
    def at_samples(self, q: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Pitch and roll (NaN where unknown) at every sample from each sample's segment
        parameters ``q`` (:meth:`_Batch._between_fixes`), each shape ``(n,)``."""
        if self.b.T.shape[0] == 0:
            return np.zeros(0), np.zeros(0)
        coupled = q[:, 4] > 0.5
        a, beta = q[:, 0] + 1j * q[:, 1], q[:, 2] + 1j * q[:, 3]
        z = tilt_at(self.cum, self.rot, slice(None), a, beta, coupled, self.product)
        return np.asarray(z.real), np.where(coupled, z.imag, np.nan)
