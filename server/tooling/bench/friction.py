"""Friction estimator accuracy on the four-wheel simulator (``method.md`` §5, source 004).

``slipfleet bench friction [--seeds 1,2,101,102] [--holdout-seeds 201,202] [--random N]
[--modes product,paper,…] [--no-holdout] [--wheel-sensor tooth|instant] [--json PATH]`` or
``python -m server.tooling.bench.friction``.

Every named manoeuvre of :mod:`estimator.sim.four_wheel` runs once per seed of each seed set
(``--seeds`` is the set the estimator was tuned on, ``--holdout-seeds`` one it never was),
plus ``--random N`` random manoeuvres on random vehicles per set. The CAN wheel speeds
(``--wheel-sensor``): ``tooth`` (default), the named runs' ECU times a 48-tooth ring and
reports the mean over its period, each random vehicle draws its ring and ECU
(:func:`~estimator.sim.four_wheel.random_wheel_sensor`: 40-100 teeth, one ECU in ten
sampling); ``instant``, every run's ECU samples the instantaneous speed. Each run feeds four filters
side by side: fixed-stiffness CKF, load-adaptive CKF, the source's SCKF-MEE (paper mode, the
paper's front end) and the product mode; first with sensor-derived inputs (the whole
:class:`~estimator.friction.FrictionFleet`, all runs of a set as one batched fleet), then with
the true inputs (truth κ, α, δ, Fz and accelerations straight into the filter), and last the
true inputs with the truth's own tyres (each wheel's brush stiffness and ``kz``, which the
config knows to ±3 % and, for a damaged tyre, not at all): the gap between the last two tables
is what the tyres' stiffness costs μ.

Per manoeuvre and filter (median over runs, worst in brackets):

* ``conv``: seconds from the manoeuvre's start until the filter's μ is within 5 % of the true
  μ and stays there to the segment's end (``after step``: the same from a μ step); ``>``
  when it never is;
* ``conv_claim``: the same for the *reported* μ (the INFORMED value, held; none before the
  first INFORMED tick): when the product claims μ within 5 %. The floors on convergence from
  the start (accelerate and steering step on μ 0.8) are judged on it: the filter's μ can sit
  in the band by its start value while its 1-σ is ±20 % (``friction_info``), which is no
  learnt μ (with true inputs no tick is flagged, so ``>`` there);
* ``steady``: mean |error| over the last 2 s, percent of true μ;
* ``rms``: RMS error over the manoeuvre, percent;
* ``informed``: share of the manoeuvre's ticks flagged INFORMED, percent;
* ``worst inf``: the largest error of the *reported* μ while flagged INFORMED, percent.

The floors (product mode, sensor inputs, each set) are checked at the end.
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from estimator.friction import FilterConfig, FrictionFleet, FrictionFleetConfig, FrictionMode
from estimator.friction.axle import AxleConfig
from estimator.friction.filter import (
    TickInputs,
    TyreArrays,
    filter_step,
    initial_state,
    mu_of,
)
from estimator.friction.model import Chassis
from estimator.friction_spec import FrictionFlag
from estimator.sim.four_wheel import (
    FOUR_WHEEL_CONFIG,
    INSTANT_WHEEL_SENSOR,
    NAMED,
    FourWheelRun,
    WheelSpeedSensor,
    random_config,
    random_manoeuvre,
    random_wheel_sensor,
    simulate_four_wheel,
)
from estimator.sim.four_wheel.dynamics import AIR_DENSITY_KGPM3
from server.tooling.bench import int_list, write_json

__all__ = ["main", "run"]

TICK_S = 0.02
STEP_NS = 100_000_000
"""Sensor time between the fleet's advance calls."""
BAND = 0.05
MODES = tuple(FrictionMode)


@dataclass(frozen=True, slots=True)
class Series:
    """One run's μ through one filter: times [s], filter μ, reported μ, INFORMED flags and the
    reported μ's 1-σ (NaN before the first informed μ; ``None`` where the filter states none)."""

    t_s: np.ndarray
    mu_filter: np.ndarray
    mu_reported: np.ndarray
    informed: np.ndarray
    mu_std: np.ndarray | None = None


