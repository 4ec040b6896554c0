"""Tracked-vehicle bench: the ``tracked`` estimator's modes against the crawler simulator.

``slipfleet bench tracked [--seeds 1,2] [--random N] [--random-from S]
[--scenarios route_firm,route_soft,route_firm_hill] [--modes product,paper,…] [--flat]
[--json PATH]``
simulates every scenario once per seed (:mod:`estimator.sim.tracked`), and ``--random N``
adds N random routes (seeds S, S + 1, …; S = 1000 by default), then feeds every run to each mode
side by side (``--modes`` picks some, ``product`` always among them): ``product``,
``paper`` (the source as printed, lateral term ``−φ̇·L`` included), ``paper_no_lateral``
and ``raw_odometer`` (the odometer speed as the hull's). Each mode is one
:class:`~estimator.tracked.TrackedFleet` holding every run as a vehicle, fed in sensor order
and advanced every second of sensor time; each row is compared with the truth at its stamp.
The product gives its rows at a fixed lag (one tick, up to ``report_lag_ticks`` = 4 ticks,
0.4 s, while a state change is under way; :mod:`estimator.tracked.lag`): a row keeps its own
stamp and is scored against the truth there; the last held rows of a run are not scored.

Terrain
-------
``route_firm`` and ``route_soft`` are level; ``route_firm_hill`` is ``route_firm`` over hills
(grades ±10 % with 60 m ramps every 150 m, cross grades ±5 % every 220 m). Random routes
drive over a terrain drawn by a generator of their own (the route's every other draw is the
same with ``--flat``, which levels every run): a largest grade uniform in 5-15 % and knots
every 20-80 m (uniform) each uniform within ± that grade; a largest cross grade uniform in
0-10 % and knots every 30-120 m; cosine interpolation between knots along the hull's
along-ground distance (``estimator.sim.tracked.terrain.TERRAIN_RANGES``). The DR metrics
are horizontal (distance driven: the hull centre's horizontal path).

Metrics per run and mode
------------------------
``state_pct`` / ``settled_pct``
    Share of rows whose motion state is the true one: all rows, and rows more than 1.5 s after
    a true state change (the confusion matrix sums the product's and the paper's).
``slip_rms_pp`` / ``slip_p95_pp`` (per track)
    Slip error in percentage points where the track is driven and moves (true sprocket speed
    ≥ 0.5 m/s) and the row gives a slip (a braked track's −100 % included). A row without
    one (its ``SLIP_*_VALID`` flag unset: not observable, e.g. a lever moving, a sprocket
    settling, a 1-sigma above ``slip_std_max_pct``, a state change backdated over it,
    ``STATE_BACKDATED``) is not scored: ``slip_coverage_pct`` is the share of moving rows that
    give one (printed as ``cov%``, the smaller track's). A braked track (sprocket still) is
    never scored: its true sprocket speed is below the moving threshold.
``dr_end_m`` / ``dr_end_pct`` / ``dr_max_m``
    Position error of the hull centre at the end of each GNSS outage (m, and % of the distance
    driven in it; the worst outage of the run), and the largest error within it. The end is
    the last row stamped before the first fix after the outage: a receiver whose clock runs
    behind the IMU's stamps that fix before the outage's end on the IMU's clock, and a row
    from its tick on has fused it.
``pitch_rms_mrad`` / ``roll_rms_mrad`` (and ``…_max_mrad``, ``…_z_rms``)
    The rows' hull attitude against the terrain's (mrad) over the rows that give it
    (``attitude_pct`` of the rows), and the RMS of each error over the row's own 1-sigma (1
    where that 1-sigma is honest); printed for the product in a table of their own, with
    the share of rows whose error is within 2σ (``…_in2s_gnss_pct`` beside GNSS,
    ``…_in2s_outage_pct`` in outages: 95.4 % if honest) and the NEES (``…_nees_gnss``,
    ``…_nees_outage``: mean of (error/σ)², 1 if honest), pooled over every run's rows.
``dr_nees``
    Median over the second half of that outage of the position's NEES per degree of freedom
    (``dᵀ C⁻¹ d / 2`` with the row's east-north covariance ``C``; printed as ``NEES``): about
    1 where the stated covariance is honest (the median of a χ²₂/2 is 0.69), below where it is
    over-cautious. One run's rows are one draw (the error drifts slowly), so judge it over
    many runs.

Each run's JSON entry also names its gyro's grade (``gyro_grade``: its noise over the
ADIS16470 data sheet's, :class:`~estimator.sim.tracked.CrawlerSensors`) and the grade its
config names (``config_gyro_grade``: 1 where the config names the data sheet), and the
streams' clocks (``gnss_clock_offset_s``, ``odometer_clock_offset_s``,
``sprocket_clock_offset_s``: each stream's clock less the IMU's; ``gnss_epoch_jitter_s``: the
receiver's epoch jitter 1σ; all 0 on named routes), and per mode the receiver's clock its
filter held at the last second before the first outage (``gnss_clock_ms``, its 1σ, its error
against the run's and that over 1σ; a table for the product); the summary gives the DR end %
over the runs (median, p95, worst).

Floors (product mode, every run): settled ≥ 99.5 %, all ≥ 98.5 %, slip RMS ≤ 1.5 pp per
track, DR at the end of a > 1 km outage ≤ 0.3 % (firm) / ≤ 0.5 % (soft, random) of distance.
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

import numpy as np

from estimator.sim.tracked import TrackedRun, simulate_tracked
from estimator.sim.tracked.route import CLOCK_KEYS
from estimator.tracked import MotionState, TrackedEstimatorConfig, TrackedFleet, TrackedMode
from estimator.tracked.model import TrackedState as S
from estimator.types import GnssFix, GnssSample
from server.tooling.bench import int_list, write_json

__all__ = ["main", "run"]

MODES = tuple(TrackedMode)
SETTLE_S = 1.5
MOVING_MPS = 0.5
FLOORS = {"settled_pct": 99.5, "state_pct": 98.5, "slip_rms_pp": 1.5}
_STAMP_SLACK_NS = 1_000_000_000


def _feed(
    mode: TrackedMode, runs: list[TrackedRun]
) -> tuple[list[np.ndarray], list[tuple[float, float]]]:
    """Every run through one fleet of ``mode``; rows per run, and per run the receiver's
    clock the filter holds (:func:`_clock_before_outage`)."""
    fleet = TrackedFleet(TrackedEstimatorConfig(mode=mode))
    ids = [f"run{k}" for k in range(len(runs))]
    for vid, r in zip(ids, runs, strict=True):
        fleet.add_vehicle(vid, r.config)
        fleet.set_anchor(vid, r.frame.lat0_deg, r.frame.lon0_deg, r.frame.h0_m)
    pos = [0] * len(runs)
    out: list[list[np.ndarray]] = [[] for _ in runs]
    clocks = [(float("nan"), float("nan"))] * len(runs)
    t = min(r.start_ns for r in runs)
    end = max(r.measurements[-1][0] for r in runs)
    while t <= end + 1_000_000_000:
        t += 1_000_000_000
        for k, r in enumerate(runs):
            ms, i = r.measurements, pos[k]
            while i < len(ms) and ms[i][0] <= t:
                fleet.push(ids[k], ms[i][1])
                i += 1
            pos[k] = i
        for vid, rows in fleet.advance(dict.fromkeys(ids, t)):
            out[ids.index(vid)].append(rows)
        for k, r in enumerate(runs):
            clocks[k] = _clock_before_outage(fleet, ids[k], r, t, clocks[k])
    return [np.concatenate(parts) for parts in out], clocks


def _clock_before_outage(
    fleet: TrackedFleet, vid: str, run: TrackedRun, t_ns: int, held: tuple[float, float]
) -> tuple[float, float]:
    """The receiver's clock less the IMU's the filter holds and its 1σ (s) at ``t_ns``,
    while ``t_ns`` is before the run's first outage (what its dead reckoning starts from);
    ``held`` after it."""
    outages = run.outages_ns
    if outages and t_ns > outages[0][0]:
        return held
    x, P = fleet.filter_state(vid)
    return float(x[S.GNSS_CLOCK]), float(np.sqrt(P[S.GNSS_CLOCK, S.GNSS_CLOCK]))


def _settled(run: TrackedRun, idx: np.ndarray) -> np.ndarray:
    """Rows more than ``SETTLE_S`` after the last true state change."""
    state = run.truth.state
    change = np.concatenate([[0], np.nonzero(np.diff(state))[0] + 1])
    last = change[np.searchsorted(change, idx, side="right") - 1]
    return (idx - last) > SETTLE_S * 100


def _state_metrics(run: TrackedRun, rows: np.ndarray, idx: np.ndarray) -> dict[str, Any]:
    truth = run.truth.state[idx]
    got = rows["motion_state"]
    settled = _settled(run, idx)
    cm = np.zeros((len(MotionState), len(MotionState)), dtype=np.int64)
    np.add.at(cm, (truth, got), 1)
    return {
        "state_pct": 100.0 * float(np.mean(got == truth)),
        "settled_pct": 100.0 * float(np.mean(got[settled] == truth[settled])),
        "confusion": cm.tolist(),
    }


def _slip_metrics(run: TrackedRun, rows: np.ndarray, idx: np.ndarray) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for side, name in ((0, "left"), (1, "right")):
        est = rows[f"slip_{name}_pct"]
        true = 100.0 * run.truth.slip[idx, side]
        moving = run.truth.sprocket_mps[idx, side] >= MOVING_MPS
        err = np.abs(est - true)[moving & np.isfinite(est) & np.isfinite(true)]
        out[f"slip_{name}_rms_pp"] = float(np.sqrt(np.mean(err**2))) if err.size else float("nan")
        out[f"slip_{name}_p95_pp"] = float(np.percentile(err, 95)) if err.size else float("nan")
        out[f"slip_{name}_coverage_pct"] = 100.0 * err.size / max(int(moving.sum()), 1)
    return out


def _nees(rows: np.ndarray, d_east: np.ndarray, d_north: np.ndarray) -> np.ndarray:
    """Position NEES per row over its two degrees of freedom (1 on average if honest):
    ``dᵀ C⁻¹ d / 2``, ``C`` the row's east-north covariance."""
    ee, nn = rows["east_std_m"] ** 2, rows["north_std_m"] ** 2
    en = rows["east_north_cov_m2"]
    det = ee * nn - en * en
    return 0.5 * (nn * d_east**2 - 2.0 * en * d_east * d_north + ee * d_north**2) / det


