"""What the data can tell of μ: grip use and the Cramér-Rao bound along a simulated manoeuvre.

``python -m server.tooling.bench.friction_info [--manoeuvre accelerate_mu08|steer_mu08|…]
[--seeds 1,2,101,102] [--wheel-sensor tooth|instant]``

For each seed the manoeuvre is simulated (:mod:`estimator.sim.four_wheel`) and run through the
product filter (:class:`~estimator.friction.FrictionFleet`, sensor inputs). At the truth's
operating point of every filter tick (each wheel's relaxed κ, α, load and the truth's own
tyres) the filter's model (:mod:`estimator.friction.brush`, :mod:`estimator.friction.model`)
gives the change of the measured ``h = [a_x, a_y, ṙ]`` for a change of each parameter
:class:`Param` (``ln μ``; the axles' longitudinal and cornering stiffness factors; one κ offset
shared by the four wheels, the speed's error; the lateral speed's error ``δv_y``, which moves
every slip angle by ``∂α/∂v_y ≈ −cos δ / v_x``). Each tick is weighed as the product filter
weighs it: ``R + D Dᵀ`` with ``R`` its own 1-σ of ``a_x``, ``a_y`` and ``ṙ`` (the yaw model's
error included) and ``D`` the change of ``h`` for each wheel's own κ 1-σ (the front end's) and
for the slip angles' relaxation lag scaled by ``1 + relaxation_rel_std``. The Fisher information
``Σ Hᵀ (R + D Dᵀ)⁻¹ H`` is accumulated from the run's start, the nuisances' priors added, and
``δv_y`` walks as the filter's ``v_y`` does (``vy_walk_mps_per_sqrt_s``) and is measured by the
GNSS lateral speed the filter reads (its own 1-σ), or not at all ("no GNSS": integrated from
``a_y`` alone). The bound on μ's relative 1-σ is ``√(I⁻¹)₀₀`` (:func:`bound_series`).

Columns (:data:`COLUMNS`): ``a_x …`` the longitudinal row alone; the rest read all three rows.
``g ±1.7 %``: the four stiffness factors with the simulated tyres' own spread as their prior
(the truth's ``c_p`` is the config's ×0.97-1.03, uniform: a 1.7 % 1-σ; no real fleet knows its
tyres that well); ``g ±10 %``: the product filter's own factor prior (``factor0_rel_std``);
``known``: μ the only unknown; ``v_y known``: no lateral-speed error; ``no GNSS``: ``v_y``
integrated only; ``+ b_κ``: ``g ±1.7 %`` and the shared κ offset with the front end's
``kappa_common_std`` (its median over the run); ``IMU σ``: ``a_x``, ``a_y`` weighed by the
accelerometer's white noise and ``ṙ`` by the differenced gyro's; ``v_y sensor``: the GNSS
lateral speed at the simulated receiver's own 1-σ and ``v_y``'s error walking only as the
accelerometer's white noise integrates (no bias, no tilt): what a filter with a perfect model,
the tyres known to the simulator's ±3 % (or to the filter's prior) could reach.

Not in the bound: the yaw rate and the steering angle as inputs of the slip angles (the gyro's
0.003 rad/s is ~0.3 mrad of α at 60 km/h, the steering wheel's ≤0.5° offset ~0.5 mrad at the
road wheel), the left-right spread of the tyres (in the yaw model's error), and the response of
the motion to μ (the bound reads each tick's forces at the truth's slips, as the filter does).

Beside the bound: the truth's grip use (the most used rear and front tyre) and the product
filter's μ, its relative 1-σ and its INFORMED flag at the same tick; under each table, the
first time each column falls to 5 % at 1-σ and at 2-σ (a 2.5 % 1-σ: the far end at which the
grip gate judges).
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Sequence
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from estimator.friction import FilterConfig, FrictionFleet, FrictionFleetConfig
from estimator.friction import fleet as fleet_module
from estimator.friction.brush import brush_forces, load_adaptive_stiffness_n
from estimator.friction.filter import FilterState, TickInputs
from estimator.friction.model import Chassis, Measured, body_accelerations
from estimator.friction_spec import FrictionFlag
from estimator.sim.four_wheel import (
    INSTANT_WHEEL_SENSOR,
    FourWheelRun,
    Truth,
    WheelSpeedSensor,
    named_manoeuvre,
    simulate_four_wheel,
)
from server.tooling.bench import int_list

__all__ = ["COLUMNS", "Column", "Info", "Param", "bound_series", "information", "main"]

TICK_S = 0.02
STEP_NS = 100_000_000
TIMES_S = (-1.0, 0.0, 0.1, 0.2, 0.3, 0.5, 0.75, 0.88, 1.0, 1.52, 2.0, 3.0, 4.0, 6.0, 8.0, 10.0)
"""Times after the manoeuvre's start the table prints, those within the run (the accelerating
manoeuvres' steady window, their last 2 s, is 8-10 s)."""
TRUTH_G_STD = 0.03 / np.sqrt(3.0)
"""The simulated tyres' spread about the config (``c_p`` ×0.97-1.03 uniform) as a 1-σ."""
IMU_STD = (0.05 / np.sqrt(2), 0.05 / np.sqrt(2), 0.003 / TICK_S)
"""``a_x``, ``a_y`` and ``ṙ``'s 1-σ in a 50 Hz tick from the simulated IMU's white noise alone
(0.05 m/s² and 0.003 rad/s at 100 Hz; ``ṙ`` the difference of two ticks' mean yaw rates):
every model error the filter allows for taken away (the bound no filter on these sensors
beats)."""
BAND = 0.05
"""The convergence band of the floors: μ within 5 %."""


