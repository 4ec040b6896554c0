"""Estimator registry: which estimators exist, which ones each vehicle runs, and routing.

Names map to factories of :class:`estimator.base.FleetEstimator`, one for every spec of the
catalog (:data:`estimator.catalog.SPECS`), imported lazily so the server starts without loading
an estimator nobody runs::

    "mdsf"             -> estimator.mdsf.MdsfFleet                  (ESTIMATE_DTYPE rows)
    "reference_speed"  -> estimator.reference_fleet.ReferenceSpeedFleet
    "friction"         -> estimator.friction.fleet.FrictionFleet
    "tracked"          -> estimator.tracked.TrackedFleet

An estimator's name is its spec's name (checked when it is built): storage, REST and live
views key its rows by it.

A vehicle runs ``config.estimators`` when that is non-empty, otherwise its kind's defaults:

    ============================  ===================================================
    VehicleKind                   default estimators
    ============================  ===================================================
    ``wheeled_rear_drive``        ``("mdsf",)``
    ``tracked``                   ``("tracked",)``
    ``wheeled_4wd_steered``       ``("friction",)``
    ============================  ===================================================

The first one is the vehicle's *primary* (REST's default). :meth:`EstimatorRegistry.advance`
returns one :class:`~estimator.types.EstimateBatch` per estimator; a measurement is pushed only
to the estimators whose ``spec.inputs`` name its stream (:func:`estimator.base.stream_of`).

Isolation: every call that configures, feeds or steps an estimator (``add_vehicle``,
``remove_vehicle``, ``push``, ``align_ticks``, ``advance``; also ``counters``) is guarded on
its own. One that raises is reported to ``on_error(vehicle_id, estimator, operation, exc)``
and costs that vehicle that call only: a
batched ``advance`` that raises is retried on halves of its vehicles down to the one that
fails, so the other vehicles' rows and the other estimators' are all delivered. A config that
an estimator refuses is taken back (:class:`ConfigRefusedError`; the vehicle keeps its old
config). Unknown names raise :class:`UnknownEstimatorError`.

Online calibration: an estimator whose spec declares ``calibrations`` (and implements
:class:`Calibrating`) keeps a vehicle's calibration when the vehicle is registered again (a new
config, a clock re-anchor: taken before, given back after, as the rows carry it), starts a
vehicle it did not hold from the stored calibration the registry was given (``calibrations``,
the newest stored row's, once) and forgets it on :data:`RESET_CALIBRATION` (counted
``calibration_resets`` in its counters, logged).

Rows held back: an estimator that gives rows late (:class:`estimator.base.HoldsRows`, the
tracked estimator's fixed lag) is asked for the vehicle's held rows before a new config starts
it afresh; they come out with the next :meth:`EstimatorRegistry.advance`. A removed (deleted)
vehicle's held rows go with it.

The registry holds one ``FleetEstimator`` per name and is used from one thread (the pipeline).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from typing import Protocol, runtime_checkable

import numpy as np

from estimator.base import (
    STREAMS,
    Anchored,
    FleetEstimator,
    KeepsCounters,
    Pushed,
    TakesCommands,
    held_rows,
    stream_of,
)
from estimator.catalog import SPECS
from estimator.config import VehicleConfig, VehicleKind
from estimator.spec import EstimatorSpec
from estimator.types import EstimateBatch
from server.estimation.calibration import known_calibrations

__all__ = [
    "DEFAULT_FACTORIES",
    "KIND_DEFAULTS",
    "RESET_CALIBRATION",
    "Calibrating",
    "CalibrationValues",
    "ConfigRefusedError",
    "ErrorHandler",
    "EstimatorRegistry",
    "UnknownEstimatorError",
    "estimator_names_for",
]

log = logging.getLogger(__name__)

EstimatorFactory = Callable[[], FleetEstimator]


def _mdsf() -> FleetEstimator:
    from estimator.mdsf import MdsfFleet  # lazy: heavy numerics only when a vehicle runs it

    fleet: FleetEstimator = MdsfFleet()
    return fleet


def _reference_speed() -> FleetEstimator:
    from estimator.reference_fleet import ReferenceSpeedFleet  # lazy, as MDSF

    fleet: FleetEstimator = ReferenceSpeedFleet()
    return fleet


def _friction() -> FleetEstimator:
    from estimator.friction.fleet import FrictionFleet  # lazy, as MDSF

    fleet: FleetEstimator = FrictionFleet()
    return fleet


def _tracked() -> FleetEstimator:
    from estimator.tracked import TrackedFleet  # lazy, as MDSF

    fleet: FleetEstimator = TrackedFleet()
    return fleet


DEFAULT_FACTORIES: Mapping[str, EstimatorFactory] = {
    "mdsf": _mdsf,
    "reference_speed": _reference_speed,
    "friction": _friction,
    "tracked": _tracked,
}

KIND_DEFAULTS: Mapping[VehicleKind, tuple[str, ...]] = {
    VehicleKind.WHEELED_REAR_DRIVE: ("mdsf",),
    VehicleKind.TRACKED: ("tracked",),
    VehicleKind.WHEELED_4WD_STEERED: ("friction",),
}


#: A vehicle's calibration as its estimator's rows carry it: ``{field: value}`` of the spec's
#: ``calibrations`` (values and stds).
CalibrationValues = Mapping[str, float]

#: The command key (never one of a spec's ``commands``) that makes an estimator forget a
#: vehicle's calibration and learn it anew.
RESET_CALIBRATION = "reset_calibration"


@runtime_checkable
class Calibrating(Protocol):
    """What an estimator whose spec declares ``calibrations`` implements (state out and in)."""

    def calibration_fields(self, vehicle_id: str) -> dict[str, float]: ...

    def restore_calibration_fields(self, vehicle_id: str, values: CalibrationValues) -> None: ...

    def reset_calibration(self, vehicle_id: str) -> None: ...


class UnknownEstimatorError(ValueError):
    """A vehicle config names an estimator the registry does not know."""


def estimator_names_for(
    config: VehicleConfig,
    known: Mapping[str, object] = DEFAULT_FACTORIES,
    kind_defaults: Mapping[VehicleKind, tuple[str, ...]] = KIND_DEFAULTS,
) -> tuple[str, ...]:
    """The estimators ``config`` runs: ``config.estimators`` or its kind's defaults, validated."""
    names = (
        tuple(config.estimators) if config.estimators else tuple(kind_defaults.get(config.kind, ()))
    )
    unknown = [n for n in names if n not in known]
    if unknown:
        raise UnknownEstimatorError(f"unknown estimator(s) {unknown}; known: {sorted(known)}")
    if len(set(names)) != len(names):
        raise UnknownEstimatorError(f"estimator listed twice in {list(names)}")
    kind = str(config.kind)
    wrong = [n for n in names if n in SPECS and kind not in SPECS[n].kinds]
    if wrong:
        served = {n: list(SPECS[n].kinds) for n in wrong}
        raise UnknownEstimatorError(f"estimator(s) {wrong} do not run on {kind} vehicles: {served}")
    return names


