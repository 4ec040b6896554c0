"""Accuracy bench: metrics on hand-made cases, the traditional baseline, the report."""

from __future__ import annotations

import io
import json
import math
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pytest

from estimator.base import FleetEstimator, Pushed
from estimator.config import VehicleConfig
from estimator.sim import TRUTH_DTYPE, simulate, truth_at
from estimator.sim.drives import draw_drives
from estimator.types import ESTIMATE_DTYPE, GnssSample, empty_estimates
from server.tooling.bench import accuracy
from server.tooling.bench.accuracy import (
    MOVING_MPS,
    check_floors,
    evaluate,
    print_table,
    run,
    run_random,
    traditional_estimates,
)

START_NS = accuracy.START_NS


def _truth(n: int = 1001, speed: float = 2.0) -> np.ndarray:
    """10 s at 100 Hz: standing 1 s, then constant speed with 10 % / 5 % slip."""
    tr = np.zeros(n, dtype=TRUTH_DTYPE)
    tr["stamp_ns"] = START_NS + np.arange(n, dtype=np.int64) * 10_000_000
    moving = np.arange(n) >= 100
    v = np.where(moving, speed, 0.0)
    tr["v0_mps"] = v
    tr["vl_mps"] = v * 0.9
    tr["vr_mps"] = v * 1.1
    tr["slip_left_pct"] = np.where(moving, 10.0, np.nan)
    tr["slip_right_pct"] = np.where(moving, 5.0, np.nan)
    tr["omega_left_radps"] = tr["vl_mps"] / 0.9 / 0.85
    tr["omega_right_radps"] = tr["vr_mps"] / 0.95 / 0.85
    return tr


def _rows_from_truth(tr: np.ndarray, step: int = 5) -> np.ndarray:
    pick = tr[::step]
    rows = empty_estimates(pick.shape[0])
    for name in ("stamp_ns", "vl_mps", "vr_mps", "slip_left_pct", "slip_right_pct"):
        rows[name] = pick[name]
    rows["omega_left_radps"] = pick["omega_left_radps"]
    rows["omega_right_radps"] = pick["omega_right_radps"]
    return rows


def test_perfect_estimate_has_zero_error_and_full_coverage() -> None:
    tr = _truth()
    m = evaluate(_rows_from_truth(tr), tr)
    for key in ("vw_max_pct", "vw_rms_pct", "slip_rms_pp", "slip_p95_pp", "slip_max_pp"):
        assert m[key] == pytest.approx(0.0, abs=1e-12), key
    assert m["omega_max_pct"] == pytest.approx(0.0, abs=1e-12)
    assert m["coverage_pct"] == pytest.approx(100.0)


def test_known_offsets_give_known_errors() -> None:
    tr = _truth(speed=2.0)
    rows = _rows_from_truth(tr)
    rows["vl_mps"] += 0.036  # left mean speed 1.8 m/s -> 2 %
    rows["slip_right_pct"] += 0.5
    rows["omega_left_radps"] *= 1.01
    m = evaluate(rows, tr)
    assert m["vw_max_pct"] == pytest.approx(2.0)
    # RMS pooled over both wheels: sqrt((2² + 0²) / 2)
    assert m["vw_rms_pct"] == pytest.approx(math.sqrt(2.0))
    assert m["slip_max_pp"] == pytest.approx(0.5)
    assert m["slip_p95_pp"] == pytest.approx(0.5)
    assert m["slip_rms_pp"] == pytest.approx(math.sqrt(0.125))
    assert m["omega_max_pct"] == pytest.approx(1.0)


