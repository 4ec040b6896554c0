"""Stream helpers: completion time, arrival order, replay chunks and watermarks."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.sim import (
    completion_ns,
    first_ns,
    in_arrival_order,
    replay,
    replay_arrivals,
    simulate,
)
from estimator.types import GnssSample, ImuBatch, Wheel, WheelEdges

START_NS = 1_700_000_000_000_000_000


def _imu(stamps: list[int]) -> ImuBatch:
    n = len(stamps)
    return ImuBatch(np.array(stamps, dtype=np.int64), np.zeros((n, 3)), np.zeros((n, 3)))


def _gnss(stamp: int) -> GnssSample:
    return GnssSample(stamp, (0.0, 1.0, 0.0), 0.0, 0.0, 0.0, 52.0, 5.0, 10.0)


def test_completion_time_is_the_last_stamp() -> None:
    assert completion_ns(_gnss(5)) == 5
    assert completion_ns(_imu([1, 2, 3])) == 3
    assert completion_ns(WheelEdges(Wheel.LEFT, np.array([7, 9], dtype=np.int64))) == 9
    with pytest.raises(ValueError):
        completion_ns(_imu([]))


def test_replay_chunks_and_watermarks() -> None:
    ms = [_imu([0, 10]), _gnss(50), _imu([60, 90]), _imu([150, 190]), _gnss(420)]
    out = list(replay(ms, step_ns=100, hold_ns=30, end_ns=500))
    chunks = [[completion_ns(m) for m in c] for c, _ in out]
    untils = [u for _, u in out]
    assert chunks == [[10, 50, 90], [190], [], [], [420]]
    assert untils == [80, 180, 280, 380, 500]
    with pytest.raises(ValueError, match="sensor order"):
        list(replay([_gnss(5), _gnss(4)]))


def test_replay_watermark_never_passes_unpushed_samples() -> None:
    run = simulate("figure_eight", seed=1, start_ns=START_NS)
    pushed_until = -1
    for chunk, until in replay(run.measurements, end_ns=run.end_ns):
        for m in chunk:
            stamps = [m.stamp_ns] if isinstance(m, GnssSample) else list(m.stamp_ns)
            # nothing pushed now lies at or before a watermark already announced
            assert min(stamps) > pushed_until
        pushed_until = until
    assert pushed_until == run.end_ns


def test_arrival_order_follows_latency() -> None:
    run = simulate("figure_eight", seed=2, start_ns=START_NS, gnss_latency_ms=150.0)
    pairs = run.in_arrival_order()
    arrivals = [a for a, _ in pairs]
    assert arrivals == sorted(arrivals)
    assert len(pairs) == len(run.measurements)
    # a GNSS epoch arrives after IMU batches that complete later than its stamp
    first_gnss = next(i for i, (_, m) in enumerate(pairs) if isinstance(m, GnssSample))
    before = [m for _, m in pairs[:first_gnss] if isinstance(m, ImuBatch)]
    assert any(completion_ns(m) > pairs[first_gnss][1].stamp_ns for m in before)
    with pytest.raises(ValueError):
        list(in_arrival_order(run.measurements, run.arrival_ns[:-1]))


def test_replay_arrivals_mirrors_the_server_reorder_buffer() -> None:
    run = simulate("figure_eight", seed=3, start_ns=START_NS, gnss_latency_ms=60.0)
    seen: list[int] = []
    previous_until = None
    released_firsts: list[int] = []
    for chunk, until in replay_arrivals(
        run.measurements, run.arrival_ns, lateness_ns=150_000_000, end_ns=run.end_ns
    ):
        firsts = [first_ns(m) for m in chunk]
        assert firsts == sorted(firsts)
        if previous_until is not None:
            assert until > previous_until
            # nothing released now lies at or before a horizon already announced
            assert all(f > previous_until for f in firsts)
        released_firsts += firsts
        seen += [id(m) for m in chunk]
        previous_until = until
    assert previous_until == run.end_ns
    assert sorted(seen) == sorted(id(m) for m in run.measurements)
    assert released_firsts == sorted(released_firsts)


def test_replay_arrivals_refuses_data_later_than_the_window() -> None:
    run = simulate("figure_eight", seed=4, start_ns=START_NS, gnss_latency_ms=400.0)
    with pytest.raises(ValueError, match="after the horizon"):
        list(replay_arrivals(run.measurements, run.arrival_ns, lateness_ns=150_000_000))
    # a wide enough window takes it
    n = sum(
        len(c)
        for c, _ in replay_arrivals(run.measurements, run.arrival_ns, lateness_ns=500_000_000)
    )
    assert n == len(run.measurements)
