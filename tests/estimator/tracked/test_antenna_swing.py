"""The mast's swing in the tracked filter: a hull pitching or rolling carries its antenna
forward, sideways and up at the lever arm times the rate, and the fix's velocity says so."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimator.config import TrackedConfig, TrackedGeometry
from estimator.tracked import TrackedEstimatorConfig
from estimator.tracked.model import N_STATES
from estimator.tracked.model import TrackedState as S
from estimator.tracked.params import VehicleParams
from estimator.tracked.step import _fuse_gnss, initial_filter
from tests.estimator.tracked._ticks import quiet_tick

SPEED_MPS, HEADING_RAD = 8.0, 0.7
LEVER_M = (0.3, 1.2, 2.6)  # antenna right, ahead, up of the hull centre


def _offset_enu(theta: float, phi: float) -> np.ndarray:
    """By hand: the antenna's offset from the hull centre (east, north, up), the lever arm
    pitched by ``theta`` (nose up), rolled by ``phi`` (right side down), at ``HEADING_RAD``."""
    x, y, z = LEVER_M
    fwd = y * math.cos(theta) - z * math.sin(theta) * math.cos(phi)
    right = x * math.cos(phi) + z * math.sin(phi)
    up = z * math.cos(theta) * math.cos(phi) + y * math.sin(theta) - x * math.sin(phi)
    s, c = math.sin(HEADING_RAD), math.cos(HEADING_RAD)
    return np.array([right * c + fwd * s, -right * s + fwd * c, up])


def _antenna(theta: float, phi: float, d_theta: float, d_phi: float) -> tuple[np.ndarray, ...]:
    """The antenna's position (east, north), horizontal velocity and up velocity for a hull
    at the origin driving straight at ``SPEED_MPS`` along the ground, its attitude changing
    at ``d_theta``, ``d_phi`` (rad/s): the offset's rate by a central difference."""
    h = 1e-6
    rate = (
        _offset_enu(theta + h * d_theta, phi + h * d_phi)
        - _offset_enu(theta - h * d_theta, phi - h * d_phi)
    ) / (2 * h)
    level = SPEED_MPS * math.cos(theta)
    hull = np.array([level * math.sin(HEADING_RAD), level * math.cos(HEADING_RAD)])
    up = SPEED_MPS * math.sin(theta) + rate[2]
    return _offset_enu(theta, phi)[:2], hull + rate[:2], np.array([up])


def _fused(theta: float, phi: float, pitch_gyro: float, roll_gyro: float, swing: bool) -> float:
    """The largest change of any state after one fix of the antenna (taken at the state's
    instant) whose velocity has the mast's swing (``swing``) or not: the pitch and roll
    rates by hand from the gyros, ``θ̇ = ω_x·cos φ``, ``φ̇ = ω_y + tan θ·ω_x·sin φ`` with the
    yaw gyro at 0. The heading stands (its rate ``−ω_x·sin φ/cos θ`` is 0 in every case: no
    pitch rate on a rolled hull), so the hull's yaw adds nothing; the hull is pitched or
    rolled, not both, where the filter's lever arm ahead (``y·cos θ − z·sin θ``) is the
    exact one."""
    cfg = TrackedEstimatorConfig(gnss_gate_nis=1e9, gnss_up_gate_nis=1e9)
    p = VehicleParams.of(TrackedConfig(geometry=TrackedGeometry(antenna_lever_arm_m=LEVER_M)))
    f = initial_filter(cfg)
    f.started[:] = True
    f.x[0, S.HEADING], f.x[0, S.SPEED] = HEADING_RAD, SPEED_MPS
    f.x[0, S.PITCH], f.x[0, S.ROLL] = theta, phi
    f.P = np.diag(np.full(N_STATES, 1e-4))[None]
    before = f.x[0].copy()
    d_theta = pitch_gyro * math.cos(phi)
    d_phi = roll_gyro + math.tan(theta) * pitch_gyro * math.sin(phi)
    pos, vel, up = _antenna(theta, phi, d_theta if swing else 0.0, d_phi if swing else 0.0)
    inp = quiet_tick(
        1,
        100_000_000,
        pitch_rate_radps=np.array([pitch_gyro]),
        roll_rate_radps=np.array([roll_gyro]),
        gnss_pos_pair_m=pos[None],
        gnss_vel_pair_mps=vel[None],
        gnss_vel_std_mps=np.array([0.03]),
        gnss_vel_up_mps=up,
    )
    lateral = (np.zeros(1), None, None)
    used, _, _ = _fuse_gnss(f, inp, p, cfg, lateral, np.zeros(1), np.zeros(1, bool))
    assert used[0]
    return float(np.abs(f.x[0] - before).max())


@pytest.mark.parametrize(
    ("theta", "phi", "pitch_gyro", "roll_gyro"),
    [
        (0.08, 0.0, 0.05, 0.0),  # pitching over a crest
        (-0.1, 0.0, -0.04, 0.03),  # pitching and rolling, nose down
        (0.0, 0.05, 0.0, 0.04),  # rolling on a side slope
        (0.0, -0.07, 0.0, -0.03),
    ],
)
def test_a_fix_of_a_swinging_mast_moves_no_state(
    theta: float, phi: float, pitch_gyro: float, roll_gyro: float
) -> None:
    assert _fused(theta, phi, pitch_gyro, roll_gyro, swing=True) < 1e-9
    # the same fix without the swing (the mast as if still) is read as a wrong state
    assert _fused(theta, phi, pitch_gyro, roll_gyro, swing=False) > 1e-4
