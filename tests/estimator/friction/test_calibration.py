"""The tyre calibration: carried from a filter's state, inflated, restored, started from."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from estimator.config import ConfigError
from estimator.friction import FilterConfig, FrictionFleet, FrictionFleetConfig, FrictionMode
from estimator.friction.calibration import (
    AGING_REL_STD,
    FACTOR_STATES,
    TyreCalibration,
    start_factors,
)
from estimator.friction.filter import ProductState, initial_state
from estimator.sim.four_wheel import (
    LEAD_S,
    FourWheelRun,
    Manoeuvre,
    named_manoeuvre,
    simulate_four_wheel,
)
from tests.estimator.friction.test_fleet import _drive

IDX = [int(i) for i in FACTOR_STATES]


def _state(seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    n = len(ProductState)
    x = rng.normal(size=n)
    x[IDX] = rng.uniform(0.8, 1.2, 4)
    s = np.tril(rng.normal(scale=0.05, size=(n, n)))
    return x, s


def test_from_state_is_the_posterior_block_plus_the_aging_by_hand() -> None:
    x, s = _state(1)
    cal = TyreCalibration.from_state(x, s, aging_rel_std=0.03)
    p = s @ s.T
    want = p[np.ix_(IDX, IDX)] + np.diag((x[IDX] * 0.03) ** 2)
    np.testing.assert_allclose(np.asarray(cal.factor_cov), want, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(cal.factor, x[IDX], rtol=0, atol=0)
    np.testing.assert_allclose(cal.std, np.sqrt(np.diag(want)), rtol=1e-12)
    # the carried 1-σ is never the raw posterior's: each factor's grows by the aging term
    assert np.all(cal.std > np.sqrt(np.diag(p[np.ix_(IDX, IDX)])))


def test_round_trips_through_json() -> None:
    cal = TyreCalibration.from_state(*_state(2))
    back = TyreCalibration.from_dict(json.loads(json.dumps(cal.to_dict())))
    assert back == cal


@pytest.mark.parametrize(
    ("factor", "cov"),
    [
        ((1.0, 1.0, 1.0), np.eye(4) * 1e-4),
        ((1.0, -1.0, 1.0, 1.0), np.eye(4) * 1e-4),
        ((1.0, math.nan, 1.0, 1.0), np.eye(4) * 1e-4),
        ((1.0, 1.0, 1.0, 1.0), np.diag([1e-4, 1e-4, 1e-4, -1e-4])),
        ((1.0, 1.0, 1.0, 1.0), np.eye(4) * 1e-4 + np.triu(np.ones((4, 4)), 1) * 1e-5),
    ],
)
def test_refuses_what_is_no_calibration(factor: tuple[float, ...], cov: np.ndarray) -> None:
    with pytest.raises(ConfigError):
        TyreCalibration(factor, tuple(tuple(r) for r in cov))  # type: ignore[arg-type]


def test_start_factors_puts_the_calibration_in_the_prior_and_leaves_the_rest() -> None:
    cfg = FilterConfig()
    prior = initial_state(cfg, None, np.full((2, 4), 4000.0))  # type: ignore[arg-type]
    cal = TyreCalibration.from_state(*_state(3))
    f = np.asarray(cal.factor)[None].repeat(2, axis=0)
    p = np.asarray(cal.factor_cov)[None].repeat(2, axis=0)
    st = start_factors(prior, f, p)
    np.testing.assert_allclose(st.x[:, IDX], f)
    cov = np.einsum("bij,bkj->bik", st.s, st.s)
    np.testing.assert_allclose(cov[:, IDX][:, :, IDX], p, rtol=1e-12, atol=1e-15)
    rest = [int(ProductState.LN_MU), int(ProductState.VY)]
    np.testing.assert_allclose(st.x[:, rest], prior.x[:, rest])
    np.testing.assert_allclose(
        cov[:, rest][:, :, rest], np.einsum("bij,bkj->bik", prior.s, prior.s)[:, rest][:, :, rest]
    )
    assert np.all(cov[:, rest][:, :, IDX] == 0.0)


ACCEL = named_manoeuvre("accelerate_mu08")
GENTLE = Manoeuvre(
    "gentle",
    LEAD_S + 3.0,
    ((0.0, 40 / 3.6), (1e4, 40 / 3.6)),
    ((0.0, 0.0), (1e4, 0.0)),
    ((0.0, 0.8), (1e4, 0.8)),
)


@pytest.fixture(scope="module")
def accel() -> list[FourWheelRun]:
    return simulate_four_wheel([ACCEL, GENTLE], seeds=[21, 22])


def _truth_calibration(r: FourWheelRun, rel_std: float) -> TyreCalibration:
    px, py = r.config.tyre.c_px_npm2, r.config.tyre.c_py_npm2
    g = np.array(
        [
            r.tyre_c_px_npm2[:2].mean() / px,
            r.tyre_c_px_npm2[2:].mean() / px,
            r.tyre_c_py_npm2[:2].mean() / py,
            r.tyre_c_py_npm2[2:].mean() / py,
        ]
    )
    x = np.zeros(len(ProductState))
    x[IDX] = g
    s = np.zeros((len(x), len(x)))
    s[IDX, IDX] = g * rel_std
    return TyreCalibration.from_state(x, s, aging_rel_std=0.005)


def test_a_filter_started_from_a_calibration_is_surer_of_mu(accel: list[FourWheelRun]) -> None:
    """Accelerating on μ 0.8, the same drive: started from the tyres' factors known to 1 %,
    the product's μ ends with a smaller 1-σ than from the default 1 ± 10 % (μ and ``g`` trade
    along a ridge near the limit; knowing ``g`` narrows it), and its factors stay surer."""
    r = accel[0]
    end = r.start_ns + round(ACCEL.duration_s * 1e9)
    sd = {}
    for name, cal in (("plain", None), ("carried", _truth_calibration(r, 0.01))):
        fleet = FrictionFleet(FrictionFleetConfig())
        fleet.add_vehicle("v", r.config)
        fleet.set_tyre_calibration("v", cal)
        _drive(fleet, [r], ["v"], end)
        s = fleet._slots.s[fleet._vehicles["v"].slot]
        sd[name] = np.sqrt(np.einsum("ij,ij->i", s, s))
    assert sd["carried"][ProductState.LN_MU] < 0.75 * sd["plain"][ProductState.LN_MU]
    assert np.all(sd["carried"][IDX] < sd["plain"][IDX])


def test_calibrated_batched_equals_per_vehicle(accel: list[FourWheelRun]) -> None:
    cfg = FrictionFleetConfig()
    cals = [_truth_calibration(r, 0.02) for r in accel]
    both = FrictionFleet(cfg)
    for vid, r, c in zip(("a", "b"), accel, cals, strict=True):
        both.add_vehicle(vid, r.config)
        if vid == "a":
            both.set_tyre_calibration(vid, c)
    end = accel[0].start_ns + round(GENTLE.duration_s * 1e9)
    batched = _drive(both, accel, ["a", "b"], end)
    for vid, r, c in zip(("a", "b"), accel, cals, strict=True):
        alone = FrictionFleet(cfg)
        alone.add_vehicle(vid, r.config)
        if vid == "a":
            alone.set_tyre_calibration(vid, c)
        single = _drive(alone, [r], [vid], end)[vid]
        for name in ("mu", "mu_filter", "mu_std", "flags", "vy_mps"):
            a, b = batched[vid][name].astype(float), single[name].astype(float)
            assert np.allclose(a, b, rtol=0, atol=1e-9, equal_nan=True), name
    got = both.tyre_calibration("a")
    assert got is not None and both.tyre_calibration("b") is not None


def test_the_fleet_carries_a_calibration_and_refuses_it_outside_the_product() -> None:
    r = simulate_four_wheel([GENTLE], seeds=[23])[0]
    fleet = FrictionFleet(FrictionFleetConfig())
    fleet.add_vehicle("v", r.config)
    assert fleet.tyre_calibration("v") is None  # no tick yet
    _drive(fleet, [r], ["v"], r.start_ns + 1_000_000_000)
    cal = fleet.tyre_calibration("v")
    assert cal is not None and np.all(cal.std > AGING_REL_STD * np.asarray(cal.factor) * 0.999)
    paper = FrictionFleet(FrictionFleetConfig(filter=FilterConfig(mode=FrictionMode.PAPER)))
    paper.add_vehicle("v", r.config)
    with pytest.raises(ConfigError):
        paper.set_tyre_calibration("v", cal)
    assert paper.tyre_calibration("v") is None
