"""Each equation and threshold of the tracked estimator, computed by hand (``method.md`` §4)."""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

from estimator.config import TrackedConfig
from estimator.tracked.edges import OVERDUE, EdgeBuffer, edge_speed, span_speed
from estimator.tracked.filter import kalman_update, predict
from estimator.tracked.model import N_STATES, MotionState, TrackedMode
from estimator.tracked.model import TrackedState as S
from estimator.tracked.odometer import (
    lateral_speed,
    odometer_measurement,
    paper_ratio,
    side_slip,
    turn_tightness,
)
from estimator.tracked.params import VehicleParams
from estimator.tracked.recognise import (
    change_onset,
    fallback_states,
    gearbox_bound,
    gearbox_speed,
    paper_states,
    product_states,
    ratio_noise,
)
from estimator.tracked.settings import TrackedEstimatorConfig
from estimator.tracked.step import (
    _dead_reckoning_noise,
    _fuse_odometer,
    _ground_patch,
    _released,
    _track_slip,
    fresh_patch_var,
    initial_filter,
    odometer_start,
    patch_std,
    recognise,
)
from estimator.tracked.vehicle import TickInputs, odometer_edges_at

M = MotionState
P1 = VehicleParams.of(TrackedConfig())  # B = 2 m, L = 2.5 m: r = 1.531 m, R_II = 5.76 m


def _paper(speed: float, yaw: float, odo: float, step: float = 0.0) -> int:
    got = paper_states(np.array([speed]), np.array([yaw]), np.array([odo]), np.array([step]), P1)
    return int(got[0])


def test_thresholds_of_the_source() -> None:
    assert P1.pivot_radius_m[0] == pytest.approx(1.531)  # Eq. 10: r = 1.531 · B/2
    assert P1.separated_radius_m[0] == pytest.approx(5.76)  # R_II = 2.88 · B


@pytest.mark.parametrize(
    ("rho_m", "state"),
    [
        (1.0, M.STRAIGHT),  # |ρ| < r matches no printed rule: the odometer is used as it is
        (2.0, M.PIVOT),  # Eq. 11: r ≤ |ρ| < R_II
        (8.0, M.ARC),  # Eq. 14: r ≤ |ρ| ≤ 2·R_II^max = 4·R_II = 23.04 m
        (15.0, M.ARC),  # Eq. 14 and 15 overlap on (11.52, 23.04]: the arc comes first
        (30.0, M.SEPARATED),  # Eq. 15: |ρ| > 2·R_II
        (300.0, M.STRAIGHT),  # |ρ| > R_max = 200 m
    ],
)
def test_paper_radius_rules(rho_m: float, state: MotionState) -> None:
    speed = 3.0
    assert _paper(speed, speed / rho_m, speed) == state
    assert _paper(speed, -speed / rho_m, speed) == state  # either way round


def test_paper_low_gear_rule_eq6_compares_with_the_instantaneous_speed() -> None:
    assert _paper(2.0, 0.0, 1.42 * 2.0) == M.LOW_STRAIGHT  # v_o ≥ 1.42 · v_y
    assert _paper(2.0, 0.0, 1.42 * 2.0 - 0.01) == M.STRAIGHT


def test_paper_large_heading_change_and_standstill() -> None:
    assert _paper(3.0, 0.0, 3.0, step=0.11) == M.HEADING_JUMP  # Eq. 16, δφ_max = 0.1 rad
    assert _paper(3.0, 0.0, 3.0, step=0.09) == M.STRAIGHT
    assert _paper(0.1, 0.0, 0.1, step=0.5) == M.STOP


@pytest.mark.parametrize(
    ("left", "right", "gear", "state"),
    [
        (3.0, 3.0, 1.0, M.STRAIGHT),
        (3.0 / 1.42, 3.0 / 1.42, 1 / 1.42, M.LOW_STRAIGHT),
        (3.0 / 1.42, 3.0, 1.0, M.ARC),  # left slow: a left arc
        (3.0, 2.7, 1.0, M.SEPARATED),
        (3.0, 0.0, 1.0, M.PIVOT),
        (0.0, 0.0, 1.0, M.STOP),
    ],
)
def test_product_states_from_sprocket_ratios(
    left: float, right: float, gear: float, state: MotionState
) -> None:
    fast, slow = max(left, right), min(left, right)
    yaw = fast * (1 - slow / fast) / 2.0 if fast > 0 else 0.0  # the turn the ratio makes
    got, conf = product_states(
        np.array([[left, right]]),
        np.array([gear]),
        np.zeros(1),
        P1,
        TrackedEstimatorConfig(),
        np.array([yaw]),
        np.array([fast / gear]),
    )
    assert int(got[0]) == state
    assert conf[0] > 0.9  # not near a threshold (a straight's q = 1 is 1.5 σ from 0.985)


def test_product_confidence_falls_at_a_threshold() -> None:
    cfg = TrackedEstimatorConfig()
    q = cfg.straight_ratio_min
    _, conf = product_states(
        np.array([[3.0 * q, 3.0]]), np.ones(1), np.zeros(1), P1, cfg, np.array([0.1]), np.ones(1)
    )
    assert conf[0] == pytest.approx(0.5)


