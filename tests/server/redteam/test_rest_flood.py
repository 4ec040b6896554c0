"""A viewer token flooding the heaviest endpoint (the fleet report) with 50 connections of a
real ``slipfleet serve`` (real pipeline, real SQLite): refused with 429 and ``Retry-After``
beyond its share, no 5xx, ``/health`` answering fast throughout, another token still served,
and the refusals counted in ``/metrics``."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from collections import Counter
from pathlib import Path

import httpx
import numpy as np
import pytest

from server.settings import StorageSettings
from server.storage import open_store
from server.tokens import Role, issue_token
from tests.server.api._data import T0, ramp_series
from tests.server.faults._harness import ServerProcess

VEHICLES = 500
ROWS = 1200  # 2 min at 10 Hz each
CONNECTIONS = 50
FLOOD_S = 8.0
REPORT = f"/api/v1/fleet/report?start={T0}&end={T0 + 3_600_000_000_000}"


def _seed(data_dir: Path) -> tuple[str, str]:
    """A fleet's stored rows and two viewer tokens (flood, other)."""
    store = open_store(StorageSettings(data_dir=data_dir))
    try:
        rows = ramp_series(ROWS)
        batch = []
        for i in range(VEHICLES):
            vid = f"v{i:04d}"
            store.upsert_vehicle(vid, {}, T0)
            batch.append((vid, rows))
        store.write_estimates(batch)
        flood, _ = issue_token(store, "flood", Role.VIEWER, time.time_ns())
        other, _ = issue_token(store, "other", Role.VIEWER, time.time_ns())
    finally:
        store.close()
    return flood, other


def _get(c: httpx.Client, token: str, out: Counter[int]) -> httpx.Response:
    """One report request, sent once more on a new connection if the server closed the reused
    one before answering: an idle keep-alive connection may be closed just as the next request
    goes out, and a client may retry an idempotent request then (RFC 9112 §9.3.1.1). Counted
    under status 0; a second close in a row fails the test."""
    headers = {"authorization": f"Bearer {token}"}
    try:
        return c.get(REPORT, headers=headers)
    except httpx.RemoteProtocolError:
        out[0] += 1
        return c.get(REPORT, headers=headers)


def _hammer(base: str, token: str, until: float, out: Counter[int], retry: list[str]) -> None:
    with httpx.Client(base_url=base, timeout=60) as c:
        while time.monotonic() < until:
            r = _get(c, token, out)
            out[r.status_code] += 1
            if r.status_code == 429:
                retry.append(r.headers.get("retry-after", ""))


#: ``/health`` every 50 ms for argv[2] seconds from a process of its own (a probe thread among
#: the flood's would measure its own interpreter lock); prints the latencies and statuses.
_PROBE = """
import json, sys, time, httpx
lat, codes = [], []
until = time.monotonic() + float(sys.argv[2])
with httpx.Client(base_url=sys.argv[1], timeout=30) as c:
    while time.monotonic() < until:
        t0 = time.perf_counter()
        try:
            codes.append(c.get("/api/v1/health", timeout=10).status_code)
        except httpx.HTTPError:
            codes.append(0)  # no answer within 10 s
        lat.append(time.perf_counter() - t0)
        time.sleep(0.05)
print(json.dumps({"latencies_s": lat, "codes": codes}))
"""


def _probe_health(base: str, seconds: float) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-c", _PROBE, base, str(seconds)], stdout=subprocess.PIPE, text=True
    )


@pytest.mark.zenoh
@pytest.mark.slow
def test_report_flood_is_refused_with_429_and_health_keeps_answering(tmp_path: Path) -> None:
    flood, other = _seed(tmp_path / "data")
    server = ServerProcess(tmp_path, extra_env={"SLIPFLEET_API__REQUIRE_AUTH": "true"})
    server.start()
    codes: Counter[int] = Counter()
    other_codes: Counter[int] = Counter()
    retry_after: list[str] = []
    try:
        server.wait_ready()
        idle = _probe_health(server.base_url, 3.0)  # the machine's own latency, no flood
        idle_s = json.loads(idle.communicate(timeout=60)[0])["latencies_s"]
        until = time.monotonic() + FLOOD_S
        probe = _probe_health(server.base_url, FLOOD_S)
        threads = [
            threading.Thread(
                target=_hammer, args=(server.base_url, flood, until, codes, retry_after)
            )
            for _ in range(CONNECTIONS)
        ]
        threads.append(
            threading.Thread(target=_hammer, args=(server.base_url, other, until, other_codes, []))
        )
        for t in threads:
            t.start()
        for t in threads:
            t.join(120)
        probed = json.loads(probe.communicate(timeout=120)[0])
        with server.client() as c:
            metrics = c.get("/api/v1/metrics", headers={"authorization": f"Bearer {other}"}).text
    finally:
        server.stop()
    latencies_s, health_codes = probed["latencies_s"], Counter(probed["codes"])
    p99_ms = float(np.percentile(latencies_s, 99)) * 1000
    idle_p99_ms = float(np.percentile(idle_s, 99)) * 1000
    print(
        f"flood {dict(codes)}, other {dict(other_codes)}, health p99 {p99_ms:.0f} ms "
        f"(idle {idle_p99_ms:.0f} ms)"
    )
    assert not [s for s in (*codes, *other_codes, *health_codes) if s >= 500]
    assert codes[429] > 0 and codes[200] > 0
    assert set(retry_after) == {"1"}
    assert other_codes[200] > 0
    assert health_codes == Counter({200: len(latencies_s)})
    # never starved (before the limits, /health went unanswered for minutes under this flood);
    # the latency itself is a measurement, printed above, not a pass mark: a loaded machine
    # adds its own
    assert max(latencies_s) < 5.0
    refused = sum(
        float(line.rsplit(" ", 1)[1])
        for line in metrics.splitlines()
        if line.startswith('slipfleet_api_requests_refused_total{route="fleet_report"')
    )
    assert refused == codes[429] + other_codes[429]
