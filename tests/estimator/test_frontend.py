"""Fleet front end: batch invariance across vehicles, joins and call intervals; the tilt track
(pitch and roll) through turns and outages; the "latest at or before" join; slot reuse."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimator.base import Measurement
from estimator.config import NoiseConfig, VehicleConfig, WheeledRearDriveConfig
from estimator.geo import EnuFrame
from estimator.mdsf import MdsfConfig, MdsfFleet, MdsfMode
from estimator.mdsf.frontend import FleetFrontEnd, _asof
from estimator.mdsf.model import MdsfObs
from estimator.sim import SimRun, simulate, truth_at
from estimator.sim.drives import draw_drive
from estimator.types import ESTIMATE_DTYPE, GnssSample, ImuBatch, WheelEdges, WheelSpeeds
from estimator.wheel_speed import WheelSpeedConfig

START = 1_767_225_600_000_000_000
S = 1_000_000_000


@dataclasses.dataclass
class _Vehicle:
    config: VehicleConfig
    measurements: list[Measurement]
    join_ns: int
    tick_anchor_ns: int | None = None


def _stamp(m: Measurement) -> int:
    return int(m.stamp_ns if isinstance(m, GnssSample) else np.asarray(m.stamp_ns)[-1])


def _vehicle(name: str, seed: int, join_s: float, variant: str = "", **kw: Any) -> _Vehicle:
    start = START + round(join_s * S)
    if variant == "single_antenna":  # no receiver attitude: heading from the velocity
        kw = {**kw, "gnss_attitude": False}
    sim: SimRun = simulate(name, seed=seed, start_ns=start, **kw)
    ms: list[Measurement] = list(sim.measurements)
    if variant == "direct":  # CAN wheel speeds (with every IMU batch) instead of edges
        out: list[Measurement] = []
        for m in ms:
            if isinstance(m, WheelEdges):
                continue
            out.append(m)
            if isinstance(m, ImuBatch):
                t = np.asarray(m.stamp_ns, dtype=np.int64)[-1:]
                om = [truth_at(sim.truth, t, f"omega_{w}_radps")[0] for w in ("left", "right")]
                out.append(WheelSpeeds(t, np.array([om])))
        ms = out
    return _Vehicle(dataclasses.replace(sim.config, noise=sim.sensor_noise), ms, start)


def _drive(
    vehicles: dict[str, _Vehicle], step_ns: int, config: MdsfConfig | None = None
) -> tuple[dict[str, np.ndarray], dict[str, dict[str, int]]]:
    """Push each vehicle's data in sensor order and advance every ``step_ns`` to a horizon
    0.2 s behind (at most to their last data); vehicles join when the clock reaches their
    first data."""
    fleet = MdsfFleet(config)
    end = max(_stamp(v.measurements[-1]) for v in vehicles.values()) + S
    pos = dict.fromkeys(vehicles, 0)
    out: dict[str, list[np.ndarray]] = {vid: [] for vid in vehicles}
    now = START
    while now < end:
        now += step_ns
        until = {}
        for vid, v in vehicles.items():
            if now < v.join_ns:
                continue
            if vid not in fleet.vehicle_ids():
                fleet.add_vehicle(vid, v.config)
                if v.tick_anchor_ns is not None:
                    fleet.align_ticks(vid, v.tick_anchor_ns)
            i = pos[vid]
            while i < len(v.measurements) and _stamp(v.measurements[i]) <= now:
                fleet.push(vid, v.measurements[i])
                i += 1
            pos[vid] = i
            until[vid] = min(now - 200_000_000, _stamp(v.measurements[-1]))
        for vid, rows in fleet.advance(until):
            out[vid].append(rows)
    rows = {vid: np.concatenate(p) for vid, p in out.items()}
    return rows, {vid: fleet.counters(vid) for vid in vehicles}


def _assert_same_rows(a: np.ndarray, b: np.ndarray) -> None:
    assert a.shape == b.shape and a.shape[0] > 0
    assert np.array_equal(a["stamp_ns"], b["stamp_ns"])
    assert np.array_equal(a["flags"], b["flags"])
    for name in ESTIMATE_DTYPE.names or ():
        assert np.allclose(a[name], b[name], rtol=0, atol=1e-9, equal_nan=True), name


def test_each_vehicle_gets_the_rows_it_gets_alone_joining_late_at_any_call_interval() -> None:
    fleet = {
        "a": _vehicle("hard_braking", 1, 0.0, cycles=1),
        "b": _vehicle("figure_eight", 2, 3.05, laps=1),
        "c": _vehicle("paper_straight", 3, 7.3, "single_antenna"),
        "d": _vehicle("hard_braking", 4, 1.5, "direct", cycles=1),
        "e": _vehicle("slope_wet_patch", 5, 0.02),
    }
    together, counts = _drive(fleet, 70_000_000)
    for vid, v in fleet.items():
        for step_ms in (100, 200):
            alone, alone_counts = _drive({vid: v}, step_ms * 1_000_000)
            _assert_same_rows(together[vid], alone[vid])
            assert counts[vid] == alone_counts[vid]


def test_ticks_on_each_vehicles_own_phase_equal_the_vehicle_alone() -> None:
    """Vehicles whose tick grids are put on their first IMU batch's end (different phases)
    are batched together, and each gets exactly what it gets alone."""
    fleet = {
        "a": _vehicle("hard_braking", 1, 0.013, cycles=1),
        "b": _vehicle("figure_eight", 2, 3.071, laps=1),
        "c": _vehicle("slope_wet_patch", 5, 0.046),
        "d": _vehicle("hard_braking", 4, 1.5, "direct", cycles=1),
    }
    for v in fleet.values():
        first_imu = next(m for m in v.measurements if isinstance(m, ImuBatch))
        v.tick_anchor_ns = int(first_imu.stamp_ns[-1])
    together, counts = _drive(fleet, 70_000_000)
    tick = MdsfConfig().tick_ns
    phases = set()
    for vid, v in fleet.items():
        assert v.tick_anchor_ns is not None
        stamps = together[vid]["stamp_ns"]
        assert np.all((stamps - v.tick_anchor_ns) % tick == 0)  # on the vehicle's own grid
        phases.add(v.tick_anchor_ns % tick)
        alone, alone_counts = _drive({vid: v}, 100_000_000)
        _assert_same_rows(together[vid], alone[vid])
        assert counts[vid] == alone_counts[vid]
    assert len(phases) == len(fleet)  # four grids of different phase


def test_paper_mode_is_batch_invariant_too() -> None:
    cfg = MdsfConfig(mode=MdsfMode.PAPER)
    fleet = {
        "a": _vehicle("paper_straight", 6, 0.0),
        "b": _vehicle("paper_circle", 7, 2.5, "single_antenna"),
    }
    together, _ = _drive(fleet, 50_000_000, cfg)
    for vid, v in fleet.items():
        alone, _ = _drive({vid: v}, 150_000_000, cfg)
        _assert_same_rows(together[vid], alone[vid])


def test_a_reused_slot_starts_clean() -> None:
    v = _vehicle("hard_braking", 8, 0.0, cycles=1)
    other = _vehicle("figure_eight", 9, 0.0, laps=1)
    fleet = MdsfFleet()
    fleet.add_vehicle("old", other.config)
    for m in other.measurements[:200]:  # buffered, never advanced
        fleet.push("old", m)
    fleet.remove_vehicle("old")
    fleet.add_vehicle("v", v.config)
    for m in v.measurements:
        fleet.push("v", m)
    ((_, rows),) = fleet.advance({"v": _stamp(v.measurements[-1])})
    alone, _ = _drive({"v": v}, 100_000_000)
    n = alone["v"].shape[0]
    _assert_same_rows(rows[:n], alone["v"])


def _still_on(alpha_rad: float, psi: np.ndarray) -> np.ndarray:
    """Specific force of a body standing on a plane of slope ``α``, turned ``Ψ`` (CCW) from
    the contour with its right side down: gravity's reaction ``g·(−sin φ·cos θ, sin θ,
    cos φ·cos θ)`` with ``sin θ = sin α·sin Ψ`` and ``sin φ·cos θ = sin α·cos Ψ``."""
    s = math.sin(alpha_rad)
    return 9.80665 * np.stack(
        [-s * np.cos(psi), s * np.sin(psi), np.full_like(psi, math.cos(alpha_rad))], axis=1
    )


def test_the_tilt_turns_with_the_heading_on_a_side_slope() -> None:
    """A U-turn on a plane of slope α = 0.1 rad begun along the contour (roll α, pitch 0), the
    receiver's attitude at the start only. The body turns about the plane's normal, its own Z
    axis, so the gyros read ``(0, 0, r)``; the tilt must follow the plane: ``θ = asin(sin α·sin
    Ψ)``, pitch α a quarter turn in, roll −α at the end (a roll held from the fix read α
    throughout and put ``r·sin α`` into the pitch rate: 0.31 rad of pitch at the end)."""
    alpha, rate = 0.1, 0.4
    fe = FleetFrontEnd(MdsfConfig(mode=MdsfMode.PRODUCT), WheelSpeedConfig())
    fe.add(0, WheeledRearDriveConfig())
    fe.push(0, GnssSample(START, (0.0, 0.0, 0.0), 0.0, 0.0, alpha, 52.0, 5.0, 10.0))
    t_ns = START + np.arange(round(math.pi / rate * 100) + 1) * (S // 100)
    psi = rate * (t_ns - START) * 1e-9
    gyro = np.zeros((t_ns.shape[0], 3))
    gyro[:, 2] = rate
    fe.push(0, ImuBatch(t_ns, _still_on(alpha, psi), gyro))
    ticks = fe.assemble(np.array([0]), np.array([t_ns[-1]]))
    assert ticks is not None
    inp = ticks.inputs
    turned = rate * (inp.stamp_ns - START) * 1e-9
    pitch = np.arcsin(math.sin(alpha) * np.sin(turned))
    roll = np.arcsin(math.sin(alpha) * np.cos(turned) / np.cos(pitch))
    ok = inp.imu_ok
    assert ok.sum() >= 75 and turned[ok][-1] > 3.1
    np.testing.assert_allclose(inp.attitude[ok, 1], pitch[ok], atol=1e-3)
    np.testing.assert_allclose(inp.attitude[ok, 2], roll[ok], atol=1e-3)


def test_the_roll_gyros_bias_is_learnt_and_holds_the_roll_without_fixes() -> None:
    """Driving straight on a bank (roll 0.05 rad) with a roll gyro biased by 0.003 rad/s: the
    GNSS roll of 60 s teaches the track the bias, so through the 20 s without fixes that follow
    the roll stays put (an unknown bias would carry it 0.06 rad away)."""
    alpha, bias = 0.05, 0.003
    fe = FleetFrontEnd(MdsfConfig(mode=MdsfMode.PRODUCT), WheelSpeedConfig())
    fe.add(0, WheeledRearDriveConfig())
    for m in _fixes_along(0.0, 0.0, [0.2] * 601, [0.0] * 601, set(), roll_rad=alpha):
        fe.push(0, m)
    t_ns = START + np.arange(8001) * (S // 100)
    gyro = np.zeros((t_ns.shape[0], 3))
    gyro[:, 1] = bias
    fe.push(0, ImuBatch(t_ns, _still_on(alpha, np.zeros(t_ns.shape[0])), gyro))
    ticks = fe.assemble(np.array([0]), np.array([t_ns[-1]]))
    assert ticks is not None
    inp = ticks.inputs
    assert fe.roll_gyro_bias[0] == pytest.approx(bias, rel=0.05)
    after = (inp.stamp_ns > START + 60 * S) & inp.imu_ok
    assert after.sum() >= 190
    assert np.abs(inp.attitude[after, 2] - alpha).max() < 0.005
    assert np.abs(inp.attitude[after, 1]).max() < 0.005


def test_a_nan_roll_rate_keeps_the_sample_as_no_roll_rate() -> None:
    """An IMU whose roll axis reads NaN: its samples still give the forward acceleration and the
    pitch and yaw rates (none skipped), the roll taken as not turning: the same inputs as a
    roll gyro reading 0."""
    sim = simulate("paper_circle", seed=2, start_ns=START, duration_s=12.0)

    def inputs(roll_rate: float) -> tuple[Any, dict[str, int]]:
        fe = FleetFrontEnd(MdsfConfig(mode=MdsfMode.PRODUCT), WheelSpeedConfig())
        fe.add(0, sim.config)
        for m in sim.measurements:
            if isinstance(m, ImuBatch):
                gyro = np.array(m.gyro_radps, dtype=np.float64)
                gyro[:, 1] = roll_rate
                m = ImuBatch(m.stamp_ns, m.accel_mps2, gyro)
            fe.push(0, m)
        ticks = fe.assemble(np.array([0]), np.array([sim.end_ns]))
        assert ticks is not None
        return ticks.inputs, fe.counts(0)

    nan, nan_counts = inputs(math.nan)
    zero, _ = inputs(0.0)
    assert nan_counts["skipped_imu"] == 0
    assert nan.imu_ok.mean() > 0.99
    np.testing.assert_array_equal(nan.z, zero.z)
    np.testing.assert_array_equal(nan.attitude, zero.attitude)


def _one_antenna_circle(speed_mps: float, rate_radps: float, n: int) -> list[GnssSample]:
    """10 Hz fixes of a receiver without attitude (heading, pitch, roll NaN) on a level circle
    driven counter-clockwise at ``speed_mps`` and ``rate_radps`` (0: straight north)."""
    frame = EnuFrame(52.0, 5.0, 10.0)
    out = []
    for k in range(n):
        t = 0.1 * k
        psi = -rate_radps * t  # heading, clockwise from north
        if rate_radps:
            e = speed_mps / rate_radps * (math.cos(psi) - 1.0)
            north = -speed_mps / rate_radps * math.sin(psi)
        else:
            e, north = 0.0, speed_mps * t
        lat, lon, h = frame.to_geodetic(e, north, 0.0)
        vel = (speed_mps * math.sin(psi), speed_mps * math.cos(psi), 0.0)
        out.append(GnssSample(START + k * S // 10, vel, math.nan, math.nan, math.nan, lat, lon, h))
    return out


def _one_antenna_drive(
    speed_mps: float, rate_radps: float, accel_mps2: np.ndarray, gyro_radps: np.ndarray
) -> tuple[FleetFrontEnd, Any, np.ndarray]:
    """20 s of a receiver without attitude (:func:`_one_antenna_circle`) and a 100 Hz IMU that
    reads ``accel_mps2`` and ``gyro_radps`` (shape ``(3,)``) throughout: the front end, its tick
    inputs and which ticks have IMU data after the first 5 s."""
    n = 200
    fe = FleetFrontEnd(MdsfConfig(mode=MdsfMode.PRODUCT), WheelSpeedConfig())
    fe.add(0, WheeledRearDriveConfig())
    for m in _one_antenna_circle(speed_mps, rate_radps, n):
        fe.push(0, m)
    t_ns = START + np.arange(10 * (n - 1) + 1) * (S // 100)
    k = t_ns.shape[0]
    fe.push(0, ImuBatch(t_ns, np.tile(accel_mps2, (k, 1)), np.tile(gyro_radps, (k, 1))))
    ticks = fe.assemble(np.array([0]), np.array([t_ns[-1]]))
    assert ticks is not None
    late = (ticks.inputs.stamp_ns > START + 5 * S) & ticks.inputs.imu_ok
    assert late.sum() >= 140
    return fe, ticks.inputs, late


def test_the_tilt_variance_grows_from_the_last_fix() -> None:
    """``TickInputs.tilt_var``: a receiver without attitude whose fixes stop at 10 s while the
    IMU goes on to 20 s. Up to the last fix the pitch and roll variance stay at the fixes'
    level; after it they grow with the gyro biases' uncertainty, every tick."""
    fe = FleetFrontEnd(MdsfConfig(mode=MdsfMode.PRODUCT), WheelSpeedConfig())
    fe.add(0, WheeledRearDriveConfig())
    for m in _one_antenna_circle(2.5, 0.0, 100):
        fe.push(0, m)
    t_ns = START + np.arange(2001) * (S // 100)
    accel = _still_on(0.0, np.zeros(1))[0]
    fe.push(0, ImuBatch(t_ns, np.tile(accel, (2001, 1)), np.zeros((2001, 3))))
    ticks = fe.assemble(np.array([0]), np.array([t_ns[-1]]))
    assert ticks is not None
    inp = ticks.inputs
    assert inp.tilt_var is not None and inp.tilt_var.shape == (inp.m, 2)
    t = (inp.stamp_ns - START) / S
    before, after = inp.tilt_var[(t > 5) & (t < 9.9)], inp.tilt_var[t > 10.5]
    assert np.isfinite(before).all() and np.isfinite(after).all()
    assert (np.diff(after, axis=0) > 0).all()
    assert (after[-1] > 2.0 * before.max(axis=0)).all()


@pytest.mark.parametrize(
    ("speed_mps", "rate_radps", "bank_rad"),
    [(0.0, 0.0, 0.08), (2.5, 0.0, -0.05), (2.5, 0.3, 0.0)],
    ids=["standing_on_a_bank", "straight_on_a_bank", "level_circle"],
)
def test_without_a_receiver_roll_the_lateral_accelerometer_gives_it(
    speed_mps: float, rate_radps: float, bank_rad: float
) -> None:
    """A receiver without attitude: the roll comes from the lateral specific force less the
    centripetal acceleration, ``sin φ = −(f_x + v·ωz)/(g·cos θ)``. On a bank the track finds
    the bank's roll; on a level circle (``f_x = −v·ωz = −0.75 m/s²``, 4.4° if read as roll)
    none. Before, the roll of such a receiver was 0 whatever the ground."""
    accel = _still_on(bank_rad, np.zeros(1))[0]
    accel[0] -= speed_mps * rate_radps  # centripetal, towards the centre (left)
    _, inp, late = _one_antenna_drive(
        speed_mps, rate_radps, accel, np.array([0.0, 0.0, rate_radps])
    )
    assert np.abs(inp.attitude[late, 2] - bank_rad).max() < 0.004
    assert np.abs(inp.attitude[late, 1]).max() < 0.004  # level: no pitch


def test_standing_without_a_receiver_pitch_the_forward_accelerometer_gives_it() -> None:
    """A receiver without attitude on a vehicle standing nose up on a 0.06 rad slope, its pitch
    gyro biased by 0.002 rad/s: the velocity gives no pitch below 0.5 m/s, so the forward
    specific force does (``sin θ = f̄_y/g`` while standing); the pitch is the slope's and the
    gyro's bias is learnt. Before, the pitch stayed level and then drifted with the bias
    (a gravity leak of 0.6 m/s² into the speed filter at the first metre)."""
    slope, bias = 0.06, 0.002
    accel = 9.80665 * np.array([0.0, math.sin(slope), math.cos(slope)])
    fe, inp, late = _one_antenna_drive(0.0, 0.0, accel, np.array([bias, 0.0, 0.0]))
    assert np.abs(inp.attitude[late, 1] - slope).max() < 0.004
    assert fe.pitch_gyro_bias[0] == pytest.approx(bias, rel=0.1)


@pytest.mark.parametrize(
    ("attitude", "pitch_max_deg"), [(True, 1.0), (False, 3.0)], ids=["dual_antenna", "one_antenna"]
)
def test_an_outage_through_a_headland_turn_on_a_bank_keeps_speed_and_slip(
    attitude: bool, pitch_max_deg: float
) -> None:
    """``field_work`` on a 6° bank with GNSS lost from 30 to 60 s, a U-turn inside: the filter's
    speed, the slip and the pitch hold through it. Measured, receiver with attitude: slip 2.3 pp
    RMS, speed 0.10 m/s and pitch 0.5° at worst (with the roll held from the last fix the speed
    ran to 64 m/s); one antenna, the roll from the lateral accelerometer: 2.3 pp, 0.17 m/s,
    2.2° (with roll 0: 43 m/s)."""
    sim = simulate(
        "field_work",
        seed=1,
        start_ns=START,
        duration_s=80.0,
        bank_roll_deg=6.0,
        gnss_outages=((30.0, 60.0),),
        gnss_attitude=attitude,
    )
    vehicle = _Vehicle(sim.config, list(sim.measurements), START)
    rows = _drive({"v": vehicle}, S // 10, MdsfConfig(mode=MdsfMode.PRODUCT))[0]["v"]
    st = rows["stamp_ns"]
    t = (st - START) * 1e-9
    assert abs(np.sum(truth_at(sim.truth, st[(t >= 30) & (t < 60)], "yaw_rate_radps"))) * 0.1 > 3.0
    w = (t >= 30) & (t < 65) & (truth_at(sim.truth, st, "v0_mps") > 0.5)
    slip = np.concatenate(
        [
            rows[f"slip_{s}_pct"][w] - truth_at(sim.truth, st[w], f"slip_{s}_pct")
            for s in ("left", "right")
        ]
    )
    assert np.isfinite(slip).mean() > 0.99
    assert np.sqrt(np.nanmean(slip**2)) < 4.5
    assert np.abs(rows["v0_mps"][w] - truth_at(sim.truth, st[w], "v0_mps")).max() < 0.3
    pitch_err = rows["pitch_rad"][w] - truth_at(sim.truth, st[w], "pitch_rad")
    assert np.abs(pitch_err).max() < math.radians(pitch_max_deg)


# -- "latest at or before" ---------------------------------------------------------------------


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.tuples(st.integers(0, 3), st.integers(-5, 5)), max_size=30),
    st.lists(st.tuples(st.integers(0, 3), st.integers(-6, 6)), max_size=30),
)
def test_asof_is_searchsorted_per_row(a: list[tuple[int, int]], b: list[tuple[int, int]]) -> None:
    a.sort()  # rows grouped, keys sorted within a row (as the front end's queues)
    row_a = np.array([r for r, _ in a], dtype=np.int64)
    key_a = np.array([k for _, k in a], dtype=np.int64)
    row_b = np.array([r for r, _ in b], dtype=np.int64)
    key_b = np.array([k for _, k in b], dtype=np.int64)
    got = _asof(row_a, key_a, row_b, key_b)
    for i, (r, k) in enumerate(b):
        mine = np.flatnonzero(row_a == r)
        j = int(np.searchsorted(key_a[mine], k, side="right")) - 1
        assert got[i] == (mine[j] if j >= 0 else -1)


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.tuples(st.integers(0, 3), st.integers(-5, 5)), max_size=30),
    st.lists(st.tuples(st.integers(0, 3), st.integers(-6, 6)), max_size=30),
    st.sampled_from([0, 1_767_225_600_000_000_000]),
)
def test_asof_in_push_order_is_the_last_in_key_then_index_order(
    a: list[tuple[int, int]], b: list[tuple[int, int]], base_ns: int
) -> None:
    a.sort(key=lambda rk: rk[0])  # rows grouped, keys in push order (fixes may go back in time)
    row_a = np.array([r for r, _ in a], dtype=np.int64)
    key_a = np.array([k + base_ns for _, k in a], dtype=np.int64)
    row_b = np.array([r for r, _ in b], dtype=np.int64)
    key_b = np.array([k + base_ns for _, k in b], dtype=np.int64)
    got = _asof(row_a, key_a, row_b, key_b)
    for i, (r, k) in enumerate(b):
        cands = [(ka, j) for j, (ra, ka) in enumerate(a) if ra == r and ka <= k]
        assert got[i] == (max(cands)[1] if cands else -1)


