"""Vehicle config by kind: round trips, earlier shapes, and every field's range and unit."""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Iterator
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimator.config import (
    Bound,
    ConfigError,
    DrivenAxle,
    GyroConfig,
    SlipConfig,
    TrackedConfig,
    VehicleConfig,
    VehicleGeometry,
    VehicleKind,
    Wheeled4wdSteeredConfig,
    WheeledRearDriveConfig,
    WheelPosition,
    bound_of,
    config_class,
    expect_kind,
    upgrade_legacy_config,
    vehicle_config_from_dict,
)
from estimator.mdsf import MdsfFleet

KINDS: tuple[type[VehicleConfig], ...] = (
    WheeledRearDriveConfig,
    TrackedConfig,
    Wheeled4wdSteeredConfig,
)


def _bounded_fields() -> Iterator[tuple[type[VehicleConfig], str, str, Bound]]:
    """(kind, section, field, bound) of every numeric field of every kind."""
    for cls in KINDS:
        for section in dataclasses.fields(cls):
            if isinstance(section.default_factory, type):
                for f in dataclasses.fields(section.default_factory):
                    bound = bound_of(f)
                    if bound is not None:
                        yield cls, section.name, f.name, bound


BOUNDED = list(_bounded_fields())


def _ids(case: tuple[type[VehicleConfig], str, str, Bound]) -> str:
    return f"{case[0].kind.value}.{case[1]}.{case[2]}"


def test_every_kind_has_its_class_and_named_positions() -> None:
    assert {config_class(k) for k in VehicleKind} == set(KINDS)
    assert WheeledRearDriveConfig.positions == (WheelPosition.REAR_LEFT, WheelPosition.REAR_RIGHT)
    assert TrackedConfig.positions == (WheelPosition.TRACK_LEFT, WheelPosition.TRACK_RIGHT)
    assert set(Wheeled4wdSteeredConfig.positions) == {
        WheelPosition.FRONT_LEFT,
        WheelPosition.FRONT_RIGHT,
        WheelPosition.REAR_LEFT,
        WheelPosition.REAR_RIGHT,
    }
    assert TrackedConfig().motion.low_gear_ratio == 1.42
    with pytest.raises(ConfigError, match="kind must be one of"):
        config_class("hovercraft")


@pytest.mark.parametrize(
    "config",
    [
        WheeledRearDriveConfig(),
        WheeledRearDriveConfig(
            geometry=VehicleGeometry(track_width_m=2.2, antenna_offset_m=(0.1, 0.5)),
            slip=SlipConfig(band_edges_pct=(2.0, 8.0, 30.0)),
            estimators=("mdsf",),
        ),
        TrackedConfig(),
        Wheeled4wdSteeredConfig(),
    ],
)
def test_each_kind_round_trips_through_json(config: VehicleConfig) -> None:
    data = json.loads(json.dumps(config.to_dict()))
    assert data["kind"] == config.kind.value
    got = vehicle_config_from_dict(data)
    assert got == config and type(got) is type(config)
    assert got.to_dict() == data


def test_a_partial_dict_takes_the_kinds_defaults() -> None:
    cfg = vehicle_config_from_dict({"kind": "wheeled_4wd_steered", "chassis": {"mass_kg": 900}})
    assert isinstance(cfg, Wheeled4wdSteeredConfig)
    assert cfg.chassis.mass_kg == 900 and cfg.chassis.driven_axle is DrivenAxle.ALL
    assert cfg.tyre == Wheeled4wdSteeredConfig().tyre
    assert vehicle_config_from_dict({}) == WheeledRearDriveConfig()


def _legacy(kind: str) -> dict[str, Any]:
    """A config as the code before kinds wrote it (``dataclasses.asdict`` of every section)."""
    return {
        "kind": kind,
        "geometry": {
            "h0_m": 1.2,
            "h1_m": 1.4,
            "track_width_m": 2.3,
            "wheel_radius_left_m": 0.5,
            "wheel_radius_right_m": 0.6,
            "antenna_offset_m": (0.1, -0.2),
            "imu_offset_m": (0.0, 0.3),
        },
        "encoder": {"teeth_per_rev": 60, "has_direction": False},
        "noise": {
            "gnss_vel_std_mps": 0.05,
            "accel_std_mps2": 0.07,
            "gyro_std_radps": 0.005,
            "accel_bias_walk_mps2": 0.002,
            "gnss_pos_std_m": 0.02,
        },
        "slip": {
            "min_ground_speed_mps": 0.2,
            "band_edges_pct": (5.0, 15.0),
            "alert_threshold_pct": 12.0,
            "alert_hold_s": 5.0,
            "settle_max_change": 0.5,
        },
        "estimators": (),
    }


