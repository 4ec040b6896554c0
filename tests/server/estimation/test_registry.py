"""Estimator registry: names, kind defaults, overrides, routing."""

from __future__ import annotations

from collections.abc import Callable, Mapping

import numpy as np
import pytest

from estimator.base import FleetEstimator, Measurement, Pushed
from estimator.config import (
    TrackedConfig,
    VehicleConfig,
    VehicleKind,
    Wheeled4wdSteeredConfig,
    WheeledRearDriveConfig,
)
from estimator.types import ESTIMATE_DTYPE, ImuBatch, empty_estimates
from server.estimation import (
    DEFAULT_FACTORIES,
    KIND_DEFAULTS,
    EstimatorRegistry,
    UnknownEstimatorError,
    estimator_names_for,
)


class RecordingFleet:
    """A FleetEstimator that records calls and emits one row per advance."""

    output_dtype = ESTIMATE_DTYPE

    def __init__(self, name: str) -> None:
        self.name = name
        self.vehicles: dict[str, VehicleConfig] = {}
        self.pushed: list[tuple[str, Measurement]] = []
        self.aligned: list[tuple[str, int]] = []

    def add_vehicle(self, vehicle_id: str, config: VehicleConfig) -> None:
        self.vehicles[vehicle_id] = config

    def remove_vehicle(self, vehicle_id: str) -> None:
        self.vehicles.pop(vehicle_id, None)

    def vehicle_ids(self) -> list[str]:
        return list(self.vehicles)

    def push(self, vehicle_id: str, measurement: Pushed) -> None:
        if vehicle_id not in self.vehicles:
            raise KeyError(vehicle_id)
        self.pushed.append((vehicle_id, measurement))

    def align_ticks(self, vehicle_id: str, stamp_ns: int) -> None:
        self.aligned.append((vehicle_id, stamp_ns))

    def advance(self, until_ns: Mapping[str, int]) -> list[tuple[str, np.ndarray]]:
        out = []
        for vid, t in until_ns.items():
            row = empty_estimates(1)
            row["stamp_ns"] = t
            out.append((vid, row))
        return out


def _registry() -> tuple[EstimatorRegistry, dict[str, RecordingFleet]]:
    built: dict[str, RecordingFleet] = {}

    def factory(name: str) -> Callable[[], FleetEstimator]:
        def make() -> FleetEstimator:
            built[name] = RecordingFleet(name)
            return built[name]

        return make

    reg = EstimatorRegistry(
        factories={"mdsf": factory("mdsf"), "friction": factory("friction")},
        kind_defaults={**KIND_DEFAULTS},
    )
    return reg, built


def test_defaults_per_kind() -> None:
    assert estimator_names_for(WheeledRearDriveConfig()) == ("mdsf",)
    assert estimator_names_for(TrackedConfig()) == ()
    assert estimator_names_for(Wheeled4wdSteeredConfig()) == ()
    assert set(KIND_DEFAULTS) == set(VehicleKind)
    assert "mdsf" in DEFAULT_FACTORIES


def test_config_overrides_kind_defaults() -> None:
    reg, _ = _registry()
    cfg = TrackedConfig(estimators=("friction", "mdsf"))
    assert reg.names_for(cfg) == ("friction", "mdsf")


def test_unknown_estimator_is_a_clear_error() -> None:
    reg, built = _registry()
    with pytest.raises(UnknownEstimatorError, match="nope"):
        reg.add_vehicle("v", WheeledRearDriveConfig(estimators=("nope",)))
    with pytest.raises(UnknownEstimatorError):
        reg.names_for(WheeledRearDriveConfig(estimators=("mdsf", "mdsf")))
    with pytest.raises(UnknownEstimatorError):
        reg.estimator("nope")
    assert not reg.has_vehicle("v") and not built


def test_routing_push_and_advance() -> None:
    reg, built = _registry()
    assert reg.add_vehicle("a", WheeledRearDriveConfig()) == ("mdsf",)
    assert reg.add_vehicle("b", WheeledRearDriveConfig(estimators=("friction", "mdsf"))) == (
        "friction",
        "mdsf",
    )
    assert reg.add_vehicle("c", TrackedConfig()) == ()
    m = ImuBatch(np.array([1], np.int64), np.zeros((1, 3)), np.zeros((1, 3)))
    for vid in ("a", "b", "c"):
        reg.push(vid, m)
    assert [v for v, _ in built["mdsf"].pushed] == ["a", "b"]
    assert [v for v, _ in built["friction"].pushed] == ["b"]
    result = reg.advance({"a": 10, "b": 20, "c": 30})
    # primary: a -> mdsf, b -> friction; c runs nothing
    assert sorted((v, int(r["stamp_ns"][0])) for v, r in result.primary) == [("a", 10), ("b", 20)]
    assert sorted(v for v, _ in result.by_estimator["mdsf"]) == ["a", "b"]
    assert [v for v, _ in result.by_estimator["friction"]] == ["b"]
    with pytest.raises(KeyError):
        reg.push("zzz", m)


def test_reconfigure_and_remove() -> None:
    reg, built = _registry()
    reg.add_vehicle("b", WheeledRearDriveConfig(estimators=("friction", "mdsf")))
    reg.add_vehicle("b", WheeledRearDriveConfig(estimators=("mdsf",)))
    assert built["friction"].vehicle_ids() == [] and built["mdsf"].vehicle_ids() == ["b"]
    assert reg.estimators_of("b") == ("mdsf",)
    reg.remove_vehicle("b")
    reg.remove_vehicle("b")  # no error
    assert built["mdsf"].vehicle_ids() == [] and reg.vehicle_ids() == []


def test_estimators_built_lazily_once() -> None:
    reg, built = _registry()
    assert built == {}
    reg.add_vehicle("a", WheeledRearDriveConfig())
    first = built["mdsf"]
    reg.add_vehicle("z", WheeledRearDriveConfig())
    assert built["mdsf"] is first and reg.estimator("mdsf") is first
    assert reg.available == ("friction", "mdsf")


def test_counters_come_from_estimators_that_keep_them() -> None:
    registry = EstimatorRegistry()  # the real MDSF, which counts its events
    registry.add_vehicle("v1", WheeledRearDriveConfig())
    counters = registry.counters()
    assert set(counters) == {"mdsf"}
    assert set(counters["mdsf"]) == {"v1"}
    events = counters["mdsf"]["v1"]
    assert events["resets"] == 0 and events["ticks"] == 0 and "gnss_gated" in events

    recording, _ = _registry()  # estimators without counters are left out
    recording.add_vehicle("v2", WheeledRearDriveConfig())
    assert recording.counters() == {}


def test_anchors_are_each_vehicles_first_fix() -> None:
    from estimator.sim import simulate
    from estimator.types import GnssSample

    run = simulate("paper_straight", seed=3, start_ns=1_700_000_000_000_000_000)
    registry = EstimatorRegistry()
    registry.add_vehicle("v1", run.config)
    assert registry.anchors() == {}
    until = run.start_ns + 3_000_000_000
    for m in run.measurements:
        stamp = m.stamp_ns if isinstance(m, GnssSample) else int(m.stamp_ns[-1])
        if stamp <= until:
            registry.push("v1", m)
    registry.advance({"v1": until})
    first = next(m for m in run.measurements if isinstance(m, GnssSample))
    lat, lon, h = registry.anchors()["v1"]
    assert abs(lat - first.lat_deg) < 1e-5 and abs(lon - first.lon_deg) < 1e-5  # within ~1 m
    assert abs(h - first.height_m) < 1.0