def test_malformed_gnss_is_counted_not_raised_and_counts_are_current_before_advance() -> None:
    v = _vehicle("hard_braking", 10, 0.0, cycles=1)
    fleet = MdsfFleet()
    fleet.add_vehicle("v", v.config)
    gnss = next(m for m in v.measurements if isinstance(m, GnssSample))
    fleet.push("v", dataclasses.replace(gnss, vel_enu_mps=(1.0, 2.0)))  # type: ignore[arg-type]
    fleet.push("v", dataclasses.replace(gnss, vel_enu_mps=(np.nan, 0.0, 0.0)))
    imu = next(m for m in v.measurements if isinstance(m, ImuBatch))
    bad = np.array(imu.accel_mps2, dtype=float)
    bad[0, 1] = np.inf
    fleet.push("v", ImuBatch(imu.stamp_ns, bad, imu.gyro_radps))
    before = fleet.counters("v")
    assert before["skipped_gnss"] == 1 and before["skipped_imu"] == 1  # checked on asking
    fleet.advance({"v": _stamp(v.measurements[-1])})
    after = fleet.counters("v")
    assert after["skipped_gnss"] == 2 and after["skipped_imu"] == 1  # NaN velocity: when used


# -- along-track distance from RTK positions ---------------------------------------------------


