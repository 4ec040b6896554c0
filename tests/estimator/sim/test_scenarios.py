"""Scenario contents: the settings method.md gives, realistic slip levels, profile helpers."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimator.sim import SCENARIOS, scenario_names, simulate
from estimator.sim._signals import BoundedSines, EasedKnots, smooth_window

START_NS = 1_700_000_000_000_000_000


def _t(run) -> np.ndarray:  # type: ignore[no-untyped-def]
    return (run.truth["stamp_ns"] - START_NS) * 1e-9


def test_registry_lists_every_named_scenario() -> None:
    want = {
        "paper_straight",
        "paper_circle",
        "figure_eight",
        "slope_wet_patch",
        "hard_braking",
        "gnss_outage",
        "slow_creep",
        "field_work",
        "random_drive",
    }
    assert set(scenario_names()) == want
    for s in SCENARIOS.values():
        assert s.summary


def test_paper_straight_profile() -> None:
    run = simulate("paper_straight", seed=1, start_ns=START_NS)
    tr, t = run.truth, _t(run)
    assert tr["v0_mps"][0] == 0.0 and tr["v0_mps"][-1] == 0.0
    cruise = (t > 6.0) & (t < 30.0)
    np.testing.assert_allclose(tr["v0_mps"][cruise], 3.0, atol=1e-12)
    assert np.max(np.abs(tr["pitch_rate_radps"])) <= 0.0201
    assert np.max(np.abs(tr["yaw_rate_radps"])) <= 0.0501
    assert np.max(np.abs(tr["yaw_rate_radps"][cruise])) > 0.03
    assert run.sensors.gnss_rate_hz == 5.0
    assert run.sensors.gnss_speed_steps == ((14.0, -1.0, 0.2),)


def test_paper_circle_profile() -> None:
    run = simulate("paper_circle", seed=2, start_ns=START_NS)
    tr, t = run.truth, _t(run)
    circling = t >= 6.0
    assert np.all(np.abs(tr["v0_mps"][circling] - 3.0) <= 0.0301)
    assert np.all(np.abs(tr["yaw_rate_radps"][circling] - 0.4) <= 0.0201)
    assert np.max(np.abs(tr["pitch_rate_radps"])) <= 0.0201
    # counter-clockwise: right wheel faster than left
    assert np.all(tr["vr_mps"][circling] > tr["vl_mps"][circling])
    assert t[-1] == pytest.approx(70.0)


def test_figure_eight_laps_and_slip() -> None:
    run = simulate("figure_eight", seed=3, start_ns=START_NS)
    tr = run.truth
    moving = tr["v0_mps"] > 0.5
    cruising = np.abs(tr["v0_mps"] - 2.7) < 0.06
    assert cruising.mean() > 0.7
    # two laps = four loops of 2π, alternating direction; path closes on itself
    heading = np.unwrap(tr["heading_rad"])
    assert abs(abs(heading[-1] - heading[0])) < 0.3
    turned = np.sum(np.abs(np.diff(heading)))
    assert abs(turned - 4 * 2 * math.pi) < 0.6
    # slip within ±7 %, outer wheel higher while turning
    for side in ("left", "right"):
        s = tr[f"slip_{side}_pct"][moving]
        assert np.nanmax(np.abs(s)) < 7.0
    turning = cruising & (np.abs(tr["yaw_rate_radps"]) > 0.3)
    outer_minus_inner = np.where(
        tr["yaw_rate_radps"] > 0,
        tr["slip_right_pct"] - tr["slip_left_pct"],
        tr["slip_left_pct"] - tr["slip_right_pct"],
    )
    assert np.mean(outer_minus_inner[turning]) > 0.5


def test_slope_wet_patch_gravity_and_slip() -> None:
    run = simulate("slope_wet_patch", seed=4, start_ns=START_NS)
    tr = run.truth
    assert abs(np.degrees(np.median(tr["pitch_rad"][tr["dist_m"] > 30][:500])) - 8.0) < 0.2
    wet = (tr["dist_m"] > 47) & (tr["dist_m"] < 58)
    for side in ("left", "right"):
        s = tr[f"slip_{side}_pct"][wet]
        assert np.min(s) >= 20.0 and np.max(s) <= 30.0
    dry_slope = (tr["dist_m"] > 30) & (tr["dist_m"] < 40)
    assert 8.0 < np.mean(tr["slip_left_pct"][dry_slope]) < 15.0


def test_hard_braking_slip_signs() -> None:
    run = simulate("hard_braking", seed=5, start_ns=START_NS)
    tr = run.truth
    moving = tr["v0_mps"] > 0.5
    s = np.concatenate([tr["slip_left_pct"][moving], tr["slip_right_pct"][moving]])
    assert np.nanmax(s) > 10.0
    assert np.nanmin(s) < -10.0
    cruising = np.abs(tr["a0_mps2"]) < 0.05
    c = tr["slip_left_pct"][cruising & moving]
    assert np.all(np.abs(c) < 4.0)


def test_gnss_outage_window_is_mid_run_and_configurable() -> None:
    run = simulate("gnss_outage", seed=6, start_ns=START_NS, duration_s=100.0, outage_s=30.0)
    assert run.sensors.gnss_outages == ((35.0, 65.0),)
    t = _t(run)
    assert not run.truth["gnss_valid"][(t >= 35.0) & (t < 65.0)].any()
    assert np.all(run.truth["v0_mps"][(t >= 35.0) & (t < 65.0)] > 1.0)


def test_slow_creep_speed_band() -> None:
    run = simulate("slow_creep", seed=7, start_ns=START_NS)
    t, v = _t(run), run.truth["v0_mps"]
    steady = (t > 6.0) & (t < 84.0)
    assert np.all((v[steady] >= 0.5 - 1e-9) & (v[steady] <= 0.8 + 1e-9))
    assert np.ptp(v[steady]) > 0.1


def test_field_work_fills_its_duration_with_passes_turns_and_stops() -> None:
    run = simulate("field_work", seed=8, start_ns=START_NS, duration_s=240.0)
    tr, t = run.truth, _t(run)
    assert t[-1] == pytest.approx(240.0)
    assert tr["v0_mps"][-1] == 0.0
    assert np.max(np.abs(tr["yaw_rate_radps"])) > 0.2  # headland turns
    stops = np.sum(np.diff((tr["v0_mps"] < 0.01).astype(int)) == 1)
    assert stops >= 2  # a mid-run stop and the final one
    assert np.nanmax(tr["slip_left_pct"]) > 10.0  # wet patches
    assert run.sensors.gnss_float_windows == ((72.0, 82.0),)
    assert run.sensors.gnss_outages == ((144.0, 152.0),)


def test_overrides_reach_the_scenario() -> None:
    run = simulate("hard_braking", seed=1, start_ns=START_NS, speed_mps=5.0, cycles=1)
    assert abs(np.max(run.truth["v0_mps"]) - 5.0) < 0.06
    assert run.params["cycles"] == 1


@settings(max_examples=30, deadline=None)
@given(st.floats(0.01, 2.0), st.floats(1.0, 200.0), st.integers(0, 2**32 - 1))
def test_bounded_sines_respect_their_bound(bound: float, span: float, seed: int) -> None:
    rng = np.random.default_rng(seed)
    x = np.linspace(0.0, span, 20001)
    w = BoundedSines.draw(rng, bound, span, 0.05, 1.0)
    assert np.max(np.abs(w(x))) <= bound * 1.001
    r = BoundedSines.draw(rng, bound, span, 0.05, 1.0, bound_on="rate")
    rate = np.gradient(r(x), x)
    assert np.max(np.abs(rate)) <= bound * 1.01


def test_eased_knots_hold_values_and_are_c1() -> None:
    k = EasedKnots((0.0, 1.0, 3.0), (0.0, 2.0, 2.0))
    x = np.linspace(-1.0, 4.0, 5001)
    y = k(x)
    assert y[0] == 0.0 and y[-1] == 2.0
    np.testing.assert_allclose(k(np.array([0.5, 1.0, 2.0])), [1.0, 2.0, 2.0])
    slope = np.gradient(y, x)
    assert np.max(np.abs(np.diff(slope))) < 0.05  # no jumps in slope
    assert abs(np.max(slope) - math.pi) < 0.01  # π/2 × mean slope of 2


def test_smooth_window_edges() -> None:
    x = np.array([0.0, 9.0, 10.0, 11.0, 15.0, 19.0, 20.0, 21.0, 30.0])
    np.testing.assert_allclose(smooth_window(x, 10.0, 20.0, 2.0), [0, 0, 0.5, 1, 1, 1, 0.5, 0, 0])


def test_body_wobble_grows_with_speed_in_field_scenarios() -> None:
    run = simulate("slow_creep", seed=9, start_ns=START_NS)
    # 0.5-0.8 m/s against full wobble at 3 m/s: at most 0.8/3 of the ±0.02 rad/s pitch rate
    assert np.max(np.abs(run.truth["pitch_rate_radps"])) < 0.02 * 0.8 / 3 + 0.002
    standing = run.truth["v0_mps"] == 0.0
    assert np.all(np.abs(run.truth["pitch_rate_radps"][standing]) < 1e-4)


def test_impossible_settings_are_refused() -> None:
    with pytest.raises(ValueError):
        simulate("gnss_outage", seed=1, start_ns=START_NS, duration_s=30.0)
    with pytest.raises(ValueError):
        simulate("figure_eight", seed=1, start_ns=START_NS, laps=0)
    with pytest.raises(ValueError):
        simulate("slow_creep", seed=1, start_ns=START_NS, duration_s=5.0)
