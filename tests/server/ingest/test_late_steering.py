"""A steered vehicle whose steering stream starts late, through the real pipeline (reorder
buffer, watermarks, the real friction estimator): its rows before the first steering angle
say why μ is not used (``NO_STEERING`` with ``NO_UPDATE`` and ``HELD``, no μ), read as
degraded in the live view, and the stream's absence is counted (``stalled_steering``); from
the first angle on μ is learnt and informed as usual."""

from __future__ import annotations

import numpy as np

from estimator.friction import FrictionFleet
from estimator.friction_spec import FRICTION_SPEC, FrictionFlag
from estimator.sim.four_wheel import simulate_four_wheel
from server.estimation import EstimatorRegistry
from server.ingest import Pipeline
from server.live.hub import quality
from server.protocol import Packet
from server.tooling.steered_fleet import steered_packets
from tests.estimator.friction.test_fleet import TURN, late_steering
from tests.server.ingest.fakes import CapturingSink
from tests.server.ingest.test_pipeline import MS, T0, make


def _pipeline(clock: list[int]) -> tuple[Pipeline, CapturingSink]:
    """A pipeline (1 s lateness, a hand-moved clock) on the real friction estimator."""
    registry = EstimatorRegistry(factories={"friction": FrictionFleet})
    pipe, _, sink = make(
        lateness_ms=1_000, advance_step_ms=100, clock_ns=lambda: clock[0], registry=registry
    )
    return pipe, sink


def test_rows_before_the_first_steering_angle_say_why_mu_is_not_used() -> None:
    run, first_ns = late_steering(simulate_four_wheel([TURN], seeds=[11], start_ns=T0)[0])
    clock = [10**12]
    pipe, sink = _pipeline(clock)
    pipe.register_vehicle("s1", run.config)
    pipe._apply_control()
    seq: dict[object, int] = {}
    for p in steered_packets(run.measurements, run.start_ns):
        (m,) = p.measurements
        stamps = np.atleast_1d(m.stamp_ns)
        k = seq[p.stream] = seq.get(p.stream, -1) + 1
        packet = Packet("s1", p.stream, k, 1, (m,), int(stamps[0]), int(stamps[-1]), None)
        clock[0] = 10**12 + p.arrival_offset_ns
        pipe._handle([packet], clock[0])
        pipe._tick(clock[0], flush=False)
    pipe._tick(clock[0] + 5_000 * MS, flush=True)
    rows = np.concatenate(sink.by_estimator["friction"]["s1"])
    flags = rows["flags"]
    before = rows["stamp_ns"] < first_ns
    assert before.sum() > 200 and (~before).sum() > 50
    unused = int(FrictionFlag.NO_UPDATE | FrictionFlag.HELD)
    assert ((flags[before] & unused) == unused).all()
    assert ((flags[before] & FrictionFlag.NO_STEERING) > 0).all()
    assert np.isnan(rows["mu"][before]).all() and np.isnan(rows["mu_std"][before]).all()
    assert all(quality(FRICTION_SPEC, int(f)) == "degraded" for f in flags[before])
    assert "NO_STEERING" in FRICTION_SPEC.flag_names(int(flags[0]))
    assert not (flags[~before] & FrictionFlag.NO_STEERING).any()
    informed = (flags & FrictionFlag.INFORMED) > 0
    assert informed[~before].sum() > 25
    assert np.abs(rows["mu"][informed] / 0.4 - 1).max() < 0.1
    assert pipe.counters_snapshot()["s1"].get("stalled_steering") == 1