class Param(IntEnum):
    """The parameters ``θ`` the bound is on (μ) or carries as nuisances."""

    LN_MU = 0
    LN_GX_REAR = 1
    LN_GX_FRONT = 2
    B_KAPPA = 3
    LN_GY_FRONT = 4
    LN_GY_REAR = 5
    VY = 6
    """The lateral speed's error [m/s]."""


_STEPS = np.array([1e-4, 1e-4, 1e-4, 1e-6, 1e-4, 1e-4, 1e-4])
"""Central-difference steps per :class:`Param`."""


@dataclass(frozen=True, slots=True)
class Column:
    """One bound: the measured ``rows`` it reads, the stiffness factors' prior 1-σ ``g_std``
    (0: known), the shared κ offset's ``b_std`` (0: known; NaN: the front end's median), the
    lateral speed (``vy``: ``known``, ``gnss`` or ``integrated``; ``vy_sensor``: its GNSS
    1-σ and its error's walk the simulated sensors' own, :data:`SENSOR_VY_WALK` and
    ``Ticks.vy_sensor_std_mps``, else the filter's) and whose 1-σ weighs the rows (``imu``:
    the sensors' white noise; else the filter's)."""

    name: str
    rows: tuple[Measured, ...] = tuple(Measured)
    g_std: float = 0.0
    b_std: float = 0.0
    vy: str = "gnss"
    imu: bool = False
    vy_sensor: bool = False


_AX = (Measured.AX,)
SENSOR_VY_WALK = 0.05 * math.sqrt(0.01)
"""The walk of ``v_y`` integrated from the simulated accelerometer's white noise alone (0.05
m/s² at 100 Hz) [m/s/√s]: no bias, no tilt (the filter allows 0.05)."""
COLUMNS = (
    Column("a_x, g ±1.7 %", _AX, TRUTH_G_STD),
    Column("known", vy="known"),
    Column("g ±1.7 %, v_y known", g_std=TRUTH_G_STD, vy="known"),
    Column("g ±1.7 %", g_std=TRUTH_G_STD),
    Column("g ±10 %", g_std=0.1),
    Column("g ±10 %, no GNSS", g_std=0.1, vy="integrated"),
    Column("+ b_κ", g_std=TRUTH_G_STD, b_std=math.nan),
    Column("known, IMU σ", vy="known", imu=True),
    Column("g ±1.7 %, IMU σ, v_y sensor", g_std=TRUTH_G_STD, imu=True, vy_sensor=True),
    Column("g ±10 %, IMU σ, v_y sensor", g_std=0.1, imu=True, vy_sensor=True),
)
"""The printed bounds (see the module docstring)."""


