"""Pipeline without Zenoh (packets fed by ``submit``): reorder, registration, counters, sinks."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import numpy as np
import pytest

import server.ingest.pipeline as pipeline_module
from estimator.config import (
    SlipConfig,
    TrackedConfig,
    VehicleConfig,
    VehicleKind,
    WheeledRearDriveConfig,
)
from estimator.geo import enu_from_geodetic
from estimator.mdsf import MdsfFleet
from estimator.mdsf_spec import MDSF_SPEC
from estimator.reference_speed_spec import REFERENCE_SPEED_SPEC
from estimator.sim import simulate
from estimator.types import (
    EstimateBatch,
    GnssSample,
    ImuBatch,
    OdometerEdges,
    SprocketEdges,
    SteeringAngles,
    TrackSide,
    WheelSpeeds4,
)
from server.estimation import EstimatorRegistry
from server.estimation.registry import KIND_DEFAULTS
from server.ingest import Pipeline
from server.protocol import (
    DecodeError,
    Packet,
    Stream,
    encode_imu,
    encode_odometer,
    encode_sprockets,
    encode_steering,
    encode_wheel_speeds4,
    sensor_key,
)
from server.settings import IngestSettings, Settings, UnknownVehiclePolicy
from server.tooling.fleet_sim import encode_packets, packetize
from tests.server.ingest.fakes import CapturingSink, RecordingFleet, first_stamp

BOTH = ("mdsf", "reference_speed")

MS = 1_000_000
T0 = 1_763_700_000 * 10**9


def imu_batch(first_ms: int, n: int = 10) -> ImuBatch:
    t = T0 + (first_ms + np.arange(n)) * MS
    return ImuBatch(t, np.zeros((n, 3)), np.zeros((n, 3)))


def imu(vid: str, seq: int, first_ms: int, n: int = 10) -> Packet:
    batch = imu_batch(first_ms, n)
    t = batch.stamp_ns
    return Packet(vid, Stream.IMU, seq, 1, (batch,), int(t[0]), int(t[-1]))


def gnss(vid: str, seq: int, at_ms: int) -> Packet:
    t = T0 + at_ms * MS
    g = GnssSample(t, (0.0, 1.0, 0.0), 0.0, 0.0, 0.0, 48.0, 11.0, 500.0)
    return Packet(vid, Stream.GNSS, seq, 1, (g,), t, t)


def make(
    policy: UnknownVehiclePolicy = UnknownVehiclePolicy.AUTO_REGISTER,
    lateness_ms: int = 100,
    on_new: Callable[[str, VehicleConfig], None] | None = None,
    sinks: list[object] | None = None,
    advance_step_ms: int = 200,
    clock_ns: Callable[[], int] = time.monotonic_ns,
    second: RecordingFleet | None = None,
    registry: EstimatorRegistry | None = None,
) -> tuple[Pipeline, RecordingFleet, CapturingSink]:
    """A pipeline on a recording MDSF (and ``second``, a recording reference-speed estimator,
    for vehicles that name it) whose rows go to ``sinks`` and a capturing sink."""
    fleet = RecordingFleet()
    factories = {"mdsf": lambda: fleet}
    if second is not None:
        factories["reference_speed"] = lambda: second
    registry = registry or EstimatorRegistry(factories=factories)
    sink = CapturingSink()
    settings = Settings(
        ingest=IngestSettings.model_validate(
            {
                "lateness_ms": lateness_ms,
                "unknown_vehicle": policy,
                "process_interval_ms": 5,
                "estimate_interval_ms": 5,
                "advance_step_ms": advance_step_ms,
            }
        )
    )
    pipe = Pipeline(
        settings,
        None,
        registry,
        [*(sinks or []), sink],  # type: ignore[list-item]
        on_new,
        clock_ns=clock_ns,
        wall_clock_ns=lambda: T0,  # the packets' stamps are near T0
    )
    return pipe, fleet, sink


def wait_for(cond: Callable[[], bool], timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError("condition not met in time")
        time.sleep(0.005)


def test_feeds_in_order_and_counts_add_up() -> None:
    new: list[tuple[str, VehicleConfig]] = []
    pipe, fleet, sink = make(on_new=lambda v, c: new.append((v, c)))
    pipe.start()
    pipe.submit([imu("a", 2, 20), gnss("a", 0, 5), imu("a", 0, 0), imu("b", 0, 0)])
    pipe.submit([imu("a", 1, 10), imu("a", 1, 10), DecodeError("non_finite", vehicle_id="a")])
    pipe.submit([imu("a", 5, 50), DecodeError("bad_key")])  # seq 3, 4 never come
    pipe.stop()
    stamps = [first_stamp(m) for m in fleet.pushed["a"]]
    assert stamps == sorted(stamps) and len(stamps) == 5
    assert len(fleet.pushed["b"]) == 1
    snap = pipe.counters_snapshot()
    a = snap["a"]
    assert a["received"] == 7 and a["accepted"] == 5 and a["duplicate"] == 1
    assert a["rejected_non_finite"] == 1 and a["lost_by_seq_gap"] == 2 and a["late"] == 0
    assert snap[""]["rejected_bad_key"] == 1
    for c in snap.values():
        assert c["received"] == c["accepted"] + c["late"] + c["duplicate"] + c["rejected"]
    assert [v for v, _ in new] == ["a", "b"] and new[0][1] == WheeledRearDriveConfig()
    # the sink saw rows up to the last released time of each vehicle
    assert int(sink.rows["a"][-1]["stamp_ns"][-1]) == T0 + 59 * MS
    assert pipe.stats()["rows"] >= 2 and not pipe.stats()["running"]


def test_unknown_vehicle_rejected_unless_registered() -> None:
    pipe, fleet, _ = make(policy=UnknownVehiclePolicy.REJECT)
    pipe.register_vehicle("known", WheeledRearDriveConfig())
    pipe.start()
    pipe.submit([imu("known", 0, 0), imu("stranger", 0, 0), imu("stranger", 1, 10)])
    pipe.stop()
    snap = pipe.counters_snapshot()
    assert snap["known"]["accepted"] == 1
    assert snap["stranger"]["rejected_unknown_vehicle"] == 2 and snap["stranger"]["accepted"] == 0
    assert "stranger" not in fleet.vehicles


def test_late_packet_is_counted_and_not_fed() -> None:
    pipe, fleet, _ = make(lateness_ms=0)
    pipe.start()
    pipe.submit([imu("a", 1, 100)])
    wait_for(lambda: len(fleet.pushed.get("a", [])) == 1)
    pipe.submit([imu("a", 0, 0)])  # older than what was already fed
    pipe.stop()
    c = pipe.counters_snapshot()["a"]
    assert (c["accepted"], c["late"], c["lost_by_seq_gap"]) == (1, 1, 0)
    assert len(fleet.pushed["a"]) == 1


def test_remove_vehicle_forgets_everything() -> None:
    pipe, fleet, _ = make()
    pipe.start()
    pipe.submit([imu("a", 0, 0)])
    wait_for(lambda: "a" in pipe.counters_snapshot())
    pipe.remove_vehicle("a")
    wait_for(lambda: "a" not in pipe.counters_snapshot())
    pipe.stop()
    assert "a" not in fleet.vehicles


def test_tracked_vehicle_accepted_without_estimators() -> None:
    fleet = RecordingFleet()
    registry = EstimatorRegistry(  # a server whose tracked vehicles run no estimator
        factories={"mdsf": lambda: fleet},
        kind_defaults={**KIND_DEFAULTS, VehicleKind.TRACKED: ()},
    )
    pipe, _, sink = make(policy=UnknownVehiclePolicy.REJECT, registry=registry)
    pipe.register_vehicle("t1", TrackedConfig())
    pipe.start()
    pipe.submit([imu("t1", 0, 0)])
    pipe.stop()
    assert pipe.counters_snapshot()["t1"]["accepted"] == 1
    assert "t1" not in fleet.vehicles and "t1" not in sink.rows


def test_a_config_an_estimator_refuses_is_not_applied_and_ingest_goes_on() -> None:
    pipe, _, _ = make(registry=EstimatorRegistry())  # the real MDSF: rear-drive vehicles only
    pipe.register_vehicle("crawler", TrackedConfig(estimators=("mdsf",)))
    pipe.start()
    pipe.submit([imu("a", 0, 0), gnss("a", 0, 5), imu("a", 1, 10)])
    wait_for(lambda: "a" in pipe.counters_snapshot())
    assert pipe.stats()["running"]
    pipe.stop()


class BrokenSink:
    def on_estimates(self, batch: EstimateBatch) -> None:
        raise RuntimeError("disk full")


def test_failing_sink_does_not_stop_others() -> None:
    pipe, _, sink = make(sinks=[BrokenSink()])
    pipe.start()
    pipe.submit([imu("a", 0, 0)])
    pipe.stop()
    assert "a" in sink.rows and pipe.stats()["sink_errors"] >= 1


def test_submit_to_a_stopped_pipeline_drops_and_counts() -> None:
    pipe, _, _ = make()
    pipe.start()
    pipe.stop()
    for _ in range(300):  # more bursts than the queue holds: must not block
        pipe.submit([imu("a", 0, 0)])
    assert pipe.stats()["dropped_not_running"] > 0


def test_estimators_advance_in_steps_then_to_the_end() -> None:
    pipe, fleet, _ = make(lateness_ms=0, advance_step_ms=250)
    pipe.start()
    for k in range(10):  # 1 s of data, one 100 ms packet at a time
        pipe.submit([imu("a", k, 100 * k)])
        wait_for(lambda k=k: len(fleet.pushed.get("a", [])) == k + 1)
    pipe.stop()
    untils = [adv["a"] for adv in fleet.advances]
    # one call per crossing of a 250 ms multiple (T0 is one), then the final one
    steps = np.array(untils[:-1]) // (250 * MS) - T0 // (250 * MS)
    assert list(steps) == list(range(len(steps)))
    assert untils[-1] == T0 + 909 * MS  # and the last sample is reached
    assert len(untils) <= 5


def test_a_vehicle_that_falls_silent_gets_its_tail_released() -> None:
    """The reorder window holds a vehicle's newest packets back; when the vehicle stops
    sending, the idle look-out releases them (the pipeline keeps running)."""
    skew = [0]  # the pipeline's monotonic clock runs ahead by this much

    def clock() -> int:
        return time.monotonic_ns() + skew[0]

    pipe, fleet, _ = make(lateness_ms=300, advance_step_ms=100, clock_ns=clock)
    pipe.start()
    try:
        pipe.submit([imu("a", k, 100 * k) for k in range(8)])
        wait_for(lambda: len(fleet.pushed.get("a", [])) >= 4)
        time.sleep(0.1)  # a few ticks: the window still holds the newest batches
        held = len(fleet.pushed["a"])
        assert held < 8
        skew[0] = 5 * 10**9  # longer than the idle time (1 s) without a packet
        wait_for(lambda: len(fleet.pushed["a"]) == 8)
        wait_for(lambda: bool(fleet.advances) and fleet.advances[-1]["a"] == T0 + 709 * MS)
    finally:
        pipe.stop()


def test_ticks_are_put_on_the_end_of_the_first_imu_batch() -> None:
    """The estimators learn the vehicle's tick phase (the last sample of its first IMU batch)
    before its first push, and advance steps fall on that grid, so a tick at a batch's end is
    computed as soon as that batch is released."""
    pipe, fleet, _ = make(lateness_ms=0, advance_step_ms=100)
    pipe.start()
    # GNSS first in the burst: not what the ticks are put on (in one burst with the first IMU
    # batch, so both are offered before anything is pushed)
    pipe.submit([gnss("a", 0, 60), imu("a", 0, 73, n=5)])
    wait_for(lambda: len(fleet.pushed.get("a", [])) == 2)
    for k in range(1, 8):  # 50 ms IMU batches ending at 77, 127, 177, ... ms
        pipe.submit([imu("a", k, 73 + 50 * k, n=5)])
        wait_for(lambda k=k: len(fleet.pushed.get("a", [])) == k + 2)
    pipe.stop()
    anchor = T0 + 77 * MS
    assert fleet.aligned == {"a": anchor}
    untils = [adv["a"] for adv in fleet.advances][:-1]  # the last one is the final flush
    assert len(untils) >= 3
    assert all((u - anchor) % (100 * MS) == 0 for u in untils)


def test_refusals_of_many_unregistered_ids_share_one_bucket(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(pipeline_module, "MAX_UNREGISTERED_COUNTED", 3)
    pipe, _, _ = make(policy=UnknownVehiclePolicy.REJECT)
    pipe.register_vehicle("known", WheeledRearDriveConfig())
    pipe.start()
    pipe.submit([imu(f"x{i}", 0, 0) for i in range(10)])
    pipe.submit([DecodeError("wrong_type", vehicle_id=f"y{i}") for i in range(5)])
    pipe.submit([DecodeError("wrong_type", vehicle_id="known")])
    pipe.stop()
    snap = pipe.counters_snapshot()
    assert sorted(snap) == ["", "known", "x0", "x1", "x2"]
    assert snap[""]["rejected_unknown_vehicle"] == 7 and snap[""]["rejected_wrong_type"] == 5
    assert snap["known"]["rejected_wrong_type"] == 1


def test_sequence_tracking_resumes_after_a_restart() -> None:
    """Packets sent while the server was down count as lost once it is back."""
    pipe, _, _ = make()
    pipe.start()
    pipe.submit([imu("a", 0, 0), imu("a", 1, 10), imu("a", 2, 20)])
    pipe.stop()
    stored = pipe.counters_snapshot()["a"]
    assert stored["seq_high_imu"] == 2 and stored["lost_by_seq_gap"] == 0
    again, _, _ = make()  # the next server run, from the stored totals
    again.restore_counters("a", stored)
    again.start()
    again.submit([imu("a", 7, 70), imu("a", 8, 80)])  # 3..6 were sent while it was down
    again.stop()
    c = again.counters_snapshot()["a"]
    assert c["lost_by_seq_gap"] == 4 and c["seq_high_imu"] == 8
    assert c["received"] == 5 == c["accepted"]


def test_the_boot_id_is_stored_with_the_sequence_numbers() -> None:
    """After a restart the stored boot id keeps the numbers seen under it duplicates, and a new
    boot (the vehicle rebooted while the server was down) starts afresh without a loss."""
    boot, rebooted = 2**62 + 5, 17
    pipe, _, _ = make()
    pipe.start()
    pipe.submit([dataclasses.replace(imu("a", k, 10 * k), boot=boot) for k in range(3)])
    pipe.stop()
    stored = pipe.restorable_counters()["a"]
    assert stored["seq_boot"] == boot and stored["seq_high_imu"] == 2
    assert "seq_boot" not in pipe.counters_snapshot()["a"]  # not a counter: never reported
    again, _, _ = make()
    again.restore_counters("a", stored)
    again.start()
    again.submit([dataclasses.replace(imu("a", 2, 20), boot=boot)])  # seen before the restart
    again.submit([dataclasses.replace(imu("a", k, 30 + 10 * k), boot=rebooted) for k in range(3)])
    again.stop()
    c = again.counters_snapshot()["a"]
    assert c["duplicate"] == 1 and c["seq_restarts"] == 1 and c["lost_by_seq_gap"] == 0
    assert c["accepted"] == 6 and again.restorable_counters()["a"]["seq_boot"] == rebooted


def test_final_snapshots_include_vehicles_seen_since_the_last_refresh(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Stopping refreshes the estimators' counters and anchors one last time: a vehicle first
    seen after the periodic refresh is in them (a worker's final report is this snapshot)."""
    monkeypatch.setattr(pipeline_module, "ESTIMATOR_COUNTERS_EVERY_NS", 3600 * 10**9)
    settings = Settings(ingest=IngestSettings.model_validate({"process_interval_ms": 5}))
    pipe = Pipeline(settings, None, EstimatorRegistry(), [], wall_clock_ns=lambda: T0)
    pipe.start()
    time.sleep(0.1)  # the periodic refresh at start runs before any vehicle is seen
    pipe.submit([gnss("late", 0, 0), imu("late", 0, 0)])
    pipe.stop()
    assert "late" in pipe.estimator_counters_snapshot()["mdsf"]
    assert pipe.anchors_snapshot()["late"] == pytest.approx((48.0, 11.0, 500.0))


