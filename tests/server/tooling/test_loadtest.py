"""Load test harness against real server processes: a small fleet with nothing lost, and two
shards that each see only their own vehicles while both APIs list the whole fleet."""

from __future__ import annotations

import math
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from server.metrics.latency import BOUNDS_S, LatencyHistogram, quantiles_from_buckets
from server.protocol import Stream, decode, sensor_key
from server.tooling.loadtest import (
    DRAIN_MAX_S,
    DRAIN_S,
    VEHICLES_PER_PUBLISHER,
    DrainWatch,
    LoadSpec,
    Target,
    _jobs,
    _Publisher,
    _wait_sending,
    assignments,
    format_report,
    local_server,
    publisher_count,
    run_loadtest,
    scrape,
    window_cores,
)

pytestmark = [pytest.mark.zenoh, pytest.mark.slow]


def test_quantiles_from_buckets_recover_known_latencies() -> None:
    hist = LatencyHistogram()
    latencies_ms = np.arange(1, 1001)  # 1 … 1000 ms, uniform
    hist.add((latencies_ms * 1_000_000).astype(np.int64))
    counts, _, max_ns = hist.snapshot()
    q = quantiles_from_buckets(list(BOUNDS_S), counts.tolist(), (0.5, 0.99))
    assert q[0.5] == pytest.approx(0.5, rel=0.05)  # buckets are 5 % wide
    assert q[0.99] == pytest.approx(0.99, rel=0.05)
    assert max_ns == 1_000_000_000


def test_one_publisher_process_per_1500_vehicles_unless_asked() -> None:
    def shares(spec: LoadSpec) -> list[int]:
        return [sum(g["count"] for g in groups) for groups in assignments(spec, ["sim-{:05d}"])]

    assert publisher_count(LoadSpec(vehicles=1000, duration_s=1)) == 1
    assert shares(LoadSpec(vehicles=1000, duration_s=1)) == [1000]
    assert publisher_count(LoadSpec(vehicles=VEHICLES_PER_PUBLISHER + 1, duration_s=1)) == 2
    assert shares(LoadSpec(vehicles=3000, duration_s=1)) == [1500, 1500]
    assert shares(LoadSpec(vehicles=1000, duration_s=1, publishers=4)) == [250] * 4
    assert shares(LoadSpec(vehicles=3, duration_s=1, publishers=8)) == [1, 1, 1]


def test_small_fleet_against_a_server_process_loses_nothing() -> None:
    # the window of the other runs here: latencies reported and ordered, not held to a bound
    spec = LoadSpec(vehicles=5, duration_s=3.0, warmup_s=1.0, publishers=1)
    with local_server() as server:
        target = Target((server.endpoint,), (server.api,), (server.pid,))
        r = run_loadtest(spec, target, progress=False)
    assert r["vehicles_seen"] == 5
    assert r["packets_sent"] > 5 * 3 * 20  # ≈30 packets per vehicle-second
    assert r["packets_received"] == r["packets_sent"]
    assert r["packets_lost_by_seq_gap"] == 0
    assert r["packets_missing"] == 0
    assert r["packets_rejected"] == 0
    assert r["loss_free"]
    assert r["estimates_stored"] > 0
    assert r["estimates_stored"] == r["estimates_produced"]
    assert r["estimates_not_inserted"] == 0
    for stage in ("live", "stored"):
        lat = r["latency"][stage]
        assert lat["rows"] > 0
        assert 0 < lat["p50_ms"] <= lat["p95_ms"] <= lat["p99_ms"] <= lat["max_ms"]
        assert math.isfinite(lat["max_ms"])
    # how late the load generator sent, over the window's packets only
    late = r["publisher_late_ms"]
    assert late["p50"] is not None and 0 <= late["p50"] <= late["p99"] <= late["max"]
    assert late["max"] <= r["publisher_max_behind_ms"] + 1  # the run's maximum covers it
    assert f"sent late by p50 {late['p50']} / p99 {late['p99']}" in format_report(r)
    assert r["server_cpu_cores"] > 0
    assert r["server_rss_mb_peak"] > 0
    before, after = r["machine_probe_s"]
    assert 0 < before < 60 and 0 < after < 60
    assert f"Python probe {before:.3f} s before" in format_report(r)
    # the server's pipeline thread decoded and estimated: it used CPU in the window, and no
    # thread used more than a whole core
    threads = r["server_thread_cores"]
    assert threads.get("server/slipfleet-pipeline", 0.0) > 0.0, threads
    assert all(0.0 < cores <= 1.05 for cores in threads.values()), threads
    assert list(threads.values()) == sorted(threads.values(), reverse=True)
    assert "threads  " in format_report(r)
    # ... and its phases are reported: estimator calls and decoding at least
    phases = r["pipeline_phase_cores"]
    assert phases.get("estimate", 0.0) > 0.0 and phases.get("decode", 0.0) > 0.0, phases
    assert sum(phases.values()) <= threads["server/slipfleet-pipeline"] + 0.05, (phases, threads)
    assert "pipeline estimate" in format_report(r) or "pipeline decode" in format_report(r)


