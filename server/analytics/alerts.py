"""Fleet alerts from any estimator's rows: sustained slip, degraded rows, vehicles gone quiet.

:class:`AlertEngine` is a pipeline sink (``on_estimates(batch)`` on the pipeline thread, once per
estimator per tick). Its rules name a channel of the batch's
:class:`estimator.spec.EstimatorSpec`, never a column. It keeps, per vehicle and condition,
whether the condition holds and since when (sensor time), opens an alert once it has held for
the condition's hold time and closes it on the first row where it no longer holds:

==============================  ===========================================  =================
kind                            condition on one row of estimator ``e``      hold
==============================  ===========================================  =================
``slip:<e>:<channel key>``      ``|slip| > alert_threshold_pct`` of one of    ``alert_hold_s``
                                ``e``'s slip channels
``flag:<e>:<FLAG>``             one of ``e``'s ``degraded_flags`` is set      ``flag_hold_s``
``rule:<e>:<key>``              one of ``e``'s ``alerts`` (an                 the rule's
                                :class:`~estimator.spec.AlertRule`: a field   ``hold_s``
                                above or below its limit, flags set or not)
``stale``                       no row of any estimator for                  ``check_stale``
                                ``stale_after_s`` of wall time, once the
                                vehicle has sent a row (a vehicle that has
                                sent none is not stale: it has no last stamp)
``storage_down``                the server's database is unreachable/full    set by the runtime
``zenoh_down``                  the server has no Zenoh router               set by the runtime
==============================  ===========================================  =================

The last two are about the server itself: their ``vehicle_id`` is ``""`` (:data:`SYSTEM`) and their
stamps are wall-clock times (:meth:`AlertEngine.set_system_condition`).

(``alert_threshold_pct`` and ``alert_hold_s`` from the vehicle's ``SlipConfig``.) A spec's rule
that names a slip channel takes the place of that channel's ``slip`` rule (a crawler's track
slip band: a braked track's −100 % in a pivot is no alert). A rule's limit and hold time are
the spec's unless ``rule_limits`` sets them (``{"tracked:long_dead_reckoning": {"hold_s":
60}}``). Examples: a crawler's track slip out of its band, dead reckoning held too long, a
crawler on a steep side slope (its ``|roll|``), a low friction μ.

A NaN slip (standstill, invalid) does not hold. ``start_ns`` is the sensor stamp where the
condition began (for ``stale``: the vehicle's last stamp), ``end_ns`` where it stopped (for
``stale``: the first new stamp). ``peak`` is the largest ``|slip|`` (percent) seen in a slip alert,
and a rule's most extreme value past its limit (the lowest μ of a low-μ alert).
An alert names its ``estimator`` and ``channel`` (slip channel key or flag name; None for the
others).

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
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from enum import StrEnum
from typing import Any

import numpy as np

from estimator.config import SlipConfig
from estimator.spec import AlertRule, EstimatorSpec
from estimator.types import EstimateBatch

__all__ = [
    "SYSTEM",
    "Alert",
    "AlertEngine",
    "AlertKind",
    "PublishHook",
    "flag_kind",
    "rule_kind",
    "slip_kind",
]

_log = logging.getLogger(__name__)

PublishHook = Callable[[str, dict[str, Any]], None]


class AlertKind(StrEnum):
    """Alert kinds that name no estimator channel (those: :func:`slip_kind`, :func:`flag_kind`)."""

    STALE = "stale"
    STORAGE_DOWN = "storage_down"
    ZENOH_DOWN = "zenoh_down"


def slip_kind(estimator: str, channel: str) -> str:
    """Kind of a slip alert on ``estimator``'s slip channel ``channel``: ``slip:<e>:<key>``."""
    return f"slip:{estimator}:{channel}"


def flag_kind(estimator: str, flag: str) -> str:
    """Kind of an alert on ``estimator``'s degraded flag ``flag``: ``flag:<e>:<FLAG>``."""
    return f"flag:{estimator}:{flag}"


