"""The crawler simulator's stream clocks: each stream's offset from the IMU's clock, the
receiver's epochs on whole tenths of its own clock with jitter, and their own draws."""

from __future__ import annotations

import dataclasses
from functools import cache

import numpy as np

from estimator.sim.tracked import START_NS, TrackedRun, _random_sensors, simulate_tracked
from estimator.sim.tracked.route import CLOCK_KEYS, RANDOM_RANGES
from estimator.sim.tracked.sensors import CrawlerSensors, gnss_epochs_s
from estimator.types import GnssSample, ImuBatch, OdometerEdges, SprocketEdges, TrackSide

_ZERO = dict.fromkeys(CLOCK_KEYS, 0.0)


@cache
def _run(name: str, seed: int, **clocks: float) -> TrackedRun:
    base = simulate_tracked(name, seed)
    if not clocks:
        return base
    return simulate_tracked(name, seed, sensors=dataclasses.replace(base.sensors, **clocks))


def _fixes(run: TrackedRun) -> list[GnssSample]:
    return [m for _, m in run.measurements if isinstance(m, GnssSample) and np.isfinite(m.lat_deg)]


def _edges(run: TrackedRun, side: TrackSide | None) -> np.ndarray:
    parts = [
        m.stamp_ns
        for _, m in run.measurements
        if (side is None and isinstance(m, OdometerEdges))
        or (isinstance(m, SprocketEdges) and m.side == side)
    ]
    return np.concatenate(parts)


def _enu(run: TrackedRun, fixes: list[GnssSample]) -> np.ndarray:
    lat = np.array([f.lat_deg for f in fixes])
    lon = np.array([f.lon_deg for f in fixes])
    h = np.array([f.height_m for f in fixes])
    e, n, _ = run.frame.to_enu(lat, lon, h)
    return np.stack([e, n], axis=1)


def test_random_routes_draw_their_clocks_within_the_stated_ranges() -> None:
    drawn = {k: np.array([getattr(_random_sensors(s), k) for s in range(40)]) for k in CLOCK_KEYS}
    for key, values in drawn.items():
        lo, hi = RANDOM_RANGES[key]
        assert np.all((values >= lo) & (values <= hi)), key
        assert np.ptp(values) > 0.5 * (hi - lo), key  # drawn per route, over the range
    assert RANDOM_RANGES["gnss_clock_offset_s"] == (-0.1, 0.1)
    assert RANDOM_RANGES["odometer_clock_offset_s"] == (-0.02, 0.02)
    assert RANDOM_RANGES["sprocket_clock_offset_s"] == (-0.02, 0.02)
    # the named routes keep one clock for every stream
    named = _run("route_firm", 1).sensors
    assert all(getattr(named, k) == 0.0 for k in CLOCK_KEYS)
    assert all(getattr(CrawlerSensors(), k) == 0.0 for k in CLOCK_KEYS)


def test_without_clocks_every_fix_falls_on_a_whole_tenth_of_the_imus_clock() -> None:
    t = np.arange(1, 50) * 0.1
    stamp, taken = gnss_epochs_s(t, CrawlerSensors(), np.random.default_rng(0))
    assert stamp is t and taken is None  # the grid's own samples, not an interpolation
    stamps = np.array([f.stamp_ns for f in _fixes(_run("route_firm", 1))])
    assert np.all((stamps - START_NS) % 100_000_000 == 0)


def test_a_random_routes_clocks_leave_every_other_draw_alone() -> None:
    run = _run("random", 1001)
    zero = _run("random", 1001, **_ZERO)
    spec = run.sensors
    assert abs(spec.gnss_clock_offset_s) > 0.0 and spec.gnss_epoch_jitter_s > 0.0
    # the route, the truth and the IMU are those of the seed
    assert run.route == zero.route
    assert np.array_equal(run.truth.east_m, zero.truth.east_m)
    imu = [m for _, m in run.measurements if isinstance(m, ImuBatch)]
    imu0 = [m for _, m in zero.measurements if isinstance(m, ImuBatch)]
    assert len(imu) == len(imu0)
    assert all(np.array_equal(a.gyro_radps, b.gyro_radps) for a, b in zip(imu, imu0, strict=True))
    # the edges are the same edges, each stamped by its stream's offset
    for side, key in (
        (None, "odometer_clock_offset_s"),
        (TrackSide.TRACK_LEFT, "sprocket_clock_offset_s"),
        (TrackSide.TRACK_RIGHT, "sprocket_clock_offset_s"),
    ):
        a, b = _edges(run, side), _edges(zero, side)
        shift = round(getattr(spec, key) * 1e9)
        n = min(a.size, b.size)  # an edge may cross the run's last window
        assert n > 1000 and abs(a.size - b.size) <= 2
        assert np.abs(a[:n] - shift - b[:n]).max() <= 1  # ns: the stamps' rounding
    # as many epochs (an epoch at an outage's edge may fall on the other side of it)
    epochs = [m for _, m in run.measurements if isinstance(m, GnssSample)]
    epochs0 = [m for _, m in zero.measurements if isinstance(m, GnssSample)]
    assert len(epochs) == len(epochs0)
    assert abs(len(_fixes(run)) - len(_fixes(zero))) <= 2


def test_a_fix_is_where_the_antenna_was_at_its_stamp_less_the_receivers_offset() -> None:
    exact = {"gnss_pos_std_m": 0.0, "gnss_vel_std_mps": 0.0}
    base = simulate_tracked("random", 1002)
    spec = dataclasses.replace(base.sensors, **exact)
    clocked = simulate_tracked("random", 1002, sensors=spec)
    grid = simulate_tracked("random", 1002, sensors=dataclasses.replace(spec, **_ZERO))
    fixes, fixes0 = _fixes(clocked), _fixes(grid)
    stamps = np.array([f.stamp_ns for f in fixes]) - START_NS
    stamps0 = np.array([f.stamp_ns for f in fixes0]) - START_NS
    # stamped on whole tenths of the receiver's clock, each moved by its jitter
    jitter_s = (stamps - stamps0) * 1e-9
    sigma = spec.gnss_epoch_jitter_s
    assert abs(float(np.std(jitter_s)) / sigma - 1.0) < 0.1
    assert np.abs(jitter_s).max() <= 3.0 * sigma + 1e-9
    # taken at stamp − offset: the grid's antenna track, read there
    taken_s = stamps * 1e-9 - spec.gnss_clock_offset_s
    track = _enu(grid, fixes0)
    expected = np.stack([np.interp(taken_s, stamps0 * 1e-9, track[:, i]) for i in (0, 1)], axis=1)
    inner = (taken_s > stamps0[0] * 1e-9) & (taken_s < stamps0[-1] * 1e-9)
    inner[1:] &= np.diff(stamps0) == 100_000_000  # not across an outage
    got = _enu(clocked, fixes)
    assert np.abs(got - expected)[inner].max() < 0.02
    # and not where it was at the stamp: the offset is the lead times the speed
    moved = np.hypot(*(got - track).T)
    fast = moved > 5.0 * abs(spec.gnss_clock_offset_s)
    assert fast.mean() > 0.3