def test_legacy_dicts_load_as_their_kind() -> None:
    rear = vehicle_config_from_dict(_legacy("wheeled_rear_drive"))
    assert isinstance(rear, WheeledRearDriveConfig)
    assert rear.geometry.wheel_radius_right_m == 0.6 and rear.encoder.teeth_per_rev == 60

    crawler = vehicle_config_from_dict(_legacy("tracked"))
    assert isinstance(crawler, TrackedConfig)
    assert crawler.geometry.track_gauge_m == 2.3
    assert crawler.geometry.imu_lever_arm_m == (0.0, 0.3, 1.2)
    assert crawler.geometry.antenna_lever_arm_m == pytest.approx((0.1, -0.2, 2.6))
    assert crawler.noise.accel_std_mps2 == 0.07 and crawler.slip.alert_threshold_pct == 12.0
    assert crawler.sprocket == TrackedConfig().sprocket

    steered = vehicle_config_from_dict(_legacy("wheeled_4wd_steered"))
    assert isinstance(steered, Wheeled4wdSteeredConfig)
    assert steered.chassis.front_track_m == steered.chassis.rear_track_m == 2.3
    assert steered.chassis.imu_lever_arm_m == (0.0, 0.3, 1.2)
    assert steered.tyre.unloaded_radius_m == pytest.approx(0.55)


def test_only_a_whole_legacy_dict_is_upgraded() -> None:
    part = {"kind": "tracked", "encoder": {"teeth_per_rev": 60}}
    assert upgrade_legacy_config(part) is part
    with pytest.raises(ConfigError, match=r"tracked: unknown field\(s\) \['encoder'\]"):
        vehicle_config_from_dict(part)
    today = TrackedConfig().to_dict()
    assert upgrade_legacy_config(today) is today
    rear = _legacy("wheeled_rear_drive")
    assert upgrade_legacy_config(rear) is rear


def test_a_crawlers_stored_gyro_std_is_dropped_and_its_gyro_section_is_the_one_truth() -> None:
    """A tracked config stored while its ``noise`` still had ``gyro_std_radps`` (which nothing
    read: its gyro is ``gyro``) loads as today's, the field gone from it and from what it
    writes; a rear-drive config keeps the field, which MDSF reads."""
    stored = TrackedConfig(gyro=GyroConfig(angle_random_walk_deg_rt_h=0.5)).to_dict()
    assert "gyro_std_radps" not in stored["noise"]
    stored["noise"] = {**stored["noise"], "gyro_std_radps": 0.004, "accel_std_mps2": 0.06}
    crawler = vehicle_config_from_dict(json.loads(json.dumps(stored)))
    assert isinstance(crawler, TrackedConfig)
    assert crawler.noise.accel_std_mps2 == 0.06
    assert crawler.gyro.resolved().angle_random_walk_deg_rt_h == 0.5
    assert not hasattr(crawler.noise, "gyro_std_radps")
    assert "gyro_std_radps" not in crawler.to_dict()["noise"]
    assert "gyro_std_radps" in stored["noise"]  # the caller's dict is left as it was
    with pytest.raises(ConfigError, match=r"tracked: noise: unknown field\(s\) \['gyro_rms'\]"):
        vehicle_config_from_dict({"kind": "tracked", "noise": {"gyro_rms": 0.004}})
    rear = vehicle_config_from_dict({"noise": {"gyro_std_radps": 0.004}})
    assert isinstance(rear, WheeledRearDriveConfig) and rear.noise.gyro_std_radps == 0.004


def test_a_crawlers_stored_accel_bias_walk_is_dropped_and_a_tractors_kept() -> None:
    """A tracked config stored while its ``noise`` still had ``accel_bias_walk_mps2`` (the
    tracked filter has no accelerometer bias state: nothing read it) loads as today's, the
    field gone from it and from what it writes, its other figures kept; a rear-drive
    config keeps it (MDSF's bias state walks by it)."""
    stored = TrackedConfig().to_dict()
    assert "accel_bias_walk_mps2" not in stored["noise"]
    stored["noise"] = {**stored["noise"], "accel_bias_walk_mps2": 0.003, "accel_std_mps2": 0.08}
    crawler = vehicle_config_from_dict(json.loads(json.dumps(stored)))
    assert isinstance(crawler, TrackedConfig)
    assert crawler.noise.accel_std_mps2 == 0.08
    assert not hasattr(crawler.noise, "accel_bias_walk_mps2")
    assert "accel_bias_walk_mps2" not in crawler.to_dict()["noise"]
    assert "accel_bias_walk_mps2" in stored["noise"]  # the caller's dict is left as it was
    rear = vehicle_config_from_dict({"noise": {"accel_bias_walk_mps2": 0.003}})
    assert isinstance(rear, WheeledRearDriveConfig) and rear.noise.accel_bias_walk_mps2 == 0.003


