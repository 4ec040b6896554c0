"""Benchmark of the history endpoints: one vehicle-hour on SQLite, served over HTTP.

Run ``python -m server.tooling.bench.series [--rows 36000] [--repeats 9] [--json out.json]``.

A SQLite store in a temporary directory gets one vehicle with ``--rows`` estimates at 10 Hz (the
default is one hour). The app from :func:`server.api.create_app` runs in-process behind httpx's
ASGI transport (no sockets: this measures the store, decimation, statistics and encoding, not the
network). Each case is requested twice to warm up, then ``--repeats`` times; the table shows the
median, fastest and slowest wall time per request, the answer size, and for the two cases the
issue sets targets for (a series query < 100 ms — taken both as every field at
``max_points=2000`` and as the dashboard's history query — and a report < 200 ms) whether the
median meets it. ``store.query_series`` alone is timed as well, to show where the time goes.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import tempfile
import time
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from estimator.mdsf_spec import MDSF_SPEC
from estimator.types import EstimateFlag, empty_estimates
from server.analytics.reports import report_fields
from server.api import NoVehicleEvents, create_app
from server.metrics.prometheus import MetricFamily
from server.settings import ApiSettings, Settings, StorageSettings
from server.storage import Store, open_store

__all__ = ["main", "run", "vehicle_hour"]

_S = 1_000_000_000
_T0 = 1_714_564_800 * _S  # 2024-05-01T12:00:00Z
_VEHICLE = "bench-1"
_TARGETS_MS = {
    "series json max_points=2000": 100.0,
    "series json dashboard (10 fields, 4000)": 100.0,
    "report": 200.0,
}
#: What the dashboard's history view asks for (web/js/history.js).
_DASHBOARD_FIELDS = (
    "slip_left_pct",
    "slip_right_pct",
    "vg_mps",
    "vl_mps",
    "vr_mps",
    "rim_left_mps",
    "rim_right_mps",
    "east_m",
    "north_m",
    "flags",
)


def vehicle_hour(rows: int = 36_000, rate_hz: float = 10.0, t0_ns: int = _T0) -> np.ndarray:
    """Deterministic estimates of one working vehicle: ``rows`` at ``rate_hz`` from ``t0_ns``.

    Speed 0–4 m/s with stops, slip wandering 0–25 % with spikes, a GNSS outage every 10 minutes,
    every float field filled (NaN slip at standstill), so encoding costs are realistic.
    """
    rng = np.random.default_rng(7)
    out = empty_estimates(rows)
    step_ns = round(_S / rate_hz)
    t_s = np.arange(rows) / rate_hz
    out["stamp_ns"] = t0_ns + np.arange(rows, dtype=np.int64) * step_ns
    vg = np.clip(2.5 + 1.5 * np.sin(t_s / 90.0), 0.0, None)
    vg[(t_s % 600.0) < 30.0] = 0.0  # a stop every 10 min
    slip_l = 8.0 + 6.0 * np.sin(t_s / 37.0) + rng.normal(0, 1.5, rows)
    slip_r = 7.0 + 5.0 * np.sin(t_s / 41.0) + rng.normal(0, 1.5, rows)
    slip_l[rng.integers(0, rows, rows // 500)] += 30.0
    moving = vg >= 0.2
    for name in out.dtype.names or ():
        if out.dtype[name].kind == "f":
            out[name] = rng.normal(0.0, 1.0, rows)
    out["vg_mps"] = vg
    out["vl_mps"] = vg * (1 + slip_l / 100)
    out["vr_mps"] = vg * (1 + slip_r / 100)
    out["slip_left_pct"] = np.where(moving, slip_l, np.nan)
    out["slip_right_pct"] = np.where(moving, slip_r, np.nan)
    degraded = (t_s % 600.0) > 580.0
    flags = np.where(degraded, int(EstimateFlag.DEGRADED), int(EstimateFlag.GNSS_OK)) | np.where(
        moving,
        int(EstimateFlag.SLIP_LEFT_VALID | EstimateFlag.SLIP_RIGHT_VALID),
        int(EstimateFlag.STANDSTILL),
    )
    out["flags"] = flags
    return out


class _BenchRuntime:
    """Just a store: what the API needs to serve history (no Zenoh, no estimators)."""

    def __init__(self, settings: Settings) -> None:
        self._settings = settings
        self._store: Store | None = None
        self.writer = None  # reads only: the API writes nothing here
        self.vehicle_events = NoVehicleEvents()
        self.live_hub = None  # history only: no live views, no alerts
        self.alert_engine = None

    @property
    def store(self) -> Store:
        assert self._store is not None
        return self._store

    def viewer_port(self) -> int | None:
        return None  # no 3D view

    def open(self) -> None:
        self._store = open_store(self._settings.storage)

    def close(self) -> None:
        if self._store is not None:
            self._store.close()

    def health(self) -> Mapping[str, bool]:
        return {"storage": self.store.ping()}

    def metrics(self, by_vehicle: bool = True) -> Iterable[MetricFamily]:
        return ()


def _stats_ms(samples_s: Sequence[float]) -> dict[str, float]:
    ms = [s * 1000.0 for s in samples_s]
    return {"median_ms": statistics.median(ms), "min_ms": min(ms), "max_ms": max(ms)}


async def _time_requests(
    client: httpx.AsyncClient, cases: Mapping[str, str], repeats: int
) -> dict[str, dict[str, Any]]:
    results: dict[str, dict[str, Any]] = {}
    for name, url in cases.items():
        for _ in range(2):  # warm-up: page cache, statement cache, imports
            r = await client.get(url)
            r.raise_for_status()
        times = []
        size = 0
        for _ in range(repeats):
            t = time.perf_counter()
            r = await client.get(url)
            times.append(time.perf_counter() - t)
            r.raise_for_status()
            size = len(r.content)
        results[name] = {"url": url, "bytes": size, **_stats_ms(times)}
    return results


def _cases(start: int, end: int) -> dict[str, str]:
    """The HTTP cases timed, by name: series in each format and width, and the report."""
    q = f"start={start}&end={end}"
    base = f"/api/v1/vehicles/{_VEHICLE}"
    return {
        "series json max_points=2000": f"{base}/series?{q}&max_points=2000",
        "series json max_points=2000, 4 fields": f"{base}/series?{q}&max_points=2000"
        "&fields=vg_mps,slip_left_pct,slip_right_pct,flags",
        "series json dashboard (10 fields, 4000)": f"{base}/series?{q}&max_points=4000"
        f"&fields={','.join(_DASHBOARD_FIELDS)}",
        "series json full rate": f"{base}/series?{q}",
        "series json full rate, 4 fields": f"{base}/series?{q}"
        "&fields=vg_mps,slip_left_pct,slip_right_pct,flags",
        "series csv full rate": f"{base}/series?{q}&format=csv",
        "series parquet full rate": f"{base}/series?{q}&format=parquet",
        "report": f"{base}/report?{q}",
    }


def _seed_and_time_store(
    settings: Settings, data: np.ndarray, start: int, end: int, repeats: int
) -> dict[str, list[float]]:
    """Write ``data`` in the writer's batches, then time ``query_series`` (all fields, the
    report's fields) ``2 + repeats`` times; seconds per call by field set."""
    rows = data.shape[0]
    seed = open_store(settings.storage)
    try:
        seed.upsert_vehicle(_VEHICLE, {}, _T0)
        for i in range(0, rows, 5000):  # the writer's batch size
            seed.write_estimates([(_VEHICLE, data[i : i + 5000])])
        store_times: dict[str, list[float]] = {"all fields": [], "report fields": []}
        field_sets = (("all fields", None), ("report fields", report_fields(MDSF_SPEC)))
        for _ in range(2 + repeats):
            for label, fields in field_sets:
                t = time.perf_counter()
                got = seed.query_series(_VEHICLE, start, end, fields)
                store_times[label].append(time.perf_counter() - t)
                assert got.shape[0] == rows
    finally:
        seed.close()
    return store_times


