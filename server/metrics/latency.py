"""End-to-end latency of estimates: sensor time of a row → wall time it reached a stage.

Two stages are measured inside the server process:

* ``live``: the pipeline handed the row to its sinks (the live hub sees it in the same call, so
  this is when it reaches the live feed);
* ``stored``: the writer's transaction holding the row committed.

For every row of every estimator, ``latency = wall clock now − row["stamp_ns"]`` (the row's
sensor timestamp, the vehicle's GNSS-disciplined clock; every spec's rows start with it). On
one machine, or with synchronized clocks, that is the full sensor-to-stage delay: batching on
the vehicle, network, reorder window (``ingest.lateness_ms``), estimator stepping
(``ingest.advance_step_ms``) and, for ``stored``, the writer's commit interval.

Latencies are counted in a fixed histogram per stage (log-spaced bounds, 5 % apart, 1 ms … 100 s),
exposed on ``/metrics`` as cumulative ``slipfleet_estimate_latency_seconds_bucket{stage,le}``
with ``_count`` and ``_sum``. A client takes two scrapes and differences them to get the
quantiles of a time window (:func:`quantiles_from_buckets`); the error is half a bucket (±2.5 %).
Recording is one ``searchsorted`` + ``bincount`` per batch of rows.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any, cast

import numpy as np
import numpy.typing as npt

from estimator.types import EstimateBatch
from server.metrics.prometheus import MetricFamily, Sample
from server.storage.base import Store

__all__ = [
    "BOUNDS_S",
    "LatencyHistogram",
    "LatencyProbe",
    "quantiles_from_buckets",
]

#: Upper bounds of the histogram buckets, seconds (the last bucket is +Inf).
BOUNDS_S: npt.NDArray[np.float64] = np.round(1e-3 * 1.05 ** np.arange(0, 237), 6)
_BOUNDS_NS = (BOUNDS_S * 1e9).astype(np.int64)


class LatencyHistogram:
    """Thread-safe counts of latencies (ns) in the :data:`BOUNDS_S` buckets, plus +Inf."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._counts = np.zeros(len(_BOUNDS_NS) + 1, dtype=np.int64)
        self._sum_s = 0.0
        self._max_ns = 0

    def add(self, latency_ns: npt.NDArray[np.int64]) -> None:
        """Count a batch of latencies (negative ones, clock skew, fall in the first bucket)."""
        if latency_ns.size == 0:
            return
        idx = np.searchsorted(_BOUNDS_NS, latency_ns, side="left")
        counts = np.bincount(idx, minlength=len(self._counts))
        total_s = float(latency_ns.sum()) / 1e9
        peak = int(latency_ns.max())
        with self._lock:
            self._counts += counts
            self._sum_s += total_s
            self._max_ns = max(self._max_ns, peak)

    def snapshot(self) -> tuple[npt.NDArray[np.int64], float, int]:
        """``(counts per bucket (non-cumulative, last is +Inf), sum seconds, max ns)``."""
        with self._lock:
            return self._counts.copy(), self._sum_s, self._max_ns


class _TimedStore:
    """A :class:`Store` that records the commit latency of every row it writes."""

    def __init__(self, store: Store, histogram: LatencyHistogram, clock_ns: Callable[[], int]):
        self._store = store
        self._histogram = histogram
        self._clock_ns = clock_ns

    def write_estimates(self, *batches: EstimateBatch) -> int:
        """The store's ``write_estimates`` (one transaction, any estimators' batches), then
        each row's commit latency recorded."""
        written = self._store.write_estimates(*batches)
        now = self._clock_ns()
        for batch in batches:
            self._histogram.add(now - batch.rows["stamp_ns"].astype(np.int64))
        return written

    def __getattr__(self, name: str) -> Any:
        return getattr(self._store, name)