def _fix_stamps(run: TrackedRun) -> tuple[np.ndarray, np.ndarray]:
    """Stamps (ns, sorted) of the run's fixes with a solution, and of those without."""
    fixes = [m for _, m in run.measurements if isinstance(m, GnssSample)]
    got = [m.stamp_ns for m in fixes if m.fix != GnssFix.NONE]
    lost = [m.stamp_ns for m in fixes if m.fix == GnssFix.NONE]
    return np.sort(np.asarray(got, dtype=np.int64)), np.sort(np.asarray(lost, dtype=np.int64))


def _dr_end_ns(got: np.ndarray, lost: np.ndarray, a_ns: int, b_ns: int) -> int:
    """The last stamp that counts as inside the outage ``(a_ns, b_ns]``: before the first fix
    with a solution stamped after the outage's last fix without one (searched within a
    second of the outage: the receiver's stamps sit up to a tenth off the IMU's clock)."""
    near = lost[(lost > a_ns - _STAMP_SLACK_NS) & (lost <= b_ns + _STAMP_SLACK_NS)]
    if not near.size:
        return b_ns
    back = got[got > near[-1]]
    return min(b_ns, int(back[0]) - 1) if back.size else b_ns


def _dr_metrics(run: TrackedRun, rows: np.ndarray, idx: np.ndarray) -> dict[str, Any]:
    tr = run.truth
    d_east, d_north = rows["east_m"] - tr.east_m[idx], rows["north_m"] - tr.north_m[idx]
    err = np.hypot(d_east, d_north)
    nees = _nees(rows, d_east, d_north)
    dist = run.distance_m()
    worst: dict[str, Any] = {
        "dr_end_m": 0.0,
        "dr_end_pct": 0.0,
        "dr_max_m": 0.0,
        "outage_km": 0.0,
        "dr_nees": float("nan"),
    }
    got, lost = _fix_stamps(run)
    for a_ns, b_ns in run.outages_ns:
        until = _dr_end_ns(got, lost, a_ns, b_ns)
        inside = (rows["stamp_ns"] > a_ns) & (rows["stamp_ns"] <= until)
        if not inside.any():
            continue
        end = int(np.nonzero(inside)[0][-1])
        late_ns = (a_ns + b_ns) // 2
        driven = dist[idx[end]] - dist[run.index_at(np.array([a_ns]))[0]]
        pct = 100.0 * err[end] / max(driven, 1.0)
        if pct >= worst["dr_end_pct"]:
            worst = {
                "dr_end_m": float(err[end]),
                "dr_end_pct": float(pct),
                "dr_max_m": float(np.nanmax(err[inside])),
                "outage_km": driven / 1e3,
                "dr_nees": float(np.nanmedian(nees[inside & (rows["stamp_ns"] > late_ns)])),
            }
    return worst


