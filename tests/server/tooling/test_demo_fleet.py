"""The demo's tractors are worth comparing: each drives its own scenario, pace and soil, so
their stops, GNSS outages and slip differ and fall at different times (they once ran one
scenario in lock-step: the same stops and the same GNSS loss in the same second). The runs are
the ones the demo's :class:`FleetSim` simulates, built on a real Zenoh session."""

from __future__ import annotations

from itertools import combinations

import numpy as np
import pytest

from estimator.sim import SimRun
from server.tooling.fleet_commands import DEMO_PLANS, demo_plans
from server.tooling.fleet_sim import FleetSim, RunPlan, loop_period_ns
from tests.server.ingest.fakes import client_session, embedded_router

T0 = 1_763_700_000 * 10**9
LOOPED_S = 1800  # half an hour of the demo, each vehicle looping its own drive
STOP_MPS = 0.05


def _demo_runs(vehicles: int) -> list[SimRun]:
    with embedded_router() as (_router, _zs, endpoint), client_session(endpoint) as session:
        sim = FleetSim(session, vehicles, loop=True, plans=demo_plans(vehicles, "mix"))
        return sim.simulate_runs(T0)


def _looped(run: SimRun, field: str) -> np.ndarray:
    """``field`` of the run's truth, a sample a second over LOOPED_S s of looping."""
    period_s = loop_period_ns(run.start_ns, run.end_ns) / 1e9
    t_s = (run.truth["stamp_ns"] - run.start_ns) / 1e9
    at = np.arange(LOOPED_S) % period_s
    return np.asarray(run.truth[field])[np.searchsorted(t_s, at).clip(0, t_s.size - 1)]


@pytest.fixture(scope="module")
def runs() -> list[SimRun]:
    return _demo_runs(4)


def test_every_demo_vehicle_drives_its_own_scenario_and_loop(runs: list[SimRun]) -> None:
    assert len(runs) == 4
    assert len({r.name for r in runs}) >= 3
    periods = [loop_period_ns(r.start_ns, r.end_ns) for r in runs]
    assert len(set(periods)) == 4, periods
    # each starts at its own place (not on top of another)
    assert len({round(r.frame.lon0_deg, 6) for r in runs}) == 4


def test_demo_vehicles_stop_and_lose_gnss_at_different_times(runs: list[SimRun]) -> None:
    stopped = [_looped(r, "vg_mps") < STOP_MPS for r in runs]
    no_gnss = [~_looped(r, "gnss_valid").astype(bool) for r in runs]
    for a, b in combinations(range(len(runs)), 2):
        # standing in the same seconds: less than half of either one's stops
        both = np.sum(stopped[a] & stopped[b])
        assert both < 0.5 * min(stopped[a].sum(), stopped[b].sum()), (a, b, both)
        # and never the same GNSS loss in the same second for more than a few seconds
        assert np.sum(no_gnss[a] & no_gnss[b]) <= 5, (a, b)
    assert sum(int(g.any()) for g in no_gnss) >= 1  # the fleet does meet a GNSS outage


def test_demo_vehicles_see_different_slip(runs: list[SimRun]) -> None:
    moving = [r.truth["vg_mps"] > 0.5 for r in runs]
    p95 = [
        float(np.percentile(np.abs(r.truth["slip_left_pct"][m]), 95))
        for r, m in zip(runs, moving, strict=True)
    ]
    assert max(p95) - min(p95) > 2.0, p95


def test_more_vehicles_than_plans_get_their_own_seeds_up_to_the_cap() -> None:
    plans = demo_plans(10, "mix")
    assert len(plans) == 8 and plans[:4] == list(DEMO_PLANS) and plans[4:] == list(DEMO_PLANS)
    assert demo_plans(3, "gnss_outage") == [RunPlan("gnss_outage")] * 3