class LatencyProbe:
    """Histograms of the ``live`` and ``stored`` stages (see the module docstring).

    Use :meth:`on_estimates` as a pipeline sink (after the live hub) and give the writer
    :meth:`wrap_store` instead of the store itself.
    """

    def __init__(self, clock_ns: Callable[[], int] = time.time_ns) -> None:
        self._clock_ns = clock_ns
        self.live = LatencyHistogram()
        self.stored = LatencyHistogram()

    def on_estimates(self, batch: EstimateBatch) -> None:
        """Pipeline sink: count the batch's rows (any estimator's) in :attr:`live`."""
        self.live.add(self._clock_ns() - batch.rows["stamp_ns"].astype(np.int64))

    def wrap_store(self, store: Store) -> Store:
        """``store`` with commit latencies recorded in :attr:`stored`."""
        return cast(Store, _TimedStore(store, self.stored, self._clock_ns))

    def families(self) -> list[MetricFamily]:
        """The histograms as one Prometheus family (cumulative buckets, ``_count``, ``_sum``)."""
        samples: list[Sample] = []
        for stage, hist in (("live", self.live), ("stored", self.stored)):
            counts, total_s, max_ns = hist.snapshot()
            cum = np.cumsum(counts)
            les = [f"{b:g}" for b in BOUNDS_S] + ["+Inf"]
            for le, c in zip(les, cum.tolist(), strict=True):
                samples.append(Sample(float(c), {"stage": stage, "le": le}, "_bucket"))
            samples.append(Sample(float(cum[-1]), {"stage": stage}, "_count"))
            samples.append(Sample(total_s, {"stage": stage}, "_sum"))
            samples.append(Sample(max_ns / 1e9, {"stage": stage}, "_max"))
        return [
            MetricFamily(
                "slipfleet_estimate_latency_seconds",
                "untyped",
                "Histogram: estimate sensor time to wall time at a stage (live feed, stored).",
                samples,
            )
        ]


def quantiles_from_buckets(
    bounds_s: Sequence[float], counts: Sequence[float], qs: Iterable[float]
) -> dict[float, float]:
    """Quantiles (seconds) of non-cumulative bucket ``counts`` (last one +Inf), interpolated
    linearly inside a bucket; NaN when there are no counts. A quantile in the +Inf bucket is
    reported as the last finite bound."""
    c = np.asarray(counts, dtype=np.float64)
    total = float(c.sum())
    out: dict[float, float] = {}
    if total <= 0:
        return {q: float("nan") for q in qs}
    cum = np.cumsum(c)
    lower = np.r_[0.0, np.asarray(bounds_s, dtype=np.float64)]
    upper = np.r_[np.asarray(bounds_s, dtype=np.float64), bounds_s[-1]]
    for q in qs:
        target = q * total
        i = int(np.searchsorted(cum, target, side="left"))
        i = min(i, len(c) - 1)
        before = float(cum[i - 1]) if i > 0 else 0.0
        frac = (target - before) / c[i] if c[i] > 0 else 1.0
        out[q] = float(lower[i] + (upper[i] - lower[i]) * min(max(frac, 0.0), 1.0))
    return out


def parse_histogram(
    metrics_text: str, name: str = "slipfleet_estimate_latency_seconds"
) -> Mapping[str, dict[str, Any]]:
    """``{stage: {"bounds": [...], "counts": [...] (non-cumulative), "max_s": float}}`` from
    Prometheus text."""
    cum: dict[str, list[tuple[float, float]]] = {}
    maxes: dict[str, float] = {}
    for line in metrics_text.splitlines():
        if line.startswith(name + "_bucket{"):
            labels, value = line[len(name) + 8 :].rsplit("} ", 1)
            lab = dict(part.split("=", 1) for part in labels.split(","))
            stage = lab["stage"].strip('"')
            le = lab["le"].strip('"')
            cum.setdefault(stage, []).append(
                (float("inf") if le == "+Inf" else float(le), float(value))
            )
        elif line.startswith(name + "_max{"):
            labels, value = line[len(name) + 5 :].rsplit("} ", 1)
            stage = labels.split("=", 1)[1].strip('"')
            maxes[stage] = float(value)
    out: dict[str, dict[str, Any]] = {}
    for stage, pairs in cum.items():
        pairs.sort()
        values = np.array([v for _, v in pairs])
        out[stage] = {
            "bounds": [b for b, _ in pairs[:-1]],
            "counts": np.diff(np.r_[0.0, values]).tolist(),
            "max_s": maxes.get(stage, float("nan")),
        }
    return out
