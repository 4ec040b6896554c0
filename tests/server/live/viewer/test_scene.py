"""Pure scene maps: attitude quaternions, vehicle layout from the spec's channels, colours."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimator.config import VehicleGeometry
from estimator.mdsf_spec import MDSF_SPEC
from estimator.reference_speed_spec import REFERENCE_SPEED_SPEC
from estimator.spec import (
    EstimatorSpec,
    FieldSpec,
    PositionChannel,
    SlipChannel,
    SpeedChannel,
    WheelPosition,
)
from estimator.types import empty_estimates
from server.live.viewer.colors import SLIP_COLOR_NONE, slip_rgb
from server.live.viewer.scene import (
    FRONT_AXLE_M,
    attitude_fields,
    attitude_from_wxyz,
    box_mesh,
    concat_frames,
    cylinder_mesh_x,
    fleet_frame,
    quat_mul,
    rotation_matrix_from_wxyz,
    wxyz_from_attitude,
)

headings = st.floats(-math.pi + 1e-6, math.pi, allow_nan=False)
pitches = st.floats(-1.4, 1.4, allow_nan=False)  # away from the ±90° gimbal lock
rolls = st.floats(-math.pi + 1e-6, math.pi, allow_nan=False)


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


@settings(max_examples=300, deadline=None)
@given(headings, pitches, rolls)
def test_attitude_round_trips_through_the_quaternion(psi: float, theta: float, phi: float) -> None:
    q = wxyz_from_attitude(psi, theta, phi)
    assert math.isclose(float(np.linalg.norm(q)), 1.0, abs_tol=1e-12)
    assert q[0] >= 0
    h, p, r = attitude_from_wxyz(q)
    assert abs(_wrap(float(h) - psi)) < 1e-9
    assert abs(float(p) - theta) < 1e-9
    assert abs(_wrap(float(r) - phi)) < 1e-9


@settings(max_examples=200, deadline=None)
@given(headings, pitches, rolls)
def test_forward_axis_points_along_heading_and_pitch(psi: float, theta: float, phi: float) -> None:
    R = rotation_matrix_from_wxyz(wxyz_from_attitude(psi, theta, phi))
    forward = R @ np.array([0.0, 1.0, 0.0])
    expected = [math.sin(psi) * math.cos(theta), math.cos(psi) * math.cos(theta), math.sin(theta)]
    np.testing.assert_allclose(forward, expected, atol=1e-12)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert math.isclose(float(np.linalg.det(R)), 1.0, abs_tol=1e-12)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(headings, pitches, rolls), min_size=1, max_size=20))
def test_vectorised_equals_one_by_one(att: list[tuple[float, float, float]]) -> None:
    a = np.array(att)
    q = wxyz_from_attitude(a[:, 0], a[:, 1], a[:, 2])
    for i, (psi, theta, phi) in enumerate(att):
        np.testing.assert_allclose(q[i], wxyz_from_attitude(psi, theta, phi), atol=1e-15)


def test_hand_computed_attitudes() -> None:
    # heading east (90°): forward is +x; right is -y (south)
    R = rotation_matrix_from_wxyz(wxyz_from_attitude(math.pi / 2, 0.0, 0.0))
    np.testing.assert_allclose(R @ [0, 1, 0], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(R @ [1, 0, 0], [0, -1, 0], atol=1e-12)
    # roll 30° right side down: the right axis tips down
    R = rotation_matrix_from_wxyz(wxyz_from_attitude(0.0, 0.0, math.radians(30)))
    np.testing.assert_allclose(R @ [1, 0, 0], [math.cos(math.radians(30)), 0, -0.5], atol=1e-12)
    # quaternion product: two quarter turns about z make a half turn
    qz = np.array([math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)])
    np.testing.assert_allclose(quat_mul(qz, qz), [0, 0, 0, 1], atol=1e-12)


def test_fleet_frame_places_wheels_and_colours_them() -> None:
    g = VehicleGeometry(
        h0_m=1.0, h1_m=1.6, track_width_m=2.0, wheel_radius_left_m=0.8, wheel_radius_right_m=0.8
    )
    rows = empty_estimates(2)
    rows["east_m"] = [10.0, -5.0]
    rows["north_m"] = [20.0, 3.0]
    rows["up_m"] = [2.6, 2.6]
    rows["heading_rad"] = [0.0, math.pi / 2]
    rows["pitch_rad"] = 0.0
    rows["roll_rad"] = 0.0
    rows["vg_mps"] = [2.0, 3.0]
    rows["slip_left_pct"] = [0.0, 40.0]
    rows["slip_right_pct"] = [5.0, float("nan")]
    f = fleet_frame(["a", "b"], rows, MDSF_SPEC, g, ["live", "offline"])
    np.testing.assert_allclose(f.ground_m, [[10, 20, 0], [-5, 3, 0]], atol=1e-12)
    # vehicle a faces north: left wheel to the west, right to the east
    np.testing.assert_allclose(f.wheel_position_m[0], [9.0, 20.0, 0.8], atol=1e-12)
    np.testing.assert_allclose(f.wheel_position_m[1], [11.0, 20.0, 0.8], atol=1e-12)
    # vehicle b faces east: left wheel to the north
    np.testing.assert_allclose(f.wheel_position_m[2], [-5.0, 4.0, 0.8], atol=1e-12)
    np.testing.assert_allclose(f.velocity_mps, [[0, 2, 0], [3, 0, 0]], atol=1e-12)
    assert f.wheel_rgb.tolist() == [
        [26, 152, 80],
        [240, 200, 40],
        [140, 20, 30],
        list(SLIP_COLOR_NONE),
    ]
    assert f.body_rgb[1].tolist() != f.body_rgb[0].tolist()
    np.testing.assert_allclose(f.wheel_wxyz[2], f.body_wxyz[1])


def test_missing_attitude_is_level_and_north() -> None:
    rows = empty_estimates(1)
    rows["east_m"] = 1.0
    rows["north_m"] = 2.0
    rows["up_m"] = 0.0
    f = fleet_frame(["a"], rows, MDSF_SPEC)
    np.testing.assert_allclose(f.body_wxyz, [[1, 0, 0, 0]])


#: A steered four-wheel estimator's spec: a slip channel per wheel, no up, pitch or roll.
FOUR_WHEEL = EstimatorSpec(
    name="four_wheel_test",
    title="four wheels",
    kinds=("wheeled_4wd_steered",),
    inputs=("gnss", "wheels"),
    fields=(
        FieldSpec("stamp_ns", "i8", "ns", "time"),
        FieldSpec("x_m", "f8", "m", "east"),
        FieldSpec("y_m", "f8", "m", "north"),
        FieldSpec("yaw_rad", "f8", "rad", "heading"),
        FieldSpec("v_mps", "f8", "m/s", "speed"),
        *(FieldSpec(f"s_{k}_pct", "f8", "%", f"slip {k}") for k in ("fl", "fr", "rl", "rr")),
    ),
    slips=tuple(
        SlipChannel(k, k, f"s_{k}_pct", WheelPosition(p))
        for k, p in (
            ("fl", "front_left"),
            ("fr", "front_right"),
            ("rl", "rear_left"),
            ("rr", "rear_right"),
        )
    ),
    speeds=(SpeedChannel("v", "speed", "v_mps"),),
    motion="v",
    position=PositionChannel("x_m", "y_m", heading_field="yaw_rad"),
)


def test_one_wheel_per_slip_channel_placed_by_its_position() -> None:
    g = VehicleGeometry(h0_m=1.0, h1_m=1.0, track_width_m=2.0)
    rows = FOUR_WHEEL.empty_rows(2)
    rows["x_m"] = [0.0, 50.0]
    rows["y_m"] = 0.0
    rows["yaw_rad"] = [0.0, math.pi / 2]
    rows["v_mps"] = [1.0, 2.0]
    for k, v in zip(("fl", "fr", "rl", "rr"), (0.0, 5.0, 40.0, math.nan), strict=True):
        rows[f"s_{k}_pct"] = v
    f = fleet_frame(["a", "b"], rows, FOUR_WHEEL, g)
    r = g.wheel_radius_left_m
    # vehicle a faces north, its antenna (no up field: 0) 2 m above the ground point
    np.testing.assert_allclose(
        f.wheel_position_m[:4],
        [[-1, FRONT_AXLE_M, r - 2], [1, FRONT_AXLE_M, r - 2], [-1, 0, r - 2], [1, 0, r - 2]],
        atol=1e-12,
    )
    # vehicle b faces east: its front wheels are east of its rear wheels
    assert f.wheel_position_m[4, 0] - f.wheel_position_m[6, 0] == pytest.approx(FRONT_AXLE_M)
    assert f.wheel_owner.tolist() == [0, 0, 0, 0, 1, 1, 1, 1]
    assert f.wheel_rgb[:4].tolist() == slip_rgb([0.0, 5.0, 40.0, math.nan]).tolist()
    np.testing.assert_allclose(f.velocity_mps, [[0, 1, 0], [2, 0, 0]], atol=1e-12)
    assert attitude_fields(FOUR_WHEEL) == (None, None)
    assert attitude_fields(MDSF_SPEC) == ("pitch_rad", "roll_rad")


def test_frames_of_two_specs_join_with_their_wheel_owners() -> None:
    four = FOUR_WHEEL.empty_rows(1)
    two = empty_estimates(2)
    f = concat_frames(
        [fleet_frame(["m1", "m2"], two, MDSF_SPEC), fleet_frame(["w"], four, FOUR_WHEEL)]
    )
    assert f.ids == ["m1", "m2", "w"]
    assert f.estimators == ["mdsf", "mdsf", "four_wheel_test"]
    assert f.wheel_owner.tolist() == [0, 0, 1, 1, 2, 2, 2, 2]
    assert f.wheel_rgb.shape == (8, 3) and f.body_wxyz.shape == (3, 4)


def test_a_spec_without_position_is_not_drawn() -> None:
    with pytest.raises(ValueError, match="no position"):
        fleet_frame(["a"], REFERENCE_SPEED_SPEC.empty_rows(1), REFERENCE_SPEED_SPEC)


def test_slip_colour_scale_interpolates_and_clamps() -> None:
    assert slip_rgb(0.0).tolist() == [26, 152, 80]
    assert slip_rgb(-5.0).tolist() == [240, 200, 40]
    assert slip_rgb(10.0).tolist() == [235, 142, 35]
    assert slip_rgb(100.0).tolist() == [140, 20, 30]
    assert slip_rgb(float("nan")).tolist() == list(SLIP_COLOR_NONE)


def test_meshes_are_closed_and_outward() -> None:
    for v, f in (box_mesh((1.0, 2.0, 3.0)), cylinder_mesh_x(0.5, 0.4, 16)):
        edges: dict[tuple[int, int], int] = {}
        for a, b, c in f.tolist():
            for e in ((a, b), (b, c), (c, a)):
                edges[e] = edges.get(e, 0) + 1
        # closed, consistently oriented: each directed edge once and its reverse once
        assert all(edges.get((b, a)) == 1 for (a, b) in edges)
        # outward: the signed volume is positive
        tri = v[f]
        vol = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6
        assert vol > 0
