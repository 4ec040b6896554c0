"""Worker pool: the pipeline in worker processes, each owning a share of the vehicles."""

from __future__ import annotations

import fcntl
import time
from collections.abc import Callable

import numpy as np
import pytest

from estimator.config import WheeledRearDriveConfig
from estimator.sim import simulate
from server.estimation.registry import EstimatorRegistry
from server.ingest.pipeline import Pipeline
from server.ingest.workers import PIPE_BYTES, WorkerPool, owner_of
from server.protocol import sensor_key
from server.settings import Settings
from server.tooling.fleet_sim import encode_packets, packetize
from tests.server.ingest.fakes import FAILING_VEHICLE, CapturingSink, mixed_registry

VEHICLES = [f"w{i:03d}" for i in range(6)]


def _packets(vehicles: list[str]) -> list[tuple[str, bytes]]:
    """A 20 s drive per vehicle, interleaved as a fleet's packets arrive."""
    run = simulate("paper_straight", seed=1, start_ns=time.time_ns() - 60 * 10**9)
    encoded = encode_packets(packetize(run.sent_in_arrival_order(), run.start_ns))
    limit = sum(1 for _ in encoded) * 20 // max(1, round(run.duration_s))
    return [
        (sensor_key("fleet", vid, stream), payload)
        for stream, payload in encoded[:limit]
        for vid in vehicles
    ]


def _feed(pool: WorkerPool, packets: list[tuple[str, bytes]], burst: int = 64) -> None:
    for i in range(0, len(packets), burst):
        pool.route(packets[i : i + burst])


def _pool(
    sink: CapturingSink,
    workers: int = 2,
    restart_registry_factory: Callable[[], Callable[[], EstimatorRegistry]] | None = None,
    **ingest: object,
) -> WorkerPool:
    settings = Settings(ingest={"workers": workers, **ingest}, viewer={"enabled": False})
    return WorkerPool(settings, None, [sink], restart_registry_factory=restart_registry_factory)


def test_owner_is_stable_and_spreads_the_fleet() -> None:
    owners = [owner_of(f"sim-{i:04d}", 3) for i in range(3000)]
    assert owners == [owner_of(f"sim-{i:04d}", 3) for i in range(3000)]
    assert set(owners) == {0, 1, 2}
    assert min(np.bincount(owners)) > 800  # crc32 spreads numbered ids about evenly


def test_pipes_to_and_from_a_worker_are_widened() -> None:
    pool = _pool(CapturingSink(), workers=1)
    pool.start()
    try:
        w = pool._workers[0]
        for conn in (w.feed, w.results):
            assert fcntl.fcntl(conn.fileno(), fcntl.F_GETPIPE_SZ) >= PIPE_BYTES
    finally:
        pool.stop()


def test_every_vehicle_is_estimated_once_and_counted() -> None:
    sink = CapturingSink()
    pool = _pool(sink)
    packets = _packets(VEHICLES)
    # one packet the worker must refuse, with its reason, for w001 alone
    bad = (sensor_key("fleet", "w001", "imu"), b"\xc1not msgpack")
    assert len({owner_of(v, 2) for v in VEHICLES}) == 2, "both workers own vehicles"
    pool.start()
    try:
        _feed(pool, [*packets[:100], bad, *packets[100:]])
        deadline = time.monotonic() + 30
        while sum(c["received"] for c in pool.counters_snapshot().values()) < len(packets) + 1:
            assert time.monotonic() < deadline, pool.counters_snapshot()
            time.sleep(0.2)
        assert pool.stats()["running"] and pool.stats()["workers"] == 2
        # each worker reports its threads' CPU; its pipeline thread did the decoding and
        # estimating (the snapshots come once a second)
        while not all(
            cpu.get("slipfleet-pipeline", 0.0) > 0.0 for cpu in pool.thread_cpu_snapshot().values()
        ):
            assert time.monotonic() < deadline, pool.thread_cpu_snapshot()
            time.sleep(0.2)
        assert sorted(pool.thread_cpu_snapshot()) == ["worker-0", "worker-1"]
    finally:
        pool.stop()
    assert not pool.stats()["running"]
    counters = pool.counters_snapshot()
    per_vehicle = len(packets) // len(VEHICLES)
    for vid in VEHICLES:
        c = counters[vid]
        assert c["accepted"] == per_vehicle and c["late"] == 0, (vid, c)
        assert c["rejected"] == (1 if vid == "w001" else 0), (vid, c)
    assert counters["w001"]["rejected_undecodable"] == 1
    # every vehicle's ticks, each once, in time order, from exactly one worker
    stamps = {vid: np.concatenate([r["stamp_ns"] for r in sink.rows[vid]]) for vid in VEHICLES}
    lengths = {len(s) for s in stamps.values()}
    assert len(lengths) == 1 and lengths.pop() >= 190  # 20 s of 100 ms ticks
    for s in stamps.values():
        assert np.all(np.diff(s) > 0)
    # the estimators' own counters and anchors come back from both workers
    ticks = pool.estimator_counters_snapshot()["mdsf"]
    assert sorted(ticks) == VEHICLES
    assert sorted(pool.anchors_snapshot()) == VEHICLES