def _server(received: int, written: int, produced: int, backlog: int = 0) -> dict[str, int]:
    return {
        "received": received,
        "rows_written": written,
        "rows_not_inserted": 0,
        "rows_dropped": 0,
        "estimate_rows": produced,
        "backlog": backlog,
    }


def test_the_drain_waits_while_a_server_that_fell_behind_catches_up() -> None:
    watch = DrainWatch(sent_total=1000, started_s=0.0)
    # far behind, but counting packets every second: no end short of the overall bound
    t_s = 0.0
    while t_s < DRAIN_MAX_S - 1:
        assert not watch.done(_server(int(t_s), 0, 10), t_s), t_s
        t_s += 1.0
    assert watch.done(_server(int(t_s) + 1, 0, 10), DRAIN_MAX_S + 0.5)


def test_the_drain_ends_when_settled_or_when_nothing_moves() -> None:
    settled = DrainWatch(sent_total=1000, started_s=0.0)
    assert not settled.done(_server(1000, 8, 10), 1.0)  # rows still on their way
    assert not settled.done(_server(1000, 10, 10), 2.0)  # settled; 1.5 s to go
    assert settled.done(_server(1000, 10, 10), 2.6)
    stuck = DrainWatch(sent_total=1000, started_s=0.0)
    assert not stuck.done(_server(990, 10, 10), 1.0)
    assert not stuck.done(_server(990, 10, 10), 1.0 + DRAIN_S)
    assert stuck.done(_server(990, 10, 10), 1.5 + DRAIN_S)  # 10 packets never came
    backlog = DrainWatch(sent_total=1000, started_s=0.0)
    assert not backlog.done(_server(1000, 10, 10, backlog=5), 1.0)
    assert not backlog.done(_server(1000, 10, 10, backlog=5), 3.0)


def test_a_stopped_publisher_keeps_its_sessions_open_until_closed() -> None:
    # what its sessions still queue for a server that fell behind must reach it during the
    # drain: the child stops sending, reports its counts and exits only when told to
    spec = LoadSpec(vehicles=2, duration_s=1.0, publishers=1, scenario="figure_eight")
    with local_server() as server:
        (job,) = _jobs(spec, Target((server.endpoint,), (server.api,)), "fleet")
        pub = _Publisher(0, job)
        try:
            _wait_sending([pub])
            pub.stop()
            pub.wait_final()
            assert pub.final is not None and pub.final["sent"] > 0
            time.sleep(1.0)
            assert pub.proc.poll() is None
        finally:
            pub.close()
            pub.join(30.0)
    assert pub.proc.returncode == 0


def test_window_cores_are_cpu_seconds_over_the_window_busiest_first() -> None:
    before = {"at_s": 100.0, "thread_cpu": {"server/writer": 5.0, "worker-0/pipeline": 10.0}}
    after = {
        "at_s": 110.0,
        "thread_cpu": {
            "server/writer": 7.0,  # 2 s of CPU in 10 s
            "worker-0/pipeline": 16.0,
            "server/AnyIO worker thread": 0.5,  # started in the window: from zero
            "server/idle": 0.0,
        },
    }
    assert window_cores(before, after) == {
        "worker-0/pipeline": 0.6,
        "server/writer": 0.2,
        "server/AnyIO worker thread": 0.05,
    }
    assert window_cores(after, before) == {}  # no window
    before["pipeline_cpu"] = {"decode": 1.0}
    after["pipeline_cpu"] = {"decode": 2.5, "estimate": 3.0}
    assert window_cores(before, after, "pipeline_cpu") == {"estimate": 0.3, "decode": 0.15}


