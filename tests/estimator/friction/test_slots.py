"""The fleet's per-slot arrays: the informed window against a per-vehicle deque, slot reuse."""

from __future__ import annotations

from collections import deque

import numpy as np

from estimator.config import Wheeled4wdSteeredConfig
from estimator.friction.filter import FilterConfig, FilterState, ProductState, initial_state
from estimator.friction.slots import FleetSlots


def _deque_informed(window: deque[tuple[bool, float]], ok: bool, mu: float, spread: float) -> bool:
    """The per-vehicle rule: a full window, every tick ok, μ's range below ``spread`` of μ."""
    window.append((ok, mu))
    if len(window) < (window.maxlen or 1) or not all(o for o, _ in window):
        return False
    mus = [m for _, m in window]
    return (max(mus) - min(mus)) / mu < spread


def test_informed_window_equals_the_per_vehicle_rule() -> None:
    rng = np.random.default_rng(7)
    slots = FleetSlots(len(ProductState), window=5)
    config = Wheeled4wdSteeredConfig()
    for slot in range(6):
        slots.reset(slot, config)
    oracle = {slot: deque[tuple[bool, float]](maxlen=5) for slot in range(6)}
    informed_seen = 0
    for tick in range(400):
        if tick == 200:  # a vehicle replaced in its slot starts an empty window
            slots.reset(3, config)
            oracle[3].clear()
        part = np.flatnonzero(rng.random(6) < 0.7)
        ok = rng.random(part.size) < 0.9
        mu = 0.8 + rng.normal(0.0, 0.004, part.size)
        got = slots.informed(part, ok, mu, 0.03)
        want = [
            _deque_informed(oracle[int(s)], bool(o), float(m), 0.03)
            for s, o, m in zip(part, ok, mu, strict=True)
        ]
        assert got.tolist() == want
        informed_seen += int(got.sum())
    assert informed_seen > 50  # the case was exercised both ways


def test_states_take_the_prior_for_fresh_slots_and_keep_the_rest() -> None:
    cfg = FilterConfig()
    config = Wheeled4wdSteeredConfig()
    slots = FleetSlots(len(ProductState), window=3)
    for slot in range(12):  # past the first growth
        slots.reset(slot, config)
    s = np.array([10, 2, 7])
    tyres, _ = slots.constants(s, np.full((3, 4), config.tyre.kz_npm))
    fz = np.full((3, 4), 4000.0)
    prior = initial_state(cfg, tyres, fz)
    st = slots.states(s, prior, np.ones(3, dtype=bool))
    np.testing.assert_array_equal(st.x, prior.x)
    moved = FilterState(st.x + 0.1, st.s * 2.0, st.fz_prev_n + 1.0, st.nis + 3.0)
    slots.keep(s, moved)
    fresh = np.array([False, True, False])
    again = slots.states(s, FilterState(*(a[fresh] for a in (st.x, st.s, fz, st.nis))), fresh)
    np.testing.assert_array_equal(again.x[[0, 2]], moved.x[[0, 2]])
    np.testing.assert_array_equal(again.x[1], prior.x[1])
    np.testing.assert_array_equal(again.nis, [3.0, 0.0, 3.0])
    assert slots.has_state[s].all() and not slots.has_state[[0, 1, 11]].any()
