"""Ordering and replay of simulated measurements.

Two orders matter:

* **sensor order** — by the sensor time that completes a measurement (:func:`completion_ns`:
  a GNSS epoch's stamp, a batch's last stamp). :class:`estimator.base.FleetEstimator` wants each
  vehicle's measurements pushed in this order. :attr:`SimRun.measurements` is in it.
* **arrival order** — when the measurement reaches the server (sensor time plus latency, and a
  wheel packet only when its window closes). A live publisher sends in this order; the server's
  reorder buffer restores sensor order within its lateness window.

:func:`replay` plays a sensor-ordered list with a fixed watermark lag. :func:`replay_arrivals`
plays a run the way the server's pipeline does: measurements come in arrival order, wait in a
buffer keyed by their *first* sample time, and are released once the horizon (newest sample time
seen minus the lateness) has passed them; the estimator is advanced to that horizon.
"""

from __future__ import annotations

import heapq
import itertools
from collections.abc import Iterable, Iterator, Sequence

import numpy as np

from estimator.base import Measurement
from estimator.types import GnssSample, ImuBatch

__all__ = ["completion_ns", "first_ns", "in_arrival_order", "replay", "replay_arrivals"]


def completion_ns(measurement: Measurement) -> int:
    """Sensor time at which ``measurement`` is complete: its stamp, or its last sample's stamp."""
    if isinstance(measurement, GnssSample):
        return int(measurement.stamp_ns)
    stamps = measurement.stamp_ns
    if len(stamps) == 0:
        raise ValueError("an empty batch has no completion time")
    return int(stamps[-1])


def first_ns(measurement: Measurement) -> int:
    """Sensor time of the first sample of ``measurement`` (the server's reorder key)."""
    if isinstance(measurement, GnssSample):
        return int(measurement.stamp_ns)
    stamps = measurement.stamp_ns
    if len(stamps) == 0:
        raise ValueError("an empty batch has no first sample")
    return int(stamps[0])


def _stream_rank(measurement: Measurement) -> int:
    if isinstance(measurement, GnssSample):
        return 0
    return 1 if isinstance(measurement, ImuBatch) else 2


def in_arrival_order(
    measurements: Sequence[Measurement], arrival_ns: Sequence[int] | np.ndarray
) -> Iterator[tuple[int, Measurement]]:
    """Yield ``(arrival_ns, measurement)`` sorted by arrival (stable for equal arrivals)."""
    if len(measurements) != len(arrival_ns):
        raise ValueError("measurements and arrival_ns differ in length")
    order = np.argsort(np.asarray(arrival_ns, dtype=np.int64), kind="stable")
    for i in order:
        yield int(arrival_ns[i]), measurements[int(i)]


def replay(
    measurements: Iterable[Measurement],
    *,
    step_ns: int = 100_000_000,
    hold_ns: int = 100_000_000,
    end_ns: int | None = None,
) -> Iterator[tuple[list[Measurement], int]]:
    """Group sensor-ordered ``measurements`` into chunks with the time it is safe to advance to.

    Yields ``(chunk, until_ns)``: push ``chunk`` (in order), then advance the estimator to
    ``until_ns``. A chunk holds the measurements completing within one ``step_ns``; ``until_ns``
    trails the chunk's end by ``hold_ns`` (at least the longest batch span, so every sample at or
    before ``until_ns`` has been pushed). The last chunk advances to ``end_ns`` (default: the last
    completion time).
    """
    if step_ns <= 0 or hold_ns < 0:
        raise ValueError("step_ns must be > 0 and hold_ns >= 0")
    chunk: list[Measurement] = []
    boundary: int | None = None
    last = None
    for m in measurements:
        key = completion_ns(m)
        if last is not None and key < last:
            raise ValueError("measurements are not in sensor order")
        last = key
        if boundary is None:
            boundary = key + step_ns
        while key >= boundary:
            yield chunk, boundary - hold_ns
            chunk = []
            boundary += step_ns
        chunk.append(m)
    final = end_ns if end_ns is not None else (last if last is not None else 0)
    yield chunk, final


def replay_arrivals(
    measurements: Sequence[Measurement],
    arrival_ns: Sequence[int] | np.ndarray,
    *,
    lateness_ns: int = 150_000_000,
    step_ns: int = 100_000_000,
    end_ns: int | None = None,
) -> Iterator[tuple[list[Measurement], int]]:
    """Play measurements as the server's pipeline sees them; yield ``(release, until_ns)``.

    Every ``step_ns`` of arrival time the buffer releases, in order of first sample time (GNSS
    before IMU before wheels on ties), the measurements whose first sample is at or before
    ``horizon = newest sample time seen − lateness_ns``; push them, then advance the estimator to
    ``until_ns = horizon``. At the end everything left is released and ``until_ns`` is
    ``end_ns`` (default: the newest sample time). A measurement whose first sample is at or
    before an earlier horizon would be dropped by the server as late; here it raises
    ``ValueError`` (the simulator's latencies must fit in the lateness window).
    """
    if step_ns <= 0 or lateness_ns < 0:
        raise ValueError("step_ns must be > 0 and lateness_ns >= 0")
    heap: list[tuple[int, int, int, Measurement]] = []
    counter = itertools.count()
    newest: int | None = None
    released: int | None = None
    next_step: int | None = None

    def drain(horizon: int) -> list[Measurement]:
        out: list[Measurement] = []
        while heap and heap[0][0] <= horizon:
            out.append(heapq.heappop(heap)[3])
        return out

    for arrival, m in in_arrival_order(measurements, arrival_ns):
        if next_step is None:
            next_step = arrival + step_ns
        while arrival >= next_step:
            if newest is not None:
                horizon = newest - lateness_ns
                if released is None or horizon > released:
                    released = horizon
                    yield drain(horizon), horizon
            next_step += step_ns
        first = first_ns(m)
        if released is not None and first <= released:
            raise ValueError(f"measurement at {first} arrived after the horizon {released}")
        heapq.heappush(heap, (first, _stream_rank(m), next(counter), m))
        last = completion_ns(m)
        newest = last if newest is None else max(newest, last)
    final = end_ns if end_ns is not None else (newest if newest is not None else 0)
    rest: list[Measurement] = []
    while heap:
        rest.append(heapq.heappop(heap)[3])
    yield rest, final