def _outage_rows(run: TrackedRun, rows: np.ndarray) -> np.ndarray:
    """Rows inside a GNSS outage ``(n,)`` bool."""
    inside = np.zeros(rows.size, dtype=bool)
    for a_ns, b_ns in run.outages_ns:
        inside |= (rows["stamp_ns"] > a_ns) & (rows["stamp_ns"] <= b_ns)
    return inside


def _attitude_metrics(run: TrackedRun, rows: np.ndarray, idx: np.ndarray) -> dict[str, Any]:
    """Pitch and roll errors (mrad) where the rows give them, and their RMS over the rows' σ;
    the NEES (mean of (error/σ)²) and the share within 2σ beside GNSS and in its outages."""
    given = np.isfinite(rows["pitch_rad"]) & np.isfinite(rows["roll_rad"])
    out: dict[str, Any] = {"attitude_pct": 100.0 * float(given.mean()) if given.size else 0.0}
    lost = _outage_rows(run, rows)[given]
    out["attitude_rows_gnss"], out["attitude_rows_outage"] = int((~lost).sum()), int(lost.sum())
    for name in ("pitch", "roll"):
        err = (rows[f"{name}_rad"] - getattr(run.truth, f"{name}_rad")[idx])[given]
        z = err / rows[f"{name}_std_rad"][given]
        some = err.size > 0
        out[f"{name}_rms_mrad"] = 1e3 * float(np.sqrt(np.mean(err**2))) if some else float("nan")
        out[f"{name}_max_mrad"] = 1e3 * float(np.max(np.abs(err))) if some else float("nan")
        out[f"{name}_z_rms"] = float(np.sqrt(np.mean(z**2))) if some else float("nan")
        for part, sel in (("gnss", ~lost), ("outage", lost)):
            zs = z[sel]
            out[f"{name}_nees_{part}"] = float(np.mean(zs**2)) if zs.size else float("nan")
            out[f"{name}_in2s_{part}_pct"] = (
                100.0 * float(np.mean(np.abs(zs) < 2.0)) if zs.size else float("nan")
            )
    return out