def _random_base(seeds: Sequence[int]) -> int:
    """Seeds of a set's random runs: ``10,000 + 100·(its first seed) + k``, so each seed set
    has random runs of its own (disjoint sets, disjoint random runs)."""
    return 10_000 + 100 * seeds[0]


def _runs(
    seeds: Sequence[int], random_n: int, random_base: int, wheel_sensor: str = "tooth"
) -> list[FourWheelRun]:
    """The named runs of every seed, then ``random_n`` random ones; each random vehicle's
    wheel-speed sensor drawn after its manoeuvre and config (``wheel_sensor`` ``tooth``) or
    every run's instantaneous (``instant``)."""
    instant = wheel_sensor == "instant"
    named = [(m, s, None) for s in seeds for m in NAMED.values()]
    sensors = [INSTANT_WHEEL_SENSOR if instant else WheelSpeedSensor()] * len(named)
    extra = []
    for k in range(random_n):
        rng = np.random.default_rng(random_base + k)
        extra.append((random_manoeuvre(rng, k), random_base + k, random_config(rng)))
        sensors.append(INSTANT_WHEEL_SENSOR if instant else random_wheel_sensor(rng))
    todo = named + extra
    configs = [c if c is not None else FOUR_WHEEL_CONFIG for _, _, c in todo]
    return simulate_four_wheel(
        [m for m, _, _ in todo], [s for _, s, _ in todo], configs, wheel_sensors=sensors
    )


def _last_stamp(m: Any) -> int:
    st = m.stamp_ns
    return int(st[-1]) if hasattr(st, "__len__") else int(st)


def feed_runs(fleet: FrictionFleet, runs: list[FourWheelRun]) -> list[list[np.ndarray]]:
    """Every run as one vehicle of ``fleet``, fed its sensor packets 100 ms at a time; the
    fleet's rows per run, in order."""
    for i, r in enumerate(runs):
        fleet.add_vehicle(str(i), r.config)
    cursor = [0] * len(runs)
    rows: list[list[np.ndarray]] = [[] for _ in runs]
    start = runs[0].start_ns
    end = start + round(max(r.manoeuvre.duration_s for r in runs) * 1e9) + STEP_NS
    for now in range(start + STEP_NS, end + STEP_NS, STEP_NS):
        for i, r in enumerate(runs):
            ms = r.measurements
            while cursor[i] < len(ms) and _last_stamp(ms[cursor[i]]) <= now:
                fleet.push(str(i), ms[cursor[i]])
                cursor[i] += 1
        for vid, out in fleet.advance({str(i): now for i in range(len(runs))}):
            rows[int(vid)].append(out)
    return rows


def sensor_series(runs: list[FourWheelRun], mode: FrictionMode) -> list[Series]:
    """Every run as one vehicle of one fleet, fed its sensor packets 100 ms at a time."""
    fleet = FrictionFleet(FrictionFleetConfig(filter=FilterConfig(mode=mode, tick_s=TICK_S)))
    rows = feed_runs(fleet, runs)
    series = []
    for r, parts in zip(runs, rows, strict=True):
        a = np.concatenate(parts)
        series.append(
            Series(
                (a["stamp_ns"] - r.start_ns) / 1e9,
                a["mu_filter"],
                a["mu"],
                (a["flags"] & FrictionFlag.INFORMED) > 0,
                a["mu_std"],
            )
        )
    return series


