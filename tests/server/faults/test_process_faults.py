"""The server process killed (SIGKILL) and restarted, or stopped (SIGTERM), while vehicles stream.

Real processes: ``slipfleet serve`` (embedded router, SQLite in ``tmp_path``) and a vehicle
client publishing deterministic simulated runs. What the server stores is compared with
:func:`reference_rows`, the estimates of the same packets through a pipeline that never failed.
"""

from __future__ import annotations

import signal
import sqlite3
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from server.storage.migrations import latest_version
from tests.server.faults._harness import (
    ADVANCE_STEP_NS,
    LATENESS_NS,
    TICK_NS,
    Publisher,
    ServerProcess,
    reference_rows,
    series_positions,
    series_stamps,
    stamp_gaps,
    wait_until,
)

pytestmark = [pytest.mark.zenoh, pytest.mark.slow]

COMMIT_INTERVAL_S = 0.2
#: Time the server may take from receiving a packet to handing its rows to the writer
#: (decode, pipeline tick every 20 ms, queues) on a loaded 2-core machine.
PIPELINE_SLACK_S = 0.5


def _window(pub: Publisher) -> tuple[int, int]:
    return pub.start_ns - 10**9, pub.start_ns + int((pub.duration_s + 60) * 1e9)


def _ingest_counters(client: httpx.Client, pub: Publisher) -> dict[str, dict[str, int]]:
    """Each published vehicle's ingest counters over the drive (its report's)."""
    window = dict(zip(("start", "end"), _window(pub), strict=True))
    return {
        vid: client.get(f"/api/v1/vehicles/{vid}/report", params=window).json()["ingest"]
        for vid in pub.vehicle_ids
    }


def _stored(server: ServerProcess, pub: Publisher) -> dict[str, np.ndarray]:
    start, end = _window(pub)
    with server.client() as client:
        return {vid: series_stamps(client, vid, start, end) for vid in pub.vehicle_ids}


def _wait_for_tail(server: ServerProcess, pub: Publisher, ref: dict[str, np.ndarray]) -> None:
    """Until every vehicle's last reference row is stored (the idle release flushed the tail)."""

    def reached() -> bool:
        stored = _stored(server, pub)
        return all(
            s.size and int(s[-1]) >= int(ref[vid]["stamp_ns"][-1]) for vid, s in stored.items()
        )

    wait_until(reached, 60, "the last estimates to be stored", poll_s=0.5)


def _schema_versions(data_dir: Path) -> list[int]:
    with sqlite3.connect(data_dir / "slipfleet.sqlite") as db:
        return [int(v) for (v,) in db.execute("SELECT version FROM schema_version ORDER BY 1")]