def _drive(pipe: Pipeline, vid: str, seconds: range) -> None:
    """GNSS and IMU packets of ``vid`` in time order, one of each per 100 ms."""
    pipe.submit([p for i in seconds for p in (gnss(vid, i, 100 * i), imu(vid, i, 100 * i, 100))])


def test_an_estimator_command_reaches_the_running_estimator_between_steps() -> None:
    """An operator's calibration drive turns on in the vehicle's MDSF fleet on the pipeline
    thread; a command for an estimator the vehicle does not run is an estimator error of that
    vehicle, and the pipeline goes on."""
    settings = Settings(ingest=IngestSettings.model_validate({"process_interval_ms": 5}))
    registry = EstimatorRegistry()
    pipe = Pipeline(settings, None, registry, [CapturingSink()], wall_clock_ns=lambda: T0)
    pipe.register_vehicle("a", WheeledRearDriveConfig())
    pipe.register_vehicle("b", WheeledRearDriveConfig(estimators=("reference_speed",)))
    pipe.start()
    try:
        wait_for(lambda: registry.has_vehicle("a") and registry.has_vehicle("b"))
        mdsf = registry.estimator("mdsf")  # built by the pipeline thread's registration
        assert isinstance(mdsf, MdsfFleet) and "a" in mdsf.vehicle_ids()
        assert not mdsf.calibration_drive_on("a")
        pipe.send_command("a", "mdsf", "calibration_drive", True)
        wait_for(lambda: mdsf.calibration_drive_on("a"))
        pipe.send_command("b", "mdsf", "calibration_drive", True)
        wait_for(lambda: pipe.counters_snapshot().get("b", {}).get("estimator_errors") == 1)
        pipe.send_command("a", "mdsf", "calibration_drive", False)
        wait_for(lambda: not mdsf.calibration_drive_on("a"))
        _drive(pipe, "a", range(12))
        wait_for(lambda: pipe.counters_snapshot().get("a", {}).get("accepted") == 24)
    finally:
        pipe.stop()