def true_series(
    runs: list[FourWheelRun], mode: FrictionMode, true_tyres: bool = False
) -> list[Series]:
    """The filter alone, fed the truth's relaxed slips, loads, steer angles and accelerations;
    with ``true_tyres`` also the truth's own tyres (per wheel ``c_px``, ``c_py``, ``kz``) instead
    of the config's: what μ is worth where the stiffness is known."""
    cfg = FilterConfig(mode=mode, tick_s=TICK_S)
    configs = [r.config for r in runs]
    chassis = Chassis.of(configs)
    tyres = TyreArrays(
        *(
            np.array([[getattr(c.tyre, f)] for c in configs])
            for f in ("kz_npm", "unloaded_radius_m", "c_px_npm2", "c_py_npm2")
        )
    )
    if true_tyres:
        tyres = TyreArrays(
            np.stack([r.tyre_kz_npm for r in runs]),
            tyres.radius_m,
            np.stack([r.tyre_c_px_npm2 for r in runs]),
            np.stack([r.tyre_c_py_npm2 for r in runs]),
        )
    n = min(r.truth.t_s.size for r in runs)
    idx = np.arange(0, n, round(TICK_S / 0.01))
    st = None
    mus = []
    for k in idx:
        u = _truth_inputs(runs, int(k))
        st = initial_state(cfg, tyres, u.fz_n) if st is None else st
        st = filter_step(st, cfg, tyres, chassis, u)
        mus.append(mu_of(st.x[:, 0], mode))
    mu = np.array(mus).T
    t = runs[0].truth.t_s[idx]
    return [Series(t, mu[i], mu[i], np.zeros(t.size, dtype=bool)) for i in range(len(runs))]


def _truth_inputs(runs: list[FourWheelRun], k: int) -> TickInputs:
    def col(name: str) -> np.ndarray:
        return np.stack([getattr(r.truth, name)[k] for r in runs])

    fz = col("fz_n")
    ch = [r.config.chassis for r in runs]
    vx = col("vx_mps")
    resist = np.array(
        [0.5 * AIR_DENSITY_KGPM3 * c.drag_area_m2 * v * v for c, v in zip(ch, vx, strict=True)]
    ) + np.array([c.rolling_resistance for c in ch]) * fz.sum(1)
    mass = np.array([c.mass_kg for c in ch])
    z = np.stack([col("ax_mps2") + resist / mass, col("ay_mps2"), col("yaw_accel_radps2")], 1)
    tiny = np.full(fz.shape, 1e-4)
    return TickInputs(
        fz_n=fz,
        alpha_rad=col("alpha_rad"),
        delta_rad=col("delta_rad"),
        kappa=col("kappa"),
        kappa_std=tiny,
        kappa_common_std=np.zeros(vx.shape),
        alpha_std_rad=tiny,
        z=z,
        valid=vx > 3.0,
        vx_mps=vx,
        yaw_rate_radps=col("yaw_rate_radps"),
        vy_meas_mps=col("vy_mps"),
        vy_meas_std_mps=np.full(vx.shape, 0.01),
        alpha_lag_rad=np.zeros(fz.shape),
        radius_m=np.stack([r.config.tyre.unloaded_radius_m * np.ones(4) for r in runs]),
        balance_std_n=np.full((len(runs), 2), AxleConfig().weightless_std_n),
    )


@dataclass(frozen=True, slots=True)
class Score:
    conv_s: float
    conv_claim_s: float
    conv_step_s: float
    steady_pct: float
    rms_pct: float
    informed_pct: float
    worst_informed_pct: float


def _conv(t: np.ndarray, err: np.ndarray, start: float, end: float) -> float:
    seg = (t >= start) & (t < end)
    if not seg.any():
        return math.nan
    bad = np.flatnonzero(seg & (err > BAND))
    if not bad.size:
        return 0.0
    last = t[bad[-1]]
    return math.inf if last >= t[seg][-1] - 1e-9 else float(last - start + TICK_S)


def score(r: FourWheelRun, s: Series) -> Score:
    """The run's figures (see the module docstring)."""
    m = r.manoeuvre
    mu_true = np.interp(s.t_s, r.truth.t_s, r.truth.mu)
    err = np.abs(s.mu_filter - mu_true) / mu_true
    seg = s.t_s >= m.t0_s
    step = m.mu_step_s if math.isfinite(m.mu_step_s) else math.inf
    conv = _conv(s.t_s, err, m.t0_s, step)
    rep_err = np.abs(s.mu_reported - mu_true) / mu_true
    claim = _conv(s.t_s, np.where(np.isnan(rep_err), math.inf, rep_err), m.t0_s, step)
    conv_step = _conv(s.t_s, err, step, math.inf) if math.isfinite(step) else math.nan
    last = s.t_s >= s.t_s[-1] - 2.0
    inf = s.informed & seg
    return Score(
        conv,
        claim,
        conv_step,
        100 * float(err[last].mean()),
        100 * float(np.sqrt((err[seg] ** 2).mean())),
        100 * float(inf[seg].mean()),
        100 * float(rep_err[inf].max()) if inf.any() else math.nan,
    )


