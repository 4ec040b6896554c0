"""The accelerometer's white noise (the config's ``noise.accel_std_mps2``) in the tracked
filter: the forward speed's process noise over a tick, ``Δt²·σ_a²/N`` for a tick's mean of
``N`` samples (:func:`estimator.tracked.step.accel_speed_var`)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from estimator.config import TrackedConfig, TrackedNoiseConfig
from estimator.tracked import TrackedEstimatorConfig
from estimator.tracked.model import TrackedState as S
from estimator.tracked.params import VehicleParams
from estimator.tracked.step import Filter, accel_speed_var, initial_filter, tick_step
from estimator.tracked.vehicle import TickInputs, VehicleInputs
from estimator.types import ImuBatch
from tests.estimator.tracked._ticks import quiet_tick

CFG = TrackedEstimatorConfig()
T0_NS = 1_700_000_000_000_000_000


def _crawler(accel_std_mps2: float) -> TrackedConfig:
    return TrackedConfig(noise=TrackedNoiseConfig(accel_std_mps2=accel_std_mps2))


def test_the_speeds_noise_from_the_accelerometer_by_hand() -> None:
    p = VehicleParams.stack([VehicleParams.of(_crawler(s)) for s in (0.05, 0.5, 0.5)])
    got = accel_speed_var(p, np.array([10, 10, 20]), 0.1)
    # (0.1 s)² · σ² / N
    np.testing.assert_allclose(got, [0.01 * 0.0025 / 10, 0.01 * 0.25 / 10, 0.01 * 0.25 / 20])
    none = accel_speed_var(p, np.array([0, 0, 0]), 0.1)  # no sample: taken as one
    np.testing.assert_allclose(none, [0.01 * 0.0025, 0.01 * 0.25, 0.01 * 0.25])


def _blind_tick(samples: int) -> TickInputs:
    """A tick of two vehicles with nothing but the IMU (no odometer, sprockets or GNSS):
    the filter only predicts."""
    return quiet_tick(2, T0_NS, imu_samples=np.full(2, samples))


def _two(f: Filter) -> Filter:
    return Filter(
        **{k.name: np.repeat(getattr(f, k.name), 2, axis=0) for k in dataclasses.fields(f)}
    )


@pytest.mark.parametrize("samples", [10, 40])
def test_a_noisier_accelerometer_widens_the_predicted_speed_by_its_noise_over_the_tick(
    samples: int,
) -> None:
    """Two vehicles alike but for the accelerometer their configs name (0.05 and 1 m/s² per
    sample): over a tick with nothing to fuse, the speed's variance grows by ``Δt²·σ²/N``
    more on the noisier one, and nothing else differs."""
    p = VehicleParams.stack([VehicleParams.of(_crawler(s)) for s in (0.05, 1.0)])
    f = _two(initial_filter(CFG))
    before = f.P.copy()
    tick_step(f, _blind_tick(samples), p, CFG)
    grown = f.P[:, S.SPEED, S.SPEED] - before[:, S.SPEED, S.SPEED]
    dt = CFG.tick_s
    assert grown[1] - grown[0] == pytest.approx(dt**2 * (1.0 - 0.05**2) / samples, rel=1e-9)
    other = np.ones(f.P.shape[1:], dtype=bool)
    other[S.SPEED, S.SPEED] = False
    np.testing.assert_array_equal(f.P[0][other], f.P[1][other])


def test_a_ticks_samples_are_counted_at_the_imus_rate() -> None:
    """The inputs say how many IMU samples each tick's mean is of: 10 at 100 Hz, 20 at
    200 Hz (0.1 s ticks)."""
    for rate_hz, expected in ((100, 10), (200, 20)):
        inputs = VehicleInputs(TrackedConfig(), CFG)
        step_ns = 1_000_000_000 // rate_hz
        stamps = T0_NS + step_ns * np.arange(1, 3 * rate_hz + 1)
        n = stamps.size
        accel = np.zeros((n, 3))
        inputs.push_imu(ImuBatch(stamps, accel, np.zeros((n, 3))))
        ticks = inputs.due(int(stamps[-1]))
        got = inputs.take(ticks)
        assert ticks.size >= 20
        np.testing.assert_array_equal(got.imu_samples, expected)
