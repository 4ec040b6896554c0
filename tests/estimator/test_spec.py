"""Estimator specs: self-consistency checks and what the catalog declares."""

from __future__ import annotations

import json

import numpy as np
import pytest

from estimator.catalog import SPECS, spec_of
from estimator.config import WheeledRearDriveConfig
from estimator.spec import (
    CalibrationChannel,
    EstimatorSpec,
    FieldSpec,
    FlagSpec,
    SlipChannel,
    SpecError,
    StateChannel,
    StateValue,
    ValueChannel,
    WheelPosition,
    WheelValueChannel,
)
from estimator.tracked.model import MotionState
from estimator.types import ESTIMATE_DTYPE, EstimateFlag


def _spec(**kw: object) -> EstimatorSpec:
    base: dict[str, object] = {
        "name": "x",
        "title": "X",
        "kinds": ("wheeled_rear_drive",),
        "inputs": ("imu",),
        "fields": (
            FieldSpec("stamp_ns", "i8", "ns", "time"),
            FieldSpec("s_pct", "f8", "%", "slip"),
            FieldSpec("flags", "i4", "", "flags"),
        ),
        "flags": (FlagSpec("OK", 0), FlagSpec("S_VALID", 3)),
    }
    base.update(kw)
    return EstimatorSpec(**base)  # type: ignore[arg-type]


def test_mdsf_spec_describes_the_rows_mdsf_emits() -> None:
    spec = spec_of("mdsf")
    assert spec.dtype == ESTIMATE_DTYPE
    assert {f.name: f.mask for f in spec.flags} == {f.name: int(f) for f in EstimateFlag if f.value}
    assert [s.field for s in spec.slips] == ["slip_left_pct", "slip_right_pct"]
    assert spec.motion_field == "vg_mps"


@pytest.mark.parametrize("name", sorted(SPECS))
def test_every_spec_is_json_and_has_units(name: str) -> None:
    spec = SPECS[name]
    doc = json.loads(json.dumps(spec.to_dict()))
    assert doc["name"] == name
    assert [f["name"] for f in doc["fields"]] == list(spec.field_names)
    for f in spec.fields:
        assert f.label, f.name
        assert f.description, f.name
    rows = spec.empty_rows(3)
    assert rows.dtype == spec.dtype and rows.shape == (3,)
    assert spec.check_rows(rows) is rows


def test_flag_names_and_masks() -> None:
    spec = _spec()
    assert spec.flag_mask("S_VALID") == 8
    assert spec.flag_names(1 | 8) == ["OK", "S_VALID"]
    with pytest.raises(KeyError, match="no flag 'NOPE'"):
        spec.flag_mask("NOPE")


def test_empty_rows_are_nan_floats_and_zero_ints() -> None:
    rows = _spec().empty_rows(2)
    assert np.isnan(rows["s_pct"]).all()
    assert (rows["flags"] == 0).all() and (rows["stamp_ns"] == 0).all()


def test_check_rows_refuses_another_dtype() -> None:
    with pytest.raises(TypeError, match="rows of 'x' must have its dtype"):
        _spec().check_rows(np.zeros(2, dtype=ESTIMATE_DTYPE))


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"fields": (FieldSpec("t", "i8", "ns", "t"),)}, "first field must be stamp_ns"),
        (
            {"slips": (SlipChannel("l", "left", "nope_pct", WheelPosition.REAR_LEFT),)},
            "names 'nope_pct'",
        ),
        (
            {"slips": (SlipChannel("l", "left", "s_pct", WheelPosition.REAR_LEFT, "NOPE"),)},
            "unknown flag 'NOPE'",
        ),
        ({"flags": (FlagSpec("A", 1), FlagSpec("B", 1))}, "distinct"),
        ({"motion": "ground"}, "unknown speed channel"),
        (
            {
                "slips": (
                    SlipChannel(
                        "l", "left", "s_pct", WheelPosition.REAR_LEFT, band_edges_pct=(15, 5)
                    ),
                )
            },
            "band edges",
        ),
    ],
)
def test_contradictions_are_refused(change: dict[str, object], message: str) -> None:
    with pytest.raises(SpecError, match=message):
        _spec(**change)


