"""A standalone Zenoh router killed and restarted while the server and a vehicle are its clients.

Both clients must reconnect by themselves; packets published while the router was down are
lost on the wire and must show up as ``lost_by_seq_gap``; estimation resumes.
"""

from __future__ import annotations

import time
from pathlib import Path

import httpx
import pytest

from tests.server.faults._harness import (
    Publisher,
    RouterProcess,
    ServerProcess,
    wait_until,
)

pytestmark = [pytest.mark.zenoh, pytest.mark.slow]

DOWN_S = 2.0


def _ingest(client: httpx.Client, vids: list[str], window: dict[str, int]) -> dict[str, dict]:
    """Stored ingest counters per vehicle (all zero while the vehicle is not known yet)."""
    out: dict[str, dict] = {}
    for vid in vids:
        r = client.get(f"/api/v1/vehicles/{vid}/report", params=window)
        out[vid] = r.json()["ingest"] if r.status_code == 200 else {"received": 0}
    return out


def test_router_restart_clients_reconnect_and_gap_is_counted(tmp_path: Path) -> None:
    router = RouterProcess(tmp_path)
    router.start()
    server = ServerProcess(tmp_path, zenoh_connect=router.endpoint)
    pub = Publisher(router.endpoint, n_vehicles=2, duration_s=40.0, rate=2.0)
    window = {"start": pub.start_ns - 10**9, "end": pub.start_ns + int(100 * 1e9)}
    server.start()
    try:
        server.wait_ready()
        pub.start()
        with server.client() as client:
            wait_until(
                lambda: all(
                    v["received"] > 50 for v in _ingest(client, pub.vehicle_ids, window).values()
                ),
                30,
                "packets through the router",
            )
            time.sleep(3.0)
            t_kill = time.monotonic()
            router.kill()
            down_code, down_checks = 200, {}
            while time.monotonic() - t_kill < DOWN_S:
                r = client.get("/api/v1/health")
                if r.status_code == 503:
                    down_code, down_checks = 503, r.json()["checks"]
                time.sleep(0.2)
            assert down_code == 503 and down_checks["zenoh"] is False, "health: router away"
            router.start()
            t_up = time.monotonic()
            # counters reach the store once a second; the live report is the store's view
            before = {
                vid: c["received"] for vid, c in _ingest(client, pub.vehicle_ids, window).items()
            }
            time.sleep(1.5)
            before = {
                vid: c["received"] for vid, c in _ingest(client, pub.vehicle_ids, window).items()
            }

            def flowing() -> bool:
                now = _ingest(client, pub.vehicle_ids, window)
                return all(now[v]["received"] > before[v] + 5 for v in pub.vehicle_ids)

            flow_s = wait_until(flowing, 60, "packets after the router restart", poll_s=0.2)
            recovery_s = time.monotonic() - t_up
            pub.wait_done(120)
            time.sleep(3.0)  # idle release, counter flush, commit
            counts = _ingest(client, pub.vehicle_ids, window)
            health = client.get("/api/v1/health").status_code
    finally:
        server.stop()
        router.stop()

    published = {vid: 0 for vid in pub.vehicle_ids}
    during = {vid: 0 for vid in pub.vehicle_ids}
    for (t, _), (key, _) in zip(pub.timeline, pub.sent_order, strict=True):
        vid = key.split("/")[1]
        published[vid] += 1
        if t_kill <= t <= t_up + recovery_s:
            during[vid] += 1
    print(
        f"\nrouter restart: down {DOWN_S:.1f} s (killed at t=0, up at {t_up - t_kill:.2f} s); "
        f"packets flowing again {recovery_s:.2f} s after the router was up "
        f"(upper bound, polled; {flow_s:.2f} s after the first poll)"
    )
    wall_s = pub.timeline[-1][0] - pub.timeline[0][0]
    for vid in pub.vehicle_ids:
        c = counts[vid]
        lost_s = c["lost"] * wall_s / published[vid]
        print(
            f"  {vid}: the lost packets span ~{lost_s:.2f} s of publishing: clients were cut off "
            f"~{lost_s - (t_up - t_kill):.2f} s longer than the router was away"
        )
        print(
            f"  {vid}: published {published[vid]}, received {c['received']}, lost_by_seq_gap "
            f"{c['lost']} (published in the outage window {during[vid]}), late {c['late']}, "
            f"other {c['other']}"
        )
        assert c["received"] == c["accepted"] + c["late"] + c["duplicate"] + c["rejected"]
        assert c["lost"] > 0, "the packets published while the router was down are counted lost"
        assert c["received"] + c["lost"] == published[vid], "every packet received or counted lost"
    assert health == 200
