"""Named scenarios: a motion plan plus the sensor settings that go with it.

Each scenario is a :class:`Scenario` with a ``build(params, rng) -> MotionPlan`` function, its
default parameters (all overridable by name through :func:`estimator.sim.simulate`) and sensor
defaults (fields of :class:`~estimator.sim.sensors.SensorSpec`, also overridable).

Speeds are forward speeds of ``O`` (the rear-axle midpoint's ground projection); yaw rates are
body rates, counter-clockwise positive. "± bound" wobbles are sums of random sines scaled so
their largest excursion over the run equals the bound; they fade out toward standstill so the
vehicle does not turn or pitch while standing: speed and yaw wobbles below 0.5 m/s, body pitch
and roll wobbles in proportion to speed up to ``wobble_full_speed_mps`` (3 m/s; 0.5 m/s in the
paper scenarios, whose bounds hold over the whole motion).

The two ``paper_*`` scenarios follow ``../shared/docs/method.md`` section 1 ("The paper's
scenarios") and the source's section 2.1: GNSS at the paper's 5 Hz (dt = 0.2 s, so sample 70 is
t = 14 s), speed noise of ≈5 % *amplitude* (uniform in ±5 %), a −1 m/s disturbance of one epoch
at t = 14 s. The source adds the other sensors' noise "according to the actual values
(acceleration 3 %, angular rate 2 %)": here white noise of 3 % (1σ) of the inertial acceleration
at the IMU and 2 % of the angular rate, per 100 Hz sample, on top of a small MEMS floor
(0.02 m/s², 0.002 rad/s) so that a zero signal is not noise-free. No IMU bias (the source models
none).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np

from estimator._arrays import FloatArray
from estimator.sim._signals import BoundedSines, EasedKnots, ramp_steps, smooth_window
from estimator.sim.kinematics import MotionPlan, TractionModel

Params = Mapping[str, Any]
Builder = Callable[[Params, np.random.Generator], MotionPlan]

__all__ = ["SCENARIOS", "Scenario", "scenario_names"]


@dataclass(frozen=True, slots=True)
class Scenario:
    """A named scenario.

    Attributes
    ----------
    name : str
    summary : str
        One line for listings.
    build : callable
        ``(params, rng) -> MotionPlan``.
    defaults : Mapping[str, Any]
        Scenario parameters and their defaults (units in the names).
    sensor_defaults : Mapping[str, Any]
        Overrides of :class:`~estimator.sim.sensors.SensorSpec` defaults for this scenario; a
        value may be a callable of the scenario parameters (windows placed relative to the
        duration).
    """

    name: str
    summary: str
    build: Builder
    defaults: Mapping[str, Any] = field(default_factory=dict)
    sensor_defaults: Mapping[str, Any] = field(default_factory=dict)


class _Timeline:
    """Accumulates speed, yaw-rate and drawbar knots event by event (cosine-eased between)."""

    def __init__(self) -> None:
        self.t = 0.0
        self.v = 0.0
        self.yaw = 0.0
        self.draw = 0.0
        self.knots: list[tuple[float, float, float, float]] = [(0.0, 0.0, 0.0, 0.0)]

    def go(
        self,
        duration_s: float,
        *,
        speed: float | None = None,
        yaw: float | None = None,
        drawbar: float | None = None,
    ) -> None:
        """Move to new values over ``duration_s`` (values not given are held)."""
        self.t += max(duration_s, 0.0)
        self.v = self.v if speed is None else speed
        self.yaw = self.yaw if yaw is None else yaw
        self.draw = self.draw if drawbar is None else drawbar
        self.knots.append((self.t, self.v, self.yaw, self.draw))

    def profiles(self) -> tuple[EasedKnots, EasedKnots, EasedKnots]:
        x = tuple(k[0] for k in self.knots)
        return (
            EasedKnots(x, tuple(k[1] for k in self.knots)),
            EasedKnots(x, tuple(k[2] for k in self.knots)),
            EasedKnots(x, tuple(k[3] for k in self.knots)),
        )


def _moving(v0: FloatArray) -> FloatArray:
    return np.clip(np.asarray(v0) / 0.5, 0.0, 1.0)


def _wobbles(
    p: Params, rng: np.random.Generator, span: float
) -> tuple[BoundedSines, BoundedSines, BoundedSines, BoundedSines]:
    """Speed, yaw-rate, pitch (rate-bounded) and roll wobbles from the common parameters."""
    speed = BoundedSines.draw(rng, p["speed_wobble_mps"], span, 0.02, 0.2)
    yaw = BoundedSines.draw(rng, p["yaw_wobble_radps"], span, 0.05, 0.5)
    pitch = BoundedSines.draw(rng, p["pitch_rate_wobble_radps"], span, 0.3, 1.5, bound_on="rate")
    roll = BoundedSines.draw(rng, p["roll_wobble_rad"], span, 0.2, 1.0)
    return speed, yaw, pitch, roll


_COMMON: dict[str, Any] = {
    "wobble_full_speed_mps": 3.0,
    "speed_wobble_mps": 0.05,
    "yaw_wobble_radps": 0.02,
    "pitch_rate_wobble_radps": 0.02,
    "roll_wobble_rad": 0.005,
    "heading0_deg": 0.0,
    "mu_soil": 0.6,
    "slip_scale": 0.15,
    "rolling_resistance": 0.05,
    "rear_load_fraction": 0.6,
    "turn_slip_gain": 0.1,
    "slip_texture": 0.003,
    "slip_texture_tau_s": 1.5,
    "sway_hz": 1.0,
    "sway_pitch_deg": 0.0,
    "sway_roll_deg": 0.0,
    "slip_steps": (),
    "free_rolling": (False, False),
}
"""Parameters every scenario takes. Body sway: pitch ``A_θ·sin(2π·f·t)`` and roll
``A_φ·cos(2π·f·t)`` about the rear axle (``sway_*``), in full from 1 m/s and faded to none at
standstill; ``slip_steps``: ``((t_s, delta_pct, ramp_s), ...)`` added to both driven wheels' slip
(:func:`estimator.sim._signals.ramp_steps`; a wet patch, an implement lowered or lifted);
``free_rolling``: (left, right) wheels that are not driven and roll without slip."""


def _traction(p: Params) -> TractionModel:
    return TractionModel(
        s0=p["slip_scale"],
        rolling_resistance=p["rolling_resistance"],
        rear_load_fraction=p["rear_load_fraction"],
        turn_gain=p["turn_slip_gain"],
        texture_std=p["slip_texture"],
        texture_tau_s=p["slip_texture_tau_s"],
    )


def _tilt_wobbles(
    p: Params,
    w_pitch: Callable[[FloatArray], FloatArray],
    w_roll: Callable[[FloatArray], FloatArray],
) -> tuple[Callable[[FloatArray, FloatArray], FloatArray], ...]:
    """Body pitch and roll wobbles ``f(t, v0)`` (the bumps grown with speed, the roll's sway
    added) and the pitch sway about the axle, kept apart: the ground under the axle does not
    sway."""
    full = float(p["wobble_full_speed_mps"])

    def body_gate(v0: FloatArray) -> FloatArray:
        # bumps come faster the faster the vehicle goes: body pitch/roll motion grows with speed
        return np.clip(np.asarray(v0) / full, 0.0, 1.0)

    sway_w = 2.0 * math.pi * float(p["sway_hz"])
    sway_pitch, sway_roll = math.radians(p["sway_pitch_deg"]), math.radians(p["sway_roll_deg"])

    def sway_gate(v0: FloatArray) -> FloatArray:
        return np.clip(np.asarray(v0), 0.0, 1.0)

    def pitch_f(t: FloatArray, v0: FloatArray) -> FloatArray:
        return w_pitch(t) * body_gate(v0)

    def sway_f(t: FloatArray, v0: FloatArray) -> FloatArray:
        if not sway_pitch:
            return np.zeros_like(np.asarray(t, dtype=np.float64))
        return sway_pitch * np.sin(sway_w * t) * sway_gate(v0)

    def roll_f(t: FloatArray, v0: FloatArray) -> FloatArray:
        out = w_roll(t) * body_gate(v0)
        if sway_roll:
            out = out + sway_roll * np.cos(sway_w * t) * sway_gate(v0)
        return out

    return pitch_f, roll_f, sway_f


def _plan(
    p: Params,
    rng: np.random.Generator,
    duration: float,
    speed: Callable[[FloatArray], FloatArray],
    yaw: Callable[[FloatArray], FloatArray],
    *,
    drawbar: Callable[[FloatArray], FloatArray] | None = None,
    terrain_pitch: Callable[[FloatArray], FloatArray] | None = None,
    terrain_roll: Callable[[FloatArray], FloatArray] | None = None,
    mu_max: Callable[[FloatArray], FloatArray] | None = None,
    speed_wobble_when: Callable[[FloatArray], FloatArray] | None = None,
) -> MotionPlan:
    """Assemble a plan: base profiles plus the common wobbles (faded at standstill)."""
    w_speed, w_yaw, w_pitch, w_roll = _wobbles(p, rng, duration)
    mu_soil = float(p["mu_soil"])

    def speed_f(t: FloatArray) -> FloatArray:
        base = speed(t)
        gate = speed_wobble_when(t) if speed_wobble_when is not None else _moving(base)
        return np.maximum(base + w_speed(t) * gate, 0.0)

    def yaw_f(t: FloatArray, v0: FloatArray) -> FloatArray:
        return yaw(t) + w_yaw(t) * _moving(v0)

    pitch_f, roll_f, sway_f = _tilt_wobbles(p, w_pitch, w_roll)
    steps = tuple((float(t0), 0.01 * float(d), float(w)) for t0, d, w in p["slip_steps"])

    def slip_offset(t: FloatArray) -> FloatArray:
        return ramp_steps(t, steps)

    def zero(x: FloatArray) -> FloatArray:
        return np.zeros_like(np.asarray(x, dtype=np.float64))

    def soil(x: FloatArray) -> FloatArray:
        return np.full_like(np.asarray(x, dtype=np.float64), mu_soil)

    return MotionPlan(
        duration_s=duration,
        speed_mps=speed_f,
        yaw_rate_ts=yaw_f,
        pitch_wobble_ts=pitch_f,
        pitch_sway_ts=sway_f,
        roll_wobble_ts=roll_f,
        terrain_pitch_rad=terrain_pitch or zero,
        terrain_roll_rad=terrain_roll or zero,
        mu_max=mu_max or soil,
        drawbar=drawbar or zero,
        heading0_rad=math.radians(p["heading0_deg"]),
        traction=_traction(p),
        slip_offset=slip_offset,
        free_rolling=(bool(p["free_rolling"][0]), bool(p["free_rolling"][1])),
    )


# --------------------------------------------------------------------------------------------
# paper scenarios


def _paper_straight(p: Params, rng: np.random.Generator) -> MotionPlan:
    tl = _Timeline()
    tl.go(p["stand_s"])
    tl.go(p["accel_s"], speed=p["speed_mps"])
    tl.go(p["cruise_s"])
    tl.go(p["decel_s"], speed=0.0)
    tl.go(p["stop_s"])
    speed, yaw, _ = tl.profiles()
    return _plan(p, rng, tl.t, speed, yaw)


def _paper_circle(p: Params, rng: np.random.Generator) -> MotionPlan:
    v, w = float(p["speed_mps"]), float(p["yaw_rate_radps"])
    lead = float(p["lead_in_s"])
    # lead-in from rest onto the circle (constant radius v/w), then circling for duration_s
    tl = _Timeline()
    tl.go(1.0)
    tl.go(lead, speed=v)
    tl.go(float(p["duration_s"]))
    base, _, _ = tl.profiles()

    def yaw(t: FloatArray) -> FloatArray:
        return w * base(t) / v

    return _plan(p, rng, tl.t, base, yaw)


_PAPER_SENSORS: dict[str, Any] = {
    "gnss_rate_hz": 5.0,
    "gnss_speed_noise_rel": 0.05,
    "gnss_vel_std_mps": 0.005,
    "gnss_speed_steps": ((14.0, -1.0, 0.2),),
    "gnss_latency_ms": 0.0,
    "accel_std_mps2": 0.02,
    "gyro_std_radps": 0.002,
    "accel_noise_rel": 0.03,
    "gyro_noise_rel": 0.02,
    "accel_bias_std_mps2": 0.0,
    "gyro_bias_std_radps": 0.0,
    "accel_bias_walk_mps2": 0.0,
    "gyro_bias_walk_radps": 0.0,
}


# --------------------------------------------------------------------------------------------
# field scenarios


def _figure_eight(p: Params, rng: np.random.Generator) -> MotionPlan:
    lap, tau, laps = float(p["lap_s"]), float(p["reverse_s"]), int(p["laps"])
    if laps < 1 or not 0.0 < tau < lap / 4:
        raise ValueError("figure_eight needs laps >= 1 and 0 < reverse_s < lap_s / 4")
    half = lap / 2.0
    # each loop (half lap) turns exactly 2π: a cosine reversal over τ contributes Ω·τ/π on
    # each side of its midpoint, an entry/exit ramp over τ/2 contributes Ω·τ/4.
    omega = 2 * math.pi / (half - tau + 2 * tau / math.pi)
    end_hold = 2 * math.pi / omega - tau / 4 - tau / math.pi
    tl = _Timeline()
    tl.go(p["stand_s"])
    tl.go(p["ramp_s"], speed=p["speed_mps"])
    sign = 1.0
    n_loops = 2 * laps
    tl.go(tau / 2, yaw=sign * omega)
    for k in range(n_loops):
        last = k == n_loops - 1
        first = k == 0
        if first and last:
            hold = 2 * math.pi / omega - tau / 2
        elif first or last:
            hold = end_hold
        else:
            hold = half - tau
        tl.go(hold)
        if last:
            tl.go(tau / 2, yaw=0.0)
        else:
            sign = -sign
            tl.go(tau, yaw=sign * omega)
    tl.go(p["ramp_s"], speed=0.0)
    tl.go(p["stand_s"])
    speed, yaw, _ = tl.profiles()
    return _plan(p, rng, tl.t, speed, yaw)


def _slope_wet_patch(p: Params, rng: np.random.Generator) -> MotionPlan:
    tl = _Timeline()
    tl.go(p["stand_s"])
    tl.go(p["accel_s"], speed=p["speed_mps"])
    tl.go(p["cruise_s"])
    tl.go(p["decel_s"], speed=0.0)
    tl.go(p["stand_s"])
    speed, yaw, _ = tl.profiles()
    slope = math.radians(p["slope_deg"])
    cross = math.radians(p["cross_slope_deg"])
    d0, d1, edge = float(p["slope_start_m"]), float(p["slope_end_m"]), float(p["slope_edge_m"])
    w0, w1 = float(p["wet_start_m"]), float(p["wet_end_m"])
    mu_soil, mu_wet = float(p["mu_soil"]), float(p["mu_wet"])

    def pitch(d: FloatArray) -> FloatArray:
        return slope * smooth_window(d, d0, d1, edge)

    def roll(d: FloatArray) -> FloatArray:
        return cross * smooth_window(d, d0, d1, edge)

    def mu(d: FloatArray) -> FloatArray:
        return mu_soil + (mu_wet - mu_soil) * smooth_window(d, w0, w1, 1.0)

    return _plan(p, rng, tl.t, speed, yaw, terrain_pitch=pitch, terrain_roll=roll, mu_max=mu)


def _hard_braking(p: Params, rng: np.random.Generator) -> MotionPlan:
    tl = _Timeline()
    for _ in range(int(p["cycles"])):
        tl.go(p["stand_s"])
        tl.go(p["accel_s"], speed=p["speed_mps"])
        tl.go(p["cruise_s"])
        tl.go(p["brake_s"], speed=0.0)
    tl.go(p["stand_s"])
    speed, yaw, _ = tl.profiles()
    return _plan(p, rng, tl.t, speed, yaw)


def _gnss_outage(p: Params, rng: np.random.Generator) -> MotionPlan:
    if (
        float(p["duration_s"]) < 60.0
        or not 0.0 < float(p["outage_s"]) <= float(p["duration_s"]) - 20.0
    ):
        raise ValueError("gnss_outage needs duration_s >= 60 and 0 < outage_s <= duration_s - 20")
    tl = _Timeline()
    v, w = float(p["speed_mps"]), float(p["turn_rate_radps"])
    tl.go(2.0)
    tl.go(5.0, speed=v)
    tl.go(10.0)
    tl.go(3.0, yaw=w)
    tl.go(6.0)
    tl.go(4.0, yaw=-w, speed=0.7 * v)
    tl.go(8.0)
    tl.go(3.0, yaw=0.0, speed=1.15 * v)
    rest = float(p["duration_s"]) - tl.t - 8.0
    # the remaining time alternates gentle turns and speed changes
    k = 0
    while rest > 12.0:
        tl.go(3.0, yaw=w if k % 2 == 0 else -w, speed=(0.8 if k % 3 == 0 else 1.1) * v)
        tl.go(6.0)
        rest -= 9.0
        k += 1
    tl.go(3.0, yaw=0.0)
    tl.go(max(rest - 3.0, 0.0))
    tl.go(5.0, speed=0.0)
    tl.go(3.0)
    speed, yaw, _ = tl.profiles()
    drawbar = float(p["drawbar"])

    def draw(t: FloatArray) -> FloatArray:
        return np.full_like(t, drawbar)

    return _plan(p, rng, tl.t, speed, yaw, drawbar=draw)


def _slow_creep(p: Params, rng: np.random.Generator) -> MotionPlan:
    if float(p["duration_s"]) < 4.0 * float(p["ramp_s"]) + 2.0:
        raise ValueError("slow_creep needs duration_s >= 4 * ramp_s + 2")
    v_lo, v_hi = float(p["speed_min_mps"]), float(p["speed_max_mps"])
    mid, amp = 0.5 * (v_lo + v_hi), 0.5 * (v_hi - v_lo)
    dur = float(p["duration_s"])
    tl = _Timeline()
    tl.go(1.0)
    tl.go(p["ramp_s"], speed=mid)
    tl.go(dur - 2.0 - 2 * float(p["ramp_s"]))
    tl.go(p["ramp_s"], speed=0.0)
    tl.go(1.0)
    base, _, _ = tl.profiles()
    swing = BoundedSines.draw(rng, amp, dur, 1 / 40, 1 / 10, n=3)
    ramp_end, ramp_back = 1.0 + float(p["ramp_s"]), dur - 1.0 - float(p["ramp_s"])
    drawbar = float(p["drawbar"])

    def gate(t: FloatArray) -> FloatArray:
        return smooth_window(t, ramp_end + 2.0, ramp_back - 2.0, 4.0)

    def speed(t: FloatArray) -> FloatArray:
        return base(t) + swing(t) * gate(t)

    def yaw(t: FloatArray) -> FloatArray:
        return np.zeros_like(t)

    def draw(t: FloatArray) -> FloatArray:
        return drawbar * smooth_window(t, ramp_end, ramp_back, 3.0)

    return _plan(p, rng, tl.t, speed, yaw, drawbar=draw, speed_wobble_when=gate)


def _field_work(p: Params, rng: np.random.Generator) -> MotionPlan:
    tl = _field_timeline(p)
    speed, yaw, drawbar = tl.profiles()
    pitch, roll, mu = _field_terrain(p)
    return _plan(
        p, rng, tl.t, speed, yaw, drawbar=drawbar, terrain_pitch=pitch, terrain_roll=roll, mu_max=mu
    )


def _field_timeline(p: Params) -> _Timeline:
    """Working passes with the implement in, stops every few passes, headland U-turns."""
    dur = float(p["duration_s"])
    v_work, v_turn = float(p["work_speed_mps"]), float(p["turn_speed_mps"])
    radius, draw = float(p["turn_radius_m"]), float(p["drawbar"])
    pass_s = float(p["pass_length_m"]) / v_work
    ramp, tau = 3.0, 1.5
    omega = v_turn / radius
    turn_hold = math.pi / omega - tau
    end_s = 6.0  # final stop: 4 s braking, at least 2 s standing
    every = int(p["stop_every_passes"])
    turn_need = 2 * ramp + 2 * tau + turn_hold
    tl = _Timeline()
    tl.go(2.0)
    tl.go(4.0, speed=v_work)
    k = 0
    while True:
        budget = dur - end_s - tl.t
        if budget < 6.0:
            tl.go(max(budget, 0.0))
            break
        # working pass: implement in the ground
        this_pass = min(pass_s, budget)
        tl.go(2.0, drawbar=draw)
        tl.go(this_pass - 4.0)
        tl.go(2.0, drawbar=0.0)
        k += 1
        budget = dur - end_s - tl.t
        if k % every == 0 and budget >= 13.0 + 6.0:
            tl.go(4.0, speed=0.0)
            tl.go(5.0)
            tl.go(4.0, speed=v_work)
            continue
        if budget < turn_need + 6.0:
            tl.go(max(budget, 0.0))
            break
        # headland U-turn, alternating sides
        sign = 1.0 if k % 2 else -1.0
        tl.go(ramp, speed=v_turn)
        tl.go(tau, yaw=sign * omega)
        tl.go(turn_hold)
        tl.go(tau, yaw=0.0)
        tl.go(ramp, speed=v_work)
    tl.go(4.0, speed=0.0, drawbar=0.0)
    tl.go(dur - tl.t)
    return tl


def _field_terrain(p: Params) -> tuple[Callable[[FloatArray], FloatArray], ...]:
    """Terrain pitch and roll (sines over distance) and the wet patches' grip, of distance."""
    hill, hill_len = math.radians(p["hill_pitch_deg"]), float(p["hill_length_m"])
    bank = math.radians(p["bank_roll_deg"])
    wet_every, wet_len = float(p["wet_every_m"]), float(p["wet_length_m"])
    mu_soil, mu_wet = float(p["mu_soil"]), float(p["mu_wet"])

    def pitch(d: FloatArray) -> FloatArray:
        return hill * np.sin(2 * math.pi * d / hill_len)

    def roll(d: FloatArray) -> FloatArray:
        return bank * np.sin(2 * math.pi * d / (0.77 * hill_len) + 1.0)

    def mu(d: FloatArray) -> FloatArray:
        phase = np.mod(d, wet_every)
        return mu_soil + (mu_wet - mu_soil) * smooth_window(
            phase, 0.5 * wet_every, 0.5 * wet_every + wet_len, 1.0
        )

    return pitch, roll, mu


