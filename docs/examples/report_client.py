"""A minimal Slipfleet report client: the field report of every vehicle, and one series as CSV.

It needs only ``httpx`` and talks to the REST API (``/api/v1``, OpenAPI at ``/docs``)::

    python docs/examples/report_client.py --url http://127.0.0.1:8000 --hours 1 \
        --csv-vehicle sim-0001 --csv-out sim-0001.csv

With access control on, pass a viewer token with ``--token`` or ``SLIPFLEET_TOKEN``.
The last line printed is a JSON summary (for scripts).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from typing import Any

import httpx


def fleet_report(client: httpx.Client, start_ns: int, end_ns: int) -> list[dict[str, Any]]:
    """``GET /api/v1/fleet/report``: one entry per registered vehicle."""
    r = client.get("/api/v1/fleet/report", params={"start": start_ns, "end": end_ns})
    r.raise_for_status()
    vehicles: list[dict[str, Any]] = r.json()["vehicles"]
    return vehicles


def save_series_csv(
    client: httpx.Client, vehicle_id: str, start_ns: int, end_ns: int, path: str
) -> int:
    """Stream ``GET /api/v1/vehicles/{id}/series?format=csv`` to ``path``; return data rows."""
    params = {
        "start": start_ns,
        "end": end_ns,
        "fields": "vg_mps,vl_mps,vr_mps,slip_left_pct,slip_right_pct,flags",
        "format": "csv",
    }
    lines = 0
    with client.stream("GET", f"/api/v1/vehicles/{vehicle_id}/series", params=params) as r:
        r.raise_for_status()
        with open(path, "wb") as fh:
            for chunk in r.iter_bytes():
                fh.write(chunk)
                lines += chunk.count(b"\n")
    return max(lines - 1, 0)  # minus the header


def _fmt(value: float | None, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--url", default="http://127.0.0.1:8000")
    p.add_argument("--hours", type=float, default=1.0, help="report over the last N hours")
    p.add_argument("--token", default=os.environ.get("SLIPFLEET_TOKEN"))
    p.add_argument("--csv-vehicle", default=None)
    p.add_argument("--csv-out", default="series.csv")
    args = p.parse_args(argv)

    end_ns = time.time_ns()
    start_ns = end_ns - int(args.hours * 3600e9)
    headers = {"Authorization": f"Bearer {args.token}"} if args.token else {}
    with httpx.Client(base_url=args.url, headers=headers, timeout=30) as client:
        vehicles = fleet_report(client, start_ns, end_ns)
        print(
            f"{'vehicle':<12} {'estimator':<16} {'dist m':>8} {'moving s':>9} "
            f"{'slip p95 %':>11}  mean slip % per channel"
        )
        for v in vehicles:
            rep = v["report"]
            slips = rep["slips"]  # one entry per slip channel of the estimator, by key
            p95 = max(
                (s["p95_pct"] for s in slips.values() if s["p95_pct"] is not None), default=None
            )
            means = " ".join(f"{key}={_fmt(s['mean_pct'], '.2f')}" for key, s in slips.items())
            print(
                f"{v['vehicle_id']:<12} {v['estimator']:<16} {_fmt(rep['distance_m'], '>8.1f')} "
                f"{_fmt(rep['moving_s'], '>9.1f')} {_fmt(p95, '>11.2f')}  {means}"
            )
        csv_rows = None
        if args.csv_vehicle:
            csv_rows = save_series_csv(client, args.csv_vehicle, start_ns, end_ns, args.csv_out)
            print(f"wrote {csv_rows} rows of {args.csv_vehicle} to {args.csv_out}")
    summary = {"vehicles": [v["vehicle_id"] for v in vehicles], "csv_rows": csv_rows}
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