def test_ratio_noise_from_the_teeth_the_acceleration_and_the_carry() -> None:
    cfg = TrackedEstimatorConfig()
    pitch = float(P1.sprocket_pitch_m[0])  # 2π·0.35/13 = 0.169 m
    e, sa = cfg.sprocket_tooth_std_pitch, cfg.carry_accel_std_mps2

    def by_hand(v: float, a: float, periods: int) -> float:
        lag = max(0.15, 1.5 * pitch / v)  # half the window, or 1.5 periods at a crawl
        side = math.sqrt((math.sqrt(2) * e / periods) ** 2 + (a * pitch / v**2) ** 2)
        return math.sqrt(2) * math.hypot(side, sa * lag / v)

    # 1 m/s: a 0.3 s window holds 1.77 pitches, taken as one period; 4 m/s: 7.1, capped at 5
    slow = ratio_noise(np.array([[1.0, 1.0]]), np.zeros(1), P1, cfg)[0]
    assert slow == pytest.approx(by_hand(1.0, 0.0, 1))
    fast = ratio_noise(np.array([[4.0, 4.0]]), np.zeros(1), P1, cfg)[0]
    assert fast == pytest.approx(by_hand(4.0, 0.0, 5))
    # 2 m/s (3.5 pitches: 2 periods) slowing at 1.5 m/s²: the speed moves 1.5·pitch/v² a period
    braking = ratio_noise(np.array([[2.0, 2.0]]), np.array([-1.5]), P1, cfg)[0]
    assert braking == pytest.approx(by_hand(2.0, 1.5, 2))
    assert fast < 0.005 < slow < braking


def _separated(pair: list[float], yaw_share: float, gear: float = 1.0, accel: float = 0.0) -> int:
    cfg = TrackedEstimatorConfig()
    fast, slow = max(pair), min(pair)
    kinematic = fast * (1 - slow / fast) / 2.0
    got, _ = product_states(
        np.array([pair]),
        np.array([gear]),
        np.zeros(1),
        P1,
        cfg,
        np.array([yaw_share * kinematic]),
        np.array([fast / gear]),
        None,
        np.array([accel]),
    )
    return int(got[0])


def test_a_separated_ratio_within_its_noise_of_one_must_show_its_turn() -> None:
    # 1.5 m/s, q = 0.96: 4 % below 1 against a 1-sigma of 1.3 % (one period per window);
    # the kinematic ω is 0.03 rad/s: all of it shown is a turn, 40 % of it is not
    assert _separated([1.5, 1.44], 1.0) == M.SEPARATED
    assert _separated([1.5, 1.44], 0.4) == M.STRAIGHT
    # the same ratio in the low gear (fast sprocket at 1/1.42 of the odometer) is a low straight
    assert _separated([1.5, 1.44], 0.4, gear=1 / 1.42) == M.LOW_STRAIGHT


def test_a_separated_ratio_well_below_one_is_a_turn_without_its_yaw() -> None:
    # 3 m/s, q = 0.95: 1-sigma 0.5 % (four periods), 10 sigma below 1: the lever, whatever
    # the yaw rate (a gentle turn on soft ground loses most of it to turn slip and skid)
    assert _separated([3.0, 2.85], 0.2) == M.SEPARATED
    # slowing down hard, the two windows read the gearbox up to a period apart: checked again
    assert _separated([3.0, 2.85], 0.2, accel=-1.5) == M.STRAIGHT


def test_a_crawl_must_turn_more_than_a_straights_yaw_noise() -> None:
    # 0.5 m/s, q = 0.9: the kinematic ω (0.025 rad/s) half shown is below the yaw noise
    cfg = TrackedEstimatorConfig()
    assert cfg.yaw_lead_noise_radps > 0.6 * 0.5 * 0.1 / 2.0
    assert _separated([0.5, 0.45], 0.6) == M.STRAIGHT
    assert _separated([0.5, 0.45], 2.0) == M.SEPARATED  # 0.05 rad/s: a turn


def test_a_crawls_jumping_ratio_is_not_a_lever() -> None:
    cfg = TrackedEstimatorConfig()
    # q 1 -> 0.9 in a tick: at 3 m/s a lever (read where it goes, past the arc's 0.704 ...)
    # at 0.5 m/s within what the windows' noise makes of a tick (1-sigma ~7 %): read as is
    for speed, lever in ((3.0, True), (0.5, False)):
        before = (np.array([[speed, speed]]), np.ones(1))
        got, _ = product_states(
            np.array([[speed, 0.9 * speed]]),
            np.ones(1),
            np.zeros(1),
            P1,
            cfg,
            np.array([0.5 * speed * 0.1 / 2.0]),
            np.array([speed]),
            before,
            np.zeros(1),
        )
        assert (int(got[0]) == M.ARC) == lever


def test_a_start_from_standstill_is_a_straight_before_the_sprockets_read() -> None:
    cfg = TrackedEstimatorConfig()
    args = (np.zeros((2, 2)), np.full(2, np.nan), np.zeros(2), VehicleParams.stack([P1, P1]), cfg)
    odo = np.array([0.5 * cfg.start_odometer_mps, 2.0 * cfg.start_odometer_mps])
    got, _ = product_states(*args, np.zeros(2), odo)
    assert got.tolist() == [M.STOP, M.STRAIGHT]