def test_a_restored_anchor_keeps_the_frame_across_runs_and_reconfigurations() -> None:
    """East/north go on in the frame a previous run stored (not at this run's first fix), also
    after the vehicle is configured again (a fresh estimator); a deleted vehicle starts anew."""
    stored = (47.99, 11.01, 480.0)  # the earlier run's anchor; this run's first fix is 48/11
    settings = Settings(ingest=IngestSettings.model_validate({"process_interval_ms": 5}))
    sink = CapturingSink()
    pipe = Pipeline(settings, None, EstimatorRegistry(), [sink], wall_clock_ns=lambda: T0)
    pipe.register_vehicle("a", WheeledRearDriveConfig())
    pipe.restore_anchor("a", stored)
    pipe.start()
    try:
        _drive(pipe, "a", range(12))
        wait_for(lambda: pipe.anchors_snapshot().get("a") == stored)
        pipe.register_vehicle(
            "a", WheeledRearDriveConfig(slip=SlipConfig(alert_threshold_pct=20.0))
        )
        time.sleep(0.2)  # control is applied on the pipeline thread, between bursts
        _drive(pipe, "a", range(12, 24))
        wait_for(lambda: pipe.counters_snapshot()["a"]["accepted"] == 48)
        time.sleep(1.2)  # one more snapshot of the anchors
        assert pipe.anchors_snapshot()["a"] == stored  # not this run's first fix
        first_rows = np.concatenate(sink.rows["a"])
        pipe.remove_vehicle("a")
        pipe.register_vehicle("a", WheeledRearDriveConfig())
        time.sleep(0.2)
        _drive(pipe, "a", range(24, 36))
        wait_for(lambda: pipe.anchors_snapshot().get("a") == pytest.approx((48.0, 11.0, 500.0)))
    finally:
        pipe.stop()
    east, north, _ = enu_from_geodetic(48.0, 11.0, 500.0, *stored)
    assert abs(east) > 500 and abs(north) > 500  # far from where a new frame would put it
    placed = np.isfinite(first_rows["east_m"])
    assert placed.sum() >= 10
    # the first two registrations' rows lie where 48/11 is in the stored frame
    np.testing.assert_allclose(first_rows["east_m"][placed], east, atol=1.0)
    np.testing.assert_allclose(first_rows["north_m"][placed], north, atol=1.0)


