"""Rows an estimator holds back (the tracked estimator's fixed lag) survive a re-registration:
the real registry takes them before the new config starts the vehicle afresh."""

from __future__ import annotations

import dataclasses

import numpy as np

from estimator.base import held_rows
from estimator.sim.tracked import TrackedRun, simulate_tracked
from estimator.tracked import TrackedFleet
from estimator.types import EstimateBatch
from server.estimation import EstimatorRegistry

SECOND = 1_000_000_000


def _stamps(batches: list[EstimateBatch], name: str = "tracked") -> list[int]:
    return [int(t) for b in batches if b.estimator == name for t in b.rows["stamp_ns"]]


def _fed(seconds: int) -> tuple[TrackedRun, EstimatorRegistry, int]:
    """A real registry running a simulated crawler ``c``, fed its first ``seconds``."""
    run = simulate_tracked("route_firm", 3)
    reg = EstimatorRegistry()
    reg.add_vehicle("c", run.config)
    until = run.start_ns + seconds * SECOND
    for stamp, m in run.measurements:
        if stamp <= until:
            reg.push("c", m)
    return run, reg, until


def test_a_new_config_gives_the_rows_held_by_the_lag_with_the_next_advance() -> None:
    run, reg, until = _fed(20)
    before = _stamps(reg.advance({"c": until}))
    fleet = reg.estimator("tracked")
    assert isinstance(fleet, TrackedFleet)
    ticks = fleet.counters("c")["ticks"]
    assert 0 < ticks - len(before) <= fleet.config.lag_ticks  # the last ticks are held
    geometry = dataclasses.replace(
        run.config.geometry, track_gauge_m=run.config.geometry.track_gauge_m + 0.01
    )
    reg.add_vehicle("c", dataclasses.replace(run.config, geometry=geometry))  # a new config
    after = _stamps(reg.advance({"c": until}))
    got = before + after
    assert len(got) == ticks and np.all(np.diff(got) == fleet.config.tick_ns)
    assert _stamps(reg.advance({"c": until})) == []  # given once


def test_a_removed_vehicle_takes_its_held_rows_with_it() -> None:
    run, reg, until = _fed(5)
    reg.advance({"c": until})
    reg.add_vehicle("c", run.config)  # flushed, waiting for the next advance ...
    reg.remove_vehicle("c")  # ... and dropped with the vehicle
    assert reg.advance({}) == []
    fleet = reg.estimator("tracked")
    left = held_rows(fleet, "c")
    assert left is not None and left.size == 0
    assert held_rows(reg.estimator("mdsf"), "c") is None  # an estimator that holds nothing
