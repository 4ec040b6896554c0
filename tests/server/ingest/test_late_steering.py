"""A steered vehicle whose steering stream starts late, through the real pipeline (reorder
buffer, watermarks, the real friction estimator): its rows before the first steering angle
say why μ is not used (``NO_STEERING`` with ``NO_UPDATE`` and ``HELD``, no μ), read as
degraded in the live view, and the stream's absence is counted (``stalled_steering``); from
the first angle on μ is learnt and informed as usual. Likewise a steering stream that stops
mid-drive, from ``steer_timeout_s`` after its last angle until its next."""

from __future__ import annotations

import numpy as np

from estimator.friction import FrictionFleet
from estimator.friction.frontend import FrontEndConfig
from estimator.friction_spec import FRICTION_SPEC, FrictionFlag
from estimator.sim.four_wheel import FourWheelRun, simulate_four_wheel
from server.estimation import EstimatorRegistry
from server.ingest import Pipeline
from server.live.hub import quality
from server.protocol import Packet
from server.tooling.steered_fleet import steered_packets
from tests.estimator.friction.test_fleet import (
    TURN,
    front_columns_empty,
    late_steering,
    rear_columns_known,
    stalled_steering,
)
from tests.server.ingest.fakes import CapturingSink
from tests.server.ingest.test_pipeline import MS, T0, make


def _pipeline(clock: list[int]) -> tuple[Pipeline, CapturingSink]:
    """A pipeline (1 s lateness, a hand-moved clock) on the real friction estimator."""
    registry = EstimatorRegistry(factories={"friction": FrictionFleet})
    pipe, _, sink = make(
        lateness_ms=1_000, advance_step_ms=100, clock_ns=lambda: clock[0], registry=registry
    )
    return pipe, sink


def _rows(run: FourWheelRun) -> tuple[np.ndarray, Pipeline]:
    """``run``'s packets sent as the steered fleet sends them (arrival times and all), the
    friction rows stored for it, and the pipeline."""
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
    return np.concatenate(sink.by_estimator["friction"]["s1"]), pipe


def test_rows_before_the_first_steering_angle_say_why_mu_is_not_used() -> None:
    run, first_ns = late_steering(simulate_four_wheel([TURN], seeds=[11], start_ns=T0)[0])
    rows, pipe = _rows(run)
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


def test_rows_while_the_steering_stream_is_stalled_say_why_mu_is_not_used() -> None:
    """The stream stops 1.4 s into the turn for 0.8 s: from ``steer_timeout_s`` after its last
    angle the rows say why (``NO_STEERING``, no μ update, the front pair's columns NULL) and
    read as degraded, where the pipeline sees no stall; with the next angle μ is informed
    again."""
    run, last_ns, resumed_ns = stalled_steering(
        simulate_four_wheel([TURN], seeds=[11], start_ns=T0)[0]
    )
    rows, pipe = _rows(run)
    flags, t = rows["flags"], rows["stamp_ns"]
    stale = (t > last_ns + round(FrontEndConfig().steer_timeout_s * 1e9)) & (t < resumed_ns)
    assert stale.sum() > 20
    assert ((flags[stale] & FrictionFlag.NO_STEERING) > 0).all()
    assert ((flags[stale] & FrictionFlag.NO_UPDATE) > 0).all()
    assert all(quality(FRICTION_SPEC, int(f)) == "degraded" for f in flags[stale])
    assert front_columns_empty(rows[stale]).all() and rear_columns_known(rows).all()
    assert not (flags[~stale] & FrictionFlag.NO_STEERING).any()
    informed = (flags & FrictionFlag.INFORMED) > 0
    assert informed[t >= resumed_ns].sum() > 10
    assert np.abs(rows["mu"][informed] / 0.4 - 1).max() < 0.1
    # shorter than the reorder window (1 s): the pipeline does not count it, the rows say it
    assert pipe.counters_snapshot()["s1"].get("stalled_steering", 0) == 0
