"""The shared sensor rows (:class:`FleetSensors`, every vehicle of a call read in one pass)
against the per-vehicle :class:`FrontEnd`'s own sensor reads, tick by tick, on random streams:
IMU, wheel and steering packets of random rates and sizes, GNSS epochs with and without a
heading and with outages, steering with outages longer than its timeout, wheels that start
late, a vehicle without steering, tick grids aligned or not, vehicles left out of calls;
packets pushed out of order are read sorted; a full row keeps its newest samples."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest

from estimator.friction.frontend import FrontEnd, FrontEndConfig
from estimator.friction.sensors import MAX_SAMPLES, FleetSensors, SensedTicks
from estimator.sim.four_wheel import random_config
from estimator.types import GnssSample, ImuBatch, SteeringAngles, WheelSpeeds4
from tests.estimator.friction._reference import TICK_NS, Reference

START_NS = 1_700_000_000_000_000_000
TIMEOUT_S = FrontEndConfig().gnss_timeout_s
STEER_TIMEOUT_S = FrontEndConfig().steer_timeout_s
Packet = ImuBatch | WheelSpeeds4 | SteeringAngles | GnssSample


def _stream(rng: np.random.Generator, rate_hz: float, start_s: float, end_s: float) -> np.ndarray:
    """Jittered sample times [ns] at about ``rate_hz``."""
    n = int((end_s - start_s) * rate_hz)
    t = start_s + (np.arange(n) + rng.uniform(0.0, 0.3, n)) / rate_hz
    return START_NS + np.round(t * 1e9).astype(np.int64)


def _packets(rng: np.random.Generator, vehicle: int, end_s: float) -> list[tuple[int, Packet]]:
    """One vehicle's packets keyed by their last stamp, in arrival order."""
    out: list[tuple[int, Packet]] = []
    imu = _stream(rng, rng.uniform(80, 220), rng.uniform(0.0, 0.3), end_s)
    out += _split(
        rng,
        imu,
        lambda s: ImuBatch(s, rng.normal(0, 1, (s.size, 3)), rng.normal(0, 0.1, (s.size, 3))),
    )
    wheels = _stream(
        rng, rng.uniform(40, 120), rng.uniform(0.0, 1.0 if vehicle % 3 else 0.1), end_s
    )
    out += _split(rng, wheels, lambda s: WheelSpeeds4(s, rng.uniform(5, 30, (s.size, 4))))
    if vehicle % 4 != 3:  # one in four without steering
        steer = _stream(rng, rng.uniform(20, 100), rng.uniform(0.0, 0.5), end_s)
        phase = (steer - START_NS) * 1e-9 % 2.0
        steer = steer[(phase < 1.0) | (phase > 1.0 + 4 * STEER_TIMEOUT_S)]  # outages
        out += _split(rng, steer, lambda s: SteeringAngles(s, rng.normal(0, 0.3, s.size)))
    for t in _stream(rng, rng.uniform(5, 20), rng.uniform(0.0, 0.5), end_s):
        if TIMEOUT_S * 1.5 < (t - START_NS) * 1e-9 % 3.0 < TIMEOUT_S * 4:  # outages
            continue
        heading = math.nan if rng.random() < 0.2 else rng.uniform(-math.pi, math.pi)
        vel = (rng.normal(0, 10), rng.normal(0, 10), 0.0)
        roll, pitch = rng.normal(0, 0.05, 2)
        out.append((int(t), GnssSample(int(t), vel, heading, pitch, roll, 48.0, 11.0, 500.0)))
    out.sort(key=lambda p: p[0])
    return out


def _split(
    rng: np.random.Generator, stamps: np.ndarray, make: Callable[[np.ndarray], Packet]
) -> list[tuple[int, Packet]]:
    """``stamps`` cut into packets of 1-12 samples."""
    out: list[tuple[int, Packet]] = []
    k = 0
    while k < stamps.size:
        n = int(rng.integers(1, 13))
        part = stamps[k : k + n]
        out.append((int(part[-1]), make(part)))
        k += n
    return out


