"""The lateral accelerometer's centripetal force observes the yaw gyro: ``f_x = −ω·V − g·cos θ·
sin φ + b_x`` with ``ω = (g_z − b_g)·(1 − s_g)``, so the row of
:func:`~estimator.tracked.step._fuse_lateral_force` carries ``∂h/∂b_g = V·(1 − s_g)`` and
``∂h/∂s_g = V·(g_z − b_g)`` beside the roll's and the bias's."""

from __future__ import annotations

import math

import numpy as np

from estimator.config import TrackedConfig
from estimator.tracked import TrackedEstimatorConfig
from estimator.tracked.filter import GRAVITY_MPS2
from estimator.tracked.model import N_STATES
from estimator.tracked.model import TrackedState as S
from estimator.tracked.params import VehicleParams
from estimator.tracked.step import _fuse_lateral_force, initial_filter
from tests.estimator.tracked._ticks import quiet_tick

DT = 0.1


def _moving(speed_mps: float, variances: dict[S, float]) -> tuple:
    cfg = TrackedEstimatorConfig()
    p = VehicleParams.of(TrackedConfig())
    f = initial_filter(cfg)
    f.x[0] = 0.0
    f.x[0, S.SPEED] = speed_mps
    diag = np.full(N_STATES, 1e-12)
    for index, var in variances.items():
        diag[index] = var
    f.P = np.diag(diag)[None]
    return cfg, p, f


def _noise_var(cfg: TrackedEstimatorConfig, p: VehicleParams, samples: int) -> float:
    return float(p.accel_std_mps2[0] ** 2 / samples + cfg.lateral_force_std_mps2**2)


def test_a_straight_drive_whose_gyro_reads_a_rate_moves_the_gyro_bias_by_its_kalman_share() -> None:
    # 10 m/s straight on level ground: no centripetal force, the gyro reading 2 mrad/s; the
    # filter (bias 0) expects −ω·V = −0.02 m/s², and shares the 0.02 m/s² between the lateral
    # bias, the roll, the speed and the gyro's bias by their variances times their rows
    v, gyro = 10.0, 2e-3
    var = {S.GYRO_BIAS: 1e-6, S.ACCEL_BIAS_X: 1e-4, S.ROLL: 1e-6, S.SPEED: 1e-4}
    cfg, p, f = _moving(v, var)
    inp = quiet_tick(1, int(DT * 1e9), gyro_radps=np.array([gyro]), lateral_accel_mps2=np.zeros(1))
    _fuse_lateral_force(f, inp, p, cfg, np.array([gyro]))
    y = gyro * v
    rows = {S.GYRO_BIAS: v, S.ACCEL_BIAS_X: 1.0, S.ROLL: -GRAVITY_MPS2, S.SPEED: -gyro}
    s = sum(rows[i] ** 2 * var[i] for i in rows) + _noise_var(cfg, p, 10)
    assert math.isclose(f.x[0, S.GYRO_BIAS], var[S.GYRO_BIAS] * v * y / s, rel_tol=1e-6)
    assert f.x[0, S.GYRO_BIAS] > 0.0  # towards the bias the gyro shows


def test_a_turns_centripetal_force_moves_the_gyro_scale() -> None:
    # a turn at 0.2 rad/s and 5 m/s read 1 % high by the gyro: the accelerometer reads the
    # true −ω·V = −1.0 m/s², the filter expects −1.01 m/s²; the scale takes its share
    v, w = 5.0, 0.2
    gyro = 1.01 * w
    var = {S.GYRO_SCALE: 1e-4, S.ROLL: 1e-6}
    cfg, p, f = _moving(v, var)
    inp = quiet_tick(
        1, int(DT * 1e9), gyro_radps=np.array([gyro]), lateral_accel_mps2=np.array([-w * v])
    )
    _fuse_lateral_force(f, inp, p, cfg, np.array([gyro]))
    y = -w * v + gyro * v
    rows = {S.GYRO_SCALE: v * gyro, S.ROLL: -GRAVITY_MPS2}
    s = sum(rows[i] ** 2 * var[i] for i in rows) + _noise_var(cfg, p, 10)
    assert math.isclose(f.x[0, S.GYRO_SCALE], var[S.GYRO_SCALE] * v * gyro * y / s, rel_tol=1e-6)
    assert f.x[0, S.GYRO_SCALE] > 0.0  # ω = g_z·(1 − s): a gyro reading high has s > 0
