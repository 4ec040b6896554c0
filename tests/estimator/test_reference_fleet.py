"""The standalone reference-speed estimator: a GNSS-free speed from IMU and rim speed."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.catalog import spec_of
from estimator.reference_fleet import ReferenceSpeedFleet
from estimator.reference_speed_spec import ReferenceFlag
from estimator.sim import SimRun, first_ns, replay, simulate, truth_at
from estimator.types import GnssSample, Wheel, WheelEdges, WheelGap

START_NS = 1_700_000_000_000_000_000


def _run(name: str, seed: int = 1) -> SimRun:
    return simulate(name, seed=seed, start_ns=START_NS)


def _drive(fleet: ReferenceSpeedFleet, runs: dict[str, SimRun]) -> dict[str, np.ndarray]:
    for vid, run in runs.items():
        fleet.add_vehicle(vid, run.config)
    out: dict[str, list[np.ndarray]] = {vid: [] for vid in runs}
    streams = {vid: list(replay(run.measurements)) for vid, run in runs.items()}
    for k in range(max(len(s) for s in streams.values())):
        until = {}
        for vid, s in streams.items():
            if k < len(s):
                chunk, until[vid] = s[k]
                for m in chunk:
                    fleet.push(vid, m)
        for vid, rows in fleet.advance(until):
            out[vid].append(rows)
    return {vid: np.concatenate(parts) for vid, parts in out.items()}


def test_rows_follow_the_rim_speed_without_gnss() -> None:
    run = _run("figure_eight")
    rows = _drive(ReferenceSpeedFleet(), {"v": run})["v"]
    assert rows.dtype == spec_of("reference_speed").dtype
    assert set(np.diff(rows["stamp_ns"]).tolist()) == {100_000_000}
    t = rows["stamp_ns"]
    rim = (truth_at(run.truth, t, "rim_left_mps") + truth_at(run.truth, t, "rim_right_mps")) / 2
    ok = (rows["flags"] & ReferenceFlag.WHEEL_OK) != 0
    assert ok.mean() > 0.9
    err = rows["speed_mps"][ok] - rim[ok]
    assert np.sqrt(np.mean(err**2)) < 0.05  # m/s; the truth's rim speed is what it measures
    assert np.all(rows["speed_std_mps"][ok] > 0)


def test_gnss_changes_nothing() -> None:
    run = _run("figure_eight")
    gnss_free = [m for m in run.measurements if not isinstance(m, GnssSample)]
    a = _drive(ReferenceSpeedFleet(), {"v": run})["v"]
    fleet = ReferenceSpeedFleet()
    fleet.add_vehicle("v", run.config)
    parts = []
    for chunk, until in replay(gnss_free):
        for m in chunk:
            fleet.push("v", m)
        parts.extend(rows for _, rows in fleet.advance({"v": until}))
    b = np.concatenate(parts)
    assert len(a) == len(b)
    for name in a.dtype.names or ():
        np.testing.assert_array_equal(a[name], b[name])


def test_batched_equals_one_vehicle_at_a_time() -> None:
    runs = {
        "a": _run("figure_eight", 1),
        "b": _run("slope_wet_patch", 2),
        "c": _run("slow_creep", 3),
    }
    together = _drive(ReferenceSpeedFleet(), runs)
    for vid, run in runs.items():
        alone = _drive(ReferenceSpeedFleet(), {vid: run})[vid]
        np.testing.assert_allclose(
            alone["speed_mps"], together[vid]["speed_mps"], rtol=0, atol=1e-12
        )
        np.testing.assert_array_equal(alone["flags"], together[vid]["flags"])


def test_lost_wheel_data_gives_accelerometer_only_rows_then_recovers() -> None:
    run = _run("figure_eight")
    gap_at = START_NS + 20_000_000_000 - 5_000_000  # just before a tick
    measurements = list(run.measurements)
    cut = next(i for i, m in enumerate(measurements) if first_ns(m) > gap_at)
    # each wheel's third edge after the loss: the fits' min_edges
    resume = max(
        np.sort(
            np.concatenate(
                [
                    m.stamp_ns
                    for m in measurements[cut:]
                    if isinstance(m, WheelEdges) and m.wheel == w
                ]
            )
        )[2]
        for w in (Wheel.LEFT, Wheel.RIGHT)
    )
    fleet = ReferenceSpeedFleet()
    fleet.add_vehicle("v", run.config)
    rows = []
    pushed = 0
    for chunk, until in replay(measurements):
        for m in chunk:
            if pushed == cut:
                fleet.push("v", WheelGap(after_ns=gap_at))
            fleet.push("v", m)
            pushed += 1
        rows.extend(r for _, r in fleet.advance({"v": until}))
    out = np.concatenate(rows)
    waiting = (out["stamp_ns"] > gap_at) & (out["stamp_ns"] < resume)
    assert waiting.any()
    assert ((out["flags"][waiting] & ReferenceFlag.NO_WHEEL) != 0).all()
    after = out[out["stamp_ns"] >= resume]
    assert ((after["flags"] & ReferenceFlag.WHEEL_OK) != 0).all()


def test_ticks_follow_the_aligned_grid_and_unknown_vehicles_raise() -> None:
    run = _run("figure_eight")
    fleet = ReferenceSpeedFleet()
    fleet.add_vehicle("v", run.config)
    first_imu = min(int(m.stamp_ns[0]) for m in run.measurements if hasattr(m, "accel_mps2"))
    fleet.align_ticks("v", first_imu + 37_000_000)
    for chunk, until in replay(run.measurements):
        for m in chunk:
            fleet.push("v", m)
        got = fleet.advance({"v": until})
        if got:
            offset = got[0][1]["stamp_ns"] - first_imu - 37_000_000
            assert (offset % 100_000_000 == 0).all() and (offset >= 0).all()
    with pytest.raises(KeyError):
        fleet.push("nope", WheelGap(after_ns=0))