def test_a_clock_reanchor_restarts_the_estimators_in_the_same_frame() -> None:
    settings = Settings(ingest=IngestSettings.model_validate({"process_interval_ms": 5}))
    pipe = Pipeline(
        settings, None, EstimatorRegistry(), [CapturingSink()], wall_clock_ns=lambda: T0
    )
    pipe.register_vehicle("a", WheeledRearDriveConfig())
    pipe.start()
    try:
        _drive(pipe, "a", range(12))
        wait_for(lambda: "a" in pipe.anchors_snapshot())
        moved = []  # the vehicle's clock jumps 5 min ahead; it stands 1 km further north
        for i in range(12, 24):
            t = T0 + (300_000 + 100 * i) * MS
            g = GnssSample(t, (0.0, 1.0, 0.0), 0.0, 0.0, 0.0, 48.009, 11.0, 500.0)
            moved += [
                Packet("a", Stream.GNSS, i, 1, (g,), t, t),
                imu("a", i, 300_000 + 100 * i, 100),
            ]
        pipe.submit(moved)
        wait_for(lambda: pipe.counters_snapshot()["a"]["clock_reanchors"] == 1)
        time.sleep(1.2)  # the next snapshot of the anchors
        assert pipe.anchors_snapshot()["a"] == pytest.approx((48.0, 11.0, 500.0))
    finally:
        pipe.stop()


