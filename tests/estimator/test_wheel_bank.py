"""WheelBank / query_many against trackers queried one by one, each in a bank of its own (the
oracle: batching many wheels into one fit must not change any wheel's result)."""

from __future__ import annotations

import gc

import numpy as np
import pytest

from estimator.config import EncoderConfig, WheeledRearDriveConfig
from estimator.sim import simulate
from estimator.types import WheelEdges
from estimator.wheel_speed import (
    WheelBank,
    WheelSpeedConfig,
    WheelSpeedResult,
    WheelTracker,
    query_many,
)

NS = 120
T0 = 1_700_000_000_000_000_000
PITCH = 2 * np.pi / NS


def _packets(rng: np.random.Generator, kind: str, seconds: float = 12.0) -> list:
    """(arrival_ns, stamps, direction) packets of 100 ms for one synthetic wheel."""
    t = np.arange(0.0, seconds, 2e-4)
    if kind == "reverse":
        omega = 4.0 * np.sin(2 * np.pi * t / 5.0) + 0.5
    elif kind == "fast":  # ~700 edges/s: rings grow, the frequency config kicks in
        # (not faster: from about 80 rad/s with 120 teeth the tooth calibration amplifies
        # rounding, so no two differently-ordered computations agree to 1e-9 there)
        omega = 30.0 + 10.0 * np.sin(t)
    elif kind == "stop_go":
        omega = np.where((t % 6.0) < 3.0, 3.0, 0.0)
    else:
        omega = 2.0 + 0.5 * t
    ang = np.cumsum(omega) * 2e-4
    k = np.floor(ang / PITCH)
    at = np.flatnonzero(np.diff(k) != 0) + 1
    stamps = T0 + np.round(t[at] * 1e9).astype(np.int64) + rng.integers(0, 20_000, at.size)
    stamps = np.maximum.accumulate(stamps)
    d = np.sign(np.diff(k)[at - 1]).astype(np.int8) if kind == "reverse" else None
    win = (stamps - T0) // 100_000_000
    cuts = np.flatnonzero(np.diff(win)) + 1
    out = []
    for i, (s, w) in enumerate(zip(np.split(stamps, cuts), np.split(win, cuts), strict=True)):
        dd = None if d is None else d[np.searchsorted(stamps, s[0]) :][: s.size]
        if i % 23 == 7 and s.size > 2:  # an edge back in time now and then
            s = s.copy()
            s[1] = s[0] - 1_000
        out.append((T0 + (int(w[0]) + 1) * 100_000_000 + 3_000_000, s, dd))
    return out


def _sim_packets(name: str, seed: int, has_direction: bool) -> list[list]:
    run = simulate(
        name,
        seed=seed,
        start_ns=T0,
        config=WheeledRearDriveConfig(encoder=EncoderConfig(has_direction=has_direction)),
    )
    per: list[list] = [[], []]
    for arrival, m in run.in_arrival_order():
        if isinstance(m, WheelEdges) and arrival < T0 + 15_000_000_000:
            per[int(m.wheel)].append((arrival, m.stamp_ns, m.direction))
    return per


