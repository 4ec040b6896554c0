"""The friction spec reads as every spec does: inputs the server knows, channels on fields."""

from __future__ import annotations

import json

from estimator.base import STREAMS
from estimator.friction_spec import FRICTION_DTYPE, FRICTION_SPEC, FrictionFlag


def test_spec_is_consistent() -> None:
    assert FRICTION_SPEC.dtype is FRICTION_DTYPE
    assert set(FRICTION_SPEC.inputs) <= set(STREAMS)
    assert FRICTION_SPEC.kinds == ("wheeled_4wd_steered",)
    assert [s.position.value for s in FRICTION_SPEC.slips] == [
        "front_left",
        "front_right",
        "rear_left",
        "rear_right",
    ]
    assert FRICTION_SPEC.motion_field == "vx_mps"
    assert FRICTION_SPEC.flag_mask("INFORMED") == FrictionFlag.INFORMED
    assert FRICTION_SPEC.flag_names(int(FrictionFlag.HELD | FrictionFlag.GNSS_SPEED)) == [
        "HELD",
        "GNSS_SPEED",
    ]
    # a vehicle without a steering angle yet: its rows say so and read as degraded
    assert FRICTION_SPEC.flag_mask("NO_STEERING") == FrictionFlag.NO_STEERING
    assert "NO_STEERING" in FRICTION_SPEC.degraded_flags
    json.dumps(FRICTION_SPEC.to_dict())


def test_every_field_has_a_unit_in_its_name() -> None:
    suffix = {"_ns": "ns", "_n": "N", "_pct": "%", "_rad": "rad", "_mps": "m/s"}
    for f in FRICTION_SPEC.fields:
        for end, unit in suffix.items():
            if f.name.endswith(end):
                assert f.unit == unit, f.name
    assert FRICTION_SPEC.field("mu").unit == ""


def test_the_position_is_a_channel_with_its_dead_reckoned_flag() -> None:
    p = FRICTION_SPEC.position
    assert p is not None
    assert (p.east_field, p.north_field, p.up_field, p.heading_field) == (
        "east_m",
        "north_m",
        "up_m",
        "heading_rad",
    )
    assert p.carried_flag == "DEAD_RECKONED"
    assert FRICTION_SPEC.flag_mask("DEAD_RECKONED") == FrictionFlag.DEAD_RECKONED
    assert "DEAD_RECKONED" in FRICTION_SPEC.degraded_flags
    assert all(FRICTION_SPEC.field(n).unit == "m" for n in ("east_m", "north_m", "up_m"))
