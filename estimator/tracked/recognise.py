"""Motion-state recognisers (``method.md`` §4, source 002 §2), batched over vehicles.

:func:`paper_states` applies the source's rules as printed, first match wins in the paper's
order: large heading change (Eq. 16), straight ``|ρ| > R_max`` split by Eq. 6
``v_o ≥ 1.42·v_y`` (a windowed odometer speed against the instantaneous INS speed, as
printed), pivot ``r ≤ |ρ| < R_II`` (Eq. 11, ``r = 1.531·B/2``), arc ``r ≤ |ρ| ≤ 2·R_II^max``
(Eq. 14, ``R_II^max = 2·R_II``) and separated ``|ρ| > 2·R_II`` (Eq. 15). Eq. 14 and 15 overlap on
``(2·R_II, 4·R_II]`` (the arc wins, being first); ``|ρ| < r`` matches no rule and is taken as
straight (the odometer used as it is). A standstill (no rule in the source) is STOP.

:func:`product_states` reads the levers from the sprockets instead: the slow-over-fast ratio
``q`` is 1 (straight), ``1/1.42`` (arc), between (separated) or ~0 (pivot: one track braked;
both braked: stop); the fast sprocket over the odometer, 1 or 1/1.42, tells the low gear.
Its confidence is the normal probability of the margin to the nearest threshold.
Arrays are shape ``(k,)``, one entry per vehicle.
"""

from __future__ import annotations

import numpy as np
from scipy.special import ndtr

from estimator._arrays import BoolArray, FloatArray, IntArray
from estimator.tracked.model import MotionState
from estimator.tracked.params import VehicleParams
from estimator.tracked.settings import TrackedEstimatorConfig

__all__ = [
    "change_onset",
    "fallback_states",
    "gearbox_bound",
    "gearbox_speed",
    "paper_states",
    "product_states",
    "ratio_noise",
    "turn_radius_m",
]

M = MotionState


def turn_radius_m(speed_mps: FloatArray, yaw_rate_radps: FloatArray) -> FloatArray:
    """``|ρ| = |v_y/φ̇|`` (Eq. 1), +inf where the yaw rate is zero."""
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = np.abs(speed_mps / yaw_rate_radps)
    return np.where(np.isfinite(rho), rho, np.inf)


def _common(
    out: IntArray,
    speed_mps: FloatArray,
    odometer_mps: FloatArray,
    heading_step_rad: FloatArray,
    p: VehicleParams,
) -> IntArray:
    """Large heading change (Eq. 16) over the radius rules, standstill over both."""
    out[np.abs(heading_step_rad) > p.heading_jump_rad] = int(M.HEADING_JUMP)
    still = (np.abs(speed_mps) < p.stop_speed_mps) & (odometer_mps < p.stop_speed_mps)
    out[still] = int(M.STOP)
    return out


def paper_states(
    speed_mps: FloatArray,
    yaw_rate_radps: FloatArray,
    odometer_mps: FloatArray,
    heading_step_rad: FloatArray,
    p: VehicleParams,
) -> IntArray:
    """The source's state per vehicle (see the module docstring)."""
    rho = turn_radius_m(speed_mps, yaw_rate_radps)
    r, r_ii = p.pivot_radius_m, p.separated_radius_m
    out = np.full(speed_mps.shape, int(M.STRAIGHT), dtype=np.int64)
    rules = [
        (rho > 2.0 * r_ii, M.SEPARATED),
        ((rho >= r) & (rho <= 4.0 * r_ii), M.ARC),
        ((rho >= r) & (rho < r_ii), M.PIVOT),
        (rho > p.straight_radius_m, M.STRAIGHT),
    ]
    for hit, state in rules:  # last assignment wins: applied in reverse of the paper's order
        out[hit] = int(state)
    low = (rho > p.straight_radius_m) & (odometer_mps >= p.low_gear_ratio * speed_mps)
    out[low] = int(M.LOW_STRAIGHT)
    return _common(out, speed_mps, odometer_mps, heading_step_rad, p)


def _ratios(
    sprocket_mps: FloatArray, gear_ratio: FloatArray, p: VehicleParams
) -> tuple[BoolArray, FloatArray, FloatArray]:
    """``(read, q, g)``: sprockets read (fast one above the stop speed), slow over fast
    sprocket ``q`` and fast sprocket over odometer ``g`` (1 where unread or unknown)."""
    fast = sprocket_mps.max(axis=1)
    read = fast > p.stop_speed_mps
    with np.errstate(divide="ignore", invalid="ignore"):
        q = np.where(read, sprocket_mps.min(axis=1) / fast, 1.0)
        g = np.where(read & np.isfinite(gear_ratio), gear_ratio, 1.0)
    return read, q, g


