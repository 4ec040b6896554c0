"""The slip-step test inside a GNSS outage (:mod:`estimator.mdsf.outage_step`), by hand.

Windows of ``r`` (rims less the inertial speed), ``V1`` and ``ωz`` built from a known
step, an inertial drift and a turn: the step is found at its tick with its size, the drift
and the turn are not.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from estimator.mdsf import MdsfConfig, MdsfFleet
from estimator.mdsf.outage_step import StepBuf, StepPrior, step_test
from estimator.sim import simulate, truth_at
from tests.support import replay_in_order

DT = 0.1
N = 60
START = 1_767_225_600_000_000_000


def _windows(r: np.ndarray, v1: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """Every window of N ticks of the series, (len − N + 1, C, N)."""
    m = r.shape[0] - N + 1
    buf = np.zeros((m, len(StepBuf), N))
    for i in range(m):
        buf[i, StepBuf.R] = r[i : i + N]
        buf[i, StepBuf.V1] = v1[i : i + N]
        buf[i, StepBuf.YAW] = yaw[i : i + N]
        buf[i, StepBuf.OK] = 1.0
    return buf


def test_a_step_on_a_trend_is_found_at_its_tick_with_its_size() -> None:
    rng = np.random.default_rng(3)
    n, at, delta = 200, 120, 0.04
    t = np.arange(n) * DT
    v1 = np.full(n, 2.0)
    r = 0.01 + 0.004 * t + delta * v1 * (np.arange(n) >= at) + rng.normal(0, 0.004, n)
    fit = step_test(_windows(r, v1, np.zeros(n)), DT, StepPrior())
    middles = np.arange(fit.z.shape[0]) + N // 2
    assert middles[np.argmax(np.abs(fit.z))] == at
    assert fit.found[at - N // 2]
    assert fit.delta[at - N // 2] == pytest.approx(delta, abs=0.004)
    # shrunk toward 0 by the prior, never beyond the raw step
    assert abs(fit.delta[at - N // 2]) < delta + 3 * np.sqrt(fit.delta_var[at - N // 2])
    # far from the step (its tick outside the window) nothing is found
    far = (middles < at - N // 2) | (middles >= at + N // 2)
    assert not fit.found[far].any()


def test_an_inertial_drift_alone_is_not_found() -> None:
    # A bias that walks: r is its integral, a curve, plus the integrated accelerometer noise.
    rng = np.random.default_rng(5)
    n = 400
    t = np.arange(n) * DT
    bias = 0.02 + np.cumsum(rng.normal(0, 0.002 * np.sqrt(DT), n))
    r = np.cumsum(bias) * DT + np.cumsum(rng.normal(0, 0.003, n)) + rng.normal(0, 0.004, n)
    v1 = 2.0 + 0.3 * np.sin(0.2 * t)
    fit = step_test(_windows(r, v1, np.zeros(n)), DT, StepPrior())
    assert not fit.found.any()
    assert np.abs(fit.z).max() < StepPrior().z_min


def test_a_turns_yaw_driven_change_is_not_found() -> None:
    # A turn entered within half a second at 0.35 rad/s: the slip follows the lateral load
    # (2.1 pp at 2 m/s) and a 1° yaw misalignment leaks the lateral acceleration V1·ωz into
    # ā. Without the turn regressors (their priors ~0) that reads as a step.
    rng = np.random.default_rng(7)
    n = 160
    i = np.arange(n)
    yaw = 0.35 * np.clip((i - 78) / 5.0, 0.0, 1.0)
    v1 = np.full(n, 2.0)
    misalign = np.deg2rad(1.0)
    r = misalign * np.cumsum(v1 * yaw) * DT + 0.06 * v1 * yaw + rng.normal(0, 0.004, n)
    buf = _windows(r, v1, yaw)
    fit = step_test(buf, DT, StepPrior())
    assert not fit.found.any()
    blind = dataclasses.replace(StepPrior(), load_s=1e-6, yaw_rad=1e-6, cent_m=1e-6)
    assert step_test(buf, DT, blind).found.any()


def _turn_with_a_tilt_error(tilt_rad: float, step: float, seed: int) -> np.ndarray:
    """Windows of a U-turn at 0.25 rad/s entered at tick 70 (2 m/s) with a level-frame pitch
    and roll error, each ``tilt_rad``, leaking ``g·(θ·(cos ψ − 1) + φ·sin ψ)`` into ``ā`` as
    the heading turns, and a slip step ``step`` at tick 80, the turn's middle."""
    rng = np.random.default_rng(seed)
    n = 160
    i = np.arange(n)
    yaw = 0.25 * np.clip((i - 70) / 3.0, 0.0, 1.0)
    psi = np.cumsum(yaw) * DT
    v1 = np.full(n, 2.0)
    leak = np.cumsum(9.80665 * tilt_rad * (np.cos(psi) - 1.0 + np.sin(psi))) * DT
    r = leak + step * v1 * (i >= 80) + rng.normal(0, 0.004, n)
    return _windows(r, v1, yaw)