LOW_MU = 0.5
"""The μ bands of the calibration table: true μ below it, and at or above it."""


@dataclass(frozen=True, slots=True)
class Calibration:
    """One run's ticks from the manoeuvre's start, for the stated σ's calibration: the
    normalised error ``(μ̂ − μ)/σ`` of the informed rows (μ̂ and σ as reported) and of the
    held rows (the held μ against the truth now, with the σ the row states, or where it
    states none, the σ stated at its last informed tick), and each row's true μ."""

    z_informed: np.ndarray
    mu_informed: np.ndarray
    z_held: np.ndarray
    mu_held: np.ndarray


def _held_std(informed: np.ndarray, std: np.ndarray) -> np.ndarray:
    """The 1-σ stated at each row's last informed tick (NaN before the first)."""
    idx = np.where(informed, np.arange(informed.size), -1)
    last = np.maximum.accumulate(idx)
    return np.where(last >= 0, std[np.maximum(last, 0)], math.nan)


def calibration(r: FourWheelRun, s: Series) -> Calibration:
    """The run's normalised errors (see :class:`Calibration`)."""
    mu_true = np.interp(s.t_s, r.truth.t_s, r.truth.mu)
    std = s.mu_std if s.mu_std is not None else np.full(s.t_s.size, math.nan)
    seg = s.t_s >= r.manoeuvre.t0_s
    stated = np.where(np.isfinite(std), std, _held_std(s.informed, std))
    inf = seg & s.informed & np.isfinite(std)
    held = seg & ~s.informed & np.isfinite(s.mu_reported) & np.isfinite(stated)
    with np.errstate(invalid="ignore", divide="ignore"):
        z = (s.mu_reported - mu_true) / stated
    return Calibration(z[inf], mu_true[inf], z[held], mu_true[held])


def _cal_cells(z: np.ndarray) -> list[str]:
    """Ticks, share within 2σ [%], NEES (``z²``) median and p95."""
    if not z.size:
        return ["0", "-", "-", "-"]
    nees = z * z
    return [
        str(z.size),
        f"{100 * float((np.abs(z) < 2.0).mean()):.1f}",
        f"{float(np.median(nees)):.2f}",
        f"{float(np.percentile(nees, 95)):.2f}",
    ]


def _cal_rows(
    names: list[str], runs: list[FourWheelRun], cals: list[Calibration]
) -> list[tuple[str, list[Calibration]]]:
    """The table's rows: each manoeuvre (the random ones as one), then every run by μ band."""
    rows = [
        (name, [c for r, c in zip(runs, cals, strict=True) if _group(r) == name]) for name in names
    ]
    return [*rows, ("all", cals)]


def _band(c: Calibration, low: bool) -> Calibration:
    """The ticks of ``c`` whose true μ is in the band (below :data:`LOW_MU` or not)."""
    a = (c.mu_informed < LOW_MU) == low
    b = (c.mu_held < LOW_MU) == low
    return Calibration(c.z_informed[a], c.mu_informed[a], c.z_held[b], c.mu_held[b])


def _calibration_table(
    runs: list[FourWheelRun], cals: list[Calibration], mode: str
) -> dict[str, Any]:
    """Print the stated σ's calibration of ``mode`` (ticks pooled over a manoeuvre's runs)."""
    print(f"  calibration of the stated σ, {mode}: ticks, |μ̂ − μ| < 2σ [%], NEES median, p95")
    head = ["informed", "≤2σ", "NEES50", "NEES95", "held", "≤2σ", "NEES50", "NEES95"]
    print("  " + f"{'manoeuvre':18s}{'band':>7s}" + "".join(f"{h:>9s}" for h in head))
    names = list(dict.fromkeys(_group(r) for r in runs))
    out: dict[str, Any] = {}
    for name, group in _cal_rows(names, runs, cals):
        for band, low in (("<0.5", True), ("≥0.5", False)):
            part = [_band(c, low) for c in group]
            zi = np.concatenate([c.z_informed for c in part])
            zh = np.concatenate([c.z_held for c in part])
            if not zi.size and not zh.size:
                continue
            cells = _cal_cells(zi) + _cal_cells(zh)
            out.setdefault(name, {})[band] = {"informed": cells[:4], "held": cells[4:]}
            print("  " + f"{name:18s}{band:>7s}" + "".join(f"{c:>9s}" for c in cells))
    return out