@dataclass(frozen=True, slots=True)
class Ticks:
    """Per filter tick ``T``: the Jacobian ``∂h/∂θ`` ``(T, 3, 7)``, the inputs' spread ``D``
    ``(T, 3, 5)``, whether the filter updates ``(T,)``, and the GNSS lateral speed's 1-σ
    (NaN: none that tick) ``(T,)`` as the filter weighs it and as the simulated receiver
    gives it (``hypot(0.03 m/s, v_x · 0.15°)``: velocity noise and heading noise)."""

    jac: np.ndarray
    spread: np.ndarray
    valid: np.ndarray
    vy_std_mps: np.ndarray
    vy_sensor_std_mps: np.ndarray


@dataclass(frozen=True, slots=True)
class Info:
    """Per filter tick ``(T,)``: time [s], rear and front grip use, CRLB relative 1-σ of μ per
    column ``(T, len(COLUMNS))``, and the product filter's μ, relative 1-σ and INFORMED flag."""

    t_s: np.ndarray
    use_rear: np.ndarray
    use_front: np.ndarray
    crlb: np.ndarray
    mu: np.ndarray
    mu_rel_std: np.ndarray
    informed: np.ndarray
    kappa_common_std: float


def _filter_ticks(run: FourWheelRun) -> tuple[list[TickInputs], list[FilterState], np.ndarray]:
    """The product filter on ``run``'s sensors: every tick's inputs and posterior, and rows.

    The fleet's call of :func:`~estimator.friction.filter.filter_step` is wrapped for the run
    (and put back after) to read what the rows do not carry: the inputs' 1-σ and the state's."""
    seen: list[tuple[TickInputs, FilterState]] = []
    step = fleet_module.filter_step

    def spy(st: FilterState, cfg: FilterConfig, *rest: object) -> FilterState:
        out = step(st, cfg, *rest)  # type: ignore[arg-type]
        seen.append((rest[2], out))  # type: ignore[arg-type]
        return out

    fleet_module.filter_step = spy  # type: ignore[assignment]
    try:
        fleet = FrictionFleet(FrictionFleetConfig(filter=FilterConfig(tick_s=TICK_S)))
        fleet.add_vehicle("v", run.config)
        ms, k, rows = run.measurements, 0, []
        end = run.start_ns + round(run.manoeuvre.duration_s * 1e9) + STEP_NS
        for now in range(run.start_ns + STEP_NS, end, STEP_NS):
            while k < len(ms) and int(np.max(ms[k].stamp_ns)) <= now:
                fleet.push("v", ms[k])
                k += 1
            rows += [out for _, out in fleet.advance({"v": now})]
    finally:
        fleet_module.filter_step = step
    return [u for u, _ in seen], [s for _, s in seen], np.concatenate(rows)


def _kinematic_alpha(chassis: Chassis, tr: Truth, i: int, vy_mps: float) -> np.ndarray:
    """The rigid-body slip angles ``(4,)`` at truth row ``i`` with lateral speed ``vy_mps``
    (the filter's relation, source eq. 9-13)."""
    r = float(tr.yaw_rate_radps[i])
    along = float(tr.vx_mps[i]) - chassis.wheel_y_m[0] * r
    across = vy_mps + chassis.wheel_x_m[0] * r
    d = tr.delta_rad[i]
    v_long = along * np.cos(d) + across * np.sin(d)
    v_lat = -along * np.sin(d) + across * np.cos(d)
    alpha: np.ndarray = -np.arctan2(v_lat, np.maximum(np.abs(v_long), 0.5))
    return alpha


