"""One tick of the tracked estimator for ``k`` vehicles at once: recognise the motion state,
predict, fuse GNSS, the corrected odometer and (product) standstill, and derive track slip.

Stages, each its own function: :func:`recognise`, :func:`_ground_patch` (the patch of ground
dying out over the distance driven), :func:`_start` (first GNSS fix at speed),
:func:`_fuse_gnss`, :func:`_fuse_odometer`, :func:`_fuse_standstill`, :func:`_track_slip`.
Arrays are batched over the leading axis ``k``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from estimator._arrays import BoolArray, FloatArray, IntArray
from estimator.tracked.filter import GRAVITY_MPS2, hull_accel, kalman_update, predict, yaw_rate
from estimator.tracked.gyro_noise import initial_stats, learn_standing, noise_ratio
from estimator.tracked.model import N_STATES, MotionState, TrackedMode
from estimator.tracked.model import TrackedState as S
from estimator.tracked.odometer import (
    lateral_speed,
    odometer_measurement,
    side_creep,
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
)
from estimator.tracked.settings import TrackedEstimatorConfig
from estimator.tracked.vehicle import TickInputs

__all__ = [
    "Filter",
    "TickOut",
    "accel_speed_var",
    "accel_steady",
    "creep_roll_band",
    "fix_age_s",
    "fresh_patch_var",
    "hull_settled",
    "initial_filter",
    "patch_std",
    "standing_rate_var",
    "state_lead_s",
    "tick_step",
]

M = MotionState
_FACTORS = [S.F_STRAIGHT, S.F_LOW, S.TURN_SLIP, S.F_PIVOT]
#: What the odometer teaches beside GNSS only: the factors and the ground's patch.
_LEARNED = [*_FACTORS, S.GROUND_PATCH]
#: Every state the odometer's model reads but fuses only beside GNSS.
_BESIDE_ONLY = [*_LEARNED, S.ACCEL_LAG, S.ACCEL_SLIP]


@dataclass(slots=True)
class Filter:
    """Filter state of ``k`` vehicles: ``x (k, n)``, ``P (k, n, n)``, ``started (k,)``,
    ``since_gnss_s (k,)`` (time since the last fused fix), ``gated_s (k,)`` (how long every
    fix has been refused by the gate); since the last fused fix, ``since_gnss_m (k,)`` the
    distance driven and ``odometer_gain (k, m)`` how far the odometer's learnt states
    (``_BESIDE_ONLY``, ``m`` = 7) have moved the hull per unit of their error at the fix,
    whose covariance then was ``fix_learnt_cov (k, m, m)``
    (:func:`_dead_reckoning_noise`); ``gyro_standing (k, 3)`` the gyro's noise measured
    while standing (:mod:`~estimator.tracked.gyro_noise`); ``accel_steady_s (k,)`` how long
    the hull's own acceleration (gravity out) has stayed below ``learn_accel_max_mps2``."""

    x: FloatArray
    P: FloatArray
    started: BoolArray
    since_gnss_s: FloatArray
    gated_s: FloatArray
    since_gnss_m: FloatArray
    odometer_gain: FloatArray
    fix_learnt_cov: FloatArray
    gyro_standing: FloatArray
    accel_steady_s: FloatArray


@dataclass(frozen=True, slots=True)
class TickOut:
    """What one tick gives per vehicle, shapes ``(k,)`` (``*_pair``: ``(k, 2)``)."""

    state: IntArray
    confidence: FloatArray
    yaw_rate_radps: FloatArray
    lateral_mps: FloatArray
    odometer_mps: FloatArray
    odometer_used: BoolArray
    gnss_used: BoolArray
    gnss_gated: BoolArray
    gnss_nis: FloatArray
    track_pair_mps: FloatArray
    track_std_mps: FloatArray
    slip_pair_pct: FloatArray
    slip_std_pair_pct: FloatArray
    slip_valid_pair: BoolArray
    braked_pair: BoolArray
    standstill: BoolArray
    onset: BoolArray


def _initial_p(cfg: TrackedEstimatorConfig) -> FloatArray:
    learn = 1.0 if cfg.learns else 0.0
    diag = np.zeros(N_STATES)
    diag[[S.EAST, S.NORTH]] = cfg.initial_position_std_m**2
    diag[S.HEADING] = cfg.initial_heading_std_rad**2
    diag[S.SPEED] = cfg.initial_speed_std_mps**2
    diag[S.GYRO_BIAS] = learn * cfg.initial_gyro_bias_std_radps**2
    diag[S.GYRO_SCALE] = learn * cfg.initial_gyro_scale_std**2
    diag[_FACTORS] = learn * cfg.initial_factor_std**2
    diag[S.F_PIVOT] = learn * cfg.initial_pivot_factor_std**2
    diag[S.F_LOW] = learn * cfg.initial_low_offset_std**2
    diag[S.TURN_SLIP] = learn * cfg.initial_turn_slip_std**2
    diag[S.ACCEL_LAG] = learn * cfg.initial_accel_lag_std_s**2
    diag[S.ACCEL_SLIP] = learn * cfg.initial_accel_slip_std_s2pm**2
    diag[S.GROUND_PATCH] = learn * cfg.ground_patch_slip_std**2
    diag[S.SIDE_SLIP] = learn * cfg.initial_side_slip_std**2
    diag[[S.PITCH, S.ROLL]] = cfg.initial_tilt_std_rad**2
    diag[[S.PITCH_GYRO_BIAS, S.ROLL_GYRO_BIAS]] = cfg.initial_gyro_bias_std_radps**2
    diag[[S.ACCEL_BIAS_X, S.ACCEL_BIAS_Y]] = learn * cfg.accel_bias_std_mps2**2
    diag[S.GNSS_CLOCK] = learn * cfg.gnss_clock_offset_std_s**2
    return np.diag(diag)


def initial_filter(cfg: TrackedEstimatorConfig) -> Filter:
    """A vehicle's filter before its first fix: factors 1 (the low gear's offset 0, the pivot's
    offset and the turn slip from their priors), position and heading unknown."""
    x = np.zeros((1, N_STATES))
    x[0, _FACTORS] = 1.0
    x[0, S.F_LOW] = 0.0  # offsets from F_straight
    x[0, S.F_PIVOT] = -cfg.initial_pivot_slip if cfg.learns else 0.0
    x[0, S.TURN_SLIP] = cfg.initial_turn_slip if cfg.learns else 0.0
    x[0, S.ACCEL_SLIP] = cfg.initial_accel_slip_s2pm if cfg.learns else 0.0
    x[0, S.SIDE_SLIP] = 1.0
    P = _initial_p(cfg)[None].copy()
    P[0, S.HEADING, S.HEADING] = 10.0
    P[0, [S.EAST, S.NORTH], [S.EAST, S.NORTH]] = 1e6
    m = len(_BESIDE_ONLY)
    return Filter(
        x,
        P,
        np.zeros(1, dtype=bool),
        np.full(1, np.inf),
        np.zeros(1),
        np.zeros(1),
        np.zeros((1, m)),
        np.zeros((1, m, m)),
        initial_stats(1),
        np.zeros(1),
    )