def _time_http(settings: Settings, cases: dict[str, str], repeats: int) -> dict[str, Any]:
    """The cases through the app in process (ASGI transport, lifespan run)."""
    app = create_app(settings, _BenchRuntime(settings))

    async def serve() -> dict[str, dict[str, Any]]:
        async with app.router.lifespan_context(app):
            transport = httpx.ASGITransport(app=app)
            async with httpx.AsyncClient(
                transport=transport, base_url="http://bench", timeout=60
            ) as client:
                return await _time_requests(client, cases, repeats)

    return asyncio.run(serve())


def run(
    json_path: Path | str | None = None, *, rows: int = 36_000, repeats: int = 9
) -> dict[str, Any]:
    """Fill a SQLite store with ``rows`` estimates, time the HTTP cases, print a table.

    Returns ``{"rows": …, "cases": {name: {median_ms, min_ms, max_ms, bytes, url, target_ms?,
    meets_target?}}}`` and writes it to ``json_path`` when given.
    """
    data = vehicle_hour(rows)
    start, end = int(data["stamp_ns"][0]), int(data["stamp_ns"][-1]) + 1
    cases = _cases(start, end)
    with tempfile.TemporaryDirectory(prefix="slipfleet-bench-") as tmp:
        settings = Settings(
            storage=StorageSettings.model_validate({"data_dir": Path(tmp)}),
            api=ApiSettings.model_validate({"require_auth": False}),
        )
        store_times = _seed_and_time_store(settings, data, start, end, repeats)
        results = _time_http(settings, cases, repeats)

    for name, target in _TARGETS_MS.items():
        results[name]["target_ms"] = target
        results[name]["meets_target"] = results[name]["median_ms"] < target
    for label, times in store_times.items():
        results[f"store.query_series ({label})"] = {"bytes": 0, **_stats_ms(times[2:])}
    report = {"rows": rows, "repeats": repeats, "cases": results}
    _print_table(report)
    if json_path is not None:
        Path(json_path).write_text(json.dumps(report, indent=2) + "\n")
    return report


def _print_table(report: Mapping[str, Any]) -> None:
    print(f"{report['rows']} rows (10 Hz), SQLite, in-process ASGI; median of {report['repeats']}")
    print(f"{'case':<42}{'median ms':>10}{'min':>8}{'max':>8}{'bytes':>11}  target")
    for name, r in report["cases"].items():
        target = ""
        if "target_ms" in r:
            target = f"< {r['target_ms']:.0f} ms {'ok' if r['meets_target'] else 'MISSED'}"
        print(
            f"{name:<42}{r['median_ms']:>10.1f}{r['min_ms']:>8.1f}{r['max_ms']:>8.1f}"
            f"{r['bytes']:>11}  {target}"
        )


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--rows", type=int, default=36_000, help="estimates (10 Hz)")
    parser.add_argument("--repeats", type=int, default=9, help="timed requests per case")
    parser.add_argument("--json", type=Path, default=None, help="also write results here")
    args = parser.parse_args(argv)
    run(args.json, rows=args.rows, repeats=args.repeats)


if __name__ == "__main__":
    main()