def _group(r: FourWheelRun) -> str:
    """A run's manoeuvre name, the random ones as ``random``."""
    name: str = r.manoeuvre.name
    return "random" if name.startswith("random") else name


def _fmt(values: list[float], unit: str = "") -> str:
    v = np.array(values, dtype=float)
    if np.all(np.isnan(v)):
        return "-"
    fin = v[np.isfinite(v)]
    med = float(np.nanmedian(np.where(np.isinf(v), np.nan, v))) if fin.size else math.inf
    worst = float(np.nanmax(v))

    def f(x: float) -> str:
        return ">" if math.isinf(x) else f"{x:.2f}{unit}"

    if np.isinf(v).sum() * 2 > np.isfinite(v).sum() + np.isinf(v).sum():
        med = math.inf
    return f"{f(med)} [{f(worst)}]"


FIGURES = (
    "conv_s",
    "conv_claim_s",
    "conv_step_s",
    "steady_pct",
    "rms_pct",
    "informed_pct",
    "worst_informed_pct",
)


def _table(
    title: str,
    runs: list[FourWheelRun],
    scores: dict[str, list[Score]],
    modes: Sequence[FrictionMode],
) -> dict[str, Any]:
    print(f"\n{title}")
    names = list(
        dict.fromkeys(
            r.manoeuvre.name.split("_")[0]
            if r.manoeuvre.name.startswith("random")
            else r.manoeuvre.name
            for r in runs
        )
    )
    out: dict[str, Any] = {}
    for fig in FIGURES:
        print(f"  {fig}: median [worst] over runs")
        print("  " + f"{'manoeuvre':18s}" + "".join(f"{m.value:>22s}" for m in modes))
        for name in names:
            pick = [
                i
                for i, r in enumerate(runs)
                if r.manoeuvre.name == name
                or (name == "random" and r.manoeuvre.name.startswith("random"))
            ]
            cells = []
            for mode in modes:
                vals = [getattr(scores[mode.value][i], fig) for i in pick]
                out.setdefault(name, {}).setdefault(mode.value, {})[fig] = vals
                cells.append(_fmt(vals))
            print("  " + f"{name:18s}" + "".join(f"{c:>22s}" for c in cells))
    return out


def _floors(runs: list[FourWheelRun], sc: list[Score]) -> dict[str, bool]:
    def of(name: str) -> list[Score]:
        return [s for r, s in zip(runs, sc, strict=True) if r.manoeuvre.name == name]

    def worst(name: str, fig: str) -> float:
        vals = [getattr(s, fig) for s in of(name)]
        return max(vals) if vals else math.nan

    informed = [s.worst_informed_pct for s in sc if math.isfinite(s.worst_informed_pct)]
    checks = {
        "accelerate μ 0.8 within 5 % ≤ 1.52 s": worst("accelerate_mu08", "conv_claim_s") <= 1.52,
        "steering step μ 0.8 ≤ 0.88 s": worst("steer_mu08", "conv_claim_s") <= 0.88,
        "steady error < 1 % high μ": max(
            worst("accelerate_mu08", "steady_pct"), worst("steer_mu08", "steady_pct")
        )
        < 1.0,
        "steady error < 4 % low μ": max(
            worst("accelerate_mu03", "steady_pct"), worst("steer_mu03", "steady_pct")
        )
        < 4.0,
        "μ step re-converged ≤ 1.5 s": max(
            worst("accelerate_step", "conv_step_s"), worst("steer_step", "conv_step_s")
        )
        <= 1.5,
        "damaged tyre within 5 %": worst("damaged_tyre", "steady_pct") < 5.0,
        "never > 10 % while informed": (max(informed) if informed else 0.0) <= 10.0,
        "constant speed uninformed ≥ 95 %": worst("constant_speed", "informed_pct") <= 5.0,
    }
    return checks


