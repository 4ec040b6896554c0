"""Steering μ 0.8 replayed with named filter inputs taken from the bench's true-input path.

``python -m server.tooling.bench.friction_ticks [--seeds 1,2,2001,2002] [--exact]
[--specs "none;base;every;every-vy_meas_std_mps"]``

Each seed's ``steer_mu08`` run is fed to one :class:`~estimator.friction.FrictionFleet` as the
bench feeds it; every round's :class:`~estimator.friction.filter.TickInputs` then has the
named fields replaced by those :func:`~server.tooling.bench.friction._truth_inputs` builds at
the truth's sample nearest the tick. A spec is ``+``-joined fields (``base``: κ, α, Fz, ``z``,
δ, the lateral speed and κ's and α's 1-σ; ``every``: all) or ``every-F-G`` (all but F, G);
``truepath`` is the bench's own true-input path. ``--exact``: wheel speeds unrounded. Printed
per seed: the filter's μ error over the last 2 s, signed [%].
"""

from __future__ import annotations

import argparse
from dataclasses import fields as dc_fields
from dataclasses import replace
from typing import Any

import numpy as np

from estimator.friction import FilterConfig, FrictionFleet, FrictionFleetConfig, FrictionMode
from estimator.friction import fleet as fleet_mod
from estimator.friction.filter import TickInputs
from estimator.sim.four_wheel import NAMED, FourWheelRun, WheelSpeedSensor, simulate_four_wheel
from server.tooling.bench import int_list
from server.tooling.bench.friction import TICK_S, _truth_inputs, feed_runs, true_series
from server.tooling.bench.friction_swap import _truth_index, steady_signed_pct

FIELDS = tuple(f.name for f in dc_fields(TickInputs))
BASE = (
    "kappa",
    "alpha_rad",
    "fz_n",
    "z",
    "delta_rad",
    "vy_meas_mps",
    "kappa_std",
    "alpha_std_rad",
)


def run_fields(runs: list[FourWheelRun], names: list[str], **filter_kw: Any) -> list[float]:
    """Each run's steady signed μ error [%] with ``names`` from the truth; ``filter_kw``
    changes the fleet's :class:`FilterConfig`."""
    cfg = FilterConfig(mode=FrictionMode.PRODUCT, tick_s=TICK_S, **filter_kw)
    fleet = FrictionFleet(FrictionFleetConfig(filter=cfg))
    inner_round, inner_inputs = fleet._round, fleet_mod._tick_inputs
    cur: dict[str, np.ndarray] = {}

    def round_(s: Any, t_ns: Any, fe: Any, out: Any, at: Any) -> None:
        cur["s"], cur["t"] = s, t_ns
        inner_round(s, t_ns, fe, out, at)

    def inputs(fe: Any, axles: Any, axle_cfg: Any) -> TickInputs:
        u = inner_inputs(fe, axles, axle_cfg)
        if not names:
            return u
        rows = [
            _truth_inputs([runs[int(i)]], int(_truth_index(runs[int(i)], np.asarray([t]))[0]))
            for i, t in zip(cur["s"], cur["t"], strict=True)
        ]
        return replace(u, **{f: np.concatenate([getattr(r, f) for r in rows]) for f in names})

    fleet._round = round_  # type: ignore[method-assign]
    fleet_mod._tick_inputs = inputs  # type: ignore[assignment]
    try:
        parts = feed_runs(fleet, runs)
    finally:
        fleet_mod._tick_inputs = inner_inputs
    errs = []
    for r, p in zip(runs, parts, strict=True):
        a = np.concatenate(p)
        errs.append(steady_signed_pct(r, (a["stamp_ns"] - r.start_ns) / 1e9, a["mu_filter"]))
    return errs


def spec_fields(spec: str) -> list[str]:
    """The fields a spec names (module docstring)."""
    if spec.startswith("every-"):
        return [f for f in FIELDS if f not in spec[len("every-") :].split("-")]
    out: set[str] = set()
    for n in spec.split("+"):
        if n == "base":
            out.update(BASE)
        elif n == "every":
            out.update(FIELDS)
        elif n and n != "none":
            out.add(n)
    return sorted(out)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--seeds", type=int_list, default=[1, 2, 2001, 2002])
    ap.add_argument("--exact", action="store_true")
    ap.add_argument("--specs", default="truepath;none;base;every")
    args = ap.parse_args(argv)
    seeds = list(args.seeds)
    sensors = [WheelSpeedSensor(tooth_mean=False, quantum_radps=1e-9)] * len(seeds)
    runs = simulate_four_wheel(
        [NAMED["steer_mu08"]] * len(seeds), seeds, wheel_sensors=sensors if args.exact else None
    )
    print("| filter's inputs from the truth | " + " | ".join(map(str, seeds)) + " |")
    print("| --- |" + " --- |" * len(seeds))
    for spec in args.specs.split(";"):
        if spec == "truepath":
            ser = true_series(runs, FrictionMode.PRODUCT)
            errs = [
                steady_signed_pct(r, s.t_s, s.mu_filter) for r, s in zip(runs, ser, strict=True)
            ]
        else:
            errs = run_fields(runs, spec_fields(spec))
        print(f"| {spec} | " + " | ".join(f"{e:+.2f}" for e in errs) + " |", flush=True)


if __name__ == "__main__":
    main()