def _metrics(run: TrackedRun, rows: np.ndarray) -> dict[str, Any]:
    idx = run.index_at(rows["stamp_ns"])
    return {
        **_state_metrics(run, rows, idx),
        **_slip_metrics(run, rows, idx),
        **_dr_metrics(run, rows, idx),
        **_attitude_metrics(run, rows, idx),
    }


def _clock_metrics(run: TrackedRun, clock: tuple[float, float]) -> dict[str, Any]:
    """The receiver's clock the filter learnt before the first outage against the run's
    (ms): value, 1σ, error, error over 1σ."""
    learnt_s, std_s = clock
    err_s = learnt_s - run.sensors.gnss_clock_offset_s
    z = err_s / std_s if std_s > 0.0 else float("nan")
    return {
        "gnss_clock_ms": 1e3 * learnt_s,
        "gnss_clock_std_ms": 1e3 * std_s,
        "gnss_clock_err_ms": 1e3 * err_s,
        "gnss_clock_z": z,
    }


def _clock_table(labels: list[str], product: list[dict[str, Any]], runs: list[TrackedRun]) -> None:
    """Per run, the receiver's clock the product learnt before the first outage beside the
    run's; the mean error and the RMS of error over 1σ."""
    print("\nreceiver clock, product   true ms  learnt ms  1σ ms  error ms  error/σ")
    for label, m, r in zip(labels, product, runs, strict=True):
        true_ms = 1e3 * r.sensors.gnss_clock_offset_s
        print(
            f"{label:<22} {true_ms:>9.1f} {m['gnss_clock_ms']:>10.1f} "
            f"{m['gnss_clock_std_ms']:>6.1f} {m['gnss_clock_err_ms']:>9.1f} "
            f"{m['gnss_clock_z']:>8.2f}"
        )
    err = np.array([m["gnss_clock_err_ms"] for m in product])
    z = np.array([m["gnss_clock_z"] for m in product])
    if np.isfinite(z).any():
        print(
            f"product receiver clock error over runs: mean {np.nanmean(err):+.1f} ms, "
            f"RMS {np.sqrt(np.nanmean(err**2)):.1f} ms, error/σ RMS {np.sqrt(np.nanmean(z**2)):.2f}"
        )