def _with_tilt_std(buf: np.ndarray, std_rad: float) -> np.ndarray:
    out = buf.copy()
    out[:, StepBuf.PITCH_VAR] = std_rad**2
    out[:, StepBuf.ROLL_VAR] = std_rad**2
    return out


def test_the_tilt_prior_is_the_windows_own_tilt_variance() -> None:
    # A 2° pitch and roll error turning with the heading, no step: a tilt track that says it
    # may be off by that much lets the tilt columns take the leak; one that says 0.1° does
    # not, and the leak reads as a step. The window's variance decides, not StepPrior.tilt_rad.
    buf = _turn_with_a_tilt_error(np.deg2rad(2.0), 0.0, 11)
    loose = step_test(_with_tilt_std(buf, np.deg2rad(2.0)), DT, StepPrior())
    tight = step_test(_with_tilt_std(buf, np.deg2rad(0.1)), DT, StepPrior())
    assert not loose.found.any()
    assert tight.found.any()
    # NaN (no tilt track): the prior's constant, as loose here
    assert not step_test(_with_tilt_std(buf, np.nan), DT, StepPrior()).found.any()


def test_a_step_in_a_turn_is_found_whole_when_the_tilt_is_well_known() -> None:
    # A +4 pp step in the middle of a U-turn, the tilt right: with the receiver's attitude
    # (0.1°) the step is found at its size and known better than under a 2° tilt prior, whose
    # columns share the jump's uncertainty.
    buf = _turn_with_a_tilt_error(0.0, 0.04, 13)
    at = 80 - N // 2
    known = step_test(_with_tilt_std(buf, np.deg2rad(0.1)), DT, StepPrior())
    loose = step_test(_with_tilt_std(buf, np.deg2rad(2.0)), DT, StepPrior())
    assert known.found[at]
    assert known.delta[at] == pytest.approx(0.04, abs=0.006)
    assert known.delta_var[at] < 0.85 * loose.delta_var[at]


def _slip_rms_after_step(config: MdsfConfig) -> float:
    """``field_work`` (seed 1) with GNSS lost 60-85 s and a +6 pp slip step at 70 s: the left
    wheel's slip RMS over 75-85 s (the step found) [pp]."""
    sim = simulate(
        "field_work",
        seed=1,
        start_ns=START,
        gnss_outages=((60.0, 85.0),),
        slip_steps=((70.0, 6.0, 0.0),),
    )
    cfg = dataclasses.replace(sim.config, noise=sim.sensor_noise)
    fleet = MdsfFleet(config)
    fleet.add_vehicle("v", cfg)
    rows = replay_in_order(
        sim,
        lambda m: fleet.push("v", m),
        lambda until: [rows for _, rows in fleet.advance({"v": until})],
    )
    t_s = (rows["stamp_ns"] - START) * 1e-9
    sel = (t_s > 75.0) & (t_s < 85.0) & np.isfinite(rows["slip_left_pct"])
    err = rows["slip_left_pct"][sel] - truth_at(sim.truth, rows["stamp_ns"][sel], "slip_left_pct")
    assert sel.sum() > 80
    return float(np.sqrt(np.mean(err**2)))


def test_a_slip_step_in_an_outage_moves_the_slip_not_the_speed() -> None:
    # Without the test the outage's slip reverts to its level before the step and the rims
    # carry the speed: the slip reads the step's size off. With it the step is found half a
    # window (3 s) after it, and the slip follows from then on.
    off = _slip_rms_after_step(MdsfConfig(outage_step_window_s=0.0))
    on = _slip_rms_after_step(MdsfConfig())  # the test is on by default
    assert off > 4.0
    assert on < 0.5 * off and on < 3.0  # measured 2.22 pp (off: 7.29)


