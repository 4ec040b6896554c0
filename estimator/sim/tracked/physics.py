"""Truth of a single-flow-transmission crawler on flat ground (``method.md`` §4).

The gearbox output (speed ``v_g``, a track's speed in direct drive) feeds one planetary
steering unit per side: direct (ratio 1), I (1/1.42), II (brake, 0), or slipping between I
and direct in a separated turn. Each sprocket turns at ``Vs = v_g·ratio``; each track's ground
speed follows from its slip ``s = (Vs − v)/max(Vs, v)`` (traction slip on the fast side, skid
on the slow one, growing with turn tightness ``B/ρ_t`` and acceleration); a braked track is
dragged; the ground speeds follow with a 0.4 s lag (the hull's inertia: a lever thrown makes
the track slip until the hull has caught up). The hull moves at ``V = (v_l + v_r)/2``, turns
at ``ω = (v_r − v_l)/B`` and slides outward at ``v_x = ω·D``: the turning pole lies
``D = L·|V·ω|/(2·μ_t·g)`` ahead of the centre. Grid 100 Hz; arrays of shape ``(n,)`` unless said.

On sloped ground (:mod:`~estimator.sim.tracked.terrain`, along the hull's along-ground
distance) the hull's pitch ``θ`` and roll ``φ`` follow the ground; the tracks' speeds are
along the ground, so the hull's horizontal speed is ``V·cos θ`` and it climbs at ``V·sin θ``;
the drawbar demand is ``a + g·sin θ`` (uphill slips more, downhill less); a cross slope
makes the hull creep downhill sideways at a slip angle ``SIDE_CREEP·sin φ/μ_t`` (right
side down: to the right); the tracks turn the hull about its own up axis at
``r = (v_r − v_l)/B``, so the heading turns at ``(r − θ̇·sin φ)/(cos θ·cos φ)`` (Z-X-Y
Euler angles: yaw, pitch about the right axis, roll about the forward axis).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter

from estimator._arrays import FloatArray, IntArray
from estimator.config import TrackedConfig
from estimator.sim._signals import cumtrapz, ou_process
from estimator.sim.tracked.route import Ground, Route
from estimator.tracked.model import MotionState

__all__ = ["GRAVITY_MPS2", "RATE_HZ", "SIDE_CREEP", "CrawlerTruth", "integrate_route"]

GRAVITY_MPS2 = 9.80665
RATE_HZ = 100
_RAMP_S = 0.3  # a steering lever moves within this
_ACCEL_UP_MPS2, _ACCEL_DOWN_MPS2 = 0.8, 1.5
_BRAKE_MPS2 = 3.0  # a braked track's ground speed falls at most this fast
_SLIP_TAU_S = 0.4  # the hull's inertia: a track's ground speed follows its sprocket this fast
SIDE_CREEP = 0.05  # a cross slope's side creep: slip angle per unit of sin φ/μ_t
M = MotionState


@dataclass(frozen=True, slots=True)
class CrawlerTruth:
    """Truth on the 100 Hz grid (``t_s`` from the start); per-track arrays ``(n, 2)`` are
    (left, right). ``speed_mps`` is along the ground, ``east_m``/``north_m``/``up_m`` the hull
    centre's position, ``pitch_rad`` (nose up +) and ``roll_rad`` (right side down +) its
    attitude, ``yaw_rate_radps`` its turn rate about its own up axis."""

    t_s: FloatArray
    gearbox_mps: FloatArray
    sprocket_mps: FloatArray
    track_mps: FloatArray
    slip: FloatArray
    speed_mps: FloatArray
    lateral_mps: FloatArray
    yaw_rate_radps: FloatArray
    heading_rad: FloatArray
    east_m: FloatArray
    north_m: FloatArray
    state: IntArray
    pitch_rad: FloatArray
    roll_rad: FloatArray
    up_m: FloatArray


def _ratios(route: Route, low_gear: float) -> tuple[FloatArray, FloatArray, IntArray]:
    """Per grid point: target gearbox speed, (left, right) steering ratios (ramped over
    ``_RAMP_S``), and the lever state of each segment."""
    counts = [round(s.duration_s * RATE_HZ) for s in route.segments]
    target = np.repeat([s.speed_mps for s in route.segments], counts)
    state = np.repeat([int(s.state) for s in route.segments], counts)
    pairs = []
    for s in route.segments:
        fast, slow = {
            M.STOP: (0.0, 0.0),
            M.STRAIGHT: (1.0, 1.0),
            M.LOW_STRAIGHT: (1.0 / low_gear, 1.0 / low_gear),
            M.ARC: (1.0, 1.0 / low_gear),
            M.SEPARATED: (1.0, s.ratio),
            M.PIVOT: (1.0, 0.0),
        }[s.state]
        pairs.append((slow, fast) if s.left else (fast, slow))
    lr = np.repeat(np.array(pairs, dtype=np.float64), counts, axis=0)
    k = round(_RAMP_S * RATE_HZ)
    padded = np.concatenate([np.repeat(lr[:1], k - 1, axis=0), lr])
    kernel = np.ones(k) / k
    ramped = np.stack([np.convolve(padded[:, j], kernel, mode="valid") for j in range(2)], axis=1)
    return target.astype(np.float64), ramped, state.astype(np.int64)


def _gearbox(target: FloatArray) -> FloatArray:
    """Gearbox speed following ``target`` within the acceleration limits."""
    dt = 1.0 / RATE_HZ
    out = np.empty_like(target)
    v = 0.0
    up, down = _ACCEL_UP_MPS2 * dt, _ACCEL_DOWN_MPS2 * dt
    for i, goal in enumerate(target.tolist()):
        v = min(goal, v + up) if goal > v else max(goal, v - down)
        out[i] = v
    return out


def _slip_of(
    sprocket: FloatArray, accel: FloatArray, ground: Ground, texture: FloatArray, patch: FloatArray
) -> FloatArray:
    """Slip of each driven track, shape ``(n, 2)``: rolling and drawbar terms on both
    (``accel`` the drawbar demand per unit mass, ``a + g·sin θ``), the turn term
    ``± turn_slip·B/ρ_t`` (+ fast, − slow) with ``B/ρ_t = 2(1 − q)/(1 + q)``."""
    fast = sprocket.max(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        q = np.where(fast > 1e-6, sprocket.min(axis=1) / fast, 1.0)
    tight = 2.0 * (1.0 - q) / (1.0 + q)
    base = ground.rolling_slip + ground.accel_slip_per_g * accel / GRAVITY_MPS2
    sign = np.where(sprocket >= fast[:, None] - 1e-9, 1.0, -1.0)
    sign[np.abs(sprocket[:, 0] - sprocket[:, 1]) < 1e-9] = 0.0
    turn = sign * (ground.turn_slip * tight)[:, None]
    return np.clip((base[:, None] + turn) * patch[:, None] + texture, -0.5, 0.6)


def _lag(x: FloatArray, tau_s: float) -> FloatArray:
    """First-order lag of each column of ``x`` (shape ``(n, 2)``), starting at its first row."""
    alpha = 1.0 / (1.0 + tau_s * RATE_HZ)
    out, _ = lfilter([alpha], [1.0, alpha - 1.0], x, axis=0, zi=(1 - alpha) * x[:1])
    return np.asarray(out, dtype=np.float64)


def _ground_speeds(sprocket: FloatArray, slip: FloatArray, drag: float) -> FloatArray:
    """Track ground speeds, shape ``(n, 2)``: from slip where driven; a braked track
    (sprocket below 2 % of the other's and 0.05 m/s) dragged at ``drag`` of the other track,
    falling at most ``_BRAKE_MPS2``."""
    driven = np.where(slip >= 0.0, sprocket * (1.0 - slip), sprocket / (1.0 + slip))
    braked = sprocket < np.maximum(0.02 * sprocket[:, ::-1], 0.05)
    out = np.empty_like(driven)
    prev = np.zeros(2)
    fall = _BRAKE_MPS2 / RATE_HZ
    drv, brk = driven.tolist(), braked.tolist()
    for i in range(driven.shape[0]):
        for j in (0, 1):
            if brk[i][j]:
                other = 0.0 if brk[i][1 - j] else drv[i][1 - j]
                prev[j] = max(drag * other, prev[j] - fall, 0.0)
            else:
                prev[j] = drv[i][j]
            out[i, j] = prev[j]
    return out


def _tracks(
    route: Route,
    sprocket: FloatArray,
    demand: FloatArray,
    texture: FloatArray,
    patch: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """Track ground speeds ``(n, 2)`` (lagged) and the hull's along-ground distance ``(n,)``
    for the drawbar ``demand``."""
    slip = _slip_of(sprocket, demand, route.ground, texture, patch)
    track = _lag(_ground_speeds(sprocket, slip, route.ground.brake_drag), _SLIP_TAU_S)
    return track, cumtrapz(track.mean(axis=1), 1.0 / RATE_HZ)


def _attitude(
    route: Route, vg: FloatArray, sprocket: FloatArray, texture: FloatArray, patch: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Track speeds ``(n, 2)``, pitch and roll ``(n,)``: the slopes are read at the hull's
    along-ground distance, which the slip (fed by the grade) sets: iterated from the
    gearbox's distance (two rounds leave centimetres)."""
    dt = 1.0 / RATE_HZ
    accel = np.gradient(vg, dt)
    dist = cumtrapz(vg, dt)
    for _ in range(3 if not route.terrain.flat else 1):
        pitch = np.arctan(route.terrain.grade_of(dist))
        track, dist = _tracks(route, sprocket, accel + GRAVITY_MPS2 * np.sin(pitch), texture, patch)
    pitch = np.arctan(route.terrain.grade_of(dist))
    roll = np.arctan(route.terrain.cross_of(dist))
    return track, pitch, roll


def integrate_route(route: Route, config: TrackedConfig, rng: np.random.Generator) -> CrawlerTruth:
    """The crawler's truth along ``route`` (see the module docstring)."""
    dt = 1.0 / RATE_HZ
    target, ratio, state = _ratios(route, config.motion.low_gear_ratio)
    n = target.size
    t: FloatArray = np.arange(n, dtype=np.float64) * dt
    vg = _gearbox(target)
    sprocket = vg[:, None] * ratio
    texture = np.stack([ou_process(rng, t, route.ground.texture_std, 2.0) for _ in range(2)], 1)
    dist = cumtrapz(vg, dt)
    patches = 1.0 + route.ground.patch_std * rng.standard_normal(
        int(dist[-1] // route.ground.patch_m) + 2
    )
    patch = patches[(dist // route.ground.patch_m).astype(np.int64)]
    track, pitch, roll = _attitude(route, vg, sprocket, texture, patch)
    b = config.geometry.track_gauge_m
    speed = track.mean(axis=1)
    yaw = (track[:, 1] - track[:, 0]) / b
    mu = route.ground.lateral_resistance
    pole = np.minimum(
        0.5 * config.geometry.contact_length_m,
        config.geometry.contact_length_m * np.abs(speed * yaw) / (2.0 * mu * GRAVITY_MPS2),
    )
    lateral = yaw * pole + np.abs(speed) * SIDE_CREEP * np.sin(roll) / mu
    pitch_rate = np.gradient(pitch, dt)
    turn = (yaw - pitch_rate * np.sin(roll)) / (np.cos(pitch) * np.cos(roll))
    heading = route.heading0_rad - cumtrapz(turn, dt)
    level = speed * np.cos(pitch)
    ve = level * np.sin(heading) + lateral * np.cos(heading)
    vn = level * np.cos(heading) - lateral * np.sin(heading)
    true_slip = np.where(
        np.maximum(sprocket, track) > 1e-3,
        (sprocket - track) / np.maximum(np.maximum(sprocket, track), 1e-9),
        np.nan,
    )
    return CrawlerTruth(
        t_s=t,
        gearbox_mps=vg,
        sprocket_mps=sprocket,
        track_mps=track,
        slip=true_slip,
        speed_mps=speed,
        lateral_mps=lateral,
        yaw_rate_radps=yaw,
        heading_rad=heading,
        east_m=cumtrapz(ve, dt),
        north_m=cumtrapz(vn, dt),
        state=_label(state, heading, config.motion.heading_jump_rad),
        pitch_rad=pitch,
        roll_rad=roll,
        up_m=cumtrapz(speed * np.sin(pitch), dt),
    )


def _label(state: IntArray, heading: FloatArray, jump_rad: float) -> IntArray:
    """Lever state, with HEADING_JUMP where the heading turned more than ``jump_rad`` over the
    last 0.1 s (Eq. 16 on the truth)."""
    k = RATE_HZ // 10
    turned = np.zeros(heading.size)
    turned[k:] = np.abs(heading[k:] - heading[:-k])
    out = state.copy()
    out[(turned > jump_rad) & (state != int(M.STOP))] = int(M.HEADING_JUMP)
    return out
