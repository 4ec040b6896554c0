"""Per-wheel and per-vehicle wheel speeds: the encoder tracker and direct (CAN) speeds.

:class:`WheelTracker` is one wheel's slot of a :class:`~estimator.wheel_speed.bank.WheelBank`;
:func:`query_many` queries trackers through their bank in one fit. :class:`DirectWheelSpeed`
holds the speeds a vehicle reports directly.
"""

from __future__ import annotations

import weakref

import numpy as np
import numpy.typing as npt

from estimator._arrays import FloatArray, IntArray
from estimator.config import ConfigError
from estimator.wheel_speed.bank import WheelBank
from estimator.wheel_speed.methods import WheelSpeedConfig, WheelSpeedResult, _tooth

__all__ = ["DirectWheelSpeed", "WheelTracker", "gather_bank", "query_many"]


class WheelTracker:
    """Streaming, causal speed of one wheel from its encoder edges.

    Push :class:`~estimator.types.WheelEdges` batches in time order with :meth:`push`; ask
    :meth:`query` for the speed at times not earlier than the previous query. Keeps only the
    edges a later query can need.

    Tooth calibration: real rings have unevenly spaced teeth (a fixed pattern, a percent of
    the pitch), which puts a fixed error on every edge's angle and, through the fit, a
    speed error that repeats every turn. The tracker learns the pattern: each edge with
    ``calibration_half_window`` edges on both sides (already received) is compared with a
    local quadratic fit of its neighbours, and the tooth's angle correction moves by
    ``calibration_gain`` of the residual (corrections kept zero-mean), on a fixed time grid.
    Tooth ``j`` is the edge count modulo ``teeth_per_rev``. Only past edges are used, so
    speeds stay causal.

    A tracker is a slot of a :class:`WheelBank`: its own bank unless one is given. The first
    :func:`query_many` over trackers of several banks (same config) moves them into one, so
    later calls fit them all in one pass.

    Parameters
    ----------
    config : WheelSpeedConfig
    bank : WheelBank, optional
        Bank to hold the edges (its config must equal ``config``).
    """

    def __init__(self, config: WheelSpeedConfig, bank: WheelBank | None = None) -> None:
        if bank is not None and bank.config != config:
            raise ConfigError("a WheelTracker's bank must have the tracker's config")
        self.config = config
        self._bank = bank if bank is not None else WheelBank(config)
        self._slot = self._bank.add()
        self._finalizer = weakref.finalize(self, WheelBank.remove, self._bank, self._slot)

    @property
    def skipped(self) -> int:
        """Edges dropped because they went back in time."""
        return self._bank.skipped[self._slot]

    @property
    def calibrated_edges(self) -> int:
        """Edges the tooth calibration has learnt from."""
        return self._bank.calibrated_edges(self._slot)

    @property
    def angle_noise_rad(self) -> float:
        """1-sigma angle error of one edge: the prior ``angle_noise_rel`` of the pitch, then
        what the tooth calibration measures."""
        return self._bank.angle_noise_rad(self._slot)

    @property
    def last_edge_ns(self) -> int | None:
        """Time of the newest edge held, or None."""
        stamp = self._bank.held_stamp_ns(self._slot)
        return int(stamp[-1]) if stamp.size else None

    @property
    def held_stamp_ns(self) -> IntArray:
        """Times of the edges held, shape ``(n,)``."""
        return self._bank.held_stamp_ns(self._slot)

    @property
    def tooth_correction_rad(self) -> FloatArray:
        """Learnt angle correction of each tooth, shape ``(teeth_per_rev,)``, zero mean."""
        return self._bank.tooth_correction_rad(self._slot)

    def push(self, stamp_ns: IntArray, direction: npt.NDArray[np.int8] | None = None) -> int:
        """Append edges (non-decreasing stamps; earlier-than-held ones are skipped and counted);
        returns how many of these were skipped."""
        return self._bank.push(self._slot, stamp_ns, direction)

    def query(self, query_ns: IntArray) -> WheelSpeedResult:
        """Speed at each time in ``query_ns`` (shape ``(m,)``, non-decreasing); trims history.

        The tooth corrections in force at time ``t`` are those learnt from the edges up to the
        last instant ``t0 + k·calibration_period_s`` at or before ``t`` (``t0`` the wheel's
        first edge), so results depend neither on how queries are batched nor on the absolute
        clock.
        """
        r = self._bank.query(np.array([self._slot]), query_ns)
        return WheelSpeedResult(r.omega_radps[0], r.std_radps[0], r.method[0])

    def _move_to(self, bank: WheelBank) -> None:
        """Carry this wheel's state (held edges, calibration, counters) into ``bank``."""
        old, slot = self._bank, self._slot
        old._flush()
        bank._flush()
        new = bank.add()
        stamp = old.held_stamp_ns(slot)
        n = stamp.shape[0]
        if n:
            angle = old._angle[
                old._at(np.int64(slot), np.arange(old._head[slot], old._count[slot]))
            ]
            bank._fit_rings(np.array([new]), np.array([n]))
            bank._count[new] = n
            at = bank._at(np.int64(new), np.arange(n))
            bank._stamp[at] = stamp
            bank._angle[at] = angle
            ns = self.config.teeth_per_rev
            bank._dslot[at] = new * ns + _tooth(angle, ns)
            bank._corr[at] = old._corr[
                old._at(np.int64(slot), np.arange(old._head[slot], old._count[slot]))
            ]
        shift = int(old._head[slot])
        bank._cal_from[new] = old._cal_from[slot] - shift
        for name in (
            "_last_angle",
            "_angle_before",
            "_signed",
            "_cal_upto",
            "_cal_origin",
            "_calibrated",
            "_angle_var",
            "_delta",
        ):
            getattr(bank, name)[new] = getattr(old, name)[slot]
        bank._floor_ns[new] = old._floor_ns[slot]
        bank.skipped[new] = old.skipped[slot]
        self._finalizer.detach()
        old.remove(slot)
        self._bank, self._slot = bank, new
        self._finalizer = weakref.finalize(self, WheelBank.remove, bank, new)


