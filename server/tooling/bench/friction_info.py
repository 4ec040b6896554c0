"""What the data can tell of μ: grip use and the Cramér-Rao bound along a simulated manoeuvre.

``python -m server.tooling.bench.friction_info [--manoeuvre accelerate_mu08] [--seeds 1,2,101,102]
[--wheel-sensor tooth|instant]``

A straight manoeuvre only: the bound reads ``a_x`` alone (in a steering manoeuvre ``a_y`` and
``ṙ`` carry μ, with the slip angles' own unknowns). For each seed the manoeuvre is simulated
(:mod:`estimator.sim.four_wheel`) and run through the product filter
(:class:`~estimator.friction.FrictionFleet`, sensor inputs); at the truth's operating point of
every filter tick (each wheel's relaxed κ, α, load and the truth's own tyres) the brush model
(:mod:`estimator.friction.brush`) gives the change of the measured ``a_x`` for a change of each
parameter ``θ = [ln μ, ln g_x,rear, ln g_x,front, b_κ]`` (the two axles' stiffness factors, and
one κ offset shared by the four wheels: the speed's error, correlated over seconds, so it does
not average out tick by tick). Each tick is weighed by the product filter's own 1-σ of ``a_x``
and of each wheel's own κ (``R + D Dᵀ``, the front end's ``kappa_std``); the Fisher
information ``Σ J Jᵀ / σ²`` is summed from the run's start (the lead-in included), and
the bound on μ's relative 1-σ is ``√(I⁻¹)₀₀``:

* ``known``: stiffness and speed known exactly (μ the only unknown);
* ``g ±1.7 %``: the factors with the simulated tyres' own spread as their prior (the truth's
  ``c_p`` is the config's ×0.97-1.03, uniform: a 1.7 % 1-σ), which no real fleet knows;
* ``g ±10 %``: the product filter's own factor prior (``factor0_rel_std``);
* ``+ b_κ``: ``g ±1.7 %`` and the shared κ offset with a prior of the front end's
  ``kappa_common_std`` (its median over the run);
* ``known, IMU σ``: as ``known`` with ``a_x`` weighed by the accelerometer's white noise alone.

Beside it: the truth's grip use (the most used rear and front tyre) and the product filter's μ,
its relative 1-σ and its INFORMED flag at the same tick.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from estimator.friction import FilterConfig, FrictionFleet, FrictionFleetConfig
from estimator.friction import fleet as fleet_module
from estimator.friction.brush import brush_forces, load_adaptive_stiffness_n
from estimator.friction.filter import FilterState, TickInputs
from estimator.friction_spec import FrictionFlag
from estimator.sim.four_wheel import (
    INSTANT_WHEEL_SENSOR,
    FourWheelRun,
    WheelSpeedSensor,
    named_manoeuvre,
    simulate_four_wheel,
)
from server.tooling.bench import int_list

__all__ = ["Info", "information", "main"]

TICK_S = 0.02
STEP_NS = 100_000_000
TIMES_S = (-1.0, 0.0, 0.1, 0.2, 0.3, 0.5, 0.75, 1.0, 1.52, 2.0, 3.0, 4.0, 6.0)
"""Times after the manoeuvre's start the table prints."""
TRUTH_G_STD = 0.03 / np.sqrt(3.0)
"""The simulated tyres' spread about the config (``c_p`` ×0.97-1.03 uniform) as a 1-σ."""
PRIORS = {"known": (0.0, 0.0), "g ±1.7 %": (TRUTH_G_STD, 0.0), "g ±10 %": (0.1, 0.0)}
"""Column → (prior 1-σ of ln g, of b_κ); ``+ b_κ`` takes the front end's shared κ 1-σ."""
IMU_STD_MPS2 = 0.05 / np.sqrt(2)
"""``a_x``'s 1-σ in a 50 Hz tick from the simulated accelerometer's white noise alone (0.05
m/s² at 100 Hz): the last column's, with every model error the filter's 0.2 m/s² allows for
taken away (the bound no filter on these sensors can beat)."""


@dataclass(frozen=True, slots=True)
class Info:
    """Per filter tick ``(T,)``: time [s], rear and front grip use, CRLB relative 1-σ of μ per
    column ``(T, 4)``, and the product filter's μ, relative 1-σ and INFORMED flag."""

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


def _a_x(run: FourWheelRun, i: int, theta: np.ndarray, kappa_shift: np.ndarray) -> float:
    """``a_x`` [m/s²] at truth row ``i`` for parameters ``θ`` (module docstring) and each
    wheel's κ shifted by ``kappa_shift`` ``(4,)``."""
    tr = run.truth
    radius = run.config.tyre.unloaded_radius_m
    c_x = load_adaptive_stiffness_n(tr.fz_n[i], run.tyre_kz_npm, radius, run.tyre_c_px_npm2)
    c_y = load_adaptive_stiffness_n(tr.fz_n[i], run.tyre_kz_npm, radius, run.tyre_c_py_npm2)
    g = np.exp(np.array([theta[2], theta[2], theta[1], theta[1]]))
    mu = tr.mu[i] * np.exp(theta[0])
    kappa = tr.kappa[i] + theta[3] + kappa_shift
    fx, fy = brush_forces(kappa, tr.alpha_rad[i], tr.fz_n[i], mu, g * c_x, c_y)
    d = tr.delta_rad[i]
    return float(np.sum(fx * np.cos(d) - fy * np.sin(d)) / run.config.chassis.mass_kg)