def _h(
    run: FourWheelRun,
    chassis: Chassis,
    i: int,
    theta: np.ndarray,
    kappa_shift: np.ndarray | None = None,
    alpha_shift: np.ndarray | None = None,
) -> np.ndarray:
    """``[a_x, a_y, ṙ]`` ``(3,)`` at truth row ``i`` for parameters ``θ`` (:class:`Param`),
    each wheel's κ and α shifted by ``kappa_shift``, ``alpha_shift`` ``(4,)``."""
    tr = run.truth
    radius = run.config.tyre.unloaded_radius_m
    c_x = load_adaptive_stiffness_n(tr.fz_n[i], run.tyre_kz_npm, radius, run.tyre_c_px_npm2)
    c_y = load_adaptive_stiffness_n(tr.fz_n[i], run.tyre_kz_npm, radius, run.tyre_c_py_npm2)
    gx = np.exp(theta[[Param.LN_GX_FRONT] * 2 + [Param.LN_GX_REAR] * 2])
    gy = np.exp(theta[[Param.LN_GY_FRONT] * 2 + [Param.LN_GY_REAR] * 2])
    mu = tr.mu[i] * np.exp(theta[Param.LN_MU])
    kappa = tr.kappa[i] + theta[Param.B_KAPPA]
    alpha = np.asarray(tr.alpha_rad[i], dtype=np.float64)
    if theta[Param.VY] != 0.0:
        vy = float(tr.vy_mps[i])
        alpha = alpha + _kinematic_alpha(chassis, tr, i, vy + theta[Param.VY])
        alpha = alpha - _kinematic_alpha(chassis, tr, i, vy)
    if kappa_shift is not None:
        kappa = kappa + kappa_shift
    if alpha_shift is not None:
        alpha = alpha + alpha_shift
    fx, fy = brush_forces(kappa, alpha, tr.fz_n[i], mu, gx * c_x, gy * c_y)
    delta = np.asarray(tr.delta_rad[i], dtype=np.float64)[None, None, :]
    acc: np.ndarray = body_accelerations(fx[None, None], fy[None, None], delta, chassis)[0, 0]
    return acc


def _jacobian(run: FourWheelRun, chassis: Chassis, i: int) -> tuple[np.ndarray, np.ndarray]:
    """``∂h/∂θ`` ``(3, 7)`` and ``∂h/∂κ_w`` per wheel ``(3, 4)`` at truth row ``i`` (central
    differences)."""
    zero = np.zeros(len(Param))
    jac = np.stack(
        [
            (_h(run, chassis, i, e) - _h(run, chassis, i, -e)) / (2 * s)
            for e, s in zip(np.diag(_STEPS), _STEPS, strict=True)
        ],
        axis=1,
    )
    per_wheel = np.stack(
        [
            (_h(run, chassis, i, zero, e) - _h(run, chassis, i, zero, -e)) / 2e-6
            for e in np.eye(4) * 1e-6
        ],
        axis=1,
    )
    return jac, per_wheel


def _ticks(
    run: FourWheelRun, inputs: list[TickInputs], idx: np.ndarray, cfg: FilterConfig
) -> Ticks:
    """The Jacobians and the spread the filter adds (``D``: each wheel's κ 1-σ, and the slip
    angles' lag scaled by ``1 + relaxation_rel_std``) at truth rows ``idx`` of its ticks."""
    chassis = Chassis.of([run.config])
    zero = np.zeros(len(Param))
    jac = np.zeros((idx.size, 3, len(Param)))
    spread = np.zeros((idx.size, 3, 5))
    for k, (u, i) in enumerate(zip(inputs, idx, strict=True)):
        if not u.valid[0]:
            continue
        jac[k], per_wheel = _jacobian(run, chassis, int(i))
        lag = u.alpha_lag_rad[0] * cfg.relaxation_rel_std
        base = _h(run, chassis, int(i), zero)
        spread[k, :, :4] = per_wheel * u.kappa_std[0]
        spread[k, :, 4] = _h(run, chassis, int(i), zero, alpha_shift=lag) - base
    vy_std = np.array(
        [u.vy_meas_std_mps[0] if np.isfinite(u.vy_meas_mps[0]) else np.nan for u in inputs]
    )
    vx = np.array([float(u.vx_mps[0]) for u in inputs])
    sensor = np.where(np.isnan(vy_std), np.nan, np.hypot(0.03, vx * math.radians(0.15)))
    return Ticks(jac, spread, np.array([bool(u.valid[0]) for u in inputs]), vy_std, sensor)