def _attitude_table(labels: list[str], product: list[dict[str, Any]]) -> None:
    """The product's attitude per run, and median / p95 / worst over the runs; the NEES and
    the share within 2σ over every run's rows, beside GNSS and in outages."""
    print(
        f"\nattitude, product  {'given%':>6} {'pitch rms/max mrad':>18} {'z rms':>5} "
        f"{'in2σ% gnss/out':>14} {'roll rms/max mrad':>17} {'z rms':>5} {'in2σ% gnss/out':>14}"
    )
    for label, m in zip(labels, product, strict=True):
        cells = [f"{label:<18} {m['attitude_pct']:6.1f}"]
        for name, width in (("pitch", 8), ("roll", 7)):
            cells.append(
                f"{m[f'{name}_rms_mrad']:{width}.2f}/{m[f'{name}_max_mrad']:<9.2f} "
                f"{m[f'{name}_z_rms']:5.2f} {m[f'{name}_in2s_gnss_pct']:6.1f}/"
                f"{m[f'{name}_in2s_outage_pct']:<7.1f}"
            )
        print(" ".join(cells))
    for name in ("pitch", "roll"):
        rms = [m[f"{name}_rms_mrad"] for m in product if np.isfinite(m[f"{name}_rms_mrad"])]
        z = [m[f"{name}_z_rms"] for m in product if np.isfinite(m[f"{name}_z_rms"])]
        if rms:
            print(
                f"product {name} RMS mrad over runs: median {np.median(rms):.2f}, "
                f"p95 {np.percentile(rms, 95):.2f}, worst {np.max(rms):.2f}; "
                f"error/σ RMS median {np.median(z):.2f}, worst {np.max(z):.2f}"
            )
        for part in ("gnss", "outage"):
            n = np.array([m[f"attitude_rows_{part}"] for m in product], dtype=np.float64)
            nees = np.array([m[f"{name}_nees_{part}"] for m in product])
            cov = np.array([m[f"{name}_in2s_{part}_pct"] for m in product])
            have = n > 0
            if have.any():
                w = n[have] / n[have].sum()
                print(
                    f"product {name} {part:<6} over every row: NEES {np.sum(w * nees[have]):.2f}, "
                    f"within 2σ {np.sum(w * cov[have]):.1f} % (95.4 if honest)"
                )


