"""Estimator registry: names, kind defaults, overrides, routing by stream, isolation."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from estimator.base import (
    _STREAM_OF_TYPE,
    STREAMS,
    Anchored,
    FleetEstimator,
    TakesCommands,
)
from estimator.catalog import SPECS
from estimator.config import (
    SlipConfig,
    TrackedConfig,
    VehicleKind,
    Wheeled4wdSteeredConfig,
    WheeledRearDriveConfig,
)
from estimator.mdsf_spec import MDSF_SPEC
from estimator.reference_speed_spec import REFERENCE_SPEED_SPEC
from estimator.types import GnssSample, ImuBatch, WheelGap
from server.estimation import (
    DEFAULT_FACTORIES,
    KIND_DEFAULTS,
    ConfigRefusedError,
    EstimatorRegistry,
    UnknownEstimatorError,
    estimator_names_for,
)
from tests.server.ingest.fakes import RecordingFleet

BOTH = ("reference_speed", "mdsf")
IMU = ImuBatch(np.array([1], np.int64), np.zeros((1, 3)), np.zeros((1, 3)))
GNSS = GnssSample(2, (0.0, 1.0, 0.0), 0.0, 0.0, 0.0, 48.0, 11.0, 500.0)

Failure = tuple[str, str, str]


def _registry(
    fail_for: frozenset[str] = frozenset(), refuse_threshold_pct: float | None = None
) -> tuple[EstimatorRegistry, dict[str, RecordingFleet], list[Failure]]:
    """Recording MDSF and reference-speed estimators (the latter failing for ``fail_for`` and
    refusing configs with ``refuse_threshold_pct``); failures are collected."""
    built: dict[str, RecordingFleet] = {}
    failures: list[Failure] = []

    def factory(fleet: Callable[[], RecordingFleet]) -> Callable[[], FleetEstimator]:
        def make() -> FleetEstimator:
            est = fleet()
            built[est.name] = est
            return est

        return make

    reg = EstimatorRegistry(
        factories={
            "mdsf": factory(RecordingFleet),
            "reference_speed": factory(
                lambda: RecordingFleet(REFERENCE_SPEED_SPEC, fail_for, refuse_threshold_pct)
            ),
        },
        kind_defaults={**KIND_DEFAULTS, VehicleKind.TRACKED: ()},  # a kind that runs none
        on_error=lambda vid, name, op, _exc: failures.append((vid, name, op)),
    )
    return reg, built, failures


def test_defaults_per_kind_and_a_factory_per_spec() -> None:
    assert estimator_names_for(WheeledRearDriveConfig()) == ("mdsf",)
    assert estimator_names_for(TrackedConfig()) == ("tracked",)
    assert estimator_names_for(Wheeled4wdSteeredConfig()) == ("friction",)
    assert set(KIND_DEFAULTS) == set(VehicleKind)
    assert set(DEFAULT_FACTORIES) == set(SPECS)


def test_every_default_factory_builds_the_estimator_of_its_spec() -> None:
    registry = EstimatorRegistry()
    for name, spec in SPECS.items():
        est = registry.estimator(name)
        assert est.spec is spec and est.name == name


def test_every_stream_declared_by_the_server_names_its_measurements_as_stream_of_does() -> None:
    from server.protocol.streams import STREAMS as DECLARED

    assert set(STREAMS) == {str(s) for s in DECLARED}
    for stream, declared in DECLARED.items():
        for kind in declared.measurements:
            assert _STREAM_OF_TYPE[kind] == stream


def test_config_overrides_kind_defaults() -> None:
    reg, _, _ = _registry()
    cfg = WheeledRearDriveConfig(estimators=BOTH)
    assert reg.names_for(cfg) == BOTH


def test_an_estimator_runs_only_on_the_kinds_its_spec_serves() -> None:
    reg, built, _ = _registry()
    with pytest.raises(UnknownEstimatorError, match=r"do not run on tracked vehicles.*mdsf"):
        reg.add_vehicle("c", TrackedConfig(estimators=("mdsf",)))
    assert not reg.has_vehicle("c") and not built


def test_unknown_estimator_is_a_clear_error() -> None:
    reg, built, _ = _registry()
    with pytest.raises(UnknownEstimatorError, match="nope"):
        reg.add_vehicle("v", WheeledRearDriveConfig(estimators=("nope",)))
    with pytest.raises(UnknownEstimatorError):
        reg.names_for(WheeledRearDriveConfig(estimators=("mdsf", "mdsf")))
    with pytest.raises(UnknownEstimatorError):
        reg.estimator("nope")
    assert not reg.has_vehicle("v") and not built


def test_measurements_reach_the_estimators_whose_spec_takes_their_stream() -> None:
    reg, built, failures = _registry()
    assert reg.add_vehicle("a", WheeledRearDriveConfig()) == ("mdsf",)
    assert reg.add_vehicle("b", WheeledRearDriveConfig(estimators=BOTH)) == BOTH
    assert reg.add_vehicle("c", TrackedConfig()) == ()
    for vid in ("a", "b", "c"):
        reg.push(vid, IMU)
        reg.push(vid, GNSS)
    reg.push("b", WheelGap(5, None))
    gap = built["mdsf"].pushed["b"][-1]
    assert built["mdsf"].pushed == {"a": [IMU, GNSS], "b": [IMU, GNSS, gap]}
    # reference speed takes imu and wheels, no GNSS; a wheel gap is news of "wheels"
    assert built["reference_speed"].pushed == {"b": [IMU, gap]} and gap == WheelGap(5, None)
    with pytest.raises(KeyError):
        reg.push("zzz", IMU)
    assert failures == []


def test_push_all_hands_a_packets_measurements_on_as_push_does_each() -> None:
    """One packet's measurements pushed together reach the same estimators, in order, as
    each pushed alone; an estimator that raises is told per measurement, the others go on."""
    imu2 = ImuBatch(np.array([3], np.int64), np.ones((1, 3)), np.ones((1, 3)))
    one, one_built, one_failures = _registry(fail_for=frozenset({"b"}))
    each, each_built, each_failures = _registry(fail_for=frozenset({"b"}))
    for reg in (one, each):
        reg.add_vehicle("a", WheeledRearDriveConfig())
        reg.add_vehicle("b", WheeledRearDriveConfig(estimators=BOTH))
    for vid in ("a", "b"):
        one.push_all(vid, "imu", (IMU, imu2))
        one.push_all(vid, "gnss", (GNSS,))
        for m in (IMU, imu2, GNSS):
            each.push(vid, m)
    assert one_built["mdsf"].pushed == each_built["mdsf"].pushed
    assert one_built["mdsf"].pushed["b"] == [IMU, imu2, GNSS]
    assert one_built["reference_speed"].pushed == each_built["reference_speed"].pushed
    assert one_failures == each_failures == [("b", "reference_speed", "push")] * 2
    with pytest.raises(KeyError):
        one.push_all("zzz", "imu", (IMU,))


def test_advance_gives_one_batch_per_estimator_of_its_spec() -> None:
    reg, _, _ = _registry()
    reg.add_vehicle("a", WheeledRearDriveConfig())
    reg.add_vehicle("b", WheeledRearDriveConfig(estimators=BOTH))
    reg.add_vehicle("c", TrackedConfig())
    batches = {b.estimator: b for b in reg.advance({"a": 10, "b": 20, "c": 30})}
    assert sorted(batches) == ["mdsf", "reference_speed"]
    mdsf, ref = batches["mdsf"], batches["reference_speed"]
    assert mdsf.spec is MDSF_SPEC and ref.spec is REFERENCE_SPEED_SPEC
    assert sorted((v, int(r["stamp_ns"][0])) for v, r in mdsf) == [("a", 10), ("b", 20)]
    assert [(v, int(r["stamp_ns"][0])) for v, r in ref] == [("b", 20)]
    assert ref.rows.dtype == REFERENCE_SPEED_SPEC.dtype
    assert reg.advance({"c": 40}) == []


def test_an_estimator_failing_for_one_vehicle_costs_that_vehicle_alone() -> None:
    """A batched advance that raises is retried on halves down to the failing vehicle: every
    other vehicle's rows and the other estimator's all come."""
    vehicles = [f"v{i}" for i in range(9)]
    reg, built, failures = _registry(fail_for=frozenset({"v5"}))
    for vid in vehicles:
        reg.add_vehicle(vid, WheeledRearDriveConfig(estimators=BOTH))
        reg.push(vid, IMU)
    batches = {b.estimator: b for b in reg.advance(dict.fromkeys(vehicles, 100))}
    assert sorted(batches["mdsf"].ids) == vehicles
    assert sorted(batches["reference_speed"].ids) == [v for v in vehicles if v != "v5"]
    assert failures == [("v5", "reference_speed", "push"), ("v5", "reference_speed", "advance")]
    assert built["reference_speed"].rows_emitted == {v: 1 for v in vehicles if v != "v5"}


class _WrongRows(RecordingFleet):
    """Emits MDSF's rows although its spec is reference speed's, for vehicle "bad" only."""

    def advance(self, until_ns: dict[str, int]) -> list[tuple[str, np.ndarray]]:  # type: ignore[override]
        rows = super().advance(until_ns)
        return [(v, MDSF_SPEC.empty_rows(1) if v == "bad" else r) for v, r in rows]


def test_rows_of_another_dtype_are_dropped_for_that_vehicle() -> None:
    failures: list[Failure] = []
    reg = EstimatorRegistry(
        factories={"reference_speed": lambda: _WrongRows(REFERENCE_SPEED_SPEC)},
        on_error=lambda vid, name, op, _exc: failures.append((vid, name, op)),
    )
    for vid in ("bad", "good"):
        reg.add_vehicle(vid, WheeledRearDriveConfig(estimators=("reference_speed",)))
    (batch,) = reg.advance({"bad": 1, "good": 2})
    assert batch.ids == ["good"] and failures == [("bad", "reference_speed", "advance")]


def test_a_refused_config_leaves_the_old_one_in_every_estimator() -> None:
    reg, built, _ = _registry(refuse_threshold_pct=99.0)
    old = WheeledRearDriveConfig(estimators=("mdsf",))
    reg.add_vehicle("a", old)
    new = WheeledRearDriveConfig(estimators=BOTH, slip=SlipConfig(alert_threshold_pct=99.0))
    with pytest.raises(ConfigRefusedError, match="reference_speed") as refused:
        reg.add_vehicle("a", new)
    assert refused.value.vehicle_id == "a" and refused.value.estimator == "reference_speed"
    assert reg.estimators_of("a") == ("mdsf",)
    assert built["mdsf"].vehicles == {"a": old}  # took the new config, then the old again
    assert built["reference_speed"].vehicles == {}
    reg.push("a", IMU)
    assert built["reference_speed"].pushed == {}
    # a new vehicle whose config is refused stays unknown everywhere
    with pytest.raises(ConfigRefusedError):
        reg.add_vehicle("n", new)
    assert not reg.has_vehicle("n") and "n" not in built["mdsf"].vehicles


def test_an_estimator_that_cannot_be_built_refuses_the_config() -> None:
    def broken() -> FleetEstimator:
        raise ImportError("no such module")

    reg = EstimatorRegistry(factories={"mdsf": RecordingFleet, "reference_speed": broken})
    reg.add_vehicle("a", WheeledRearDriveConfig())
    with pytest.raises(ConfigRefusedError, match="no such module"):
        reg.add_vehicle("a", WheeledRearDriveConfig(estimators=BOTH))
    assert reg.estimators_of("a") == ("mdsf",)
    misnamed = EstimatorRegistry(factories={"reference_speed": RecordingFleet})  # MDSF's spec
    with pytest.raises(ConfigRefusedError, match="spec 'mdsf'"):
        misnamed.add_vehicle("a", WheeledRearDriveConfig(estimators=("reference_speed",)))


def test_reconfigure_and_remove() -> None:
    reg, built, _ = _registry()
    reg.add_vehicle("b", WheeledRearDriveConfig(estimators=BOTH))
    reg.add_vehicle("b", WheeledRearDriveConfig(estimators=("mdsf",)))
    assert built["reference_speed"].vehicle_ids() == [] and built["mdsf"].vehicle_ids() == ["b"]
    assert reg.estimators_of("b") == ("mdsf",)
    assert [b.estimator for b in reg.advance({"b": 5})] == ["mdsf"]
    reg.remove_vehicle("b")
    reg.remove_vehicle("b")  # no error
    assert built["mdsf"].vehicle_ids() == [] and reg.vehicle_ids() == []
    assert reg.advance({"b": 6}) == []


def test_estimators_built_lazily_once() -> None:
    reg, built, _ = _registry()
    assert built == {}
    reg.add_vehicle("a", WheeledRearDriveConfig())
    first = built["mdsf"]
    reg.add_vehicle("z", WheeledRearDriveConfig())
    assert built["mdsf"] is first and reg.estimator("mdsf") is first
    assert reg.available == ("mdsf", "reference_speed") and "reference_speed" not in built


def test_counters_come_from_estimators_that_keep_them() -> None:
    registry = EstimatorRegistry()  # the real MDSF, which counts its events
    registry.add_vehicle("v1", WheeledRearDriveConfig())
    counters = registry.counters()
    assert set(counters) == {"mdsf"}
    assert set(counters["mdsf"]) == {"v1"}
    events = counters["mdsf"]["v1"]
    assert events["resets"] == 0 and events["ticks"] == 0 and "gnss_gated" in events

    recording, _, _ = _registry()  # estimators without counters are left out
    recording.add_vehicle("v2", WheeledRearDriveConfig())
    assert recording.counters() == {}


@pytest.mark.parametrize("name", sorted(DEFAULT_FACTORIES))
def test_each_estimator_has_the_capabilities_its_spec_promises(name: str) -> None:
    """The registry finds commands and anchors by their protocols: an estimator whose spec
    offers commands takes them, one whose rows carry a position keeps that position's anchor."""
    est = DEFAULT_FACTORIES[name]()
    assert isinstance(est, TakesCommands) == bool(est.spec.commands)
    assert isinstance(est, Anchored) == (est.spec.position is not None)


def test_anchors_are_each_vehicles_first_fix() -> None:
    from estimator.sim import simulate

    run = simulate("paper_straight", seed=3, start_ns=1_700_000_000_000_000_000)
    registry = EstimatorRegistry()
    registry.add_vehicle("v1", run.config)
    assert registry.anchors() == {}
    until = run.start_ns + 3_000_000_000
    for m in run.measurements:
        stamp = m.stamp_ns if isinstance(m, GnssSample) else int(m.stamp_ns[-1])
        if stamp <= until:
            registry.push("v1", m)
    (batch,) = registry.advance({"v1": until})
    assert batch.spec is MDSF_SPEC and batch.ids == ["v1"] and len(batch.rows) > 20
    first = next(m for m in run.measurements if isinstance(m, GnssSample))
    lat, lon, h = registry.anchors()["v1"]
    assert abs(lat - first.lat_deg) < 1e-5 and abs(lon - first.lon_deg) < 1e-5  # within ~1 m
    assert abs(h - first.height_m) < 1.0