def test_stats_before_the_first_report_hold_every_pipeline_stat_at_zero() -> None:
    # /metrics may be read the moment the server is up, a second before any worker reports
    reference = Pipeline(Settings(viewer={"enabled": False}), None, EstimatorRegistry()).stats()
    pool = _pool(CapturingSink())
    pool.start()
    try:
        stats = pool.stats()
        assert all(not w.snapshot.get("stats") for w in pool._workers), "reported already"
    finally:
        pool.stop()
    numeric = {k for k, v in reference.items() if isinstance(v, int | float) and k != "running"}
    missing = numeric - {"queue_capacity"} - stats.keys()
    assert not missing, missing
    assert stats["rows"] == stats["ticks"] == stats["queue_bursts"] == 0
    assert stats["last_tick_ms"] == 0.0 and stats["workers"] == 2


def test_registrations_and_stored_counters_reach_the_owner() -> None:
    sink = CapturingSink()
    pool = _pool(sink, unknown_vehicle="reject")
    pool.register_vehicle("w000", WheeledRearDriveConfig())
    pool.register_vehicle("w003", WheeledRearDriveConfig())
    pool.restore_counters("w003", {"received": 1000, "accepted": 1000})
    pool.restore_anchor("w003", (47.5, 10.5, 400.0))  # the frame of its stored rows
    pool.start()
    try:
        _feed(pool, _packets(["w000", "w003", "w004"]))
    finally:
        pool.stop()
    anchors = pool.anchors_snapshot()
    assert anchors["w003"] == (47.5, 10.5, 400.0)
    assert anchors["w000"] != anchors["w003"]  # its own first fix
    counters = pool.counters_snapshot()
    assert sorted(sink.rows) == ["w000", "w003"]  # w004 is not registered
    assert counters["w004"]["accepted"] == 0
    assert counters["w004"]["rejected_unknown_vehicle"] == counters["w004"]["received"] > 0
    assert counters["w003"]["received"] == 1000 + counters["w000"]["received"]


def test_new_vehicles_are_reported_to_the_server() -> None:
    sink = CapturingSink()
    settings = Settings(ingest={"workers": 2}, viewer={"enabled": False})
    seen: list[str] = []
    pool = WorkerPool(settings, None, [sink], on_new_vehicle=lambda vid, _cfg: seen.append(vid))
    pool.start()
    try:
        _feed(pool, _packets(VEHICLES[:3])[:30])
    finally:
        pool.stop()
    assert sorted(seen) == VEHICLES[:3]


