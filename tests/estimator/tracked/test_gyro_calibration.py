"""The gyro's noise measured standing as an online calibration (``TRACKED_SPEC.calibrations``):
its row fields by hand, taken out and given back without loss, and a reset that returns to the
data sheet; on a crawler whose unit is twice as noisy as the data sheet its config names."""

from __future__ import annotations

import dataclasses
from functools import cache

import numpy as np
import pytest

from estimator.config import TrackedCalibrationConfig, TrackedConfig
from estimator.gyro import ADIS16470
from estimator.sim.tracked import CrawlerSensors, TrackedRun, simulate_tracked
from estimator.tracked import TrackedEstimatorConfig, TrackedFleet
from estimator.tracked.gyro_noise import (
    LAST,
    PAIRS,
    SUM_SQ,
    arw_fields,
    initial_stats,
    learn_standing,
    noise_ratio,
    stats_from_fields,
)
from estimator.tracked.model import TrackedState as S
from estimator.tracked.params import VehicleParams
from estimator.tracked_spec import TRACKED_SPEC, TrackedFlag

SECOND = 1_000_000_000
FIELDS = [f for c in TRACKED_SPEC.calibrations for f in (c.field, c.std_field)]
#: The gyro's two fields (the receiver's clock has its own tests, test_clock_calibration).
GYRO = FIELDS[:2]
CFG = TrackedEstimatorConfig()


def test_the_rows_arw_and_its_std_by_hand_and_back() -> None:
    # 75 pairs whose squared changes sum to s: ARW² = s·Δt/(2n), σ = ARW·√(3/(4n)) = ARW/10
    arw_rad = ADIS16470.arw_rad_rt_s * 1.5
    stats = initial_stats(3)
    stats[0, [SUM_SQ, PAIRS]] = (2 * 75 * arw_rad**2 / CFG.tick_s, 75)
    stats[1, [SUM_SQ, PAIRS]] = (0.0, 0)
    stats[2, [SUM_SQ, PAIRS]] = (2 * 7 * arw_rad**2 / CFG.tick_s, 7)
    arw, std = arw_fields(stats, CFG)
    deg_rt_h = ADIS16470.angle_random_walk_deg_rt_h * 1.5
    assert arw[0] == pytest.approx(deg_rt_h, rel=1e-12)
    assert std[0] == pytest.approx(deg_rt_h / 10.0, rel=1e-12)
    assert np.isnan(arw[1]) and np.isnan(std[1])  # nothing measured yet
    back = stats_from_fields(arw, std, CFG)
    assert back[:, PAIRS].tolist() == [75, 0, 7]
    np.testing.assert_allclose(back[:, SUM_SQ], stats[:, SUM_SQ], rtol=1e-12)
    assert np.isnan(back[:, LAST]).all()
    # and so the filter's ratio, against the data sheet the config names now
    p = VehicleParams.stack([VehicleParams.of(TrackedConfig())] * 3)
    np.testing.assert_allclose(noise_ratio(back, p, CFG), noise_ratio(stats, p, CFG), rtol=1e-12)


def test_over_many_stops_the_rows_arw_is_unbiased_within_its_stated_std() -> None:
    """Monte Carlo of the measurement over 20,000 crawlers, each standing three times (31, 71
    and 33 ticks, the stops of ``random[1000]``: 132 pairs) with a unit 1.67 times the
    ADIS16470: the rows' ARW is the unit's on average (within 1 %), and spreads by the std the
    rows state (``ARW·√(3/(4n))``, within 5 %). Its std is stated from the reading itself, so a
    low reading states a smaller std: beyond 2 of it, low readings outnumber high ones."""
    rng = np.random.default_rng(26)
    k, grade = 20_000, 1.67
    arw_rad = grade * ADIS16470.arw_rad_rt_s
    stats = initial_stats(k)
    for ticks in (31, 71, 33):
        bias = rng.normal(0.0, 5e-4, k)  # a stop's bias: the walk between stops
        for _ in range(ticks):
            rate = bias + arw_rad / np.sqrt(CFG.tick_s) * rng.standard_normal(k)
            stats = learn_standing(stats, rate, np.ones(k, dtype=bool))
        stats = learn_standing(stats, np.zeros(k), np.zeros(k, dtype=bool))  # driving
    assert (stats[:, PAIRS] == 132).all()
    arw, std = arw_fields(stats, CFG)
    unit = grade * ADIS16470.angle_random_walk_deg_rt_h
    assert np.mean(arw) / unit == pytest.approx(1.0, abs=0.01)
    stated = unit * np.sqrt(3.0 / (4.0 * 132))
    assert np.std(arw) / stated == pytest.approx(1.0, abs=0.05)
    z = (arw - unit) / std
    assert np.sqrt(np.mean(z**2)) == pytest.approx(1.0, abs=0.05)
    assert np.mean(z < -2.0) > 2.0 * np.mean(z > 2.0)


