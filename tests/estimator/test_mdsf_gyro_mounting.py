"""The gyro's rates turned into the body's axes by the calibration's IMU mounting before the
tilt track: a pitched IMU's roll gyro reads ``sin β·ωz`` in every turn."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from estimator.config import VehicleConfig
from estimator.mdsf import MdsfConfig, MdsfFleet
from estimator.mdsf.frontend import _gyro_in_body
from estimator.sim import SimRun, replay, simulate, truth_at
from estimator.sim.sensors import imu_mounting
from estimator.types import ESTIMATE_DTYPE
from tests.estimator.test_engine import _run

START = 1_767_225_600_000_000_000
_OUTAGE_S = (10.0, 45.0)


def _pitched_figure_eight(seed: int = 1) -> tuple[SimRun, VehicleConfig]:
    """One lap of the figure eight (loops at 0.5 rad/s) after 4 s standing, the IMU pitched
    3° against the body, GNSS lost through both loops."""
    sim = simulate(
        "figure_eight",
        seed=seed,
        start_ns=START,
        laps=1,
        stand_s=4.0,
        imu_misalign_deg=(0.0, 3.0),
        gnss_outages=(_OUTAGE_S,),
    )
    return sim, dataclasses.replace(sim.config, noise=sim.sensor_noise)


def test_rates_read_by_a_pitched_imu_are_turned_back_into_the_body_axes() -> None:
    rng = np.random.default_rng(5)
    body = rng.normal(0.0, 0.3, (50, 3))
    beta = rng.uniform(-0.1, 0.1, 50)
    read = np.stack([body[i] @ imu_mounting((0.0, math.degrees(b))) for i, b in enumerate(beta)])
    assert np.array_equal(read[:, 0], body[:, 0])  # the pitch gyro is not turned
    back = _gyro_in_body(read[:, 1], read[:, 2], beta)
    assert np.allclose(np.stack(back, axis=1), body[:, 1:], rtol=0, atol=1e-12)
    # a pitched IMU's roll gyro reads a pure turn's yaw rate; turned back, no roll rate
    wy, wz = _gyro_in_body(
        np.array([math.sin(0.05) * 0.4]), np.array([math.cos(0.05) * 0.4]), np.array([0.05])
    )
    assert abs(wy[0]) < 1e-15 and abs(wz[0] - 0.4) < 1e-15


def test_a_pitched_imu_keeps_the_pitch_through_an_outage_with_turns() -> None:
    # The mounting pitch is learnt in the standstill (with the receiver's pitch); without
    # its turn of the rates each loop's yaw rate was integrated as roll and carried into
    # pitch by the tilt track's yaw coupling: 6.1° of pitch error in the outage (seed 1).
    sim, cfg = _pitched_figure_eight()
    rows = _run(MdsfFleet(MdsfConfig()), {"v": (sim, cfg)})["v"]
    t = (rows["stamp_ns"] - START) * 1e-9
    assert abs(math.degrees(rows["imu_pitch_mount_rad"][-1]) - 3.0) < 0.3
    err = rows["pitch_rad"] - truth_at(sim.truth, rows["stamp_ns"], "pitch_rad")
    outage = (t > _OUTAGE_S[0]) & (t < _OUTAGE_S[1])
    turning = np.abs(truth_at(sim.truth, rows["stamp_ns"], "yaw_rate_radps")) > 0.3
    assert np.count_nonzero(outage & turning) > 150
    assert math.degrees(np.max(np.abs(err[outage]))) < 1.5


def test_a_pitched_imu_batched_with_others_equals_it_alone() -> None:
    sims = {
        "pitched": _pitched_figure_eight(2),
        "level": (lambda s: (s, dataclasses.replace(s.config, noise=s.sensor_noise)))(
            simulate("paper_straight", seed=3, start_ns=START)
        ),
    }
    together = _run(MdsfFleet(), sims)
    alone = _run(MdsfFleet(), {"pitched": sims["pitched"]})["pitched"]
    assert together["pitched"].shape == alone.shape
    for name in ESTIMATE_DTYPE.names or ():
        assert np.allclose(
            together["pitched"][name], alone[name], rtol=0, atol=1e-9, equal_nan=True
        ), name


def test_the_gyro_mounting_follows_the_calibration_and_its_reset() -> None:
    sim, cfg = _pitched_figure_eight()
    fleet = MdsfFleet()
    fleet.add_vehicle("v", cfg)
    slot = fleet._slot["v"]
    used = []
    end_ns = START + 8 * 10**9
    for chunk, until in replay(sim.measurements, step_ns=100_000_000, end_ns=end_ns):
        for m in chunk:
            fleet.push("v", m)
        fleet.advance({"v": until})
        used.append(float(fleet.front.gyro_mount_rad[slot]))
    assert used[0] == 0.0  # the prior's 0 ± 3°: nothing turned before anything is learnt
    fleet.advance({"v": end_ns})  # no tick due: the mounting is still taken from the calibration
    cal = fleet.calibration("v")
    beta, var = cal.imu_pitch_rad, cal.imu_pitch_std_rad**2
    assert abs(math.degrees(beta) - 3.0) < 0.3
    assert fleet.front.gyro_mount_rad[slot] == np.float64(beta * beta**2 / (beta**2 + var))
    fleet.reset_calibration("v")
    fleet.advance({"v": end_ns + 100_000_000})
    assert fleet.front.gyro_mount_rad[slot] == 0.0


def test_a_pitched_imu_rows_do_not_depend_on_the_delivery_schedule() -> None:
    # the mounting pitch is learnt in the first second: pushed at once, every tick still
    # turns the rates by the pitch learnt up to the tick before, as when stepped
    sim, cfg = _pitched_figure_eight(3)
    stepped = _run(MdsfFleet(), {"v": (sim, cfg)})["v"]
    at_once = _run(MdsfFleet(), {"v": (sim, cfg)}, step_ns=10**12)["v"]  # one advance
    assert at_once.shape == stepped.shape
    assert abs(math.degrees(at_once["imu_pitch_mount_rad"][-1]) - 3.0) < 0.3
    for name in ESTIMATE_DTYPE.names or ():
        assert np.allclose(at_once[name], stepped[name], rtol=0, atol=1e-9, equal_nan=True), name