def test_tick_schedule_keeps_the_estimator_cadence_and_the_duty() -> None:
    """Ticks every process_interval_ms; none later than the next estimator call is due (so calls
    come every estimate_interval_ms instead of at the first tick after it); a slow tick spaced
    by its duty, never further than MAX_TICK_GAP_NS."""
    settings = Settings(
        ingest=IngestSettings.model_validate(
            {"process_interval_ms": 20, "estimate_interval_ms": 50}
        )
    )
    pipe = Pipeline(settings, None, EstimatorRegistry(factories={"mdsf": RecordingFleet}))
    now = 1_000 * MS
    # an estimator call started at `now`: the next one is due 50 ms later
    pipe._next_estimate_ns = now + 50 * MS
    # a cheap tick: the next one a process interval later
    assert pipe._next_tick_ns(now, now, 1 * MS) == now + 20 * MS
    # the regular tick after 40 ms would come at 60 ms: it comes when the call is due, at 50
    assert pipe._next_tick_ns(now + 40 * MS, now + 40 * MS, 1 * MS) == now + 50 * MS
    # a 20 ms tick is followed by a gap of its duty, not by the next regular tick
    spaced = now + int(pipeline_module.TICK_DUTY * 20 * MS)
    assert pipe._next_tick_ns(now, now, 20 * MS) == spaced > now + 20 * MS
    # however slow the tick, the next one comes within MAX_TICK_GAP_NS
    assert pipe._next_tick_ns(now, now, 10_000 * MS) == now + pipeline_module.MAX_TICK_GAP_NS
    # no estimator call pending (its due time passed): the regular interval
    pipe._next_estimate_ns = now - 1
    assert pipe._next_tick_ns(now + 40 * MS, now + 40 * MS, 1 * MS) == now + 60 * MS


