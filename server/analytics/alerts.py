"""Fleet alerts: sustained wheel slip, degraded GNSS, vehicles gone quiet.

:class:`AlertEngine` is a pipeline sink (``on_estimates(batch)`` on the pipeline thread). It keeps,
per vehicle and alert kind, whether the condition holds and since when (sensor time), opens an
alert once it has held for the kind's hold time and closes it on the first row where it no longer
holds:

=================  =============================================  ============================
kind               condition on one estimate row                  hold
=================  =============================================  ============================
``slip_left``      ``|slip_left_pct| > alert_threshold_pct``      ``alert_hold_s``
``slip_right``     same for the right wheel                       same
``gnss_degraded``  ``flags & EstimateFlag.DEGRADED`` (GNSS lost)  ``gnss_hold_s``
``stale``          no row for ``stale_after_s`` of wall time      found by ``check_stale``
``storage_down``   the server's database is unreachable/full      set by the runtime
``zenoh_down``     the server has no Zenoh router                 set by the runtime
=================  =============================================  ============================

The last two are about the server itself: their ``vehicle_id`` is ``""`` (:data:`SYSTEM`) and their
stamps are wall-clock times (:meth:`AlertEngine.set_system_condition`).

(``alert_threshold_pct`` and ``alert_hold_s`` from the vehicle's ``SlipConfig``.)

A NaN slip (standstill, invalid) does not hold. ``start_ns`` is the sensor stamp where the
condition began (for ``stale``: the vehicle's last stamp), ``end_ns`` where it stopped (for
``stale``: the first new stamp). ``peak`` is the largest ``|slip|`` (percent) seen in a slip alert.

Every open and close is passed to ``publish(vehicle_id, event)`` when given: ``event`` is
``Alert.to_dict()`` plus ``"event": "open" | "close"``; the runtime puts it, JSON-encoded, on the
Zenoh key ``<prefix>/<vehicle_id>/alerts``. ``publish`` runs on the calling thread (pipeline or
the stale-check thread) and must not block; exceptions it raises are logged and counted.

Closed alerts are kept in a bounded deque (``max_closed``), newest last.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from enum import IntEnum, StrEnum
from typing import Any

import numpy as np

from estimator.config import SlipConfig
from estimator.types import EstimateBatch, EstimateFlag

__all__ = ["SYSTEM", "Alert", "AlertEngine", "AlertKind", "PublishHook"]

_log = logging.getLogger(__name__)

PublishHook = Callable[[str, dict[str, Any]], None]


class AlertKind(StrEnum):
    """What an alert is about."""

    SLIP_LEFT = "slip_left"
    SLIP_RIGHT = "slip_right"
    GNSS_DEGRADED = "gnss_degraded"
    STALE = "stale"
    STORAGE_DOWN = "storage_down"
    ZENOH_DOWN = "zenoh_down"


#: ``vehicle_id`` of alerts about the server itself rather than a vehicle.
SYSTEM = ""


class _K(IntEnum):
    """Column of a row condition in the per-vehicle state arrays."""

    SLIP_LEFT = 0
    SLIP_RIGHT = 1
    GNSS = 2


_KIND_OF = {
    _K.SLIP_LEFT: AlertKind.SLIP_LEFT,
    _K.SLIP_RIGHT: AlertKind.SLIP_RIGHT,
    _K.GNSS: AlertKind.GNSS_DEGRADED,
}
_NK = len(_K)


@dataclass(frozen=True, slots=True)
class Alert:
    """One alert; ``end_ns`` is None while it is open."""

    id: int
    vehicle_id: str
    kind: AlertKind
    start_ns: int
    end_ns: int | None
    opened_wall_ns: int
    threshold: float | None = None
    peak: float | None = None

    @property
    def is_open(self) -> bool:
        return self.end_ns is None

    def to_dict(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "vehicle_id": self.vehicle_id,
            "kind": self.kind.value,
            "start_ns": self.start_ns,
            "end_ns": self.end_ns,
            "open": self.is_open,
            "opened_wall_ns": self.opened_wall_ns,
            "threshold": self.threshold,
            "peak": self.peak,
        }


class AlertEngine:
    """Open and close alerts from estimate rows (a thread-safe pipeline sink).

    Parameters
    ----------
    slip_config_for : callable, optional
        ``vehicle_id -> SlipConfig``, asked once when a vehicle is first seen (the runtime passes a
        lookup in the vehicle registry). Default: ``SlipConfig()`` for every vehicle. Change a
        vehicle's later with :meth:`set_slip_config`.
    gnss_hold_s : float
        GNSS must be degraded this long (sensor time) before an alert opens.
    stale_after_s : float
        Wall time without a row after which :meth:`check_stale` opens a ``stale`` alert.
    publish : callable, optional
        ``publish(vehicle_id, event_dict)`` on every open and close.
    clock_ns : callable
        Wall clock (injected in tests).
    max_closed : int
        How many closed alerts are kept.
    """

    def __init__(
        self,
        *,
        slip_config_for: Callable[[str], SlipConfig] | None = None,
        gnss_hold_s: float = 2.0,
        stale_after_s: float = 10.0,
        publish: PublishHook | None = None,
        clock_ns: Callable[[], int] = time.time_ns,
        max_closed: int = 10_000,
    ) -> None:
        if gnss_hold_s < 0 or stale_after_s <= 0 or max_closed < 1:
            raise ValueError("need gnss_hold_s >= 0, stale_after_s > 0, max_closed >= 1")
        self._config_for = slip_config_for or (lambda _vid: SlipConfig())
        self.gnss_hold_s = float(gnss_hold_s)
        self.stale_after_s = float(stale_after_s)
        self.publish = publish
        self._clock_ns = clock_ns
        self._lock = threading.Lock()
        self._ids: list[str] = []
        self._slot: dict[str, int] = {}
        self._free: list[int] = []  # slots of forgotten vehicles, reused first
        n = 64
        self._thr = np.zeros(n)  # slip threshold, percent
        self._hold_ns = np.zeros((n, _NK), dtype=np.int64)
        self._active = np.zeros((n, _NK), dtype=bool)  # condition held on the newest row
        self._since = np.zeros((n, _NK), dtype=np.int64)
        self._run_peak = np.zeros((n, _NK))  # largest |slip| of the current run, percent
        self._open = np.full((n, _NK), -1, dtype=np.int64)  # id of the open alert or -1
        self._last_stamp = np.zeros(n, dtype=np.int64)
        self._last_arrival = np.zeros(n, dtype=np.int64)
        self._stale_open: dict[str, int] = {}
        self._system_open: dict[AlertKind, int] = {}
        self._open_alerts: dict[int, Alert] = {}
        self._open_pos: dict[int, tuple[int, int]] = {}  # open alert id -> (slot, kind column)
        self._closed: deque[Alert] = deque(maxlen=max_closed)
        self._next_id = 1
        self.publish_errors = 0
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    # ---------------------------------------------------------------- configuration
    def set_slip_config(self, vehicle_id: str, config: SlipConfig) -> None:
        """Use ``config``'s threshold and hold for this vehicle from now on."""
        with self._lock:
            s = self._slot_of(vehicle_id)
            self._apply_config(s, config)

    def _apply_config(self, s: int, config: SlipConfig) -> None:
        self._thr[s] = config.alert_threshold_pct
        hold = round(config.alert_hold_s * 1e9)
        self._hold_ns[s] = (hold, hold, round(self.gnss_hold_s * 1e9))

    def _slot_of(self, vehicle_id: str) -> int:
        s = self._slot.get(vehicle_id)
        if s is not None:
            return s
        if self._free:
            s = self._free.pop()
            self._ids[s] = vehicle_id
            self._slot[vehicle_id] = s
            self._apply_config(s, self._config_for(vehicle_id))
            return s
        s = len(self._ids)
        if s >= self._thr.shape[0]:
            n = 2 * s

            def grow(a: np.ndarray, fill: float | int | bool) -> np.ndarray:
                extra = np.full((n - a.shape[0], *a.shape[1:]), fill, dtype=a.dtype)
                return np.concatenate([a, extra])

            self._thr = grow(self._thr, 0.0)
            self._hold_ns = grow(self._hold_ns, 0)
            self._active = grow(self._active, False)
            self._since = grow(self._since, 0)
            self._run_peak = grow(self._run_peak, 0.0)
            self._open = grow(self._open, -1)
            self._last_stamp = grow(self._last_stamp, 0)
            self._last_arrival = grow(self._last_arrival, 0)
        self._ids.append(vehicle_id)
        self._slot[vehicle_id] = s
        self._apply_config(s, self._config_for(vehicle_id))
        return s

    # ---------------------------------------------------------------- sink
    def on_estimates(self, batch: Sequence[tuple[str, np.ndarray]]) -> None:
        """Update alert state from ``[(vehicle_id, rows of ESTIMATE_DTYPE), ...]``.

        Vectorised over the batch; only vehicles where a condition changes (or waits out its hold
        time) are walked row by row.
        """
        now = self._clock_ns()
        joined = EstimateBatch.of(batch)
        if not joined:
            return
        events: list[tuple[str, str, Alert]] = []
        with self._lock:
            slots = np.array([self._slot_of(v) for v in joined.ids], dtype=np.int64)
            rows, slot = joined.grouped(slots)
            stamp = rows["stamp_ns"].astype(np.int64)
            cond = np.empty((rows.shape[0], _NK), dtype=bool)
            thr = self._thr[slot]
            with np.errstate(invalid="ignore"):
                cond[:, _K.SLIP_LEFT] = np.abs(rows["slip_left_pct"]) > thr
                cond[:, _K.SLIP_RIGHT] = np.abs(rows["slip_right_pct"]) > thr
            cond[:, _K.GNSS] = (rows["flags"].astype(np.int64) & int(EstimateFlag.DEGRADED)) != 0
            first = np.r_[True, slot[1:] != slot[:-1]]
            prev = np.empty_like(cond)
            prev[1:] = cond[:-1]
            prev[first] = self._active[slot[first]]
            changed: np.ndarray = (cond != prev).any(axis=1)
            last = np.r_[slot[1:] != slot[:-1], True]
            s_last, t_last = slot[last], stamp[last]
            # vehicles whose hold time runs out in this batch
            due = np.asarray(
                np.any(
                    self._active[s_last]
                    & (self._open[s_last] < 0)
                    & (t_last[:, None] - self._since[s_last] >= self._hold_ns[s_last]),
                    axis=1,
                )
            )
            busy = np.unique(np.r_[slot[changed], s_last[due]])
            quiet = ~np.isin(slot, busy) if busy.size else np.ones(slot.shape[0], dtype=bool)
            if quiet.any():  # steady vehicles: only the peaks of running slip episodes move
                self._track_peaks(slot[quiet], cond[quiet], rows[quiet])
            if busy.size:  # each vehicle's rows are one run: walk the busy runs
                lo = np.flatnonzero(first)
                hi = np.r_[lo[1:], slot.shape[0]]
                walk = np.isin(slot[lo], busy)
                for s_, a_, b_ in zip(
                    slot[lo[walk]].tolist(), lo[walk].tolist(), hi[walk].tolist(), strict=True
                ):
                    events.extend(self._walk(s_, stamp[a_:b_], cond[a_:b_], rows[a_:b_], now))
            self._last_stamp[s_last] = t_last
            self._last_arrival[s_last] = now
            if self._stale_open:
                for s_ in s_last.tolist():
                    vid = self._ids[s_]
                    if vid in self._stale_open:
                        aid = self._stale_open.pop(vid)
                        events.append(("close", vid, self._close(aid, int(self._last_stamp[s_]))))
        self._emit(events)

    def _track_peaks(self, slot: np.ndarray, cond: np.ndarray, rows: np.ndarray) -> None:
        """Raise the running |slip| peak of each active slip episode (vectorised)."""
        for k, field in ((_K.SLIP_LEFT, "slip_left_pct"), (_K.SLIP_RIGHT, "slip_right_pct")):
            m = cond[:, k]
            if m.any():
                np.maximum.at(self._run_peak[:, k], slot[m], np.abs(rows[field][m]))

    def _walk(
        self, s: int, stamp: np.ndarray, cond: np.ndarray, rows: np.ndarray, now: int
    ) -> list[tuple[str, str, Alert]]:
        """Row-by-row state machine for one vehicle (only where something changes)."""
        events: list[tuple[str, str, Alert]] = []
        vid = self._ids[s]
        mags = {
            _K.SLIP_LEFT: np.abs(rows["slip_left_pct"]).tolist(),
            _K.SLIP_RIGHT: np.abs(rows["slip_right_pct"]).tolist(),
        }
        stamps = stamp.tolist()
        for k in _K:
            col = cond[:, k].tolist()
            hold = int(self._hold_ns[s, k])
            for i, c in enumerate(col):
                t = stamps[i]
                if c:
                    if not self._active[s, k]:
                        self._active[s, k] = True
                        self._since[s, k] = t
                        self._run_peak[s, k] = 0.0
                    if k in mags:
                        self._run_peak[s, k] = max(self._run_peak[s, k], mags[k][i])
                    aid = int(self._open[s, k])
                    if aid < 0 and t - int(self._since[s, k]) >= hold:
                        alert = Alert(
                            id=self._next_id,
                            vehicle_id=vid,
                            kind=_KIND_OF[k],
                            start_ns=int(self._since[s, k]),
                            end_ns=None,
                            opened_wall_ns=now,
                            threshold=float(self._thr[s]) if k != _K.GNSS else None,
                            peak=round(float(self._run_peak[s, k]), 3) if k in mags else None,
                        )
                        self._next_id += 1
                        self._open_alerts[alert.id] = alert
                        self._open_pos[alert.id] = (s, int(k))
                        self._open[s, k] = alert.id
                        aid = alert.id
                        events.append(("open", vid, alert))
                elif self._active[s, k]:
                    self._active[s, k] = False
                    aid = int(self._open[s, k])
                    if aid >= 0:
                        self._open[s, k] = -1
                        events.append(("close", vid, self._close(aid, t)))
        # an alert opened in this batch carries its peak so far in the open event
        return [(e, v, self._with_peak(a)) for e, v, a in events]

    def _with_peak(self, alert: Alert) -> Alert:
        """An open slip alert with its running peak filled in."""
        pos = self._open_pos.get(alert.id)
        if pos is None or alert.kind not in (AlertKind.SLIP_LEFT, AlertKind.SLIP_RIGHT):
            return alert
        return replace(alert, peak=round(float(self._run_peak[pos]), 3))

    def _close(self, aid: int, end_ns: int) -> Alert:
        alert = self._with_peak(self._open_alerts.pop(aid))
        self._open_pos.pop(aid, None)
        alert = replace(alert, end_ns=end_ns)
        self._closed.append(alert)
        return alert

    def forget(self, vehicle_id: str) -> bool:
        """Drop a vehicle (deleted from the fleet): close its open alerts at its last stamp and
        forget its state. Closed alerts stay in the history. False if the vehicle is unknown."""
        events: list[tuple[str, str, Alert]] = []
        with self._lock:
            s = self._slot.pop(vehicle_id, None)
            if s is None:
                return False
            end = int(self._last_stamp[s])
            for k in _K:
                aid = int(self._open[s, k])
                if aid >= 0:
                    events.append(("close", vehicle_id, self._close(aid, end)))
            if vehicle_id in self._stale_open:
                events.append(
                    ("close", vehicle_id, self._close(self._stale_open.pop(vehicle_id), end))
                )
            self._open[s] = -1
            self._active[s] = False
            self._since[s] = 0
            self._run_peak[s] = 0.0
            self._last_stamp[s] = 0
            self._last_arrival[s] = 0
            self._ids[s] = ""
            self._free.append(s)
        self._emit(events)
        return True

    def set_system_condition(
        self, kind: AlertKind, active: bool, now_ns: int | None = None
    ) -> Alert | None:
        """Open (``active``) or close the server-wide alert ``kind``; repeated calls with the same
        state do nothing. Returns the alert opened or closed, if any."""
        now = self._clock_ns() if now_ns is None else now_ns
        events: list[tuple[str, str, Alert]] = []
        with self._lock:
            aid = self._system_open.get(kind)
            if active and aid is None:
                alert = Alert(
                    id=self._next_id,
                    vehicle_id=SYSTEM,
                    kind=kind,
                    start_ns=now,
                    end_ns=None,
                    opened_wall_ns=now,
                )
                self._next_id += 1
                self._open_alerts[alert.id] = alert
                self._system_open[kind] = alert.id
                events.append(("open", SYSTEM, alert))
            elif not active and aid is not None:
                del self._system_open[kind]
                events.append(("close", SYSTEM, self._close(aid, now)))
        self._emit(events)
        return events[0][2] if events else None

    def check_stale(self, now_ns: int | None = None) -> list[Alert]:
        """Open a ``stale`` alert for every vehicle silent for ``stale_after_s``; return them."""
        now = self._clock_ns() if now_ns is None else now_ns
        events: list[tuple[str, str, Alert]] = []
        limit = round(self.stale_after_s * 1e9)
        with self._lock:
            n = len(self._ids)
            quiet = np.flatnonzero(now - self._last_arrival[:n] > limit)
            for s in quiet.tolist():
                vid = self._ids[s]
                if vid not in self._slot or vid in self._stale_open:
                    continue
                alert = Alert(
                    id=self._next_id,
                    vehicle_id=vid,
                    kind=AlertKind.STALE,
                    start_ns=int(self._last_stamp[s]),
                    end_ns=None,
                    opened_wall_ns=now,
                )
                self._next_id += 1
                self._open_alerts[alert.id] = alert
                self._stale_open[vid] = alert.id
                events.append(("open", vid, alert))
        self._emit(events)
        return [a for _, _, a in events]

    def _emit(self, events: list[tuple[str, str, Alert]]) -> None:
        if self.publish is None:
            return
        for event, vid, alert in events:
            try:
                self.publish(vid, {"event": event, **alert.to_dict()})
            except Exception:
                self.publish_errors += 1
                _log.exception("alert publish failed for %s", vid)

    # ---------------------------------------------------------------- reading
    def alerts(
        self, *, state: str = "all", vehicle_id: str | None = None, limit: int = 500
    ) -> list[Alert]:
        """Alerts, newest first; ``state`` is ``open``, ``closed`` or ``all``."""
        if state not in ("open", "closed", "all"):
            raise ValueError("state must be open, closed or all")
        with self._lock:
            found: list[Alert] = []
            if state in ("open", "all"):
                found.extend(self._with_peak(a) for a in self._open_alerts.values())
            if state in ("closed", "all"):
                found.extend(self._closed)
        if vehicle_id is not None:
            found = [a for a in found if a.vehicle_id == vehicle_id]
        found.sort(key=lambda a: a.id, reverse=True)
        return found[:limit]

    def open_count(self) -> int:
        with self._lock:
            return len(self._open_alerts)

    # ---------------------------------------------------------------- stale-check thread
    def start(self, interval_s: float = 1.0) -> None:
        """Run :meth:`check_stale` every ``interval_s`` on a daemon thread until :meth:`stop`."""
        if self._thread is not None:
            return
        self._stop.clear()

        def loop() -> None:
            while not self._stop.wait(interval_s):
                self.check_stale()

        self._thread = threading.Thread(target=loop, name="alert-stale-check", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        if self._thread is None:
            return
        self._stop.set()
        self._thread.join(timeout=5.0)
        self._thread = None
