"""Wheel speed from encoder edges (method.md §2): methods by hand, round trips, latency, stops."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimator.config import ConfigError
from estimator.wheel_speed import (
    DirectWheelSpeed,
    WheelSpeedConfig,
    WheelSpeedMethod,
    WheelTracker,
    edge_angles,
    omega_at,
    omega_frequency,
    omega_k_tooth,
    query_many,
    stop_bound,
)

NS = 120
PITCH = 2 * math.pi / NS
T0 = 1_700_000_000_000_000_000


def edges_for(angle_of_t, t_end_s: float, n_max: int = 100_000) -> np.ndarray:
    """Edge times (int ns) where ``angle(t)`` crosses multiples of the tooth pitch."""
    t = np.linspace(0.0, t_end_s, 200_001)
    a = angle_of_t(t)
    k = np.arange(1, min(int(a[-1] / PITCH), n_max) + 1) * PITCH
    te = np.interp(k, a, t)
    return T0 + np.round(te * 1e9).astype(np.int64)


def test_k_tooth_by_hand() -> None:
    # 120 teeth, one edge every 10 ms: ω = 2π/(120·0.01) = 5.236 rad/s for any k.
    t = T0 + np.arange(10, dtype=np.int64) * 10_000_000
    for k in (1, 3, 9):
        w = omega_k_tooth(t, k, NS)
        assert w.shape == (10 - k,)
        assert w == pytest.approx(2 * math.pi / (NS * 0.01))


def test_frequency_by_hand() -> None:
    # edges every 8 ms; window (390 ms, 640 ms] holds the edges at 392 … 640 ms: 32 of them,
    # ω = 2π·32/(120·0.25) = 6.702 rad/s
    t = T0 + np.arange(100, dtype=np.int64) * 8_000_000
    q = np.array([t[80]])
    assert omega_frequency(t, q, 0.25, NS) == pytest.approx(2 * math.pi * 32 / (NS * 0.25))


def test_stop_bound_by_hand() -> None:
    assert stop_bound(T0, T0 + 500_000_000, NS) == pytest.approx(2 * math.pi / (NS * 0.5))


def test_edge_angles_with_direction() -> None:
    d = np.array([1, 1, -1, 1], dtype=np.int8)
    assert edge_angles(4, NS, d) == pytest.approx(PITCH * np.array([1, 2, 1, 2]))


@settings(max_examples=60, deadline=None)
@given(omega=st.floats(0.3, 150.0), phase=st.floats(0.0, 0.999))
def test_round_trip_constant_speed(omega: float, phase: float) -> None:
    # pulses from a wheel turning at ω → speed back within the edge-time quantisation (1 ns)
    n = 400
    t = T0 + np.round((np.arange(n) + phase) * PITCH / omega * 1e9).astype(np.int64)
    ang = edge_angles(n, NS)
    q = t[-1] + np.array([0, int(0.2 * PITCH / omega * 1e9)])
    r = omega_at(t, ang, q, WheelSpeedConfig(teeth_per_rev=NS))
    assert np.all(r.method == WheelSpeedMethod.PERIOD)
    assert r.omega_radps == pytest.approx(omega, rel=1e-4)


def test_latency_compensation_under_acceleration() -> None:
    # ω(t) = 2 + 1.5·t: the k-tooth average (linear fit) lags by α·(t − t_mid); the
    # quadratic fit evaluated at t does not.
    om0, alpha = 2.0, 1.5
    t_edges = edges_for(lambda t: om0 * t + 0.5 * alpha * t * t, 4.0)
    ang = edge_angles(t_edges.size, NS)
    q = T0 + np.arange(1_000_000_000, 3_900_000_000, 50_000_000, dtype=np.int64)
    true = om0 + alpha * (q - T0) * 1e-9
    err = {}
    for order in (1, 2):
        r = omega_at(t_edges, ang, q, WheelSpeedConfig(teeth_per_rev=NS, fit_order=order))
        err[order] = np.max(np.abs(r.omega_radps - true))
    # the uncompensated lag is about α·(window/2 + a fraction of a tooth) ≈ 0.2 rad/s
    assert err[1] > 0.1
    assert err[2] < 1e-3
    assert err[2] < err[1] / 100


def test_stopped_wheel_decays_to_zero() -> None:
    t = T0 + np.arange(50, dtype=np.int64) * 20_000_000  # 2π/(120·0.02) = 2.62 rad/s
    ang = edge_angles(50, NS)
    cfg = WheelSpeedConfig(teeth_per_rev=NS, stop_timeout_s=2.0)
    after = np.array([0.01, 0.1, 0.5, 1.0, 1.9, 2.1, 5.0])
    q = t[-1] + np.round(after * 1e9).astype(np.int64)
    r = omega_at(t, ang, q, cfg)
    bound = (1 + cfg.stop_bound_margin) * 2 * math.pi / (NS * after)
    assert r.omega_radps[0] == pytest.approx(2 * math.pi / (NS * 0.02), rel=1e-3)
    assert np.all(r.omega_radps[1:5] <= bound[1:5] + 1e-12)
    assert np.all(np.diff(r.omega_radps[1:]) <= 0)
    assert r.omega_radps[-2:] == pytest.approx([0.0, 0.0])


def test_restart_after_stop_ignores_edges_before_the_stop() -> None:
    fast = T0 + np.arange(40, dtype=np.int64) * 10_000_000
    restart = fast[-1] + 5_000_000_000 + np.arange(6, dtype=np.int64) * 100_000_000
    t = np.concatenate([fast, restart])
    ang = edge_angles(t.size, NS)
    r = omega_at(t, ang, restart[-1:], WheelSpeedConfig(teeth_per_rev=NS))
    assert r.omega_radps[0] == pytest.approx(2 * math.pi / (NS * 0.1), rel=1e-3)


def test_reverse_with_direction() -> None:
    n = 100
    t = T0 + np.arange(n, dtype=np.int64) * 10_000_000
    d = np.full(n, -1, dtype=np.int8)
    tr = WheelTracker(WheelSpeedConfig(teeth_per_rev=NS))
    tr.push(t, d)
    r = tr.query(t[-1:])
    assert r.omega_radps[0] == pytest.approx(-2 * math.pi / (NS * 0.01), rel=1e-6)


def test_without_direction_never_negative() -> None:
    # decelerating hard into a stop: the quadratic fit would overshoot below zero
    t_edges = edges_for(lambda t: 6.0 * t - 3.0 * t * t, 0.99)
    ang = edge_angles(t_edges.size, NS)
    q = t_edges[-1] + np.arange(0, 400_000_000, 20_000_000, dtype=np.int64)
    r = omega_at(t_edges, ang, q, WheelSpeedConfig(teeth_per_rev=NS))
    assert np.all(r.omega_radps >= 0.0)


def test_tracker_streaming_equals_batch_and_is_causal() -> None:
    om0, alpha = 4.0, -0.8
    t_edges = edges_for(lambda t: om0 * t + 0.5 * alpha * t * t, 4.5)
    ang = edge_angles(t_edges.size, NS)
    q = T0 + np.arange(200_000_000, 4_500_000_000, 50_000_000, dtype=np.int64)
    cfg = WheelSpeedConfig(teeth_per_rev=NS, tooth_calibration=False)
    batch = omega_at(t_edges, ang, q, cfg)
    tr = WheelTracker(cfg)
    out = []
    pushed = 0
    for qi in q:
        # push only edges up to the query time, in 100 ms packets: nothing from the future
        hi = int(np.searchsorted(t_edges, qi, side="right"))
        while pushed < hi:
            nxt = min(hi, pushed + 7)
            tr.push(t_edges[pushed:nxt])
            pushed = nxt
        out.append(tr.query(np.array([qi])))
    got = np.array([o.omega_radps[0] for o in out])
    assert got == pytest.approx(batch.omega_radps, rel=1e-9, abs=1e-12)
    assert tr.held_stamp_ns.size < t_edges.size  # history is trimmed


def test_tooth_calibration_learns_the_ring_pattern() -> None:
    # a ring with uneven teeth (1 % of the pitch, fixed per tooth), wheel at a steady 3 rad/s
    rng = np.random.default_rng(4)
    dev = rng.normal(0, 0.01, NS) * PITCH
    omega = 3.0
    k = np.arange(1, 3000)
    true_angle = k * PITCH + dev[k % NS]
    t_edges = T0 + np.round(true_angle / omega * 1e9).astype(np.int64)
    q = T0 + np.arange(100_000_000, int(t_edges[-1] - T0), 50_000_000, dtype=np.int64)
    errs = {}
    for cal in (False, True):
        tr = WheelTracker(WheelSpeedConfig(teeth_per_rev=NS, tooth_calibration=cal))
        out = []
        pushed = 0
        for qi in q:  # causal: edges up to the query time only
            hi = int(np.searchsorted(t_edges, qi, side="right"))
            tr.push(t_edges[pushed:hi])
            pushed = hi
            out.append(tr.query(np.array([qi])).omega_radps[0])
        late = np.array(out)[len(out) // 2 :]  # after about 10 turns
        errs[cal] = np.sqrt(np.mean((late / omega - 1) ** 2))
        if cal:
            learnt = tr.tooth_correction_rad
            # learnt pattern matches the ring's (up to the tooth numbering offset)
            best = max(np.corrcoef(np.roll(learnt, s), dev)[0, 1] for s in range(NS))
            assert best > 0.95
    assert errs[True] < errs[False] / 2


def test_query_many_equals_separate_queries() -> None:
    rng = np.random.default_rng(9)
    cfg = WheelSpeedConfig(teeth_per_rev=NS)
    profiles = [
        lambda t: 3.0 * t + 0.4 * t * t,  # accelerating
        lambda t: 2.0 * t + 0.1 * np.sin(3 * t),  # wobbling
        lambda t: np.minimum(t, 2.0) * 1.5,  # stops at 2 s
    ]
    edge_sets = [edges_for(p, 4.0) + rng.integers(0, 3000, 1) for p in profiles]
    edge_sets.append(np.zeros(0, dtype=np.int64))  # a wheel that never turned
    single = [WheelTracker(cfg) for _ in edge_sets]
    shared = [WheelTracker(cfg) for _ in edge_sets]
    for qi in T0 + np.arange(100_000_000, 4_000_000_000, 100_000_000, dtype=np.int64):
        q = np.array([qi - 50_000_000, qi])
        for e, a, b in zip(edge_sets, single, shared, strict=True):
            new = e[(e > (a.last_edge_ns or 0)) & (e <= qi)]
            a.push(new)
            b.push(new)
        one = [t.query(q) for t in single]
        many = query_many(shared, q)
        for r1, r2 in zip(one, many, strict=True):
            assert np.allclose(r1.omega_radps, r2.omega_radps, rtol=0, atol=1e-12, equal_nan=True)
            assert np.array_equal(r1.method, r2.method)


def test_tracker_skips_edges_back_in_time() -> None:
    tr = WheelTracker(WheelSpeedConfig(teeth_per_rev=NS))
    tr.push(T0 + np.array([0, 10, 20], dtype=np.int64) * 1_000_000)
    tr.push(T0 + np.array([15, 30], dtype=np.int64) * 1_000_000)
    assert tr.skipped == 1
    assert tr.last_edge_ns == T0 + 30_000_000


def test_frequency_method_at_high_edge_rate() -> None:
    cfg = WheelSpeedConfig(teeth_per_rev=NS, frequency_min_count=50, window_s=0.1)
    t = T0 + np.arange(2000, dtype=np.int64) * 1_000_000  # 1000 edges/s
    r = omega_at(t, edge_angles(t.size, NS), t[-1:], cfg)
    assert r.method[0] == WheelSpeedMethod.FREQUENCY
    assert r.omega_radps[0] == pytest.approx(2 * math.pi * 1000 / NS, rel=0.02)


def test_direct_speeds_hold_and_go_stale() -> None:
    d = DirectWheelSpeed(stale_s=0.5)
    d.push(T0 + np.array([0, 100_000_000]), np.array([[1.0, 2.0], [np.nan, 3.0]]))
    assert d.skipped == 1
    om, sd = d.query(T0 + np.array([-1, 50_000_000, 400_000_000, 700_000_000]))
    assert np.isnan(om[0]).all()
    assert om[1] == pytest.approx([1.0, 2.0])
    assert om[2] == pytest.approx([1.0, 2.0])
    assert np.isnan(om[3]).all() and np.isnan(sd[3]).all()


def test_config_validation() -> None:
    with pytest.raises(ConfigError):
        WheelSpeedConfig(teeth_per_rev=0)
    with pytest.raises(ConfigError):
        WheelSpeedConfig(min_edges=1)
    with pytest.raises(ConfigError):
        WheelSpeedConfig(max_edges=2, min_edges=3)
    with pytest.raises(ConfigError):
        WheelSpeedConfig(fit_order=3)
    with pytest.raises(ConfigError):
        WheelSpeedConfig(window_s=float("nan"))


def _uneven_ring(seed: int, omega: float, n_edges: int) -> np.ndarray:
    """Edge times of a ring with teeth off by 1 % of the pitch (fixed per tooth) at ``omega``."""
    dev = np.random.default_rng(seed).normal(0, 0.01, NS) * PITCH
    k = np.arange(1, n_edges)
    return T0 + np.round((k * PITCH + dev[k % NS]) / omega * 1e9).astype(np.int64)


def test_a_fit_through_three_edges_is_not_more_certain_than_the_ring() -> None:
    # Three edges fit a quadratic exactly: no residual to measure the error from. The std
    # must still carry the ring's angle noise (prior: 1 % of the pitch), not the jitter alone.
    cfg = WheelSpeedConfig(teeth_per_rev=NS, min_edges=3, window_s=0.01, tooth_calibration=False)
    omega = 1.0
    e = T0 + np.round(np.arange(1, 4) * PITCH / omega * 1e9).astype(np.int64)
    r = omega_at(e, edge_angles(3, NS), e[-1:], cfg)
    # the quadratic's slope at the last edge from edges at u = -1, -1/2, 0 has gain 3/span
    span_s = 2 * PITCH / omega
    # angle noise of the ring plus the edge-time jitter (timing_std_s at ω)
    sigma = math.hypot(0.01 * PITCH, omega * cfg.timing_std_s)
    floor = sigma * math.sqrt(1 + 16 + 9) / span_s  # ∂ω/∂θ_i = (1, -4, 3)/span
    assert float(r.std_radps[0]) == pytest.approx(floor, rel=1e-4)
    looser = WheelSpeedConfig(
        teeth_per_rev=NS, min_edges=3, window_s=0.01, tooth_calibration=False, angle_noise_rel=0.02
    )
    r2 = omega_at(e, edge_angles(3, NS), e[-1:], looser)
    assert float(r2.std_radps[0]) > 1.99 * floor


def test_calibration_measures_the_remaining_angle_noise() -> None:
    # Before calibration the fits are floored by the prior (1 % of the pitch) and their std is
    # consistent with the actual error; as the pattern is learnt the measured angle noise
    # falls far below the prior. Without calibration nothing is learnt: the prior stays.
    omega = 3.0
    t_edges = _uneven_ring(4, omega, 3000)
    tr = WheelTracker(WheelSpeedConfig(teeth_per_rev=NS))
    off = WheelTracker(WheelSpeedConfig(teeth_per_rev=NS, tooth_calibration=False))
    assert tr.angle_noise_rad == pytest.approx(0.01 * PITCH)
    q = T0 + np.arange(100_000_000, int(t_edges[-1] - T0), 50_000_000, dtype=np.int64)
    first_turn_s = 2 * math.pi / omega
    pushed, z = 0, []
    for qi in q:
        hi = int(np.searchsorted(t_edges, qi, side="right"))
        tr.push(t_edges[pushed:hi])
        off.push(t_edges[pushed:hi])
        pushed = hi
        r = tr.query(np.array([qi]))
        off.query(np.array([qi]))
        if (qi - T0) * 1e-9 < first_turn_s:
            z.append((r.omega_radps[0] - omega) / r.std_radps[0])
    assert 0.3 < float(np.sqrt(np.mean(np.square(z)))) < 2.0
    assert tr.angle_noise_rad < 0.1 * 0.01 * PITCH
    assert off.angle_noise_rad == pytest.approx(0.01 * PITCH)


def test_fast_wheel_fit_is_short_enough_to_follow_a_changing_acceleration() -> None:
    # Braking onset: the wheel's deceleration grows at 5 rad/s³ from 4.5 rad/s (86 edges/s).
    # The quadratic fit is exact under constant acceleration only; over the full 0.3 s window
    # (26 edges) the jerk biases it, the default 16 edges keep that bias small.
    w0, jerk = 4.5, -5.0

    def angle(t: np.ndarray) -> np.ndarray:
        return w0 * t + jerk * t**3 / 6.0

    e = edges_for(angle, 0.8)
    q = T0 + np.array([500_000_000, 600_000_000, 700_000_000], dtype=np.int64)
    truth = w0 + 0.5 * jerk * ((q - T0) * 1e-9) ** 2
    errs = {}
    for max_edges in (16, 64):
        cfg = WheelSpeedConfig(teeth_per_rev=NS, max_edges=max_edges, tooth_calibration=False)
        r = omega_at(e, edge_angles(e.shape[0], NS), q, cfg)
        errs[max_edges] = float(np.max(np.abs(r.omega_radps - truth)))
    assert WheelSpeedConfig().max_edges == 16
    assert errs[16] < 0.7 * errs[64]
    assert errs[16] / w0 < 0.008