def test_no_sprocket_is_read_faster_than_the_slowing_gearbox() -> None:
    cfg = TrackedEstimatorConfig()
    # 0: braking at −1.5 m/s², odometer 0.2 m/s at its centre 0.05 s back: the gearbox turns
    #    at 0.125 m/s, so a window holding 0.48 is read at 1.2 · 0.125 = 0.15 m/s
    # 1: the same odometer at a steady speed: a window never leads, nothing is bounded
    # 2: no odometer: nothing is bounded
    pair = np.array([[0.48, 0.0], [0.48, 0.0], [0.48, 0.0]])
    got = gearbox_bound(
        pair,
        np.array([0.2, 0.2, np.nan]),
        np.full(3, 0.05),
        np.array([-1.5, 0.0, -1.5]),
        cfg,
    )
    assert got[:, 1].tolist() == [0.0, 0.0, 0.0]
    assert got[0, 0] == pytest.approx(1.2 * (0.2 - 1.5 * 0.05))
    assert got[1:, 0].tolist() == [0.48, 0.48]
    # read at the bound, the stale window is no longer a pivot beside the silent one
    p2 = VehicleParams.stack([P1, P1])
    odo = np.array([0.2, 0.2])
    stale, _ = product_states(pair[:2], np.ones(2), np.zeros(2), p2, cfg, np.zeros(2), odo)
    bounded, _ = product_states(got[:2], np.ones(2), np.zeros(2), p2, cfg, np.zeros(2), odo)
    assert stale.tolist() == [M.PIVOT, M.PIVOT]
    assert bounded.tolist() == [M.STRAIGHT, M.PIVOT]
    # the gearbox's speed at the tick decides "moving": braking at −1.5 m/s², an odometer
    # window of 0.12 m/s centred 0.05 s back has stopped turning (0.045 m/s) -> stop
    at_tick = gearbox_speed(np.array([0.12, 0.12]), np.full(2, 0.05), np.array([-1.5, 0.0]))
    assert at_tick == pytest.approx([0.045, 0.12])
    moving, _ = product_states(got[:2], np.ones(2), np.zeros(2), p2, cfg, np.zeros(2), at_tick)
    assert moving[0] == M.STOP


@pytest.mark.parametrize(
    ("slow_before", "slow_now", "state"),
    [
        (3.0, 1.8, M.PIVOT),  # q 1 → 0.6 in a tick: −4/s over a 0.3 s travel ends below 0
        (3.0, 2.7, M.ARC),  # −1/s: ends at 0.7, the arc's 1/1.42
        (2.1, 2.4, M.STRAIGHT),  # an arc being left: +1/s ends at 1
        (0.3, 1.2, M.STRAIGHT),  # a pivot being left
    ],
)
def test_a_moving_lever_is_read_where_it_goes(
    slow_before: float, slow_now: float, state: MotionState
) -> None:
    cfg = TrackedEstimatorConfig()
    before = (np.array([[3.0, slow_before]]), np.ones(1))
    got, _ = product_states(
        np.array([[3.0, slow_now]]),
        np.ones(1),
        np.zeros(1),
        P1,
        cfg,
        np.zeros(1),
        np.array([3.0]),
        before,
    )
    assert int(got[0]) == state
    # without the tick before, the ratio is read where it is, in a band on the way
    alone, _ = product_states(
        np.array([[3.0, slow_now]]), np.ones(1), np.zeros(1), P1, cfg, np.ones(1), np.array([3.0])
    )
    assert int(alone[0]) != state


def test_a_stop_or_start_under_way_is_an_onset() -> None:
    cfg = TrackedEstimatorConfig()
    p3 = VehicleParams.stack([P1, P1, P1])
    pair = np.array([[0.4, 0.4], [3.0, 3.0], [0.4, 0.4]])
    # braking at 1.5 m/s² reaches standstill within the 0.4 s lag from below 0.6 m/s only
    got = change_onset(
        pair,
        np.ones(3),
        (pair, np.ones(3)),
        np.zeros((3, 2), dtype=bool),
        np.zeros(3),
        p3,
        cfg,
        np.array([-1.5, -1.5, 0.0]),
        np.array([0.4, 3.0, 0.4]),
    )
    assert got.tolist() == [True, False, False]


def test_fallback_rules_have_no_overlap() -> None:
    rho = np.array([2.0, 8.0, 15.0, 30.0, 300.0])
    got = fallback_states(
        np.full(5, 3.0),
        3.0 / rho,
        np.full(5, 3.0),
        np.zeros(5),
        VehicleParams.stack([P1] * 5),
        np.zeros(5, dtype=bool),
    )
    assert got.tolist() == [M.PIVOT, M.ARC, M.SEPARATED, M.SEPARATED, M.STRAIGHT]


def test_paper_odometer_ratios() -> None:
    state = np.array([M.STRAIGHT, M.LOW_STRAIGHT, M.ARC, M.SEPARATED, M.PIVOT, M.HEADING_JUMP])
    got = paper_ratio(state, np.full(6, 20.0), VehicleParams.stack([P1] * 6))
    assert got[:4] == pytest.approx([1.0, 1 / 1.42, 0.8688, 20.0 / 21.0])  # Eq. 7, 20, 23
    assert np.isnan(got[4:]).all()  # pivot and large heading change: no odometer


def test_lateral_speed_printed_and_physical() -> None:
    v, w, length, mu = 3.0, 0.3, np.array([2.5]), np.array([0.6])
    arc = np.array([M.ARC])
    paper = lateral_speed(TrackedMode.PAPER, arc, np.array([v]), np.array([w]), length, mu)
    assert paper[0] == pytest.approx(-0.75)  # Eq. 17: −φ̇·L, toward the centre of a left turn
    product = lateral_speed(TrackedMode.PRODUCT, arc, np.array([v]), np.array([w]), length, mu)
    pole = 2.5 * v * w / (2 * 0.6 * 9.80665)  # L·|a_y|/(2·μ_t·g)
    assert product[0] == pytest.approx(w * pole)  # outward (+ right) in a left turn
    assert 0 < product[0] < abs(paper[0]) / 5  # the printed term is several times larger
    none = lateral_speed(
        TrackedMode.PAPER_NO_LATERAL, arc, np.array([v]), np.array([w]), length, mu
    )
    assert none[0] == 0.0


