"""The receiver's clock as an online calibration (``TRACKED_SPEC.calibrations``): the rows carry
the filter's clock and its 1-sigma (product; NaN in the paper modes), a restore makes the stored
clock the state's prior (per slot, batched as alone), and a reset returns to the config's prior."""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest

from estimator.config import TrackedConfig
from estimator.sim.tracked import CrawlerSensors, TrackedRun, simulate_tracked
from estimator.tracked import (
    TrackedEstimator,
    TrackedEstimatorConfig,
    TrackedFleet,
    TrackedMode,
)
from estimator.tracked.model import TrackedState as S
from estimator.tracked_spec import TRACKED_SPEC

SECOND = 1_000_000_000
C = S.GNSS_CLOCK
CLOCK = ("gnss_clock_offset_s", "gnss_clock_offset_std_s")
NO_LAG = TrackedEstimatorConfig(report_lag_ticks=0)
PRIOR_S = TrackedEstimatorConfig().gnss_clock_offset_std_s


@cache
def _run(offset_s: float = 0.07) -> TrackedRun:
    """``route_firm`` seed 31 with the receiver ``offset_s`` ahead of the IMU."""
    return simulate_tracked(
        "route_firm",
        31,
        config=TrackedConfig(),
        sensors=CrawlerSensors(gnss_clock_offset_s=offset_s),
    )


def _drive(fleet: TrackedFleet | TrackedEstimator, vids: list[str], seconds: float) -> dict:
    """The run's first ``seconds`` pushed to each of ``vids``, advanced second by second; the
    rows per vehicle."""
    run = _run()
    until = run.start_ns + int(seconds * SECOND)
    out: dict[str, list[np.ndarray]] = {v: [] for v in vids}
    i, ms = 0, run.measurements
    for t in range(run.start_ns + SECOND, until + 1, SECOND):
        while i < len(ms) and ms[i][0] <= t:
            for v in vids:
                fleet.push(v, ms[i][1])
            i += 1
        for v, rows in fleet.advance(dict.fromkeys(vids, t)):
            out[v].append(rows)
    return {v: np.concatenate(p) for v, p in out.items()}


def _fleet(cls: type = TrackedFleet, cfg: TrackedEstimatorConfig = NO_LAG, n: int = 1) -> tuple:
    fleet = cls(cfg)
    vids = [f"v{k}" for k in range(n)]
    for v in vids:
        fleet.add_vehicle(v, _run().config)
    return fleet, vids


def test_the_spec_declares_the_clock_beside_the_gyro() -> None:
    c = TRACKED_SPEC.calibration("gnss_clock_offset")
    assert (c.field, c.std_field) == CLOCK
    assert c.limit_config == "calibration.clock_offset_converged_ms" and c.limit_scale == 1e-3
    assert not c.relative and c.enabled_config is None
    assert [TRACKED_SPEC.field(f).unit for f in CLOCK] == ["s", "s"]
    listed = TRACKED_SPEC.to_dict()["calibrations"]
    assert [d["key"] for d in listed] == ["gyro_arw", "gnss_clock_offset"]
    assert listed[1]["field"] == "gnss_clock_offset_s"
    assert TrackedConfig().calibration.clock_offset_converged_ms == 10.0


def test_the_rows_carry_the_filters_clock_and_learn_the_receivers() -> None:
    fleet, vids = _fleet()
    rows = _drive(fleet, vids, 120.0)["v0"]
    x, P = fleet.filter_state("v0")
    last = rows[-1]
    assert last["gnss_clock_offset_s"] == x[C]
    assert last["gnss_clock_offset_std_s"] == pytest.approx(np.sqrt(P[C, C]), rel=1e-12)
    assert fleet.calibration_fields("v0")["gnss_clock_offset_s"] == x[C]
    assert rows["gnss_clock_offset_std_s"][0] == pytest.approx(PRIOR_S, rel=0.01)
    # learnt: within 3 of its 1-sigma of the receiver's 70 ms, and the 1-sigma below 10 ms
    assert last["gnss_clock_offset_std_s"] < 0.01
    assert abs(last["gnss_clock_offset_s"] - 0.07) < 3 * last["gnss_clock_offset_std_s"]