class _Reference(Reference):
    """One vehicle's ticks read by :class:`FrontEnd`'s sensor methods on the same grid."""

    def record(self, t: int) -> None:
        f = self.front
        window = f._imu_window(t)
        f._latest(t)
        f.last_tick_ns = t
        if window is None or not np.isfinite(f.omega).all():
            return
        vel = f._gnss_velocity(t)
        g = f.gnss
        fresh = vel is not None and g is not None
        att = (
            (g.heading_rad, g.pitch_rad, g.roll_rad) if fresh and g is not None else (math.nan,) * 3
        )
        accel, gyro, lag_s = window
        self.ticks[t] = (
            accel,
            gyro,
            f.omega.copy(),
            np.array(f._steer_angles(t)[0]),
            np.array(vel if vel is not None else (math.nan, math.nan)),
            np.array(att),
            np.array(g.stamp_ns if fresh and g is not None else 0),
            np.array(f._gnss_recent()),
            np.array(lag_s),
        )


def _got(
    sensed: SensedTicks, counts: np.ndarray, ids: list[int]
) -> dict[int, dict[int, tuple[np.ndarray, ...]]]:
    """The read's rows per vehicle, by tick."""
    out: dict[int, dict[int, tuple[np.ndarray, ...]]] = {}
    row = 0
    fields = [f for f in SensedTicks.__dataclass_fields__ if f != "t_ns"]
    for vid, n in zip(ids, counts.tolist(), strict=True):
        for r in range(row, row + n):
            out.setdefault(vid, {})[int(sensed.t_ns[r])] = tuple(
                getattr(sensed, f)[r] for f in fields
            )
        row += n
    return out


def _assert_same(got: tuple[np.ndarray, ...], want: tuple[np.ndarray, ...], what: str) -> None:
    for k, (a, b) in enumerate(zip(got, want, strict=True)):
        np.testing.assert_allclose(
            np.asarray(a, float),
            np.asarray(b, float),
            rtol=0,
            atol=1e-12,
            err_msg=f"{what} field {k}",
        )


def _run(
    seed: int, vehicles: int, seconds: float
) -> tuple[dict[int, _Reference], dict[int, dict[int, tuple[np.ndarray, ...]]], FleetSensors]:
    rng = np.random.default_rng(seed)
    config = random_config(rng)
    sensors = FleetSensors(TICK_NS, TIMEOUT_S, STEER_TIMEOUT_S)
    refs: dict[int, _Reference] = {}
    streams = {v: _packets(rng, v, seconds) for v in range(vehicles)}
    got: dict[int, dict[int, tuple[np.ndarray, ...]]] = {v: {} for v in range(vehicles)}
    for v in range(vehicles):
        sensors.add(v)
        aligned = START_NS + int(rng.integers(0, TICK_NS)) if v % 2 else None
        if aligned is not None:
            sensors.align(v, aligned)
        refs[v] = _Reference(FrontEnd(config, FrontEndConfig(), TICK_NS * 1e-9), aligned)
    cursor = dict.fromkeys(streams, 0)
    for now in range(START_NS, START_NS + round(seconds * 1e9), 25_000_000):
        for v, packets in streams.items():
            while cursor[v] < len(packets) and packets[cursor[v]][0] <= now:
                m = packets[cursor[v]][1]
                cursor[v] += 1
                refs[v].push(m)
                _push(sensors, v, m)
        ids = [v for v in streams if rng.random() < 0.7]  # some left out of each call
        until = {v: now - int(rng.integers(0, 80_000_000)) for v in ids}
        sensed, counts = sensors.read(
            np.array(ids, dtype=np.int64), np.array([until[v] for v in ids], dtype=np.int64)
        )
        assert counts.sum() == sensed.t_ns.size
        for v, ticks in _got(sensed, counts, ids).items():
            got[v].update(ticks)
        for v in ids:
            refs[v].advance(until[v])
    return refs, got, sensors


