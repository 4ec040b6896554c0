"""The tracked fleet: batched = per-vehicle, covariance SPD, NIS within chi-square bounds, bad
input counted and kept from the filter, rows of the spec."""

from __future__ import annotations

import dataclasses
from functools import cache

import numpy as np
import pytest
from scipy.stats import chi2

from estimator.base import Measurement
from estimator.config import GyroConfig, TrackedConfig, TrackedGeometry, WheeledRearDriveConfig
from estimator.gyro import ADIS16470
from estimator.sim.tracked import ORIGIN, START_NS, CrawlerSensors, TrackedRun, simulate_tracked
from estimator.sim.tracked.physics import integrate_route
from estimator.sim.tracked.route import named_route
from estimator.sim.tracked.sensors import draw_errors, emissions
from estimator.tracked import (
    MotionState,
    TrackedEstimator,
    TrackedEstimatorConfig,
    TrackedFleet,
    TrackedMode,
)
from estimator.tracked_spec import TRACKED_SPEC, TrackedFlag
from estimator.types import OdometerEdges, SprocketEdges, TrackSide

SECOND = 1_000_000_000
M = MotionState


@cache
def _run(name: str, seed: int) -> TrackedRun:
    return simulate_tracked(name, seed)


def _feed(
    fleet: TrackedFleet | TrackedEstimator,
    streams: dict[str, list[tuple[int, Measurement]]],
    until_ns: int,
    step_ns: int = SECOND,
) -> dict[str, np.ndarray]:
    """Push each vehicle's packets in key order, advancing every ``step_ns``; rows per vehicle."""
    pos = dict.fromkeys(streams, 0)
    t = min(s[0][0] for s in streams.values())
    out: dict[str, list[np.ndarray]] = {vid: [] for vid in streams}
    while t < until_ns:
        t += step_ns
        for vid, ms in streams.items():
            i = pos[vid]
            while i < len(ms) and ms[i][0] <= t:
                fleet.push(vid, ms[i][1])
                i += 1
            pos[vid] = i
        for vid, rows in fleet.advance(dict.fromkeys(streams, t)):
            out[vid].append(rows)
    return {vid: np.concatenate(parts) for vid, parts in out.items()}


def _fleet_of(cls: type, runs: dict[str, TrackedRun], mode: TrackedMode) -> TrackedFleet:
    fleet = cls(TrackedEstimatorConfig(mode=mode))
    for vid, r in runs.items():
        fleet.add_vehicle(vid, r.config)
    return fleet