def rule_kind(estimator: str, key: str) -> str:
    """Kind of an alert on ``estimator``'s spec rule ``key``: ``rule:<e>:<key>``."""
    return f"rule:{estimator}:{key}"


#: ``vehicle_id`` of alerts about the server itself rather than a vehicle.
SYSTEM = ""


@dataclass(frozen=True, slots=True)
class Alert:
    """One alert; ``end_ns`` is None while it is open."""

    id: int
    vehicle_id: str
    kind: str
    start_ns: int
    end_ns: int | None
    opened_wall_ns: int
    threshold: float | None = None
    peak: float | None = None
    estimator: str | None = None
    channel: str | None = None

    @property
    def is_open(self) -> bool:
        return self.end_ns is None

    def to_dict(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "vehicle_id": self.vehicle_id,
            "kind": str(self.kind),
            "estimator": self.estimator,
            "channel": self.channel,
            "start_ns": self.start_ns,
            "end_ns": self.end_ns,
            "open": self.is_open,
            "opened_wall_ns": self.opened_wall_ns,
            "threshold": self.threshold,
            "peak": self.peak,
        }


@dataclass(frozen=True, slots=True)
class _Rule:
    """One condition on a row of a spec: the vehicle's slip threshold on a slip channel's
    ``|field|`` (``slip``), or ``field`` (``|field|`` with ``absolute``) times ``sign``
    above ``limit`` (``sign`` -1: the field below ``-limit``), with the ``when`` bits set and
    the ``unless`` bits clear. ``hold_ns`` None: the vehicle's slip hold (slip rules) or the
    engine's flag hold."""

    kind: str
    channel: str
    field: str | None = None
    slip: bool = False
    absolute: bool = False
    sign: float = 1.0
    limit: float = 0.0
    when: int = 0
    unless: int = 0
    hold_ns: int | None = None

    @property
    def threshold(self) -> float | None:
        """The limit an alert of this rule reports (slip rules: the vehicle's)."""
        return None if self.field is None or self.slip else self.sign * self.limit


def _spec_rule(spec: EstimatorSpec, rule: AlertRule) -> _Rule:
    mask = 0
    for name in rule.when:
        mask |= spec.flag_mask(name)
    unless = 0
    for name in rule.unless:
        unless |= spec.flag_mask(name)
    sign, limit = (1.0, rule.above) if rule.above is not None else (-1.0, rule.below)
    return _Rule(
        rule_kind(spec.name, rule.key),
        rule.key,
        field=rule.field,
        absolute=rule.absolute,
        sign=sign,
        limit=0.0 if limit is None else sign * limit,
        when=mask,
        unless=unless,
        hold_ns=round(rule.hold_s * 1e9),
    )


def _limited(rule: AlertRule, values: Mapping[str, float]) -> AlertRule:
    """``rule`` with the limit and hold time of ``values`` (one of ``rule_limits``)."""
    side = "above" if rule.above is not None else "below"
    if rule.field is None and ("above" in values or "below" in values):
        raise ValueError(f"alert rule {rule.key} has no field to limit")
    if rule.field is not None and ({"above", "below"} - {side}) & set(values):
        raise ValueError(f"alert rule {rule.key} alerts {side} its limit")
    return replace(
        rule,
        hold_s=values.get("hold_s", rule.hold_s),
        above=values.get("above", rule.above),
        below=values.get("below", rule.below),
    )


def _rules(
    spec: EstimatorSpec, limits: Mapping[str, Mapping[str, float]] = {}
) -> tuple[_Rule, ...]:
    """The spec's rules: its slip channels' (but those a spec rule takes the place of), its
    degraded flags', its own (``limits`` keyed ``<estimator>:<key>`` overriding theirs)."""
    own = [_limited(a, limits.get(f"{spec.name}:{a.key}", {})) for a in spec.alerts]
    taken = {a.slip for a in own}
    slips = [
        _Rule(slip_kind(spec.name, c.key), c.key, field=c.field, slip=True, absolute=True)
        for c in spec.slips
        if c.key not in taken
    ]
    flags = [_Rule(flag_kind(spec.name, f), f, when=spec.flag_mask(f)) for f in spec.degraded_flags]
    return (*slips, *flags, *(_spec_rule(spec, a) for a in own))


