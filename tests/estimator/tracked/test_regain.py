"""A fix refused for ``gnss_regain_s``: the filter, not the fixes, is wrong. A crawler whose
position and heading jump while it stands (carried off, or a replayed drive starting over)
must start again from its next fix at speed, not read the turned course as a reversed speed."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest

from estimator.geo import EnuFrame
from estimator.sim.tracked import TrackedRun, simulate_route
from estimator.sim.tracked.route import FIRM, Route, Segment
from estimator.tracked import TrackedEstimatorConfig, TrackedFleet
from estimator.tracked.model import MotionState as M

START_NS = 1_700_000_000_000_000_000


def _turning_loop(seed: int) -> TrackedRun:
    """From rest: a straight at 6 m/s, a left arc, a short left pivot and rest again, ending
    some 50 m away and turned about half round (177-190° on seeds 0-3); no outage."""
    segments = (
        Segment(M.STOP, 4.0, 0.0),
        Segment(M.STRAIGHT, 12.0, 6.0),
        Segment(M.ARC, 7.0, 3.0, left=True),
        Segment(M.STRAIGHT, 2.0, 1.5),
        Segment(M.PIVOT, 1.0, 1.5, left=True),
        Segment(M.STOP, 5.0, 0.0),
    )
    route = Route("turning_loop", segments, FIRM, ())
    return simulate_route(route, seed, start_ns=START_NS, frame=EnuFrame(52.0, 5.6, 10.0))


def _shifted(m: Any, d_ns: int) -> Any:
    """Measurement ``m`` with every ``*stamp_ns`` field ``d_ns`` later."""
    names = [f.name for f in dataclasses.fields(m) if f.name.endswith("stamp_ns")]
    return dataclasses.replace(m, **{n: getattr(m, n) + d_ns for n in names})


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_a_jump_of_position_and_heading_at_rest_starts_the_filter_again(seed: int) -> None:
    # before the filter started again on a regain, seed 0 read the turned course as a
    # reversed speed (-5.5 m/s)
    run = _turning_loop(seed)
    period_ns = run.measurements[-1][0] - START_NS + 100_000_000
    fleet = TrackedFleet(TrackedEstimatorConfig())
    fleet.add_vehicle("v", run.config)
    rows = []
    for loop in range(2):  # the same drive again, from where it first started
        d = loop * period_ns
        for _key_ns, m in run.measurements:
            fleet.push("v", _shifted(m, d) if d else m)
        rows += [r for _, r in fleet.advance({"v": run.measurements[-1][0] + d})]
    out = np.concatenate(rows)
    second = out["stamp_ns"] >= START_NS + period_ns + 8_000_000_000  # moving again, settled
    truth = run.truth.speed_mps[run.index_at(out["stamp_ns"][second] - period_ns)]
    err = out["speed_mps"][second] - truth
    assert out["speed_mps"].min() > -0.5
    assert np.sqrt(np.mean(err**2)) < 0.3