def _replay(
    feeds: list[list], old: list, new: list, interval_ms: int, ticks: int, phased: bool = False
):
    """Feed both implementations the same packets; yield their results per call. ``phased``:
    each tracker queried at its own times (the shared times moved by a per-tracker phase)."""
    ptr = [0] * len(feeds)
    step = interval_ms * 1_000_000
    now = T0
    while now < T0 + 13_000_000_000:
        now += step
        for i, feed in enumerate(feeds):
            while ptr[i] < len(feed) and feed[ptr[i]][0] <= now:
                _, s, d = feed[ptr[i]]
                old[i].push(s, d)
                new[i].push(s, d)
                ptr[i] += 1
        q = (now - 150_000_000 - np.arange(ticks)[::-1] * (step // ticks)).astype(np.int64)
        if phased:
            rows = q[None, :] + (np.arange(len(feeds)) * 7_777_777 % step)[:, None]
            yield [t.query(r) for t, r in zip(old, rows, strict=True)], query_many(new, rows)
        else:
            yield solo_query(old, q), query_many(new, q)


def solo(cfg: WheelSpeedConfig, n: int) -> list[WheelTracker]:
    """``n`` trackers, each in a bank of its own (never merged: see :func:`solo_query`)."""
    return [WheelTracker(cfg) for _ in range(n)]


def solo_query(trackers: list[WheelTracker], q: np.ndarray) -> list[WheelSpeedResult]:
    """Each tracker queried on its own."""
    return [t.query(q) for t in trackers]


def _assert_same(a: list[WheelSpeedResult], b: list[WheelSpeedResult]) -> float:
    worst = 0.0
    for r1, r2 in zip(a, b, strict=True):
        assert np.array_equal(r1.method, r2.method)
        assert np.array_equal(np.isnan(r1.omega_radps), np.isnan(r2.omega_radps))
        assert np.allclose(r1.omega_radps, r2.omega_radps, rtol=0, atol=1e-9, equal_nan=True)
        assert np.allclose(r1.std_radps, r2.std_radps, rtol=1e-8, atol=1e-12, equal_nan=True)
        d = np.abs(r1.omega_radps - r2.omega_radps)
        worst = max(worst, float(np.nanmax(d, initial=0.0)))
    return worst


@pytest.mark.parametrize(
    ("cfg", "interval_ms", "ticks", "phased"),
    [
        (WheelSpeedConfig(teeth_per_rev=NS), 50, 1, False),
        (WheelSpeedConfig(teeth_per_rev=NS), 200, 2, False),
        (WheelSpeedConfig(teeth_per_rev=NS, tooth_calibration=False, fit_order=1), 100, 2, False),
        (WheelSpeedConfig(teeth_per_rev=NS, frequency_min_count=40, max_edges=16), 100, 1, False),
        (WheelSpeedConfig(teeth_per_rev=NS), 100, 1, True),
        (WheelSpeedConfig(teeth_per_rev=NS), 200, 3, True),
    ],
)
def test_bank_equals_per_tracker_implementation(
    cfg: WheelSpeedConfig, interval_ms: int, ticks: int, phased: bool
) -> None:
    rng = np.random.default_rng(3)
    feeds = [_packets(rng, k) for k in ("reverse", "fast", "stop_go", "accel")]
    feeds += _sim_packets("field_work", 1, has_direction=True)
    feeds.append([])  # a wheel that never turns
    feeds.append([p for p in feeds[0] if p[0] > T0 + 6_000_000_000])  # starts late
    bank = WheelBank(cfg)
    new = [WheelTracker(cfg, bank) for _ in feeds]
    old = solo(cfg, len(feeds))
    worst = 0.0
    for old_res, new_res in _replay(feeds, old, new, interval_ms, ticks, phased):
        worst = max(worst, _assert_same(old_res, new_res))
    assert [t.skipped for t in new] == [t.skipped for t in old]
    assert sum(t.skipped for t in new) > 0
    for a, b in zip(new, old, strict=True):
        assert np.array_equal(a.held_stamp_ns, b.held_stamp_ns)  # same history kept
        assert np.allclose(a.tooth_correction_rad, b.tooth_correction_rad, atol=1e-12)
        assert a.calibrated_edges == b.calibrated_edges
    assert worst <= 1e-9


def test_trackers_of_separate_banks_merge_and_keep_their_state() -> None:
    cfg = WheelSpeedConfig(teeth_per_rev=NS)
    rng = np.random.default_rng(8)
    feeds = [_packets(rng, k) for k in ("reverse", "accel", "stop_go")]
    old = solo(cfg, len(feeds))
    new = [WheelTracker(cfg) for _ in feeds]  # one bank each
    assert len({id(t._bank) for t in new}) == 3
    ptr = [0] * len(feeds)
    for call in range(120):
        now = T0 + (call + 1) * 100_000_000
        for i, feed in enumerate(feeds):
            while ptr[i] < len(feed) and feed[ptr[i]][0] <= now:
                old[i].push(feed[ptr[i]][1], feed[ptr[i]][2])
                new[i].push(feed[ptr[i]][1], feed[ptr[i]][2])
                ptr[i] += 1
        q = np.array([now - 150_000_000], dtype=np.int64)
        if call < 40:  # calibrated and trimmed on their own first
            _assert_same([t.query(q) for t in old], [t.query(q) for t in new])
        else:  # then moved into one bank by query_many, state and all
            _assert_same(solo_query(old, q), query_many(new, q))
            assert len({id(t._bank) for t in new}) == 1
    assert [t.skipped for t in new] == [t.skipped for t in old]


def test_slots_are_reused_and_duplicates_answered() -> None:
    cfg = WheelSpeedConfig(teeth_per_rev=NS)
    bank = WheelBank(cfg)
    a = WheelTracker(cfg, bank)
    slot = a._slot
    del a
    gc.collect()
    b = WheelTracker(cfg, bank)
    assert b._slot == slot and b.skipped == 0 and b.last_edge_ns is None
    t = T0 + np.arange(200, dtype=np.int64) * 10_000_000
    b.push(t)
    r = query_many([b, b], t[-1:])
    assert r[0].omega_radps == pytest.approx(r[1].omega_radps)
    assert r[0].omega_radps[0] == pytest.approx(2 * np.pi / (NS * 0.01), rel=1e-6)


def test_bank_query_gives_arrays_per_slot() -> None:
    cfg = WheelSpeedConfig(teeth_per_rev=NS)
    bank = WheelBank(cfg)
    slots = [bank.add() for _ in range(3)]
    for i, s in enumerate(slots):
        bank.push(s, T0 + np.arange(100, dtype=np.int64) * (i + 1) * 10_000_000)
    q = np.array([T0 + 990_000_000], dtype=np.int64)
    r = bank.query(np.array(slots), q)
    assert r.omega_radps.shape == (3, 1)
    want = [2 * np.pi / (NS * 0.01 * (i + 1)) for i in range(3)]
    assert r.omega_radps[:, 0] == pytest.approx(want, rel=1e-6)


def test_churn_moves_and_compacts_rings_without_changing_results() -> None:
    # wheels come and go, rings grow (unqueried wheels hold every edge) and are abandoned:
    # the arena is compacted, and the survivors' speeds still equal those of trackers alone
    cfg = WheelSpeedConfig(teeth_per_rev=NS)
    bank = WheelBank(cfg)
    steady = [WheelTracker(cfg, bank) for _ in range(3)]
    oracle = solo(cfg, 3)
    period_ns = [9_000_000, 4_000_000, 23_000_000]
    for rnd in range(6):
        churn = [WheelTracker(cfg, bank) for _ in range(100)]
        for i, tr in enumerate(churn):
            tr.push(T0 + rnd * 10**9 + np.arange(1500, dtype=np.int64) * 600_000 + i)
        t = T0 + rnd * 10**9 + np.arange(0, 10**9, 100_000_000, dtype=np.int64)
        for q in t:
            for tr, old, per in zip(steady, oracle, period_ns, strict=True):
                e = np.arange(q - 100_000_000 + per, q + 1, per, dtype=np.int64)
                tr.push(e)
                old.push(e)
            qs = np.array([q - 30_000_000], dtype=np.int64)
            _assert_same([o.query(qs) for o in oracle], query_many(steady, qs))
        del churn
        gc.collect()
    assert bank.compactions > 0
    assert bank._slots <= 203  # removed slots were handed out again