def test_raw_bursts_are_decoded_on_the_pipeline_thread_refusals_counted() -> None:
    pipe, fleet, _ = make()
    pipe.start()
    good = [("fleet/a/sensors/imu", encode_imu(imu_batch(10 * k), k)) for k in range(12)]
    bad = [("fleet/a/sensors/imu", b"\xc1 not msgpack"), ("fleet/a/oops", b"")]
    pipe.submit_raw(good[:6] + bad)  # a burst large enough to be decoded together
    pipe.submit_raw(good[6:])
    pipe.stop()
    assert len(fleet.pushed["a"]) == 12
    snap = pipe.counters_snapshot()
    assert snap["a"]["accepted"] == 12 and snap["a"]["rejected_undecodable"] == 1
    assert snap[""]["rejected_bad_key"] == 1


def test_the_pipeline_thread_adds_up_its_cpu_by_phase() -> None:
    pipe, _, sink = make()
    assert all(pipe.stats()[f"cpu_{phase}_s"] == 0.0 for phase in pipeline_module.PHASES)
    pipe.start()
    try:
        pipe.submit_raw(
            [("fleet/a/sensors/imu", encode_imu(imu_batch(10 * k), k)) for k in range(12)]
        )
        wait_for(lambda: pipe.counters_snapshot().get("a", {}).get("accepted") == 12)
        wait_for(lambda: bool(sink.rows.get("a")))  # released, estimated, delivered
        stats = pipe.stats()
    finally:
        pipe.stop()
    # each phase ran on the pipeline thread and its CPU time was added up
    assert all(stats[f"cpu_{phase}_s"] > 0.0 for phase in pipeline_module.PHASES), stats
    assert sum(stats[f"cpu_{phase}_s"] for phase in pipeline_module.PHASES) < 5.0