def _floors(m: dict[str, Any], run: TrackedRun) -> list[str]:
    """The product floors this run misses (names)."""
    bad = [k for k in ("settled_pct", "state_pct") if m[k] < FLOORS[k]]
    bad += [k for k in ("slip_left_rms_pp", "slip_right_rms_pp") if m[k] > FLOORS["slip_rms_pp"]]
    limit = 0.3 if run.route.ground.name == "firm" else 0.5
    if m["outage_km"] > 1.0 and m["dr_end_pct"] > limit:
        bad.append(f"dr_end_pct>{limit}")
    return bad


def _line(label: str, mode: str, m: dict[str, Any]) -> str:
    return (
        f"{label:<22} {mode:<17} {m['state_pct']:7.2f} {m['settled_pct']:7.2f} "
        f"{m['slip_left_rms_pp']:6.2f}/{m['slip_left_p95_pp']:<6.2f} "
        f"{m['slip_right_rms_pp']:6.2f}/{m['slip_right_p95_pp']:<6.2f} "
        f"{m['dr_end_m']:7.2f} {m['dr_end_pct']:6.3f} {m['dr_max_m']:7.2f} {m['outage_km']:5.2f} "
        f"{min(m['slip_left_coverage_pct'], m['slip_right_coverage_pct']):5.1f} {m['dr_nees']:5.2f}"
    )


def _confusion(title: str, cm: np.ndarray) -> None:
    names = [s.name.lower()[:8] for s in MotionState]
    print(f"\n{title} (rows: truth, columns: recognised)")
    print(" " * 10 + "".join(f"{n:>9}" for n in names))
    for name, row in zip(names, cm, strict=True):
        print(f"{name:<10}" + "".join(f"{v:9d}" for v in row))


def _summary(
    results: dict[str, Any], failures: list[tuple[str, list[str]]], product: list[dict[str, Any]]
) -> None:
    """The product floors missed, the random routes meeting all, the DR NEES over runs."""
    random_ok = [not e["product_misses"] for e in results["runs"] if e["ground"] == "random"]
    results["random_pass_pct"] = 100.0 * float(np.mean(random_ok)) if random_ok else None
    print(
        "\nproduct floors: "
        + (
            "all met"
            if not failures
            else "; ".join(f"{lab}: {', '.join(b)}" for lab, b in failures)
        )
    )
    if random_ok:
        print(f"random routes meeting every floor: {results['random_pass_pct']:.0f} %")
    nees = [m["dr_nees"] for m in product if np.isfinite(m["dr_nees"])]
    if nees:
        print(f"product DR NEES over runs: median {np.median(nees):.2f}, mean {np.mean(nees):.2f}")
    dr = [m["dr_end_pct"] for m in product if m["outage_km"] > 0.0]
    if dr:
        print(
            f"product DR end % over runs: median {np.median(dr):.3f}, "
            f"p95 {np.percentile(dr, 95):.3f}, worst {np.max(dr):.3f}"
        )


def _per_mode(
    runs: list[TrackedRun], modes: tuple[TrackedMode, ...], seconds: dict[str, float]
) -> dict[str, list[dict[str, Any]]]:
    """Each mode fed every run; its metrics per run, its seconds into ``seconds``."""
    per_mode: dict[str, list[dict[str, Any]]] = {}
    for mode in modes:
        t1 = time.perf_counter()
        rows_of, clocks = _feed(mode, runs)
        per_mode[mode.value] = [
            {**_metrics(r, rows), **_clock_metrics(r, clock)}
            for r, rows, clock in zip(runs, rows_of, clocks, strict=True)
        ]
        seconds[mode.value] = time.perf_counter() - t1
    return per_mode


def _entry(
    k: int, r: TrackedRun, modes: tuple[TrackedMode, ...], per_mode: dict[str, list[Any]]
) -> dict[str, Any]:
    """Run ``k``'s result: its sensors and terrain, each mode's metrics (printed a line each)
    and the product's missed floors."""
    label = f"{r.name}[{r.seed}]"
    entry: dict[str, Any] = {
        "run": label,
        "ground": r.route.ground.name,
        "gyro_grade": r.sensors.gyro_grade,
        "config_gyro_grade": _config_grade(r),
        "gnss_up_vel_std_ratio": r.sensors.gnss_up_vel_std_ratio,
        **{k: getattr(r.sensors, k) for k in CLOCK_KEYS},
        "grade_max": float(np.max(np.abs(np.tan(r.truth.pitch_rad)))),
        "cross_max": float(np.max(np.abs(np.tan(r.truth.roll_rad)))),
        "modes": {},
    }
    for mode in modes:
        m = per_mode[mode.value][k]
        entry["modes"][mode.value] = m
        print(_line(label, mode.value, m))
    entry["product_misses"] = _floors(per_mode["product"][k], r)
    return entry