def test_sigkill_then_restart_keeps_committed_estimates_once(tmp_path: Path) -> None:
    server = ServerProcess(tmp_path, commit_interval_s=COMMIT_INTERVAL_S)
    pub = Publisher(server.zenoh_listen, n_vehicles=2, duration_s=50.0, rate=2.0)
    ref = reference_rows(pub)
    for vid, rows in ref.items():
        assert stamp_gaps(rows["stamp_ns"]) == [], f"{vid}: the reference has no gaps"
    server.start()
    try:
        server.wait_ready()
        pub.start()
        time.sleep(9.0)
        t_kill = time.monotonic()
        server.signal(signal.SIGKILL)
        assert server.wait_exit(10) == -signal.SIGKILL
        newest_at_kill = pub.newest_at(t_kill)
        committed_at = pub.newest_at(t_kill - COMMIT_INTERVAL_S - PIPELINE_SLACK_S)
        time.sleep(1.0)
        t_restart = time.monotonic()
        server.start()
        ready_s = server.wait_ready()
        versions = _schema_versions(tmp_path / "data")
        assert versions == list(range(1, latest_version() + 1)), "each migration applied once"

        def resumed() -> bool:
            stored = _stored(server, pub)
            return all(s.size and int(s[-1]) > newest_at_kill[vid] for vid, s in stored.items())

        resume_s = wait_until(resumed, 60, "estimates after the restart", poll_s=0.2)
        pub.wait_done(120)
        _wait_for_tail(server, pub, ref)
        stored = _stored(server, pub)
        start, end = _window(pub)
        with server.client() as client:
            positions = {vid: series_positions(client, vid, start, end) for vid in pub.vehicle_ids}
            reports = _ingest_counters(client, pub)
    finally:
        server.stop()

    print(
        f"\nSIGKILL: restart to health 200 {ready_s:.2f} s; to first new estimate stored "
        f"{ready_s + resume_s:.2f} s after the restart began ({t_restart - t_kill:.1f} s down)"
    )
    for vid in pub.vehicle_ids:
        s, r = stored[vid], ref[vid]["stamp_ns"]
        assert (np.diff(s) > 0).all(), f"{vid}: a stamp is stored twice or out of order"
        gaps = stamp_gaps(s)
        assert len(gaps) == 1, f"{vid}: one gap (the kill window) expected, got {gaps}"
        before, after = gaps[0]
        must_have = committed_at[vid] - LATENESS_NS - ADVANCE_STEP_NS - TICK_NS
        pre = s[s <= before]
        assert np.array_equal(pre, r[r <= before]), f"{vid}: pre-kill rows differ from reference"
        assert before >= must_have, (
            f"{vid}: rows up to {(must_have - r[0]) / 1e9:.2f} s must survive the kill, stored "
            f"only up to {(before - r[0]) / 1e9:.2f} s"
        )
        assert int(s[-1]) == int(r[-1]), f"{vid}: estimation resumed and reached the end"
        # east/north after the restart are in the frame of the rows before it (the stored
        # anchor), where a server that never failed puts them, not in a frame anchored anew
        pos, ref_rows = positions[vid], ref[vid]
        later = np.isin(ref_rows["stamp_ns"], pos["stamp_ns"][pos["stamp_ns"] >= after])
        mine = np.isin(pos["stamp_ns"], ref_rows["stamp_ns"][later])
        assert mine.sum() > 50, f"{vid}: rows after the restart to compare"
        for axis in ("east_m", "north_m"):
            off = np.abs(pos[axis][mine] - ref_rows[axis][later])
            worst = float(np.nanmax(off))
            assert worst < 1.0, f"{vid}: {axis} after the restart off by {worst:.1f} m"
        rep = reports[vid]
        # counters are totals over the vehicle's life: what was flushed before the kill stays
        sent_before = sum(
            1
            for (t, _), (key, _) in zip(pub.timeline, pub.sent_order, strict=True)
            if key.split("/")[1] == vid and t < t_kill - 1.5  # counter flush 1 s + commit
        )
        sent_all = sum(1 for key, _ in pub.sent_order if key.split("/")[1] == vid)
        assert rep["received"] >= sent_before, f"{vid}: counters restarted from zero: {rep}"
        assert rep["received"] <= sent_all, rep
        print(
            f"  {vid}: newest published at kill {(newest_at_kill[vid] - r[0]) / 1e9:.2f} s, "
            f"stored up to {(before - r[0]) / 1e9:.2f} s (lost tail "
            f"{(newest_at_kill[vid] - before) / 1e9:.2f} s of sensor time), gap "
            f"{(after - before) / 1e9:.2f} s, rows before/after {pre.size}/{s.size - pre.size} "
            f"of {r.size}; ingest after restart {rep}"
        )


def test_sigterm_flushes_every_estimate(tmp_path: Path) -> None:
    server = ServerProcess(tmp_path, commit_interval_s=COMMIT_INTERVAL_S)
    pub = Publisher(server.zenoh_listen, n_vehicles=2, duration_s=25.0, rate=3.0)
    ref = reference_rows(pub)
    server.start()
    try:
        server.wait_ready()
        pub.start()
        pub.wait_done(120)
        t_term = time.monotonic()
        server.signal(signal.SIGTERM)  # at once: the reorder buffers still hold the tail
        rc = server.wait_exit(60)
        stop_s = time.monotonic() - t_term
        # uvicorn shuts down gracefully, then re-raises the signal: the exit status says SIGTERM
        assert rc in (0, -signal.SIGTERM), server.log_tail()
        assert "runtime closed" in server.log_tail(), server.log_tail()
        server.start()  # read what was stored
        server.wait_ready()
        stored = _stored(server, pub)
        with server.client() as client:
            counters = _ingest_counters(client, pub)
    finally:
        server.stop()
    published = len(pub.sent_order)
    received = sum(c["received"] for c in counters.values())
    print(
        f"\nSIGTERM: stopped in {stop_s:.2f} s; packets published {published}, counted "
        f"{received}; rows stored {sum(s.size for s in stored.values())} of "
        f"{sum(r.size for r in ref.values())}"
    )
    assert received == published, "every packet sent before SIGTERM was counted"
    for vid in pub.vehicle_ids:
        assert np.array_equal(stored[vid], ref[vid]["stamp_ns"]), f"{vid}: rows lost on SIGTERM"
