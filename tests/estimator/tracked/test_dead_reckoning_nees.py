"""The dead-reckoned position's covariance against the simulator's truth over tens of short
GNSS outages: its NEES per degree of freedom averages about 1 where it is honest."""

from __future__ import annotations

from dataclasses import replace
from functools import cache

import numpy as np

from estimator.config import TrackedConfig
from estimator.sim.tracked import ORIGIN, START_NS, CrawlerSensors, TrackedRun
from estimator.sim.tracked.physics import integrate_route
from estimator.sim.tracked.route import named_route
from estimator.sim.tracked.sensors import draw_errors, emissions
from estimator.tracked import TrackedEstimatorConfig, TrackedFleet
from estimator.tracked_spec import TrackedFlag

SECOND = 1_000_000_000
#: Outages of 8 s every 20 s from 30 s: ~30 on a named route.
OUTAGE_S, EVERY_S, FIRST_S = 8.0, 20.0, 30.0


@cache
def _run(name: str, seed: int) -> TrackedRun:
    """The named route with short outages all along it instead of its long one."""
    base = named_route(name)
    starts = np.arange(FIRST_S, base.duration_s - EVERY_S, EVERY_S)
    route = replace(base, outages_s=tuple((float(a), OUTAGE_S) for a in starts))
    rng = np.random.default_rng(seed)
    config, sensors = TrackedConfig(), CrawlerSensors()
    truth = integrate_route(route, config, rng)
    errors = draw_errors(rng, truth.t_s.size, sensors)
    sent = emissions(truth, config, sensors, errors, ORIGIN, route.outages_s, START_NS, rng)
    return TrackedRun(name, seed, route, config, truth, errors, START_NS, ORIGIN, sent, sensors)


def _rows(run: TrackedRun) -> np.ndarray:
    fleet = TrackedFleet(TrackedEstimatorConfig())
    fleet.add_vehicle("v", run.config)
    fleet.set_anchor("v", run.frame.lat0_deg, run.frame.lon0_deg, run.frame.h0_m)
    out, i, ms = [], 0, run.measurements
    for t in range(run.start_ns + SECOND, ms[-1][0] + SECOND, SECOND):
        while i < len(ms) and ms[i][0] <= t:
            fleet.push("v", ms[i][1])
            i += 1
        out += [rows for _, rows in fleet.advance({"v": t})]
    return np.concatenate(out)


def _nees_at_outage_ends(run: TrackedRun) -> np.ndarray:
    """NEES per degree of freedom ``dᵀC⁻¹d/2`` of the last dead-reckoned row of each outage
    in which the crawler moved more than 5 m."""
    rows = _rows(run)
    dr = (rows["flags"] & int(TrackedFlag.DEAD_RECKONING)) != 0
    idx = run.index_at(rows["stamp_ns"])
    dist = run.distance_m()
    out = []
    for a_ns, b_ns in run.outages_ns:
        inside = np.flatnonzero(dr & (rows["stamp_ns"] >= a_ns) & (rows["stamp_ns"] < b_ns))
        if inside.size == 0 or dist[idx[inside[-1]]] - dist[idx[inside[0]]] < 5.0:
            continue
        r, k = rows[inside[-1]], idx[inside[-1]]
        d = np.array([r["east_m"] - run.truth.east_m[k], r["north_m"] - run.truth.north_m[k]])
        ee, nn, en = r["east_std_m"] ** 2, r["north_std_m"] ** 2, r["east_north_cov_m2"]
        C = np.array([[ee, en], [en, nn]])
        out.append(0.5 * float(d @ np.linalg.solve(C, d)))
    return np.array(out)


def test_the_dead_reckoned_positions_covariance_is_honest_over_short_outages() -> None:
    nees = np.concatenate([_nees_at_outage_ends(_run(n, 21)) for n in ("route_firm", "route_soft")])
    assert nees.size >= 40
    # mean of a χ²₂/2 is 1 (its 1-sigma over ~50 outages ~0.14, more as a run's draws correlate);
    # over-cautious below 0.5, over-confident above 2; its median 0.69
    assert 0.5 < float(np.mean(nees)) < 2.0
    assert 0.3 < float(np.median(nees)) < 1.4