def accel_speed_var(p: VehicleParams, imu_samples: IntArray, tick_s: float) -> FloatArray:
    """Variance ``(k,)`` the accelerometer's white noise adds to the forward speed over a
    tick: the prediction integrates the tick's mean specific force, the mean of ``N``
    (``imu_samples``) samples of noise ``σ_a`` (the config's ``noise.accel_std_mps2``), so
    ``Var ΔV = Δt²·σ_a²/N`` (``N`` taken as at least 1)."""
    n = np.maximum(np.asarray(imu_samples, dtype=np.float64), 1.0)
    return np.asarray(tick_s**2 * p.accel_std_mps2**2 / n)


def _q_diag(
    cfg: TrackedEstimatorConfig,
    p: VehicleParams,
    lateral_mps: FloatArray,
    gyro_ratio: FloatArray,
    imu_samples: IntArray,
) -> FloatArray:
    """Process noise per tick, ``(k, N_STATES)``; the heading's and the gyro bias's from each
    vehicle's gyro (``r·ARW²·Δt``, ``r·walk²·Δt``, :mod:`estimator.gyro`; ``gyro_ratio``
    ``r (k,)`` the unit's noise over its data sheet's, :mod:`~estimator.tracked.gyro_noise`);
    the speed's the walk the accelerometer does not explain (``speed_walk_mps2``) and its
    own white noise over the tick (:func:`accel_speed_var`, ``imu_samples (k,)``); the
    pitch's, the roll's and their gyro biases' as the yaw's (one gyro part on all axes)."""
    dt = cfg.tick_s
    k = p.gauge_m.shape[0]
    learn = 1.0 if cfg.learns else 0.0
    q = np.zeros((k, N_STATES))
    pos = cfg.position_walk_mps**2 + (cfg.lateral_model_error * lateral_mps) ** 2
    q[:, S.EAST] = q[:, S.NORTH] = pos * dt
    q[:, S.HEADING] = gyro_ratio * p.gyro_arw_rad_rt_s**2 * dt
    q[:, S.SPEED] = cfg.speed_walk_mps2**2 * dt + accel_speed_var(p, imu_samples, dt)
    q[:, S.GYRO_BIAS] = learn * gyro_ratio * p.gyro_bias_walk_radps_rt_s**2 * dt
    q[:, S.GYRO_SCALE] = learn * cfg.gyro_scale_walk**2 * dt
    q[:, _FACTORS] = learn * cfg.factor_walk**2 * dt
    q[:, S.ACCEL_LAG] = learn * cfg.accel_lag_walk_s**2 * dt
    q[:, S.ACCEL_SLIP] = learn * cfg.accel_slip_walk_s2pm**2 * dt
    q[:, S.SIDE_SLIP] = learn * cfg.side_slip_walk**2 * dt
    q[:, [S.PITCH, S.ROLL]] = (gyro_ratio * p.gyro_arw_rad_rt_s**2 * dt)[:, None]
    q[:, [S.PITCH_GYRO_BIAS, S.ROLL_GYRO_BIAS]] = (
        gyro_ratio * p.gyro_bias_walk_radps_rt_s**2 * dt
    )[:, None]
    q[:, [S.ACCEL_BIAS_X, S.ACCEL_BIAS_Y]] = learn * cfg.accel_bias_walk_mps2_rt_s**2 * dt
    q[:, S.GNSS_CLOCK] = learn * cfg.gnss_clock_offset_walk_s_rt_s**2 * dt
    return q


def patch_std(f: Filter, p: VehicleParams, cfg: TrackedEstimatorConfig) -> FloatArray:
    """1-sigma ``σ_p`` of the ground's patch per vehicle, shape ``(k,)``: ``r·√((1 − F)² +
    σ_KD² + σ_F²)``, ``r`` = ``ground_patch_rel_std``. ``1 − F`` (``F`` the straight's learnt
    factor) is the ground's traction slip less ``K_D``'s error, so the slip level is known to
    ``K_D``'s 1-sigma ``σ_KD`` and the factor's own ``σ_F``: its root mean square given what
    is known is taken."""
    var_f = np.maximum(f.P[:, S.F_STRAIGHT, S.F_STRAIGHT], 0.0)
    level = 1.0 - f.x[:, S.F_STRAIGHT]
    return cfg.ground_patch_rel_std * np.sqrt(level**2 + p.odometer_scale_std**2 + var_f)


def _ground_patch(f: Filter, p: VehicleParams, cfg: TrackedEstimatorConfig) -> None:
    """The patch state ``p`` over a tick (product): a Gauss-Markov process over the distance
    ``Δd = |V|·Δt``, ``p' = e·p`` with ``e = exp(−Δd/ℓ)`` and ``Var p' = e²·Var p +
    σ_p²·(1 − e²)`` (``ℓ`` = ``ground_patch_m``, ``σ_p`` from :func:`patch_std`): a
    patch learned beside GNSS is forgotten as the tracks leave it. ``x``, ``P`` in place."""
    if not cfg.learns:
        return
    g = S.GROUND_PATCH
    e = np.exp(-np.abs(f.x[:, S.SPEED]) * cfg.tick_s / cfg.ground_patch_m)
    f.x[:, g] *= e
    f.P[:, g, :] *= e[:, None]
    f.P[:, :, g] *= e[:, None]
    f.P[:, g, g] += patch_std(f, p, cfg) ** 2 * (1.0 - e * e)


def fresh_patch_var(d_m: FloatArray, sigma_p: FloatArray, patch_m: float) -> FloatArray:
    """Variance ``(k,)`` of ``∫₀^d w(s) ds``, ``w`` the patches met since the last fix (the
    Gauss-Markov patch of 1-sigma ``σ_p`` and length ``ℓ``, started at 0 there):
    ``σ_p²·ℓ²·(2x − 2u − u²)``, ``x = d/ℓ``, ``u = 1 − exp(−x)``; ``≈ (2/3)·σ_p²·d³/ℓ``
    near the fix, ``≈ 2·σ_p²·ℓ·d`` far from it."""
    x = d_m / patch_m
    u = -np.expm1(-x)
    return np.asarray(sigma_p**2 * patch_m**2 * np.maximum(2.0 * x - 2.0 * u - u * u, 0.0))