def _push(sensors: FleetSensors, slot: int, m: Packet) -> None:
    if isinstance(m, ImuBatch):
        sensors.push_imu(slot, m)
    elif isinstance(m, WheelSpeeds4):
        sensors.push_wheels(slot, m)
    elif isinstance(m, SteeringAngles):
        sensors.push_steering(slot, m)
    else:
        sensors.push_gnss(slot, m)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_fleet_sensors_read_what_the_front_end_reads(seed: int) -> None:
    refs, got, sensors = _run(seed, vehicles=8, seconds=6.0)
    fresh = 0
    for v, ref in refs.items():
        assert list(got[v]) == list(ref.ticks), v
        assert len(ref.ticks) > 100, v
        for t, want in ref.ticks.items():
            _assert_same(got[v][t], want, f"vehicle {v} at {t}")
            fresh += bool(np.isfinite(want[4]).all())
    assert fresh > 50  # fresh GNSS velocities are compared, not only their absence
    assert sensors.dropped == 0


def test_packets_pushed_out_of_order_are_read_sorted() -> None:
    """IMU, wheel and steering packets shuffled between two calls read as those in order."""
    rng = np.random.default_rng(7)
    streams = {v: _packets(rng, v, 4.0) for v in range(4)}
    ordered, shuffled = (
        FleetSensors(TICK_NS, TIMEOUT_S, STEER_TIMEOUT_S),
        FleetSensors(TICK_NS, TIMEOUT_S, STEER_TIMEOUT_S),
    )
    for v in streams:
        ordered.add(v)
        shuffled.add(v)
    cursor = dict.fromkeys(streams, 0)
    ids = np.arange(len(streams), dtype=np.int64)
    moved = read = 0
    for now in range(START_NS, START_NS + 4_000_000_000, 100_000_000):
        for v, packets in streams.items():
            batch = []
            while cursor[v] < len(packets) and packets[cursor[v]][0] <= now:
                batch.append(packets[cursor[v]][1])
                cursor[v] += 1
            for m in batch:
                _push(ordered, v, m)
            late = [m for m in batch if not isinstance(m, GnssSample)]
            order = rng.permutation(len(late))
            moved += int((order != np.arange(len(late))).any())
            for m in [late[i] for i in order] + [m for m in batch if isinstance(m, GnssSample)]:
                _push(shuffled, v, m)
        until = np.full(ids.size, now - 30_000_000, dtype=np.int64)
        a, b = ordered.read(ids, until), shuffled.read(ids, until)
        np.testing.assert_array_equal(a[1], b[1])
        for f in SensedTicks.__dataclass_fields__:
            np.testing.assert_array_equal(getattr(a[0], f), getattr(b[0], f), err_msg=f)
        read += a[0].t_ns.size
    assert moved > 50 and read > 500


def test_a_full_row_keeps_its_newest_samples() -> None:
    """Wheel speeds without an IMU fill the row up to ``MAX_SAMPLES`` (the oldest dropped and
    counted); once the IMU comes, the first tick reads the latest wheel speeds before it, and
    the rows' capacity shrinks once they are read."""
    sensors = FleetSensors(TICK_NS, TIMEOUT_S, STEER_TIMEOUT_S)
    for slot in range(3):
        sensors.add(slot)
    n = MAX_SAMPLES + 500
    stamps = START_NS + 10_000_000 * np.arange(n, dtype=np.int64)
    omega = np.arange(4 * n, dtype=float).reshape(n, 4)
    for k in range(0, n, 7):
        sensors.push_wheels(1, WheelSpeeds4(stamps[k : k + 7], omega[k : k + 7]))
        sensed, counts = sensors.read(np.array([0, 1]), np.array([stamps[k]] * 2))
        assert not counts.any()
    assert sensors.wheels.count[1] == MAX_SAMPLES
    assert sensors.wheels.capacity == MAX_SAMPLES
    assert sensors.dropped == 500
    t = stamps[-1] + 1_000_000
    imu = np.array([t - 5_000_000, t])
    sensors.push_imu(1, ImuBatch(imu, np.ones((2, 3)), np.zeros((2, 3))))
    sensors.align(1, int(t))
    sensed, counts = sensors.read(np.array([1]), np.array([t]))
    assert counts.tolist() == [1]
    np.testing.assert_array_equal(sensed.omega_radps, omega[-1:])
    np.testing.assert_array_equal(sensed.accel_mps2, [[1.0, 1.0, 1.0]])
    assert sensors.wheels.capacity == MAX_SAMPLES // 2  # read: every row short again
