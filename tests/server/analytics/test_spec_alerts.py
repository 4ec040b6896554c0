"""The specs' own alert rules on the real AlertEngine: a crawler's track slip out of its band
(a braked track's −100 % in a pivot is none), dead reckoning held too long, a crawler on a steep
side slope (and none on the simulator's hilly route), a low friction μ;
their limits and hold times set per server (``rule_limits``)."""

from __future__ import annotations

from functools import cache
from typing import Any

import numpy as np
import pytest

from estimator.config import SlipConfig
from estimator.friction_spec import FRICTION_SPEC, FrictionFlag
from estimator.sim.tracked import simulate_tracked
from estimator.spec import AlertRule, EstimatorSpec, SpecError
from estimator.tracked import TrackedFleet
from estimator.tracked_spec import TRACKED_SPEC, TrackedFlag
from estimator.types import EstimateBatch
from server.analytics.alerts import Alert, AlertEngine, flag_kind, rule_kind, slip_kind

S = 1_000_000_000
T0 = 1_700_000_000 * S
F = TrackedFlag


def _rows(spec: EstimatorSpec, t_s: np.ndarray, **columns: Any) -> np.ndarray:
    r = spec.empty_rows(t_s.size)
    r["stamp_ns"] = T0 + np.round(t_s * S).astype(np.int64)
    for name, value in columns.items():
        r[name] = value
    return r


def _run(spec: EstimatorSpec, rows: np.ndarray, **kw: Any) -> list[Alert]:
    """Every alert the rows raise, fed 10 rows a batch (as the pipeline delivers them)."""
    cfg = SlipConfig(alert_threshold_pct=15.0, alert_hold_s=2.0)
    eng = AlertEngine(slip_config_for=lambda _v: cfg, clock_ns=lambda: T0, **kw)
    for lo in range(0, rows.size, 10):
        eng.on_estimates(EstimateBatch.of([("c1", rows[lo : lo + 10])], spec))
    return sorted(eng.alerts(), key=lambda a: a.id)


def _tracked(seconds: float, **columns: Any) -> np.ndarray:
    t = np.arange(0.0, seconds, 0.1)
    return _rows(TRACKED_SPEC, t, **columns)


def test_track_slip_out_of_its_band_alerts_in_place_of_the_slip_threshold() -> None:
    rows = _tracked(8.0, slip_left_pct=4.0, slip_right_pct=-20.0)
    rows["flags"] = F.SLIP_LEFT_VALID | F.SLIP_RIGHT_VALID | F.GNSS_OK
    spin = (rows["stamp_ns"] >= T0 + 2 * S) & (rows["stamp_ns"] < T0 + 6 * S)
    rows["slip_left_pct"][spin] = np.linspace(26.0, 31.0, spin.sum())
    alerts = _run(TRACKED_SPEC, rows)
    # the right track's −20 % skid is inside the band (over the 15 % wheel threshold)
    assert [a.kind for a in alerts] == [rule_kind("tracked", "track_slip_left")]
    (a,) = alerts
    assert a.start_ns == T0 + 2 * S and a.end_ns == T0 + 6 * S
    assert a.threshold == 25.0 and a.peak == 31.0 and a.channel == "track_slip_left"


def test_a_braked_track_in_a_pivot_and_an_invalid_slip_raise_no_alert() -> None:
    rows = _tracked(10.0, slip_left_pct=-100.0, slip_right_pct=40.0)
    rows["flags"] = F.SLIP_LEFT_VALID | F.BRAKED_LEFT | F.GNSS_OK  # right: not valid
    assert _run(TRACKED_SPEC, rows) == []


def test_slip_channels_no_rule_takes_keep_the_vehicles_threshold() -> None:
    spec = EstimatorSpec(  # the tracked spec with the right track's band rule left out
        **{
            **{k: getattr(TRACKED_SPEC, k) for k in ("name", "title", "kinds", "inputs")},
            **{k: getattr(TRACKED_SPEC, k) for k in ("fields", "flags", "slips")},
            "alerts": TRACKED_SPEC.alerts[:1],
        }
    )
    rows = _tracked(5.0, slip_left_pct=0.0, slip_right_pct=-20.0)
    rows["flags"] = F.SLIP_RIGHT_VALID
    assert [a.kind for a in _run(spec, rows)] == [slip_kind("tracked", "right")]


def test_dead_reckoning_held_longer_than_its_hold_alerts_once_more() -> None:
    rows = _tracked(50.0)
    outage = (rows["stamp_ns"] >= T0 + 5 * S) & (rows["stamp_ns"] < T0 + 45 * S)
    rows["flags"] = np.where(outage, int(F.DEAD_RECKONING), int(F.GNSS_OK))
    alerts = _run(TRACKED_SPEC, rows)
    assert [a.kind for a in alerts] == [
        flag_kind("tracked", "DEAD_RECKONING"),
        rule_kind("tracked", "long_dead_reckoning"),
    ]
    long = alerts[1]
    assert long.start_ns == T0 + 5 * S and long.end_ns == T0 + 45 * S
    assert long.opened_wall_ns == T0 and long.threshold is None and long.peak is None
    later = _run(TRACKED_SPEC, rows, rule_limits={"tracked:long_dead_reckoning": {"hold_s": 60}})
    assert [a.kind for a in later] == [flag_kind("tracked", "DEAD_RECKONING")]


def test_a_short_outage_is_no_long_dead_reckoning() -> None:
    rows = _tracked(40.0)
    outage = (rows["stamp_ns"] >= T0 + 5 * S) & (rows["stamp_ns"] < T0 + 34 * S)
    rows["flags"] = np.where(outage, int(F.DEAD_RECKONING), int(F.GNSS_OK))
    kinds = [a.kind for a in _run(TRACKED_SPEC, rows)]
    assert kinds == [flag_kind("tracked", "DEAD_RECKONING")]