def test_a_row_dtype_is_the_specs_dtype_object_and_must_match_the_fields() -> None:
    own = np.dtype([("stamp_ns", "i8"), ("s_pct", "f8"), ("flags", "i4")])
    assert _spec(row_dtype=own).dtype is own
    with pytest.raises(SpecError, match="row_dtype differs"):
        _spec(row_dtype=np.dtype([("stamp_ns", "i8")]))
    assert spec_of("mdsf").dtype is ESTIMATE_DTYPE


def _state(field: str = "flags", values: tuple[int, ...] = (0, 1)) -> StateChannel:
    return StateChannel(
        "st", "state", field, tuple(StateValue(v, f"s{v}", f"s{v}") for v in values)
    )


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"states": (_state("s_pct"),)}, "not a i4 field"),
        ({"states": (_state(values=(1, 1)),)}, "distinct values"),
        ({"states": (_state(values=()),)}, "distinct values"),
    ],
)
def test_state_channels_are_checked(change: dict[str, object], message: str) -> None:
    with pytest.raises(SpecError, match=message):
        _spec(**change)


def test_value_and_wheel_value_channels_are_checked() -> None:
    with pytest.raises(SpecError, match="unknown flag 'NOPE'"):
        _spec(values=(ValueChannel("v", "v", "s_pct", valid_flag="NOPE"),))
    with pytest.raises(SpecError, match="not a f8 field"):
        _spec(values=(ValueChannel("v", "v", "missing"),))
    with pytest.raises(SpecError, match="wheel value channel w"):
        _spec(wheel_values=(WheelValueChannel("w", "w", "flags", WheelPosition.REAR_LEFT),))
    spec = _spec(values=(ValueChannel("v", "v", "s_pct", valid_flag="OK", mapped=True),))
    assert spec.value("v").mapped
    assert spec.to_dict()["values"][0]["valid_flag"] == "OK"
    with pytest.raises(KeyError, match="no value channel 'w'"):
        spec.value("w")


def test_the_crawler_state_channel_names_the_estimators_motion_states() -> None:
    channel = spec_of("tracked").states[0]
    assert [(s.value, s.name) for s in channel.states] == [
        (int(m), m.name.lower()) for m in MotionState
    ]


def test_calibration_channels_are_checked() -> None:
    """A calibration names an f8 value and std field of the rows, keys are unique, and the
    uncalibrated flag is one of the spec's."""
    cal = CalibrationChannel("r", "radius", "s_pct", "s_pct", "calibration.radius_converged_pct")
    with pytest.raises(SpecError, match="calibration r"):
        _spec(calibrations=(CalibrationChannel("r", "r", "s_pct", "nope", "x"),))
    with pytest.raises(SpecError, match="duplicate channel keys"):
        _spec(calibrations=(cal, cal))
    with pytest.raises(SpecError, match="unknown flag 'NOPE'"):
        _spec(calibrations=(cal,), uncalibrated_flag="NOPE")
    spec = _spec(calibrations=(cal,), uncalibrated_flag="OK")
    assert spec.calibration("r") is cal
    assert spec.to_dict()["calibrations"][0]["limit_config"] == "calibration.radius_converged_pct"
    with pytest.raises(KeyError, match="no calibration 'q'"):
        spec.calibration("q")


def test_mdsf_calibrations_name_its_config_thresholds_and_switches() -> None:
    """Every MDSF calibration's limit and switch are numbers and booleans of the config (the
    server reads them by these paths)."""
    config = WheeledRearDriveConfig()
    for c in spec_of("mdsf").calibrations:
        for path, kind in ((c.limit_config, float), (c.enabled_config, bool)):
            assert path is not None
            value: object = config
            for part in path.split("."):
                value = getattr(value, part)
            assert isinstance(value, kind), (c.key, path)