def _step_window() -> np.ndarray:
    """The one window (1, C, N) centred on a 4 % step on a trend at 2 m/s, with noise."""
    rng = np.random.default_rng(3)
    n, at, delta = 200, 120, 0.04
    t = np.arange(n) * DT
    v1 = np.full(n, 2.0)
    r = 0.01 + 0.004 * t + delta * v1 * (np.arange(n) >= at) + rng.normal(0, 0.004, n)
    return _windows(r, v1, np.zeros(n))[at - N // 2 : at - N // 2 + 1]


def test_a_degenerate_window_finds_nothing_and_leaves_the_others_as_alone() -> None:
    # A window with no usable row (no rim read for its length) makes the regression's
    # matrix singular (level and trend have no prior); batched with a window holding a
    # step, it must not raise, must find nothing itself, and the step's window must be
    # solved as on its own.
    step = _step_window()
    still = _windows(np.zeros(N), np.full(N, 2.0), np.zeros(N))
    still[:, StepBuf.OK] = 0.0
    both = step_test(np.concatenate([still, step]), DT, StepPrior())
    alone = step_test(step, DT, StepPrior())
    assert not both.found[0]
    assert both.found[1] and alone.found[0]
    assert both.delta[1] == alone.delta[0] and both.delta_var[1] == alone.delta_var[0]


def test_a_window_whose_fit_overflows_finds_nothing_and_leaves_the_others_as_alone() -> None:
    # A corrupted sensor can put the rims-less-inertial residual far outside any drive's
    # (here 1e200 m/s on a few ticks): its squares overflow. That window must find nothing,
    # without a warning (an error under the tests' filterwarnings), and a window holding a
    # step batched with it must be solved as on its own.
    step = _step_window()
    wild = step.copy()
    wild[0, StepBuf.R, N // 2 : N // 2 + 3] = 1e200
    both = step_test(np.concatenate([wild, step]), DT, StepPrior())
    alone = step_test(step, DT, StepPrior())
    assert not both.found[0] and both.delta[0] == 0.0
    assert both.found[1] and alone.found[0]
    assert both.delta[1] == alone.delta[0] and both.delta_var[1] == alone.delta_var[0]


def _creep_shift(rim_std_mps: float) -> np.ndarray:
    """Windows of a creep at 0.5 m/s whose rims shift by 30 mm/s for good at tick 100 (6 pp of
    the speed) on 4 mm/s of white scatter, the rims' reported std ``rim_std_mps`` each."""
    rng = np.random.default_rng(11)
    n = 200
    v1 = np.full(n, 0.5)
    r = 0.03 * (np.arange(n) >= 100) + rng.normal(0, 0.004, n)
    buf = _windows(r, v1, np.zeros(n))
    buf[:, StepBuf.RIM_VAR] = rim_std_mps**2 / 2.0
    return buf


def test_a_shift_within_the_rims_own_noise_is_not_taken_while_creeping() -> None:
    # The same 30 mm/s shift: a step when the rims are known to a few mm/s, not when each
    # reading is known to 50 mm/s (a coarse ring's few edges per fit at creeping speed).
    assert step_test(_creep_shift(0.004), DT, StepPrior()).found.any()
    assert not step_test(_creep_shift(0.05), DT, StepPrior()).found.any()


def test_a_step_well_above_the_rims_noise_is_still_taken_on_a_coarse_ring() -> None:
    # 2 pp at 2 m/s (40 mm/s) on 10 mm/s of scatter, each rim reported to 30 mm/s (a coarse
    # ring at speed): the step moves the rims by more than a reading scatters, so it is taken
    # as it would be with the rims known exactly; the rims' std is not the fit's noise.
    rng = np.random.default_rng(13)
    n = 200
    v1 = np.full(n, 2.0)
    r = 0.02 * v1 * (np.arange(n) >= 100) + rng.normal(0, 0.01, n)
    buf = _windows(r, v1, np.zeros(n))
    exact = step_test(buf, DT, StepPrior())
    buf[:, StepBuf.RIM_VAR] = 0.03**2 / 2.0
    coarse = step_test(buf, DT, StepPrior())
    assert exact.found[100 - N // 2]
    np.testing.assert_array_equal(coarse.found, exact.found)


def test_a_few_ticks_of_a_wheel_restarting_do_not_mask_a_step() -> None:
    # The rims known to 4 mm/s but for 5 ticks of a restart reported at 0.5 m/s: the step's
    # speed change is weighed against a typical reading, not against those few.
    buf = _creep_shift(0.004)
    plain = step_test(buf, DT, StepPrior())
    buf[:, StepBuf.RIM_VAR, :5] = 0.5**2 / 2.0
    restart = step_test(buf, DT, StepPrior())
    assert plain.found.any()
    np.testing.assert_array_equal(restart.found, plain.found)