def _random_drive(p: Params, rng: np.random.Generator) -> MotionPlan:
    """From rest, legs of random speed and yaw rate (``leg_s`` apart, each eased over 2-5 s),
    now and then a stop (``stop_prob``), to rest again. A leg's yaw rate is at most
    ``turn_rate_max_radps`` and at most ``0.55·V`` rad/s (so the inner wheel of a 1.8 m track
    keeps rolling forward), zero on half of the legs."""
    dur = float(p["duration_s"])
    v_lo, v_hi = float(p["speed_min_mps"]), float(p["speed_max_mps"])
    leg_lo, leg_hi = p["leg_s"]
    if not (0.0 < v_lo <= v_hi and dur >= 20.0 and 0.0 < leg_lo <= leg_hi):
        raise ValueError(
            "random_drive needs 0 < speed_min <= speed_max, duration_s >= 20, legs > 0"
        )
    tl = _Timeline()
    tl.go(float(p["stand_s"]))
    while tl.t < dur - 12.0:
        if tl.v > 0 and rng.random() < float(p["stop_prob"]):
            tl.go(rng.uniform(2.0, 4.0), speed=0.0, yaw=0.0)
            tl.go(rng.uniform(1.0, 4.0))
            continue
        v = rng.uniform(v_lo, v_hi)
        w_max = min(float(p["turn_rate_max_radps"]), 0.55 * v, 0.55 * max(tl.v, v))
        w = rng.uniform(-w_max, w_max) if rng.random() < 0.5 else 0.0
        if tl.v > 0 and abs(tl.yaw) > 0.55 * v:
            w = 0.0
        tl.go(rng.uniform(2.0, 5.0), speed=v, yaw=w)
        tl.go(rng.uniform(leg_lo, leg_hi))
    tl.go(4.0, speed=0.0, yaw=0.0)
    tl.go(max(dur - tl.t, 2.0))
    speed, yaw, _ = tl.profiles()
    drawbar = float(p["drawbar"])

    def draw(t: FloatArray) -> FloatArray:
        return np.full_like(t, drawbar)

    return _plan(p, rng, tl.t, speed, yaw, drawbar=draw)