def test_undecoded_bursts_queued_back_to_back_are_decoded_as_one(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    pipe, _, _ = make()  # not started: the queue is filled by hand, as a backlog would be
    key = "fleet/a/sensors/imu"
    burst = [[(key, encode_imu(imu_batch(10 * k), k))] * n for k, n in enumerate((4, 3, 2, 1))]
    raw = pipeline_module._Raw
    pipe._queue.put((2, raw(burst[1])))
    pipe._queue.put((3, raw(burst[2])))
    pipe._queue.put((4, [imu("a", 9, 90)]))  # decoded items: not joined, held for next turn
    pipe._queue.put((5, raw(burst[3])))
    received_ns, joined = pipe._coalesce(1, raw(burst[0]))
    assert (received_ns, len(joined)) == (3, 9)
    assert joined.received == burst[0] + burst[1] + burst[2]
    assert pipe._next_item(None)[0] == 4 and pipe._next_item(None)[0] == 5
    # a bound on the joined burst's size
    monkeypatch.setattr(pipeline_module, "COALESCE_PACKETS", 5)
    for k in (1, 2, 3):
        pipe._queue.put((k, raw(burst[k])))
    received_ns, joined = pipe._coalesce(0, raw(burst[0]))
    assert (received_ns, len(joined)) == (1, 7)
    assert pipe._next_item(None)[0] == 2


def _mixed_fleet_drive(pipe: Pipeline, vehicles: list[str], seconds: int) -> None:
    """GNSS and IMU packets of every vehicle, one of each per 100 ms, bursts interleaved."""
    for i in range(seconds * 10):
        pipe.submit([p for vid in vehicles for p in (gnss(vid, i, 100 * i), imu(vid, i, 100 * i))])


def _rows_of(sink: CapturingSink, estimator: str, vid: str) -> np.ndarray:
    return np.concatenate([r["stamp_ns"] for r in sink.by_estimator[estimator][vid]])


def test_a_mixed_fleet_delivers_every_row_of_every_estimator_once() -> None:
    """MDSF vehicles and MDSF + reference-speed vehicles: each estimator's rows reach every
    sink once, as batches of that estimator's spec; reference speed gets no GNSS."""
    second = RecordingFleet(REFERENCE_SPEED_SPEC)
    other = CapturingSink()
    pipe, fleet, sink = make(
        policy=UnknownVehiclePolicy.REJECT, sinks=[other], second=second, advance_step_ms=100
    )
    mdsf_only, mixed = ["m0", "m1", "m2"], ["x0", "x1"]
    for vid in mdsf_only:
        pipe.register_vehicle(vid, WheeledRearDriveConfig())
    for vid in mixed:
        pipe.register_vehicle(vid, WheeledRearDriveConfig(estimators=BOTH))
    pipe.start()
    _mixed_fleet_drive(pipe, mdsf_only + mixed, seconds=2)
    pipe.stop()
    for s in (sink, other):
        assert sorted(s.by_estimator["mdsf"]) == sorted(mdsf_only + mixed)
        assert sorted(s.by_estimator["reference_speed"]) == mixed
        for name, est in (("mdsf", fleet), ("reference_speed", second)):
            for vid, emitted in est.rows_emitted.items():
                stamps = _rows_of(s, name, vid)
                assert len(stamps) == emitted >= 1 and np.all(np.diff(stamps) > 0), (name, vid)
    assert pipe.stats()["rows"] == sum(fleet.rows_emitted.values()) + sum(
        second.rows_emitted.values()
    )
    assert all(isinstance(m, ImuBatch) for vid in mixed for m in second.pushed[vid])
    assert len(second.pushed["x0"]) == 20 and len(fleet.pushed["x0"]) == 40
    assert all(c["estimator_errors"] == 0 for c in pipe.counters_snapshot().values())


def test_an_estimator_failing_for_one_vehicle_costs_only_that_vehicle_its_rows(
    caplog: pytest.LogCaptureFixture,
) -> None:
    second = RecordingFleet(REFERENCE_SPEED_SPEC, fail_for=frozenset({"x1"}))
    pipe, fleet, sink = make(policy=UnknownVehiclePolicy.REJECT, second=second)
    vehicles = ["x0", "x1", "x2", "x3"]
    for vid in vehicles:
        pipe.register_vehicle(vid, WheeledRearDriveConfig(estimators=BOTH))
    pipe.start()
    _mixed_fleet_drive(pipe, vehicles, seconds=2)
    pipe.stop()
    assert sorted(sink.by_estimator["reference_speed"]) == ["x0", "x2", "x3"]
    for vid in ("x0", "x2", "x3"):
        assert len(_rows_of(sink, "reference_speed", vid)) == second.rows_emitted[vid] >= 1
    for vid in vehicles:  # MDSF of the failing vehicle goes on as if nothing happened
        assert len(_rows_of(sink, "mdsf", vid)) == fleet.rows_emitted[vid] >= 1
    counters = pipe.counters_snapshot()
    assert counters["x1"]["estimator_errors"] >= 20  # its 20 IMU pushes, then its advances
    assert all(counters[vid]["estimator_errors"] == 0 for vid in ("x0", "x2", "x3"))
    stats = pipe.stats()
    assert stats["estimator_errors"] == counters["x1"]["estimator_errors"]
    assert stats["pipeline_errors"] == 0
    # one line names the vehicle and the estimator; the repeats within ERROR_LOG_EVERY_NS
    # are counted, not logged
    lines = [r.getMessage() for r in caplog.records if r.name == pipeline_module.__name__]
    assert len(lines) == 1 and "estimator reference_speed:" in lines[0]
    assert "for vehicle x1 (0 more failures" in lines[0]


def test_a_config_an_estimator_refuses_is_not_applied_and_the_pipeline_lives_on() -> None:
    second = RecordingFleet(REFERENCE_SPEED_SPEC, refuse_threshold_pct=99.0)
    pipe, fleet, sink = make(policy=UnknownVehiclePolicy.REJECT, second=second)
    old = WheeledRearDriveConfig()
    pipe.register_vehicle("a", old)
    pipe.start()
    try:
        pipe.submit([imu("a", 0, 0)])
        wait_for(lambda: len(fleet.pushed.get("a", [])) == 1)
        refused = WheeledRearDriveConfig(estimators=BOTH, slip=SlipConfig(alert_threshold_pct=99.0))
        pipe.register_vehicle("a", refused)
        pipe.register_vehicle("new", refused)  # a vehicle that never got a config it takes
        wait_for(lambda: pipe.counters_snapshot().get("a", {}).get("configs_refused") == 1)
        pipe.submit([imu("a", 1, 100), imu("new", 0, 0)])
        wait_for(lambda: len(fleet.pushed["a"]) == 2)
        assert pipe.stats()["running"]
    finally:
        pipe.stop()
    assert fleet.vehicles == {"a": old} and second.vehicles == {}
    counters = pipe.counters_snapshot()
    assert counters["new"]["configs_refused"] == 1
    assert counters["new"]["rejected_unknown_vehicle"] == 1
    assert list(sink.by_estimator) == ["mdsf"] and pipe.stats()["pipeline_errors"] == 0


def test_real_estimators_of_a_mixed_fleet_reach_the_sinks_as_batches_of_their_specs() -> None:
    """The real MDSF and reference-speed estimators on simulated drives: MDSF for every
    vehicle, reference speed for the ones that run it too, each as its own spec's rows."""
    run = simulate("paper_straight", seed=2, start_ns=time.time_ns() - 60 * 10**9)
    encoded = encode_packets(packetize(run.sent_in_arrival_order(), run.start_ns))
    encoded = encoded[: len(encoded) * 10 // max(1, round(run.duration_s))]  # 10 s
    sink = CapturingSink()
    settings = Settings(ingest=IngestSettings.model_validate({"unknown_vehicle": "reject"}))
    pipe = Pipeline(settings, None, EstimatorRegistry(), [sink])
    pipe.register_vehicle("m", WheeledRearDriveConfig())
    pipe.register_vehicle("x", WheeledRearDriveConfig(estimators=BOTH))
    pipe.start()
    for k in range(0, len(encoded), 32):
        pipe.submit_raw(
            [(sensor_key("fleet", vid, st), pl) for st, pl in encoded[k : k + 32] for vid in "mx"]
        )
    pipe.stop()
    assert sorted(sink.by_estimator["mdsf"]) == ["m", "x"]
    assert sorted(sink.by_estimator["reference_speed"]) == ["x"]
    mdsf = {vid: np.concatenate(parts) for vid, parts in sink.by_estimator["mdsf"].items()}
    np.testing.assert_array_equal(mdsf["m"]["stamp_ns"], mdsf["x"]["stamp_ns"])
    ref = np.concatenate(sink.by_estimator["reference_speed"]["x"])
    assert ref.dtype == REFERENCE_SPEED_SPEC.dtype and len(ref) >= 90  # 10 s of 100 ms ticks
    assert np.all(np.diff(ref["stamp_ns"]) > 0)
    # the GNSS-free speed follows MDSF's once both have settled (a straight drive, no slip),
    # up to the last tick, which the final flush computes without all of its wheel data
    both = np.intersect1d(ref["stamp_ns"], mdsf["x"]["stamp_ns"])[20:-1]
    v_ref = ref[REFERENCE_SPEED_SPEC.motion_field][np.isin(ref["stamp_ns"], both)]
    v_mdsf = mdsf["x"][MDSF_SPEC.motion_field][np.isin(mdsf["x"]["stamp_ns"], both)]
    assert len(both) > 50 and np.nanmax(np.abs(v_ref - v_mdsf)) < 0.5


def test_new_streams_are_accepted_counted_and_ordered_but_reach_no_estimator() -> None:
    """Odometer, sprockets, steering and four-wheel-speed packets go through decoding,
    counting and the reorder buffer; the estimators here read GNSS, IMU and wheels only."""
    pipe, fleet, _ = make()
    pipe.start()
    t = T0 + np.arange(10, dtype=np.int64) * 10 * MS
    direction = np.ones(10, dtype=np.int8)
    others = [
        ("odometer", encode_odometer(OdometerEdges(t, direction), 0)),
        ("sprockets", encode_sprockets([SprocketEdges(TrackSide.TRACK_RIGHT, t)], 0)),
        ("steering", encode_steering(SteeringAngles(t, np.full(10, 0.3)), 0)),
        ("wheel_speeds4", encode_wheel_speeds4(WheelSpeeds4(t, np.full((10, 4), 2.0)), 0)),
        ("steering", encode_steering(SteeringAngles(t, np.full(10, np.inf)), 1)),
    ]
    imus = [("fleet/a/sensors/imu", encode_imu(imu_batch(10 * k), k)) for k in range(12)]
    pipe.submit_raw(imus[:4] + [(f"fleet/a/sensors/{s}", p) for s, p in others] + imus[4:])
    pipe.stop()
    assert [type(m) for m in fleet.pushed["a"]] == [ImuBatch] * 12
    snap = pipe.counters_snapshot()["a"]
    assert snap["accepted"] == 12 + 4 and snap["rejected_non_finite"] == 1
    assert pipe.stats()["estimator_errors"] == 0
