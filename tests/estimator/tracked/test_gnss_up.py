"""The fix's up velocity in the tracked filter: fused within the receiver's vertical 1-sigma,
its stated (horizontal) velocity 1-sigma times the config's up-over-horizontal ratio."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimator.config import TrackedConfig
from estimator.tracked import TrackedEstimatorConfig
from estimator.tracked.model import N_STATES
from estimator.tracked.model import TrackedState as S
from estimator.tracked.params import VehicleParams
from estimator.tracked.step import _fuse_gnss_up, initial_filter
from tests.estimator.tracked._ticks import quiet_tick

SPEED_MPS, PITCH_RAD, UP_MPS, STD_MPS = 8.0, 0.05, 0.5, 0.03
P_SPEED, P_PITCH = 0.01**2, 0.004**2
PARAMS = VehicleParams.of(TrackedConfig())  # the mast upright; no pitch or roll rate below


def _pitch_after_up_fix(cfg: TrackedEstimatorConfig) -> tuple[float, float]:
    """The pitch and its variance after one up velocity ``UP_MPS`` against a climb of
    ``SPEED_MPS·sin PITCH_RAD`` (≈ 0.40 m/s), the state's covariance diagonal."""
    f = initial_filter(cfg)
    f.x[0, S.SPEED], f.x[0, S.PITCH] = SPEED_MPS, PITCH_RAD
    diag = np.full(N_STATES, 1e-6)
    diag[S.SPEED], diag[S.PITCH] = P_SPEED, P_PITCH
    f.P = np.diag(diag)[None]
    inp = quiet_tick(1, 100_000_000, gnss_vel_up_mps=np.array([UP_MPS]))
    _fuse_gnss_up(f, inp, PARAMS, np.ones(1, dtype=bool), np.full(1, STD_MPS), cfg)
    return float(f.x[0, S.PITCH]), float(f.P[0, S.PITCH, S.PITCH])


@pytest.mark.parametrize("ratio", [1.0, 1.75, 2.0])
def test_the_up_velocity_is_weighed_by_the_vertical_sigma(ratio: float) -> None:
    cfg = TrackedEstimatorConfig(gnss_up_to_horizontal_vel_std_ratio=ratio, gnss_up_gate_nis=1e9)
    pitch, var = _pitch_after_up_fix(cfg)
    # by hand: H = [sin θ on V, V·cos θ on θ], R = (ratio·σ)²
    h_v, h_t = math.sin(PITCH_RAD), SPEED_MPS * math.cos(PITCH_RAD)
    s = h_v**2 * P_SPEED + h_t**2 * P_PITCH + (ratio * STD_MPS) ** 2
    y = UP_MPS - SPEED_MPS * math.sin(PITCH_RAD)
    assert math.isclose(pitch, PITCH_RAD + P_PITCH * h_t * y / s, rel_tol=1e-9)
    assert math.isclose(var, P_PITCH - (P_PITCH * h_t) ** 2 / s, rel_tol=1e-9)


def test_the_default_ratio_is_a_receivers_noisier_vertical() -> None:
    cfg = TrackedEstimatorConfig()
    assert 1.5 <= cfg.gnss_up_to_horizontal_vel_std_ratio <= 2.0
    equal = TrackedEstimatorConfig(gnss_up_to_horizontal_vel_std_ratio=1.0, gnss_up_gate_nis=1e9)
    noisier = TrackedEstimatorConfig(gnss_up_gate_nis=1e9)
    # the vertical weighed as noisier: a smaller step toward the fix, more variance left
    step_equal, var_equal = _pitch_after_up_fix(equal)
    step_noisier, var_noisier = _pitch_after_up_fix(noisier)
    assert PITCH_RAD < step_noisier < step_equal
    assert var_noisier > var_equal


def test_the_ratio_is_validated() -> None:
    with pytest.raises(ValueError):
        TrackedEstimatorConfig(gnss_up_to_horizontal_vel_std_ratio=-1.0)