def _lever_target(
    now: FloatArray,
    before: FloatArray,
    both: BoolArray,
    cfg: TrackedEstimatorConfig,
    noise: FloatArray | None = None,
) -> tuple[FloatArray, BoolArray]:
    """Where a moving lever takes a ratio: a lever crosses its travel in ``lever_travel_s`` at
    a steady rate ``r = Δ/travel``, so a ratio changing faster than ``lever_rate_min_per_s``
    over the tick, and faster than ``lever_noise_sigmas`` times what its window noise
    ``noise`` ``(k,)`` makes of a change over a tick (``√2·σ/tick``: at a crawl the reads
    jump by more than a lever moves), ends near ``before + r·travel`` (clipped to [0, 1]);
    ``(target, moving)``."""
    rate = (now - before) / cfg.tick_s
    rate_min = cfg.lever_rate_min_per_s
    if noise is not None:
        noisy = cfg.lever_noise_sigmas * np.sqrt(2.0) * noise / cfg.tick_s
        rate_min = np.maximum(rate_min, noisy)
    moving = both & (np.abs(rate) > rate_min)
    target = np.clip(before + rate * cfg.lever_travel_s, 0.0, 1.0)
    return np.where(moving, target, now), moving


def ratio_noise(
    sprocket_mps: FloatArray, accel_mps2: FloatArray, p: VehicleParams, cfg: TrackedEstimatorConfig
) -> FloatArray:
    """1-sigma ``(k,)`` of the slow-over-fast sprocket ratio ``q`` read through the windows.

    Per sprocket, a relative error of: the teeth's position error ``e``
    (``sprocket_tooth_std_pitch``, a share of the pitch) over a window of ``n`` periods,
    ``√2·e/n`` (first and last edge each off by ``e``; ``n`` the fewest periods a window
    ``W`` holds at speed ``v``, ``clip(⌊v·W/pitch⌋ − 1, 1, max_edges − 1)``, two held edges
    at least); the speed's change over one period ``|a|·pitch/v²`` (``a`` the gearbox's
    acceleration, not the hull's, which also slows in a lever move; the sprockets' edges
    fall at different phases, so while the gearbox speeds up or slows down the two windows
    read it up to a period apart); and the carry of each window's speed from its centre to
    the tick, ``σ_a·lag/v`` with the odometer acceleration's 1-sigma ``σ_a``
    (``carry_accel_std_mps2``) and ``lag = max(W/2, 1.5·pitch/v)`` (at a crawl the held
    pair's centre is one to two periods back). ``q``'s relative error adds both sprockets';
    ``accel_mps2`` ``(k,)``, ``sprocket_mps`` ``(k, 2)``.
    """
    pitch = p.sprocket_pitch_m[:, None]
    v = np.maximum(sprocket_mps, cfg.start_odometer_mps)
    periods = np.floor(v * cfg.sprocket_window_s / pitch) - 1.0
    periods = np.clip(periods, 1.0, cfg.sprocket_max_edges - 1.0)
    teeth = np.sqrt(2.0) * cfg.sprocket_tooth_std_pitch / periods
    change = np.abs(np.nan_to_num(accel_mps2))[:, None] * pitch / v**2
    lag_s = np.maximum(0.5 * cfg.sprocket_window_s, 1.5 * pitch / v)
    carry = cfg.carry_accel_std_mps2 * lag_s / v
    return np.sqrt((teeth**2 + change**2 + carry**2).sum(axis=1))


def gearbox_speed(
    odometer_mps: FloatArray, odometer_lag_s: FloatArray, gearbox_accel_mps2: FloatArray
) -> FloatArray:
    """The gearbox's speed at the tick ``(k,)``: the odometer's window speed carried from its
    centre, ``max(v_o + a·lag, 0)`` (NaN where the odometer is unknown)."""
    accel = np.nan_to_num(gearbox_accel_mps2)
    return np.maximum(odometer_mps + accel * odometer_lag_s, 0.0)


def gearbox_bound(
    sprocket_mps: FloatArray,
    odometer_mps: FloatArray,
    odometer_lag_s: FloatArray,
    gearbox_accel_mps2: FloatArray,
    cfg: TrackedEstimatorConfig,
) -> FloatArray:
    """Sprocket speeds ``(k, 2)`` no faster than ``sprocket_over_gearbox_max`` times the
    gearbox's speed at the tick, ``v_o + a·lag`` (the odometer's window speed carried from its
    centre, at least 0; ``(k,)`` each) while the gearbox slows. A sprocket turns at the
    gearbox's speed times 1, ``1/1.42`` or 0, so a read above that bound is a window holding
    the speed of before a stop (a window only lags: above the present speed only while the
    gearbox slows); read at the bound, the stop is not taken for a pivot (one sprocket's
    window silent, the other's still holding). Where the odometer is unknown, or the gearbox
    does not slow, nothing is bounded."""
    accel = np.nan_to_num(gearbox_accel_mps2)
    gearbox = gearbox_speed(odometer_mps, odometer_lag_s, gearbox_accel_mps2)
    slowing = np.isfinite(gearbox) & (accel < 0.0)
    limit = np.where(slowing, cfg.sprocket_over_gearbox_max * gearbox, np.inf)
    return np.minimum(sprocket_mps, limit[:, None])