def _fixes_along(
    heading_rad: float,
    pitch_rad: float,
    steps_m: list[float],
    side_m: list[float],
    skip: set[int],
    roll_rad: float = 0.0,
) -> list[GnssSample]:
    """10 Hz RTK-fixed samples of an antenna moving ``steps_m[k]`` along the body's forward axis
    (heading ``ψ``, pitch ``θ``, roll ``φ`` as given) and ``side_m[k]`` sideways (body X) per
    epoch; epochs in ``skip`` are left out."""
    frame = EnuFrame(52.0, 5.0, 10.0)
    fwd = np.array(
        [
            math.sin(heading_rad) * math.cos(pitch_rad),
            math.cos(heading_rad) * math.cos(pitch_rad),
            math.sin(pitch_rad),
        ]
    )
    right = np.array([math.cos(heading_rad), -math.sin(heading_rad), 0.0])
    p = np.zeros(3)
    out = []
    for k, (ds, dx) in enumerate(zip(steps_m, side_m, strict=True)):
        p = p + ds * fwd + dx * right
        if k in skip:
            continue
        lat, lon, h = frame.to_geodetic(p[0], p[1], p[2])
        vel = tuple(float(v) for v in 10.0 * ds * fwd)
        out.append(
            GnssSample(
                START + k * S // 10,
                (vel[0], vel[1], vel[2]),
                heading_rad,
                pitch_rad,
                roll_rad,
                float(lat),
                float(lon),
                float(h),
                vel_std_mps=0.03,
            )
        )
    return out


