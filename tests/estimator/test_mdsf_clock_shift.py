"""What a GNSS clock offset makes of a fix's speed and of the RTK distance
(:mod:`estimator.mdsf.clock_shift`): the shift against the antenna's true speed change on
hand-made body rates, under noise, ahead of the newest tick, and the batched call against
one slot at a time."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimator.config import VehicleGeometry, WheeledRearDriveConfig
from estimator.mdsf.clock_shift import GnssClockShift, _node_weights
from estimator.mdsf.frontend import FleetFrontEnd
from estimator.mdsf.model import MdsfConfig
from estimator.wheel_speed import WheelSpeedConfig

_DT = 0.1
_SLOT = np.array([0])
_START_NS = 1_700_000_000_000_000_000


def _shift_and_front(*geos: VehicleGeometry) -> tuple[GnssClockShift, FleetFrontEnd]:
    """A shift and the front end that holds the geometry it reads, one slot per ``geos``."""
    config = MdsfConfig()
    shift, front = GnssClockShift(config), FleetFrontEnd(config, WheelSpeedConfig())
    for slot, geo in enumerate(geos):
        shift.add(slot)
        front.add(slot, WheeledRearDriveConfig(geometry=geo))
    return shift, front


def _shift(
    shift: GnssClockShift, front: FleetFrontEnd, offset_s: float, age_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """One tick's shift and variance of slot 0's fix ``age_s`` old under ``offset_s`` (the
    offset's std 0), as the fleet takes them: rates at the fix, sway powers, shift."""
    fix = shift.fix_rates(_SLOT, np.array([offset_s]), np.array([age_s]), front)
    shift.record_sway(_SLOT, fix)
    return shift.shift_mps(_SLOT, fix, np.array([0.0]))


def _shift_with_sway(offset_s: float, age_s: float) -> tuple[float, float, float]:
    """:class:`GnssClockShift` fed 1 Hz pitch sway ``ωx = 0.4·sin(2π·t)`` rad/s, a yaw rate
    ``ωz = 0.1·sin(0.5·t)`` and a speed at ``O`` rising 0.5 m/s² on ticks to 3 s, the antenna
    3.5 m up and 0.4 m right: its shift and variance for a fix ``age_s`` before the last
    tick under ``offset_s``, and the antenna's true speed change over that offset."""
    geo = VehicleGeometry(h0_m=1.0, h1_m=2.5, antenna_offset_m=(0.4, 0.0))
    shift, front = _shift_and_front(geo)

    def wx(t: float) -> float:
        return 0.4 * math.sin(2.0 * math.pi * t)

    def wz(t: float) -> float:
        return 0.1 * math.sin(0.5 * t)

    for k in range(31):
        t = k * _DT
        shift.record_rates(
            _SLOT, np.array([_START_NS + k * 100_000_000]), np.array([[wx(t), wz(t)]])
        )
        shift.record_speed(_SLOT, np.array([1.0 + 0.5 * t]), np.array([True]))
    got, var = _shift(shift, front, offset_s, age_s)
    t_fix, t_was = 3.0 - age_s, 3.0 - age_s - offset_s
    true = 0.5 * offset_s + 0.4 * (wz(t_fix) - wz(t_was)) - 3.5 * (wx(t_fix) - wx(t_was))
    return float(got[0]), float(var[0]), true


@pytest.mark.parametrize(("offset_s", "age_s"), [(0.07, 0.03), (0.09, 0.08), (0.03, 0.0)])
def test_gnss_clock_shift_is_the_antennas_speed_change(offset_s: float, age_s: float) -> None:
    """A fix describing an instant within the history: the shift is the antenna's speed
    change over the offset (sway ``(h0 + h1)·Δωx`` of up to 2.5 m/s here, yaw and the
    speed's rate) to 2 cm/s; the tick-mean acceleration's ``δ·a`` misses the mast's sway."""
    got, var, true = _shift_with_sway(offset_s, age_s)
    assert abs(true) > 0.2
    assert abs(got - true) < 0.02
    assert var == 0.0


@pytest.mark.parametrize(("offset_s", "age_s"), [(-0.06, 0.0), (-0.09, 0.02)])
def test_gnss_clock_shift_ahead_of_the_last_tick(offset_s: float, age_s: float) -> None:
    """A GNSS clock behind the IMU's: the fix describes an instant after the last tick; the
    rates are carried on by their slope, the error within 3σ of the variance returned."""
    got, var, true = _shift_with_sway(offset_s, age_s)
    assert var > 0.0
    assert abs(got - true) < 3.0 * math.sqrt(var)
    assert abs(got - true) < 0.25 * abs(true)


def _slow_sway_shifts(gyro_std_radps: float, offset_s: float) -> tuple[np.ndarray, np.ndarray]:
    """:class:`GnssClockShift` over 60 s of a 0.35 Hz pitch sway ``ωx = 0.1·sin(2π·0.35·t)``
    rad/s on a 4.5 m antenna (1.6 m cab, 2.9 m mast) at a steady crawl, each tick's rates
    with white noise of ``gyro_std_radps`` (seeded) and that variance given: per tick the
    shift of a fix 30 ms before its tick and the antenna's true speed change over the offset
    (the last 40 s)."""
    geo = VehicleGeometry(h0_m=1.6, h1_m=2.9)
    shift, front = _shift_and_front(geo)
    rng = np.random.default_rng(5)

    def wx(t: float) -> float:
        return 0.1 * math.sin(2.0 * math.pi * 0.35 * t)

    got, true = [], []
    for k in range(600):
        t = k * _DT
        rate = np.array([[wx(t) + rng.normal(0.0, gyro_std_radps), 0.0]])
        shift.record_rates(
            _SLOT, np.array([_START_NS + k * 100_000_000]), rate, np.array([gyro_std_radps**2])
        )
        shift.record_speed(_SLOT, np.array([0.4]), np.array([True]))
        value, _ = _shift(shift, front, offset_s, 0.03)
        got.append(float(value[0]))
        true.append(-4.5 * (wx(t - 0.03) - wx(t - 0.03 - offset_s)))
    return np.array(got[200:]), np.array(true[200:])


@pytest.mark.parametrize("offset_s", [-0.0885, 0.07])
def test_gnss_clock_shift_under_noisy_rates_beats_no_shift(offset_s: float) -> None:
    """A 0.35 Hz sway on a 4.5 m antenna moves the fix by ~4 cm/s RMS over a 70-90 ms
    offset; the tick rates' noise (6 mrad/s), carried through the cubic (and ~3× by its
    slope ahead of the newest tick) and times 4.5 m, was larger than that (held-out 1004
    drive 1 read its fixes worse moved than not). Applied by the Wiener gain, the shift's
    error is below the uncorrected one (the whole change; 0.050 against 0.062 m/s ahead of
    the newest tick, where the whole shift read 0.078), and without noise it is whole."""
    got, true = _slow_sway_shifts(0.006, offset_s)
    assert np.sqrt(np.mean((got - true) ** 2)) < 0.9 * np.sqrt(np.mean(true**2))
    clean, true = _slow_sway_shifts(0.0, offset_s)
    assert np.sqrt(np.mean((clean - true) ** 2)) < 0.1 * np.sqrt(np.mean(true**2))


def test_the_distance_clock_correction_follows_the_filters_speed() -> None:
    """The converged offset moves the RTK distance by ``δ·(V1(t) − V1(t0))`` over its chain;
    summed per tick, ``imu_speed_step_mps`` is that change of the IMU point's speed from the
    filter's speed at ``O`` (rising 0.4 → 0.8 m/s over 20 s here) and the IMU's sway
    ``−h0·Δωx`` (0.35 Hz, 1.6 m), with no accelerometer in it: ``δ·∫a1·dt`` carried the
    accelerometer's bias and gravity leak for as long as a chain lasts (held-out 1004 drive
    1, a crawl with a converged −94 ms: 2.46 → 3.66 pp; 2.50 from the filter's speed)."""
    geo = VehicleGeometry(h0_m=1.6, h1_m=2.9, imu_offset_m=(0.2, 0.0))
    shift, front = _shift_and_front(geo)

    def wx(t: float) -> float:
        return 0.1 * math.sin(2.0 * math.pi * 0.35 * t)

    def wz(t: float) -> float:
        return 0.05 * math.sin(0.3 * t)

    def v1(t: float) -> float:
        return 0.4 + 0.02 * t + 0.2 * wz(t) - 1.6 * wx(t)

    total = 0.0
    for k in range(201):
        t = k * _DT
        shift.record_rates(
            _SLOT, np.array([_START_NS + k * 100_000_000]), np.array([[wx(t), wz(t)]])
        )
        if k >= 5:
            total += float(shift.imu_speed_step_mps(_SLOT, front)[0])
        shift.record_speed(_SLOT, np.array([0.4 + 0.02 * t]), np.array([True]))
    # from the tick before the first summed one; the low-pass of the rate (0.3 s) lags 2.5 mm/s
    assert abs(total - (v1(20.0) - v1(0.4))) < 0.004


def test_batched_fixes_equal_one_slot_at_a_time() -> None:
    """Three vehicles of other geometry, fixes of other ages, one without offset, through one
    call (the node weights of all instants at once) give what each gives alone: the shift,
    its variance and the mast's distance term, bit for bit."""
    geos = (
        VehicleGeometry(h0_m=1.0, h1_m=2.5, antenna_offset_m=(0.4, 0.0)),
        VehicleGeometry(h0_m=1.6, h1_m=2.9, imu_offset_m=(0.2, 0.0)),
        VehicleGeometry(h0_m=0.8, h1_m=1.2, antenna_offset_m=(-0.3, 0.1)),
    )
    offset_s = np.array([0.07, 0.0, -0.05])
    age_s = np.array([0.03, 0.08, np.nan])
    applied = np.array([True, False, True])
    rng = np.random.default_rng(3)
    rates = rng.normal(0.0, 0.2, (12, 3, 2))
    slots = np.arange(3)
    together, front = _shift_and_front(*geos)
    alone = [_shift_and_front(geo) for geo in geos]
    for k in range(12):
        stamp = np.full(3, _START_NS + k * 100_000_000)
        together.record_rates(slots, stamp, rates[k], np.full(3, 1e-4))
        together.record_speed(slots, 1.0 + 0.1 * k * np.arange(1, 4), np.ones(3, bool))
        for i, (one, _) in enumerate(alone):
            one.record_rates(_SLOT, stamp[:1], rates[k, i : i + 1], np.full(1, 1e-4))
            one.record_speed(_SLOT, np.array([1.0 + 0.1 * k * (i + 1)]), np.ones(1, bool))
    fix = together.fix_rates(slots, offset_s, age_s, front)
    together.record_sway(slots, fix)
    got = together.shift_mps(slots, fix, np.full(3, 0.004))
    mast = together.mast_shift_m(slots, fix, applied, front)
    assert np.any(got[0] != 0.0) and np.any(mast != 0.0)
    for i, (one, one_front) in enumerate(alone):
        fix1 = one.fix_rates(_SLOT, offset_s[i : i + 1], age_s[i : i + 1], one_front)
        one.record_sway(_SLOT, fix1)
        shift1, var1 = one.shift_mps(_SLOT, fix1, np.full(1, 0.004))
        assert shift1[0] == got[0][i] and var1[0] == got[1][i]
        assert one.mast_shift_m(_SLOT, fix1, applied[i : i + 1], one_front)[0] == mast[i]


def test_without_offset_a_fix_is_not_moved() -> None:
    """No offset: all three instants are the fix's own, so the sway part, its noise and the
    shift are 0 even under a 1 Hz sway on a 3.5 m antenna and noisy rates."""
    shift, front = _shift_and_front(VehicleGeometry(h0_m=1.0, h1_m=2.5))
    for k in range(8):
        rate = np.array([[0.4 * math.sin(2.0 * math.pi * k * _DT), 0.05]])
        shift.record_rates(_SLOT, np.array([_START_NS + k * 100_000_000]), rate, np.array([1e-4]))
        shift.record_speed(_SLOT, np.array([2.0 + 0.3 * k * _DT]), np.array([True]))
    fix = shift.fix_rates(_SLOT, np.array([0.0]), np.array([0.04]), front)
    assert fix.lever_mps[0] == 0.0 and fix.noise_var[0] == 0.0
    assert np.array_equal(fix.at_fix, fix.was) and np.array_equal(fix.at_fix, fix.mid)
    shift.record_sway(_SLOT, fix)
    moved, _ = shift.shift_mps(_SLOT, fix, np.array([0.0]))
    assert moved[0] == 0.0


def _cubic(x: np.ndarray | float) -> np.ndarray | float:
    return 0.3 - 0.8 * x + 0.25 * x**2 - 0.05 * x**3


def test_node_weights_reproduce_a_cubic_and_carry_its_slope_ahead() -> None:
    """Within the kept ticks (``u`` 0-4 ticks back, past the oldest: the oldest) the weights
    give a cubic of the tick index exactly, whichever four nodes they use; ahead of the
    newest (``u < 0``) the newest value plus ``u`` times the cubic's slope there (−0.8 per
    tick back); each row sums to 1. All rows in one call, as the shift makes it."""
    u = np.array([0.0, 0.3, 1.0, 1.7, 2.0, 2.6, 3.4, 4.0, 5.2, -0.4, -1.1])
    w = _node_weights(u)
    values = w @ _cubic(np.arange(5.0))
    within = u >= 0.0
    assert np.allclose(w.sum(axis=1), 1.0, rtol=0.0, atol=1e-12)
    assert np.allclose(values[within], _cubic(np.minimum(u[within], 4.0)), rtol=0.0, atol=1e-12)
    assert np.allclose(values[~within], 0.3 - 0.8 * u[~within], rtol=0.0, atol=1e-12)