def run(
    seeds: list[int],
    random_routes: int,
    scenarios: list[str],
    json_path: str | None = None,
    random_from: int = 1000,
    modes: tuple[TrackedMode, ...] = MODES,
    flat: bool = False,
) -> dict[str, Any]:
    """Simulate the runs, feed them to each mode, print the tables; the results by run."""
    t0 = time.perf_counter()
    runs = [simulate_tracked(s, seed, flat=flat) for s in scenarios for seed in seeds]
    runs += [simulate_tracked("random", random_from + i, flat=flat) for i in range(random_routes)]
    sim_s = time.perf_counter() - t0
    results: dict[str, Any] = {"runs": [], "seconds": {"simulate": sim_s}}
    modes = (TrackedMode.PRODUCT, *(m for m in modes if m != TrackedMode.PRODUCT))
    per_mode = _per_mode(runs, modes, results["seconds"])
    print(
        f"{'run':<22} {'mode':<17} {'state%':>7} {'settl%':>7} {'slipL rms/p95':>13} "
        f"{'slipR rms/p95':>13} {'DR end m':>8} {'DR %':>6} {'DR max':>7} {'km':>5} {'cov%':>5} "
        f"{'NEES':>5}"
    )
    results["runs"] = [_entry(k, r, modes, per_mode) for k, r in enumerate(runs)]
    failures = [(e["run"], e["product_misses"]) for e in results["runs"] if e["product_misses"]]
    for mode in (m for m in (TrackedMode.PRODUCT, TrackedMode.PAPER) if m in modes):
        cm = sum(np.array(m["confusion"]) for m in per_mode[mode.value])
        _confusion(f"confusion, {mode.value}", np.asarray(cm))
    _attitude_table([e["run"] for e in results["runs"]], per_mode["product"])
    _clock_table([e["run"] for e in results["runs"]], per_mode["product"], runs)
    _summary(results, failures, per_mode["product"])
    print("seconds: " + ", ".join(f"{k} {v:.1f}" for k, v in results["seconds"].items()))
    write_json(results, json_path)
    return results


def _config_grade(run: TrackedRun) -> float:
    """The gyro the run's config names, as its angle random walk over the fitted part's
    data sheet (1: the data sheet; the unit's ``gyro_grade`` when the config gives its own)."""
    named = run.config.gyro.resolved().arw_rad_rt_s
    return named / run.sensors.gyro_part.arw_rad_rt_s


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="slipfleet bench tracked",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("--seeds", type=int_list, default=[1, 2], help="seeds of the named runs")
    ap.add_argument("--random", type=int, default=0, help="random routes to add")
    ap.add_argument("--random-from", type=int, default=1000, help="seed of the first one")
    ap.add_argument(
        "--scenarios",
        default="route_firm,route_soft,route_firm_hill",
        help="named scenarios, comma-separated ('' for none)",
    )
    ap.add_argument(
        "--modes",
        default=",".join(m.value for m in MODES),
        help="modes to run, comma-separated (product always runs)",
    )
    ap.add_argument("--flat", action="store_true", help="level ground for every run")
    ap.add_argument("--json", default=None, help="write the numbers to this file")
    args = ap.parse_args(argv)
    scenarios = [s for s in args.scenarios.split(",") if s]
    modes = tuple(TrackedMode(m) for m in args.modes.split(",") if m)
    run(args.seeds, args.random, scenarios, args.json, args.random_from, modes, args.flat)
    return 0


if __name__ == "__main__":
    sys.exit(main())