def test_standstill_rows_do_not_count_and_missing_slip_lowers_coverage() -> None:
    tr = _truth()
    rows = _rows_from_truth(tr)
    rows["vl_mps"][:20] += 5.0  # standing: ignored
    moving_rows = np.flatnonzero(rows["stamp_ns"] >= START_NS + 1_000_000_000)
    drop = moving_rows[: moving_rows.size // 4]
    rows["slip_left_pct"][drop] = np.nan
    m = evaluate(rows, tr)
    assert m["vw_max_pct"] == pytest.approx(0.0, abs=1e-12)
    assert m["coverage_pct"] == pytest.approx(100 - 12.5, abs=0.3)
    # no rows at all
    assert evaluate(empty_estimates(0), tr)["coverage_pct"] == 0.0


def test_estimates_are_compared_at_their_own_stamp() -> None:
    tr = _truth()
    tr["vl_mps"] = 1.0 + 0.001 * np.arange(tr.shape[0])
    rows = _rows_from_truth(tr)
    # a row that reports the value of one row (50 ms) earlier is wrong by 0.005 m/s
    rows["vl_mps"][1:] = rows["vl_mps"][:-1]
    rows["vl_mps"][0] = 0.0
    m = evaluate(rows, tr)
    mean_left = float(np.mean(tr["vl_mps"][tr["v0_mps"] > 0.5]))
    assert m["vw_max_pct"] == pytest.approx(100 * 0.005 / mean_left, rel=1e-6)


def test_floors() -> None:
    good = {"vw_max_pct": 1.0, "slip_rms_pp": 0.5, "slip_p95_pp": 1.0, "coverage_pct": 99.0}
    assert check_floors(good, "paper_straight") == (True, [])
    bad = dict(good, vw_max_pct=2.0)
    ok, failed = check_floors(bad, "paper_circle")
    assert not ok and failed[0].startswith("vw_max_pct")
    assert check_floors(bad, "figure_eight")[0]  # the speed floor is for paper scenarios only
    assert not check_floors(dict(good, coverage_pct=math.nan), "slow_creep")[0]


def test_traditional_baseline_uses_vehicle_speed_for_both_wheels() -> None:
    sim = simulate("paper_circle", seed=2, start_ns=START_NS)
    rows = traditional_estimates(sim, sim.config)
    assert rows.dtype == ESTIMATE_DTYPE
    assert np.array_equal(rows["vl_mps"], rows["vr_mps"], equal_nan=True)
    m = evaluate(rows, sim.truth)
    # circling at 0.4 rad/s with b = 1.8 m: each wheel is off by ωz·b/2 = 0.36 m/s ≈ 12-14 %
    assert 10.0 < m["vw_rms_pct"] < 16.0
    # wheel speeds from edges are good, slip error comes from the ground speed
    assert m["omega_rms_pct"] < 5.0
    assert m["slip_rms_pp"] > 8.0


def test_traditional_has_no_values_in_a_gnss_outage() -> None:
    sim = simulate("gnss_outage", seed=3, start_ns=START_NS, duration_s=60.0, outage_s=20.0)
    rows = traditional_estimates(sim, sim.config)
    t = rows["stamp_ns"]
    assert not np.any((t >= START_NS + 20 * 10**9) & (t < START_NS + 40 * 10**9))
    assert evaluate(rows, sim.truth)["coverage_pct"] < 75.0


class _TruthEstimator:
    """A fake FleetEstimator that reports the truth at 20 Hz ticks (plus an optional offset)."""

    name = "truth"
    output_dtype = ESTIMATE_DTYPE

    def __init__(self, truth: np.ndarray, slip_offset_pp: float = 0.0) -> None:
        self.truth = truth
        self.offset = slip_offset_pp
        self.ids: list[str] = []
        self.next_ns = int(truth["stamp_ns"][0])
        self.pushed = 0
        self.last_key = -1
        self.last_until = -1

    def add_vehicle(self, vehicle_id: str, config: VehicleConfig) -> None:
        self.ids.append(vehicle_id)

    def remove_vehicle(self, vehicle_id: str) -> None:
        self.ids.remove(vehicle_id)

    def vehicle_ids(self) -> list[str]:
        return list(self.ids)

    def push(self, vehicle_id: str, measurement: Pushed) -> None:
        # the bench pushes in first-sample order, never behind a horizon already advanced to
        key = (
            measurement.stamp_ns
            if isinstance(measurement, GnssSample)
            else int(measurement.stamp_ns[0])
        )
        assert key >= self.last_key
        assert key > self.last_until
        self.last_key = key
        self.pushed += 1

    def align_ticks(self, vehicle_id: str, stamp_ns: int) -> None:
        return None  # ticks on the fixed 50 ms grid

    def advance(self, until_ns: Mapping[str, int]) -> list[tuple[str, np.ndarray]]:
        until = until_ns["bench"]
        assert until > self.last_until
        self.last_until = until
        stamps = np.arange(self.next_ns, until + 1, 50_000_000, dtype=np.int64)
        if stamps.size == 0:
            return []
        self.next_ns = int(stamps[-1]) + 50_000_000
        idx = np.searchsorted(self.truth["stamp_ns"], stamps)
        pick = self.truth[np.minimum(idx, self.truth.shape[0] - 1)]
        rows = empty_estimates(stamps.size)
        rows["stamp_ns"] = stamps
        for name in ("vl_mps", "vr_mps", "omega_left_radps", "omega_right_radps"):
            rows[name] = pick[name]
        rows["slip_left_pct"] = pick["slip_left_pct"] + self.offset
        rows["slip_right_pct"] = pick["slip_right_pct"] + self.offset
        return [("bench", rows)]


def test_run_with_fake_estimators_writes_json_and_table(tmp_path: Path) -> None:
    def factories(offset: float) -> dict[str, accuracy.EstimatorFactory]:
        def make() -> FleetEstimator:
            sim = simulate("figure_eight", seed=5, start_ns=START_NS)
            return _TruthEstimator(sim.truth, offset)

        return {"product": make}

    out = io.StringIO()
    path = tmp_path / "acc.json"
    res = run(path, scenarios=["figure_eight"], seed=5, estimators=factories(0.0), out=out)
    product = next(r for r in res["results"] if r["method"] == "product")
    assert product["slip_rms_pp"] == pytest.approx(0.0, abs=1e-9)
    assert product["coverage_pct"] > 99.5
    assert product["floors_pass"] and res["all_pass"]
    data = json.loads(path.read_text())
    assert data["results"][0]["slip_rms_pp"] == pytest.approx(product["slip_rms_pp"])
    assert {r["method"] for r in data["results"]} == {"product", "traditional"}
    text = out.getvalue()
    assert "figure_eight" in text and "PASS" in text and "traditional" in text

    res2 = run(None, scenarios=["figure_eight"], seed=5, estimators=factories(1.5), quiet=True)
    p2 = next(r for r in res2["results"] if r["method"] == "product")
    assert p2["slip_rms_pp"] == pytest.approx(1.5, abs=1e-9)
    assert not p2["floors_pass"] and not res2["all_pass"]
    out2 = io.StringIO()
    print_table(res2, file=out2)
    assert "FAIL: slip_rms_pp 1.50" in out2.getvalue()


def test_unknown_scenario_is_refused() -> None:
    with pytest.raises(KeyError):
        run(None, scenarios=["nowhere"], estimators={}, quiet=True)


class _Broken(_TruthEstimator):
    def advance(self, until_ns: Mapping[str, int]) -> list[tuple[str, np.ndarray]]:
        raise RuntimeError("filter blew up")


def test_a_crashing_method_is_reported_not_hidden() -> None:
    sim = simulate("hard_braking", seed=1, start_ns=START_NS)

    def make() -> FleetEstimator:
        return _Broken(sim.truth)

    out = io.StringIO()
    res = run(None, scenarios=["hard_braking"], seed=1, estimators={"product": make}, out=out)
    product = res["results"][0]
    assert product["error"] == "RuntimeError: filter blew up"
    assert product["coverage_pct"] == 0.0 and not product["floors_pass"]
    assert "RuntimeError: filter blew up" in out.getvalue()


def _seed_result(seed: int, slip_rms: float, coverage: float, vw_max: float) -> dict[str, object]:
    metrics = {k: 0.1 for k in accuracy._METRIC_KEYS}
    metrics.update(slip_rms_pp=slip_rms, coverage_pct=coverage, vw_max_pct=vw_max)
    return {
        "seed": seed,
        "results": [
            {"scenario": "paper_circle", "method": "product", **metrics},
            {"scenario": "paper_circle", "method": "traditional", **metrics},
        ],
    }


def test_summarize_seeds_takes_worst_and_mean_and_judges_floors_on_the_worst() -> None:
    rows = accuracy.summarize_seeds(
        [
            _seed_result(1, 0.4, 99.9, 1.0),
            _seed_result(2, 1.2, 99.0, 1.4),
            _seed_result(3, 0.5, 97.0, 0.9),
        ]
    )
    assert [(r["scenario"], r["method"]) for r in rows] == [
        ("paper_circle", "product"),
        ("paper_circle", "traditional"),
    ]
    product = rows[0]
    assert product["seeds"] == [1, 2, 3]
    assert product["worst"]["slip_rms_pp"] == pytest.approx(1.2)
    assert product["worst_seed"]["slip_rms_pp"] == 2
    assert product["mean"]["slip_rms_pp"] == pytest.approx(0.7)
    # coverage: higher is better, so the worst is the smallest
    assert product["worst"]["coverage_pct"] == pytest.approx(97.0)
    assert product["worst_seed"]["coverage_pct"] == 3
    assert product["worst"]["vw_max_pct"] == pytest.approx(1.4)
    assert not product["floors_pass"]
    assert any(f.startswith("slip_rms_pp 1.20") for f in product["floors_failed"])
    assert any(f.startswith("coverage_pct 97.00") for f in product["floors_failed"])
    assert "floors_pass" not in rows[1]


def test_summarize_seeds_a_nan_seed_makes_the_worst_nan() -> None:
    rows = accuracy.summarize_seeds(
        [_seed_result(1, 0.4, 99.9, 1.0), _seed_result(2, math.nan, 99.9, 1.0)]
    )
    assert math.isnan(rows[0]["worst"]["slip_rms_pp"])
    assert rows[0]["worst_seed"]["slip_rms_pp"] == 2
    assert not rows[0]["floors_pass"]


def test_run_seeds_runs_each_seed_and_writes_worst_and_mean(tmp_path: Path) -> None:
    plan = iter([(3, 0.2), (4, 0.6)])  # one estimator per seed, in seed order

    def make() -> FleetEstimator:
        seed, offset = next(plan)
        sim = simulate("hard_braking", seed=seed, start_ns=START_NS)
        return _TruthEstimator(sim.truth, offset)

    out = io.StringIO()
    path = tmp_path / "seeds.json"
    res = accuracy.run_seeds(
        path, scenarios=["hard_braking"], seeds=[3, 4], estimators={"product": make}, out=out
    )
    assert [r["seed"] for r in res["runs"]] == [3, 4]
    product = next(r for r in res["summary"] if r["method"] == "product")
    assert product["worst"]["slip_rms_pp"] == pytest.approx(0.6, abs=1e-9)
    assert product["worst_seed"]["slip_rms_pp"] == 4
    assert product["mean"]["slip_rms_pp"] == pytest.approx(0.4, abs=1e-9)
    assert product["floors_pass"] and res["all_pass"]
    data = json.loads(path.read_text())
    assert data["seeds"] == [3, 4]
    assert data["summary"][0]["worst"]["slip_rms_pp"] == pytest.approx(0.6, abs=1e-9)
    text = out.getvalue()
    assert "worst" in text and "mean" in text and "seeds 3,4" in text and "PASS" in text


def test_main_parses_seeds_and_scenarios(monkeypatch: pytest.MonkeyPatch) -> None:
    seen: dict[str, object] = {}

    def fake_run_seeds(json_path: Path | None, **kw: object) -> dict[str, object]:
        seen.update(kw)
        return {"all_pass": False}

    monkeypatch.setattr(accuracy, "run_seeds", fake_run_seeds)
    code = accuracy.main(["--seeds", "1,2,5", "--scenarios", "paper_circle,slow_creep"])
    assert code == 1
    assert seen["seeds"] == [1, 2, 5]
    assert seen["scenarios"] == ["paper_circle", "slow_creep"]
    with pytest.raises(SystemExit):
        accuracy.main(["--seeds", "1,x"])


def test_variants_run_the_changed_scenarios_under_their_own_label() -> None:
    def factories() -> dict[str, accuracy.EstimatorFactory]:
        def make() -> FleetEstimator:
            return _TruthEstimator(simulate("figure_eight", seed=5, start_ns=START_NS).truth)

        return {"product": make}

    plain = run(None, scenarios=["figure_eight"], seed=5, estimators=factories(), quiet=True)
    out = io.StringIO()
    res = run(
        None, scenarios=["figure_eight"], seed=5, estimators=factories(), variants=True, out=out
    )
    label = "figure_eight[gnss_outlier_prob=0.02]"
    assert ("figure_eight", {"gnss_outlier_prob": 0.02}) in accuracy.VARIANTS
    assert {r["scenario"] for r in res["results"]} == {label}
    # the override reached the simulator: GNSS outliers move the GNSS-based traditional method
    trad = next(r for r in res["results"] if r["method"] == "traditional")
    trad0 = next(r for r in plain["results"] if r["method"] == "traditional")
    assert trad["vw_rms_pct"] != pytest.approx(trad0["vw_rms_pct"], rel=1e-9)
    lines = [ln for ln in out.getvalue().splitlines() if ln.startswith(label)]
    assert len(lines) == 2 and lines[0].index("product") == lines[1].index("traditional")


def test_slow_rows_report_their_largest_slip_error_apart() -> None:
    tr = _truth()
    ramp = np.clip((np.arange(tr.shape[0]) - 100) * 0.02, 0.0, 2.0)  # 0 -> 2 m/s in 1 s
    tr["v0_mps"] = ramp
    tr["slip_left_pct"] = np.where(ramp > 0, 10.0, np.nan)
    tr["slip_right_pct"] = np.where(ramp > 0, 5.0, np.nan)
    rows = _rows_from_truth(tr)
    v0 = truth_at(tr, rows["stamp_ns"], "v0_mps")
    slow = np.flatnonzero((v0 <= MOVING_MPS) & np.isfinite(rows["slip_left_pct"]))
    assert slow.size  # the hand-made run passes through low speed with slip values
    rows["slip_left_pct"][slow[0]] += 40.0
    m = evaluate(rows, tr)
    assert m["slip_low_max_pp"] == pytest.approx(40.0)
    assert m["slip_max_pp"] == pytest.approx(0.0)  # the moving rows' metrics do not see it
    rows["slip_left_pct"][slow] = np.nan
    rows["slip_right_pct"][slow] = np.nan
    assert evaluate(rows, tr)["slip_low_max_pp"] == 0.0  # none shown: no error shown


def test_random_drives_report_distribution_floors_and_worst(tmp_path: Path) -> None:
    drives = draw_drives(3, 7)
    sims = iter(
        [
            simulate(
                "random_drive",
                seed=d.sim_seed,
                start_ns=START_NS,
                config=d.config(),
                **dict(d.overrides),
            )
            for d in drives
        ]
    )
    offsets = iter([0.0, 2.5, 0.5])

    def make() -> FleetEstimator:
        return _TruthEstimator(next(sims).truth, next(offsets))

    out = io.StringIO()
    path = tmp_path / "random.json"
    res = run_random(3, 7, path, estimators={"product": make}, out=out)
    rms = [r["slip_rms_pp"] for r in res["results"]]
    assert rms == pytest.approx([0.0, 2.5, 0.5], abs=1e-9)
    q = res["summary"]["product"]["slip_rms_pp"]
    assert q["median"] == pytest.approx(0.5) and q["worst"] == pytest.approx(2.5)
    assert res["worst"][:2] == [1, 2]
    assert not res["all_pass"]
    assert "2/3 drives within" in res["floors_failed"][0]
    assert "1 drives with RMS > 2 pp" in res["floors_failed"]
    data = json.loads(path.read_text())
    assert data["drives"][1]["knobs"]["teeth_per_rev"] == drives[1].teeth_per_rev
    text = out.getvalue()
    assert "drive    1" in text and "FAIL" in text and "slip_rms_pp" in text


def test_main_runs_random_drives(monkeypatch: pytest.MonkeyPatch) -> None:
    seen: dict[str, object] = {}

    def fake(
        n: int, seed: int, json_path: Path | None, *, start_calibration: str
    ) -> dict[str, object]:
        seen.update(n=n, seed=seed, start=start_calibration)
        return {"all_pass": True}

    monkeypatch.setattr(accuracy, "run_random", fake)
    assert accuracy.main(["--random", "12", "--seed", "1001"]) == 0
    assert seen == {"n": 12, "seed": 1001, "start": "calibration-drive"}
    assert accuracy.main(["--random", "2", "--seed", "1", "--start-calibration", "none"]) == 0
    assert seen == {"n": 2, "seed": 1, "start": "none"}
    with pytest.raises(SystemExit):
        accuracy.main(["--random", "3", "--variants"])


def test_a_calibration_drive_start_gives_mdsf_each_wheels_true_radius_within_its_std() -> None:
    """``--start-calibration calibration-drive``: the vehicle starts from the radii a calibration
    drive left (the drive's truth within the converged std); the rest stays at its priors."""
    from estimator.mdsf import MdsfFleet

    drive = draw_drives(1, 3)[0]
    config = drive.config()
    fleet = MdsfFleet()
    fleet.add_vehicle("v", config)
    prior = fleet.calibration("v")
    accuracy._radii_from_a_calibration_drive(drive, config)(fleet, "v")
    got = fleet.calibration("v")
    sigma = config.calibration.radius_converged_pct / 100
    left, right = (1.0 + e for e in drive.overrides["wheel_radius_error_rel"])
    assert max(abs(left - 1.0), abs(right - 1.0)) > 4 * sigma  # the draw's radii are off
    assert abs(got.radius_scale_left - left) <= 4 * sigma * left
    assert abs(got.radius_scale_right - right) <= 4 * sigma * right
    assert got.radius_scale_left_std == pytest.approx(sigma, rel=0.05)
    assert prior.radius_scale_left == 1.0 and prior.radius_scale_left_std > 0.01
    assert got.gnss_clock_offset_std_s == prior.gnss_clock_offset_std_s  # learnt online
    assert got.imu_pitch_std_rad == prior.imu_pitch_std_rad
    with pytest.raises(ValueError, match="start_calibration"):
        run_random(1, 3, start_calibration="stored")
