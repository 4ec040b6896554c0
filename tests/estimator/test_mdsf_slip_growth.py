"""MDSF's rim excess at a constant slip ratio: it grows with the speed the accelerometer
predicts, so it shares the accelerometer's noise and bias with ``V1``.

``e' = e·(1 + dt·(ā − b)/V)`` linearised (:meth:`estimator.mdsf.MdsfEngine._slip_ratio_growth`)
couples the rim excess to the bias state, and the tick's accelerometer noise enters ``e`` by
``ε·dt`` where it enters ``V1`` by ``dt`` (:meth:`MdsfEngine._accel_noise_into_excess`). A GNSS
correction of ``V1`` then corrects the excess's share too; without the coupling a gravity leak
(a pitch error without receiver attitude) that the GNSS takes out of ``V1`` stayed in ``e``.
"""

from __future__ import annotations

import numpy as np
import pytest

from estimator import kalman
from estimator.config import WheeledRearDriveConfig
from estimator.mdsf import MdsfConfig, MdsfEngine, MdsfObs, MdsfState, TickInputs
from tests.estimator.mdsf_tick import one_vehicle_inputs

_V1, _A1, _B, _D = MdsfState.V1, MdsfState.A1, MdsfState.ACCEL_BIAS, MdsfState.DIST
_E = (MdsfState.RIM_EXCESS_LEFT, MdsfState.RIM_EXCESS_RIGHT)


def _tick(accel_mps2: float, accel_var: float) -> TickInputs:
    """One tick with GNSS just fused (so the accelerometer keeps its white variance)."""
    z = np.zeros((1, 4))
    z[0, MdsfObs.A1] = accel_mps2
    return one_vehicle_inputs(
        stamp_ns=np.array([100_000_000]),
        z=z,
        gnss_var=np.full(1, 0.03**2),
        accel_var=np.array([accel_var]),
        gyro_var=np.full(1, 1e-4),
        force_fwd=np.full(1, accel_mps2),
    )


def _process(
    x: np.ndarray, accel_mps2: float, accel_var: float
) -> tuple[MdsfEngine, np.ndarray, np.ndarray, np.ndarray]:
    """The engine's predict matrices ``F``, ``Q``, ``u`` for state ``x`` (n,) on one tick."""
    eng = MdsfEngine(MdsfConfig())
    slots = np.array([eng.add(WheeledRearDriveConfig())])
    eng.initialized[slots] = True
    eng.last_fused_ns[slots] = 100_000_000
    t = _tick(accel_mps2, accel_var)
    z = np.zeros((1, eng.m))
    z[0, MdsfObs.A1] = accel_mps2
    F, Q, u = eng._process(slots, t, z, x[None].copy(), np.array([True]), np.array([accel_var]))
    assert u is not None
    return eng, F[0], Q[0], u[0]


def _state(v1_mps: float, excess_mps: tuple[float, float], bias_mps2: float) -> np.ndarray:
    x = np.zeros(len(MdsfState))
    x[_V1] = v1_mps
    x[_B] = bias_mps2
    x[list(_E)] = excess_mps
    return x


def test_the_growth_is_linearised_in_the_bias_and_keeps_its_mean() -> None:
    # Hand-computed: V1 0.6 m/s, slip ratios 0.15 and 0.10, ā 0.3, b 0.1 m/s², dt 0.1 s:
    # e' = e·(1 + 0.1·0.2/0.6); ∂e'/∂b = −ε·dt; ∂e'/∂e = 1 + dt·ā/V.
    x = _state(0.6, (0.09, 0.06), 0.1)
    eng, F, _, u = _process(x, 0.3, 0.01)
    dt = eng.dt_s
    for e, eps in zip(_E, (0.15, 0.10), strict=True):
        assert F[e, _B] == pytest.approx(-eps * dt)
        assert F[e, e] == pytest.approx(1.0 + dt * 0.3 / 0.6)
        assert (F @ x + u)[e] == pytest.approx(x[e] * (1.0 + dt * 0.2 / 0.6))


def test_the_accelerometer_noise_enters_the_excess_as_it_enters_the_speed() -> None:
    # Q's cross terms: the noise w moves V1 by dt·w, a1 by w, D by dt²·w/2 and e by ε·dt·w.
    x = _state(0.6, (0.09, 0.06), 0.1)
    var = 0.04
    eng, _, Q, _ = _process(x, 0.3, var)
    base = MdsfEngine(MdsfConfig())
    q0 = base.Q_base[base.add(WheeledRearDriveConfig())]
    dt = eng.dt_s
    g = {_E[0]: 0.15 * dt, _E[1]: 0.10 * dt}
    for e, ge in g.items():
        assert Q[e, _V1] - q0[e, _V1] == pytest.approx(var * ge * dt)
        assert Q[e, _A1] - q0[e, _A1] == pytest.approx(var * ge)
        assert Q[e, _D] - q0[e, _D] == pytest.approx(var * ge * 0.5 * dt * dt)
        assert Q[_V1, e] == pytest.approx(Q[e, _V1])
    assert Q[_E[0], _E[1]] - q0[_E[0], _E[1]] == pytest.approx(var * g[_E[0]] * g[_E[1]])
    assert np.allclose(Q, Q.T)
    assert np.all(np.linalg.eigvalsh(Q) > -1e-15)


def test_a_gnss_correction_of_the_speed_corrects_the_excess_by_its_slip_ratio() -> None:
    # A tick whose accelerometer noise dominates V1's prior: a GNSS speed 2 cm/s below the
    # prediction moves V1 down, and each rim excess by its slip ratio times that (the same
    # noise grew both); uncoupled, the excess kept the whole error.
    x = _state(0.6, (0.09, 0.06), 0.0)
    eng, F, Q, u = _process(x, 0.0, 0.5)
    P = np.diag(np.full(eng.n, 1e-8))
    _, P_pr = kalman.predict(x[None], P[None], F[None], Q[None], u[None])
    h = np.zeros(eng.n)
    h[_V1] = 1.0
    s = h @ P_pr[0] @ h + 0.03**2
    gain = P_pr[0] @ h / s
    dv = gain[_V1] * -0.02
    assert dv < -0.01
    for e, eps in zip(_E, (0.15, 0.10), strict=True):
        assert gain[e] * -0.02 == pytest.approx(eps * dv, rel=0.05)