def _one_set(
    label: str,
    seeds: Sequence[int],
    random_n: int,
    modes: Sequence[FrictionMode],
    wheel_sensor: str,
) -> dict[str, Any]:
    t0 = time.process_time()
    runs = _runs(seeds, random_n, _random_base(seeds), wheel_sensor)
    sim_s = time.process_time() - t0
    result: dict[str, Any] = {
        "seeds": list(seeds),
        "random": random_n,
        "wheel_sensor": wheel_sensor,
        "sim_cpu_s": sim_s,
    }
    inputs_of = (
        ("sensor", sensor_series),
        ("true", true_series),
        ("true_tyres", lambda r, m: true_series(r, m, true_tyres=True)),
    )
    for inputs, fn in inputs_of:
        t1 = time.process_time()
        series = {m.value: fn(runs, m) for m in modes}
        scores = {
            m: [score(r, s) for r, s in zip(runs, ss, strict=True)] for m, ss in series.items()
        }
        title = f"{label} seeds {list(seeds)} (+{random_n} random): {inputs} inputs"
        result[inputs] = _table(title, runs, scores, modes)
        if inputs == "sensor":
            result["calibration"] = {
                m: _calibration_table(
                    runs, [calibration(r, s) for r, s in zip(runs, ss, strict=True)], m
                )
                for m, ss in series.items()
            }
        result[f"{inputs}_cpu_s"] = time.process_time() - t1
        if inputs == "sensor" and FrictionMode.PRODUCT in modes:
            floors = _floors(runs, scores[FrictionMode.PRODUCT.value])
            result["floors"] = floors
    print(f"\n{label}: floors (product mode, sensor inputs)")
    for name, ok in result.get("floors", {}).items():
        print(f"  {'pass' if ok else 'FAIL'}  {name}")
    print(
        f"  cpu: simulation {result['sim_cpu_s']:.0f} s, sensor {result['sensor_cpu_s']:.0f} s, "
        f"true {result['true_cpu_s'] + result['true_tyres_cpu_s']:.0f} s"
    )
    return result


def run(
    seeds: Sequence[int] = (1, 2, 101, 102),
    holdout: Sequence[int] = (201, 202),
    random_n: int = 2,
    json_path: str | None = None,
    modes: Sequence[FrictionMode] = MODES,
    wheel_sensor: str = "tooth",
) -> dict[str, Any]:
    """Both seed sets (an empty ``holdout`` skips the second), figures as in the docstring."""
    if set(seeds) & set(holdout):
        raise ValueError("the tuning and hold-out seed sets must be disjoint")
    result = {"tuning": _one_set("tuning set", seeds, random_n, modes, wheel_sensor)}
    if holdout:
        result["holdout"] = _one_set("hold-out set", holdout, random_n, modes, wheel_sensor)
    write_json(result, json_path)
    return result


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="slipfleet bench friction", description=__doc__.split("\n")[0])
    p.add_argument("--seeds", type=int_list, default=[1, 2, 101, 102], help="tuning seed set")
    p.add_argument(
        "--holdout-seeds",
        type=int_list,
        default=[201, 202],
        help="seed set never tuned on (disjoint from --seeds)",
    )
    p.add_argument("--random", type=int, default=2, help="random manoeuvres per seed set")
    p.add_argument("--json", default=None, help="write the figures as JSON here")
    p.add_argument(
        "--modes",
        type=lambda t: [FrictionMode(m) for m in t.split(",")],
        default=list(MODES),
        help="filters to compare (default: all: " + ",".join(m.value for m in MODES) + ")",
    )
    p.add_argument("--no-holdout", action="store_true", help="the tuning set only")
    p.add_argument(
        "--wheel-sensor",
        choices=("tooth", "instant"),
        default="tooth",
        help="CAN wheel speeds: tooth-timed means (random vehicles drawn) or instantaneous",
    )
    a = p.parse_args(argv)
    holdout = [] if a.no_holdout else a.holdout_seeds
    run(a.seeds, holdout, a.random, a.json, a.modes, a.wheel_sensor)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
