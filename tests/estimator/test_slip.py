"""Slip, method.md §1 eq. (8)(9): hand-computed values, standstill rule, reverse, std."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimator.slip import fit_span_s, slip_pct, unsettled

THR = 0.2


def test_driving_by_hand() -> None:
    # rW = 3.3, V = 3.0: (3.3 - 3.0)/3.3 = 9.0909 %
    r = slip_pct(3.3, 3.0, THR)
    assert float(r.slip_pct) == pytest.approx(100 * 0.3 / 3.3)
    assert bool(r.valid) and not bool(r.standstill)


def test_braking_by_hand() -> None:
    # rW = 2.4, V = 3.0: (2.4 - 3.0)/3.0 = -20 %
    r = slip_pct(2.4, 3.0, THR)
    assert float(r.slip_pct) == pytest.approx(-20.0)


def test_locked_wheel_is_minus_100() -> None:
    assert float(slip_pct(0.0, 2.0, THR).slip_pct) == pytest.approx(-100.0)


def test_spinning_wheel_at_standstill_is_plus_100() -> None:
    # The ground does not move but the rim does: full slip, not a blow-up.
    assert float(slip_pct(1.0, 0.0, THR).slip_pct) == pytest.approx(100.0)


def test_standstill_gives_no_value() -> None:
    r = slip_pct(np.array([0.0, 0.1, 0.19]), np.array([0.0, 0.05, 0.1]), THR)
    assert np.all(np.isnan(r.slip_pct)) and np.all(np.isnan(r.std_pct))
    assert np.all(r.standstill) and not np.any(r.valid)


def test_threshold_needs_both_speeds_low() -> None:
    r = slip_pct(np.array([0.25, 0.1]), np.array([0.1, 0.25]), THR)
    assert np.all(r.valid)
    assert r.slip_pct == pytest.approx([100 * 0.15 / 0.25, -100 * 0.15 / 0.25])


def test_reverse_uses_direction_of_travel() -> None:
    # Backwards at 3 m/s with the wheel turning faster: positive (driving) slip.
    r = slip_pct(-3.3, -3.0, THR)
    assert float(r.slip_pct) == pytest.approx(100 * 0.3 / 3.3)
    assert float(slip_pct(-2.4, -3.0, THR).slip_pct) == pytest.approx(-20.0)


def test_non_finite_inputs_are_invalid_not_standstill() -> None:
    r = slip_pct(np.array([np.nan, 1.0, np.inf]), np.array([1.0, np.nan, 1.0]), THR)
    assert np.all(np.isnan(r.slip_pct))
    assert not np.any(r.valid) and not np.any(r.standstill)


def test_infinite_or_huge_uncertainty_gives_unknown_std_not_inf() -> None:
    # a degenerate encoder fit can report an infinite (or overflowing) rim-speed std: the slip
    # value stands, its uncertainty is unknown (NaN), never inf
    r = slip_pct(np.array([3.3, 3.3, 3.3]), 3.0, THR, np.array([np.inf, 1e308, 0.02]), 0.05)
    assert r.valid.tolist() == [True, True, True]
    assert np.isnan(r.std_pct[0]) and np.isnan(r.std_pct[1])
    assert np.isfinite(r.std_pct[2])
    assert np.allclose(r.slip_pct, 100 * 0.3 / 3.3)  # eq. (8), driving


def test_threshold_broadcasts_per_row() -> None:
    r = slip_pct(np.array([0.3, 0.3]), np.array([0.25, 0.25]), np.array([0.2, 0.5]))
    assert r.valid.tolist() == [True, False]


def test_std_matches_numerical_propagation() -> None:
    for rim, v in ((3.3, 3.0), (2.4, 3.0), (-3.3, -3.0)):
        s_rim, s_v = 0.02, 0.05
        r = slip_pct(rim, v, THR, s_rim, s_v)
        h = 1e-6
        d_rim = (slip_pct(rim + h, v, THR).slip_pct - slip_pct(rim - h, v, THR).slip_pct) / (2 * h)
        d_v = (slip_pct(rim, v + h, THR).slip_pct - slip_pct(rim, v - h, THR).slip_pct) / (2 * h)
        expected = np.hypot(d_rim * s_rim, d_v * s_v)
        assert float(r.std_pct) == pytest.approx(float(expected), rel=1e-5)


@settings(max_examples=300, deadline=None)
@given(
    rim=st.floats(-50, 50, allow_nan=False),
    v=st.floats(-50, 50, allow_nan=False),
    thr=st.floats(1e-3, 2.0),
)
def test_never_blows_up(rim: float, v: float, thr: float) -> None:
    r = slip_pct(rim, v, thr, 0.01, 0.01)
    if bool(r.valid):
        assert abs(float(r.slip_pct)) <= 200.0 + 1e-9
        assert np.isfinite(r.std_pct)
    else:
        assert abs(rim) < thr and abs(v) < thr


def test_std_with_correlated_speeds_matches_numerical_propagation() -> None:
    # A filter estimating both speeds correlates them; the std propagates the covariance:
    # var = J Σ Jᵀ with J = (∂S/∂rW, ∂S/∂V), Σ = [[σ_rW², c], [c, σ_V²]].
    h = 1e-6
    for rim, v, c in ((3.3, 3.0, 0.0008), (2.4, 3.0, 0.0005), (-3.3, -3.0, 0.0009)):
        s_rim, s_v = 0.03, 0.04
        r = slip_pct(rim, v, THR, s_rim, s_v, c)
        d_rim = (slip_pct(rim + h, v, THR).slip_pct - slip_pct(rim - h, v, THR).slip_pct) / (2 * h)
        d_v = (slip_pct(rim, v + h, THR).slip_pct - slip_pct(rim, v - h, THR).slip_pct) / (2 * h)
        jac = np.array([float(d_rim), float(d_v)])
        cov = np.array([[s_rim**2, c], [c, s_v**2]])
        assert float(r.std_pct) == pytest.approx(math.sqrt(jac @ cov @ jac), rel=1e-5)
        assert float(r.std_pct) < float(slip_pct(rim, v, THR, s_rim, s_v).std_pct)


# --- settling: starting and stopping faster than the wheel fit follows ---------------------


def test_fit_span_by_hand() -> None:
    # r = 0.85 m, 120 teeth: arc = 2π·0.85/120 = 0.04451 m; 3 edges at 0.25 m/s take 0.534 s
    arc = 2 * math.pi * 0.85 / 120
    span = fit_span_s(np.array([0.25, -0.5, 2.0]), arc, 3)
    np.testing.assert_allclose(span, 3 * arc / np.array([0.25, 0.5, 2.0]))


def test_fit_span_at_standstill_is_infinite_and_zero_without_a_fit() -> None:
    assert float(fit_span_s(0.0, 0.05, 3)) == math.inf
    assert float(fit_span_s(np.nan, 0.05, 3)) == math.inf
    # wheel speeds given directly (arc 0): no fit, no span
    assert float(fit_span_s(0.3, 0.0, 3)) == 0.0


def test_unsettled_by_hand() -> None:
    # |a|·τ against 0.5·|V|: 0.9·0.534 = 0.48 > 0.125 (a start at 0.25 m/s); 0.9·0.067 = 0.06
    # < 1.0 (the same acceleration at 2 m/s); braking counts like accelerating
    v = np.array([0.25, 2.0, 0.25, 0.25])
    a = np.array([0.9, 0.9, -0.9, 0.05])
    span = fit_span_s(v, 2 * math.pi * 0.85 / 120, 3)
    assert unsettled(v, a, span, 0.5).tolist() == [True, False, True, False]


def test_unsettled_needs_finite_inputs_and_a_fit() -> None:
    v = np.array([0.3, np.nan, 0.3, 0.0])
    a = np.array([np.nan, 1.0, 1.0, 0.0])
    span = np.array([0.4, 0.4, 0.0, np.inf])
    # unknown acceleration, unknown speed, no fit, standing with no acceleration: not marked
    assert not unsettled(v, a, span, 0.5).any()


def test_unsettled_limit_broadcasts_per_row() -> None:
    v = np.array([[0.5, 0.5], [0.5, 0.5]])
    # change |a|·τ = 1.0·0.2 = 0.2 m/s; limits 0.3·0.5 = 0.15 m/s (row 0) and 0.5·0.5 = 0.25 m/s
    span = np.full((2, 2), 0.2)
    got = unsettled(v, np.array([[1.0], [1.0]]), span, np.array([[0.3], [0.5]]))
    assert got.tolist() == [[True, True], [False, False]]