_FIELD_SENSORS: dict[str, Any] = {"gnss_outlier_prob": 0.002}


def _mid_outage(p: Params) -> tuple[tuple[float, float], ...]:
    mid, half = 0.5 * float(p["duration_s"]), 0.5 * float(p["outage_s"])
    return ((mid - half, mid + half),)


def _float_spell(p: Params) -> tuple[tuple[float, float], ...]:
    t0 = 0.3 * float(p["duration_s"])
    return ((t0, t0 + 10.0),)


def _short_outage(p: Params) -> tuple[tuple[float, float], ...]:
    t0 = 0.6 * float(p["duration_s"])
    return ((t0, t0 + 8.0),)


def _with_common(d: dict[str, Any]) -> MappingProxyType[str, Any]:
    return MappingProxyType({**_COMMON, **d})


SCENARIOS: Mapping[str, Scenario] = MappingProxyType(
    {
        s.name: s
        for s in (
            Scenario(
                "paper_straight",
                "source sim. 1: start, accelerate, cruise 3 m/s, decelerate, stop; GNSS 5 Hz, ±5 % "
                "speed noise, −1 m/s disturbance at t = 14 s",
                _paper_straight,
                _with_common(
                    {
                        "speed_mps": 3.0,
                        "stand_s": 2.0,
                        "accel_s": 4.0,
                        "cruise_s": 24.0,
                        "decel_s": 4.0,
                        "stop_s": 2.0,
                        "speed_wobble_mps": 0.0,
                        "yaw_wobble_radps": 0.05,
                        "pitch_rate_wobble_radps": 0.02,
                        "roll_wobble_rad": 0.0,
                        "wobble_full_speed_mps": 0.5,
                    }
                ),
                MappingProxyType(dict(_PAPER_SENSORS)),
            ),
            Scenario(
                "paper_circle",
                "source sim. 2: counter-clockwise circling, Vg = 3.0 ± 0.03 m/s, ωz = 0.4 ± 0.02 "
                "rad/s, ωx = 0 ± 0.02 rad/s (after a 6 s lead-in from rest)",
                _paper_circle,
                _with_common(
                    {
                        "duration_s": 64.0,
                        "lead_in_s": 5.0,
                        "speed_mps": 3.0,
                        "yaw_rate_radps": 0.4,
                        "speed_wobble_mps": 0.03,
                        "yaw_wobble_radps": 0.02,
                        "pitch_rate_wobble_radps": 0.02,
                        "roll_wobble_rad": 0.0,
                        "wobble_full_speed_mps": 0.5,
                    }
                ),
                MappingProxyType(dict(_PAPER_SENSORS)),
            ),
            Scenario(
                "figure_eight",
                "field run: figure eight at 2.7 m/s, ≈27 s a lap, slip within ±7 %",
                _figure_eight,
                _with_common(
                    {
                        "speed_mps": 2.7,
                        "lap_s": 27.0,
                        "laps": 2,
                        "reverse_s": 2.0,
                        "ramp_s": 6.0,
                        "stand_s": 1.0,
                    }
                ),
                MappingProxyType(dict(_FIELD_SENSORS)),
            ),
            Scenario(
                "slope_wet_patch",
                "climb an 8° slope (2° cross slope) at 2 m/s through a wet patch: slip 20-30 %",
                _slope_wet_patch,
                _with_common(
                    {
                        "speed_mps": 2.0,
                        "stand_s": 1.0,
                        "accel_s": 5.0,
                        "cruise_s": 50.0,
                        "decel_s": 4.0,
                        "slope_deg": 8.0,
                        "cross_slope_deg": 2.0,
                        "slope_start_m": 15.0,
                        "slope_end_m": 90.0,
                        "slope_edge_m": 8.0,
                        "wet_start_m": 45.0,
                        "wet_end_m": 60.0,
                        "mu_wet": 0.38,
                    }
                ),
                MappingProxyType(dict(_FIELD_SENSORS)),
            ),
            Scenario(
                "hard_braking",
                "accelerate to 4 m/s (slip > 10 %), cruise, brake hard to a stop (slip < −10 %)",
                _hard_braking,
                _with_common(
                    {
                        "cycles": 2,
                        "speed_mps": 4.0,
                        "stand_s": 2.0,
                        "accel_s": 4.0,
                        "cruise_s": 8.0,
                        "brake_s": 2.0,
                    }
                ),
                MappingProxyType(dict(_FIELD_SENSORS)),
            ),
            Scenario(
                "gnss_outage",
                "mixed drive with gentle turns and a 20 s GNSS outage mid-run",
                _gnss_outage,
                _with_common(
                    {
                        "duration_s": 120.0,
                        "outage_s": 20.0,
                        "speed_mps": 3.0,
                        "turn_rate_radps": 0.12,
                        "drawbar": 0.05,
                    }
                ),
                MappingProxyType({**_FIELD_SENSORS, "gnss_outages": _mid_outage}),
            ),
            Scenario(
                "slow_creep",
                "tillage creep between 0.5 and 0.8 m/s with a heavy drawbar load",
                _slow_creep,
                _with_common(
                    {
                        "duration_s": 90.0,
                        "speed_min_mps": 0.5,
                        "speed_max_mps": 0.8,
                        "ramp_s": 3.0,
                        "drawbar": 0.12,
                        "speed_wobble_mps": 0.0,
                        "yaw_wobble_radps": 0.01,
                    }
                ),
                MappingProxyType(dict(_FIELD_SENSORS)),
            ),
            Scenario(
                "field_work",
                "long mixed field run: passes with an implement, headland U-turns, stops, rolling "
                "terrain, wet patches, an RTK-float spell and a short outage",
                _field_work,
                _with_common(
                    {
                        "duration_s": 300.0,
                        "work_speed_mps": 2.5,
                        "turn_speed_mps": 1.5,
                        "turn_radius_m": 6.0,
                        "pass_length_m": 80.0,
                        "drawbar": 0.08,
                        "stop_every_passes": 3,
                        "hill_pitch_deg": 3.0,
                        "hill_length_m": 120.0,
                        "bank_roll_deg": 1.5,
                        "wet_every_m": 150.0,
                        "wet_length_m": 10.0,
                        "mu_wet": 0.42,
                    }
                ),
                MappingProxyType(
                    {
                        **_FIELD_SENSORS,
                        "gnss_float_windows": _float_spell,
                        "gnss_outages": _short_outage,
                    }
                ),
            ),
            Scenario(
                "random_drive",
                "from rest, legs of random speed and turn rate with stops; the random-drive "
                "bench's drive (its knobs drawn over stated ranges)",
                _random_drive,
                _with_common(
                    {
                        "duration_s": 150.0,
                        "stand_s": 2.0,
                        "speed_min_mps": 1.0,
                        "speed_max_mps": 4.0,
                        "turn_rate_max_radps": 0.3,
                        "leg_s": (4.0, 15.0),
                        "stop_prob": 0.15,
                        "drawbar": 0.05,
                    }
                ),
                MappingProxyType(dict(_FIELD_SENSORS)),
            ),
        )
    }
)


def scenario_names() -> list[str]:
    """Registered scenario names, in registry order."""
    return list(SCENARIOS)