def test_product_odometer_measurement_by_hand() -> None:
    x = np.zeros((1, N_STATES))
    x[0, S.SPEED] = 2.0
    x[0, S.F_STRAIGHT] = 0.98
    x[0, S.TURN_SLIP] = 0.1  # an arc (θ = 2·(1 − 1/1.42)/(1 + 1/1.42) = 0.3471): F = 0.9453
    x[0, S.ACCEL_LAG] = 0.2
    cfg = TrackedEstimatorConfig()
    theta = turn_tightness(np.array([[3.0 / 1.42, 3.0]]))
    assert theta[0] == pytest.approx(2 * 0.42 / 2.42)
    f = 0.98 - 0.1 * theta[0]
    y, H, R, mask, corrected = odometer_measurement(
        cfg,
        P1,
        x,
        np.array([M.ARC]),
        np.array([2.5]),
        np.array([0.05]),
        np.array([1.0]),
        np.array([0.3]),
        np.ones(1, dtype=bool),
        theta,
    )
    # V − a·lag + τ·a + |ω|·B/2: the fast track's ground speed, a = 1 m/s², τ = 0.2 s
    ground = 2.0 - 1.0 * 0.05 + 0.2 * 1.0 + 0.3 * 1.0
    assert y[0, 0] == pytest.approx(2.5 - ground / f)
    assert H[0, 0, S.SPEED] == pytest.approx(1 / f)
    assert H[0, 0, S.ACCEL_LAG] == pytest.approx(1.0 / f)
    assert H[0, 0, S.F_STRAIGHT] == pytest.approx(-ground / f**2)
    assert H[0, 0, S.TURN_SLIP] == pytest.approx(ground / f**2 * theta[0])  # ∂h/∂c = h·θ/F
    assert R[0, 0, 0] == pytest.approx((0.02 + 0.01 * 2.5 + 0.3 * 1.0) ** 2)
    assert mask[0] and corrected[0] == pytest.approx(2.5 * f - 0.3 - 0.2)


