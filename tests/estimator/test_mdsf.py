"""MDSF equations and matrices, method.md §1 eq. (1)-(7), by hand; config validation."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimator.config import ConfigError, VehicleGeometry, WheeledRearDriveConfig
from estimator.mdsf.model import (
    MdsfConfig,
    MdsfFilter,
    MdsfMode,
    MdsfObs,
    MdsfOut,
    MdsfState,
    gnss_vehicle_speed,
    mdsf_matrices,
    observation_matrix,
    output_matrix,
    product_observation,
    structural_speeds,
    transition_matrix,
)

GEO = VehicleGeometry(h0_m=1.0, h1_m=1.6, track_width_m=1.8)


def test_eq1_vehicle_direction_speed_by_hand() -> None:
    psi, th = math.radians(30.0), math.radians(10.0)
    ve, vn, vu = 1.0, 2.0, 0.5
    expected = ve * 0.5 * math.cos(th) + vn * math.sqrt(3) / 2 * math.cos(th) + vu * math.sin(th)
    assert float(gnss_vehicle_speed(ve, vn, vu, psi, th)) == pytest.approx(expected)
    # heading east, level: Vg is the east component
    assert float(gnss_vehicle_speed(3.0, 1.0, 0.0, math.pi / 2, 0.0)) == pytest.approx(3.0)


def test_eq2_to_5_by_hand() -> None:
    # Vg = 3, ωx = 0.1, ωz = 0.4, h1 = 1.6, h0 = 1.0, b = 1.8
    v1, v0, vl, vr = structural_speeds(3.0, 0.1, 0.4, GEO)
    assert float(v1) == pytest.approx(3.16)  # (2) V1 = Vg + ωx·h1
    assert float(v0) == pytest.approx(3.26)  # (3) V0 = V1 + ωx·h0
    assert float(vl) == pytest.approx(3.26 - 0.36)  # (4) VL = V0 − ωz·b/2
    assert float(vr) == pytest.approx(3.26 + 0.36)  # (5) VR = V0 + ωz·b/2


def test_matrices_exactly_as_written() -> None:
    dt, h0, h1, b = 0.2, 1.0, 1.6, 1.8
    assert np.array_equal(
        transition_matrix(dt), [[1, dt, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    )
    assert np.array_equal(
        observation_matrix(h1), [[1, 0, -h1, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    )
    assert np.array_equal(
        output_matrix(h0, h1, b), [[1, 0, -h1, 0], [1, 0, h0, -b / 2], [1, 0, h0, b / 2]]
    )


def test_paper_mode_uses_source_matrices_and_dt() -> None:
    cfg = MdsfConfig(mode=MdsfMode.PAPER, tick_s=0.05)
    assert cfg.dt_s == 0.2 and cfg.n_state == 4 and cfg.n_obs == 4
    m = mdsf_matrices(cfg, WheeledRearDriveConfig(geometry=GEO))
    assert np.array_equal(m.F, transition_matrix(0.2))
    assert np.array_equal(m.H, observation_matrix(1.6))
    assert np.array_equal(m.H1, output_matrix(1.0, 1.6, 1.8))


def test_product_rows_reduce_to_source_without_offsets() -> None:
    cfg = MdsfConfig()
    m = mdsf_matrices(cfg, WheeledRearDriveConfig(geometry=GEO))
    assert cfg.n_state == 8 and cfg.n_obs == 7
    assert np.array_equal(m.H1[:, :4], output_matrix(1.0, 1.6, 1.8))
    assert np.all(m.H1[:, 4:] == 0)
    assert np.array_equal(m.H[MdsfObs.VG, :4], [1, 0, -1.6, 0])
    # rim speed = wheel ground speed + that wheel's excess
    assert np.array_equal(m.H[MdsfObs.RIM_LEFT], [1, 0, 1.0, -0.9, 0, 1, 0, 0])
    assert np.array_equal(m.H[MdsfObs.RIM_RIGHT], [1, 0, 1.0, 0.9, 0, 0, 1, 0])
    # the RTK distance observes the distance state alone
    assert np.array_equal(m.H[MdsfObs.DIST], [0, 0, 0, 0, 0, 0, 0, 1])
    # V1' = V1 + dt·(ā − b): the bias enters the speed and the acceleration
    assert m.F[MdsfState.V1, MdsfState.ACCEL_BIAS] == pytest.approx(-cfg.tick_s)
    assert m.F[MdsfState.A1, MdsfState.A1] == 0.0
    assert m.F[MdsfState.A1, MdsfState.ACCEL_BIAS] == -1.0


def test_distance_integrates_the_speed() -> None:
    """Hand-computed, dt = 0.1 s: D = 5 m, V1 = 2 m/s, b = 0.2 m/s², ā = 1.2 m/s² (the
    control ``dt²·ā/2 = 0.006 m``): D' = 5 + 0.1·2 − 0.005·0.2 + 0.006 = 5.205 m, which is
    D + dt·V1 + dt²·(ā − b)/2 = 5 + 0.2 + 0.005."""
    cfg = MdsfConfig(tick_s=0.1)
    m = mdsf_matrices(cfg, WheeledRearDriveConfig(geometry=GEO))
    x = np.zeros(cfg.n_state)
    x[MdsfState.DIST], x[MdsfState.V1], x[MdsfState.ACCEL_BIAS] = 5.0, 2.0, 0.2
    u = np.zeros(cfg.n_state)
    u[MdsfState.DIST] = 0.5 * 0.1**2 * 1.2
    assert (m.F @ x + u)[MdsfState.DIST] == pytest.approx(5.205, abs=1e-12)
    assert m.F[MdsfState.DIST, MdsfState.V1] == pytest.approx(0.1)
    assert m.F[MdsfState.DIST, MdsfState.ACCEL_BIAS] == pytest.approx(-0.005)


def test_lever_arms_follow_rigid_body_motion() -> None:
    geo = VehicleGeometry(
        h0_m=1.2,
        h1_m=0.8,
        track_width_m=2.0,
        antenna_offset_m=(0.3, -0.5),
        imu_offset_m=(-0.2, 0.4),
    )
    v0, wx, wz = 2.5, 0.05, 0.3
    omega = np.array([wx, 0.0, wz])

    def fwd(p: np.ndarray) -> float:  # forward speed of body point p: V0·e_Y + ω × p
        return float((np.array([0.0, v0, 0.0]) + np.cross(omega, p))[1])

    p_imu = np.array([-0.2, 0.4, 1.2])
    p_ant = np.array([0.3, -0.5, 2.0])
    x = np.zeros(8)
    x[MdsfState.V1], x[MdsfState.OMEGA_X], x[MdsfState.OMEGA_Z] = fwd(p_imu), wx, wz
    m = mdsf_matrices(MdsfConfig(), WheeledRearDriveConfig(geometry=geo))
    z1 = m.H1 @ x
    assert z1[MdsfOut.VG] == pytest.approx(fwd(p_ant))
    assert z1[MdsfOut.VL] == pytest.approx(fwd(np.array([-1.0, 0.0, 0.0])))
    assert z1[MdsfOut.VR] == pytest.approx(fwd(np.array([1.0, 0.0, 0.0])))
    assert m.v0_row @ x == pytest.approx(v0)
    h = product_observation(geo)
    assert h[MdsfObs.VG] @ x == pytest.approx(fwd(p_ant))


def test_filter_outputs_follow_h1() -> None:
    f = MdsfFilter(MdsfConfig(mode=MdsfMode.PAPER), WheeledRearDriveConfig(geometry=GEO))
    f.initialize(np.array([3.0, 0.2, 0.1, 0.4]), np.eye(4) * 0.01)
    z1, std = f.outputs()
    v1, v0, vl, vr = 3.0, 3.1, 3.1 - 0.36, 3.1 + 0.36
    assert z1 == pytest.approx([v1 - 0.16, vl, vr])
    assert np.all(std > 0)
    assert v0 == pytest.approx(v1 + 0.1 * 1.0)


def test_config_validation() -> None:
    with pytest.raises(ConfigError):
        MdsfConfig(mode="sideways")  # type: ignore[arg-type]
    with pytest.raises(ConfigError):
        MdsfConfig(tick_s=0.0)
    with pytest.raises(ConfigError):
        MdsfConfig(tick_s=2.0)
    with pytest.raises(ConfigError):
        MdsfConfig(gate_chi2=-1.0)
    with pytest.raises(ConfigError):
        MdsfConfig(gnss_noise_adapt=1.5)
    with pytest.raises(ConfigError):
        MdsfConfig(slip_demand_gain=float("inf"))
    assert MdsfConfig(mode="paper").mode is MdsfMode.PAPER  # type: ignore[arg-type]


def test_tyre_gain_settings_are_validated() -> None:
    MdsfConfig(tyre_gain_tau_s=0.0)
    for bad in ((0.0, 2.0), (1.2, 3.0), (0.5, 0.9), (0.5, math.inf)):
        with pytest.raises(ConfigError):
            MdsfConfig(tyre_gain_range=bad)
    with pytest.raises(ConfigError):
        MdsfConfig(tyre_gain_tau_s=-1.0)
    with pytest.raises(ConfigError):
        MdsfConfig(tyre_gain_prior=0.0)
