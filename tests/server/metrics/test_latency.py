"""Latency probe: every estimator's rows are timed from their stamp_ns, live and stored."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from estimator.catalog import SPECS
from estimator.mdsf_spec import MDSF_SPEC
from estimator.spec import EstimatorSpec
from estimator.types import EstimateBatch
from server.metrics.latency import LatencyProbe
from server.settings import StorageSettings
from server.storage import open_store

NOW_NS = 1_800_000_000_000_000_000
MS = 1_000_000


def _batch(spec: EstimatorSpec, vehicles: list[str], ages_ms: list[int]) -> EstimateBatch:
    """One row per age and vehicle, ``age`` ms before :data:`NOW_NS`."""
    parts = []
    for vid in vehicles:
        rows = spec.empty_rows(len(ages_ms))
        rows["stamp_ns"] = NOW_NS - np.array(ages_ms, np.int64) * MS
        parts.append((vid, rows))
    return EstimateBatch.of(parts, spec)


def test_rows_of_every_estimator_are_timed_live() -> None:
    probe = LatencyProbe(clock_ns=lambda: NOW_NS)
    for spec in SPECS.values():
        probe.on_estimates(_batch(spec, ["a", "b"], [10, 200]))
    counts, total_s, max_ns = probe.live.snapshot()
    assert counts.sum() == 4 * len(SPECS)
    assert abs(total_s - 2 * len(SPECS) * 0.21) < 1e-9 and max_ns == 200 * MS


def test_commits_are_timed_through_the_wrapped_store(tmp_path: Path) -> None:
    store = open_store(StorageSettings(data_dir=tmp_path))
    try:
        store.upsert_vehicle("a", {}, now_ns=NOW_NS)
        probe = LatencyProbe(clock_ns=lambda: NOW_NS)
        timed = probe.wrap_store(store)
        assert timed.write_estimates(_batch(MDSF_SPEC, ["a"], [50, 60, 70])) == 3
        counts, total_s, _ = probe.stored.snapshot()
        assert counts.sum() == 3 and abs(total_s - 0.18) < 1e-9
        assert len(timed.query_series("a", 0, NOW_NS + 1)) == 3  # the rest is the store's
    finally:
        store.close()
