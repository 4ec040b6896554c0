"""Sensor streams: determinism, encoder edges, GNSS outages and disturbances, IMU at rest."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimator.config import EncoderConfig, WheeledRearDriveConfig
from estimator.sim import SCENARIOS, completion_ns, simulate, truth_at
from estimator.sim.sensors import edge_times_s
from estimator.types import GnssFix, GnssSample, ImuBatch, Wheel, WheelEdges

START_NS = 1_700_000_000_000_000_000


def _gnss(run) -> list[GnssSample]:  # type: ignore[no-untyped-def]
    return [m for m in run.measurements if isinstance(m, GnssSample)]


def _edges(run, wheel: Wheel) -> np.ndarray:  # type: ignore[no-untyped-def]
    parts = [m.stamp_ns for m in run.measurements if isinstance(m, WheelEdges) and m.wheel == wheel]
    return np.concatenate(parts) if parts else np.zeros(0, dtype=np.int64)


def _same(a: object, b: object) -> bool:
    if isinstance(a, GnssSample):
        return repr(a) == repr(b)
    assert type(a) is type(b)
    for name in a.__slots__:  # type: ignore[attr-defined]
        x, y = getattr(a, name), getattr(b, name)
        if isinstance(x, np.ndarray):
            if not np.array_equal(x, y):
                return False
        elif x != y:
            return False
    return True


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_same_seed_same_run_other_seed_differs(name: str) -> None:
    kw = {"duration_s": 60.0} if "duration_s" in SCENARIOS[name].defaults else {}
    a = simulate(name, seed=11, start_ns=START_NS, **kw)
    b = simulate(name, seed=11, start_ns=START_NS, **kw)
    c = simulate(name, seed=12, start_ns=START_NS, **kw)
    assert a.truth.tobytes() == b.truth.tobytes()
    assert len(a.measurements) == len(b.measurements)
    assert all(_same(x, y) for x, y in zip(a.measurements, b.measurements, strict=True))
    assert np.array_equal(a.arrival_ns, b.arrival_ns)
    assert not np.array_equal(a.truth["slip_left_pct"], c.truth["slip_left_pct"], equal_nan=True)


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_stream_is_in_sensor_order_with_int_stamps(name: str) -> None:
    kw = {"duration_s": 60.0} if "duration_s" in SCENARIOS[name].defaults else {}
    run = simulate(name, seed=1, start_ns=START_NS, **kw)
    keys = [completion_ns(m) for m in run.measurements]
    assert keys == sorted(keys)
    assert keys[0] >= START_NS and keys[-1] <= run.end_ns
    for m in run.measurements:
        if isinstance(m, GnssSample):
            assert isinstance(m.stamp_ns, int)
        else:
            assert m.stamp_ns.dtype == np.int64
            assert np.all(np.diff(m.stamp_ns) >= 0)
    assert np.all(run.arrival_ns >= np.array(keys))
    # truth 100 Hz, moving wheels never roll backwards
    assert np.all(np.diff(run.truth["stamp_ns"]) == 10_000_000)
    assert np.all(run.truth["vl_mps"] >= 0) and np.all(run.truth["vr_mps"] >= 0)


@pytest.mark.parametrize("teeth", [1, 48, 120])
def test_edge_count_matches_integrated_angle(teeth: int) -> None:
    cfg = WheeledRearDriveConfig(encoder=EncoderConfig(teeth_per_rev=teeth))
    run = simulate("figure_eight", seed=2, start_ns=START_NS, config=cfg)
    t = (run.truth["stamp_ns"] - START_NS) * 1e-9
    for wheel, field in ((Wheel.LEFT, "omega_left_radps"), (Wheel.RIGHT, "omega_right_radps")):
        w = run.truth[field]
        angle = float(np.sum(0.5 * (w[1:] + w[:-1]) * np.diff(t)))
        n = _edges(run, wheel).size
        assert abs(n - angle * teeth / (2 * math.pi)) <= 1.5


def test_edge_times_hand_case() -> None:
    # constant 2π rad/s for 1 s, 4 teeth at 0, π/2, π, 3π/2, start angle 0.1 rad
    t = np.linspace(0.0, 1.0, 1001)
    angle = 2 * math.pi * t
    teeth = np.arange(4) * math.pi / 2
    got = edge_times_s(t, angle, teeth, 0.1)
    want = (np.array([1, 2, 3, 4]) * math.pi / 2 - 0.1) / (2 * math.pi)
    np.testing.assert_allclose(got, want, atol=1e-12)


def test_period_of_k_teeth_recovers_wheel_speed() -> None:
    run = simulate("paper_circle", seed=3, start_ns=START_NS)
    e = _edges(run, Wheel.RIGHT)
    e = e[e > START_NS + 7 * 10**9]  # steady circling
    ns = run.config.encoder.teeth_per_rev
    # one full revolution cancels the tooth-spacing pattern: ω = 2π / t_rev
    omega = 2 * math.pi / ((e[ns:] - e[:-ns]) * 1e-9)
    mid = (e[ns:] + e[:-ns]) // 2
    truth = truth_at(run.truth, mid, "omega_right_radps")
    assert np.max(np.abs(omega / truth - 1)) < 0.01
    # single-tooth periods carry the tooth pattern (≈ 1 % per tooth by default)
    one = 2 * math.pi / ns / (np.diff(e) * 1e-9)
    spread = np.std(one / truth_at(run.truth, e[1:], "omega_right_radps") - 1)
    assert 0.005 < spread < 0.03


def test_direction_given_when_encoder_is_quadrature() -> None:
    cfg = WheeledRearDriveConfig(encoder=EncoderConfig(has_direction=True))
    run = simulate("hard_braking", seed=1, start_ns=START_NS, config=cfg)
    packets = [m for m in run.measurements if isinstance(m, WheelEdges)]
    assert packets and all(p.direction is not None and np.all(p.direction == 1) for p in packets)
    run2 = simulate("hard_braking", seed=1, start_ns=START_NS)
    assert all(m.direction is None for m in run2.measurements if isinstance(m, WheelEdges))


def test_wheel_packets_stay_in_their_window() -> None:
    run = simulate("figure_eight", seed=4, start_ns=START_NS, wheel_latency_ms=7.0)
    for m, arrival in zip(run.measurements, run.arrival_ns, strict=True):
        if isinstance(m, WheelEdges):
            window = (m.stamp_ns - START_NS) // 100_000_000
            assert np.all(window == window[0])
            assert arrival == START_NS + (int(window[0]) + 1) * 100_000_000 + 7_000_000


@pytest.mark.parametrize("mode", ["no_fix", "missing"])
def test_gnss_outage_has_no_valid_velocity(mode: str) -> None:
    run = simulate("gnss_outage", seed=5, start_ns=START_NS, gnss_outage_mode=mode)
    t0, t1 = START_NS + 50 * 10**9, START_NS + 70 * 10**9
    inside = [g for g in _gnss(run) if t0 <= g.stamp_ns < t1]
    outside = [g for g in _gnss(run) if not t0 <= g.stamp_ns < t1]
    if mode == "missing":
        assert inside == []
    else:
        assert len(inside) == 200
        for g in inside:
            assert g.fix == GnssFix.NONE
            assert all(math.isnan(v) for v in g.vel_enu_mps)
            assert math.isnan(g.lat_deg)
    assert all(
        g.fix == GnssFix.RTK_FIXED and all(math.isfinite(v) for v in g.vel_enu_mps) for g in outside
    )
    valid = run.truth["gnss_valid"]
    ts = run.truth["stamp_ns"]
    assert not valid[(ts >= t0) & (ts < t1)].any()
    assert valid[(ts < t0) | (ts >= t1)].all()


def _forward_speed(g: GnssSample) -> float:
    ve, vn, vu = g.vel_enu_mps
    psi, th = g.heading_rad, g.pitch_rad
    return ve * math.sin(psi) * math.cos(th) + vn * math.cos(psi) * math.cos(th) + vu * math.sin(th)


def test_paper_straight_gnss_noise_and_step() -> None:
    run = simulate("paper_straight", seed=6, start_ns=START_NS)
    gnss = _gnss(run)
    assert np.all(np.diff([g.stamp_ns for g in gnss]) == 200_000_000)  # 5 Hz
    stamps = np.array([g.stamp_ns for g in gnss])
    vg = np.array([_forward_speed(g) for g in gnss])
    true = truth_at(run.truth, stamps, "vg_mps")
    # sample 70 (t = 14 s) carries the −1 m/s disturbance
    assert stamps[70] == START_NS + 14 * 10**9
    assert -1.25 < vg[70] - true[70] < -0.75
    cruise = (true > 2.9) & (np.arange(vg.size) != 70)
    rel = (vg[cruise] - true[cruise]) / true[cruise]
    assert np.max(np.abs(rel)) < 0.06 and np.std(rel) > 0.02  # ±5 % amplitude, uniform


def test_gnss_lever_arm_in_velocity() -> None:
    run = simulate(
        "paper_circle",
        seed=7,
        start_ns=START_NS,
        gnss_speed_noise_rel=0.0,
        gnss_vel_std_mps=0.0,
        gnss_speed_steps=(),
        gnss_heading_std_rad=0.0,
        gnss_pitch_std_rad=0.0,
    )
    gnss = _gnss(run)
    stamps = np.array([g.stamp_ns for g in gnss])
    vg = np.array([_forward_speed(g) for g in gnss])
    np.testing.assert_allclose(vg, truth_at(run.truth, stamps, "vg_mps"), atol=1e-9)


def test_gnss_outliers_latency_and_data_lag() -> None:
    base = {"gnss_speed_noise_rel": 0.0, "gnss_vel_std_mps": 0.0, "gnss_speed_steps": ()}
    run = simulate(
        "paper_circle",
        seed=8,
        start_ns=START_NS,
        gnss_outlier_prob=0.1,
        gnss_latency_ms=80.0,
        **base,
    )
    gnss = _gnss(run)
    stamps = np.array([g.stamp_ns for g in gnss])
    err = np.array([_forward_speed(g) for g in gnss]) - truth_at(run.truth, stamps, "vg_mps")
    big = np.abs(err) > 0.05
    assert 0.04 < big.mean() < 0.2
    arrivals = {id(m): a for m, a in zip(run.measurements, run.arrival_ns, strict=True)}
    assert all(arrivals[id(g)] == g.stamp_ns + 80_000_000 for g in gnss)
    lagged = simulate("paper_circle", seed=8, start_ns=START_NS, gnss_data_lag_ms=200.0, **base)
    g2 = _gnss(lagged)
    s2 = np.array([g.stamp_ns for g in g2])
    v2 = np.array([g.vel_enu_mps[0] for g in g2])
    np.testing.assert_allclose(
        v2[5:],
        np.array(
            [
                g.vel_enu_mps[0]
                for g in _gnss(simulate("paper_circle", seed=8, start_ns=START_NS, **base))
            ]
        )[4:-1],
        atol=1e-12,
    )
    assert s2[0] == START_NS


def test_a_single_antenna_receiver_reports_no_attitude_and_the_same_rest() -> None:
    dual = _gnss(simulate("figure_eight", seed=3, start_ns=START_NS))
    single = _gnss(simulate("figure_eight", seed=3, start_ns=START_NS, gnss_attitude=False))
    assert len(single) == len(dual)
    for s, d in zip(single, dual, strict=True):
        assert math.isnan(s.heading_rad) and math.isnan(s.pitch_rad) and math.isnan(s.roll_rad)
        assert s.vel_enu_mps == d.vel_enu_mps and s.lat_deg == d.lat_deg
    assert all(math.isfinite(d.pitch_rad) for d in dual if d.fix != GnssFix.NONE)


def test_imu_at_rest_reads_gravity_plus_bias() -> None:
    run = simulate(
        "hard_braking", seed=9, start_ns=START_NS, accel_std_mps2=0.0, accel_bias_walk_mps2=0.0
    )
    imu = [m for m in run.measurements if isinstance(m, ImuBatch)]
    assert all(len(m.stamp_ns) == 10 for m in imu[:-1])
    first = imu[0].accel_mps2
    bias = first[0] - np.array([0.0, 0.0, 9.80665])
    assert np.all(np.abs(bias) < 0.2) and np.any(bias != 0)
    np.testing.assert_allclose(first, np.tile(first[0], (10, 1)), atol=1e-12)


def test_unknown_override_and_scenario_are_refused() -> None:
    with pytest.raises(TypeError, match="unknown parameter"):
        simulate("figure_eight", seed=1, start_ns=START_NS, wheel_count=4)
    with pytest.raises(KeyError):
        simulate("moon_landing", seed=1, start_ns=START_NS)
    with pytest.raises(ValueError):
        simulate("figure_eight", seed=1, start_ns=START_NS, gnss_rate_hz=7.0)


def test_relative_imu_noise_scales_with_the_signal() -> None:
    run = simulate(
        "paper_straight", seed=10, start_ns=START_NS, accel_std_mps2=0.0, gyro_std_radps=0.0
    )
    imu = [m for m in run.measurements if isinstance(m, ImuBatch)]
    stamps = np.concatenate([m.stamp_ns for m in imu])
    accel = np.concatenate([m.accel_mps2 for m in imu])
    gyro = np.concatenate([m.gyro_radps for m in imu])
    pitch = truth_at(run.truth, stamps, "pitch_rad")
    a1 = truth_at(run.truth, stamps, "a1_mps2")
    standing = stamps < START_NS + 1_500_000_000
    np.testing.assert_allclose(accel[standing], [[0.0, 0.0, 9.80665]] * int(standing.sum()))
    strong = np.abs(a1) > 0.3
    rel = (accel[strong, 1] - 9.80665 * np.sin(pitch[strong]) - a1[strong]) / a1[strong]
    assert 0.025 < np.std(rel) < 0.035
    wz = truth_at(run.truth, stamps, "yaw_rate_radps")
    turning = np.abs(wz) > 0.02
    assert 0.015 < np.std((gyro[turning, 2] - wz[turning]) / wz[turning]) < 0.025


def test_a_generator_can_stand_in_for_the_seed() -> None:
    a = simulate("paper_straight", seed=np.random.default_rng(21), start_ns=START_NS)
    b = simulate("paper_straight", seed=np.random.default_rng(21), start_ns=START_NS)
    c = simulate("paper_straight", seed=21, start_ns=START_NS)
    assert a.truth.tobytes() == b.truth.tobytes() == c.truth.tobytes()


def test_heartbeats_fill_exactly_the_wheel_windows_without_an_edge() -> None:
    run = simulate("hard_braking", seed=4, start_ns=START_NS)  # stands still before and after
    window_ns = round(run.sensors.wheel_batch_ms * 1e6)
    n_windows = (run.end_ns - run.start_ns) // window_ns
    edges = np.concatenate([m.stamp_ns for m in run.measurements if isinstance(m, WheelEdges)])
    with_edges = set(((edges - run.start_ns) // window_ns).tolist())
    arrival, until = run.heartbeat_ns[:, 0], run.heartbeat_ns[:, 1]
    beats = ((until + 1 - run.start_ns) // window_ns - 1).tolist()
    assert len(beats) > 10
    assert sorted(set(beats) | (with_edges & set(range(n_windows)))) == list(range(n_windows))
    assert not set(beats) & with_edges
    assert np.all((until + 1 - run.start_ns) % window_ns == 0)  # a window's end - 1 ns
    assert np.all(arrival - until - 1 == round(run.sensors.wheel_latency_ms * 1e6))
    quiet = simulate("hard_braking", seed=4, start_ns=START_NS, wheel_heartbeats=False)
    assert quiet.heartbeat_ns.shape == (0, 2)
