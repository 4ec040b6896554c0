"""Truth of a single-flow-transmission crawler on flat ground (``method.md`` §4).

The gearbox output (speed ``v_g``, a track's speed in direct drive) feeds one planetary
steering unit per side: direct (ratio 1), I (1/1.42), II (brake, 0), or slipping between I
and direct in a separated turn. Each sprocket turns at ``Vs = v_g·ratio``; each track's ground
speed follows from its slip ``s = (Vs − v)/max(Vs, v)`` (traction slip on the fast side, skid
on the slow one, growing with turn tightness ``B/ρ_t`` and with the drawbar pull, the force
that accelerates the hull: loaded by the hull's own acceleration, solved with it step by
step); a braked track is dragged; the ground speeds follow with a 0.4 s lag (the hull's
inertia: a lever thrown makes the track slip until the hull has caught up). The hull moves at
``V = (v_l + v_r)/2``, turns at ``ω = (v_r − v_l)/B`` and slides outward at ``v_x = ω·D``: the
turning pole lies ``D = L·|V·ω|/(2·μ_t·g)`` ahead of the centre. Grid 100 Hz; arrays of
shape ``(n,)`` unless said.

On sloped ground (:mod:`~estimator.sim.tracked.terrain`, along the hull's along-ground
distance) the hull's pitch ``θ`` and roll ``φ`` follow the ground; the tracks' speeds are
along the ground, so the hull's horizontal speed is ``V·cos θ`` and it climbs at ``V·sin θ``;
the drawbar demand is ``a_h + g·sin θ`` (``a_h`` the hull's acceleration; uphill slips
more, downhill less); a cross slope makes the hull creep downhill sideways at a slip angle
``SIDE_CREEP·sin φ/μ_t`` (right side down: to the right); the tracks turn the hull about its
own up axis at ``r = (v_r − v_l)/B``, so the heading turns at ``(r − θ̇·sin φ)/(cos θ·cos φ)``
(Z-X-Y Euler angles: yaw, pitch about the right axis, roll about the forward axis).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

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


def _slip_parts(
    sprocket: FloatArray, ground: Ground, texture: FloatArray, patch: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Each driven track's slip as ``s = clip(s0 + gain·(a_h + g·sin θ), −0.5, 0.6)``, the
    drawbar demand ``a_h + g·sin θ`` (the hull's own acceleration and the grade) given per
    step: ``s0`` shape ``(n, 2)``, the rolling and turn terms ``± turn_slip·B/ρ_t`` (+ fast,
    − slow, ``B/ρ_t = 2(1 − q)/(1 + q)``) times the patch, plus the texture; ``gain`` shape
    ``(n,)``, the slip per m/s² of demand, ``accel_slip_per_g·patch/g``."""
    fast = sprocket.max(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        q = np.where(fast > 1e-6, sprocket.min(axis=1) / fast, 1.0)
    tight = 2.0 * (1.0 - q) / (1.0 + q)
    sign = np.where(sprocket >= fast[:, None] - 1e-9, 1.0, -1.0)
    sign[np.abs(sprocket[:, 0] - sprocket[:, 1]) < 1e-9] = 0.0
    turn = sign * (ground.turn_slip * tight)[:, None]
    s0 = (ground.rolling_slip + turn) * patch[:, None] + texture
    return s0, ground.accel_slip_per_g / GRAVITY_MPS2 * patch


class _Step:
    """One grid step's tracks as functions of the hull's acceleration ``a`` (m/s²): the
    ground speed each track is driven to (``Vs·(1 − s)`` for traction, ``Vs/(1 + s)`` for
    skid, ``s = clip(s0 + gain·(a + pull), −0.5, 0.6)`` with ``pull = g·sin θ``; a braked
    track dragged at ``drag`` of the other's, falling at most ``fall`` per step from
    ``prev``) and its derivative in ``a``. Plain floats: it runs once per step."""

    __slots__ = ("braked", "drag", "fall", "gain", "prev", "pull", "s0", "vs")

    def __init__(self, drag: float, fall: float) -> None:
        self.drag, self.fall = drag, fall
        self.vs: list[float] = [0.0, 0.0]
        self.s0: list[float] = [0.0, 0.0]
        self.braked: list[bool] = [False, False]
        self.prev: list[float] = [0.0, 0.0]
        self.gain = 0.0
        self.pull = 0.0

    def speeds(self, a: float) -> tuple[list[float], list[float]]:
        drv, d_drv = [0.0, 0.0], [0.0, 0.0]
        for j in (0, 1):
            s, ds = self.s0[j] + self.gain * (a + self.pull), self.gain
            if s <= -0.5 or s >= 0.6:
                s, ds = min(max(s, -0.5), 0.6), 0.0
            if s >= 0.0:
                drv[j], d_drv[j] = self.vs[j] * (1.0 - s), -self.vs[j] * ds
            else:
                drv[j], d_drv[j] = self.vs[j] / (1.0 + s), -self.vs[j] * ds / (1.0 + s) ** 2
        out, d_out = drv[:], d_drv[:]
        for j in (0, 1):
            if self.braked[j]:
                other = 1 - j
                dragged = 0.0 if self.braked[other] else self.drag * drv[other]
                fallen = max(self.prev[j] - self.fall, 0.0)
                if dragged > fallen:
                    out[j], d_out[j] = dragged, self.drag * d_drv[other]
                else:
                    out[j], d_out[j] = fallen, 0.0
        return out, d_out


def _hull_accel(step: _Step, v_prev: float, per_s: float, a0: float) -> float:
    """The hull's acceleration ``a`` that solves ``a = per_s·(mean_j ū_j(a) − v_prev)``
    (``ū_j`` from :class:`_Step`). The right side does not grow with ``a`` (more demand,
    more slip), so the root is unique; Newton's steps, bisected where they leave the
    bracket."""
    top = max(2.0 * max(step.vs), max(step.prev))
    lo, hi = -per_s * v_prev - 1.0, per_s * (top - v_prev) + 1.0
    a = min(max(a0, lo), hi)
    for _ in range(60):
        u, du = step.speeds(a)
        f = per_s * (0.5 * (u[0] + u[1]) - v_prev) - a
        if abs(f) < 1e-12:
            break
        if f > 0.0:
            lo = a
        else:
            hi = a
        nxt = a - f / (per_s * 0.5 * (du[0] + du[1]) - 1.0)
        a = nxt if lo < nxt < hi else 0.5 * (lo + hi)
    return a


def _tracks(
    route: Route, sprocket: FloatArray, texture: FloatArray, patch: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Track ground speeds ``u`` shape ``(n, 2)``, the hull's along-ground distance ``d`` and
    pitch ``θ`` ``(n,)``: each track lags the speed its slip drives it to, the slip loaded by
    the drawbar demand, the hull's own acceleration ``a_h = d/dt (u_l + u_r)/2`` plus the
    grade's ``g·sin θ`` where the hull is::

        τ·du_j/dt = ū_j(s_j) − u_j,   s_j = clip(s0_j + gain·(a_h + g·sin θ(d)), −0.5, 0.6)

    (``s0``, ``gain`` of :func:`_slip_parts`, ``ū_j`` of :class:`_Step`; a track is braked
    where its sprocket is below 2 % of the other's and 0.05 m/s). Backward Euler at
    ``RATE_HZ``: ``u[i] = u[i−1] + dt/(τ + dt)·(ū(a[i]) − u[i−1])`` with ``a[i] = (V[i] −
    V[i−1])/dt``, one scalar equation in ``a[i]`` per step (:func:`_hull_accel`); the grade
    read at ``d[i−1] + V[i−1]·dt``, ``d`` summed by trapezoids. Solved, not lagged a step:
    read from the step before, the slip's feedback ``Vs·gain/(τ + dt)`` exceeds 1 on soft
    ground at speed and the loop rings."""
    dt = 1.0 / RATE_HZ
    alpha = dt / (_SLIP_TAU_S + dt)
    per_s = alpha / dt
    s0, gain = _slip_parts(sprocket, route.ground, texture, patch)
    braked = sprocket < np.maximum(0.02 * sprocket[:, ::-1], 0.05)
    step = _Step(route.ground.brake_drag, _BRAKE_MPS2 * dt)
    vs_all, s0_all, gain_all = sprocket.tolist(), s0.tolist(), gain.tolist()
    brk_all = braked.tolist()
    terrain, sloped = route.terrain, any(route.terrain.grade)
    n = sprocket.shape[0]
    track, dist, pitch = np.empty_like(sprocket), np.zeros(n), np.zeros(n)
    u, d, v, a = [0.0, 0.0], 0.0, 0.0, 0.0
    for i in range(n):
        step.vs, step.s0, step.gain, step.braked = vs_all[i], s0_all[i], gain_all[i], brk_all[i]
        theta = math.atan(terrain.grade_at(d + v * dt)) if sloped else 0.0
        step.pull = GRAVITY_MPS2 * math.sin(theta)
        if i == 0:  # the lag starts at its first row
            u, _ = step.speeds(0.0)
            step.prev = u[:]
        else:
            a = _hull_accel(step, v, per_s, a)
            target, _ = step.speeds(a)
            step.prev = target
            u = [u[j] + alpha * (target[j] - u[j]) for j in (0, 1)]
            d += 0.5 * dt * (v + 0.5 * (u[0] + u[1]))
        v = 0.5 * (u[0] + u[1])
        track[i], dist[i], pitch[i] = u, d, theta
    return track, dist, pitch


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
    track, dist_m, pitch = _tracks(route, sprocket, texture, patch)
    roll = np.arctan(route.terrain.cross_of(dist_m))
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
