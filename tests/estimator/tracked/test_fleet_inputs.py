"""The batched input stage (``take_fleet``) equals each vehicle's own ``take`` exactly, on a
random fleet: IMU gaps, GNSS outages, bad fixes and two fixes a tick, odometer and sprocket
edge bursts and edges going backwards, a vehicle without sprockets, vehicles joining late;
and the segmented search equals ``np.searchsorted`` of each segment."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from estimator._arrays import IntArray
from estimator.config import OdometerConfig, SprocketConfig, TrackedConfig
from estimator.tracked import TrackedEstimatorConfig, segments
from estimator.tracked.fleet_inputs import take_fleet
from estimator.tracked.segments import Segments
from estimator.tracked.vehicle import TickInputs, VehicleInputs
from estimator.types import (
    GnssFix,
    GnssSample,
    ImuBatch,
    OdometerEdges,
    SprocketEdges,
    TrackSide,
)

MS = 1_000_000
START_NS = 1_700_000_000_000_000_000
PACKET_NS = 50 * MS


@dataclasses.dataclass
class _Drive:
    """One vehicle's random packets, made one packet interval at a time."""

    rng: np.random.Generator
    config: TrackedConfig
    joins_ns: int
    sprockets: bool
    gnss_20hz: bool
    speed_mps: float = 0.0
    imu_off_until_ns: int = 0
    gnss_off_until_ns: int = 0
    next_edge_ns: dict[int, int] = dataclasses.field(default_factory=dict)

    def packets(self, t0: int) -> list[object]:
        """Packets of ``(t0, t0 + PACKET_NS]``."""
        rng = self.rng
        if rng.random() < 0.05:  # a new speed: stops, creeping, fast
            self.speed_mps = float(rng.choice([0.0, 0.2, rng.uniform(0.5, 12.0)]))
        out: list[object] = []
        if t0 >= self.imu_off_until_ns:
            if rng.random() < 0.01:
                self.imu_off_until_ns = t0 + int(rng.uniform(0.5, 3.0) * 1e9)
            else:
                out.append(self._imu(t0))
        out += self._edges(t0, self.config.odometer.distance_per_edge_m, None)
        if self.sprockets:
            pitch = 2 * np.pi * self.config.sprocket.pitch_radius_m
            pitch /= self.config.sprocket.teeth_per_rev
            for side in (TrackSide.TRACK_LEFT, TrackSide.TRACK_RIGHT):
                out += self._edges(t0, pitch * (1.0 + 0.2 * int(side)), side)
        if ((t0 // PACKET_NS) % 2 == 0 or self.gnss_20hz) and t0 >= self.gnss_off_until_ns:
            if rng.random() < 0.005:
                self.gnss_off_until_ns = t0 + int(rng.uniform(1.0, 20.0) * 1e9)
            out.append(self._gnss(t0))
        return out

    def _imu(self, t0: int) -> ImuBatch:
        rng = self.rng
        stamps = t0 + np.arange(1, 6, dtype=np.int64) * 10 * MS + rng.integers(-200, 200, 5)
        if rng.random() < 0.02:  # a sample from before
            stamps[0] -= 100 * MS
        accel, gyro = rng.normal(0, 0.05, (5, 3)), rng.normal(0, 0.2, (5, 3))
        if rng.random() < 0.03:
            accel[rng.integers(5), 1] = np.nan
        return ImuBatch(stamps, accel, gyro)

    def _edges(self, t0: int, pitch_m: float, side: TrackSide | None) -> list[object]:
        """Edges at the speed with a 1 % jitter, and now and then a burst or a step back."""
        rng = self.rng
        key = -1 if side is None else int(side)
        if self.speed_mps <= 0.0:
            self.next_edge_ns[key] = t0 + PACKET_NS
            return []
        period_ns = pitch_m / self.speed_mps * 1e9
        first = max(self.next_edge_ns.get(key, t0), t0 + 1)
        n = max(int((t0 + PACKET_NS - first) // period_ns) + 1, 0)
        jitter = rng.normal(0.0, 0.01 * period_ns, n)
        stamps = np.sort(first + np.round(np.arange(n) * period_ns + jitter)).astype(np.int64)
        stamps = stamps[stamps <= t0 + PACKET_NS]
        self.next_edge_ns[key] = first + round(n * period_ns)
        if rng.random() < 0.02:  # a burst: many edges within a microsecond
            stamps = np.sort(np.concatenate([stamps, t0 + 7 * MS + rng.integers(0, 1000, 40)]))
        if rng.random() < 0.02 and stamps.size:  # edges going backwards
            stamps = np.concatenate([stamps, stamps[-1:] - 30 * MS])
        if not stamps.size:
            return []
        if side is None:
            return [OdometerEdges(stamps)]
        return [SprocketEdges(side, stamps)]

    def _gnss(self, t0: int) -> GnssSample:
        rng = self.rng
        fix = GnssFix.NONE if rng.random() < 0.05 else GnssFix.RTK_FIXED
        vel = (float(rng.normal(0, 5)), float(rng.normal(0, 5)), 0.0)
        if rng.random() < 0.03:
            vel = (float("nan"), vel[1], 0.0)
        lat = 48.0 + float(rng.normal(0, 1e-4))
        return GnssSample(
            t0 + PACKET_NS,
            vel,
            0.0,
            0.0,
            0.0,
            lat,
            11.0 + float(rng.normal(0, 1e-4)),
            500.0,
            fix,
            float(rng.choice([np.nan, 0.05])),
        )


def _drives(seed: int, n: int) -> list[_Drive]:
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        config = TrackedConfig(
            odometer=OdometerConfig(distance_per_edge_m=float(rng.uniform(0.005, 0.05))),
            sprocket=SprocketConfig(
                pitch_radius_m=float(rng.uniform(0.2, 0.5)), teeth_per_rev=int(rng.integers(9, 40))
            ),
        )
        joins = START_NS + int(rng.integers(0, 8)) * 1_000_000_000 * (k % 3 != 0)
        seeded = np.random.default_rng(rng.integers(1 << 31))
        out.append(_Drive(seeded, config, joins, sprockets=k != 1, gnss_20hz=k % 4 == 2))
    return out


def _assert_same(a: TickInputs, b: TickInputs) -> None:
    for f in dataclasses.fields(TickInputs):
        x, y = getattr(a, f.name), getattr(b, f.name)
        assert x.dtype == y.dtype and x.shape == y.shape, f.name
        np.testing.assert_array_equal(x, y, err_msg=f.name)


def _assert_same_buffers(a: VehicleInputs, b: VehicleInputs) -> None:
    assert (a.next_ns, a.counts, a.steady_s) == (b.next_ns, b.counts, b.steady_s)
    np.testing.assert_array_equal(a.last_gyro_radps, b.last_gyro_radps)
    np.testing.assert_array_equal(a.imu_ns, b.imu_ns)
    np.testing.assert_array_equal(a.imu, b.imu)
    assert a.gnss == b.gnss
    for x, y in zip((a.odometer, *a.sprockets), (b.odometer, *b.sprockets), strict=True):
        np.testing.assert_array_equal(x.stamps, y.stamps)


@pytest.mark.parametrize("seed", [3, 17])
def test_take_fleet_equals_each_vehicles_take(seed: int) -> None:
    cfg = TrackedEstimatorConfig()
    drives = _drives(seed, 12)
    alone = [VehicleInputs(d.config, cfg) for d in drives]
    fleet = [VehicleInputs(d.config, cfg) for d in drives]
    rng = np.random.default_rng(seed + 1000)
    calls = ticks_seen = 0
    for step in range(400):  # 20 s of sensor time, a call every packet
        t0 = START_NS + step * PACKET_NS
        due: list[tuple[int, IntArray]] = []
        for k, d in enumerate(drives):
            if t0 < d.joins_ns:
                continue
            for m in d.packets(t0):
                for inputs in (alone[k], fleet[k]):
                    _push(inputs, m)
            until = t0 + PACKET_NS - int(rng.integers(0, 400)) * MS  # catching up after a lag
            ticks = alone[k].due(until)
            np.testing.assert_array_equal(ticks, fleet[k].due(until))
            if ticks.size:
                due.append((k, ticks))
        if not due:
            continue
        got, starts = take_fleet([fleet[k] for k, _ in due], [t for _, t in due])
        for j, (k, ticks) in enumerate(due):
            rows = np.arange(starts[j], starts[j + 1])
            _assert_same(
                TickInputs(
                    **{f.name: getattr(got, f.name)[rows] for f in dataclasses.fields(TickInputs)}
                ),
                alone[k].take(ticks),
            )
            ticks_seen += ticks.size
        calls += 1
        for a, b in zip(alone, fleet, strict=True):
            _assert_same_buffers(a, b)
    assert calls > 300 and ticks_seen > 1500
    bad = [sum(v.counts.values()) + v.odometer.backwards for v in alone]
    assert min(bad) > 0  # every vehicle had bad input to count


def _push(inputs: VehicleInputs, m: object) -> None:
    if isinstance(m, ImuBatch):
        inputs.push_imu(m)
    elif isinstance(m, GnssSample):
        inputs.push_gnss(m)
    elif isinstance(m, OdometerEdges | SprocketEdges):
        inputs.push_edges(m)


@pytest.mark.parametrize(
    ("offset", "far", "stacked"),
    [(0, False, True), (START_NS, False, True), (-START_NS, False, False), (START_NS, True, False)],
)
def test_segmented_search_equals_each_segments_search(
    offset: int, far: bool, stacked: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Near zero and at epoch times (stacked into one search), negative values and keys too
    far apart to stack (each segment searched on its own)."""
    if stacked:  # the one-call path must answer on its own
        monkeypatch.setattr(segments, "_each", _not_called)
    rng = np.random.default_rng(5)
    parts = [np.sort(rng.integers(0, 10**6, rng.integers(0, 30))) + offset for _ in range(9)]
    segs = Segments([p.astype(np.int64) for p in parts])
    seg = rng.integers(0, len(parts), 400)
    keys = rng.integers(-1000, 10**6 + 1000, 400) + offset
    if far:
        keys[7] += 1 << 61
    float_keys = keys.astype(np.float64) + rng.choice([-0.5, 0.0, 0.5], 400)
    for side in ("left", "right"):
        got = segs.search(seg, keys, side)
        got_f = segs.search_float(seg, float_keys, side)
        for i in range(seg.size):
            part = parts[seg[i]]
            assert got[i] == np.searchsorted(part, keys[i], side=side)
            assert got_f[i] == np.searchsorted(part, float_keys[i], side=side)


def _not_called(*args: object) -> None:
    raise AssertionError("searched segment by segment")