def _free(col: Column, b_std: float, vy0_std: float) -> tuple[list[int], np.ndarray]:
    """The parameters the column estimates (μ first) and their prior 1-σ (μ: none, 0)."""
    free, prior = [int(Param.LN_MU)], [0.0]
    if col.g_std > 0:
        gs = (Param.LN_GX_REAR, Param.LN_GX_FRONT, Param.LN_GY_FRONT, Param.LN_GY_REAR)
        free += [int(p) for p in gs]
        prior += [col.g_std] * 4
    if b_std > 0:
        free.append(int(Param.B_KAPPA))
        prior.append(b_std)
    if col.vy != "known":
        free.append(int(Param.VY))
        prior.append(vy0_std)
    return free, np.array(prior)


def _mu_bound(info: np.ndarray) -> float:
    """μ's 1-σ from the information ``(n, n)`` over ``[ln μ, nuisances…]``: ``1/√`` of the
    Schur complement ``I₀₀ − I₀ᵣ I_rr⁻¹ I_r₀`` (infinite where nothing is known)."""
    schur = info[0, 0]
    if info.shape[0] > 1:
        schur -= info[0, 1:] @ np.linalg.solve(info[1:, 1:], info[1:, 0])
    return float(1.0 / np.sqrt(schur)) if schur > 0 else math.inf


def bound_series(
    ticks: Ticks,
    col: Column,
    sigma: Sequence[float] | np.ndarray,
    b_std: float = 0.0,
    vy0_std_mps: float = 0.05,
    vy_walk_mps_per_sqrt_s: float = 0.05,
    tick_s: float = TICK_S,
) -> np.ndarray:
    """μ's relative 1-σ bound ``(T,)`` after each tick for column ``col`` (``sigma``: the 1-σ
    of ``[a_x, a_y, ṙ]``; ``b_std`` the shared κ offset's prior, 0: known).

    The information over the free parameters starts at their priors and, each tick, the
    lateral speed's error walks (``I ← I − I e eᵀ I / (1/q + eᵀ I e)``, the information form of
    ``P ← P + q e eᵀ``, ``q`` the walk's variance a tick), the GNSS lateral speed adds
    ``1/σ²`` to it (column ``gnss``), and an updating tick adds ``Hᵀ (R + D Dᵀ)⁻¹ H`` of the
    column's rows. Without the walk this is the summed Fisher information with the priors'."""
    free, prior = _free(col, b_std, vy0_std_mps)
    info = np.diag(np.divide(1.0, prior**2, out=np.zeros_like(prior), where=prior > 0))
    rows = [int(r) for r in col.rows]
    r_cov = np.diag(np.square(np.asarray(sigma, dtype=np.float64))[rows])
    vy = free.index(int(Param.VY)) if int(Param.VY) in free else None
    walk = SENSOR_VY_WALK if col.vy_sensor else vy_walk_mps_per_sqrt_s
    q = walk**2 * tick_s
    gnss = ticks.vy_sensor_std_mps if col.vy_sensor else ticks.vy_std_mps
    out = np.empty(ticks.valid.size)
    for k in range(ticks.valid.size):
        if vy is not None:
            if q > 0:
                e = info[:, vy].copy()
                info -= np.outer(e, e) / (1.0 / q + e[vy])
            if col.vy == "gnss" and np.isfinite(gnss[k]):
                info[vy, vy] += gnss[k] ** -2.0
        if ticks.valid[k]:
            h = ticks.jac[k][np.ix_(rows, free)]
            d = ticks.spread[k][rows]
            info += h.T @ np.linalg.solve(r_cov + d @ d.T, h)
        out[k] = _mu_bound(info)
    return out