def product_states(
    sprocket_mps: FloatArray,
    gear_ratio: FloatArray,
    heading_step_rad: FloatArray,
    p: VehicleParams,
    cfg: TrackedEstimatorConfig,
    yaw_lead_radps: FloatArray,
    odometer_mps: FloatArray,
    before: tuple[FloatArray, FloatArray] | None = None,
    accel_mps2: FloatArray | None = None,
) -> tuple[IntArray, FloatArray]:
    """State and confidence per vehicle from the sprocket speeds ``(k, 2)``, the faster
    sprocket over the odometer (``gear_ratio``, same span), the tick's heading change, the
    larger of the yaw rate and the rate the hull is heading for, ``ω + τ·ω̇`` (a ratio in the
    separated band without the turn it makes is a straight; the hull follows its tracks with
    the lag ``τ``, so a turn being entered shows in ``ω̇`` before ``ω``), the odometer speed
    (its edges come ~17 times as often as a sprocket's: a start from standstill is a
    straight as soon as it turns, before the sprockets have two edges) and ``before``, the
    sprocket speeds and gear ratio of the tick before: while a lever moves, the ratios are
    read where it takes them (:func:`_lever_target`), so the state changes with the lever,
    not when the windows have crossed a threshold. ``accel_mps2`` (the gearbox's, 0 if None)
    enters the ratio's window noise (:func:`ratio_noise`), which decides where the
    separated band needs its turn's yaw rate and how fast a ratio must change to be a
    lever."""
    read, q, gear = _ratios(sprocket_mps, gear_ratio, p)
    accel = np.zeros(q.shape) if accel_mps2 is None else accel_mps2
    noise = ratio_noise(sprocket_mps, accel, p, cfg)
    lever = np.zeros(q.shape, dtype=bool)
    if before is not None:
        q, gear, lever = _lever_ratios((read, q, gear), before, p, cfg, noise)
    moving = read | (np.nan_to_num(odometer_mps) > cfg.start_odometer_mps)
    fast = sprocket_mps.max(axis=1)
    low_cut = 0.5 * (1.0 + 1.0 / p.low_gear_ratio)
    cuts = np.array([cfg.braked_ratio_max, cfg.arc_ratio_max, cfg.straight_ratio_min])
    band = np.searchsorted(cuts, q)  # 0 pivot, 1 arc, 2 separated, 3 straight
    table = np.array([M.PIVOT, M.ARC, M.SEPARATED, M.STRAIGHT], dtype=np.int64)
    out = table[band]
    out[(band == 3) & (gear < low_cut)] = int(M.LOW_STRAIGHT)
    weak = (band == 2) & ~lever & _turn_not_shown(q, fast, noise, yaw_lead_radps, p, cfg)
    out[weak] = np.where(gear[weak] < low_cut[weak], int(M.LOW_STRAIGHT), int(M.STRAIGHT))
    margin = np.min(np.abs(q[:, None] - cuts[None, :]), axis=1)
    margin = np.where(band == 3, np.minimum(margin, np.abs(gear - low_cut)), margin)
    conf = ndtr(margin / cfg.ratio_std)
    return _jump_and_stop(out, conf, heading_step_rad, moving, p)


def _lever_ratios(
    ratios: tuple[BoolArray, FloatArray, FloatArray],
    before: tuple[FloatArray, FloatArray],
    p: VehicleParams,
    cfg: TrackedEstimatorConfig,
    noise: FloatArray,
) -> tuple[FloatArray, FloatArray, BoolArray]:
    """The sprocket ratio and gear ratio ``(k,)`` read where a moving lever takes them
    (:func:`_lever_target`), from this tick's ``ratios`` (read, q, gear) and the tick
    before's sprocket speeds ``(k, 2)`` and gear ratio; ``(q, gear, lever)``."""
    read, q, gear = ratios
    read_b, q_b, gear_b = _ratios(before[0], before[1], p)
    q, lever_q = _lever_target(q, q_b, read & read_b, cfg, noise)
    gear, lever_g = _lever_target(
        gear, gear_b, read & read_b & (q >= cfg.straight_ratio_min), cfg, noise
    )
    return q, gear, lever_q | lever_g