def _jacobian(run: FourWheelRun, i: int) -> tuple[np.ndarray, np.ndarray]:
    """``∂a_x/∂θ`` ``(4,)`` and ``∂a_x/∂κ_w`` per wheel ``(4,)`` at truth row ``i``
    (central differences)."""
    zero = np.zeros(4)
    steps = np.array([1e-4, 1e-4, 1e-4, 1e-6])
    jac = np.array(
        [
            (_a_x(run, i, e, zero) - _a_x(run, i, -e, zero)) / (2 * h)
            for e, h in zip(np.diag(steps), steps, strict=True)
        ]
    )
    wheel = np.eye(4) * 1e-6
    per_wheel = np.array([(_a_x(run, i, zero, e) - _a_x(run, i, zero, -e)) / 2e-6 for e in wheel])
    return jac, per_wheel


def _bound(fisher: np.ndarray, g_std: float, b_std: float) -> float:
    """μ's relative 1-σ bound from the summed information ``(4, 4)`` with the nuisances
    ``θ[1:]`` given priors of ``g_std`` (both factors) and ``b_std`` (0: known exactly)."""
    if fisher[0, 0] <= 0:
        return float("inf")
    prior = np.array([g_std, g_std, b_std])
    free = prior > 0
    nuisance = fisher[1:, 1:][np.ix_(free, free)] + np.diag(prior[free] ** -2.0)
    cross = fisher[0, 1:][free]
    info = fisher[0, 0] - cross @ np.linalg.solve(nuisance, cross) if free.any() else fisher[0, 0]
    return float(1.0 / np.sqrt(max(info, 1e-30)))


def information(run: FourWheelRun) -> Info:
    """The table's figures for one run (see the module docstring)."""
    inputs, states, rows = _filter_ticks(run)
    cfg = FilterConfig()
    tr = run.truth
    t_s = (rows["stamp_ns"] - run.start_ns) / 1e9
    idx = np.clip(np.searchsorted(tr.t_s, t_s - 1e-9), 0, tr.t_s.size - 1)
    use = np.hypot(tr.fx_n, tr.fy_n) / (tr.mu[:, None] * tr.fz_n)
    common = float(np.median([u.kappa_common_std[0] for u in inputs]))
    fisher = np.zeros((4, 4))
    imu = 0.0
    crlb = np.full((t_s.size, len(PRIORS) + 2), np.nan)
    for k, (u, i) in enumerate(zip(inputs, idx, strict=True)):
        if u.valid[0]:
            jac, per_wheel = _jacobian(run, int(i))
            spread = float(np.sum((per_wheel * u.kappa_std[0]) ** 2))
            fisher += np.outer(jac, jac) / (cfg.accel_std_mps2**2 + spread)
            imu += jac[0] ** 2 / (IMU_STD_MPS2**2 + spread)
        crlb[k, :-1] = [_bound(fisher, g, b) for g, b in [*PRIORS.values(), (TRUTH_G_STD, common)]]
        crlb[k, -1] = 1.0 / np.sqrt(imu) if imu > 0 else np.inf
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


def table(info: Info, mu_true: float) -> str:
    """The printed rows at :data:`TIMES_S`."""
    head = [
        "t [s]",
        "use rear",
        "use front",
        *PRIORS,
        "+ b_κ",
        "known, IMU σ",
        "μ filter",
        "σ filter",
        "inf",
    ]
    lines = [" | ".join(head), " | ".join("---" for _ in head)]
    for t in TIMES_S:
        k = int(np.argmin(np.abs(info.t_s - t)))
        cells = [f"{info.t_s[k]:.2f}", f"{info.use_rear[k]:.2f}", f"{info.use_front[k]:.2f}"]
        cells += [f"{100 * c:.1f} %" for c in info.crlb[k]]
        err = 100 * (info.mu[k] / mu_true - 1)
        cells += [f"{info.mu[k]:.3f} ({err:+.1f} %)", f"{100 * info.mu_rel_std[k]:.1f} %"]
        cells.append("yes" if info.informed[k] else "no")
        lines.append(" | ".join(cells))
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
    m = named_manoeuvre(args.manoeuvre)
    if any(v != 0.0 for _, v in m.steer_knots):
        p.error("the bound reads a_x alone: straight manoeuvres only (accelerate_*, damaged_tyre)")
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
