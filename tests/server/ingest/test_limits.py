"""Byte limits of ingest: the per-vehicle token bucket and the undecoded-bytes budget."""

from __future__ import annotations

import threading
import time

from server.ingest.limits import MAX_RATE_VEHICLES, ByteBudget, ByteRate, refusal_errors
from server.protocol.keys import Stream


class _Clock:
    def __init__(self) -> None:
        self.ns = 0

    def __call__(self) -> int:
        return self.ns


def test_byte_rate_allows_the_burst_then_the_rate() -> None:
    clock = _Clock()
    rate = ByteRate(1000, 5000, clock_ns=clock)  # 1 kB/s, 5 kB bucket
    assert [rate.allow("a", 1000) for _ in range(6)] == [True] * 5 + [False]
    assert rate.allow("b", 5000)  # another vehicle has its own bucket
    clock.ns = 500_000_000  # 0.5 s: 500 bytes back
    assert not rate.allow("a", 600)
    assert rate.allow("a", 500)
    clock.ns = 100_000_000_000  # a long pause refills to the bucket, never beyond
    assert rate.allow("a", 5000) and not rate.allow("a", 1)


def test_byte_rate_forgets_the_oldest_half_of_its_buckets_when_full() -> None:
    """Random ids cannot grow memory: past MAX_RATE_VEHICLES buckets the oldest half goes,
    and a forgotten vehicle starts with a full bucket again."""
    clock = _Clock()
    rate = ByteRate(1000, 5000, clock_ns=clock)
    assert rate.allow("first", 5000) and not rate.allow("first", 1)  # emptied
    for i in range(MAX_RATE_VEHICLES - 1):
        rate.allow(f"v{i}", 1)
    assert not rate.allow("first", 1)  # still held: MAX_RATE_VEHICLES buckets in all
    assert rate.allow("one-more", 1)  # the oldest half, "first" among them, is forgotten
    assert rate.allow("first", 5000)
    last = f"v{MAX_RATE_VEHICLES - 2}"  # kept, with 4,999 bytes left
    assert rate.allow(last, 4999) and not rate.allow(last, 1)


def test_byte_rate_zero_is_no_limit() -> None:
    rate = ByteRate(0, 0)
    assert not rate.enabled
    assert all(rate.allow("a", 10**9) for _ in range(10))


def test_byte_budget_blocks_until_released() -> None:
    budget = ByteBudget(100)
    assert budget.acquire(60, 0.1)
    assert not budget.acquire(60, 0.05)  # would pass the budget
    got: list[bool] = []
    t = threading.Thread(target=lambda: got.append(budget.acquire(60, 5.0)))
    t.start()
    time.sleep(0.05)
    assert got == []
    budget.release(60)
    t.join(5)
    assert got == [True] and budget.held == 60 and budget.peak == 60


def test_byte_budget_lets_one_oversized_burst_through_when_empty() -> None:
    budget = ByteBudget(100)
    assert budget.acquire(500, 0.01)
    assert not budget.acquire(1, 0.01)
    budget.release(500)
    assert budget.held == 0 and budget.peak == 500


def test_refusals_name_vehicle_and_stream() -> None:
    errors = refusal_errors([("fleet/v-1/sensors/imu", "oversize"), ("junk", "over_rate")], "fleet")
    assert [(e.reason, e.vehicle_id, e.stream) for e in errors] == [
        ("oversize", "v-1", Stream.IMU),
        ("over_rate", None, None),
    ]