def _turn_not_shown(
    q: FloatArray,
    fast: FloatArray,
    noise: FloatArray,
    yaw_lead_radps: FloatArray,
    p: VehicleParams,
    cfg: TrackedEstimatorConfig,
) -> BoolArray:
    """A separated ratio ``q`` ``(k,)`` within the windows' noise of 1 that does not show its
    turn: at least a share of the kinematic ``ω = Vs_fast·(1 − q)/B``, and more than a
    straight's yaw noise (a crawl's kinematic ω is within it); farther from 1 the ratio alone
    is the lever."""
    kinematic = fast * (1.0 - q) / p.gauge_m
    doubtful = (1.0 - q) < cfg.separated_check_sigmas * noise
    shown = np.maximum(cfg.separated_yaw_share * kinematic, cfg.yaw_lead_noise_radps)
    return doubtful & (yaw_lead_radps < shown)


def _jump_and_stop(
    out: IntArray,
    conf: FloatArray,
    heading_step_rad: FloatArray,
    moving: BoolArray,
    p: VehicleParams,
) -> tuple[IntArray, FloatArray]:
    """The states ``out`` and confidences ``conf`` ``(k,)`` with a heading jump over the
    tick's heading step ``(k,)`` and a stop (not ``moving``) taking precedence, in that order."""
    jump = np.abs(heading_step_rad) > p.heading_jump_rad
    out[jump] = int(M.HEADING_JUMP)
    jump_margin = np.abs(np.abs(heading_step_rad) - p.heading_jump_rad)
    conf = np.where(jump, ndtr(jump_margin / (0.1 * p.heading_jump_rad)), conf)
    out[~moving] = int(M.STOP)
    conf = np.where(moving, conf, 1.0)
    return out, conf


def change_onset(
    sprocket_mps: FloatArray,
    gear_ratio: FloatArray,
    before: tuple[FloatArray, FloatArray],
    settling: BoolArray,
    yaw_accel_radps2: FloatArray,
    p: VehicleParams,
    cfg: TrackedEstimatorConfig,
    accel_mps2: FloatArray | None = None,
    odometer_mps: FloatArray | None = None,
) -> BoolArray:
    """Ticks ``(k,)`` on which a state change shows: a ratio moving faster than
    ``lever_rate_min_per_s`` (a lever, :func:`_lever_target`), a sprocket settling
    (``settling`` ``(k, 2)``) or the yaw acceleration out of its band
    ``|ω̇| > onset_yaw_accel_radps2`` (the hull entering or leaving a turn), or a start or
    stop under way: the gearbox (``accel_mps2``, 0 if None) speeding up or braking harder than
    ``lever_accel_mps2`` within reach of standstill, its odometer speed (``odometer_mps``)
    below ``|a|`` times the fixed lag (a stop is read once the windows fall silent, a start
    once the odometer has edges: the ticks before are backdated)."""
    read, q, gear = _ratios(sprocket_mps, gear_ratio, p)
    read_b, q_b, gear_b = _ratios(before[0], before[1], p)
    both = read & read_b
    accel = np.zeros(q.shape) if accel_mps2 is None else accel_mps2
    noise = ratio_noise(sprocket_mps, accel, p, cfg)
    _, lever_q = _lever_target(q, q_b, both, cfg, noise)
    _, lever_g = _lever_target(gear, gear_b, both, cfg, noise)
    yawing = np.abs(yaw_accel_radps2) > cfg.onset_yaw_accel_radps2
    onset = lever_q | lever_g | settling.any(axis=1) | yawing
    if odometer_mps is None:
        return onset
    reach_mps = np.abs(accel) * cfg.report_lag_ticks * cfg.tick_s
    speed = np.nan_to_num(odometer_mps)
    return onset | ((np.abs(accel) > cfg.lever_accel_mps2) & (speed < reach_mps))


def fallback_states(
    speed_mps: FloatArray,
    yaw_rate_radps: FloatArray,
    odometer_mps: FloatArray,
    heading_step_rad: FloatArray,
    p: VehicleParams,
    low_mask: BoolArray,
) -> IntArray:
    """Without sprockets: the source's radius rules with the overlaps removed (pivot below
    ``R_II``, arc to ``2·R_II``, separated to ``R_max``), the low gear from ``low_mask``."""
    rho = turn_radius_m(speed_mps, yaw_rate_radps)
    r_ii = p.separated_radius_m
    bounds = np.stack([r_ii, 2.0 * r_ii, p.straight_radius_m], axis=1)
    band = (rho[:, None] > bounds).sum(axis=1)
    table = np.array([M.PIVOT, M.ARC, M.SEPARATED, M.STRAIGHT], dtype=np.int64)
    out = table[band]
    out[(band == 3) & low_mask] = int(M.LOW_STRAIGHT)
    return _common(out, speed_mps, odometer_mps, heading_step_rad, p)
