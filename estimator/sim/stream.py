"""Ordering and replay of simulated measurements.

Two orders matter:

* **sensor order** — by the sensor time that completes a measurement (:func:`completion_ns`:
  a GNSS epoch's stamp, a batch's last stamp). :class:`estimator.base.FleetEstimator` wants each
  vehicle's measurements pushed in this order. :attr:`SimRun.measurements` is in it.
* **arrival order** — when the measurement reaches the server (sensor time plus latency, and a
  wheel packet only when its window closes). A live publisher sends in this order; the server's
  reorder buffer restores sensor order within its lateness window.

:func:`replay` plays a run the way the server's pipeline would: release measurements in sensor
order and advance the estimator to a watermark that every sensor has reached.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence

import numpy as np

from estimator.base import Measurement
from estimator.types import GnssSample

__all__ = ["completion_ns", "in_arrival_order", "replay"]


def completion_ns(measurement: Measurement) -> int:
    """Sensor time at which ``measurement`` is complete: its stamp, or its last sample's stamp."""
    if isinstance(measurement, GnssSample):
        return int(measurement.stamp_ns)
    stamps = measurement.stamp_ns
    if len(stamps) == 0:
        raise ValueError("an empty batch has no completion time")
    return int(stamps[-1])


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