def _dead_reckoning_noise(
    f: Filter, p: VehicleParams, cfg: TrackedEstimatorConfig, gain: FloatArray
) -> None:
    """While dead reckoning (no fix fused for over a second; product mode), the along-track
    position variance the odometer's learnt states make over the tick. They are not fused
    without GNSS (their ``H`` zeroed), so their error at the last fix, covariance ``P_L``
    (``fix_learnt_cov``), moves the hull by ``Gᵀ·ε_L`` with ``G = ∫ g dt`` (``g`` ``(k, m)``
    the tick's speed per unit of each state's error, ``−h_L/h_V``, the patch's scaled by
    ``exp(−d/ℓ)`` as the patch learnt at the fix dies out); its variance ``GᵀP_L G`` grows
    with ``G``, and the patches met since by :func:`fresh_patch_var` over the distance ``d``.
    The growth over the tick (never negative) goes along the heading. The factors' walk is
    not added: through an outage the ground's variation is the patches'. ``f`` in place."""
    if not cfg.learns:
        return
    d1 = f.since_gnss_m  # :func:`_since_fix` has counted the tick
    d0 = np.maximum(d1 - np.abs(f.x[:, S.SPEED]) * cfg.tick_s, 0.0)
    g = gain.copy()
    g[:, _BESIDE_ONLY.index(S.GROUND_PATCH)] *= np.exp(-d0 / cfg.ground_patch_m)
    g0 = f.odometer_gain
    g1 = g0 + g * cfg.tick_s
    f.odometer_gain = g1
    dr = f.started & (f.since_gnss_s > 1.0)
    if not dr.any():
        return
    P_L = f.fix_learnt_cov
    known = np.einsum("ki,kij,kj->k", g1, P_L, g1) - np.einsum("ki,kij,kj->k", g0, P_L, g0)
    sigma_p = patch_std(f, p, cfg)
    fresh = fresh_patch_var(d1, sigma_p, cfg.ground_patch_m)
    fresh -= fresh_patch_var(d0, sigma_p, cfg.ground_patch_m)
    q = np.where(dr, np.maximum(known + fresh, 0.0), 0.0)
    s, c = np.sin(f.x[:, S.HEADING]), np.cos(f.x[:, S.HEADING])
    e, n = S.EAST, S.NORTH
    f.P[:, e, e] += q * s * s
    f.P[:, n, n] += q * c * c
    f.P[:, e, n] += q * s * c
    f.P[:, n, e] += q * s * c


def _since_fix(f: Filter, fixed: BoolArray, cfg: TrackedEstimatorConfig) -> None:
    """Time and distance since the last fused fix (this tick counted); at a fix, the learnt
    states' covariance is kept and the odometer's gain starts afresh."""
    f.since_gnss_s = np.where(fixed, 0.0, f.since_gnss_s + cfg.tick_s)
    step_m = np.abs(f.x[:, S.SPEED]) * cfg.tick_s
    f.since_gnss_m = np.where(fixed, 0.0, f.since_gnss_m + step_m)
    if not fixed.any():
        return
    f.odometer_gain = np.where(fixed[:, None], 0.0, f.odometer_gain)
    cov = f.P[:, _BESIDE_ONLY][:, :, _BESIDE_ONLY]
    f.fix_learnt_cov = np.where(fixed[:, None, None], cov, f.fix_learnt_cov)


def recognise(
    f: Filter, inp: TickInputs, p: VehicleParams, cfg: TrackedEstimatorConfig, w: FloatArray
) -> tuple[IntArray, FloatArray]:
    """Motion state and confidence (:mod:`estimator.tracked.recognise`) by mode; ``inp``'s
    ``accel_mps2`` is the hull's own acceleration here (:func:`tick_step`)."""
    v = f.x[:, S.SPEED]
    step = w * cfg.tick_s
    if cfg.mode != TrackedMode.PRODUCT:
        ones = np.ones(v.shape)
        return paper_states(v, w, inp.odometer_mps, step, p), ones
    tau = np.clip(f.x[:, S.ACCEL_LAG], 0.0, cfg.max_yaw_lag_s)
    lead = np.abs(w + tau * inp.yaw_accel_radps2) - cfg.yaw_lead_noise_radps
    lead = np.maximum(np.abs(w), lead)
    before = (inp.sprocket_before_pair_mps, inp.gear_ratio_before)
    sprockets = gearbox_bound(
        inp.sprocket_pair_mps, inp.odometer_mps, inp.odometer_lag_s, inp.gearbox_accel_mps2, cfg
    )
    state, conf = product_states(
        sprockets,
        inp.gear_ratio,
        step,
        p,
        cfg,
        lead,
        gearbox_speed(inp.odometer_mps, inp.odometer_lag_s, inp.gearbox_accel_mps2),
        before,
        inp.gearbox_accel_mps2,
    )
    state = _released(state, inp, p)
    state = np.where((state == int(M.STOP)) & odometer_start(inp, cfg), int(M.STRAIGHT), state)
    missing = inp.sprocket_missing
    if missing.any():
        v_lag = v - inp.accel_mps2 * inp.odometer_lag_s
        low = inp.odometer_mps > 0.5 * (1.0 + p.low_gear_ratio) * np.abs(v_lag)
        fb = fallback_states(v, w, inp.odometer_mps, step, p, low)
        state = np.where(missing, fb, state)
        conf = np.where(missing, 0.5, conf)
    return state, conf


def odometer_start(inp: TickInputs, cfg: TrackedEstimatorConfig) -> BoolArray:
    """Ticks ``(k,)`` whose odometer edges end a silence longer than ``start_silence_s``: the
    gearbox has begun to turn, though one or two edges give its windows no speed yet."""
    return (inp.odometer_edges > 0) & (inp.odometer_gap_s > cfg.start_silence_s)


def _released(state: IntArray, inp: TickInputs, p: VehicleParams) -> IntArray:
    """The slower sprocket giving its first edges after a silence (a pivot's brake released,
    or a start) while the hull moves: the lever goes back to drive, so the state is the straight
    of the gear the odometer says; the windows read that sprocket only from its second edge,
    and while it spins up its ratio passes through the turn bands."""
    slow = np.argmin(inp.sprocket_pair_mps, axis=1)  # a pivot started from rest: not slow
    starting = np.take_along_axis(inp.sprocket_starting_pair, slow[:, None], axis=1)[:, 0]
    released = (state != int(M.STOP)) & starting
    if not released.any():
        return state
    low_cut = 0.5 * (1.0 + 1.0 / p.low_gear_ratio)
    low = np.nan_to_num(inp.gear_ratio, nan=1.0) < low_cut
    straight = np.where(low, int(M.LOW_STRAIGHT), int(M.STRAIGHT))
    return np.where(released, straight, state)


