"""Self-registration's caps: ``ingest.max_registrations_per_min`` over a sliding minute and
``ingest.max_vehicles`` in total; refusals counted as ``rejected_registration_cap``."""

from __future__ import annotations

from estimator.config import WheeledRearDriveConfig
from server.estimation import EstimatorRegistry
from server.ingest import Pipeline
from server.settings import IngestSettings, Settings
from tests.server.ingest.fakes import CapturingSink, RecordingFleet
from tests.server.ingest.test_pipeline import T0, imu, wait_for

MIN_NS = 60_000_000_000


class _Clock:
    def __init__(self) -> None:
        self.ns = 1_000_000_000

    def __call__(self) -> int:
        return self.ns


def _pipeline(clock: _Clock, **ingest: int) -> tuple[Pipeline, list[str]]:
    new: list[str] = []
    fleet = RecordingFleet()
    settings = Settings(ingest=IngestSettings.model_validate({"process_interval_ms": 5, **ingest}))
    pipe = Pipeline(
        settings,
        None,
        EstimatorRegistry(factories={"mdsf": lambda: fleet}),
        [CapturingSink()],
        lambda vid, _config: new.append(vid),
        clock_ns=clock,
        wall_clock_ns=lambda: T0,
    )
    return pipe, new


def test_registrations_per_minute_slide_and_refusals_are_counted() -> None:
    clock = _Clock()
    pipe, new = _pipeline(clock, max_registrations_per_min=3)
    pipe.start()
    pipe.submit([imu(f"v{i}", 0, 0) for i in range(5)])
    pipe.submit([imu("v0", 1, 10), imu("v4", 1, 10)])  # v0 runs; v4 is still refused
    pipe.stop(5)
    snap = pipe.counters_snapshot()
    assert new == ["v0", "v1", "v2"]
    assert snap["v0"]["accepted"] == 2
    assert snap["v3"] == {**snap["v3"], "received": 1, "rejected_registration_cap": 1}
    assert snap["v4"]["rejected_registration_cap"] == 2


def test_the_minute_slides() -> None:
    clock = _Clock()
    pipe, new = _pipeline(clock, max_registrations_per_min=3)
    pipe.start()
    pipe.submit([imu(f"w{i}", 0, 0) for i in range(4)])
    wait_for(lambda: len(pipe.counters_snapshot()) == 4)
    clock.ns += MIN_NS  # a minute on: three more may come
    pipe.submit([imu("w3", 1, 10)])
    pipe.stop(5)
    assert new == ["w0", "w1", "w2", "w3"]
    w3 = pipe.counters_snapshot()["w3"]
    assert w3["rejected_registration_cap"] == 1 and w3["accepted"] == 1


def test_max_vehicles_holds_for_self_registration_not_for_known_vehicles() -> None:
    clock = _Clock()
    pipe, new = _pipeline(clock, max_vehicles=2)
    pipe.register_vehicle("known", WheeledRearDriveConfig())
    pipe.start()
    pipe.submit([imu("known", 0, 0), imu("a", 0, 0), imu("b", 0, 0)])
    pipe.stop(5)
    snap = pipe.counters_snapshot()
    assert new == ["a"]
    assert snap["known"]["accepted"] == 1 and snap["a"]["accepted"] == 1
    assert snap["b"]["rejected_registration_cap"] == 1