#: Told of every estimator call that raised: ``(vehicle_id, estimator, operation, exception)``.
ErrorHandler = Callable[[str, str, str, Exception], None]


class ConfigRefusedError(RuntimeError):
    """An estimator raised while taking a vehicle's config (or could not be built); the
    vehicle keeps the config and estimators it had."""

    def __init__(self, vehicle_id: str, estimator: str, cause: Exception) -> None:
        super().__init__(f"estimator {estimator!r} refused the config of {vehicle_id}: {cause!r}")
        self.vehicle_id = vehicle_id
        self.estimator = estimator
        self.cause = cause


def _log_error(vehicle_id: str, estimator: str, operation: str, exc: Exception) -> None:
    log.error("estimator %s: %s failed for %s: %r", estimator, operation, vehicle_id, exc)


class EstimatorRegistry:
    """One FleetEstimator per name; routes each vehicle to the estimators it runs.

    Parameters
    ----------
    factories : mapping of name -> factory, optional
        Defaults to :data:`DEFAULT_FACTORIES`. Estimators are built on first use.
    kind_defaults : mapping of VehicleKind -> names, optional
        Defaults to :data:`KIND_DEFAULTS`.
    on_error : ErrorHandler, optional
        Told of every estimator call that raised (default: a log line); may be set later
        through the attribute of that name (the pipeline counts them per vehicle).
    calibrations : mapping of (vehicle_id, estimator) -> CalibrationValues, optional
        Stored calibrations (the newest stored rows'), each given to its estimator when it
        first starts that vehicle.
    """

    def __init__(
        self,
        factories: Mapping[str, EstimatorFactory] | None = None,
        kind_defaults: Mapping[VehicleKind, tuple[str, ...]] | None = None,
        on_error: ErrorHandler | None = None,
        calibrations: Mapping[tuple[str, str], CalibrationValues] | None = None,
    ) -> None:
        self._factories = dict(DEFAULT_FACTORIES if factories is None else factories)
        self._kind_defaults = dict(KIND_DEFAULTS if kind_defaults is None else kind_defaults)
        self.on_error: ErrorHandler = _log_error if on_error is None else on_error
        self._estimators: dict[str, FleetEstimator] = {}
        self._routes: dict[str, tuple[str, ...]] = {}  # vehicle -> names, primary first
        self._configs: dict[str, VehicleConfig] = {}  # vehicle -> the config it runs
        self._members: dict[str, set[str]] = {}  # estimator -> its vehicles
        # vehicle -> stream -> ((name, estimator), ...) whose spec takes that stream
        self._by_stream: dict[str, dict[str, tuple[tuple[str, FleetEstimator], ...]]] = {}
        self._stored_calibrations = dict(calibrations or {})  # each used once
        self._calibration_resets: dict[tuple[str, str], int] = {}  # (vehicle, estimator) -> n
        self._flushed: dict[str, list[tuple[str, np.ndarray]]] = {}  # estimator -> held rows

    def counters(self) -> dict[str, dict[str, dict[str, int]]]:
        """Event counters of every estimator that keeps them (:class:`KeepsCounters`, e.g.
        MDSF's resets and gated GNSS): ``{estimator: {vehicle_id: {event: n}}}``;
        an estimator whose counters raise is left out (and logged).

        Call on the thread that owns the registry (the pipeline's).
        """
        out: dict[str, dict[str, dict[str, int]]] = {}
        for name, est in self._estimators.items():
            if not isinstance(est, KeepsCounters):
                continue
            try:
                out[name] = {vid: dict(est.counters(vid)) for vid in est.vehicle_ids()}
            except Exception:
                log.exception("estimator %s: counters failed", name)
        for (vid, name), n in self._calibration_resets.items():
            if vid in out.get(name, {}):
                out[name][vid]["calibration_resets"] = n
        return out

    def set_anchor(self, vehicle_id: str, anchor: tuple[float, float, float]) -> None:
        """Give the vehicle's ENU frame this origin in every estimator of it that has one (the
        :class:`Anchored` ones; the others and unknown vehicles are left alone). Call on the
        thread that owns the registry."""
        for name in self._routes.get(vehicle_id, ()):
            est = self._estimators.get(name)
            if isinstance(est, Anchored):
                est.set_anchor(vehicle_id, *anchor)

    def anchor(self, vehicle_id: str) -> tuple[float, float, float] | None:
        """Geodetic anchor ``(lat_deg, lon_deg, height_m)`` of the vehicle's local ENU frame,
        from the first of its estimators that has one (the :class:`Anchored` ones, the primary
        first); None before any has one. Call on the thread that owns the registry."""
        for name in self._routes.get(vehicle_id, ()):
            est = self._estimators.get(name)
            got = est.anchor(vehicle_id) if isinstance(est, Anchored) else None
            if got is not None:
                return got
        return None

    def anchors(self) -> dict[str, tuple[float, float, float]]:
        """:meth:`anchor` of every vehicle that has one."""
        out: dict[str, tuple[float, float, float]] = {}
        for vid in self._routes:
            got = self.anchor(vid)
            if got is not None:
                out[vid] = got
        return out

    @property
    def available(self) -> tuple[str, ...]:
        """Every estimator name this registry can build."""
        return tuple(sorted(self._factories))

    def names_for(self, config: VehicleConfig) -> tuple[str, ...]:
        """Validated estimator names ``config`` would run (raises UnknownEstimatorError)."""
        return estimator_names_for(config, self._factories, self._kind_defaults)

    def estimator(self, name: str) -> FleetEstimator:
        """The fleet estimator ``name``, built on first use (``TypeError`` when what its
        factory builds has a spec of another name)."""
        est = self._estimators.get(name)
        if est is None:
            try:
                factory = self._factories[name]
            except KeyError:
                raise UnknownEstimatorError(f"unknown estimator {name!r}") from None
            est = factory()
            if est.spec.name != name:
                raise TypeError(f"estimator {name!r} was built with the spec {est.spec.name!r}")
            self._estimators[name] = est
        return est

    def add_vehicle(self, vehicle_id: str, config: VehicleConfig) -> tuple[str, ...]:
        """Start (or reconfigure) ``vehicle_id``; return the estimator names it runs.

        ``UnknownEstimatorError`` for names nobody knows; ``ConfigRefusedError`` when one of
        its estimators cannot be built or raises on the config: then the estimators that took
        it already get the old config again (a fresh state) and the vehicle keeps its old
        config and estimators (a new vehicle stays unknown).
        """
        names = self.names_for(config)
        kept = self._calibrations_of(vehicle_id)
        self._flush(vehicle_id)
        done: list[str] = []
        for name in names:
            try:
                self.estimator(name).add_vehicle(vehicle_id, config)
            except Exception as exc:
                self._take_back(vehicle_id, [*done, name])
                raise ConfigRefusedError(vehicle_id, name, exc) from exc
            done.append(name)
        for old in self._routes.get(vehicle_id, ()):
            if old not in names:
                self._guard(vehicle_id, old, "remove_vehicle", self._estimators[old].remove_vehicle)
        self._route(vehicle_id, names, config)
        self._restore_calibrations(vehicle_id, names, kept)
        return names

    def _calibrations_of(self, vehicle_id: str) -> dict[str, dict[str, float]]:
        """The calibrations the vehicle's running estimators hold, by estimator name."""
        out: dict[str, dict[str, float]] = {}
        for name in self._routes.get(vehicle_id, ()):
            est = self._estimators[name]
            if est.spec.calibrations and isinstance(est, Calibrating):
                try:
                    out[name] = est.calibration_fields(vehicle_id)
                except Exception as exc:
                    self.on_error(vehicle_id, name, "calibration_fields", exc)
        return out

    def _flush(self, vehicle_id: str) -> None:
        """Keep the rows the vehicle's running estimators still hold back, for the next
        :meth:`advance`."""
        for name in self._routes.get(vehicle_id, ()):
            try:
                rows = held_rows(self._estimators[name], vehicle_id)
            except Exception as exc:
                self.on_error(vehicle_id, name, "flush", exc)
                continue
            if rows is not None and rows.size:
                self._flushed.setdefault(name, []).append((vehicle_id, rows))

    def _restore_calibrations(
        self, vehicle_id: str, names: tuple[str, ...], kept: Mapping[str, CalibrationValues]
    ) -> None:
        """Give the estimators ``names`` of the vehicle the calibration it had (``kept``), else
        the stored one: the channels that hold a value (:func:`known_calibrations`); a
        channel with a non-finite value (not learnt yet, or rows of a mode that does not
        calibrate) is not given, and nothing where no channel holds one."""
        for name in names:
            stored = self._stored_calibrations.pop((vehicle_id, name), None)
            values = kept.get(name, stored)
            est = self._estimators[name]
            if values is None or not (est.spec.calibrations and isinstance(est, Calibrating)):
                continue
            known = known_calibrations(est.spec, values)
            restore = est.restore_calibration_fields
            if known and self._guard(vehicle_id, name, "restore_calibration", restore, known):
                log.debug("estimator %s: calibration of %s restored", name, vehicle_id)

    def _take_back(self, vehicle_id: str, touched: list[str]) -> None:
        """Undo a refused config in the estimators ``touched`` (see :meth:`add_vehicle`): the
        ones the vehicle ran before take its old config again, the others forget it."""
        old = self._configs.get(vehicle_id)
        kept = self._routes.get(vehicle_id, ())
        for name in touched:
            est = self._estimators.get(name)
            if est is None:  # its factory failed
                continue
            if old is not None and name in kept:
                if self._guard(vehicle_id, name, "add_vehicle", est.add_vehicle, old):
                    continue
                kept = tuple(n for n in kept if n != name)
            self._guard(vehicle_id, name, "remove_vehicle", est.remove_vehicle)
        if old is not None:
            self._route(vehicle_id, kept, old)

    def _route(self, vehicle_id: str, names: tuple[str, ...], config: VehicleConfig) -> None:
        """Record that ``vehicle_id`` runs ``names`` (built) with ``config``."""
        self._unroute(vehicle_id)
        self._routes[vehicle_id] = names
        self._configs[vehicle_id] = config
        for name in names:
            self._members.setdefault(name, set()).add(vehicle_id)
        ests = [(name, self._estimators[name]) for name in names]
        self._by_stream[vehicle_id] = {
            stream: tuple((n, e) for n, e in ests if stream in e.spec.inputs) for stream in STREAMS
        }

    def _unroute(self, vehicle_id: str) -> tuple[str, ...]:
        """Forget the routes of ``vehicle_id``; return the names it ran."""
        names = self._routes.pop(vehicle_id, ())
        self._configs.pop(vehicle_id, None)
        self._by_stream.pop(vehicle_id, None)
        for name in names:
            self._members[name].discard(vehicle_id)
        return names

    def _guard(
        self, vehicle_id: str, name: str, operation: str, call: Callable[..., object], *args: object
    ) -> bool:
        """``call(vehicle_id, *args)``; False (and ``on_error`` told) if it raised."""
        try:
            call(vehicle_id, *args)
        except Exception as exc:
            self.on_error(vehicle_id, name, operation, exc)
            return False
        return True

    def remove_vehicle(self, vehicle_id: str) -> None:
        """Stop estimating ``vehicle_id`` (no error if unknown)."""
        for key in [k for k in self._calibration_resets if k[0] == vehicle_id]:
            del self._calibration_resets[key]
        for name, parts in self._flushed.items():
            self._flushed[name] = [p for p in parts if p[0] != vehicle_id]
        for name in self._unroute(vehicle_id):
            self._guard(vehicle_id, name, "remove_vehicle", self._estimators[name].remove_vehicle)

    def has_vehicle(self, vehicle_id: str) -> bool:
        return vehicle_id in self._routes

    def vehicle_ids(self) -> list[str]:
        return list(self._routes)

    def estimators_of(self, vehicle_id: str) -> tuple[str, ...]:
        """Names ``vehicle_id`` runs, primary first (empty if unknown)."""
        return self._routes.get(vehicle_id, ())

    def command(self, vehicle_id: str, estimator: str, key: str, on: bool) -> bool:
        """Turn ``estimator``'s command ``key`` (one of its spec's ``commands``) on or off for
        ``vehicle_id``. False, and the error told like any other estimator error, if the
        vehicle does not run that estimator or the estimator refused it."""
        try:
            if estimator not in self.estimators_of(vehicle_id):
                raise KeyError(f"{vehicle_id!r} does not run {estimator!r}")
            if key == RESET_CALIBRATION:
                return self._reset_calibration(vehicle_id, estimator)
            est = self.estimator(estimator)
            if not isinstance(est, TakesCommands):
                raise KeyError(f"{estimator!r} takes no commands")
            take = est.command
        except KeyError as exc:
            self.on_error(vehicle_id, estimator, "command", exc)
            return False
        return self._guard(vehicle_id, estimator, "command", take, key, on)

    def _reset_calibration(self, vehicle_id: str, estimator: str) -> bool:
        """The estimator forgets the vehicle's calibration and learns it anew (counted in its
        counters as ``calibration_resets``, logged); ``KeyError`` if it does not calibrate."""
        est = self.estimator(estimator)
        if not isinstance(est, Calibrating):
            raise KeyError(f"{estimator!r} keeps no calibration")
        self._stored_calibrations.pop((vehicle_id, estimator), None)
        if not self._guard(vehicle_id, estimator, "reset_calibration", est.reset_calibration):
            return False
        key = (vehicle_id, estimator)
        self._calibration_resets[key] = self._calibration_resets.get(key, 0) + 1
        log.info("estimator %s: calibration of %s reset", estimator, vehicle_id)
        return True

    def push(self, vehicle_id: str, measurement: Pushed) -> None:
        """Hand ``measurement`` to every estimator ``vehicle_id`` runs whose spec takes its
        stream (``KeyError`` if the vehicle is unknown)."""
        for name, est in self._by_stream[vehicle_id][stream_of(measurement)]:
            try:
                est.push(vehicle_id, measurement)
            except Exception as exc:
                self.on_error(vehicle_id, name, "push", exc)

    def push_all(self, vehicle_id: str, stream: str, measurements: Sequence[Pushed]) -> None:
        """:meth:`push` of each of ``measurements``, all of ``stream`` (one packet's): the
        estimators taking the stream are looked up once, not per measurement (each estimator
        still gets them in order, and one that raises is told per measurement)."""
        for name, est in self._by_stream[vehicle_id][stream]:
            for measurement in measurements:
                try:
                    est.push(vehicle_id, measurement)
                except Exception as exc:
                    self.on_error(vehicle_id, name, "push", exc)

    def align_ticks(self, vehicle_id: str, stamp_ns: int) -> None:
        """Put ``vehicle_id``'s ticks on ``stamp_ns + k·tick`` in every estimator it runs."""
        for name in self._routes[vehicle_id]:
            self._guard(
                vehicle_id, name, "align_ticks", self._estimators[name].align_ticks, stamp_ns
            )

    def advance(self, until_ns: Mapping[str, int]) -> list[EstimateBatch]:
        """Advance every estimator for the vehicles it holds: one batch per estimator that
        gave rows (of its spec; rows flushed at a re-registration first), in the order the
        estimators were built."""
        out: list[EstimateBatch] = []
        for name, est in self._estimators.items():
            parts = self._flushed.pop(name, [])
            members = self._members.get(name, set())
            mine = {vid: t for vid, t in until_ns.items() if vid in members}
            if mine:
                parts += self._advance(name, est, mine)
            if not parts:
                continue
            batch = self._batch(name, est.spec, parts)
            if batch:
                out.append(batch)
        return out

    def _advance(
        self, name: str, est: FleetEstimator, until_ns: dict[str, int]
    ) -> list[tuple[str, np.ndarray]]:
        """``est.advance(until_ns)``; when it raises, the same on each half of the vehicles,
        down to the single vehicles that fail (told to ``on_error``, their rows lost). Rows an
        estimator had computed for others in a call that raised are lost with that call if it
        had moved their state on already."""
        try:
            return est.advance(until_ns)
        except Exception as exc:
            if len(until_ns) == 1:
                self.on_error(next(iter(until_ns)), name, "advance", exc)
                return []
        items = list(until_ns.items())
        half = len(items) // 2
        return self._advance(name, est, dict(items[:half])) + self._advance(
            name, est, dict(items[half:])
        )

    def _batch(
        self, name: str, spec: EstimatorSpec, parts: list[tuple[str, np.ndarray]]
    ) -> EstimateBatch:
        """``parts`` joined as one batch of ``spec``; when that fails, without the vehicles
        whose rows are not of ``spec``."""
        try:
            return EstimateBatch.of(parts, spec)
        except (TypeError, AttributeError):  # some rows are no 1-d array of spec.dtype
            return EstimateBatch.of(self._of_spec(name, spec, parts), spec)

    def _of_spec(
        self, name: str, spec: EstimatorSpec, parts: list[tuple[str, np.ndarray]]
    ) -> list[tuple[str, np.ndarray]]:
        """The parts whose rows are of ``spec`` (dtype, shape); the others told to
        ``on_error``."""
        good = []
        for vid, rows in parts:
            try:
                good.append((vid, spec.check_rows(rows)))
            except TypeError as exc:
                self.on_error(vid, name, "advance", exc)
        return good