@cache
def _run() -> TrackedRun:
    """``route_firm`` seed 23 with a unit twice the ADIS16470's noise, its config naming the
    data sheet (50 standing tick pairs before its outage)."""
    return simulate_tracked(
        "route_firm", 23, config=TrackedConfig(), sensors=CrawlerSensors(gyro_grade=2.0)
    )


def _replay(how: str, restart_s: float) -> tuple[TrackedFleet, np.ndarray]:
    """The run through a fleet, second by second, the vehicle registered again at
    ``restart_s`` before the outage (``how``: ``"carried"`` its measurement carried over in
    memory, ``"restored"`` through its row fields, ``"reset"`` restored then reset,
    ``"fresh"`` nothing given; ``"none"``: not registered again). The rows given after the
    restart (all rows for ``"none"``)."""
    run = _run()
    fleet = TrackedFleet(CFG)
    fleet.add_vehicle("v", run.config)
    fleet.set_anchor("v", run.frame.lat0_deg, run.frame.lon0_deg, run.frame.h0_m)
    restart_ns = run.outages_ns[0][0] - int(restart_s * SECOND)
    end_ns = run.outages_ns[0][1]
    i, ms, parts, again = 0, run.measurements, [], how != "none"
    for t in range(run.start_ns + SECOND, end_ns + 1, SECOND):
        if again and t > restart_ns:
            _register_again(fleet, run, how)
            parts.clear()
            again = False
        while i < len(ms) and ms[i][0] <= t:
            fleet.push("v", ms[i][1])
            i += 1
        parts += [rows for _, rows in fleet.advance({"v": t})]
    return fleet, np.concatenate(parts)


def _register_again(fleet: TrackedFleet, run: TrackedRun, how: str) -> None:
    slot = fleet._slots["v"]
    assert np.isnan(slot.filter.gyro_standing[0, LAST])  # moving: no standing pair is cut
    carried = slot.filter.gyro_standing.copy()
    values = fleet.calibration_fields("v")
    fleet.add_vehicle("v", run.config)
    fleet.set_anchor("v", run.frame.lat0_deg, run.frame.lon0_deg, run.frame.h0_m)
    if how == "carried":
        # the measurement carried over in memory, and the receiver's clock as a prior by hand
        new = fleet._slots["v"].filter
        new.gyro_standing = carried
        new.x[0, S.GNSS_CLOCK] = values["gnss_clock_offset_s"]
        new.P[0, S.GNSS_CLOCK, S.GNSS_CLOCK] = values["gnss_clock_offset_std_s"] ** 2
    elif how in ("restored", "reset"):
        fleet.restore_calibration_fields("v", values)
    if how == "reset":
        fleet.reset_calibration("v")


def _same_rows(a: np.ndarray, b: np.ndarray) -> None:
    """Equal to rounding: 1e-12 of each value, or of the field's largest value where a value
    is a near-cancelling sum (a covariance crossing zero differs in its last bits)."""
    assert a.shape == b.shape and a.size > 1000
    for name in TRACKED_SPEC.field_names:
        scale = np.nanmax(np.abs(b[name]), initial=0.0)
        atol = max(1e-12 * float(scale), 1e-15)
        np.testing.assert_allclose(a[name], b[name], rtol=1e-12, atol=atol, err_msg=name)