def _steady_odometer(
    cfg: TrackedEstimatorConfig,
    x: np.ndarray,
    state: MotionState,
    odometer_mps: float,
    yaw_radps: float,
    theta: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`odometer_measurement` of one vehicle at a steady speed (no lag, no acceleration)."""
    return odometer_measurement(
        cfg,
        P1,
        x,
        np.array([state]),
        np.array([odometer_mps]),
        np.zeros(1),
        np.zeros(1),
        np.array([yaw_radps]),
        np.ones(1, dtype=bool),
        theta,
    )


def test_a_separated_turn_slips_by_its_tightness_from_the_prior() -> None:
    from estimator.tracked.step import initial_filter

    cfg = TrackedEstimatorConfig()
    x = initial_filter(cfg).x.copy()
    assert x[0, S.TURN_SLIP] == cfg.initial_turn_slip
    x[0, S.SPEED] = 4.0
    pair = np.array([[4.0, 3.6]])  # q = 0.9: θ = 0.2/1.9
    theta = turn_tightness(pair)
    _, _, _, _, corrected = _steady_odometer(cfg, x, M.SEPARATED, 4.0, 0.0, theta)
    assert corrected[0] == pytest.approx(4.0 * (1.0 - cfg.initial_turn_slip * 0.2 / 1.9))
    assert turn_tightness(np.array([[4.0, 4.0], [0.0, 0.0]])).tolist() == [0.0, 0.0]


def test_low_gear_factor_is_an_offset_and_traction_slips_with_acceleration() -> None:
    x = np.zeros((1, N_STATES))
    x[0, S.SPEED] = 2.0
    x[0, S.F_STRAIGHT] = 0.95
    x[0, S.F_LOW] = 0.01  # F_low = 0.95 + 0.01
    x[0, S.ACCEL_SLIP] = 0.05  # κ: 5 % more slip per m/s²
    y, H, _, mask, corrected = odometer_measurement(
        TrackedEstimatorConfig(),
        P1,
        x,
        np.array([M.LOW_STRAIGHT]),
        np.array([2.5]),
        np.zeros(1),
        np.array([0.4]),
        np.zeros(1),
        np.ones(1, dtype=bool),
    )
    effective = 0.96 * (1 - 0.05 * 0.4)  # F_low·(1 − κ·a)
    h = 1.42 * 2.0 / effective
    assert y[0, 0] == pytest.approx(2.5 - h)
    assert H[0, 0, S.SPEED] == pytest.approx(1.42 / effective)
    assert H[0, 0, S.F_LOW] == pytest.approx(-h / 0.96)
    assert H[0, 0, S.F_STRAIGHT] == pytest.approx(-h / 0.96)  # the offset rides on F_straight
    assert H[0, 0, S.ACCEL_SLIP] == pytest.approx(h * 0.4 / (1 - 0.05 * 0.4))
    assert mask[0] and corrected[0] == pytest.approx(2.5 * effective / 1.42)


def test_pivot_factor_is_an_offset_from_the_straight_and_starts_at_the_pivot_slip() -> None:
    from estimator.tracked.step import initial_filter

    cfg = TrackedEstimatorConfig()
    x0 = initial_filter(cfg).x[0]
    assert x0[S.F_PIVOT] == -cfg.initial_pivot_slip and x0[S.F_STRAIGHT] == 1.0
    x = np.zeros((1, N_STATES))
    x[0, S.SPEED] = 1.0
    x[0, S.F_STRAIGHT] = 0.95
    x[0, S.F_PIVOT] = -0.2  # F_pivot = 0.75
    y, H, _, mask, corrected = _steady_odometer(cfg, x, M.PIVOT, 2.0, 0.5)
    ground = 1.0 + 0.5 * float(P1.gauge_m[0]) / 2  # V + |ω|·B/2, the driven track
    assert y[0, 0] == pytest.approx(2.0 - ground / 0.75)
    assert H[0, 0, S.F_PIVOT] == H[0, 0, S.F_STRAIGHT] == pytest.approx(-ground / 0.75**2)
    assert mask[0] and corrected[0] == pytest.approx(2.0 * 0.75 - (ground - 1.0))


def test_odometer_dropped_in_heading_jumps() -> None:
    x = np.zeros((1, N_STATES))
    x[0, S.F_STRAIGHT] = 1.0
    for mode in TrackedMode:
        cfg = TrackedEstimatorConfig(mode=mode)
        *_, mask, _ = odometer_measurement(
            cfg,
            P1,
            x,
            np.array([M.HEADING_JUMP]),
            np.ones(1),
            np.zeros(1),
            np.zeros(1),
            np.zeros(1),
            np.ones(1, dtype=bool),
        )
        assert mask[0] == (mode == TrackedMode.RAW_ODOMETER)


def test_edge_speed_period_method() -> None:
    stamps = np.arange(0, 1_000_000_000, 10_000_000, dtype=np.int64)  # every 10 ms
    speed, centre = edge_speed(stamps, np.array([500_000_000]), 0.01, 100_000_000, 1000, 10**9)
    assert speed[0] == pytest.approx(1.0)  # 0.01 m per 10 ms
    assert centre[0] == pytest.approx(455_000_000)  # edges 410…500 ms (400 is outside)
    stale, _ = edge_speed(stamps, np.array([3_000_000_000]), 0.01, 100_000_000, 1000, 10**9)
    assert stale[0] == 0.0  # nothing for two seconds
    bound, _ = edge_speed(stamps, np.array([1_040_000_000]), 0.01, 100_000_000, 1000, 10**9)
    # no edge for 50 ms after the last (5 periods): at most OVERDUE·pitch/50 ms, below the
    # window's own bound (no 6th edge 90 ms after the first: 5·pitch/90 ms)
    assert bound[0] == pytest.approx(OVERDUE * 0.01 / 0.05)
    assert OVERDUE * 0.01 / 0.05 < 5 * 0.01 / 0.09
    late, _ = edge_speed(stamps, np.array([995_000_000]), 0.01, 100_000_000, 1000, 10**9)
    assert late[0] == pytest.approx(1.0)  # half a period after the last edge: not overdue
    mean = span_speed(stamps, np.array([0.0]), np.array([2e8]), 0.01)
    assert mean[0] == pytest.approx(1.0)


def test_a_crawl_reads_on_until_its_next_edge_is_late() -> None:
    # 0.5 m/s on a 0.2 m pitch: an edge every 400 ms, more than the 300 ms window holds
    stamps = np.arange(0, 1_200_000_001, 400_000_000, dtype=np.int64)  # 0, 0.4, 0.8, 1.2 s
    window, hold = 300_000_000, 600_000_000
    tick = np.array([1_500_000_000])  # the pair (0.8, 1.2) began 0.7 s ago, > hold
    due, _ = edge_speed(stamps, tick, 0.2, window, 6, hold)
    assert due[0] == pytest.approx(0.5)  # the next edge is due at 1.6 s: not late
    late_tick = np.array([1_200_000_000 + int(OVERDUE * 400_000_000) + 1])
    late, _ = edge_speed(stamps, late_tick, 0.2, window, 6, hold)
    assert late[0] == 0.0  # overdue and past hold: standing


def test_edges_going_backwards_are_counted_and_dropped() -> None:
    buf = EdgeBuffer()
    buf.push(np.array([10, 20, 30], dtype=np.int64))
    buf.push(np.array([25, 40, 35, 50], dtype=np.int64))
    assert buf.stamps.tolist() == [10, 20, 30, 40, 50]
    assert buf.backwards == 2


def test_predict_moves_along_the_heading_and_turns_clockwise_for_a_right_turn() -> None:
    x = np.zeros((1, N_STATES))
    x[0, S.SPEED] = 10.0
    x[0, S.HEADING] = math.pi / 2  # east
    P = np.eye(N_STATES)[None] * 1e-4
    q = np.zeros((1, N_STATES))
    out, P2 = predict(x, P, np.array([-0.1]), np.array([1.0]), np.zeros(1), 0.1, q)
    assert out[0, S.HEADING] == pytest.approx(math.pi / 2 + 0.01)  # ψ̇ = −ω, ω = −0.1 (right)
    psi_m = math.pi / 2 + 0.005
    assert out[0, S.EAST] == pytest.approx(1.0 * math.sin(psi_m))
    assert out[0, S.NORTH] == pytest.approx(1.0 * math.cos(psi_m))
    assert out[0, S.SPEED] == pytest.approx(10.1)
    assert np.allclose(P2[0], P2[0].T) and np.linalg.eigvalsh(P2[0]).min() > 0


def test_update_equals_filterpy() -> None:
    rng = np.random.default_rng(3)
    A = rng.normal(size=(N_STATES, N_STATES))
    P = A @ A.T + np.eye(N_STATES)
    x = rng.normal(size=N_STATES)
    H = rng.normal(size=(2, N_STATES))
    R = np.diag([0.3, 0.5])
    z = rng.normal(size=2)
    kf = KalmanFilter(dim_x=N_STATES, dim_z=2)
    kf.x, kf.P, kf.H, kf.R = x.copy(), P.copy(), H, R
    kf.update(z)
    x2, P2, nis, used = kalman_update(
        x[None], P[None], (z - H @ x)[None], H[None], R[None], np.ones(1, dtype=bool)
    )
    assert used[0]
    assert np.allclose(x2[0], kf.x, atol=1e-12, rtol=0)
    assert np.allclose(P2[0], kf.P, atol=1e-10, rtol=0)
    y = z - H @ x
    assert nis[0] == pytest.approx(y @ np.linalg.solve(H @ P @ H.T + R, y))


def test_update_is_gated_and_masked() -> None:
    x = np.zeros((2, N_STATES))
    P = np.broadcast_to(np.eye(N_STATES), (2, N_STATES, N_STATES)).copy()
    H = np.zeros((2, 1, N_STATES))
    H[:, 0, S.SPEED] = 1.0
    R = np.full((2, 1, 1), 1.0)
    y = np.array([[100.0], [1.0]])
    x2, P2, nis, used = kalman_update(x, P, y, H, R, np.array([True, False]), gate_nis=16.0)
    assert not used.any() and nis[0] == pytest.approx(5000.0) and np.isnan(nis[1])
    assert np.array_equal(x2, x) and np.array_equal(P2, P)


def test_tracked_package_is_pure() -> None:
    code = (
        "import sys\nimport estimator.tracked, estimator.sim.tracked, estimator.tracked_spec\n"
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in "
        "('zenoh', 'fastapi', 'sqlite3', 'psycopg', 'server', 'viser', 'msgpack'))\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


def _tick_inputs(n: int = 3, **fields: np.ndarray) -> TickInputs:
    """``n`` ticks of zeros (``*_pair*`` fields ``(n, 2)``), ``fields`` replacing some."""
    flags = ("sprocket_missing", "sprocket_settling_pair", "sprocket_starting_pair")
    ints = dict.fromkeys(("odometer_edges", "ticks_ns", "imu_samples"), np.int64)
    kinds = {**dict.fromkeys(flags, bool), **ints}
    base = {
        f.name: np.zeros((n, 2) if "pair" in f.name else n, dtype=kinds.get(f.name, float))
        for f in dataclasses.fields(TickInputs)
    }
    return TickInputs(**{**base, **fields})


def test_a_released_brake_is_read_from_the_slow_sprockets_first_edge() -> None:
    p3 = VehicleParams.stack([P1, P1, P1])
    # 0: pivot, braked (left, slow) sprocket's first edge: released, direct gear -> straight
    # 1: the same in the low gear -> low straight
    # 2: a pivot started from rest: the driven (fast) sprocket starts, the braked one is silent
    inp = _tick_inputs(
        sprocket_pair_mps=np.array([[0.0, 1.5], [0.0, 1.5], [0.0, 0.4]]),
        sprocket_starting_pair=np.array([[True, False], [True, False], [False, True]]),
        gear_ratio=np.array([1.0, 1 / 1.42, 1.0]),
    )
    state = np.full(3, int(M.PIVOT))
    got = _released(state, inp, p3)
    assert got.tolist() == [int(M.STRAIGHT), int(M.LOW_STRAIGHT), int(M.PIVOT)]
    still = _released(np.full(3, int(M.STOP)), inp, p3)  # standing: nothing released
    assert (still == int(M.STOP)).all()


def _fresh_by_hand(d: float, sp: float, ell: float) -> float:
    """``Var ∫₀^d w(s) ds``, ``w`` Gauss-Markov from 0 (textbook form)."""
    E = math.exp(-d / ell)
    return sp**2 * ell**2 * (2 * d / ell - 3 + 4 * E - E * E)


def test_the_patches_met_since_the_fix_grow_from_nothing() -> None:
    ell, sp = 150.0, 0.003
    d = np.array([2.0, 40.0, 3000.0])
    got = fresh_patch_var(d, np.full(3, sp), ell)
    assert got == pytest.approx([_fresh_by_hand(x, sp, ell) for x in d.tolist()], rel=1e-6)
    assert got[0] == pytest.approx(2 / 3 * sp**2 * 8.0 / ell, rel=0.02)  # (2/3)·σ²·d³/ℓ
    assert got[2] == pytest.approx(sp**2 * ell * (2 * 3000.0 - 3 * ell), rel=1e-6)  # ≈ 2σ²ℓd


def test_dead_reckoning_grows_the_along_track_variance_by_the_learnt_states_error() -> None:
    """``GᵀP_L G`` with ``G = ∫ g dt`` (the patch's gain dying out over ``ℓ``) and the new
    patches' variance, both grown over the tick, along the heading."""
    cfg = TrackedEstimatorConfig()
    f = initial_filter(cfg)
    f.started[:] = True
    f.x[0, S.SPEED], f.x[0, S.HEADING] = 5.0, 0.0  # north
    f.x[0, S.F_STRAIGHT] = 0.96  # a ground slipping by 4 %
    f.P[0] = np.eye(N_STATES) * 1e-4
    f.P[0, S.F_STRAIGHT, S.F_STRAIGHT] = 1e-5
    P_L = np.eye(7) * 1e-6
    P_L[0, 0], P_L[4, 4], P_L[0, 4], P_L[4, 0] = 8e-6, 2e-6, -1e-6, -1e-6  # F_straight, patch
    f.fix_learnt_cov[0] = P_L
    G0 = np.array([40.0, 0, 0, 0, 30.0, 0, 0])
    f.odometer_gain[0] = G0
    f.since_gnss_m[:] = 40.5  # this tick's 0.5 m counted
    g = np.array([[5.2, 0, 0, 0, 5.2, 0, 0]])  # −h_L/h_V of a straight at 5.2 m/s odometer
    f.since_gnss_s[:] = 0.5  # beside GNSS: nothing added
    _dead_reckoning_noise(f, P1, cfg, g)
    assert f.P[0, S.NORTH, S.NORTH] == 1e-4
    f.odometer_gain[0] = G0
    f.since_gnss_s[:] = 10.0
    _dead_reckoning_noise(f, P1, cfg, g)
    G1 = G0 + 0.1 * np.array([5.2, 0, 0, 0, 5.2 * math.exp(-40.0 / 150.0), 0, 0])
    assert f.odometer_gain[0] == pytest.approx(G1)
    sigma_p = 0.15 * math.sqrt(0.04**2 + 0.005**2 + 1e-5)
    fresh = _fresh_by_hand(40.5, sigma_p, 150.0) - _fresh_by_hand(40.0, sigma_p, 150.0)
    q = G1 @ P_L @ G1 - G0 @ P_L @ G0 + fresh
    assert f.P[0, S.NORTH, S.NORTH] == pytest.approx(1e-4 + q, rel=1e-9)
    assert f.P[0, S.EAST, S.EAST] == pytest.approx(1e-4)  # along the heading only
    assert f.P[0, S.EAST, S.NORTH] == pytest.approx(0.0, abs=1e-15)


def test_a_firm_grounds_patches_differ_by_less_than_a_soft_ones() -> None:
    """σ_p = r·√((1 − F)² + σ_KD² + σ_F²): the patch's share of the ground's slip level."""
    cfg = TrackedEstimatorConfig()
    f = initial_filter(cfg)
    f.x = np.repeat(f.x, 3, axis=0)
    f.P = np.repeat(f.P, 3, axis=0)
    f.x[:, S.F_STRAIGHT] = [0.985, 0.955, 1.004]  # firm, soft, K_D reading short
    f.P[:, S.F_STRAIGHT, S.F_STRAIGHT] = 0.002**2
    sigma_kd = TrackedConfig().odometer.scale_std_pct / 100.0
    got = patch_std(f, VehicleParams.stack([P1, P1, P1]), cfg)
    level = np.array([0.015, 0.045, -0.004])
    assert got == pytest.approx(0.15 * np.sqrt(level**2 + sigma_kd**2 + 0.002**2))
    assert got[0] < 0.5 * got[1]
    f.P[:, S.F_STRAIGHT, S.F_STRAIGHT] = 0.03**2  # not learnt yet: the prior's width
    wide = patch_std(f, VehicleParams.stack([P1, P1, P1]), cfg)
    assert wide[0] == pytest.approx(0.15 * math.sqrt(0.015**2 + sigma_kd**2 + 0.03**2))


def test_the_ground_patch_dies_out_over_the_distance_driven() -> None:
    cfg = TrackedEstimatorConfig()
    f = initial_filter(cfg)
    assert f.x[0, S.GROUND_PATCH] == 0.0
    assert f.P[0, S.GROUND_PATCH, S.GROUND_PATCH] == pytest.approx(0.007**2)
    f.x[0, S.SPEED], f.x[0, S.GROUND_PATCH] = 10.0, 0.01
    f.x[0, S.F_STRAIGHT] = 0.96
    f.P[0, S.F_STRAIGHT, S.F_STRAIGHT] = 0.003**2
    sigma_p = 0.15 * math.sqrt(0.04**2 + 0.005**2 + 0.003**2)  # the slip level's RMS
    f.P[0, S.GROUND_PATCH, S.GROUND_PATCH] = 1e-6
    f.P[0, S.GROUND_PATCH, S.F_STRAIGHT] = f.P[0, S.F_STRAIGHT, S.GROUND_PATCH] = -5e-7
    _ground_patch(f, P1, cfg)  # 1 m driven of a 150 m patch
    e = math.exp(-1.0 / 150.0)
    assert f.x[0, S.GROUND_PATCH] == pytest.approx(0.01 * e)
    assert f.P[0, S.GROUND_PATCH, S.GROUND_PATCH] == pytest.approx(
        e * e * 1e-6 + sigma_p**2 * (1 - e * e)
    )
    assert f.P[0, S.F_STRAIGHT, S.GROUND_PATCH] == pytest.approx(-5e-7 * e)
    for _ in range(3000):  # 3 km: forgotten, its variance back to the ground's
        _ground_patch(f, P1, cfg)
    assert abs(f.x[0, S.GROUND_PATCH]) < 1e-10
    assert f.P[0, S.GROUND_PATCH, S.GROUND_PATCH] == pytest.approx(sigma_p**2, rel=1e-6)
    f.x[0, S.SPEED] = 0.0  # standing: the patch stays
    f.x[0, S.GROUND_PATCH] = 0.01
    _ground_patch(f, P1, cfg)
    assert f.x[0, S.GROUND_PATCH] == 0.01


def test_every_odometer_factor_is_the_grounds_mean_plus_its_patch() -> None:
    cfg = TrackedEstimatorConfig()
    x = np.zeros((1, N_STATES))
    x[0, S.SPEED], x[0, S.F_STRAIGHT], x[0, S.F_LOW] = 4.0, 0.97, 0.01
    x[0, S.GROUND_PATCH] = -0.02
    y, H, _, _, corrected = _steady_odometer(cfg, x, M.STRAIGHT, 4.2, 0.0)
    assert corrected[0] == pytest.approx(4.2 * 0.95)
    assert y[0, 0] == pytest.approx(4.2 - 4.0 / 0.95)
    assert H[0, 0, S.GROUND_PATCH] == pytest.approx(-4.0 / 0.95**2) == H[0, 0, S.F_STRAIGHT]
    _, H, _, _, corrected = _steady_odometer(cfg, x, M.LOW_STRAIGHT, 4.2, 0.0)
    low = 0.97 + 0.01 - 0.02
    assert corrected[0] == pytest.approx(4.2 * low / 1.42)
    assert H[0, 0, S.GROUND_PATCH] == pytest.approx(-1.42 * 4.0 / low**2)


def test_a_dead_reckoned_slip_carries_its_factors_error() -> None:
    """While dead reckoning the odometer's learnt factors are not fused, so the speed's
    variance lacks theirs: ``h_L P_LL h_Lᵀ / h_V²`` is added to the slip's. A pivot whose
    factor was never learnt (±15 %) gives no slip then; beside GNSS it does."""
    cfg = TrackedEstimatorConfig()
    f = initial_filter(cfg)
    f.x, f.P = np.repeat(f.x, 2, axis=0), np.repeat(f.P, 2, axis=0)
    f.started = np.ones(2, dtype=bool)
    f.since_gnss_s = np.array([0.5, 60.0])  # beside GNSS, dead reckoning
    f.x[:, S.SPEED], f.x[:, S.F_STRAIGHT] = 1.0, 0.96  # pivot factor 0.96 - 0.25 = 0.71
    f.P[:, S.SPEED, S.SPEED] = 1e-4
    p2 = VehicleParams.stack([P1, P1])
    w = np.full(2, 0.8)  # fast track at 1 + 0.8·B/2 = 1.8 m/s
    inp = _tick_inputs(
        2,
        odometer_mps=np.full(2, 1.8 / 0.71),
        sprocket_pair_mps=np.array([[0.0, 1.8 / 0.71], [0.0, 1.8 / 0.71]]),
    )
    state = np.full(2, int(M.PIVOT))
    _, _, factor_var, _ = _fuse_odometer(f, inp, p2, cfg, state, w)
    assert factor_var[0] == 0.0
    assert factor_var[1] == pytest.approx((1.8 / 0.71) ** 2 * (0.15**2 + 0.03**2 + 0.007**2))
    *_, valid, braked = _track_slip(f, inp, p2, cfg, w, factor_var)
    assert braked[:, 0].all()
    assert valid[:, 1].tolist() == [True, False]


def test_side_slip_gain_scales_the_turning_pole_up_to_its_cap() -> None:
    """``v_x = ω·min(g_s·L·|V·ω|/(2·μ_t·g), L/2)`` and its derivative by ``g_s``."""
    v, w, length, mu = np.array([3.0, 3.0]), np.array([0.3, 0.3]), np.array([2.5, 2.5]), 0.6
    free = 2.5 * 0.9 / (2.0 * mu * 9.80665)  # 0.191 m ahead of the centre at g_s = 1
    lateral, by_gain = side_slip(v, w, length, np.full(2, mu), np.array([1.5, 8.0]))
    assert lateral == pytest.approx([0.3 * 1.5 * free, 0.3 * 1.25])  # second: capped at L/2
    assert by_gain == pytest.approx([0.3 * free, 0.0])
    arc = np.full(2, int(M.ARC))
    assert lateral_speed(TrackedMode.PRODUCT, arc, v, w, length, np.full(2, mu)) == (
        pytest.approx(0.3 * free)
    )


def test_predict_moves_the_position_by_the_side_slip_gain() -> None:
    x = np.zeros((1, N_STATES))
    x[0, S.SPEED], x[0, S.HEADING] = 3.0, 0.0  # north; lateral is east
    P = np.zeros((1, N_STATES, N_STATES))
    P[0, S.SIDE_SLIP, S.SIDE_SLIP] = 0.25
    _, p_next = predict(
        x,
        P,
        np.zeros(1),
        np.zeros(1),
        np.full(1, 0.1),
        0.1,
        np.zeros((1, N_STATES)),
        np.full(1, 0.2),
    )
    assert p_next[0, S.EAST, S.EAST] == pytest.approx((0.1 * 0.2) ** 2 * 0.25)
    assert p_next[0, S.NORTH, S.NORTH] == pytest.approx(0.0, abs=1e-18)


def test_the_odometers_edges_per_tick_and_the_silence_before_them() -> None:
    ms = 1_000_000
    s = np.array([100, 110, 2_000, 2_030, 2_040, 2_300], dtype=np.int64) * ms
    ticks = np.array([100, 200, 2_000, 2_100, 2_200, 2_300], dtype=np.int64) * ms
    hi = np.searchsorted(s, ticks, side="right")
    lo = np.searchsorted(s, ticks - 100 * ms, side="right")
    count, gap = odometer_edges_at(s, np.zeros(1, dtype=np.int64), lo, hi)
    assert count.tolist() == [1, 1, 1, 2, 0, 1]
    # the first edge ever: no silence known (inf); 110 after 100; 2000 after 1.89 s of
    # silence; 2030 after 30 ms; none in (2100, 2200]; 2300 after 260 ms
    assert gap.tolist() == pytest.approx([math.inf, 0.010, 1.890, 0.030, 0.0, 0.260])
    empty = odometer_edges_at(np.zeros(0, dtype=np.int64), np.zeros(1, dtype=np.int64), lo, lo)
    assert empty[0].tolist() == [0] * 6 and empty[1].tolist() == [0.0] * 6


def test_a_starts_first_odometer_edges_end_a_standstill() -> None:
    cfg = TrackedEstimatorConfig()
    # one edge after a second's silence (a start); one after 0.1 s (a crawl); none; one
    # edge with nothing before it (a vehicle's first edge)
    edges, gap = np.array([1, 1, 0, 1]), np.array([1.0, 0.1, 0.0, math.inf])
    inp = _tick_inputs(4, odometer_edges=edges, odometer_gap_s=gap)
    assert odometer_start(inp, cfg).tolist() == [True, False, False, True]
    p4 = VehicleParams.stack([P1] * 4)
    f = initial_filter(cfg)
    f = dataclasses.replace(
        f, **{k.name: np.repeat(getattr(f, k.name), 4, axis=0) for k in dataclasses.fields(f)}
    )
    state, _ = recognise(f, inp, p4, cfg, np.zeros(4))  # every window silent: no speed
    assert state.tolist() == [M.STRAIGHT, M.STOP, M.STOP, M.STRAIGHT]