@pytest.mark.parametrize("mode", [TrackedMode.PAPER, TrackedMode.RAW_ODOMETER])
def test_the_paper_modes_give_no_clock_and_restore_none(mode: TrackedMode) -> None:
    fleet, vids = _fleet(cfg=TrackedEstimatorConfig(mode=mode))
    fleet.restore_calibration_fields("v0", {CLOCK[0]: 0.05, CLOCK[1]: 0.002})
    assert fleet.filter_state("v0")[0][C] == 0.0
    rows = _drive(fleet, vids, 20.0)["v0"]
    assert rows.size > 100 and np.isnan(rows["gnss_clock_offset_s"]).all()
    assert np.isnan(rows["gnss_clock_offset_std_s"]).all()
    got = fleet.calibration_fields("v0")
    assert np.isnan(got[CLOCK[0]]) and np.isnan(got[CLOCK[1]])


def test_a_restore_is_the_states_prior_per_slot() -> None:
    fleet, vids = _fleet(n=3)
    _drive(fleet, vids, 30.0)  # the clock learnt and correlated with the rest
    before = [fleet.filter_state(v) for v in vids]
    assert np.abs(before[1][1][C, :C]).max() > 0.0
    fleet.restore_calibration_fields("v1", {CLOCK[0]: -0.042, CLOCK[1]: 0.003})
    fleet.restore_calibration_fields("v2", {CLOCK[0]: 0.081})  # the std missing: nothing
    x, P = fleet.filter_state("v1")
    assert x[C] == -0.042 and P[C, C] == pytest.approx(0.003**2, rel=1e-12)
    assert not P[C, :C].any() and not P[:C, C].any()
    others = [i for i in range(len(x)) if i != C]
    assert np.array_equal(x[others], before[1][0][others])
    assert np.array_equal(P[np.ix_(others, others)], before[1][1][np.ix_(others, others)])
    assert np.all(np.linalg.eigvalsh(P) > 0.0)
    for v in (0, 2):  # the other slots untouched
        xv, Pv = fleet.filter_state(vids[v])
        assert np.array_equal(xv, before[v][0]) and np.array_equal(Pv, before[v][1])
    # a non-finite value or std restores nothing
    fleet.restore_calibration_fields("v0", {CLOCK[0]: float("nan"), CLOCK[1]: 0.003})
    fleet.restore_calibration_fields("v0", {CLOCK[0]: 0.01, CLOCK[1]: float("inf")})
    assert np.array_equal(fleet.filter_state("v0")[1], before[0][1])


def test_restored_clocks_batched_equal_per_vehicle() -> None:
    stored = {"v0": (0.065, 0.004), "v1": (-0.02, 0.05)}
    rows = {}
    for cls in (TrackedFleet, TrackedEstimator):
        fleet, vids = _fleet(cls, TrackedEstimatorConfig(), n=3)
        for v, (c, s) in stored.items():
            fleet.restore_calibration_fields(v, {CLOCK[0]: c, CLOCK[1]: s})
        rows[cls] = _drive(fleet, vids, 60.0)
    for v in ("v0", "v1", "v2"):
        a, b = rows[TrackedFleet][v], rows[TrackedEstimator][v]
        assert a.size == b.size > 500
        for name in TRACKED_SPEC.field_names:
            assert np.allclose(a[name], b[name], rtol=0, atol=1e-9, equal_nan=True), name
    # the restored vehicle starts where its clock was stored, the fresh one from the prior
    first = {v: rows[TrackedFleet][v][0] for v in ("v0", "v2")}
    assert first["v0"]["gnss_clock_offset_std_s"] < 0.0041
    assert first["v2"]["gnss_clock_offset_std_s"] == pytest.approx(PRIOR_S, rel=0.01)


def test_a_reset_returns_the_clock_to_the_configs_prior() -> None:
    fleet, vids = _fleet()
    fresh = fleet.filter_state("v0")
    _drive(fleet, vids, 60.0)
    x, P = fleet.filter_state("v0")
    assert P[C, C] < 0.01**2 and abs(x[C]) > 0.03 and np.abs(P[C, :C]).max() > 0.0
    fleet.reset_calibration("v0")
    x2, P2 = fleet.filter_state("v0")
    assert x2[C] == 0.0 and P2[C, C] == pytest.approx(PRIOR_S**2, rel=1e-12)
    assert P2[C, C] == fresh[1][C, C]
    assert not P2[C, :C].any() and np.all(np.linalg.eigvalsh(P2) > 0.0)
    got = fleet.calibration_fields("v0")
    assert got[CLOCK[0]] == 0.0 and got[CLOCK[1]] == pytest.approx(PRIOR_S, rel=1e-12)