def information(run: FourWheelRun) -> Info:
    """The table's figures for one run (see the module docstring)."""
    inputs, states, rows = _filter_ticks(run)
    cfg = FilterConfig()
    tr = run.truth
    t_s = (rows["stamp_ns"] - run.start_ns) / 1e9
    idx = np.clip(np.searchsorted(tr.t_s, t_s - 1e-9), 0, tr.t_s.size - 1)
    use = np.hypot(tr.fx_n, tr.fy_n) / (tr.mu[:, None] * tr.fz_n)
    common = float(np.median([u.kappa_common_std[0] for u in inputs]))
    ticks = _ticks(run, inputs, idx, cfg)
    own = (
        cfg.accel_std_mps2,
        cfg.accel_std_mps2,
        math.hypot(cfg.yaw_accel_std_radps2, cfg.yaw_model_std_radps2),
    )
    crlb = np.stack(
        [
            bound_series(
                ticks,
                col,
                IMU_STD if col.imu else own,
                common if math.isnan(col.b_std) else col.b_std,
                cfg.vy0_std_mps,
                cfg.vy_walk_mps_per_sqrt_s,
                cfg.tick_s,
            )
            for col in COLUMNS
        ],
        axis=1,
    )
    ln_std = np.array([np.sqrt(np.sum(s.s[0, 0] ** 2)) for s in states])
    return Info(
        t_s - run.manoeuvre.t0_s,
        use[idx][:, 2:].max(axis=1),
        use[idx][:, :2].max(axis=1),
        crlb,
        rows["mu_filter"],
        ln_std,
        (rows["flags"] & FrictionFlag.INFORMED) > 0,
        common,
    )


def first_within(t_s: np.ndarray, bound: np.ndarray, level: float) -> float:
    """The first time ``≥ 0`` [s] at which ``bound`` is ``level`` or less (NaN: never)."""
    hit = np.flatnonzero((t_s >= -1e-9) & (bound <= level))
    return float(t_s[hit[0]]) if hit.size else math.nan


def table(info: Info, mu_true: float) -> str:
    """The printed rows at :data:`TIMES_S`, and the first times within the band."""
    head = ["t [s]", "use rear", "use front", *(c.name for c in COLUMNS)]
    head += ["μ filter", "σ filter", "inf"]
    lines = [" | ".join(head), " | ".join("---" for _ in head)]
    for t in TIMES_S:
        if t > info.t_s[-1] + TICK_S:
            continue
        k = int(np.argmin(np.abs(info.t_s - t)))
        cells = [f"{info.t_s[k]:.2f}", f"{info.use_rear[k]:.2f}", f"{info.use_front[k]:.2f}"]
        cells += [f"{100 * c:.1f} %" for c in info.crlb[k]]
        err = 100 * (info.mu[k] / mu_true - 1)
        cells += [f"{info.mu[k]:.3f} ({err:+.1f} %)", f"{100 * info.mu_rel_std[k]:.1f} %"]
        cells.append("yes" if info.informed[k] else "no")
        lines.append(" | ".join(cells))
    for label, level in (("1-σ ≤ 5 %", BAND), ("2-σ ≤ 5 %", BAND / 2)):
        cells = [f"first {label}", "", ""]
        for c in range(len(COLUMNS)):
            when = first_within(info.t_s, info.crlb[:, c], level)
            cells.append("never" if math.isnan(when) else f"{when:.2f} s")
        lines.append(" | ".join([*cells, "", "", ""]))
    return "\n".join(f"| {line} |" for line in lines)


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="slipfleet bench friction_info", description=__doc__.split("\n")[0]
    )
    p.add_argument("--manoeuvre", default="accelerate_mu08")
    p.add_argument("--seeds", type=int_list, default=[1, 2, 101, 102])
    p.add_argument("--wheel-sensor", choices=("tooth", "instant"), default="tooth")
    args = p.parse_args(argv)
    sensor = INSTANT_WHEEL_SENSOR if args.wheel_sensor == "instant" else WheelSpeedSensor()
    try:
        m = named_manoeuvre(args.manoeuvre)
    except KeyError as e:
        p.error(str(e))
    runs = simulate_four_wheel(
        [m] * len(args.seeds), args.seeds, wheel_sensors=[sensor] * len(args.seeds)
    )
    for seed, run in zip(args.seeds, runs, strict=True):
        info = information(run)
        print(
            f"\n{args.manoeuvre}, seed {seed}, {args.wheel_sensor} sensor: the bound is on μ's"
            f" relative 1-σ (the front end's shared κ 1-σ: {info.kappa_common_std:.1e})"
        )
        print(table(info, float(run.truth.mu[-1])))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
