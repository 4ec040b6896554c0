"""Reference speed from acceleration and wheel speed, method.md §3."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.config import ConfigError
from estimator.reference_speed import (
    RefAux,
    ReferenceSpeedConfig,
    RefState,
    reference_step,
    transition,
)

CFG = ReferenceSpeedConfig()


def _start(n: int = 1, v: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    x = np.zeros((n, 2))
    x[:, RefState.V] = v
    P = np.tile(np.diag([0.01, 0.05**2]), (n, 1, 1))
    aux = np.zeros((n, 3))
    aux[:, RefAux.WHEEL_RATIO] = 1.0
    return x, P, aux


def test_transition_by_hand() -> None:
    # v' = v − dT·a0 + dT·a_m: v = 2, a0 = 0.1, a_m = 1, dT = 0.5 → 2.45
    F, B = transition(0.5)
    x = np.array([2.0, 0.1])
    assert F @ x + B * 1.0 == pytest.approx([2.45, 0.1])


def test_prediction_without_measurement_integrates_corrected_acceleration() -> None:
    x, P, aux = _start(v=2.0)
    x[:, RefState.A0] = 0.1
    nan = np.array([np.nan])
    x2, _, _, used = reference_step(x, P, aux, np.array([1.0]), 0.5, nan, np.array([1.0]), nan, CFG)
    assert x2[0] == pytest.approx([2.45, 0.1])
    assert not used[0]


def test_learns_accelerometer_bias_from_reference_speed() -> None:
    rng = np.random.default_rng(0)
    x, P, aux = _start()
    dt, bias = 0.05, 0.12
    v = 0.0
    for k in range(4000):
        a = np.sin(0.01 * k)  # true acceleration
        v += a * dt
        a_m = a + bias + rng.normal(0, 0.05)
        x, P, aux, _ = reference_step(
            x,
            P,
            aux,
            np.array([a_m]),
            dt,
            np.array([v + rng.normal(0, 0.05)]),
            np.array([0.05**2]),
            np.array([np.nan]),
            CFG,
        )
    assert x[0, RefState.A0] == pytest.approx(bias, abs=0.02)
    assert x[0, RefState.V] == pytest.approx(v, abs=0.05)


def test_carries_speed_from_slip_corrected_wheels_while_gnss_lost() -> None:
    x, P, aux = _start(v=3.0)
    dt = 0.05
    rim = 3.0 / 0.95  # 5 % driving slip: the rim runs faster than the ground
    for _ in range(600):  # 30 s with the reference: learns ground/rim ratio 0.95
        x, P, aux, used = reference_step(
            x, P, aux, np.array([0.0]), dt, np.array([3.0]), np.array([1e-4]), np.array([rim]), CFG
        )
        assert not used[0]
    assert aux[0, RefAux.WHEEL_RATIO] == pytest.approx(0.95, abs=0.01)
    # GNSS lost, the vehicle speeds up to 4 m/s with the same slip: wheels carry the speed
    v = 3.0
    for _ in range(200):
        v += 0.05 * dt
        x, P, aux, used = reference_step(
            x,
            P,
            aux,
            np.array([0.05]),
            dt,
            np.array([np.nan]),
            np.array([np.nan]),
            np.array([v / 0.95]),
            CFG,
        )
        assert used[0]
    assert x[0, RefState.V] == pytest.approx(v, abs=0.03)
    assert aux[0, RefAux.LOST_S] == pytest.approx(200 * dt)


def test_bias_noise_opens_when_the_acceleration_changes() -> None:
    # method.md §3: w2 = 0.527·Δa_f — a step in acceleration inflates the bias variance
    def bias_var_after(accels: list[float]) -> float:
        x, P, aux = _start(v=1.0)
        nan = np.array([np.nan])
        for a in accels:
            x, P, aux, _ = reference_step(x, P, aux, np.array([a]), 0.05, nan, nan, nan, CFG)
        return float(P[0, RefState.A0, RefState.A0])

    steady = bias_var_after([0.5] * 20)
    stepped = bias_var_after([0.0] * 10 + [2.0] * 10)
    assert stepped > 2 * steady


def test_missing_acceleration_is_not_fatal() -> None:
    x, P, aux = _start(v=1.0)
    x2, P2, _, _ = reference_step(
        x,
        P,
        aux,
        np.array([np.nan]),
        0.05,
        np.array([np.nan]),
        np.array([np.nan]),
        np.array([np.nan]),
        CFG,
    )
    assert np.all(np.isfinite(x2)) and np.all(np.isfinite(P2))
    assert P2[0, 0, 0] > P[0, 0, 0]


def test_config_validation() -> None:
    with pytest.raises(ConfigError):
        ReferenceSpeedConfig(bias_gain=0.0)
    with pytest.raises(ConfigError):
        ReferenceSpeedConfig(ratio_tau_s=float("nan"))
