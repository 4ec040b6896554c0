"""Faults of a vehicle's link, against a real server: a stall, and wheel packets lost.

* A link that stalls for longer than the reorder buffer's idle time (a cellular drop-out, a
  starved host) and then delivers everything at once must be taken as a late delivery, not as a
  vehicle that stopped: no packet late or lost, and the estimates of a link that never stalled
  (:func:`reference_rows`) — no row computes the wheels' speed from edges still on their way.
* Wheel packets lost on the link: counted lost, the estimators told (``wheel_gaps``), and no
  row reads the missing edges as a wheel that nearly stopped; the wheels' slip is unknown for
  a few ticks and then agrees with the reference again.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from server.ingest.reorder import IDLE_MIN_NS
from tests.server.faults._harness import Publisher, ServerProcess, reference_rows, wait_until

pytestmark = [pytest.mark.zenoh, pytest.mark.slow]

FIELDS = ("rim_left_mps", "rim_right_mps", "slip_left_pct", "slip_right_pct")
FAULT_AT_S = 12.0


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


def _run(tmp_path: Path, **fault: Any) -> tuple[Publisher, dict[str, Any], dict[str, Any]]:
    """Publish 4 vehicles for 24 s with ``fault`` (:class:`Publisher` fields) to a real server;
    returns the publisher, each vehicle's stored ingest counters and series."""
    server = ServerProcess(tmp_path)
    pub = Publisher(server.zenoh_listen, n_vehicles=4, duration_s=24.0, rate=1.0, **fault)
    start_ns, end_ns = pub.start_ns - 10**9, pub.start_ns + 60 * 10**9
    window = {"start": start_ns, "end": end_ns}
    server.start()
    try:
        server.wait_ready()
        pub.start()
        pub.wait_done(120)
        with server.client() as client:
            sent = dict.fromkeys(pub.vehicle_ids, 0)
            for key, _ in pub.sent_order:
                sent[key.split("/")[1]] += 1

            def ingest(vid: str) -> dict[str, Any]:
                r = client.get(f"/api/v1/vehicles/{vid}/report", params=window)
                return dict(r.json()["ingest"])

            wait_until(
                lambda: all(ingest(v)["received"] >= sent[v] for v in pub.vehicle_ids),
                30,
                "every packet counted",
            )
            time.sleep(2.0)  # the last rows committed
            counts = {vid: ingest(vid) for vid in pub.vehicle_ids}
            stored = {vid: _series(client, vid, start_ns, end_ns) for vid in pub.vehicle_ids}
    finally:
        server.stop()
    return pub, counts, stored


def _compare(
    got: dict[str, np.ndarray], want: np.ndarray, tolerances: dict[str, float], fault_ns: int
) -> None:
    """Stored rows against the reference: the rows around the fault are there, and where both
    have a value they differ by less than ``tolerances[field]``."""
    common, gi, wi = np.intersect1d(got["stamp_ns"], want["stamp_ns"], return_indices=True)
    near = want["stamp_ns"][np.abs(want["stamp_ns"] - fault_ns) < 3 * 10**9]
    assert np.isin(near, common).all(), "rows around the fault are missing"
    for f, tol in tolerances.items():
        both = np.isfinite(got[f][gi]) & np.isfinite(want[f][wi])
        err = np.abs(got[f][gi] - want[f][wi])
        worst = int(np.argmax(np.where(both, err, -1.0)))
        at_s = (common[worst] - fault_ns) / 1e9
        print(f"  {f}: largest difference {err[worst]:.3f} at {at_s:+.2f} s from the fault")
        assert err[worst] < tol, (f, err[worst], at_s)


def test_a_stalled_link_loses_nothing_and_computes_no_wheel_speed_early(tmp_path: Path) -> None:
    stall_s = 2.0
    assert stall_s * 1e9 > IDLE_MIN_NS  # longer than the idle time: the vehicle looks quiet
    pub, counts, stored = _run(tmp_path, stall_at_s=FAULT_AT_S, stall_s=stall_s)
    ref = reference_rows(pub)
    fault_ns = pub.start_ns + int(FAULT_AT_S * 1e9)
    for vid in pub.vehicle_ids:
        c = counts[vid]
        print(f"\n{vid}: {c}")
        assert c["late"] == 0 and c["lost"] == 0 and c["rejected"] == 0, c
        tolerances = dict.fromkeys(FIELDS[:2], 0.01) | dict.fromkeys(FIELDS[2:], 0.5)
        _compare(stored[vid], ref[vid], tolerances, fault_ns)


def test_lost_wheel_packets_give_no_false_slip(tmp_path: Path) -> None:
    pub, counts, stored = _run(tmp_path, drop_wheels_s=(FAULT_AT_S, FAULT_AT_S + 0.2))
    ref = reference_rows(pub)  # every packet: a link that lost nothing
    fault_ns = pub.start_ns + int(FAULT_AT_S * 1e9)
    dropped = dict.fromkeys(pub.vehicle_ids, 0)
    for key, _ in pub.dropped:
        dropped[key.split("/")[1]] += 1
    for vid in pub.vehicle_ids:
        c = counts[vid]
        print(f"\n{vid}: dropped {dropped[vid]}, {c}")
        assert dropped[vid] >= 1
        assert c["lost"] == dropped[vid] and c["late"] == 0, c
        assert c["other"]["wheel_gaps"] == 1, c
        got = stored[vid]
        # the reference's normal spread after a restarted fit (a few edges, tooth pattern not yet
        # learnt) is well under this; a gap read as a slow wheel is ~2 m/s and 70+ % off
        tolerances = dict.fromkeys(FIELDS[:2], 0.15) | dict.fromkeys(FIELDS[2:], 5.0)
        _compare(got, ref[vid], tolerances, fault_ns)
        near = np.abs(got["stamp_ns"] - fault_ns) < 2 * 10**9
        unknown = near & np.isnan(got["slip_left_pct"])
        assert 1 <= unknown.sum() <= 6, (vid, int(unknown.sum()))  # a few ticks, then back