class _SpecState:
    """Per-vehicle state of one estimator's rules: arrays of shape (slots, rules)."""

    def __init__(self, spec: EstimatorSpec, limits: Mapping[str, Mapping[str, float]]) -> None:
        self.spec = spec
        self.rules = _rules(spec, limits)
        k = len(self.rules)
        self.is_slip = np.array([r.slip for r in self.rules], dtype=bool)
        self.has_peak = np.array([r.field is not None for r in self.rules], dtype=bool)
        self.active = np.zeros((0, k), dtype=bool)  # condition held on the newest row
        self.since = np.zeros((0, k), dtype=np.int64)
        self.run_peak = np.zeros((0, k))  # largest excursion of the current run (sign applied)
        self.open = np.full((0, k), -1, dtype=np.int64)  # id of the open alert or -1

    def ensure(self, n: int) -> None:
        """Room for ``n`` vehicle slots."""
        have = self.active.shape[0]
        if n <= have:
            return
        n = max(n, 2 * have, 64)

        def grow(a: np.ndarray, fill: float | int | bool) -> np.ndarray:
            extra = np.full((n - a.shape[0], *a.shape[1:]), fill, dtype=a.dtype)
            return np.concatenate([a, extra])

        self.active = grow(self.active, False)
        self.since = grow(self.since, 0)
        self.run_peak = grow(self.run_peak, -np.inf)
        self.open = grow(self.open, -1)

    def reset(self, s: int) -> None:
        if s < self.active.shape[0]:
            self.active[s] = False
            self.since[s] = 0
            self.run_peak[s] = -np.inf
            self.open[s] = -1

    def conditions(self, rows: np.ndarray, thr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(cond, mag)``, shape (n, rules) each: whether each rule holds on each row, and
        its field's value times the rule's sign (``|slip|`` of slip rules; 0 for flag-only
        rules). ``thr``: each row's slip threshold, shape (n,)."""
        n = rows.shape[0]
        cond = np.ones((n, len(self.rules)), dtype=bool)
        mag = np.zeros((n, len(self.rules)))
        flags = rows["flags"].astype(np.int64) if self.spec.has_field("flags") else None
        for k, rule in enumerate(self.rules):
            if rule.field is not None:
                v = rows[rule.field]
                mag[:, k] = rule.sign * (np.abs(v) if rule.absolute else v)
                with np.errstate(invalid="ignore"):
                    cond[:, k] = mag[:, k] > (thr if rule.slip else rule.limit)
            if rule.when or rule.unless:
                if flags is None:
                    cond[:, k] = False
                    continue
                cond[:, k] &= (flags & rule.when) == rule.when
                cond[:, k] &= (flags & rule.unless) == 0
        return cond, mag


_LIMIT_KEYS = frozenset({"above", "below", "hold_s"})


def _checked_limits(
    limits: Mapping[str, Mapping[str, float]],
) -> dict[str, dict[str, float]]:
    """``rule_limits`` checked: keys ``<estimator>:<rule key>``, values of ``above``,
    ``below`` and ``hold_s`` only (a rule keeps its direction: one limit of the two)."""
    out: dict[str, dict[str, float]] = {}
    for key, values in limits.items():
        if key.count(":") != 1 or not set(values) <= _LIMIT_KEYS:
            raise ValueError(f"rule_limits[{key!r}]: '<estimator>:<rule>' to {sorted(_LIMIT_KEYS)}")
        if values.get("hold_s", 0.0) < 0:
            raise ValueError(f"rule_limits[{key!r}]: hold_s must be >= 0")
        out[key] = {k: float(v) for k, v in values.items()}
    return out


class AlertEngine:
    """Open and close alerts from any estimator's rows (a thread-safe pipeline sink).

    Parameters
    ----------
    slip_config_for : callable, optional
        ``vehicle_id -> SlipConfig``, asked once when a vehicle is first seen (the runtime passes a
        lookup in the vehicle registry). Default: ``SlipConfig()`` for every vehicle. Change a
        vehicle's later with :meth:`set_slip_config`.
    flag_hold_s : float
        A degraded flag must hold this long (sensor time) before an alert opens.
    stale_after_s : float
        Wall time without a row after which :meth:`check_stale` opens a ``stale`` alert.
    publish : callable, optional
        ``publish(vehicle_id, event_dict)`` on every open and close.
    clock_ns : callable
        Wall clock (injected in tests).
    max_closed : int
        How many closed alerts are kept.
    rule_limits : mapping, optional
        ``{"<estimator>:<rule key>": {"above" | "below" | "hold_s": value}}``: the specs' own
        rules (:attr:`estimator.spec.EstimatorSpec.alerts`) with other limits or hold times.
    """

    def __init__(
        self,
        *,
        slip_config_for: Callable[[str], SlipConfig] | None = None,
        flag_hold_s: float = 2.0,
        stale_after_s: float = 10.0,
        publish: PublishHook | None = None,
        clock_ns: Callable[[], int] = time.time_ns,
        max_closed: int = 10_000,
        rule_limits: Mapping[str, Mapping[str, float]] | None = None,
    ) -> None:
        if flag_hold_s < 0 or stale_after_s <= 0 or max_closed < 1:
            raise ValueError("need flag_hold_s >= 0, stale_after_s > 0, max_closed >= 1")
        self._rule_limits = _checked_limits(rule_limits or {})
        self._config_for = slip_config_for or (lambda _vid: SlipConfig())
        self.flag_hold_ns = round(flag_hold_s * 1e9)
        self.stale_after_s = float(stale_after_s)
        self.publish = publish
        self._clock_ns = clock_ns
        self._lock = threading.Lock()
        self._ids: list[str] = []
        self._slot: dict[str, int] = {}
        self._free: list[int] = []  # slots of forgotten vehicles, reused first
        n = 64
        self._thr = np.zeros(n)  # slip threshold, percent
        self._slip_hold_ns = np.zeros(n, dtype=np.int64)
        self._last_stamp = np.zeros(n, dtype=np.int64)
        self._last_arrival = np.zeros(n, dtype=np.int64)
        self._has_row = np.zeros(n, dtype=bool)  # a row arrived since the slot was taken
        self._specs: dict[str, _SpecState] = {}
        self._stale_open: dict[str, int] = {}
        self._system_open: dict[AlertKind, int] = {}
        self._open_alerts: dict[int, Alert] = {}
        # open alert id -> (estimator, slot, rule column)
        self._open_pos: dict[int, tuple[str, int, int]] = {}
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
        self._slip_hold_ns[s] = round(config.alert_hold_s * 1e9)

    def _slot_of(self, vehicle_id: str) -> int:
        s = self._slot.get(vehicle_id)
        if s is not None:
            return s
        if self._free:
            s = self._free.pop()
            self._ids[s] = vehicle_id
        else:
            s = len(self._ids)
            if s >= self._thr.shape[0]:  # double every per-vehicle array
                self._thr = np.r_[self._thr, np.zeros(s)]
                self._slip_hold_ns = np.r_[self._slip_hold_ns, np.zeros(s, np.int64)]
                self._last_stamp = np.r_[self._last_stamp, np.zeros(s, np.int64)]
                self._last_arrival = np.r_[self._last_arrival, np.zeros(s, np.int64)]
                self._has_row = np.r_[self._has_row, np.zeros(s, bool)]
            self._ids.append(vehicle_id)
        self._slot[vehicle_id] = s
        self._apply_config(s, self._config_for(vehicle_id))
        return s

    def _state(self, spec: EstimatorSpec) -> _SpecState:
        state = self._specs.get(spec.name)
        if state is None or state.spec is not spec:
            state = self._specs[spec.name] = _SpecState(spec, self._rule_limits)
        state.ensure(len(self._ids))
        return state

    # ---------------------------------------------------------------- sink
    def on_estimates(self, batch: EstimateBatch) -> None:
        """Update alert state from one estimator's rows of several vehicles.

        Vectorised over the batch; only vehicles where a condition changes (or waits out its hold
        time) are walked row by row.
        """
        if not batch:
            return
        now = self._clock_ns()
        events: list[tuple[str, str, Alert]] = []
        with self._lock:
            slots = np.array([self._slot_of(v) for v in batch.ids], dtype=np.int64)
            st = self._state(batch.spec)
            rows, slot = batch.grouped(slots)
            stamp = rows["stamp_ns"].astype(np.int64)
            first = np.r_[True, slot[1:] != slot[:-1]]
            last = np.r_[slot[1:] != slot[:-1], True]
            if st.rules:
                events.extend(self._apply_rules(st, rows, slot, stamp, first, last, now))
            s_last, t_last = slot[last], stamp[last]
            self._last_stamp[s_last] = np.maximum(self._last_stamp[s_last], t_last)
            self._last_arrival[s_last] = now
            self._has_row[s_last] = True
            if self._stale_open:
                for s_ in s_last.tolist():
                    vid = self._ids[s_]
                    if vid in self._stale_open:
                        aid = self._stale_open.pop(vid)
                        events.append(("close", vid, self._close(aid, int(self._last_stamp[s_]))))
        self._emit(events)

    def _apply_rules(
        self,
        st: _SpecState,
        rows: np.ndarray,
        slot: np.ndarray,
        stamp: np.ndarray,
        first: np.ndarray,
        last: np.ndarray,
        now: int,
    ) -> list[tuple[str, str, Alert]]:
        """Run one estimator's rules over its rows (each vehicle's rows one run, ``first`` /
        ``last`` marking the runs' ends)."""
        cond, mag = st.conditions(rows, self._thr[slot])
        prev = np.empty_like(cond)
        prev[1:] = cond[:-1]
        prev[first] = st.active[slot[first]]
        changed: np.ndarray = (cond != prev).any(axis=1)
        s_last, t_last = slot[last], stamp[last]
        hold = self._hold_ns(st, s_last)
        # vehicles whose hold time runs out in this batch
        due = np.asarray(
            np.any(
                st.active[s_last]
                & (st.open[s_last] < 0)
                & (t_last[:, None] - st.since[s_last] >= hold),
                axis=1,
            )
        )
        busy = np.unique(np.r_[slot[changed], s_last[due]])
        quiet = ~np.isin(slot, busy) if busy.size else np.ones(slot.shape[0], dtype=bool)
        if quiet.any():  # steady vehicles: only the peaks of running slip episodes move
            m = cond[quiet] & st.has_peak
            rr, kk = np.nonzero(m)
            np.maximum.at(st.run_peak, (slot[quiet][rr], kk), mag[quiet][rr, kk])
        events: list[tuple[str, str, Alert]] = []
        if busy.size:  # each vehicle's rows are one run: walk the busy runs
            lo = np.flatnonzero(first)
            hi = np.r_[lo[1:], slot.shape[0]]
            walk = np.isin(slot[lo], busy)
            for s_, a_, b_ in zip(
                slot[lo[walk]].tolist(), lo[walk].tolist(), hi[walk].tolist(), strict=True
            ):
                events.extend(self._walk(st, s_, stamp[a_:b_], cond[a_:b_], mag[a_:b_], now))
        return events

    def _hold_ns(self, st: _SpecState, slots: np.ndarray) -> np.ndarray:
        """Hold time of each rule for each slot, shape (len(slots), rules)."""
        fixed = np.array([self.flag_hold_ns if r.hold_ns is None else r.hold_ns for r in st.rules])
        return np.where(st.is_slip, self._slip_hold_ns[slots][:, None], fixed)

    def _walk(
        self,
        st: _SpecState,
        s: int,
        stamp: np.ndarray,
        cond: np.ndarray,
        mag: np.ndarray,
        now: int,
    ) -> list[tuple[str, str, Alert]]:
        """Row-by-row state machine for one vehicle (only where something changes)."""
        events: list[tuple[str, str, Alert]] = []
        vid = self._ids[s]
        stamps = stamp.tolist()
        holds = self._hold_ns(st, np.array([s]))[0].tolist()
        for k, rule in enumerate(st.rules):
            peaks = rule.field is not None
            threshold = float(self._thr[s]) if rule.slip else rule.threshold
            mags = mag[:, k].tolist()
            for i, c in enumerate(cond[:, k].tolist()):
                t = stamps[i]
                if c:
                    if not st.active[s, k]:
                        st.active[s, k] = True
                        st.since[s, k] = t
                        st.run_peak[s, k] = -np.inf
                    if peaks:
                        st.run_peak[s, k] = max(st.run_peak[s, k], mags[i])
                    if st.open[s, k] < 0 and t - int(st.since[s, k]) >= holds[k]:
                        events.append(("open", vid, self._open(st, s, k, threshold, now)))
                elif st.active[s, k]:
                    st.active[s, k] = False
                    aid = int(st.open[s, k])
                    if aid >= 0:
                        st.open[s, k] = -1
                        events.append(("close", vid, self._close(aid, t)))
        # an alert opened in this batch carries its peak so far in the open event
        return [(e, v, self._with_peak(a)) for e, v, a in events]

    def _open(self, st: _SpecState, s: int, k: int, threshold: float | None, now: int) -> Alert:
        """Open an alert of rule ``k`` for slot ``s``, whose condition has held since
        ``st.since[s, k]`` (``now``: the wall clock, ns)."""
        rule = st.rules[k]
        peak = st.run_peak[s, k]
        alert = Alert(
            id=self._next_id,
            vehicle_id=self._ids[s],
            kind=rule.kind,
            start_ns=int(st.since[s, k]),
            end_ns=None,
            opened_wall_ns=now,
            threshold=threshold,
            peak=round(rule.sign * float(peak), 3) if rule.field is not None else None,
            estimator=st.spec.name,
            channel=rule.channel,
        )
        self._next_id += 1
        self._open_alerts[alert.id] = alert
        self._open_pos[alert.id] = (st.spec.name, s, k)
        st.open[s, k] = alert.id
        return alert

    def _with_peak(self, alert: Alert) -> Alert:
        """An open slip alert with its running peak filled in."""
        pos = self._open_pos.get(alert.id)
        if pos is None or alert.peak is None:
            return alert
        name, s, k = pos
        st = self._specs[name]
        return replace(alert, peak=round(st.rules[k].sign * float(st.run_peak[s, k]), 3))

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
            for st in self._specs.values():
                if s < st.open.shape[0]:
                    for aid in st.open[s][st.open[s] >= 0].tolist():
                        events.append(("close", vehicle_id, self._close(aid, end)))
                st.reset(s)
            if vehicle_id in self._stale_open:
                events.append(
                    ("close", vehicle_id, self._close(self._stale_open.pop(vehicle_id), end))
                )
            self._last_stamp[s] = 0
            self._last_arrival[s] = 0
            self._has_row[s] = False
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
        """Open a ``stale`` alert for every vehicle silent for ``stale_after_s`` since its last
        row; return them. A vehicle known only by its config (no row yet) is never stale."""
        now = self._clock_ns() if now_ns is None else now_ns
        events: list[tuple[str, str, Alert]] = []
        limit = round(self.stale_after_s * 1e9)
        with self._lock:
            n = len(self._ids)
            quiet = np.flatnonzero(self._has_row[:n] & (now - self._last_arrival[:n] > limit))
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