def test_distance_sums_the_forward_displacement_by_hand() -> None:
    """Heading 30°, pitch 0.02 rad, 0.2 m per 0.1 s along the body axis plus 5 cm sideways per
    epoch (side-slip): the distance grows by exactly 0.2 m a tick (eq. (1) on the
    displacement removes the sideways part); the IMU point's distance is the antenna's plus
    ``h1·θ = 1.6·0.02 = 0.032 m`` (the tracked pitch: no IMU, so the fixes' 0.02 rad). Its
    variance is the position noise (0.015 m)² plus ``h1²`` times the tracked pitch's variance
    (``pitch_std² = 0.005²`` after the first fix). Epochs 5-16 missing (1.2 s >
    ``gnss_distance_gap_s``): the fix at epoch 17 starts a new chain, whose offset continues
    from the last distance."""
    cfg = MdsfConfig(gnss_distance_gap_s=1.0)
    fe = FleetFrontEnd(cfg, WheelSpeedConfig())
    veh = dataclasses.replace(WheeledRearDriveConfig(), noise=NoiseConfig(gnss_pos_std_m=0.015))
    fe.add(0, veh)
    n = 22
    for m in _fixes_along(math.radians(30.0), 0.02, [0.2] * n, [0.05] * n, set(range(5, 17))):
        fe.push(0, m)
    ticks = fe.assemble(np.array([0]), np.array([START + (n - 1) * S // 10]))
    assert ticks is not None
    t = ticks.inputs
    k = ((t.stamp_ns - START) // (S // 10)).astype(int)
    ok = t.dist_ok
    assert np.array_equal(k[ok], [*range(5), *range(17, n)])
    d = t.dist_m[ok]
    h1_theta = 1.6 * 0.02
    assert np.allclose(d[:5], 0.2 * np.arange(5) + h1_theta, atol=1e-6)  # chain from fix 0
    assert np.allclose(d[5:], 0.2 * 4 + 0.2 * np.arange(5) + h1_theta, atol=1e-6)
    assert np.array_equal(t.dist_restart[ok], [True, False, False, False, False] * 2)
    # position noise plus the lever arm's share of the tracked pitch's variance, which the
    # first fix sets to pitch_std² and later fixes shrink
    var = t.dist_var[ok]
    assert var[0] == pytest.approx(0.015**2 + (1.6 * 0.005) ** 2)
    assert np.all((var > 0.015**2) & (var <= var[0] + 1e-15))
    # the chain carries over to the next assembly: one more fix continues it
    for m in _fixes_along(math.radians(30.0), 0.02, [0.2] * (n + 1), [0.0] * (n + 1), set())[n:]:
        fe.push(0, m)
    more = fe.assemble(np.array([0]), np.array([START + n * S // 10]))
    assert more is not None
    assert more.inputs.dist_ok[-1] and not more.inputs.dist_restart[-1]
    assert more.inputs.dist_m[-1] == pytest.approx(d[-1] + 0.2, abs=1e-6)


def _swaying_mast_vg_error(attitude: bool) -> np.ndarray:
    """GNSS speed error per tick with a fix (``z[:, VG]`` against the antenna's true forward
    speed) on drive 0 of seed 1 (2.6 m mast, cab swaying 2 Hz ±2° in pitch and ±0.4° in roll,
    1-2.8 m/s) over its first 60 s, without the outage, with every clock right."""
    d = draw_drive(1, 0)
    knobs = {
        **d.overrides,
        "duration_s": 60.0,
        "gnss_outages": (),
        "clock_offset_ms": (0.0, 0.0, 0.0),
        "gnss_outlier_prob": 0.0,
        "gnss_attitude": attitude,
    }
    sim = simulate("random_drive", seed=d.sim_seed, start_ns=START, config=d.config(), **knobs)
    fe = FleetFrontEnd(MdsfConfig(mode=MdsfMode.PRODUCT), WheelSpeedConfig())
    fe.add(0, dataclasses.replace(sim.config, noise=sim.sensor_noise))
    for m in sim.measurements:
        fe.push(0, m)
    ticks = fe.assemble(np.array([0]), np.array([sim.end_ns]))
    assert ticks is not None
    inp = ticks.inputs
    use = inp.gnss_ok & (truth_at(sim.truth, inp.stamp_ns, "v0_mps") > 0.5)
    assert use.sum() > 400
    return np.asarray(inp.z[use, MdsfObs.VG] - truth_at(sim.truth, inp.stamp_ns[use], "vg_mps"))


@pytest.mark.parametrize(
    ("attitude", "mean_mps", "slow_rms_mps"),
    [(True, 0.01, 0.025), (False, 0.025, 0.05)],
    ids=["dual_antenna", "one_antenna"],
)
def test_a_receiver_without_heading_on_a_swaying_mast_gives_the_forward_speed(
    attitude: bool, mean_mps: float, slow_rms_mps: float
) -> None:
    """The antenna of a 2.6 m mast swaying 2 Hz moves ±1.2 m/s along and ±0.2 m/s across the
    body: its own course swings and, near 1 m/s, turns round, and the velocity projected on
    it reads ``|v|``: +3.7 cm/s on average over these 60 s, where a receiver with a heading
    gets +0.5 cm/s (1.4 cm/s RMS over 2 s). With ``O``'s course (yaw rate integrated, pulled to
    the velocity less the lever arm's) a receiver without one gets +1.7 cm/s (3.5 cm/s RMS
    over 2 s; the antenna's own course is kept where the lever arm's speed is under a tenth
    of the antenna's)."""
    err = _swaying_mast_vg_error(attitude)
    slow = np.convolve(err, np.ones(20) / 20, mode="valid")
    assert abs(float(err.mean())) < mean_mps
    assert float(np.sqrt(np.mean(slow**2))) < slow_rms_mps