def test_a_dead_worker_is_started_again_with_its_vehicles_counters_and_frames() -> None:
    sink = CapturingSink()
    fresh: list[int] = []

    def restart_factory() -> Callable[[], EstimatorRegistry]:
        fresh.append(1)  # the runtime reads the store's newest calibrations here
        return EstimatorRegistry

    pool = _pool(sink, restart_registry_factory=restart_factory)
    mine = [v for v in VEHICLES if owner_of(v, 2) == owner_of("w000", 2)]
    packets = _packets(mine)
    half = len(packets) // 2
    pool.start()
    try:
        _feed(pool, packets[:half])
        deadline = time.monotonic() + 30
        while sum(pool.counters_snapshot().get(v, {}).get("received", 0) for v in mine) < half:
            assert time.monotonic() < deadline
            time.sleep(0.1)
        while not set(mine) <= set(pool.anchors_snapshot()):
            assert time.monotonic() < deadline
            time.sleep(0.1)
        frames = {v: pool.anchors_snapshot()[v] for v in mine}
        victim = pool._workers[owner_of("w000", 2)]
        victim.process.kill()
        while not victim.done.is_set():  # the collector saw it go
            assert time.monotonic() < deadline
            time.sleep(0.01)
        _feed(pool, packets[half : half + 12])  # must not raise on the route thread
        while not pool.stats()["running"]:
            assert time.monotonic() < deadline, pool.stats()
            time.sleep(0.05)
        rows_before = {v: sum(len(r) for r in sink.rows.get(v, [])) for v in mine}
        _feed(pool, packets[half + 12 :])
    finally:
        pool.stop()
    stats = pool.stats()
    assert stats["worker_restarts"] == 1
    assert fresh == [1]  # the restarted worker's registry was built afresh, not the start's
    counters = pool.counters_snapshot()
    received = sum(counters[v]["received"] for v in mine)
    # counted on from the dead worker's last snapshot (which had all of the first half): what
    # was routed while it was down is counted as dropped, everything else as received
    assert received + stats["dropped_worker_down"] == len(packets)
    assert stats["dropped_worker_down"] > 0
    for v in mine:  # the restarted worker estimates its vehicles again
        assert sum(len(r) for r in sink.rows[v]) > rows_before[v] + 50
    # in the frames they had: east/north go on where they were, not at the next first fix
    assert {v: pool.anchors_snapshot()[v] for v in mine} == frames


def test_a_mixed_fleet_through_workers_loses_only_the_failing_vehicles_estimator() -> None:
    """Workers run MDSF and, for some vehicles, a reference-speed estimator that fails for
    one of them: every estimator's rows come back as batches of its spec, the failing
    vehicle's MDSF rows all come, and its failures are counted for it alone."""
    sink = CapturingSink()
    settings = Settings(
        ingest={"workers": 2, "unknown_vehicle": "reject"}, viewer={"enabled": False}
    )
    pool = WorkerPool(settings, None, [sink], registry_factory=mixed_registry)
    mixed = [FAILING_VEHICLE, "w002", "w004"]
    assert len({owner_of(v, 2) for v in mixed}) == 2, "both workers run the second estimator"
    for vid in VEHICLES:
        both = ("mdsf", "reference_speed") if vid in mixed else ()
        pool.register_vehicle(vid, WheeledRearDriveConfig(estimators=both))
    packets = _packets(VEHICLES)
    pool.start()
    try:
        _feed(pool, packets)
        deadline = time.monotonic() + 60
        while sum(c["received"] for c in pool.counters_snapshot().values()) < len(packets):
            assert time.monotonic() < deadline, pool.counters_snapshot()
            time.sleep(0.2)
    finally:
        pool.stop()
    stamps = {
        name: {vid: np.concatenate([r["stamp_ns"] for r in parts]) for vid, parts in got.items()}
        for name, got in sink.by_estimator.items()
    }
    assert sorted(stamps["mdsf"]) == VEHICLES
    assert sorted(stamps["reference_speed"]) == ["w002", "w004"]
    for per_vehicle in stamps.values():
        for s in per_vehicle.values():
            assert np.all(np.diff(s) > 0)  # each row once, in time order
    assert {len(s) for s in stamps["mdsf"].values()} == {len(stamps["mdsf"]["w000"])}
    assert len(stamps["mdsf"]["w000"]) >= 190  # 20 s of 100 ms ticks
    for vid in ("w002", "w004"):  # the recording estimator's rows reach the last advance,
        # which MDSF's last tick (on its 100 ms grid) is at most a tick before
        lead_ns = stamps["reference_speed"][vid][-1] - stamps["mdsf"][vid][-1]
        assert 0 <= lead_ns < 100_000_000
    counters = pool.counters_snapshot()
    assert counters[FAILING_VEHICLE]["estimator_errors"] > 0
    assert all(counters[v]["estimator_errors"] == 0 for v in VEHICLES if v != FAILING_VEHICLE)
    assert pool.stats()["estimator_errors"] == counters[FAILING_VEHICLE]["estimator_errors"]


@pytest.mark.parametrize("workers", [0, -1])
def test_needs_at_least_one_worker(workers: int) -> None:
    with pytest.raises(ValueError):  # the pool's own check, or the setting's validation
        _pool(CapturingSink(), workers=workers)
