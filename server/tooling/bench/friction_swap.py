"""The damaged-tyre manoeuvre replayed with one front-end input at a time swapped for the truth.

``python -m server.tooling.bench.friction_swap [--seeds 1,2,101,102] [--swaps none,kappa,…]``

Each seed's ``damaged_tyre`` run (rear-left ``kz`` 50,000 N/m, the config's 250,000) is fed to
one :class:`~estimator.friction.FrictionFleet` as the bench feeds it (100 ms of packets per
advance); the front end's output of every tick is then edited before the filter sees it:

* ``kappa``, ``kappa_soft``, ``kappa_partner``: the truth's relaxed κ (all four wheels; the
  soft tyre; the sound tyre beside it);
* ``radius``, ``radius_soft``: κ with each wheel's effective radius the truth's
  (``r_u − ρ Fz/kz`` at its own ``ρ``, ``kz`` and load) instead of the front end's, i.e.
  κ − ω·(r̂ − r)/v; ``radius_cal``: only the calibrated radius (the truth's at the
  calibration's mean load), the front end's fall with load kept; ``radius_drop``: only the
  fall with load (the truth's ``ρ/kz``), the calibrated radius kept;
* ``speed``: κ with the truth's forward speed, κ + (v̂ − v)/v;
* ``fz``, ``alpha``: the truth's loads, slip angles;
* ``kz_soft``: the filter told the soft tyre's true ``kz`` (the front end's learnt one
  replaced); ``z``: the truth's accelerations ``[a_x + resistances/m, a_y, ṙ]``;
  ``all``: κ, α, Fz and ``kz`` together; ``all_z``: and ``z``; a swap suffixed ``+nobal``
  runs without the driven axle's torque balance; ``+rho``, ``+rhohat``: the balance's radii
  at the truth's ``ρ`` or the front end's learnt one instead of the fixed 1/3; ``+rhob``: the
  truth's ``ρ`` and its differential's torque split ``1 ± b`` (the balance made exact);
  ``+cspread``: the balance's 1-σ widened by the two tyres' own stiffness spread.

``--rounding`` prints instead, per seed, each wheel's CAN reading's mean error over the
straight's GNSS epochs (the 4 s before the manoeuvre) beside the truth's wheel speed rounded
to the sensor's quantum, and the driven wheels' ring on their tyres (:func:`rounding_rows`).

The radius and speed corrections are added after the front end's relaxation lag (they move
slowly against it). Printed per seed: the filter's μ error over the last 2 s, signed [%].
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from estimator.friction import FilterConfig, FrictionFleet, FrictionFleetConfig, FrictionMode
from estimator.friction import fleet as fleet_mod
from estimator.friction.axle import AxleArrays, AxleConfig
from estimator.friction.fleetfront import FleetFrontEnd, FrontEndTicks
from estimator.friction.sensors import SensedTicks
from estimator.sim.four_wheel import NAMED, FourWheelRun, WheelSpeedSensor, simulate_four_wheel
from estimator.sim.four_wheel.dynamics import DT_S, TruthParams
from estimator.types import WheelSpeeds4
from server.tooling.bench import int_list
from server.tooling.bench.friction import TICK_S, feed_runs

__all__ = ["SWAPS", "main", "replay", "rounding_rows"]

SOFT, PARTNER = 2, 3
SWAPS = (
    "none",
    "kappa",
    "kappa_soft",
    "kappa_partner",
    "radius",
    "radius_soft",
    "radius_cal",
    "radius_drop",
    "speed",
    "fz",
    "alpha",
    "kz_soft",
    "z",
    "all",
    "all_z",
)


_BALANCE = fleet_mod.balance_std_n
_RADII = fleet_mod.effective_radii_m


def _no_balance(fz_n: np.ndarray, *_: object) -> np.ndarray:
    """No torque balance applied (every axle's row weightless)."""
    return np.full((fz_n.shape[0], 2), AxleConfig().weightless_std_n)


def _truth_params(run: FourWheelRun, seed: int) -> TruthParams:
    """The run's drawn truth (the simulator draws it first from the seed's generator)."""
    kz = np.array([[run.config.tyre.kz_npm] * 4])
    kz[0, run.manoeuvre.damaged_wheel] = run.manoeuvre.damaged_kz_npm
    return TruthParams.draw([run.config], [np.random.default_rng(seed)], kz)


_TRUE_FIELDS = ("kappa", "alpha_rad", "fz_n", "vx_mps", "ax_mps2", "ay_mps2", "yaw_accel_radps2")


def _truth_index(run: FourWheelRun, t_ns: np.ndarray) -> np.ndarray:
    """The truth's sample nearest each stamp ``t_ns`` (k,) [ns], clipped to the run, (k,)."""
    step_s = float(run.truth.t_s[1] - run.truth.t_s[0])
    t_s = (np.asarray(t_ns) - run.start_ns) / 1e9 - run.truth.t_s[0]
    return np.clip(np.round(t_s / step_s).astype(int), 0, run.truth.t_s.size - 1)


def _truth_at(
    runs: list[FourWheelRun], s: np.ndarray, t_ns: np.ndarray
) -> tuple[list[int], dict[str, np.ndarray]]:
    """The truth's sample index of each row's tick and its fields there, (k, …) each."""
    tr = [runs[int(i)].truth for i in s]
    kk = [int(_truth_index(runs[int(i)], np.asarray([j]))[0]) for i, j in zip(s, t_ns, strict=True)]
    true = {
        f: np.stack([getattr(t, f)[j] for t, j in zip(tr, kk, strict=True)]) for f in _TRUE_FIELDS
    }
    return kk, true


def _swapped_kappa(
    swap: str,
    fe: FrontEndTicks,
    front: FleetFrontEnd,
    s: np.ndarray,
    omega: np.ndarray,
    truth: tuple[dict[str, np.ndarray], np.ndarray, np.ndarray, np.ndarray],
) -> np.ndarray:
    """The κ the filter is fed under ``swap``, (k, 4); ``truth`` is (fields, ρ (k, 1), ``kz``
    (k, 4), ``r_u`` (k, 4))."""
    true, rho, kz, r_u = truth
    st = front.state
    kappa = fe.kappa.copy()
    denom = np.maximum(np.abs(fe.vx_mps), 1.0)[:, None]
    r_hat = front._radius_now(s, fe.fz_n)
    r_true = r_u - rho * true["fz_n"] / kz
    if swap in ("kappa", "all", "all_z"):
        kappa = true["kappa"]
    elif swap == "kappa_soft":
        kappa[:, SOFT] = true["kappa"][:, SOFT]
    elif swap == "kappa_partner":
        kappa[:, PARTNER] = true["kappa"][:, PARTNER]
    elif swap == "radius":
        kappa -= omega * (r_hat - r_true) / denom
    elif swap == "radius_soft":
        kappa[:, SOFT] -= omega[:, SOFT] * (r_hat - r_true)[:, SOFT] / denom[:, 0]
    elif swap == "radius_cal":
        kappa -= omega * (st.radius[s] - (r_u - rho * st.fz_cal[s] / kz)) / denom
    elif swap == "radius_drop":
        fz_cal = st.fz_cal[s]
        drop_hat = st.radius_drop[s][:, None] * (fe.fz_n - fz_cal) / st.kz_wheel[s]
        kappa -= omega * ((rho * (fe.fz_n - fz_cal) / kz) - drop_hat) / denom
    elif swap == "speed":
        kappa = kappa + (fe.vx_mps - true["vx_mps"])[:, None] / denom
    return kappa


def _swapped(
    swap: str,
    fe: FrontEndTicks,
    front: FleetFrontEnd,
    s: np.ndarray,
    kappa: np.ndarray,
    true: dict[str, np.ndarray],
    kz: np.ndarray,
) -> FrontEndTicks:
    """``fe`` with κ and, under ``swap``, the truth's Fz, α, the soft tyre's ``kz`` and ``z``."""
    fz, alpha, kz_fe, z = fe.fz_n, fe.alpha_rad, fe.kz_npm, fe.z
    if swap in ("z", "all_z"):  # the truth's [a_x + resistances/m, a_y, ṙ]
        resist = front._resistance(s, true["vx_mps"], true["fz_n"])
        z = np.stack([true["ax_mps2"] + resist, true["ay_mps2"], true["yaw_accel_radps2"]], 1)
    if swap in ("fz", "all", "all_z"):
        fz = true["fz_n"]
    if swap in ("alpha", "all", "all_z"):
        alpha = true["alpha_rad"]
    if swap in ("kz_soft", "all", "all_z"):
        kz_fe = kz_fe.copy()
        kz_fe[:, SOFT] = kz[:, SOFT]
    return replace(fe, kappa=kappa, fz_n=fz, alpha_rad=alpha, kz_npm=kz_fe, z=z)


def _fleet(extra: str) -> FrictionFleet:
    """The product fleet; ``+cspread`` widens the balance's 1-σ by the two tyres' own c_p,
    each ±3 % uniform."""
    axle = AxleConfig()
    if extra == "cspread":
        axle = AxleConfig(rel_std=math.hypot(axle.rel_std, math.sqrt(2.0) * 0.03 / math.sqrt(3.0)))
    return FrictionFleet(
        FrictionFleetConfig(
            filter=FilterConfig(mode=FrictionMode.PRODUCT, tick_s=TICK_S), axle=axle
        )
    )


def replay(
    runs: list[FourWheelRun], seeds: list[int], swap: str, probe: Callable[..., None] | None = None
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each run's (times [s], filter μ) with ``swap`` applied to every front-end tick;
    ``probe(s, t_idx, fe, r_hat, rho, kz, fz_cal, radius_cal)`` sees each tick before the edit."""
    params = [_truth_params(r, sd) for r, sd in zip(runs, seeds, strict=True)]
    swap, _, extra = swap.partition("+")
    fleet = _fleet(extra)
    front: FleetFrontEnd = fleet._front
    held: dict[str, np.ndarray] = {}
    inner = front.step

    def step(s: np.ndarray, sensed: SensedTicks) -> FrontEndTicks:
        fe = inner(s, sensed)
        st = front.state
        kk, true = _truth_at(runs, s, sensed.t_ns)
        p = [params[int(i)] for i in s]
        rho = np.array([q.radius_drop[0] for q in p])[:, None]
        kz = np.stack([q.kz_npm[0] for q in p])
        r_u = np.stack([q.radius_m[0] for q in p])
        held["rho"] = rho if extra in ("rho", "rhob") else st.radius_drop[s][:, None]
        b = np.array([q.diff_bias[0] for q in p])[:, None] if extra == "rhob" else 0.0
        held["torque"] = 1.0 + b * np.array([[1.0, -1.0, 1.0, -1.0]])
        if probe is not None:
            r_hat = front._radius_now(s, fe.fz_n)
            probe(s, kk, fe, r_hat, rho, kz, st.fz_cal[s].copy(), st.radius[s].copy())
        kappa = _swapped_kappa(swap, fe, front, s, sensed.omega_radps, (true, rho, kz, r_u))
        return _swapped(swap, fe, front, s, kappa, true, kz)

    front.step = step  # type: ignore[method-assign]

    def oracle_radii(
        fz_n: np.ndarray, kz_npm: np.ndarray, axles: AxleArrays, _: object
    ) -> np.ndarray:
        out: np.ndarray = axles.unloaded_radius_m - held["rho"] * fz_n / kz_npm
        return out / held["torque"]

    radii: Any = oracle_radii if extra in ("rho", "rhohat", "rhob") else _RADII
    balance: Any = _no_balance if extra == "nobal" else _BALANCE
    fleet_mod.balance_std_n = balance
    fleet_mod.effective_radii_m = radii
    try:
        rows = feed_runs(fleet, runs)
    finally:
        fleet_mod.balance_std_n, fleet_mod.effective_radii_m = _BALANCE, _RADII
    res = []
    for r, parts in zip(runs, rows, strict=True):
        a = np.concatenate(parts)
        res.append(((a["stamp_ns"] - r.start_ns) / 1e9, a["mu_filter"]))
    return res


def steady_signed_pct(run: FourWheelRun, t: np.ndarray, mu: np.ndarray) -> float:
    """Mean signed error of the filter's μ over the last 2 s [%]."""
    truth = np.interp(t, run.truth.t_s, run.truth.mu)
    last = t >= t[-1] - 2.0
    return 100.0 * float(((mu[last] - truth[last]) / truth[last]).mean())


def _probe_table(runs: list[FourWheelRun], seeds: list[int]) -> None:
    """Per seed: the soft tyre's learnt ``kz`` over the truth's and the rear wheels'
    calibrated-radius error against the truth's radius at the calibration's load [1e-4 of the
    radius], both at the manoeuvre's start; the means over the acceleration (t0 + 0.5 s to
    t0 + 6 s) of the soft tyre's radius error, the speed's error [1e-4 of v] and the rear
    wheels' κ error [1e-4], beside their true κ."""
    rec: dict[int, list[tuple[float, ...]]] = {i: [] for i in range(len(runs))}

    def probe(s, kk, fe, r_hat, rho, kz, fz_cal, radius_cal):
        for row, (i, k) in enumerate(zip(s.tolist(), kk, strict=True)):
            tr = runs[i].truth
            r_u = runs[i].config.tyre.unloaded_radius_m
            cal_err = (radius_cal[row] - (r_u - rho[row] * fz_cal[row] / kz[row])) / r_u
            rec[i].append(
                (
                    tr.t_s[k],
                    fe.kz_npm[row, SOFT] / kz[row, SOFT],
                    cal_err[SOFT],
                    cal_err[PARTNER],
                    (fe.vx_mps[row] - tr.vx_mps[k]) / max(tr.vx_mps[k], 1.0),
                    fe.kappa[row, SOFT] - tr.kappa[k, SOFT],
                    fe.kappa[row, PARTNER] - tr.kappa[k, PARTNER],
                    tr.kappa[k, SOFT],
                    tr.kappa[k, PARTNER],
                    (r_hat[row, SOFT] - (r_u - rho[row, 0] * tr.fz_n[k, SOFT] / kz[row, SOFT]))
                    / r_u,
                )
            )

    replay(runs, seeds, "none", probe)
    print(
        "| seed | kz soft learnt/true | cal. radius err soft, partner [1e-4] | "
        "r̂ err soft accel [1e-4] | v err accel [1e-4] | κ err soft, partner accel [1e-4] "
        "| true κ soft, partner [1e-4] |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for i, sd in enumerate(seeds):
        a = np.array(rec[i])
        t0 = runs[i].manoeuvre.t0_s
        acc = (a[:, 0] >= t0 + 0.5) & (a[:, 0] < t0 + 6.0)
        end = a[a[:, 0] < t0][-1]
        m = a[acc].mean(axis=0)
        print(
            f"| {sd} | {end[1]:.3f} | {1e4 * end[2]:+.1f}, {1e4 * end[3]:+.1f} | "
            f"{1e4 * m[9]:+.1f} | {1e4 * m[4]:+.1f} | {1e4 * m[5]:+.1f}, {1e4 * m[6]:+.1f} | "
            f"{1e4 * m[7]:.1f}, {1e4 * m[8]:.1f} |"
        )


def _ring(t_s: np.ndarray, omega: np.ndarray) -> tuple[float, float]:
    """The strongest frequency [Hz] and the 1-σ of a wheel speed ``(K,)`` on the truth's
    grid relative to its 0.1 s running mean (the slow change of speed taken out)."""
    smooth = np.convolve(omega, np.ones(51) / 51, "same")
    rel = (omega / smooth - 1.0)[30:-30]
    freq = np.fft.rfftfreq(rel.size, float(t_s[1] - t_s[0]))
    power = np.abs(np.fft.rfft(rel - rel.mean())) ** 2
    return float(freq[1 + np.argmax(power[1:])]), float(rel.std())


def rounding_rows(run: FourWheelRun, sensor: WheelSpeedSensor) -> dict[str, np.ndarray]:
    """Over the 4 s before the manoeuvre, at the GNSS epochs (every 0.1 s): each wheel's
    reading's mean relative error against the truth's wheel speed (``reading``) and the
    truth's speed rounded to ``sensor.quantum_radps`` (``rounding``), ``(4,)`` each; the
    wheels' ring (:func:`_ring`) on the straight and from 0.5 s to 5 s into the manoeuvre,
    ``ring_straight``, ``ring_drive`` ``(4, 2)`` (frequency [Hz], relative 1-σ); the
    wheels' mean speed there ``omega`` [rad/s]."""
    can = [m for m in run.measurements if isinstance(m, WheelSpeeds4)]
    stamp = np.concatenate([m.stamp_ns for m in can])
    read = np.concatenate([m.omega_radps for m in can])
    t = (stamp - run.start_ns) / 1e9
    tr, t0, q = run.truth, run.manoeuvre.t0_s, sensor.quantum_radps
    true = tr.omega_radps[_truth_index(run, stamp)]
    epoch = (t >= t0 - 4.0) & (t < t0 - 0.05) & (np.abs(t * 10 - np.round(t * 10)) < 1e-6)
    angle = tr.angle_sub_rad.reshape(-1, 4)
    grid = tr.t_s[0] + DT_S * (np.arange(1, angle.shape[0]) - 0.5)
    spin = np.diff(angle, axis=0) / DT_S
    straight, drive = (grid >= t0 - 4.0) & (grid < t0), (grid >= t0 + 0.5) & (grid < t0 + 5.0)
    return {
        "reading": ((read - true) / true)[epoch].mean(axis=0),
        "rounding": ((np.round(true / q) * q - true) / true)[epoch].mean(axis=0),
        "ring_straight": np.array([_ring(grid[straight], spin[straight, w]) for w in range(4)]),
        "ring_drive": np.array([_ring(grid[drive], spin[drive, w]) for w in range(4)]),
        "omega": true[epoch].mean(axis=0),
    }


def _rounding_table(runs: list[FourWheelRun], seeds: list[int]) -> None:
    sensor = WheelSpeedSensor()
    print(
        "| seed | quantum/ω [1e-4] | reading's mean error FL, FR, RL, RR [1e-4] | "
        "truth rounded FL, FR, RL, RR [1e-4] | ring RL, RR straight [Hz; 1-σ 1e-4] | "
        "ring RL, RR driving [Hz; 1-σ 1e-4] |"
    )
    print("| --- | --- | --- | --- | --- | --- |")
    for run, sd in zip(runs, seeds, strict=True):
        r = rounding_rows(run, sensor)
        four = [", ".join(f"{1e4 * x:+.1f}" for x in r[f]) for f in ("reading", "rounding")]
        ring = [
            ", ".join(f"{r[f][w, 0]:.0f}; {1e4 * r[f][w, 1]:.1f}" for w in (SOFT, PARTNER))
            for f in ("ring_straight", "ring_drive")
        ]
        q = 1e4 * sensor.quantum_radps / r["omega"].mean()
        print(f"| {sd} | {q:.1f} | {four[0]} | {four[1]} | {ring[0]} | {ring[1]} |", flush=True)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int_list, default=[1, 2, 101, 102])
    ap.add_argument("--swaps", default=",".join(SWAPS))
    ap.add_argument("--probe", action="store_true", help="per-seed front-end errors instead")
    ap.add_argument("--rounding", action="store_true", help="per-seed wheel readings' errors")
    args = ap.parse_args(argv)
    seeds = list(args.seeds)
    runs = simulate_four_wheel([NAMED["damaged_tyre"]] * len(seeds), seeds)
    if args.probe:
        _probe_table(runs, seeds)
        return
    if args.rounding:
        _rounding_table(runs, seeds)
        return
    print("| swapped for the truth | " + " | ".join(str(s) for s in seeds) + " |")
    print("| --- |" + " --- |" * len(seeds))
    for swap in args.swaps.split(","):
        out = replay(runs, seeds, swap)
        cells = [f"{steady_signed_pct(r, t, m):+.2f}" for r, (t, m) in zip(runs, out, strict=True)]
        print(f"| {swap} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
