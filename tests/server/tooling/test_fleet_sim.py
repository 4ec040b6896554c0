"""Simulated fleet → embedded router → pipeline with the real MDSF estimator; record and replay."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from estimator.sim import simulate
from estimator.types import ESTIMATE_DTYPE, EstimateFlag, WheelEdges
from server.estimation import EstimatorRegistry
from server.ingest import Pipeline
from server.protocol import Stream, decode, sensor_key
from server.protocol.recording import Record, read_recording, write_recording
from server.settings import IngestSettings, Settings
from server.tooling.fleet_sim import FleetSim, packetize, record, replay
from tests.server.ingest.fakes import (
    CapturingSink,
    RecordingFleet,
    client_session,
    embedded_router,
)

T0 = 1_763_700_000 * 10**9


def test_packetize_merges_wheels_and_round_trips() -> None:
    run = simulate("hard_braking", seed=3, start_ns=T0)
    packets = packetize(run.sent_in_arrival_order(), run.start_ns)
    wheel_packets = [p for p in packets if p.stream is Stream.WHEELS]
    assert any(len(p.measurements) == 2 for p in wheel_packets)
    heartbeats = [p for p in wheel_packets if all(len(m.stamp_ns) == 0 for m in p.measurements)]
    assert len(heartbeats) == len(run.heartbeat_ns) > 0  # it stands still before braking ends
    assert all(len(p.measurements) == 1 and p.until_ns is not None for p in heartbeats)
    assert sum(len(p.measurements) for p in packets) == len(run.measurements) + len(heartbeats)
    offsets = [p.arrival_offset_ns for p in packets]
    assert offsets == sorted(offsets)
    for seq, p in enumerate(packets):
        got = decode(
            sensor_key("fleet", "sim-0001", p.stream),
            p.encode(seq),
        )
        assert got.until_ns == p.until_ns
        if p in heartbeats:
            assert got.measurements == () and got.first_stamp_ns == p.until_ns
            continue
        assert len(got.measurements) == len(p.measurements)
        for a, b in zip(p.measurements, got.measurements, strict=True):
            assert type(a) is type(b)
            if isinstance(a, WheelEdges):
                assert isinstance(b, WheelEdges)
                np.testing.assert_array_equal(a.stamp_ns, b.stamp_ns)


def test_recording_file_round_trip(tmp_path: object) -> None:
    from pathlib import Path

    path = Path(str(tmp_path)) / "r.slrec"
    recs = [Record("fleet/a/sensors/imu", T0 + i, bytes([i]) * i) for i in range(5)]
    assert write_recording(path, recs) == 5
    assert list(read_recording(path)) == recs
    # a truncated tail (recorder killed) is ignored
    path.write_bytes(path.read_bytes()[:-2])
    assert list(read_recording(path)) == recs[:4]


@pytest.mark.zenoh
@pytest.mark.slow
def test_simulated_fleet_estimated_live_then_replayed(tmp_path: object) -> None:
    from pathlib import Path

    rec_path = Path(str(tmp_path)) / "fleet.slrec"
    settings_kw = {"lateness_ms": 300, "process_interval_ms": 20}
    sink = CapturingSink()
    with embedded_router() as (router, zs, endpoint):
        settings = Settings(zenoh=zs, ingest=IngestSettings.model_validate(settings_kw))
        pipe = Pipeline(settings, router, EstimatorRegistry(), [sink])
        pipe.start()
        stop_rec = threading.Event()
        with client_session(endpoint) as vehicles, client_session(endpoint) as recorder:
            counted: list[int] = []
            rec_thread = threading.Thread(
                target=lambda: counted.append(record(rec_path, recorder, "fleet/**", stop=stop_rec))
            )
            rec_thread.start()
            time.sleep(0.3)  # the recorder's subscription reaches the router
            sim = FleetSim(vehicles, 3, scenario="hard_braking", rate=25.0, seed=5)
            stats = sim.run()
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline:
                snap = pipe.counters_snapshot()
                if sum(c["received"] for c in snap.values()) >= stats.total_packets:
                    break
                time.sleep(0.05)
            stop_rec.set()
            rec_thread.join()
        pipe.stop()
    snap = pipe.counters_snapshot()
    assert sorted(snap) == ["sim-0001", "sim-0002", "sim-0003"]
    assert stats.configs == 3 and stats.max_behind_ms < 1000
    for vid, c in snap.items():
        assert c["rejected"] == 0 and c["duplicate"] == 0 and c["lost_by_seq_gap"] == 0, c
        # at 25x real time the network may reorder a little; nearly all must be accepted
        assert c["accepted"] >= 0.98 * c["received"], (vid, c)
    assert sum(c["received"] for c in snap.values()) == stats.total_packets
    # the real MDSF produced slip estimates for every vehicle
    for vid in snap:
        rows = np.concatenate(sink.rows[vid])
        assert rows.dtype == ESTIMATE_DTYPE and rows.shape[0] > 100
        assert (np.diff(rows["stamp_ns"]) > 0).all()
        assert ((rows["flags"] & int(EstimateFlag.GNSS_OK)) != 0).mean() > 0.5
        assert np.nanmax(rows["vg_mps"]) > 2.0  # the drive reaches 4 m/s
    assert counted and counted[0] >= stats.total_packets + stats.configs

    # replay the recording into a fresh server at 50x
    sink2 = CapturingSink()
    with embedded_router() as (router, zs, endpoint):
        settings = Settings(zenoh=zs, ingest=IngestSettings.model_validate(settings_kw))
        pipe2 = Pipeline(settings, router, EstimatorRegistry(), [sink2])
        pipe2.start()
        with client_session(endpoint) as player:
            time.sleep(0.3)
            rstats = replay(rec_path, player, rate=50.0)
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline:
                if (
                    sum(c["received"] for c in pipe2.counters_snapshot().values())
                    >= rstats.total_packets
                ):
                    break
                time.sleep(0.05)
        pipe2.stop()
    assert rstats.total_packets == stats.total_packets
    snap2 = pipe2.counters_snapshot()
    assert sum(c["received"] for c in snap2.values()) == stats.total_packets
    assert all(np.concatenate(sink2.rows[v]).shape[0] > 100 for v in snap2)


@pytest.mark.zenoh
def test_fleet_over_several_sessions() -> None:
    with embedded_router() as (router, zs, endpoint):
        pipe = Pipeline(Settings(zenoh=zs), router, EstimatorRegistry({"mdsf": RecordingFleet}))
        pipe.start()
        with client_session(endpoint) as a, client_session(endpoint) as b:
            time.sleep(0.2)
            sim = FleetSim([a, b], 4, scenario="hard_braking", rate=50.0, seed=2, distinct_runs=2)
            stats = sim.run(duration_s=0.5)
            deadline = time.monotonic() + 10
            while time.monotonic() < deadline:
                got = sum(c["received"] for c in pipe.counters_snapshot().values())
                if got >= stats.total_packets:
                    break
                time.sleep(0.02)
        pipe.stop()
    snap = pipe.counters_snapshot()
    assert sorted(snap) == sim.vehicle_ids == ["sim-0001", "sim-0002", "sim-0003", "sim-0004"]
    assert sum(c["accepted"] for c in snap.values()) == stats.total_packets > 0


@pytest.mark.zenoh
def test_a_fleet_stopped_while_simulating_ends_quietly_when_its_session_closes(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The demo stops its fleets, waits a few seconds for each thread, then closes the session;
    a fleet still simulating then must end without touching the closed session."""
    raised: list[BaseException | None] = []
    monkeypatch.setattr(threading, "excepthook", lambda args: raised.append(args.exc_value))
    with embedded_router() as (_, _, endpoint), client_session(endpoint) as session:
        sim = FleetSim(session, 3, seed=5)
        sim.start()
        sim.stop(timeout_s=0.0)  # simulating the runs takes far longer than this
        session.close()
        assert sim._thread is not None
        sim._thread.join(120)
        assert not sim._thread.is_alive()
    assert raised == []
    assert sim.stats.total_packets == 0