def test_a_steep_side_slope_held_past_its_hold_alerts_on_either_side() -> None:
    rows = _tracked(20.0, roll_rad=0.05, pitch_rad=0.02)
    rows["flags"] = int(F.GNSS_OK)
    t = (rows["stamp_ns"] - T0) / S
    rows["roll_rad"][(t >= 2.0) & (t < 3.5)] = 0.3  # 17° for 1.5 s: under the hold
    steep = (t >= 6.0) & (t < 10.0)
    rows["roll_rad"][steep] = -np.linspace(0.27, 0.33, steep.sum())  # left side down, 4 s
    rows["roll_rad"][(t >= 14.0) & (t < 18.0)] = np.nan  # no attitude: nothing holds
    alerts = _run(TRACKED_SPEC, rows)
    assert [a.kind for a in alerts] == [rule_kind("tracked", "side_slope")]
    (a,) = alerts
    assert a.start_ns == T0 + 6 * S and a.end_ns == T0 + 10 * S
    assert a.threshold == pytest.approx(np.radians(15.0)) and a.peak == pytest.approx(0.33)
    wider = {"tracked:side_slope": {"above": 0.35}}
    assert _run(TRACKED_SPEC, rows, rule_limits=wider) == []


@cache
def _hill_rows() -> np.ndarray:
    """The tracked estimator's rows of ``route_firm_hill`` seed 1 (10 % ramps, 5 % side
    slopes, a 4-minute GNSS outage), 0.1 s apart."""
    run = simulate_tracked("route_firm_hill", 1)
    fleet = TrackedFleet()
    fleet.add_vehicle("c1", run.config)
    for _, m in run.measurements:
        fleet.push("c1", m)
    parts = [rows for _, rows in fleet.advance({"c1": run.measurements[-1][0]})]
    return np.concatenate([*parts, fleet.flush("c1")])


def test_the_hilly_route_raises_no_side_slope_alert() -> None:
    rows = _hill_rows()
    roll = rows["roll_rad"]
    assert rows.size > 5000 and np.nanmax(np.abs(roll)) > 0.04  # it stood on its side slopes
    kinds = [a.kind for a in _run(TRACKED_SPEC, rows)]
    assert rule_kind("tracked", "side_slope") not in kinds
    assert rule_kind("tracked", "long_dead_reckoning") in kinds  # the engine saw the rows


def _friction(mu: np.ndarray) -> np.ndarray:
    t = np.arange(mu.size) * 0.02
    informed = np.isfinite(mu) & (np.arange(mu.size) % 50 < 10)  # informed now and then
    flags = np.where(informed, int(FrictionFlag.INFORMED), int(FrictionFlag.HELD))
    return _rows(FRICTION_SPEC, t, mu=mu, flags=flags)


def test_low_mu_held_past_its_hold_alerts_with_the_lowest_mu() -> None:
    mu = np.r_[np.full(100, np.nan), np.full(100, 0.8), np.linspace(0.28, 0.2, 100), [0.6] * 50]
    alerts = _run(FRICTION_SPEC, _friction(mu))
    assert [a.kind for a in alerts] == [rule_kind("friction", "low_mu")]
    (a,) = alerts
    assert a.start_ns == T0 + 200 * 20_000_000 and a.end_ns == T0 + 300 * 20_000_000
    assert a.threshold == 0.3 and a.peak == 0.2
    lower = {"friction:low_mu": {"below": 0.15}}
    assert _run(FRICTION_SPEC, _friction(mu), rule_limits=lower) == []


def test_low_mu_shorter_than_its_hold_and_no_mu_yet_raise_nothing() -> None:
    mu = np.r_[np.full(200, np.nan), np.full(40, 0.2), np.full(60, 0.7)]  # 0.8 s low
    alerts = _run(FRICTION_SPEC, _friction(mu))
    assert [a.kind for a in alerts] == [flag_kind("friction", "HELD")]  # 4 s before the first μ


@pytest.mark.parametrize(
    "limits",
    [
        {"low_mu": {"below": 0.2}},  # no estimator
        {"friction:low_mu": {"peak": 0.2}},  # not a limit
        {"friction:low_mu": {"hold_s": -1.0}},
    ],
)
def test_rule_limits_that_name_nothing_a_rule_has_are_refused(limits: Any) -> None:
    with pytest.raises(ValueError):
        AlertEngine(rule_limits=limits)


def test_a_limit_on_the_other_side_of_a_rule_is_refused_once_the_rule_is_used() -> None:
    eng = AlertEngine(rule_limits={"friction:low_mu": {"above": 0.9}})
    with pytest.raises(ValueError, match="below"):
        eng.on_estimates(EstimateBatch.of([("c1", _friction(np.full(3, 0.5)))], FRICTION_SPEC))


@pytest.mark.parametrize(
    "rule",
    [
        AlertRule("x", "x", "mu"),  # no limit
        AlertRule("x", "x", "mu", above=1.0, below=0.0),  # both
        AlertRule("x", "x"),  # nothing to hold
        AlertRule("x", "x", when=("NO_SUCH_FLAG",)),
        AlertRule("x", "x", "mu", below=0.3, slip="nowhere"),
        AlertRule("x", "x", "no_field", below=0.3),
    ],
)
def test_a_spec_with_an_alert_rule_that_cannot_hold_is_refused(rule: AlertRule) -> None:
    keep = ("name", "title", "kinds", "inputs", "fields", "flags", "slips")
    with pytest.raises(SpecError):
        EstimatorSpec(**{k: getattr(FRICTION_SPEC, k) for k in keep}, alerts=(rule,))
