"""The registry keeps, restores and resets an estimator's online calibration (real MDSF on a
simulated drive whose sensors need it: radius 2 % off, IMU pitched, GNSS clock early; the
tracked estimator's receiver clock, given back alone where the gyro is not measured yet)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from estimator.config import OdometerConfig, TrackedConfig, VehicleGeometry, WheeledRearDriveConfig
from estimator.mdsf import MdsfFleet
from estimator.mdsf_spec import MDSF_SPEC
from estimator.sim import simulate
from estimator.tracked import TrackedEstimatorConfig, TrackedFleet, TrackedState
from server.estimation.registry import RESET_CALIBRATION, Calibrating, EstimatorRegistry
from tests.support import replay_drive

_START_NS = 1_700_000_000_000_000_000
_FIELDS = [f for c in MDSF_SPEC.calibrations for f in (c.field, c.std_field)]


@pytest.fixture(scope="module")
def learnt() -> tuple[EstimatorRegistry, WheeledRearDriveConfig, np.ndarray]:
    """A registry that ran 30 s of a free-rolling drive for vehicle ``v``, its config and the
    rows."""
    geo = VehicleGeometry(wheel_driven_left=False, wheel_driven_right=False)
    sim = simulate(
        "random_drive",
        seed=4,
        start_ns=_START_NS,
        config=WheeledRearDriveConfig(geometry=geo),
        duration_s=30.0,
        free_rolling=(True, True),
        clock_offset_ms=(-80.0, 0.0, 0.0),
        wheel_radius_error_rel=(0.02, 0.02),
        imu_misalign_deg=(0.0, 3.0),
    )
    config = dataclasses.replace(sim.config, noise=sim.sensor_noise)
    registry = EstimatorRegistry()
    registry.add_vehicle("v", config)
    rows = replay_drive(
        sim,
        lambda m: registry.push("v", m),
        lambda until: [b.rows for b in registry.advance({"v": until})],
    )
    return registry, config, rows


def _fields(registry: EstimatorRegistry) -> dict[str, float]:
    est = registry.estimator("mdsf")
    assert isinstance(est, Calibrating)
    return est.calibration_fields("v")


def _prior(config: WheeledRearDriveConfig) -> dict[str, float]:
    fresh = MdsfFleet()
    fresh.add_vehicle("v", config)
    return fresh.calibration_fields("v")


def test_mdsf_calibrates_and_its_rows_carry_the_calibration(learnt) -> None:
    """The drive teaches the radius (free-rolling wheels): its std falls far below the prior,
    and the newest row holds exactly what the estimator holds (the row is the stored state)."""
    registry, config, rows = learnt
    now = _fields(registry)
    prior = _prior(config)
    assert now["radius_left_std_m"] < prior["radius_left_std_m"] / 5
    assert abs(now["radius_left_m"] / config.geometry.wheel_radius_left_m - 1.02) < 0.005
    for f in _FIELDS:
        assert rows[-1][f] == pytest.approx(now[f], rel=1e-12, abs=1e-15)


def _restored(rows: np.ndarray, config: WheeledRearDriveConfig) -> EstimatorRegistry:
    """A new registry running ``v`` from the calibration of the newest of ``rows``."""
    registry = EstimatorRegistry(
        calibrations={("v", "mdsf"): {f: float(rows[-1][f]) for f in _FIELDS}}
    )
    registry.add_vehicle("v", config)
    return registry


def test_a_new_config_keeps_the_calibration(learnt) -> None:
    """Registered again (a new config restarts the estimator): the calibration goes on."""
    _, config, rows = learnt
    registry = _restored(rows, config)
    before = _fields(registry)
    slip = dataclasses.replace(config.slip, min_ground_speed_mps=0.4)
    registry.add_vehicle("v", dataclasses.replace(config, slip=slip))
    after = _fields(registry)
    for f in _FIELDS:
        assert after[f] == pytest.approx(before[f], rel=1e-9, abs=1e-15)


def test_a_new_registry_restores_the_stored_calibration_once(learnt) -> None:
    """A restarted server's registry starts the vehicle from its newest stored row, not from
    the priors; the stored calibration is used once (a later vehicle of that id relearns)."""
    _, config, rows = learnt
    stored = {f: float(rows[-1][f]) for f in _FIELDS}
    registry = _restored(rows, config)
    got = _fields(registry)
    for f in _FIELDS:
        assert got[f] == pytest.approx(stored[f], rel=1e-9, abs=1e-15)
    registry.remove_vehicle("v")
    registry.add_vehicle("v", config)
    assert _fields(registry)["radius_left_std_m"] == pytest.approx(
        _prior(config)["radius_left_std_m"]
    )


def test_a_stored_row_without_calibration_is_not_restored() -> None:
    """Rows of a mode that does not calibrate hold NaN: the vehicle starts from its priors."""
    config = WheeledRearDriveConfig()
    stored = dict.fromkeys(_FIELDS, math.nan)
    failures: list[tuple[str, str, str]] = []
    registry = EstimatorRegistry(
        calibrations={("v", "mdsf"): stored},
        on_error=lambda vid, name, op, _exc: failures.append((vid, name, op)),
    )
    registry.add_vehicle("v", config)
    assert _fields(registry) == pytest.approx(_prior(config))
    assert failures == []


def test_reset_goes_back_to_the_priors_and_is_counted(learnt) -> None:
    """A reset forgets what was learnt (the config's priors again), keeps a calibration drive
    on, and counts itself; a vehicle that does not run the estimator is told as an error."""
    _, config, rows = learnt
    registry = _restored(rows, config)
    registry.command("v", "mdsf", "calibration_drive", True)
    assert registry.command("v", "mdsf", RESET_CALIBRATION, True)
    assert _fields(registry) == pytest.approx(_prior(config))
    est = registry.estimator("mdsf")
    assert isinstance(est, MdsfFleet) and est.calibration_drive_on("v")
    assert registry.counters()["mdsf"]["v"]["calibration_resets"] == 1
    failures: list[tuple[str, str, str]] = []
    registry.on_error = lambda vid, name, op, _exc: failures.append((vid, name, op))
    assert not registry.command("nobody", "mdsf", RESET_CALIBRATION, True)
    assert failures == [("nobody", "mdsf", "command")]


def test_a_crawlers_clock_is_restored_without_a_gyro_measurement_kept_and_reset() -> None:
    """A crawler that has not stood yet has a learnt receiver clock and no gyro measurement
    (NaN): a restart restores the clock alone (the state's prior mean and 1-sigma), a new
    config keeps it, and a reset returns it to the prior; no error is told."""
    c = TrackedState.GNSS_CLOCK
    stored = {
        "gyro_arw_deg_rt_h": math.nan,
        "gyro_arw_std_deg_rt_h": math.nan,
        "gnss_clock_offset_s": 0.0725,
        "gnss_clock_offset_std_s": 0.003,
    }
    failures: list[tuple[str, str, str]] = []
    registry = EstimatorRegistry(
        calibrations={("c", "tracked"): stored},
        on_error=lambda vid, name, op, _exc: failures.append((vid, name, op)),
    )
    registry.add_vehicle("c", TrackedConfig())
    est = registry.estimator("tracked")
    assert isinstance(est, TrackedFleet)
    x, P = est.filter_state("c")
    assert x[c] == 0.0725 and P[c, c] == pytest.approx(0.003**2, rel=1e-12)
    got = est.calibration_fields("c")
    assert math.isnan(got["gyro_arw_deg_rt_h"]) and got["gnss_clock_offset_s"] == 0.0725
    registry.add_vehicle("c", TrackedConfig(odometer=OdometerConfig(distance_per_edge_m=0.011)))
    x, P = est.filter_state("c")
    assert x[c] == 0.0725 and P[c, c] == pytest.approx(0.003**2, rel=1e-12)
    assert registry.command("c", "tracked", RESET_CALIBRATION, True)
    x, P = est.filter_state("c")
    prior_s = TrackedEstimatorConfig().gnss_clock_offset_std_s
    assert x[c] == 0.0 and P[c, c] == pytest.approx(prior_s**2, rel=1e-12)
    assert failures == []