def _start(f: Filter, inp: TickInputs, p: VehicleParams, cfg: TrackedEstimatorConfig) -> BoolArray:
    """Vehicles whose first fix at speed arrives now: position, heading (course) and speed
    taken from it, their uncertainty reset; returns the mask."""
    vel = inp.gnss_vel_pair_mps
    speed = np.hypot(vel[:, 0], vel[:, 1])
    fresh = ~f.started & np.isfinite(speed) & (speed >= cfg.init_speed_mps)
    if not fresh.any():
        return fresh
    psi = np.arctan2(vel[:, 0], vel[:, 1])
    x_ant, y_ant = p.antenna_xy_m[:, 0], p.antenna_xy_m[:, 1]
    east = inp.gnss_pos_pair_m[:, 0] - x_ant * np.cos(psi) - y_ant * np.sin(psi)
    north = inp.gnss_pos_pair_m[:, 1] + x_ant * np.sin(psi) - y_ant * np.cos(psi)
    x = f.x.copy()
    for idx, value in ((S.EAST, east), (S.NORTH, north), (S.HEADING, psi), (S.SPEED, speed)):
        x[:, idx] = np.where(fresh, value, x[:, idx])
    P0 = _initial_p(cfg)
    keep = f.P.copy()
    core = [S.EAST, S.NORTH, S.HEADING, S.SPEED]
    reset = keep.copy()
    reset[:, core, :] = 0.0
    reset[:, :, core] = 0.0
    reset[:, core, core] = P0[core, core]
    f.x = x
    f.P = np.where(fresh[:, None, None], reset, keep)
    f.started = f.started | fresh
    return fresh


def _fuse_lateral_force(
    f: Filter, inp: TickInputs, p: VehicleParams, cfg: TrackedEstimatorConfig, gyro: FloatArray
) -> None:
    """The roll from the lateral accelerometer's tick mean ``f_x = −ω·V − g·cos θ·sin φ + b_x``
    (the turn's centripetal force, gravity's share on a side slope and the accelerometer's
    bias), its variance the mean's white noise ``σ_a²/N`` and ``lateral_force_std_mps2²``;
    ``f`` in place."""
    k = f.x.shape[0]
    w = yaw_rate(f.x, gyro)
    theta, phi, v = f.x[:, S.PITCH], f.x[:, S.ROLL], f.x[:, S.SPEED]
    g = GRAVITY_MPS2
    h = -w * v - g * np.cos(theta) * np.sin(phi) + f.x[:, S.ACCEL_BIAS_X]
    H = np.zeros((k, 1, N_STATES))
    H[:, 0, S.ACCEL_BIAS_X] = 1.0
    H[:, 0, S.SPEED] = -w
    H[:, 0, S.ROLL] = -g * np.cos(theta) * np.cos(phi)
    H[:, 0, S.PITCH] = g * np.sin(theta) * np.sin(phi)
    n = np.maximum(np.asarray(inp.imu_samples, dtype=np.float64), 1.0)
    var = p.accel_std_mps2**2 / n + cfg.lateral_force_std_mps2**2
    have = np.isfinite(inp.lateral_accel_mps2)
    y = np.where(have, np.nan_to_num(inp.lateral_accel_mps2) - h, 0.0)[:, None]
    f.x, f.P, _, _ = kalman_update(f.x, f.P, y, H, var[:, None, None], have)


def _antenna_right_m(x: FloatArray, p: VehicleParams) -> FloatArray:
    """How far right of the hull centre the antenna is, horizontally ``(k,)``: its lever arm
    ``(x, z)`` (right, up) rolled by ``φ`` (right side down), ``x·cos φ + z·sin φ``."""
    phi = x[:, S.ROLL]
    return np.asarray(p.antenna_xy_m[:, 0] * np.cos(phi) + p.antenna_up_m * np.sin(phi))


def _antenna_ahead_m(x: FloatArray, p: VehicleParams) -> FloatArray:
    """How far ahead of the hull centre the antenna is, horizontally ``(k,)``: its lever
    arm ``(y, z)`` (forward, up) pitched by ``θ``, ``y·cos θ − z·sin θ``."""
    theta = x[:, S.PITCH]
    return np.asarray(p.antenna_xy_m[:, 1] * np.cos(theta) - p.antenna_up_m * np.sin(theta))


def state_lead_s(inp: TickInputs, tick_s: float) -> FloatArray:
    """How far past its tick the predicted state stands ``(k,)``: :func:`predict` integrates
    the tick's mean rates and forces over one tick, a span ``Δ`` centred on the samples'
    mean stamp (``imu_age_s`` before the tick), so the state stands at ``Δ/2 −
    imu_age_s`` after the tick (ten samples 10 ms apart ending at it: +5 ms); 0 without a
    sample."""
    return np.asarray(np.where(np.isfinite(inp.imu_age_s), 0.5 * tick_s - inp.imu_age_s, 0.0))


def fix_age_s(f: Filter, inp: TickInputs, tick_s: float) -> FloatArray:
    """How long before the state (:func:`state_lead_s`) each vehicle's fix was taken
    ``(k,)``: its age on the stamps (``t − s``), the state's lead past the tick, and the
    receiver's clock less the IMU's (``GNSS_CLOCK``, 0 outside the product mode)."""
    return np.asarray(inp.gnss_age_s + state_lead_s(inp, tick_s) + f.x[:, S.GNSS_CLOCK])


def _fuse_gnss(
    f: Filter,
    inp: TickInputs,
    p: VehicleParams,
    cfg: TrackedEstimatorConfig,
    lateral_parts: tuple[FloatArray, FloatArray | None, FloatArray | None],
    w: FloatArray,
    skip: BoolArray,
) -> tuple[BoolArray, BoolArray, FloatArray]:
    """Antenna position, then velocity (:func:`_fuse_gnss_velocity`); returns (used, gated,
    position NIS). The antenna is taken back by ``τ·u``, ``τ`` the fix's age
    (:func:`fix_age_s`) and ``u`` its velocity (:func:`_antenna_velocity`), so ``∂h/∂c =
    −u`` on the receiver's clock ``c``. ``lateral_parts``: the lateral speed and its
    derivatives by the side-slip gain and by the roll (each None outside the product mode)."""
    k = f.x.shape[0]
    psi = f.x[:, S.HEADING]
    s, c = np.sin(psi), np.cos(psi)
    xa, ya = _antenna_right_m(f.x, p), _antenna_ahead_m(f.x, p)
    have = f.started & ~skip & np.isfinite(inp.gnss_pos_pair_m).all(axis=1)
    regain = have & (f.gated_s >= cfg.gnss_regain_s)
    if regain.any():  # refused too long: the filter, not the fixes, is wrong; open up, and
        # start again from the next fix at speed (its course the heading: a heading that went
        # wrong unseen, as by a jump of position, is otherwise read as a reversed speed)
        core = [S.EAST, S.NORTH, S.HEADING, S.SPEED]
        bump = np.zeros(N_STATES)
        bump[core] = np.diag(_initial_p(cfg))[core] * 100.0
        f.P = f.P + regain[:, None, None] * np.diag(bump)[None]
        f.started = f.started & ~regain
    gate = np.where(regain, np.inf, cfg.gnss_gate_nis)
    H = np.zeros((k, 2, N_STATES))
    H[:, 0, S.EAST] = H[:, 1, S.NORTH] = 1.0
    H[:, 0, S.HEADING] = -xa * s + ya * c
    H[:, 1, S.HEADING] = -xa * c - ya * s
    # the lever arm is tilted by the attitude as it stands: the position's residuals (mostly
    # the side-slip's and the ground's, correlated over seconds) are not let into it
    vel = _antenna_velocity(f.x, inp, p, lateral_parts[0], w)
    H[:, :, S.GNSS_CLOCK] = -vel
    h = np.stack([f.x[:, S.EAST] + xa * c + ya * s, f.x[:, S.NORTH] - xa * s + ya * c], axis=1)
    h -= fix_age_s(f, inp, cfg.tick_s)[:, None] * vel  # where the antenna was at the fix
    R = np.eye(2)[None] * (p.gnss_pos_std_m**2)[:, None, None]
    f.x, f.P, nis, used = kalman_update(f.x, f.P, inp.gnss_pos_pair_m - h, H, R, have, gate)
    f.gated_s = np.where(have & ~used, f.gated_s + cfg.tick_s, np.where(used, 0.0, f.gated_s))
    std = _fuse_gnss_velocity(f, inp, p, lateral_parts, w, used, cfg.tick_s)
    if cfg.learns:
        _fuse_gnss_up(f, inp, p, used, std, cfg)
    return used, have & ~used, nis


