"""Estimator registry: which estimators exist, which ones each vehicle runs, and routing.

Names map to factories of :class:`estimator.base.FleetEstimator` (imported lazily, so the
server starts without loading an estimator nobody runs)::

    "mdsf"  -> estimator.engine.MdsfFleet     (wheeled rear-drive tractors; ESTIMATE_DTYPE rows)

A vehicle runs ``config.estimators`` when that is non-empty, otherwise its kind's defaults:

    ============================  ===================================================
    VehicleKind                   default estimators
    ============================  ===================================================
    ``wheeled_rear_drive``        ``("mdsf",)``
    ``tracked``                   none yet (a track-slip estimator is planned)
    ``wheeled_4wd_steered``       none yet (a steered-4WD estimator is planned)
    ============================  ===================================================

A vehicle may run several estimators; the first one is its *primary*, whose rows go to the
sinks' ``on_estimates`` (storage, live views). Rows of the others are handed out per estimator
name. Unknown names raise :class:`UnknownEstimatorError`.

The registry holds one ``FleetEstimator`` per name and is used from one thread (the pipeline).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np

from estimator.base import FleetEstimator, Pushed
from estimator.config import VehicleConfig, VehicleKind

__all__ = [
    "DEFAULT_FACTORIES",
    "KIND_DEFAULTS",
    "AdvanceResult",
    "EstimatorRegistry",
    "UnknownEstimatorError",
    "estimator_names_for",
]

EstimatorFactory = Callable[[], FleetEstimator]


def _mdsf() -> FleetEstimator:
    from estimator.mdsf import MdsfFleet  # lazy: heavy numerics only when a vehicle runs it

    fleet: FleetEstimator = MdsfFleet()
    return fleet


DEFAULT_FACTORIES: Mapping[str, EstimatorFactory] = {"mdsf": _mdsf}

KIND_DEFAULTS: Mapping[VehicleKind, tuple[str, ...]] = {
    VehicleKind.WHEELED_REAR_DRIVE: ("mdsf",),
    VehicleKind.TRACKED: (),
    VehicleKind.WHEELED_4WD_STEERED: (),
}


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
    return names


@dataclass(slots=True)
class AdvanceResult:
    """Rows produced by one :meth:`EstimatorRegistry.advance`.

    Attributes
    ----------
    primary : list of (vehicle_id, rows)
        Rows of each vehicle's primary estimator (``ESTIMATE_DTYPE`` for MDSF).
    by_estimator : dict of name -> list of (vehicle_id, rows)
        Every estimator's rows, primary included.
    """

    primary: list[tuple[str, np.ndarray]] = field(default_factory=list)
    by_estimator: dict[str, list[tuple[str, np.ndarray]]] = field(default_factory=dict)


class EstimatorRegistry:
    """One FleetEstimator per name; routes each vehicle to the estimators it runs.

    Parameters
    ----------
    factories : mapping of name -> factory, optional
        Defaults to :data:`DEFAULT_FACTORIES`. Estimators are built on first use.
    kind_defaults : mapping of VehicleKind -> names, optional
        Defaults to :data:`KIND_DEFAULTS`.
    """

    def __init__(
        self,
        factories: Mapping[str, EstimatorFactory] | None = None,
        kind_defaults: Mapping[VehicleKind, tuple[str, ...]] | None = None,
    ) -> None:
        self._factories = dict(DEFAULT_FACTORIES if factories is None else factories)
        self._kind_defaults = dict(KIND_DEFAULTS if kind_defaults is None else kind_defaults)
        self._estimators: dict[str, FleetEstimator] = {}
        self._routes: dict[str, tuple[str, ...]] = {}

    def counters(self) -> dict[str, dict[str, dict[str, int]]]:
        """Event counters of every estimator that keeps them (an optional ``counters(vehicle_id)``
        method, e.g. MDSF's resets and gated GNSS): ``{estimator: {vehicle_id: {event: n}}}``.

        Call on the thread that owns the registry (the pipeline's).
        """
        out: dict[str, dict[str, dict[str, int]]] = {}
        for name, est in self._estimators.items():
            per_vehicle = getattr(est, "counters", None)
            if callable(per_vehicle):
                out[name] = {vid: dict(per_vehicle(vid)) for vid in est.vehicle_ids()}
        return out

    def set_anchor(self, vehicle_id: str, anchor: tuple[float, float, float]) -> None:
        """Give the vehicle's ENU frame this origin in every estimator of it that has one (an
        optional ``set_anchor(vehicle_id, lat_deg, lon_deg, height_m)``; the others and unknown
        vehicles are left alone). Call on the thread that owns the registry."""
        for name in self._routes.get(vehicle_id, ()):
            put = getattr(self._estimators.get(name), "set_anchor", None)
            if callable(put):
                put(vehicle_id, *anchor)

    def anchor(self, vehicle_id: str) -> tuple[float, float, float] | None:
        """Geodetic anchor ``(lat_deg, lon_deg, height_m)`` of the vehicle's local ENU frame,
        from the first of its estimators that has one (an optional ``anchor(vehicle_id)``;
        the primary first); None before any has one. Call on the thread that owns the
        registry."""
        for name in self._routes.get(vehicle_id, ()):
            get = getattr(self._estimators.get(name), "anchor", None)
            got = get(vehicle_id) if callable(get) else None
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
        """The fleet estimator ``name``, built on first use."""
        est = self._estimators.get(name)
        if est is None:
            try:
                factory = self._factories[name]
            except KeyError:
                raise UnknownEstimatorError(f"unknown estimator {name!r}") from None
            est = self._estimators[name] = factory()
        return est

    def add_vehicle(self, vehicle_id: str, config: VehicleConfig) -> tuple[str, ...]:
        """Start (or reconfigure) ``vehicle_id``; return the estimator names it runs."""
        names = self.names_for(config)
        for old in self._routes.get(vehicle_id, ()):
            if old not in names:
                self._estimators[old].remove_vehicle(vehicle_id)
        for name in names:
            self.estimator(name).add_vehicle(vehicle_id, config)
        self._routes[vehicle_id] = names
        return names

    def remove_vehicle(self, vehicle_id: str) -> None:
        """Stop estimating ``vehicle_id`` (no error if unknown)."""
        for name in self._routes.pop(vehicle_id, ()):
            self._estimators[name].remove_vehicle(vehicle_id)

    def has_vehicle(self, vehicle_id: str) -> bool:
        return vehicle_id in self._routes

    def vehicle_ids(self) -> list[str]:
        return list(self._routes)

    def estimators_of(self, vehicle_id: str) -> tuple[str, ...]:
        """Names ``vehicle_id`` runs, primary first (empty if unknown)."""
        return self._routes.get(vehicle_id, ())

    def push(self, vehicle_id: str, measurement: Pushed) -> None:
        """Hand ``measurement`` to every estimator ``vehicle_id`` runs (KeyError if unknown)."""
        for name in self._routes[vehicle_id]:
            self._estimators[name].push(vehicle_id, measurement)

    def align_ticks(self, vehicle_id: str, stamp_ns: int) -> None:
        """Put ``vehicle_id``'s ticks on ``stamp_ns + k·tick`` in every estimator it runs."""
        for name in self._routes[vehicle_id]:
            self._estimators[name].align_ticks(vehicle_id, stamp_ns)

    def advance(self, until_ns: Mapping[str, int]) -> AdvanceResult:
        """Advance every estimator for the vehicles it holds; collect rows."""
        result = AdvanceResult()
        for name, est in self._estimators.items():
            mine = {vid: t for vid, t in until_ns.items() if name in self._routes.get(vid, ())}
            if not mine:
                continue
            rows = est.advance(mine)
            if not rows:
                continue
            result.by_estimator[name] = rows
            for vid, arr in rows:
                route = self._routes.get(vid)
                if route and route[0] == name:
                    result.primary.append((vid, arr))
        return result
