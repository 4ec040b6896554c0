"""End to end, a mixed fleet: MDSF-only vehicles and one running MDSF + reference_speed publish
over real Zenoh → the server (embedded router, pipeline or 2 worker processes) → SQLite or
PostgreSQL → REST. Every row of every estimator is stored once, served in every format, and the
second estimator changes nothing in the first's rows.

The fleet: ``sim-0001`` (MDSF only) and ``sim-0002`` (MDSF + reference_speed) drive the same
simulated run (same seed, same time phase, same stamps); ``sim-0003`` (MDSF only) another run,
50 ms off their tick grid.
"""

from __future__ import annotations

import csv
import io
import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pyarrow.parquet as pq
import pytest

from estimator.catalog import SPECS, spec_of
from estimator.sim import simulate
from server.tooling.estimator_mix import EstimatorMix
from server.tooling.fleet_commands import vehicle_session
from server.tooling.fleet_sim import TICK_NS, FleetSim, publish_fleets
from tests.server.fleet_stack import (
    BACKENDS,
    backend_of,
    running_server,
    stack_settings,
    wait_counted,
)

pytestmark = [pytest.mark.zenoh, pytest.mark.slow]

SCENARIO = "figure_eight"
OVERRIDES = {"laps": 1}  # one 27 s lap with start and stop
RATE = 3.0
SEED = 7
MIX = EstimatorMix(2, ("mdsf", "reference_speed"))  # sim-0002 runs both
RUNS = {  # vehicle -> (seed offset of its run, its time phase in ns)
    "sim-0001": (0, 0),
    "sim-0002": (0, 0),
    "sim-0003": (1, TICK_NS // 2),
}
ESTIMATORS = {"sim-0001": ["mdsf"], "sim-0002": ["mdsf", "reference_speed"], "sim-0003": ["mdsf"]}


@pytest.fixture(params=BACKENDS)
def backend(request: pytest.FixtureRequest) -> Iterator[tuple[str | None, int]]:
    """``(storage URL or None for SQLite, ingest.workers)``."""
    yield from backend_of(request)


def _publish(endpoints: list[str], prefix: str, t0: int) -> int:
    """Publish the fleet (two fleets on one schedule: each one's first vehicle has phase 0);
    the packets sent."""
    common: dict[str, Any] = {
        "scenario": SCENARIO,
        "prefix": prefix,
        "seed": SEED,
        "rate": RATE,
        "clock_ns": lambda: t0,
        "estimator_mix": MIX,
        **OVERRIDES,
    }
    with vehicle_session(endpoints) as session:
        fleets = [FleetSim(session, 1, **common), FleetSim(session, 2, first_index=2, **common)]
        assert [f.vehicle_ids for f in fleets] == [["sim-0001"], ["sim-0002", "sim-0003"]]
        return publish_fleets(fleets).total_packets


def _metric(text: str, name: str) -> float:
    """The value of an unlabelled sample of ``/api/v1/metrics``."""
    line = next(ln for ln in text.splitlines() if ln.startswith(f"{name} "))
    return float(line.rsplit(" ", 1)[1])


def _ticks_counted(text: str) -> dict[tuple[str, str], int]:
    """``(vehicle, estimator) -> ticks`` of the estimators' own counters in ``/metrics``."""
    out = {}
    for ln in text.splitlines():
        if ln.startswith("slipfleet_estimator_events_total{") and 'event="ticks"' in ln:
            labels = dict(
                kv.split("=", 1) for kv in ln[ln.index("{") + 1 : ln.index("}")].split(",")
            )
            key = (labels["vehicle"].strip('"'), labels["estimator"].strip('"'))
            out[key] = int(float(ln.rsplit(" ", 1)[1]))
    return out


def _wait_stored(client: httpx.Client) -> float:
    """Wait until the writer inserted every row the pipeline produced and nothing more comes;
    that count (at most 120 s, for a loaded host)."""
    deadline = time.monotonic() + 120
    last, since = -1.0, time.monotonic()
    while True:
        text = client.get("/api/v1/metrics").text
        produced = _metric(text, "slipfleet_estimate_rows_total")
        written = _metric(text, "slipfleet_writer_rows_written_total")
        if produced != last:
            last, since = produced, time.monotonic()
        elif written == produced and time.monotonic() - since > 1.5:
            return produced
        assert time.monotonic() < deadline, f"{written} of {produced} rows written"
        time.sleep(0.3)


def _get(client: httpx.Client, vid: str, route: str, **params: Any) -> httpx.Response:
    r = client.get(f"/api/v1/vehicles/{vid}/{route}", params=params)
    assert r.status_code == 200, (vid, route, params, r.text)
    return r


def _parquet(client: httpx.Client, vid: str, estimator: str, window: dict[str, int]) -> dict:
    """Every stored row of ``estimator`` (Parquet: exact; null back to NaN)."""
    r = _get(client, vid, "series", estimator=estimator, format="parquet", **window)
    table = pq.read_table(io.BytesIO(r.content))
    return {name: table[name].to_numpy(zero_copy_only=False) for name in table.column_names}


def _check_formats(
    client: httpx.Client, vid: str, estimator: str, window: dict[str, int], rows: dict
) -> None:
    """JSON (9 significant digits, NaN as null) and CSV (exact, NaN as an empty cell) hold the
    Parquet answer's rows; GeoJSON places the rows that have a position, or is refused."""
    spec = spec_of(estimator)
    names = [f.name for f in spec.fields]
    # the exports add an ISO time after stamp_ns and the flags' names after flags
    at = names.index("flags")
    exported = ["stamp_ns", "time", *names[1 : at + 1], "flag_names", *names[at + 1 :]]
    assert list(rows) == exported
    body = _get(client, vid, "series", estimator=estimator, format="json", **window).json()
    assert body["estimator"] == estimator and body["rows"] == body["stored_rows"] == len(
        rows[names[0]]
    )
    text = _get(client, vid, "series", estimator=estimator, format="csv", **window).text
    reader = csv.reader(io.StringIO(text))
    assert next(reader) == exported
    csv_rows = list(reader)
    for name in names:
        j = exported.index(name)
        want = rows[name]
        in_json = np.array([np.nan if v is None else v for v in body["columns"][name]])
        in_csv = np.array([float(r[j]) if r[j] else np.nan for r in csv_rows])
        if want.dtype.kind == "f":
            np.testing.assert_allclose(in_json, want, rtol=1e-8, err_msg=name)
            np.testing.assert_array_equal(in_csv, want, err_msg=name)
        else:
            assert np.array_equal(in_json, want) and np.array_equal(in_csv, want), name
    geo = client.get(
        f"/api/v1/vehicles/{vid}/series",
        params={**window, "estimator": estimator, "format": "geojson"},
    )
    if spec.position is None:
        assert geo.status_code == 400 and geo.json()["error"] == "bad_request", geo.text
        assert f"estimator {estimator!r} gives no position" in geo.json()["reason"], geo.text
        return
    assert geo.status_code == 200, geo.text
    placed = np.isfinite(rows[spec.position.east_field]) & np.isfinite(
        rows[spec.position.north_field]
    )
    features = geo.json()["features"]
    assert len(features) == int(placed.sum()) > 100
    stamps = [f["properties"]["stamp_ns"] for f in features]
    assert stamps == rows["stamp_ns"][placed].tolist()


def _check_grid(stamps: np.ndarray, vid: str, t0: int) -> None:
    """One row per tick: strictly increasing on one step, from the drive's start to its end."""
    seed, phase = RUNS[vid]
    run = simulate(
        SCENARIO, seed=SEED + seed, start_ns=t0, **FleetSim.spread_origin(seed), **OVERRIDES
    )
    steps = np.unique(np.diff(stamps))
    assert steps.tolist() == [TICK_NS], f"{vid}: steps between rows {steps[:5]} ns"
    assert 0 <= stamps[0] - (run.start_ns + phase) <= 2 * TICK_NS
    assert 0 <= run.end_ns + phase - stamps[-1] <= 2 * TICK_NS


def test_mixed_fleet_every_estimators_rows_stored_once_and_served(
    tmp_path: Path, backend: tuple[str | None, int]
) -> None:
    settings = stack_settings(tmp_path, *backend)
    with running_server(settings) as (_, server):
        t0 = time.time_ns()
        packets = _publish(list(settings.zenoh.listen), settings.zenoh.key_prefix, t0)
        window = {"start": t0 - 10**9, "end": t0 + 120 * 10**9}
        with httpx.Client(base_url=f"http://127.0.0.1:{server.port}", timeout=30) as client:
            reports = wait_counted(client, len(RUNS), packets, window)
            produced = _wait_stored(client)
            listed = client.get("/api/v1/estimators").json()["data"]
            assert {s["name"] for s in listed} == set(SPECS) >= {"mdsf", "reference_speed"}
            for s in listed:
                assert s == json.loads(json.dumps(spec_of(s["name"]).to_dict()))
            vehicles = client.get("/api/v1/vehicles").json()["data"]
            assert {v["vehicle_id"]: v["estimators"] for v in vehicles} == ESTIMATORS
            assert sum(r["ingest"]["received"] for r in reports.values()) == packets

            stored: dict[tuple[str, str], dict] = {}
            for vid, names in ESTIMATORS.items():
                for estimator in names:
                    rows = stored[vid, estimator] = _parquet(client, vid, estimator, window)
                    _check_grid(rows["stamp_ns"], vid, t0)
                    _check_formats(client, vid, estimator, window, rows)
                    _check_report_and_latest(client, vid, estimator, window, rows)
            assert sum(len(r["stamp_ns"]) for r in stored.values()) == produced
            text = client.get("/api/v1/metrics").text
            ticks = _ticks_counted(text)  # estimators that count their ticks per vehicle
            assert ticks.keys() >= {(vid, "mdsf") for vid in ESTIMATORS}, sorted(ticks)
            for key, n in ticks.items():
                assert n == len(stored[key]["stamp_ns"]), key
            for dropped in ("ignored", "dropped_backlog_full", "dropped_error"):
                assert _metric(text, f"slipfleet_writer_rows_{dropped}_total") == 0, dropped

            # the second estimator changes nothing in the first's rows: same drive, same rows
            # (stamps and flags exactly, values to the 1e-9: the last bits of a float
            # differ between two vehicles estimated in batches of different sizes, and the
            # filters carry them on; measured up to 1.4e-12 pp in slip)
            alone, beside = stored["sim-0001", "mdsf"], stored["sim-0002", "mdsf"]
            for name, want in alone.items():
                if want.dtype.kind == "f":
                    np.testing.assert_allclose(
                        beside[name], want, rtol=1e-9, atol=1e-9, err_msg=name
                    )
                else:
                    np.testing.assert_array_equal(beside[name], want, err_msg=name)


def _check_report_and_latest(
    client: httpx.Client, vid: str, estimator: str, window: dict[str, int], rows: dict
) -> None:
    """The report and the latest row are of the estimator asked for, over the rows stored."""
    rep = _get(client, vid, "report", estimator=estimator, **window).json()
    assert rep["estimator"] == estimator
    assert rep["report"]["rows"] == len(rows["stamp_ns"])
    assert sorted(rep["report"]["slips"]) == sorted(c.key for c in spec_of(estimator).slips)
    latest = _get(client, vid, "latest", estimator=estimator).json()
    assert latest["estimator"] == estimator
    assert latest["stamp_ns"] == int(rows["stamp_ns"][-1])