def test_a_restored_measurement_gives_the_rows_of_one_carried_on_and_its_values_go_on() -> None:
    """Registered again 60 s before the outage: the rows after it, with the measurement
    restored from its row fields, are those of a vehicle whose measurement was carried over
    in memory; the calibration's columns are those of the run never registered again; and
    without it the dead-reckoned position's covariance grows as for the data sheet."""
    _, carried = _replay("carried", 60.0)
    fleet, restored = _replay("restored", 60.0)
    _same_rows(restored, carried)
    _, whole = _replay("none", 60.0)
    at = np.isin(whole["stamp_ns"], restored["stamp_ns"])
    assert at.sum() == restored.size
    for name in GYRO:  # the clock restarts as a prior: not the correlated state it was
        np.testing.assert_allclose(restored[name], whole[name][at], rtol=1e-12, err_msg=name)
    assert np.isfinite(restored["gyro_arw_deg_rt_h"]).all()
    # the unit's measured ARW is about twice the data sheet's, and the fields are the state
    assert 1.4 < restored["gyro_arw_deg_rt_h"][-1] / ADIS16470.angle_random_walk_deg_rt_h < 2.8
    now = fleet.calibration_fields("v")
    # (the rows are given a tick late: the clock, learnt while driving, has moved on since)
    assert {f: now[f] for f in GYRO} == pytest.approx(
        {f: float(restored[f][-1]) for f in GYRO}, rel=1e-12
    )
    _, fresh = _replay("fresh", 60.0)
    # learnt anew from the stops after the restart alone: fewer pairs, a wider std
    assert np.isnan(fresh["gyro_arw_deg_rt_h"][0])
    assert fresh["gyro_arw_std_deg_rt_h"][-1] > 1.2 * restored["gyro_arw_std_deg_rt_h"][-1]
    assert fresh["east_std_m"][-1] ** 2 + fresh["north_std_m"][-1] ** 2 < 0.9 * (
        restored["east_std_m"][-1] ** 2 + restored["north_std_m"][-1] ** 2
    )


def test_a_reset_returns_to_the_data_sheet() -> None:
    """A reset right after a restore gives the rows of a vehicle that never measured its gyro,
    its calibration fields NaN until it stands again."""
    fleet, reset = _replay("reset", 60.0)
    _, fresh = _replay("fresh", 60.0)
    _same_rows(reset, fresh)
    # mid-drive: a unit measured at 4x the data sheet's ARW² is back at the data sheet
    four = {FIELDS[0]: 2 * ADIS16470.angle_random_walk_deg_rt_h, FIELDS[1]: 0.01}
    fleet.restore_calibration_fields("v", four)
    assert {f: fleet.calibration_fields("v")[f] for f in GYRO} == pytest.approx(four, rel=1e-12)
    p = fleet._slots["v"].inputs.params
    assert noise_ratio(fleet._slots["v"].filter.gyro_standing, p, CFG)[0] > 3.5
    fleet.reset_calibration("v")
    assert np.isnan([fleet.calibration_fields("v")[f] for f in GYRO]).all()
    assert noise_ratio(fleet._slots["v"].filter.gyro_standing, p, CFG)[0] == 1.0


def test_a_vehicle_whose_config_turns_it_off_measures_nothing_and_restores_nothing() -> None:
    run = _run()
    off = dataclasses.replace(run.config, calibration=TrackedCalibrationConfig(gyro_noise=False))
    fleet = TrackedFleet(CFG)
    fleet.add_vehicle("v", off)
    fleet.restore_calibration_fields("v", {FIELDS[0]: 0.5, FIELDS[1]: 0.05})
    until_ns = run.outages_ns[0][0]
    for _, m in (km for km in run.measurements if km[0] <= until_ns):
        fleet.push("v", m)
    rows = np.concatenate([r for _, r in fleet.advance({"v": until_ns})])
    assert rows.size > 1000 and np.isnan(rows[FIELDS[0]]).all()
    assert (rows["flags"] & int(TrackedFlag.STANDSTILL)).sum() > 50  # it stood, unmeasured
    assert np.isnan([fleet.calibration_fields("v")[f] for f in GYRO]).all()
