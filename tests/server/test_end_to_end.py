"""End to end: simulated vehicles publish over a real Zenoh session on loopback → the server
(embedded router, pipeline, MDSF) → SQLite or PostgreSQL → REST; the REST series must match the
simulator's truth within the estimator's accuracy, and every packet must be accounted for.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest

from estimator.sim import simulate, truth_at
from server.ingest.pipeline import PHASES
from server.tooling.fleet_commands import vehicle_session
from server.tooling.fleet_sim import TICK_NS, FleetSim
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
DURATION_S = 40.0  # upper bound of the run's length
RATE = 3.0  # publish three times faster than real time
N_VEHICLES = 2
SEED = 11
#: The issue's floor (slip RMS <= 1.0 pp) is measured by ``slipfleet bench accuracy``. Here the
#: drive goes through the whole wire path (codec, reorder buffer, pipeline, storage, REST), and
#: the second vehicle's sensor epochs sit 50 ms off the estimator's tick grid, which the bench
#: does not exercise: measured 0.79-0.85 pp for the first vehicle, 0.82-1.06 pp for the second.
#: The bound leaves room for that spread; an off-grid vehicle at the floor is an open estimator
#: item, not something this test should hide by shrinking the drive.
SLIP_RMS_BOUND_PP = 1.25


@pytest.fixture(params=BACKENDS)
def backend(request: pytest.FixtureRequest) -> Iterator[tuple[str | None, int]]:
    """``(storage URL or None for SQLite, ingest.workers)``."""
    yield from backend_of(request)


def _series(client: httpx.Client, vehicle_id: str, window: dict[str, int]) -> dict[str, np.ndarray]:
    fields = "vl_mps,vr_mps,slip_left_pct,slip_right_pct,omega_left_radps,flags"
    r = client.get(
        f"/api/v1/vehicles/{vehicle_id}/series",
        params={**window, "fields": fields, "format": "json"},
    )
    r.raise_for_status()
    body = r.json()
    cols = body["columns"]
    return {
        k: np.asarray(v, dtype=np.int64 if k in ("stamp_ns", "flags") else float)
        for k, v in cols.items()
    }


def test_simulated_fleet_reaches_rest_and_matches_truth(
    tmp_path: Path, backend: tuple[str | None, int]
) -> None:
    settings = stack_settings(tmp_path, *backend)
    with running_server(settings) as (_, server):
        t0 = time.time_ns()
        with vehicle_session(list(settings.zenoh.listen)) as session:
            sim = FleetSim(
                session,
                N_VEHICLES,
                scenario=SCENARIO,
                prefix=settings.zenoh.key_prefix,
                seed=SEED,
                rate=RATE,
                clock_ns=lambda: t0,
                **OVERRIDES,
            )
            stats = sim.run()
        base = t0  # the simulator anchors run start at its clock reading
        window = {"start": base - 10**9, "end": base + int((DURATION_S + 60) * 1e9)}
        with httpx.Client(base_url=f"http://127.0.0.1:{server.port}", timeout=30) as client:
            reports = wait_counted(client, N_VEHICLES, stats.total_packets, window)
            ids = sorted(reports)
            received = sum(rep["ingest"]["received"] for rep in reports.values())
            assert ids == sim.vehicle_ids
            assert received == stats.total_packets, "every published packet is counted once"
            for vid, rep in reports.items():
                p = rep["ingest"]
                accounted = p["accepted"] + p["late"] + p["duplicate"] + p["rejected"]
                assert accounted == p["received"], f"{vid}: counters do not add up: {p}"
                assert p["rejected"] == 0 and p["duplicate"] == 0 and p["lost"] == 0, p
                # A publisher stalled for longer than the reorder buffer's idle time (wall clock,
                # a loaded 2-core machine) lets the buffer release its tail; a packet arriving
                # after that is counted late. More than a handful would mean a real ordering bug.
                assert p["late"] <= 3, f"{vid}: {p['late']} late packets"

            metrics = client.get("/api/v1/metrics").text
            for vid in ids:  # the estimator's own counters reach /metrics
                line = next(
                    ln
                    for ln in metrics.splitlines()
                    if ln.startswith("slipfleet_estimator_events_total{")
                    and f'vehicle="{vid}"' in ln
                    and 'event="ticks"' in ln
                )
                assert float(line.rsplit(" ", 1)[1]) > 100, line
            # the pipeline threads' CPU is charged to them by name, in the process they run in
            pipeline_cpu = {
                ln.split('process="', 1)[1].split('"', 1)[0]: float(ln.rsplit(" ", 1)[1])
                for ln in metrics.splitlines()
                if ln.startswith("slipfleet_thread_cpu_seconds_total{")
                and 'thread="slipfleet-pipeline"' in ln
            }
            workers = settings.ingest.workers
            assert sorted(pipeline_cpu) == (
                [f"worker-{k}" for k in range(workers)] if workers else ["server"]
            ), pipeline_cpu
            assert all(seconds > 0.0 for seconds in pipeline_cpu.values()), pipeline_cpu
            # ... and split by phase (the workers' added up)
            phases = {
                ln.split('phase="', 1)[1].split('"', 1)[0]: float(ln.rsplit(" ", 1)[1])
                for ln in metrics.splitlines()
                if ln.startswith("slipfleet_pipeline_cpu_seconds_total{")
            }
            assert sorted(phases) == sorted(PHASES), phases
            assert phases["estimate"] > 0.0 and phases["decode"] > 0.0, phases
            for i, vid in enumerate(ids):
                phase = (i * TICK_NS) // N_VEHICLES
                truth = simulate(
                    SCENARIO, seed=SEED + i, start_ns=base, **FleetSim.spread_origin(i), **OVERRIDES
                ).truth
                truth_stamps = truth["stamp_ns"] + phase
                truth["stamp_ns"] = truth_stamps
                cols = _series(client, vid, window)
                stamp = cols["stamp_ns"]
                inside = (stamp >= truth_stamps[0]) & (stamp <= truth_stamps[-1])
                assert inside.sum() > 0.9 * (truth_stamps[-1] - truth_stamps[0]) / 1e9 * 5, (
                    "estimates cover the drive"
                )
                stamp = stamp[inside]
                vl_true = truth_at(truth, stamp, "vl_mps")
                moving = vl_true > 0.5
                assert moving.sum() > 50
                vl = cols["vl_mps"][inside]
                rel = np.abs(vl[moving] - vl_true[moving]) / np.mean(vl_true[moving])
                assert np.sqrt(np.mean(rel**2)) < 0.015, "wheel ground speed RMS error < 1.5 %"
                for side in ("left", "right"):
                    s_est = cols[f"slip_{side}_pct"][inside][moving]
                    s_true = truth_at(truth, stamp, f"slip_{side}_pct")[moving]
                    have = np.isfinite(s_est)
                    assert have.mean() >= 0.98, f"slip coverage {have.mean():.3f}"
                    rms = float(np.sqrt(np.mean((s_est[have] - s_true[have]) ** 2)))
                    assert rms <= SLIP_RMS_BOUND_PP, f"{vid} {side} slip RMS error {rms:.2f} pp"