@pytest.mark.parametrize("case", BOUNDED, ids=_ids)
def test_each_range_is_refused_with_field_range_and_unit(
    case: tuple[type[VehicleConfig], str, str, Bound],
) -> None:
    cls, section, name, bound = case
    number = bound.low if bound.integer else (bound.low + bound.high) / 2
    outside: list[Any] = [bound.high * 10 + 1, bound.low - 1, float("nan"), True]
    if bound.integer:
        outside.append(float(number))
    for value in outside:
        part = value if bound.items is None else [value] * bound.items[0]
        data = {"kind": cls.kind.value, section: {name: part}}
        with pytest.raises(ConfigError) as info:
            vehicle_config_from_dict(data)
        message = str(info.value)
        assert message.startswith(f"{cls.kind.value}: {section}.{name}"), message
        assert bound.describe() in message and bound.unit in message
    inside = number if bound.items is None else [number] * bound.items[0]
    vehicle_config_from_dict({"kind": cls.kind.value, section: {name: inside}})


def test_issue_examples_are_refused() -> None:
    with pytest.raises(ConfigError) as info:
        vehicle_config_from_dict({"noise": {"accel_std_mps2": 1e200}})
    assert str(info.value) == (
        "wheeled_rear_drive: noise.accel_std_mps2 must be a number in 1e-06..10 m/s², got 1e+200"
    )
    with pytest.raises(ConfigError) as info:
        vehicle_config_from_dict({"slip": {"alert_hold_s": 1e12}})
    assert "slip.alert_hold_s must be a number in 0.1..3600 s" in str(info.value)


@pytest.mark.parametrize(
    ("data", "words"),
    [
        ({"slip": {"band_edges_pct": [15, 5]}}, "band_edges_pct must be increasing"),
        ({"slip": {"band_edges_pct": []}}, "band_edges_pct must be a list of 1 to 10 numbers"),
        ({"geometry": {"imu_offset_m": [1.0]}}, "imu_offset_m must be a list of 2 numbers"),
        ({"encoder": {"has_direction": 1}}, "has_direction must be true or false"),
        ({"kind": "wheeled_4wd_steered", "chassis": {"driven_axle": "mid"}}, "driven_axle"),
        ({"kind": "tracked", "geometry": {"h0_m": 1.0}}, "tracked: geometry: unknown"),
        ({"kind": "tracked", "geometry": 7}, "geometry must be an object"),
        ({"estimators": "mdsf"}, "estimators must be a list"),
        ({"estimators": ["mdsf", 3]}, "estimators must hold names"),
        ({"wheels": 4}, "unknown field(s) ['wheels']"),
        ({"encoder": {"teeth_per_rev": 10**400}}, "teeth_per_rev must be an integer in 1..100000"),
        ({"noise": {"gyro_std_radps": -(10**400)}}, "gyro_std_radps must be a number in 1e-06"),
    ],
)
def test_shape_errors_name_the_field(data: dict[str, Any], words: str) -> None:
    with pytest.raises(ConfigError) as info:
        vehicle_config_from_dict(data)
    assert words in str(info.value)


def test_sections_of_another_kind_are_refused_in_code_too() -> None:
    with pytest.raises(ConfigError, match="geometry must be a VehicleGeometry"):
        WheeledRearDriveConfig(geometry=TrackedConfig().geometry)  # type: ignore[arg-type]


def test_mdsf_refuses_another_kind() -> None:
    fleet = MdsfFleet()
    fleet.add_vehicle("tractor", WheeledRearDriveConfig())
    for config in (TrackedConfig(), Wheeled4wdSteeredConfig()):
        with pytest.raises(ConfigError, match="'mdsf' runs on wheeled_rear_drive vehicles"):
            fleet.add_vehicle("other", config)
    assert expect_kind(TrackedConfig(), TrackedConfig, "tracked") == TrackedConfig()


@settings(deadline=None)  # a config per kind per example: slow on a loaded machine
@given(st.data())
def test_values_within_the_ranges_are_accepted(data: st.DataObject) -> None:
    for cls in KINDS:
        body: dict[str, Any] = {"kind": cls.kind.value}
        for kind, section, name, bound in BOUNDED:
            if kind is not cls:
                continue
            draw = (
                st.integers(int(bound.low), int(bound.high))
                if bound.integer
                else st.floats(bound.low, bound.high)
            )
            n = 1 if bound.items is None else bound.items[0]
            values = sorted(set(data.draw(st.lists(draw, min_size=n, max_size=n))))
            if bound.items is None:
                body.setdefault(section, {})[name] = values[0]
            elif len(values) == n:  # distinct: band edges must increase
                body.setdefault(section, {})[name] = values
        config = vehicle_config_from_dict(body)
        assert vehicle_config_from_dict(config.to_dict()) == config