def test_replayed_recordings_load_the_server_like_simulated_vehicles(tmp_path: Path) -> None:
    from server.tooling.fleet_commands import record

    path = tmp_path / "drive.rec"
    record(path, vehicles=2, scenario="figure_eight", duration_s=10.0)
    spec = LoadSpec(vehicles=4, duration_s=3.0, warmup_s=1.0, publishers=1, replay=(str(path),))
    with local_server() as server:
        target = Target((server.endpoint,), (server.api,), (server.pid,))
        r = run_loadtest(spec, target, progress=False)
    assert r["vehicles_seen"] == 4  # two recorded drives, each replayed by two renamed vehicles
    assert r["loss_free"]
    assert r["packets_received"] == r["packets_sent"] > 4 * 3 * 20
    assert r["latency"]["stored"]["rows"] > 0


@pytest.mark.postgres
def test_two_shards_split_the_fleet_and_both_apis_list_all_of_it(pg_database_url: str) -> None:
    from server.tooling.shards import shard_layout, sharded_servers

    filters, ids = shard_layout(2)
    spec = LoadSpec(vehicles=6, duration_s=3.0, warmup_s=1.0, publishers=1)
    with sharded_servers(pg_database_url, filters) as (router, servers):
        target = Target(
            (router.endpoint,), tuple(s.api for s in servers), tuple(s.pid for s in servers), ids
        )
        r = run_loadtest(spec, target, progress=False)
        assert r["loss_free"]
        assert r["packets_received"] == r["packets_sent"]
        seen = [scrape(s.api)["vehicles"] for s in servers]
        assert seen[0] == {"a-00001", "a-00002", "a-00003"}
        assert seen[1] == {"b-00001", "b-00002", "b-00003"}
        listed = []
        for s in servers:
            body = httpx.get(f"{s.api}/api/v1/vehicles", timeout=10).raise_for_status().json()
            listed.append({v["vehicle_id"] for v in body["data"]})
        assert listed[0] == listed[1] == seen[0] | seen[1]


def test_replay_keeps_the_recorded_wheel_heartbeats(tmp_path: Path) -> None:
    """A recorded drive that stands still holds heartbeats (wheels packets of no edges); the
    replay sends them again with their until_ns."""
    from server.tooling.fleet_commands import record
    from server.tooling.loadtest import _replay_fleet_sim_class

    path = tmp_path / "drive.rec"
    record(path, vehicles=1, scenario="hard_braking", duration_s=10.0)
    sim = _replay_fleet_sim_class()(
        None, 1, paths=[str(path)], id_format="r-{:03d}", prefix="fleet", first_index=1
    )
    ((packets, _, _),) = sim._drives()
    beats = [
        p
        for p in packets
        if p.stream is Stream.WHEELS and not any(len(m.stamp_ns) for m in p.measurements)
    ]
    assert beats and all(p.until_ns is not None for p in beats)
    decoded = decode(sensor_key("fleet", "r-001", Stream.WHEELS), beats[0].encode(0))
    assert decoded.measurements == () and decoded.until_ns == beats[0].until_ns


def test_shard_layout_gives_each_shard_its_own_prefix() -> None:
    from server.tooling.shards import MAX_SHARDS, shard_layout

    assert shard_layout(1) == (("*",), ("sim-{:05d}",))
    filters, ids = shard_layout(3)
    assert filters == ("a-$*", "b-$*", "c-$*")
    assert [f.format(7) for f in ids] == ["a-00007", "b-00007", "c-00007"]
    for bad in (0, MAX_SHARDS + 1):
        with pytest.raises(ValueError):
            shard_layout(bad)


@pytest.mark.postgres
def test_loadtest_command_starts_shards_sharing_one_database(
    pg_database_url: str, tmp_path: Path
) -> None:
    import argparse
    import json

    from server.tooling.loadtest import add_arguments, run_from_args

    p = argparse.ArgumentParser()
    add_arguments(p)
    out = tmp_path / "r.json"
    args = ["--vehicles", "4", "--duration", "3", "--warmup", "1", "--publishers", "1"]
    args += ["--shards", "2", "--storage-url", pg_database_url, "--json", str(out)]
    r = run_from_args(p.parse_args(args))
    assert r["vehicles_seen"] == 4 and r["loss_free"]
    assert r["server_settings"] == {"shards": 2}
    assert json.loads(out.read_text())["packets_received"] == r["packets_sent"] > 0
    with pytest.raises(SystemExit):
        run_from_args(p.parse_args(["--vehicles", "2", "--duration", "1", "--shards", "2"]))