@pytest.mark.parametrize("mode", [TrackedMode.PRODUCT, TrackedMode.PAPER])
def test_batched_equals_per_vehicle(mode: TrackedMode) -> None:
    runs = {"a": _run("route_firm", 1), "b": _run("route_soft", 2), "c": _run("random", 3)}
    runs["d"] = _run("route_firm_hill", 1)  # grades and cross grades (so is "c"'s terrain)
    until = {vid: r.start_ns + 70 * SECOND for vid, r in runs.items()}
    streams = {vid: [m for m in r.measurements if m[0] <= until[vid]] for vid, r in runs.items()}
    streams["c"] = streams["c"][: len(streams["c"]) * 2 // 3]  # a vehicle with fewer ticks
    end = max(until.values())
    batched = _feed(_fleet_of(TrackedFleet, runs, mode), streams, end, step_ns=SECOND // 2)
    alone = _feed(_fleet_of(TrackedEstimator, runs, mode), streams, end, step_ns=3 * SECOND)
    for vid in runs:
        a, b = batched[vid], alone[vid]
        assert a.dtype == TRACKED_SPEC.dtype and a.size == b.size > 300
        for name in TRACKED_SPEC.field_names:
            if a.dtype[name].kind == "f":
                assert np.allclose(a[name], b[name], rtol=0, atol=1e-9, equal_nan=True), name
            else:
                assert np.array_equal(a[name], b[name]), name
    # the attitude is compared where it is given, not only as NaN on both sides
    hill = batched["d"]
    assert np.isfinite(hill["pitch_rad"]).sum() > 300 and np.isfinite(hill["roll_rad"]).sum() > 300


@cache
def _product_rows(name: str, seed: int) -> tuple[TrackedFleet, np.ndarray]:
    run = _run(name, seed)
    fleet = _fleet_of(TrackedFleet, {"v": run}, TrackedMode.PRODUCT)
    until = run.start_ns + 140 * SECOND  # before the named routes' outage
    rows = _feed(fleet, {"v": [m for m in run.measurements if m[0] <= until]}, until)["v"]
    return fleet, rows


def test_covariance_stays_symmetric_positive_definite() -> None:
    fleet, _ = _product_rows("route_soft", 4)
    _, P = fleet.filter_state("v")
    assert np.allclose(P, P.T, atol=1e-12)
    assert np.linalg.eigvalsh(P).min() > 0


def test_gnss_nis_within_chi_square_bounds() -> None:
    fleet, _ = _product_rows("route_firm", 5)
    nis = fleet.gnss_nis("v")[100:]  # after the start-up transient
    n = nis.size
    assert n > 800
    low, high = chi2.ppf([0.005, 0.995], 2 * n) / n  # the mean of n NIS of 2 dof
    assert low < nis.mean() < high, nis.mean()


def test_rows_follow_the_truth_with_gnss() -> None:
    _, rows = _product_rows("route_firm", 5)
    run = _run("route_firm", 5)
    idx = run.index_at(rows["stamp_ns"])
    moving = run.truth.speed_mps[idx] > 1.0
    err = np.abs(rows["speed_mps"] - run.truth.speed_mps[idx])[moving]
    assert np.percentile(err, 95) < 0.1
    started = (rows["flags"] & int(TrackedFlag.NOT_STARTED)) == 0
    pos = np.hypot(rows["east_m"] - run.truth.east_m[idx], rows["north_m"] - run.truth.north_m[idx])
    assert np.nanmax(pos[started]) < 0.5
    assert np.mean(rows["motion_state"] == run.truth.state[idx]) > 0.95


def _edges_only(run: TrackedRun, until_ns: int) -> list[tuple[int, Measurement]]:
    return [m for m in run.measurements if m[0] <= until_ns]


def test_edges_going_backwards_never_reach_the_filter() -> None:
    run = _run("route_firm", 6)
    until = run.start_ns + 40 * SECOND
    clean = _edges_only(run, until)
    bad = list(clean)
    k = next(i for i, (_, m) in enumerate(bad) if isinstance(m, OdometerEdges) and m.stamp_ns.size)
    first = bad[k][1]
    assert isinstance(first, OdometerEdges)
    back = np.asarray(first.stamp_ns - 5 * SECOND, dtype=np.int64)  # edges from the past
    bad.insert(k + 20, (bad[k + 20][0], OdometerEdges(back)))
    fleet = _fleet_of(TrackedFleet, {"v": run}, TrackedMode.PRODUCT)
    rows = _feed(fleet, {"v": bad}, until)["v"]
    ref = _feed(_fleet_of(TrackedFleet, {"v": run}, TrackedMode.PRODUCT), {"v": clean}, until)
    assert fleet.counters("v")["odometer_backwards"] == back.size
    assert np.array_equal(rows["speed_mps"], ref["v"]["speed_mps"], equal_nan=True)


def test_a_missing_sprocket_stream_is_flagged_and_the_state_taken_from_the_radius() -> None:
    run = _run("route_firm", 7)
    until = run.start_ns + 90 * SECOND
    streams = [
        m
        for m in _edges_only(run, until)
        if not (isinstance(m[1], SprocketEdges) and m[1].side == TrackSide.TRACK_RIGHT)
    ]
    fleet = _fleet_of(TrackedFleet, {"v": run}, TrackedMode.PRODUCT)
    rows = _feed(fleet, {"v": streams}, until)["v"]
    missing = (rows["flags"] & int(TrackedFlag.SPROCKET_MISSING)) > 0
    held = fleet.counters("v")["ticks"] - rows.size  # the last ticks are held (fixed lag)
    assert 1 <= held <= fleet.config.lag_ticks and missing[-1]
    assert missing.sum() > 500
    assert fleet.counters("v")["sprocket_missing_ticks"] == missing.sum() + held
    assert np.isnan(rows["slip_right_pct"][missing]).all()  # no slip of a track not read
    assert not (rows["flags"][missing] & int(TrackedFlag.BRAKED_RIGHT)).any()
    idx = run.index_at(rows["stamp_ns"])
    straight = run.truth.state[idx] == int(MotionState.STRAIGHT)
    assert np.mean(rows["motion_state"][missing & straight] == int(MotionState.STRAIGHT)) > 0.9


def test_odometer_without_sprockets_still_dead_reckons() -> None:
    run = _run("route_firm", 8)
    until = run.start_ns + 60 * SECOND
    streams = [m for m in _edges_only(run, until) if not isinstance(m[1], SprocketEdges)]
    fleet = _fleet_of(TrackedFleet, {"v": run}, TrackedMode.PRODUCT)
    rows = _feed(fleet, {"v": streams}, until)["v"]
    assert fleet.counters("v")["odometer_fused"] > 400
    assert not (rows["flags"] & int(TrackedFlag.SLIP_LEFT_VALID)).any()


def test_refuses_other_kinds_and_checks_anchor() -> None:
    fleet = TrackedFleet()
    with pytest.raises(ValueError, match="tracked"):
        fleet.add_vehicle("t", WheeledRearDriveConfig())
    fleet.add_vehicle("c", TrackedConfig())
    with pytest.raises(ValueError):
        fleet.set_anchor("c", float("nan"), 5.0, 0.0)
    fleet.set_anchor("c", 52.0, 5.6, 10.0)
    assert fleet.anchor("c") == (52.0, 5.6, 10.0)


def test_vehicles_of_different_geometry_batch_together() -> None:
    run = _run("route_firm", 9)
    wide = dataclasses.replace(run.config, geometry=TrackedGeometry(track_gauge_m=3.0))
    fleet = TrackedFleet()
    fleet.add_vehicle("a", run.config)
    fleet.add_vehicle("b", wide)
    until = run.start_ns + 20 * SECOND
    ms = _edges_only(run, until)
    rows = _feed(fleet, {"a": ms, "b": ms}, until)
    diff = rows["a"]["track_left_mps"] - rows["b"]["track_left_mps"]
    assert np.nanmax(np.abs(diff)) > 0  # the gauge enters V ∓ ω·B/2


def test_slip_given_only_where_observable_and_close_to_the_truth() -> None:
    _, rows = _product_rows("route_firm", 5)
    run = _run("route_firm", 5)
    idx = run.index_at(rows["stamp_ns"])
    limit = TrackedEstimatorConfig().slip_std_max_pct
    for side, name, flag in (
        (0, "left", TrackedFlag.SLIP_LEFT_VALID),
        (1, "right", TrackedFlag.SLIP_RIGHT_VALID),
    ):
        valid = (rows["flags"] & int(flag)) > 0
        assert np.isfinite(rows[f"slip_{name}_pct"][valid]).all()
        assert (rows[f"slip_{name}_std_pct"][valid] <= limit).all()
        braked = (rows["flags"] & int(TrackedFlag.BRAKED_LEFT << side)) > 0
        assert np.isnan(rows[f"slip_{name}_pct"][~valid & ~braked]).all()
        err = np.abs(rows[f"slip_{name}_pct"] - 100 * run.truth.slip[idx, side])[valid]
        assert valid.mean() > 0.8 and np.percentile(err, 95) < 3.0


@cache
def _outage_run() -> TrackedRun:
    """``route_firm`` with a 30 s GNSS outage from 60 s (moving all through it)."""
    base = named_route("route_firm")
    route = dataclasses.replace(base, outages_s=((60.0, 30.0),))
    rng = np.random.default_rng(23)
    config, sensors = TrackedConfig(), CrawlerSensors()
    truth = integrate_route(route, config, rng)
    errors = draw_errors(rng, truth.t_s.size, sensors)
    sent = emissions(truth, config, sensors, errors, ORIGIN, route.outages_s, START_NS, rng)
    return TrackedRun("route_firm", 23, route, config, truth, errors, START_NS, ORIGIN, sent)


def test_a_worse_gyro_grows_the_dead_reckoned_covariance_faster() -> None:
    run = _outage_run()
    worse = GyroConfig.of(ADIS16470.scaled(4.0))
    fleet = TrackedFleet()
    fleet.add_vehicle("adis", run.config)
    fleet.add_vehicle("worse", dataclasses.replace(run.config, gyro=worse))
    until = run.start_ns + 95 * SECOND
    ms = [m for m in run.measurements if m[0] <= until]
    rows = _feed(fleet, {"adis": ms, "worse": ms}, until)
    growth = {}
    for vid, r in rows.items():
        dr = np.flatnonzero((r["flags"] & int(TrackedFlag.DEAD_RECKONING)) != 0)
        assert dr.size > 250  # the outage is dead-reckoned
        var = r["east_std_m"] ** 2 + r["north_std_m"] ** 2
        growth[vid] = var[dr[-1]] - var[dr[0]]
    # the same measurements: only the gyro's noise differs, and it adds to the heading's
    # error, so to the cross-track variance through the outage
    assert growth["worse"] > 1.5 * growth["adis"] > 0, growth
    a, b = rows["adis"], rows["worse"]
    before = slice(0, dr[0] // 2)  # with GNSS both follow it alike:
    for axis in ("east", "north"):  # apart by less than either's own 1-sigma
        gap_m = np.abs(a[f"{axis}_m"][before] - b[f"{axis}_m"][before])
        sigma_m = np.minimum(a[f"{axis}_std_m"][before], b[f"{axis}_std_m"][before])
        known = np.isfinite(gap_m)  # no position before the first fix, alike in both
        assert known.sum() > 100 and np.array_equal(known, np.isfinite(a[f"{axis}_m"][before]))
        ratio = gap_m[known] / sigma_m[known]
        assert np.all(ratio < 1.0), (axis, float(ratio.max()))


def _same_rows(a: np.ndarray, b: np.ndarray) -> None:
    assert a.dtype == b.dtype and a.size == b.size
    for name in TRACKED_SPEC.field_names:
        if a.dtype[name].kind == "f":
            assert np.allclose(a[name], b[name], rtol=0, atol=1e-9, equal_nan=True), name
        else:
            assert np.array_equal(a[name], b[name]), name


def test_a_drives_first_rows_stand_at_rest_and_move_from_the_first_odometer_edge() -> None:
    run = _run("route_firm", 9)  # stands for ~5 s, then starts
    lever_ns = run.start_ns + round(run.truth.t_s[np.argmax(run.truth.state != M.STOP)] * 1e9)
    edges = np.concatenate(
        [m.stamp_ns for _, m in run.measurements if isinstance(m, OdometerEdges)]
    )
    first_edge_ns = int(edges[edges > lever_ns].min())
    joined_ns = run.start_ns + 30 * SECOND  # the same drive joined at speed
    streams = {
        "at_rest": [m for m in run.measurements if m[0] <= run.start_ns + 10 * SECOND],
        "moving": [m for m in run.measurements if joined_ns <= m[0] <= joined_ns + 5 * SECOND],
    }
    runs = dict.fromkeys(streams, run)
    batched = _feed(
        _fleet_of(TrackedFleet, runs, TrackedMode.PRODUCT), streams, joined_ns + 5 * SECOND
    )
    for vid, ms in streams.items():  # batched = per vehicle
        alone = _feed(
            _fleet_of(TrackedEstimator, {vid: run}, TrackedMode.PRODUCT), {vid: ms}, ms[-1][0]
        )
        _same_rows(batched[vid], alone[vid])
    rows = batched["at_rest"]
    still = (rows["flags"] & int(TrackedFlag.STANDSTILL)) != 0
    state, stamp = rows["motion_state"], rows["stamp_ns"]
    assert state[0] == M.STOP and still[0]  # the first row: at rest
    standing = stamp < lever_ns - SECOND // 5
    assert standing.sum() > 40 and (state[standing] == M.STOP).all() and still[standing].all()
    # from the tick of the start's first odometer edge (its windows give no speed yet) on,
    # the crawler moves: no row reads stop or standstill
    under_way = stamp >= first_edge_ns
    assert (state[under_way] != M.STOP).all() and not still[under_way].any()
    rows = batched["moving"]
    assert rows["motion_state"][0] != M.STOP  # the first row: moving at speed
    assert not (rows["flags"] & int(TrackedFlag.STANDSTILL)).any()
