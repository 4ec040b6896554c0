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

__all__ = ["fallback_states", "paper_states", "product_states", "turn_radius_m"]

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


def product_states(
    sprocket_mps: FloatArray,
    gear_ratio: FloatArray,
    heading_step_rad: FloatArray,
    p: VehicleParams,
    cfg: TrackedEstimatorConfig,
    yaw_rate_radps: FloatArray,
) -> tuple[IntArray, FloatArray]:
    """State and confidence per vehicle from the sprocket speeds ``(k, 2)``, the faster
    sprocket over the odometer (``gear_ratio``, same span), the tick's heading change and the
    yaw rate (a ratio in the separated band without the turn it makes is a straight)."""
    fast = sprocket_mps.max(axis=1)
    slow = sprocket_mps.min(axis=1)
    moving = fast > p.stop_speed_mps
    with np.errstate(divide="ignore", invalid="ignore"):
        q = np.where(moving, slow / fast, 1.0)
        gear = np.where(moving & np.isfinite(gear_ratio), gear_ratio, 1.0)
    low_cut = 0.5 * (1.0 + 1.0 / p.low_gear_ratio)
    cuts = np.array([cfg.braked_ratio_max, cfg.arc_ratio_max, cfg.straight_ratio_min])
    band = np.searchsorted(cuts, q)  # 0 pivot, 1 arc, 2 separated, 3 straight
    table = np.array([M.PIVOT, M.ARC, M.SEPARATED, M.STRAIGHT], dtype=np.int64)
    out = table[band]
    out[(band == 3) & (gear < low_cut)] = int(M.LOW_STRAIGHT)
    # a separated turn turns: at least a share of the kinematic ω = Vs_fast·(1 − q)/B
    kinematic = fast * (1.0 - q) / p.gauge_m
    still_straight = (band == 2) & (np.abs(yaw_rate_radps) < cfg.separated_yaw_share * kinematic)
    out[still_straight] = int(M.STRAIGHT)
    margin = np.min(np.abs(q[:, None] - cuts[None, :]), axis=1)
    margin = np.where(band == 3, np.minimum(margin, np.abs(gear - low_cut)), margin)
    conf = ndtr(margin / cfg.ratio_std)
    jump = np.abs(heading_step_rad) > p.heading_jump_rad
    out[jump] = int(M.HEADING_JUMP)
    jump_margin = np.abs(np.abs(heading_step_rad) - p.heading_jump_rad)
    conf = np.where(jump, ndtr(jump_margin / (0.1 * p.heading_jump_rad)), conf)
    out[~moving] = int(M.STOP)
    conf = np.where(moving, conf, 1.0)
    return out, conf


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