def query_many(trackers: list[WheelTracker], query_ns: IntArray) -> list[WheelSpeedResult]:
    """:meth:`WheelTracker.query` of several trackers, in one vectorised fit.

    Equivalent to querying each tracker on its own. Trackers of one config that sit in
    different banks are first moved into one (the biggest), once (:func:`gather_bank`); from
    then on a call costs a fixed number of numpy calls plus a Python attribute read per tracker.

    Parameters
    ----------
    trackers : list of WheelTracker
        Distinct trackers.
    query_ns : ndarray, shape (m,) or (len(trackers), m), int64, non-decreasing along m
        The same times for every tracker, or each tracker's own.

    Returns
    -------
    list of WheelSpeedResult, one per tracker, arrays of shape (m,)
    """
    q = np.asarray(query_ns, dtype=np.int64)
    if not trackers:
        return []
    held = gather_bank(trackers)
    if held is None:
        rows = q if q.ndim == 2 else np.broadcast_to(q, (len(trackers), q.shape[0]))
        return [t.query(r) for t, r in zip(trackers, rows, strict=True)]
    bank, slots = held
    r = bank.query(slots, q)
    return list(map(_result_row, r.omega_radps, r.std_radps, r.method))


def gather_bank(trackers: list[WheelTracker]) -> tuple[WheelBank, IntArray] | None:
    """The bank that holds every one of ``trackers`` (not empty) and their slots in it.

    Trackers spread over several banks are moved into the biggest of them first. Only this
    function (also through :func:`query_many`) moves trackers, so a caller may keep the answer
    and query the bank directly (:meth:`WheelBank.query`, one row per slot) as long as it
    takes the answer of every later call for the trackers of that call. None when the
    trackers' configs differ (they cannot share a bank).
    """
    bank = trackers[0]._bank
    if not all(t._bank is bank for t in trackers):
        cfg = trackers[0].config
        if any(t.config != cfg for t in trackers):
            return None
        banks = {id(t._bank): t._bank for t in trackers}
        bank = max(banks.values(), key=lambda b: b._slots - len(b._free))
        for t in trackers:
            if t._bank is not bank:
                t._move_to(bank)
    slots = np.fromiter((t._slot for t in trackers), dtype=np.int64, count=len(trackers))
    return bank, slots


