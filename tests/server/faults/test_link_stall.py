"""A link that stalls for longer than the reorder buffer's idle time, then delivers everything.

A cellular drop-out or a starved host holds a vehicle's packets back for seconds and then lets
them through at once. The server must take that as a late delivery, not as a vehicle that
stopped: no packet is counted late (or lost), and the estimates are those of a link that never
stalled (:func:`reference_rows`) — no row computes the wheels' speed from edges that had not
arrived yet.
"""

from __future__ import annotations

import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from server.ingest.reorder import IDLE_MIN_NS
from tests.server.faults._harness import Publisher, ServerProcess, reference_rows, wait_until

pytestmark = [pytest.mark.zenoh, pytest.mark.slow]

STALL_S = 2.0
FIELDS = ("rim_left_mps", "rim_right_mps", "slip_left_pct", "slip_right_pct")


def _series(client: httpx.Client, vid: str, start_ns: int, end_ns: int) -> dict[str, np.ndarray]:
    r = client.get(
        f"/api/v1/vehicles/{vid}/series",
        params={"start": start_ns, "end": end_ns, "fields": ",".join(FIELDS), "format": "json"},
    )
    r.raise_for_status()
    cols = r.json()["columns"]
    out = {"stamp_ns": np.asarray(cols["stamp_ns"], dtype=np.int64)}
    for f in FIELDS:
        out[f] = np.array([np.nan if v is None else v for v in cols[f]], dtype=float)
    return out


def test_a_stalled_link_loses_nothing_and_computes_no_wheel_speed_early(tmp_path: Path) -> None:
    assert STALL_S * 1e9 > IDLE_MIN_NS  # longer than the idle time: the vehicle looks quiet
    server = ServerProcess(tmp_path)
    pub = Publisher(
        server.zenoh_listen,
        n_vehicles=4,
        duration_s=24.0,
        rate=1.0,
        stall_at_s=12.0,
        stall_s=STALL_S,
    )
    ref = reference_rows(pub)
    start_ns, end_ns = pub.start_ns - 10**9, pub.start_ns + 60 * 10**9
    window = {"start": start_ns, "end": end_ns}
    server.start()
    try:
        server.wait_ready()
        pub.start()
        pub.wait_done(120)
        with server.client() as client:
            sent = {vid: 0 for vid in pub.vehicle_ids}
            for key, _ in pub.sent_order:
                sent[key.split("/")[1]] += 1

            def all_counted() -> bool:
                for vid in pub.vehicle_ids:
                    c = client.get(f"/api/v1/vehicles/{vid}/report", params=window).json()
                    if c["ingest"]["received"] < sent[vid]:
                        return False
                return True

            wait_until(all_counted, 30, "every packet counted")
            time.sleep(2.0)  # the last rows committed
            ingest = {
                vid: client.get(f"/api/v1/vehicles/{vid}/report", params=window).json()["ingest"]
                for vid in pub.vehicle_ids
            }
            stored = {vid: _series(client, vid, start_ns, end_ns) for vid in pub.vehicle_ids}
    finally:
        server.stop()

    stall_ns = pub.start_ns + int(12.0 * 1e9)
    for vid in pub.vehicle_ids:
        c = ingest[vid]
        print(f"\n{vid}: {c}")
        assert c["late"] == 0 and c["lost"] == 0 and c["rejected"] == 0, c
        got, want = stored[vid], ref[vid]
        common, gi, wi = np.intersect1d(got["stamp_ns"], want["stamp_ns"], return_indices=True)
        # every reference row around the stall is stored
        near = want["stamp_ns"][np.abs(want["stamp_ns"] - stall_ns) < 3 * 10**9]
        assert np.isin(near, common).all(), "rows around the stall are missing"
        for f, tol in (("rim_left_mps", 0.01), ("rim_right_mps", 0.01)):
            err = np.abs(got[f][gi] - want[f][wi])
            worst = int(np.nanargmax(err))
            at_s = (common[worst] - stall_ns) / 1e9
            print(f"  {f}: largest difference {err[worst]:.3f} at {at_s:+.2f} s from the stall")
            assert err[worst] < tol, (f, err[worst], at_s)
        for f, tol in (("slip_left_pct", 0.5), ("slip_right_pct", 0.5)):
            both = np.isfinite(got[f][gi]) & np.isfinite(want[f][wi])
            err = np.abs(got[f][gi][both] - want[f][wi][both])
            assert err.max() < tol, (f, float(err.max()))
