"""The tilt and heading tracks (estimator/tilt.py): the per-fix updates by hand, the closed-form
tilt between fixes against a fine numerical integration and by hand."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimator._arrays import seg_cumsum
from estimator.mdsf import MdsfConfig, MdsfMode
from estimator.tilt import (
    Integral,
    angle_var_after,
    pitch_fix_update,
    pitch_kf_update,
    shrunk_roll,
    tilt_at,
    tilt_integrals,
    yaw_fix_update,
)

START = 1_767_225_600_000_000_000
S = 1_000_000_000


# -- per-fix updates by hand -------------------------------------------------------------------


def _pitch(cfg: MdsfConfig, **kw: Any) -> tuple[np.ndarray, ...]:
    a = {
        "theta_rad": np.array([0.01]),
        "var_rad2": np.array([4e-6]),
        "bias_radps": np.array([0.005]),
        "fix_ns": np.array([START]),
        "known": np.array([True]),
        "pitch_gnss_rad": np.array([0.03]),
        "stamp_ns": np.array([START + S // 2]),
    }
    a.update({k: np.asarray(v) for k, v in kw.items()})
    return pitch_fix_update(config=cfg, **a)


def test_pitch_fix_update_by_hand() -> None:
    cfg = MdsfConfig(mode=MdsfMode.PAPER)  # pitch_std_rad 0.005
    sp2 = cfg.pitch_std_rad**2
    # the first fix takes the measured pitch as it is
    theta, var, bias, _, known = _pitch(cfg, known=np.array([False]))
    assert theta[0] == 0.03 and var[0] == sp2 and bias[0] == 0.005 and known[0]
    # no GNSS pitch: nothing changes
    out = _pitch(cfg, pitch_gnss_rad=np.array([np.nan]))
    assert out[0][0] == 0.01 and out[1][0] == 4e-6 and out[2][0] == 0.005 and out[3][0] == START
    # paper mode: always the GNSS pitch, no bias
    theta, var, bias, fix_ns, known = _pitch(cfg)
    assert theta[0] == 0.03 and var[0] == sp2 and bias[0] == 0.005
    assert fix_ns[0] == START + S // 2 and known[0]


def test_pitch_fix_update_treats_each_vehicle_on_its_own() -> None:
    cfg = MdsfConfig(mode=MdsfMode.PAPER)
    both = _pitch(
        cfg,
        theta_rad=np.array([0.01, 0.2]),
        var_rad2=np.array([4e-6, 1e-3]),
        bias_radps=np.array([0.005, -0.01]),
        fix_ns=np.array([START, START - S]),
        known=np.array([True, False]),
        pitch_gnss_rad=np.array([0.03, np.nan]),
        stamp_ns=np.array([START + S // 2, START]),
    )
    first = _pitch(cfg)
    assert all(b[0] == f[0] for b, f in zip(both, first, strict=True))
    assert both[0][1] == 0.2 and both[2][1] == -0.01 and not both[4][1]
    assert both[1][1] == 1e-3 and both[3][1] == START - S


def _kf(cfg: MdsfConfig, **kw: Any) -> tuple[np.ndarray, ...]:
    a: dict[str, Any] = {
        "theta_rad": np.array([0.01]),
        "cov": np.array([[4e-6, -1e-7, 1e-6]]),
        "bias_radps": np.array([0.002]),
        "fix_ns": np.array([START]),
        "known": np.array([True]),
        "pitch_gnss_rad": np.array([0.03]),
        "stamp_ns": np.array([START + S // 2]),
    }
    a.update(kw)
    return pitch_kf_update(config=cfg, **a)


def test_pitch_kf_update_by_hand() -> None:
    cfg = MdsfConfig()  # pitch_std_rad 0.005, gyro_bias_walk 1e-4, gyro_bias_std 0.005
    r2, qb, t = cfg.pitch_std_rad**2, cfg.gyro_bias_walk_radps_per_sqrt_s**2, 0.5
    # propagate over 0.5 s with F = [[1, −T], [0, 1]], the bias walk and 1e-6 of angle noise
    ptt = 4e-6 + 2 * t * 1e-7 + t * t * 1e-6 + 1e-6 + qb * t**3 / 3
    ptb = -1e-7 - t * 1e-6 - qb * t * t / 2
    pbb = 1e-6 + qb * t
    theta, cov, bias, fix_ns, known = _kf(cfg, angle_walk_rad2=np.array([1e-6]))
    s = ptt + r2
    assert math.isclose(theta[0], 0.01 + ptt / s * 0.02)
    assert math.isclose(bias[0], 0.002 + ptb / s * 0.02)  # ptb < 0: the bias falls
    assert bias[0] < 0.002
    assert math.isclose(cov[0, 0], ptt - ptt * ptt / s)
    assert math.isclose(cov[0, 1], ptb - ptt * ptb / s)
    assert math.isclose(cov[0, 2], pbb - ptb * ptb / s)
    assert fix_ns[0] == START + S // 2 and known[0]
    # standing since the previous fix: the mean rate 0.0025 is the bias, then the pitch
    zb, rb = 0.0025, 1e-6
    theta, cov, bias, *_ = _kf(
        cfg,
        angle_walk_rad2=np.array([1e-6]),
        still_rate_radps=np.array([zb]),
        still_rate_var=np.array([rb]),
    )
    sb = pbb + rb
    kt, kb = ptb / sb, pbb / sb
    th1, b1 = 0.01 + kt * (zb - 0.002), 0.002 + kb * (zb - 0.002)
    tt1, tb1, bb1 = ptt - kt * ptb, ptb - kt * pbb, pbb - kb * pbb
    s = tt1 + r2
    assert math.isclose(theta[0], th1 + tt1 / s * (0.03 - th1))
    assert math.isclose(bias[0], b1 + tb1 / s * (0.03 - th1))
    assert math.isclose(cov[0, 2], bb1 - tb1 * tb1 / s)
    # a standstill rate far beyond its chi-square bound is not used
    far = _kf(cfg, still_rate_radps=np.array([0.05]), still_rate_var=np.array([rb]))
    base = _kf(cfg)
    assert all(np.array_equal(f, b) for f, b in zip(far, base, strict=True))
    # no GNSS pitch: only the propagation (the time of the fix moves on)
    theta, cov, bias, fix_ns, _ = _kf(cfg, pitch_gnss_rad=np.array([np.nan]))
    assert theta[0] == 0.01 and bias[0] == 0.002 and fix_ns[0] == START + S // 2
    assert math.isclose(cov[0, 0], ptt - 1e-6) and math.isclose(cov[0, 2], pbb)
    # the first pitch is taken as it is, with the bias prior
    theta, cov, bias, _, known = _kf(cfg, known=np.array([False]))
    assert theta[0] == 0.03 and known[0] and bias[0] == 0.002
    assert list(cov[0]) == [r2, 0.0, cfg.gyro_bias_std_radps**2]
    # the measurement's own variance (velocity pitch of a one-antenna receiver)
    theta, *_ = _kf(cfg, pitch_var_rad2=np.array([9 * r2]))
    p0 = 4e-6 + 2 * t * 1e-7 + t * t * 1e-6 + qb * t**3 / 3
    assert math.isclose(theta[0], 0.01 + p0 / (p0 + 9 * r2) * 0.02)


def test_angle_var_after_by_hand() -> None:
    # P = [4e-6, -1e-7, 1e-8] (rad², rad²/s, rad²/s²), T = 10 s, walk 1e-4 rad/s/√s:
    # 4e-6 + 2·10·1e-7 + 100·1e-8 + 1e-8·1000/3 = 4e-6 + 2e-6 + 1e-6 + 3.333e-6
    cov = np.array([[4e-6, -1e-7, 1e-8], [4e-6, -1e-7, 1e-8]])
    got = angle_var_after(cov, np.array([10.0, 0.0]), 1e-4)
    assert got[0] == pytest.approx(1.0333333e-5, rel=1e-6)
    assert got[1] == pytest.approx(4e-6)  # at the fix: its own variance


def test_yaw_fix_update_by_hand() -> None:
    cfg = MdsfConfig()  # attitude_tau_s 1, gyro_bias_tau_s 5
    psi, bias, fix_ns = yaw_fix_update(
        np.array([0.1, np.nan, 3.1]),
        np.array([0.0, 0.0, 0.01]),
        np.array([START, START, START]),
        np.array([0.2, 1.0, -3.1]),
        np.array([START + S // 2, START + S // 2, START + 3 * S]),
        cfg,
    )
    assert math.isclose(psi[0], 0.1 + (1 - math.exp(-0.5)) * 0.1)
    assert math.isclose(bias[0], 0.5 / 5.0 * 0.1)
    assert psi[1] == 1.0 and bias[1] == 0.0  # unknown heading: set to the GNSS one
    # the error is wrapped to ±π (3.1 → −3.1 is 0.083 rad ahead) and the gap clipped to 1 s
    err = 2 * math.pi - 6.2
    assert math.isclose(psi[2], 3.1 + (1 - math.exp(-1.0)) * err)
    assert math.isclose(bias[2], 0.01 + 1.0 / 5.0 * err)
    assert list(fix_ns) == [START + S // 2, START + S // 2, START + 3 * S]


# -- between fixes -----------------------------------------------------------------------------


def _integrals(wx: np.ndarray, wy: np.ndarray, wz: np.ndarray, dt_s: float) -> Any:
    n = wx.shape[0]
    zeros = np.zeros(n)
    return tilt_integrals(
        np.full(n, dt_s), wx, wy, wz, zeros, zeros, zeros, np.zeros(n, dtype=np.int64), True
    )


def test_a_turn_turns_the_roll_into_pitch() -> None:
    """Roll α, no pitch, turning at ``r`` about the body's Z axis with level gyros: ``ż = −i·r·z``
    so ``z = e^{−irt}·iα``; a quarter turn makes it pitch ``α``, a half turn roll ``−α``."""
    alpha, rate, dt = 0.1, 0.5, 0.001
    n = round(math.pi / rate / dt)
    cum, _, rot = _integrals(np.zeros(n), np.zeros(n), np.full(n, rate), dt)
    one = np.ones(1, dtype=bool)
    quarter = tilt_at(
        cum, rot, np.array([n // 2 - 1]), np.array([1j * alpha]), np.zeros(1) + 0j, one, True
    )
    half = tilt_at(cum, rot, np.array([n - 1]), np.array([1j * alpha]), np.zeros(1) + 0j, one, True)
    assert abs(quarter[0] - alpha) < 1e-3
    assert abs(half[0] + 1j * alpha) < 1e-3


def test_uncoupled_tilt_is_the_integrated_pitch_rate_by_hand() -> None:
    wx = np.array([0.1, 0.2, -0.1])
    cum, _, rot = _integrals(wx, np.ones(3), np.ones(3), 0.1)
    z = tilt_at(
        cum,
        rot,
        slice(None),
        np.full(3, 0.05 + 0.02j),
        np.full(3, 0.01 + 0j),
        np.zeros(3, dtype=bool),
        True,
    )
    np.testing.assert_allclose(z.real, 0.05 + np.cumsum(wx) * 0.1 - 0.01 * np.arange(1, 4) * 0.1)
    np.testing.assert_array_equal(z.imag, np.full(3, 0.02))


@settings(max_examples=30, deadline=None)
@given(
    st.lists(st.tuples(*[st.floats(-0.5, 0.5)] * 3), min_size=1, max_size=8),
    st.floats(-0.1, 0.1),
    st.floats(-0.1, 0.1),
    st.floats(-0.01, 0.01),
    st.floats(-0.01, 0.01),
)
def test_closed_form_tilt_solves_the_linear_kinematics(
    rates: list[tuple[float, float, float]], th0: float, ph0: float, bx: float, by: float
) -> None:
    """Piecewise-constant rates over 0.1 s steps: the closed form against the exact solution of
    ``ż = (ωx − b_x) + i·(ωy − b_y) − i·ωz·z`` over each step (``z' = e^{−iωz·dt}·z +
    (1 − e^{−iωz·dt})/(iωz)·w``)."""
    dt = 0.1
    w = np.array(rates)
    cum, _, rot = _integrals(w[:, 0], w[:, 1], w[:, 2], dt)
    n = w.shape[0]
    got = tilt_at(
        cum,
        rot,
        slice(None),
        np.full(n, th0 + 1j * ph0),
        np.full(n, bx + 1j * by),
        np.ones(n, dtype=bool),
        True,
    )
    z = complex(th0, ph0)
    drive_max = max(abs(complex(wx - bx, wy - by)) for wx, wy, _ in rates)
    for i, (wx, wy, wz) in enumerate(rates):
        drive = complex(wx - bx, wy - by)
        if abs(wz) > 1e-9:
            z = np.exp(-1j * wz * dt) * z + (1 - np.exp(-1j * wz * dt)) / (1j * wz) * drive
        else:
            z = z + dt * drive
        # the closed form weighs each step's rate with the turn at the step's end: off by at
        # most |ωz·dt|/2 of the step's drive per step
        assert abs(got[i] - z) <= 0.026 * dt * (i + 1) * drive_max + 1e-12


def test_shrunk_roll_and_seg_cumsum_by_hand() -> None:
    got = shrunk_roll(np.array([0.1, np.nan, 0.0, -0.02]), np.array([0.01, 1.0, 1.0, 0.0004]))
    np.testing.assert_allclose(got, [0.1 * 0.01 / 0.02, 0.0, 0.0, -0.02 * 0.0004 / 0.0008])
    x = np.array([1.0, 2.0, 3.0, 4.0, 5.0])
    np.testing.assert_array_equal(seg_cumsum(x, np.array([0, 0, 2, 2, 2])), [1, 3, 3, 7, 12])
    assert Integral.TIME == 0 and len(Integral) == 13