def _antenna_velocity(
    x: FloatArray, inp: TickInputs, p: VehicleParams, lateral: FloatArray, w: FloatArray
) -> FloatArray:
    """The antenna's horizontal velocity (east, north) ``(k, 2)`` (:func:`_antenna_fwd_right`
    turned by the heading, :func:`_east_north`)."""
    vf, vr = _antenna_fwd_right(x, inp, p, lateral, w)
    return _east_north(vf, vr, np.sin(x[:, S.HEADING]), np.cos(x[:, S.HEADING]))


def _antenna_fwd_right(
    x: FloatArray, inp: TickInputs, p: VehicleParams, lateral: FloatArray, w: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """The antenna's speed forward ``v_f = V·cos θ + ω·x_a + s_f`` and to the right ``v_r =
    v_x − ω·y_a + s_r``, each ``(k,)`` (``v_x`` the hull's lateral speed, ``x_a``, ``y_a``
    the antenna's tilted lever arm turned by the yaw ``ω``, ``s_f``, ``s_r`` the mast's swing
    with the pitch and roll rates, :func:`_antenna_swing`)."""
    swing = _antenna_swing(x, inp, p, w)
    vf = x[:, S.SPEED] * np.cos(x[:, S.PITCH]) + w * _antenna_right_m(x, p) + swing[:, 0]
    return vf, lateral - w * _antenna_ahead_m(x, p) + swing[:, 1]


def _antenna_swing(x: FloatArray, inp: TickInputs, p: VehicleParams, w: FloatArray) -> FloatArray:
    """The antenna's velocity from the mast's swing with the pitch and roll rates ``(k, 3)``
    (forward, right, up; level, along and across the heading): the time derivative of its
    lever arm ``(x, y, z)`` pitched and rolled (``y·cos θ − z·sin θ·cos φ`` ahead, ``x·cos
    φ + z·sin φ`` right, ``z·cos θ·cos φ + y·sin θ − x·sin φ`` up) at fixed heading,

        forward = −y·sin θ·θ̇ − z·(cos θ·cos φ·θ̇ − sin θ·sin φ·φ̇)
        right   = (z·cos φ − x·sin φ)·φ̇
        up      = y·cos θ·θ̇ − z·(sin θ·cos φ·θ̇ + cos θ·sin φ·φ̇) − x·cos φ·φ̇

    with the Euler rates ``θ̇ = ω_x·cos φ + ω·sin φ``, ``φ̇ = ω_y − tan θ·(ω·cos φ − ω_x·sin
    φ)`` (``ω_x``, ``ω_y`` the pitch and roll gyros less their bias states, ``ω`` the yaw
    rate), as :func:`~estimator.tracked.filter.predict` turns them. First order in the rates
    (2.6 m × 0.05 rad/s is 0.13 m/s); its derivatives by the states are second order and
    left out of the Jacobians."""
    theta, phi = x[:, S.PITCH], x[:, S.ROLL]
    ct, st, cp, sp = np.cos(theta), np.sin(theta), np.cos(phi), np.sin(phi)
    wx = np.nan_to_num(inp.pitch_rate_radps) - x[:, S.PITCH_GYRO_BIAS]
    wy = np.nan_to_num(inp.roll_rate_radps) - x[:, S.ROLL_GYRO_BIAS]
    d_theta = wx * cp + w * sp
    d_phi = wy - np.tan(theta) * (w * cp - wx * sp)
    xa, ya, z = p.antenna_xy_m[:, 0], p.antenna_xy_m[:, 1], p.antenna_up_m
    forward = -ya * st * d_theta - z * (ct * cp * d_theta - st * sp * d_phi)
    right = (z * cp - xa * sp) * d_phi
    up = ya * ct * d_theta - z * (st * cp * d_theta + ct * sp * d_phi) - xa * cp * d_phi
    return np.stack([forward, right, up], axis=1)


def _east_north(fwd: FloatArray, right: FloatArray, s: FloatArray, c: FloatArray) -> FloatArray:
    """A forward and a right component turned to (east, north) ``(k, 2)``:
    ``fwd·(sin ψ, cos ψ) + right·(cos ψ, −sin ψ)``, ``s``, ``c`` the heading's sine, cosine."""
    return np.stack([fwd * s + right * c, fwd * c - right * s], axis=1)


def _fuse_gnss_velocity(
    f: Filter,
    inp: TickInputs,
    p: VehicleParams,
    lateral_parts: tuple[FloatArray, FloatArray | None, FloatArray | None],
    w: FloatArray,
    used: BoolArray,
    tick_s: float,
) -> FloatArray:
    """The fix's horizontal velocity (where its position was ``used``) against the antenna's,
    ``v_f·(sin ψ, cos ψ) + v_r·(cos ψ, −sin ψ)`` (``v_f``, ``v_r``: :func:`_antenna_fwd_right`,
    the mast's swing included), taken back by the fix's age ``τ``: less ``τ·v̇``, ``v̇ = (a·cos
    θ + ω·v_r)·(sin ψ, cos ψ) − ω·v_f·(cos ψ, −sin ψ)`` (``a`` the hull's own acceleration,
    ``inp.accel_mps2``: along its course and turned by the yaw rate ``ω``), so ``∂h/∂c =
    −v̇``. Returns the fixes' per-axis velocity 1-sigma ``(k,)``; ``f`` in place."""
    lateral, by_gain, by_roll = lateral_parts
    k = f.x.shape[0]
    v_have = used & np.isfinite(inp.gnss_vel_pair_mps).all(axis=1)
    psi, theta = f.x[:, S.HEADING], f.x[:, S.PITCH]
    s, c = np.sin(psi), np.cos(psi)
    ct, st = np.cos(theta), np.sin(theta)
    vf, vr = _antenna_fwd_right(f.x, inp, p, lateral, w)
    rate = _east_north(np.nan_to_num(inp.accel_mps2) * ct + w * vr, -(w * vf), s, c)
    hv = _east_north(vf, vr, s, c) - fix_age_s(f, inp, tick_s)[:, None] * rate
    Hv = np.zeros((k, 2, N_STATES))
    Hv[:, 0, S.SPEED], Hv[:, 1, S.SPEED] = ct * s, ct * c
    Hv[:, 0, S.HEADING], Hv[:, 1, S.HEADING] = vf * c - vr * s, -vf * s - vr * c
    tilt = -f.x[:, S.SPEED] * st
    Hv[:, 0, S.PITCH], Hv[:, 1, S.PITCH] = tilt * s, tilt * c
    Hv[:, :, S.GNSS_CLOCK] = -rate
    if by_gain is not None:
        Hv[:, 0, S.SIDE_SLIP], Hv[:, 1, S.SIDE_SLIP] = c * by_gain, -s * by_gain
    if by_roll is not None:
        Hv[:, 0, S.ROLL], Hv[:, 1, S.ROLL] = c * by_roll, -s * by_roll
    std = np.where(np.isfinite(inp.gnss_vel_std_mps), inp.gnss_vel_std_mps, p.gnss_vel_std_mps)
    Rv = np.eye(2)[None] * (std**2)[:, None, None]
    # a fix whose position passed the gate is sound: its velocity is fused ungated
    f.x, f.P, _, _ = kalman_update(f.x, f.P, inp.gnss_vel_pair_mps - hv, Hv, Rv, v_have)
    return np.asarray(std)


def _fuse_gnss_up(
    f: Filter,
    inp: TickInputs,
    p: VehicleParams,
    used: BoolArray,
    std: FloatArray,
    cfg: TrackedEstimatorConfig,
) -> None:
    """The fix's up velocity against the antenna's: the hull's climb ``V·sin θ`` (its
    along-ground speed pitched) plus the mast's swing's up part (:func:`_antenna_swing`;
    ``−z·cos θ·sin φ·φ̇ − z·sin θ·cos φ·θ̇`` for a mast upright on the hull: it swings mostly
    forward and sideways, and up only on a tilted hull). Beside the odometer's speed it
    observes the pitch itself, which the accelerometer alone gives only with its forward
    bias (``f_y − b_y − g·sin θ``). Taken back by the fix's age ``τ``
    as the horizontal velocity is: less ``τ·(a·sin θ + V·cos θ·θ̇)``, ``θ̇ = ω_x·cos φ +
    ω·sin φ`` (the pitch gyro less its bias, and the yaw on a side slope), so ``∂h/∂c =
    −(a·sin θ + V·cos θ·θ̇)``. ``std (k,)`` the fix's per-axis velocity 1-sigma
    (horizontal), the up one's that times ``gnss_up_to_horizontal_vel_std_ratio``; gated at
    ``gnss_up_gate_nis``; ``f`` in place."""
    k = f.x.shape[0]
    theta, phi, v = f.x[:, S.PITCH], f.x[:, S.ROLL], f.x[:, S.SPEED]
    have = used & np.isfinite(inp.gnss_vel_up_mps)
    wx = np.nan_to_num(inp.pitch_rate_radps) - f.x[:, S.PITCH_GYRO_BIAS]
    w = yaw_rate(f.x, np.nan_to_num(inp.gyro_radps))
    d_theta = wx * np.cos(phi) + w * np.sin(phi)
    rate = np.nan_to_num(inp.accel_mps2) * np.sin(theta) + v * np.cos(theta) * d_theta
    H = np.zeros((k, 1, N_STATES))
    H[:, 0, S.SPEED] = np.sin(theta)
    H[:, 0, S.PITCH] = v * np.cos(theta)
    H[:, 0, S.GNSS_CLOCK] = -rate
    swing_up = _antenna_swing(f.x, inp, p, w)[:, 2]
    h = v * np.sin(theta) + swing_up - fix_age_s(f, inp, cfg.tick_s) * rate
    y = np.where(have, np.nan_to_num(inp.gnss_vel_up_mps) - h, 0.0)[:, None]
    R = ((cfg.gnss_up_to_horizontal_vel_std_ratio * std) ** 2)[:, None, None]
    f.x, f.P, _, _ = kalman_update(f.x, f.P, y, H, R, have, cfg.gnss_up_gate_nis)


def _fuse_odometer(
    f: Filter,
    inp: TickInputs,
    p: VehicleParams,
    cfg: TrackedEstimatorConfig,
    state: IntArray,
    w: FloatArray,
    pull_mps2: FloatArray | None = None,
) -> tuple[BoolArray, FloatArray, FloatArray, FloatArray]:
    """The corrected odometer (:func:`~estimator.tracked.odometer.odometer_measurement`);
    returns (used, corrected speed, :func:`_factor_speed_var`, :func:`_odometer_gain`).
    ``inp.accel_mps2`` is the hull's own acceleration, ``pull_mps2 (k,)`` the accelerometer's
    forward specific force (the drawbar demand; ``inp.accel_mps2`` if None)."""
    valid = np.isfinite(inp.odometer_mps)
    y, H, R, mask, corrected = odometer_measurement(
        cfg,
        p,
        f.x,
        state,
        inp.odometer_mps,
        inp.odometer_lag_s,
        inp.accel_mps2,
        w,
        valid,
        turn_tightness(inp.sprocket_pair_mps),
        pull_mps2,
    )
    # the factors learn only beside GNSS, at a speed steady long enough for the hull's lag
    # behind its tracks and the slip of acceleration to have died out
    steady = (np.abs(inp.accel_mps2) < cfg.learn_accel_max_mps2) & (
        inp.steady_s >= cfg.learn_steady_s
    )
    beside = f.started & (f.since_gnss_s <= 1.0)
    gain = _odometer_gain(H, mask)
    factor_var = _factor_speed_var(f.P, gain, ~beside)
    H[:, :, _LEARNED] *= (beside & steady)[:, None, None]
    H[:, :, S.ACCEL_LAG] *= beside[:, None]
    H[:, :, S.ACCEL_SLIP] *= beside[:, None]
    f.x, f.P, _, used = kalman_update(f.x, f.P, y, H, R, mask)
    return used, corrected, factor_var, gain


def _odometer_gain(H: FloatArray, mask: BoolArray) -> FloatArray:
    """``g = −h_L/h_V`` ``(k, m)``: the forward speed the odometer gives per unit of error
    of each learnt state (``_BESIDE_ONLY``), ``h`` its row of ``H (k, 1, n)``; 0 where it
    gives none (``mask`` False)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        g = -H[:, 0, _BESIDE_ONLY] / H[:, 0, S.SPEED, None]
    return np.where(mask[:, None] & np.isfinite(g), g, 0.0)


def _factor_speed_var(P: FloatArray, gain: FloatArray, dead_reckoning: BoolArray) -> FloatArray:
    """Variance ``(k,)`` of the forward speed the odometer gives through its model's learnt
    states while dead reckoning (they are not fused then, so ``P[V]`` does not hold them):
    ``gᵀ P_LL g``, ``g`` from :func:`_odometer_gain`."""
    p_ll = P[:, _BESIDE_ONLY][:, :, _BESIDE_ONLY]
    var = np.einsum("ki,kij,kj->k", gain, p_ll, gain)
    return np.where(dead_reckoning, var, 0.0)


def standing_rate_var(p: VehicleParams, gyro_ratio: FloatArray, tick_s: float) -> FloatArray:
    """Variance ``(k,)`` of a standing tick's mean gyro rate about the bias: the gyro's white
    noise averaged over the tick, ``r·ARW²/Δt`` (``r`` the unit's noise over its data sheet's,
    :mod:`~estimator.tracked.gyro_noise`). A standing hull does not turn, so this is all the
    zero-rate update's error: a stop of ``T`` seconds pins the bias to ``√r·ARW/√T``."""
    return np.asarray(gyro_ratio * p.gyro_arw_rad_rt_s**2 / tick_s)


def hull_settled(f: Filter, inp: TickInputs, cfg: TrackedEstimatorConfig) -> BoolArray:
    """Vehicles ``(k,)`` whose hull has stopped turning: the gearbox steady (``steady_s``) for
    ``standing_settle_lags`` times the hull's lag ``τ`` behind its tracks (learnt, at most
    ``max_yaw_lag_s``). A hull braked to a stop keeps the yaw its tracks' last speeds gave it,
    dying out as ``exp(−t/τ)``: ~0.5 mrad/s over a stop's first second, 5τ later under 1 %
    of that."""
    tau = np.clip(f.x[:, S.ACCEL_LAG], 0.0, cfg.max_yaw_lag_s)
    return np.asarray(inp.steady_s >= cfg.standing_settle_lags * tau)


def _fuse_standstill(
    f: Filter,
    inp: TickInputs,
    cfg: TrackedEstimatorConfig,
    still: BoolArray,
    rate_var: FloatArray,
) -> None:
    """Zero speed while standing, and zero yaw, pitch and roll rate (each gyro's mean is its bias)
    once the hull has settled (:func:`hull_settled`; product); ``rate_var (k,)`` the tick
    mean's noise about the bias (:func:`standing_rate_var`)."""
    k = f.x.shape[0]
    H = np.zeros((k, 1, N_STATES))
    H[:, 0, S.SPEED] = 1.0
    R = np.full((k, 1, 1), cfg.zero_speed_std_mps**2)
    f.x, f.P, _, _ = kalman_update(f.x, f.P, -f.x[:, S.SPEED, None], H, R, still)
    Rg = np.broadcast_to(rate_var, (k,))[:, None, None].copy()
    gyros = (
        (inp.gyro_radps, S.GYRO_BIAS),
        (inp.pitch_rate_radps, S.PITCH_GYRO_BIAS),
        (inp.roll_rate_radps, S.ROLL_GYRO_BIAS),
    )
    for rate, bias in gyros:
        Hg = np.zeros((k, 1, N_STATES))
        Hg[:, 0, bias] = 1.0
        y = (np.nan_to_num(rate) - f.x[:, bias])[:, None]
        settled = still & hull_settled(f, inp, cfg) & np.isfinite(rate)
        f.x, f.P, _, _ = kalman_update(f.x, f.P, y, Hg, Rg, settled)


def _track_slip(
    f: Filter,
    inp: TickInputs,
    p: VehicleParams,
    cfg: TrackedEstimatorConfig,
    w: FloatArray,
    factor_var: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, BoolArray, BoolArray]:
    """Track ground speeds ``V ∓ ω·B/2`` at the tick, slip
    ``S = (Vs − v)/max(Vs, v)`` in percent with its 1-sigma, validity and braked tracks.

    A slip is given only where it is observable: its 1-sigma (from the speed's variance and,
    while dead reckoning, ``factor_var`` ``(k,)``, what the odometer's learnt factor of the
    state makes of it: a pivot's factor never learnt is ±15 %) at most ``slip_std_max_pct``,
    and the track's sprocket not settling; a sprocket starting after a standstill is not
    braked (its brake is being released), so it gets no −100 % either."""
    half = 0.5 * p.gauge_m[:, None]
    track = f.x[:, S.SPEED, None] + np.stack([-w, w], axis=1) * half
    var_v = f.P[:, S.SPEED, S.SPEED] + (0.5 * p.gauge_m * cfg.zero_rate_std_radps) ** 2
    var_v = var_v + factor_var
    track_std = np.sqrt(np.maximum(var_v, 0.0))
    vs = inp.sprocket_pair_mps
    top = np.maximum(vs, track)
    moving = top >= p.min_slip_speed_mps[:, None]
    other = vs[:, ::-1]
    read = ~inp.sprocket_missing[:, None]
    settling = inp.sprocket_settling_pair
    braked = read & (vs < cfg.braked_ratio_max * other) & (other >= p.stop_speed_mps[:, None])
    braked &= ~settling
    with np.errstate(divide="ignore", invalid="ignore"):
        slip = 100.0 * (vs - track) / top
        std = 100.0 * np.sqrt(track_std[:, None] ** 2 + (0.005 * vs) ** 2) / top
    valid = read & moving & ~braked & np.isfinite(slip) & f.started[:, None]
    valid &= ~settling & (std <= cfg.slip_std_max_pct)
    slip = np.where(braked, -100.0, np.where(valid, slip, np.nan))
    std = np.where(valid, std, np.nan)
    return track, track_std, slip, std, valid, braked


def creep_roll_band(f: Filter, cfg: TrackedEstimatorConfig) -> FloatArray:
    """The roll band ``(k,)`` within which no creep is modelled: ``creep_roll_sigmas`` times
    the roll's 1-sigma ``√P_φφ``, which holds the lateral accelerometer's bias (a state:
    the roll takes it in as a level ground's tilt, and its variance says so)."""
    var = np.maximum(f.P[:, S.ROLL, S.ROLL], 0.0)
    return np.asarray(cfg.creep_roll_sigmas * np.sqrt(var))


def _lateral(
    f: Filter, state: IntArray, w: FloatArray, p: VehicleParams, cfg: TrackedEstimatorConfig
) -> tuple[FloatArray, FloatArray | None, FloatArray | None]:
    """The hull's lateral speed ``(k,)`` by mode and (product) its derivatives by the
    side-slip gain and by the roll: the turns' side-slip
    (:func:`~estimator.tracked.odometer.side_slip`) and a side slope's creep
    (:func:`~estimator.tracked.odometer.side_creep`)."""
    v = f.x[:, S.SPEED]
    if not cfg.learns:
        lateral = lateral_speed(cfg.mode, state, v, w, p.length_m, p.lateral_resistance)
        return lateral, None, None
    gain = f.x[:, S.SIDE_SLIP]
    slip, slip_by_gain = side_slip(v, w, p.length_m, p.lateral_resistance, gain)
    band = creep_roll_band(f, cfg)
    creep, creep_by_gain, by_roll = side_creep(
        v, f.x[:, S.ROLL], band, p.lateral_resistance, cfg.side_creep, gain
    )
    return slip + creep, slip_by_gain + creep_by_gain, by_roll


def accel_steady(f: Filter, inp: TickInputs, cfg: TrackedEstimatorConfig) -> TickInputs:
    """The tick's inputs with gravity out of the accelerometer: ``accel_mps2`` the hull's own
    acceleration ``f_y − g·sin θ`` (the pitch at the tick's start), and ``steady_s`` also
    ending where that acceleration reaches ``learn_accel_max_mps2`` (or is unknown): the
    inputs' own run counts the gearbox and the sprockets; ``f.accel_steady_s`` counts the
    hull's (in place)."""
    own = hull_accel(f.x, inp.accel_mps2)
    calm = np.abs(own) <= cfg.learn_accel_max_mps2
    f.accel_steady_s = np.where(calm, f.accel_steady_s + cfg.tick_s, 0.0)
    steady = np.minimum(inp.steady_s, f.accel_steady_s)
    return dataclasses.replace(inp, accel_mps2=own, steady_s=steady)


def tick_step(f: Filter, inp: TickInputs, p: VehicleParams, cfg: TrackedEstimatorConfig) -> TickOut:
    """One tick for every vehicle of ``f`` (updated in place); see the module docstring.
    The accelerometer enters the prediction as it reads (the filter takes gravity out with
    its pitch) and the drawbar's traction slip as it reads; every other use takes the hull's
    own acceleration (:func:`accel_steady`)."""
    gyro = np.nan_to_num(inp.gyro_radps)
    pull = np.nan_to_num(inp.accel_mps2)
    inp = accel_steady(f, inp, cfg)
    w = yaw_rate(f.x, gyro)
    state, conf = recognise(f, inp, p, cfg, w)
    lateral, by_gain, by_roll = _lateral(f, state, w, p, cfg)
    ratio = noise_ratio(f.gyro_standing, p, cfg) if cfg.learns else np.ones_like(w)
    _predict_tick(f, inp, p, cfg, (gyro, pull), (lateral, by_gain, by_roll), ratio)
    _fuse_lateral_force(f, inp, p, cfg, gyro)
    _ground_patch(f, p, cfg)
    fresh = _start(f, inp, p, cfg)
    w = yaw_rate(f.x, gyro)
    used, gated, nis = _fuse_gnss(f, inp, p, cfg, (lateral, by_gain, by_roll), w, fresh)
    odo_used, corrected, factor_var, gain = _fuse_odometer(f, inp, p, cfg, state, w, pull)
    still = (state == int(M.STOP)) & (inp.odometer_mps < cfg.standstill_odometer_mps)
    onset = np.zeros(state.shape, dtype=bool)
    if cfg.learns:
        onset = _learn_tick(f, inp, p, cfg, still, ratio)
    _since_fix(f, used | fresh, cfg)
    _dead_reckoning_noise(f, p, cfg, gain)
    track, track_std, slip, slip_std, valid, braked = _track_slip(f, inp, p, cfg, w, factor_var)
    return TickOut(
        state=state,
        confidence=conf,
        yaw_rate_radps=w,
        lateral_mps=lateral,
        odometer_mps=corrected,
        odometer_used=odo_used,
        gnss_used=used | fresh,
        gnss_gated=gated,
        gnss_nis=nis,
        track_pair_mps=track,
        track_std_mps=track_std,
        slip_pair_pct=slip,
        slip_std_pair_pct=slip_std,
        slip_valid_pair=valid,
        braked_pair=braked,
        standstill=still,
        onset=onset,
    )


def _predict_tick(
    f: Filter,
    inp: TickInputs,
    p: VehicleParams,
    cfg: TrackedEstimatorConfig,
    imu: tuple[FloatArray, FloatArray],
    lateral: tuple[FloatArray, FloatArray | None, FloatArray | None],
    ratio: FloatArray,
) -> None:
    """The prediction over the tick, ``f.x`` ``(k, n)`` and ``f.P`` ``(k, n, n)`` in place:
    ``imu`` the yaw rate and the forward accelerometer as they read, ``lateral``
    (:func:`_lateral`'s), ``ratio`` the gyros' noise over the config's, each ``(k,)``."""
    gyro, pull = imu
    lat, by_gain, by_roll = lateral
    q = _q_diag(cfg, p, lat, ratio, inp.imu_samples)
    tilt = (np.nan_to_num(inp.pitch_rate_radps), np.nan_to_num(inp.roll_rate_radps))
    f.x, f.P = predict(f.x, f.P, gyro, pull, lat, cfg.tick_s, q, by_gain, tilt, by_roll)


def _learn_tick(
    f: Filter,
    inp: TickInputs,
    p: VehicleParams,
    cfg: TrackedEstimatorConfig,
    still: BoolArray,
    ratio: FloatArray,
) -> BoolArray:
    """What a learning config does after the fusion: the standstill update and the standing
    gyro's noise (``f`` in place); returns the tick's change onsets ``(k,)``."""
    before = (inp.sprocket_before_pair_mps, inp.gear_ratio_before)
    settling = inp.sprocket_settling_pair
    onset = change_onset(
        inp.sprocket_pair_mps,
        inp.gear_ratio,
        before,
        settling,
        inp.yaw_accel_radps2,
        p,
        cfg,
        inp.gearbox_accel_mps2,
        inp.odometer_mps,
    )
    onset |= odometer_start(inp, cfg)  # the held tick before may have started already
    _fuse_standstill(f, inp, cfg, still, standing_rate_var(p, ratio, cfg.tick_s))
    measured = still & (p.gyro_noise_measured > 0.0)
    f.gyro_standing = learn_standing(f.gyro_standing, inp.gyro_radps, measured)
    return onset