_set_omega = WheelSpeedResult.__dict__["omega_radps"].__set__
_set_std = WheelSpeedResult.__dict__["std_radps"].__set__
_set_method = WheelSpeedResult.__dict__["method"].__set__


def _result_row(
    omega: FloatArray, std: FloatArray, method: npt.NDArray[np.int8]
) -> WheelSpeedResult:
    """``WheelSpeedResult(omega, std, method)`` without the frozen dataclass's ``__init__``.

    That ``__init__`` sets each field through ``object.__setattr__``, about 1 µs a result: as
    much as the whole fit of a wheel when :func:`query_many` answers thousands. The slot
    descriptors store the same three fields directly.
    """
    r = object.__new__(WheelSpeedResult)
    _set_omega(r, omega)
    _set_std(r, std)
    _set_method(r, method)
    return r


class DirectWheelSpeed:
    """Wheel speeds given directly (CAN :class:`~estimator.types.WheelSpeeds`), both wheels.

    The value at ``t`` is the latest finite sample at or before ``t`` (causal hold), unknown
    (NaN) once older than ``stale_s``.

    Parameters
    ----------
    stale_s : float
        Age after which a held sample is no longer used [s].
    std_radps : float
        1-sigma noise reported with the values.
    """

    def __init__(self, stale_s: float = 0.5, std_radps: float = 0.02) -> None:
        self.stale_ns = round(stale_s * 1e9)
        self.std_radps = std_radps
        self._stamp = np.zeros(0, dtype=np.int64)
        self._omega = np.zeros((0, 2), dtype=np.float64)
        self.skipped = 0
        """Samples dropped (non-finite or back in time)."""

    @property
    def has_data(self) -> bool:
        return bool(self._stamp.size)

    def push(self, stamp_ns: IntArray, omega_radps: FloatArray) -> None:
        """Append samples; shapes ``(n,)`` and ``(n, 2)``."""
        t = np.asarray(stamp_ns, dtype=np.int64)
        om = np.asarray(omega_radps, dtype=np.float64).reshape(-1, 2)
        if t.size == 0 or om.shape[0] != t.size:
            self.skipped += int(t.size)
            return
        floor = self._stamp[-1] if self._stamp.size else np.iinfo(np.int64).min
        ok = np.isfinite(om).all(axis=1) & (t >= floor)
        if t.size > 1:
            ok[1:] &= t[1:] >= t[:-1]
        self.skipped += int((~ok).sum())
        self._stamp = np.concatenate([self._stamp, t[ok]])
        self._omega = np.concatenate([self._omega, om[ok]])

    def query(self, query_ns: IntArray) -> tuple[FloatArray, FloatArray]:
        """Speeds at each query time: ``omega (m, 2)`` and ``std (m, 2)``; NaN when unknown."""
        q = np.asarray(query_ns, dtype=np.int64)
        i = np.searchsorted(self._stamp, q, side="right") - 1
        ok = (
            (i >= 0) & (q - self._stamp[np.maximum(i, 0)] <= self.stale_ns)
            if self._stamp.size
            else (np.zeros(q.size, dtype=bool))
        )
        om = np.full((q.size, 2), np.nan)
        if self._stamp.size:
            om[ok] = self._omega[i[ok]]
            keep = (
                max(0, int(np.searchsorted(self._stamp, q[-1], side="right")) - 2) if q.size else 0
            )
            if keep > 0:
                self._stamp = self._stamp[keep:]
                self._omega = self._omega[keep:]
        std = np.where(np.isfinite(om), self.std_radps, np.nan)
        return om, std
