"""A real viser server on a free port: the scene follows the hub's estimates."""

from __future__ import annotations

import math
import time
import urllib.request
from collections.abc import Iterator

import numpy as np
import pytest

from estimator.config import VehicleGeometry
from estimator.reference_speed_spec import REFERENCE_SPEED_SPEC
from estimator.types import EstimateBatch, empty_estimates
from server.live.hub import LiveHub
from server.live.viewer.colors import SLIP_COLOR_NONE, SLIP_COLOR_STOPS, slip_rgb
from server.live.viewer.fleet_view import (
    ARROW_SECONDS,
    NO_FOLLOW,
    FleetViewer,
    fleet_view_point,
    legend_html,
    outgrown,
)
from server.live.viewer.scene import STATUS_RGB, rotation_matrix_from_wxyz
from server.settings import ViewerSettings
from tests.server.live.viewer.test_scene import FOUR_WHEEL
from tests.support import free_port as _free_port

T0 = 1_700_000_000 * 1_000_000_000


def _row(t_s: float, east: float, north: float, heading: float, sl: float, sr: float) -> np.ndarray:
    r = empty_estimates(1)
    r["stamp_ns"] = T0 + round(t_s * 1e9)
    r["east_m"] = east
    r["north_m"] = north
    r["up_m"] = 2.6
    r["heading_rad"] = heading
    r["pitch_rad"] = 0.05
    r["roll_rad"] = -0.02
    r["vg_mps"] = 2.0
    r["slip_left_pct"] = sl
    r["slip_right_pct"] = sr
    return r


@pytest.fixture
def viewer() -> Iterator[tuple[FleetViewer, LiveHub]]:
    hub = LiveHub()
    v = FleetViewer(hub, ViewerSettings(host="127.0.0.1", port=_free_port(), update_hz=5.0))
    v.open()
    try:
        yield v, hub
    finally:
        v.stop()


def test_pose_and_wheel_colours_follow_the_estimates(viewer: tuple[FleetViewer, LiveHub]) -> None:
    v, hub = viewer
    # the server answers on its port (the client bundle)
    with urllib.request.urlopen(f"http://127.0.0.1:{v.port}/", timeout=10) as resp:
        assert resp.status == 200
    hub.on_estimates(
        [("a", _row(0, 10, 20, 0.0, 2.0, 8.0)), ("b", _row(0, -4, 1, 1.0, 20.0, 30.0))]
    )
    v.update()
    assert v._bodies is not None and v._wheels is not None
    g = VehicleGeometry()
    pos = np.asarray(v._wheels.batched_positions)
    assert pos.shape == (4, 3)
    assert (
        np.asarray(v._wheels.batched_colors).tolist() == slip_rgb([2.0, 8.0, 20.0, 30.0]).tolist()
    )
    wxyz = np.asarray(v._bodies.batched_wxyzs, dtype=np.float64)
    fwd = rotation_matrix_from_wxyz(wxyz[0]) @ [0.0, 1.0, 0.0]
    np.testing.assert_allclose(fwd, [0.0, math.cos(0.05), math.sin(0.05)], atol=1e-6)
    # the wheels sit track_width apart, around the antenna's ground point
    assert math.isclose(float(np.linalg.norm(pos[1] - pos[0])), g.track_width_m, rel_tol=1e-5)
    assert abs(float((pos[0, 0] + pos[1, 0]) / 2) - 10.0) < 0.5

    # new estimates: vehicle a turned east, moved and its left wheel now slips hard
    hub.on_estimates([("a", _row(1, 12, 20, math.pi / 2, 35.0, float("nan")))])
    v.update()
    wxyz = np.asarray(v._bodies.batched_wxyzs, dtype=np.float64)
    fwd = rotation_matrix_from_wxyz(wxyz[0]) @ [0.0, 1.0, 0.0]
    assert fwd[0] > 0.99  # facing east
    colors = np.asarray(v._wheels.batched_colors).tolist()
    assert colors[0] == slip_rgb(35.0).tolist()
    assert colors[1] == [160, 160, 160]
    pos = np.asarray(v._wheels.batched_positions)
    assert abs(float((pos[0, 0] + pos[1, 0]) / 2) - 12.0) < 0.5


def test_follow_draws_track_and_arrow_for_one_vehicle(viewer: tuple[FleetViewer, LiveHub]) -> None:
    v, hub = viewer
    for k in range(20):
        hub.on_estimates([("a", _row(k * 0.5, k * 1.0, 0.0, math.pi / 2, 3.0, 3.0))])
    hub.on_estimates([("b", _row(10, 0, 0, 0, 0, 0))])
    v.update()
    assert v._follow is not None
    assert set(v._follow.options) == {NO_FOLLOW, "a", "b"}
    assert v._track is None and v._arrow is None
    v.follow("a")
    v.update()
    assert v._track is not None and v._arrow is not None
    assert np.asarray(v._track.points).shape == (19, 2, 3)
    arrow = np.asarray(v._arrow.points)[0]
    # 2 m/s east, nose 0.05 rad up, over ARROW_SECONDS
    expected = [ARROW_SECONDS * 2 * math.cos(0.05), 0.0, ARROW_SECONDS * 2 * math.sin(0.05)]
    np.testing.assert_allclose(arrow[1] - arrow[0], expected, atol=1e-5)
    v.follow(None)
    assert v._track.visible is False


def test_update_thread_runs_at_its_rate(viewer: tuple[FleetViewer, LiveHub]) -> None:
    v, hub = viewer
    hub.on_estimates([(f"v{i}", _row(0, i, 0, 0, 1, 1)) for i in range(50)])
    v.settings = ViewerSettings(host="127.0.0.1", port=v.port, update_hz=20.0)
    v.start()
    deadline = time.monotonic() + 10
    while v.frames < 5 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert v.frames >= 5
    assert v._wheels is not None and np.asarray(v._wheels.batched_positions).shape == (100, 3)


def test_origin_offsets_and_grid_layout_place_vehicle_frames() -> None:
    hub = LiveHub()
    hub.on_estimates([("a", _row(0, 1, 2, 0, 1, 1)), ("b", _row(0, 1, 2, 0, 1, 1))])
    anchors = {"a": (100.0, -50.0, 3.0), "b": None}
    placed = FleetViewer(
        hub,
        ViewerSettings(host="127.0.0.1", port=_free_port()),
        origin_offset_m=lambda vid: anchors[vid],
    )
    grid = FleetViewer(
        hub, ViewerSettings(host="127.0.0.1", port=_free_port()), layout="grid", grid_spacing_m=50.0
    )
    for v in (placed, grid):
        v.open()
    try:
        placed.update()
        assert placed.frame is not None
        # b's anchor is not known yet: not drawn (in its own frame it would sit at the wrong place)
        assert placed.frame.ids == ["a"]
        np.testing.assert_allclose(placed.frame.antenna_m, [[101, -48, 5.6]])
        assert placed._count is not None and placed._count.value == "1 (1 without a position)"
        anchors["b"] = (-20.0, 0.0, 0.0)
        placed.update()
        np.testing.assert_allclose(placed.frame.antenna_m, [[101, -48, 5.6], [-19, 2, 2.6]])
        placed.follow("a")
        for k in range(1, 4):
            hub.on_estimates([("a", _row(k, 1 + k, 2, 0, 1, 1))])
        placed.update()
        assert placed._track is not None
        track = np.asarray(placed._track.points)
        assert float(track[-1, 1, 0]) == pytest.approx(104.0, abs=1e-4)  # shifted like the pose
        grid.update()
        assert grid.frame is not None
        np.testing.assert_allclose(grid.frame.antenna_m[:, :2], [[4, 2], [51, 2]])
    finally:
        for v in (placed, grid):
            v.stop()


def test_mixed_fleet_drawn_from_each_vehicles_primary_spec() -> None:
    primaries = {"m": "mdsf", "mr": "mdsf", "r": "reference_speed", "w": "four_wheel_test"}
    hub = LiveHub(primary_of=primaries.get)
    hub.on_estimates(
        EstimateBatch.of([("mr", REFERENCE_SPEED_SPEC.empty_rows(1))], REFERENCE_SPEED_SPEC)
    )
    hub.on_estimates(
        EstimateBatch.of([("r", REFERENCE_SPEED_SPEC.empty_rows(1))], REFERENCE_SPEED_SPEC)
    )
    hub.on_estimates([("m", _row(0, 0, 0, 0, 1.0, 2.0)), ("mr", _row(0, 9, 0, 0, 3.0, 4.0))])
    four = FOUR_WHEEL.empty_rows(1)
    four["stamp_ns"] = T0
    four["x_m"], four["y_m"] = 30.0, 0.0
    for k, slip in zip(("fl", "fr", "rl", "rr"), (5.0, 6.0, 7.0, 8.0), strict=True):
        four[f"s_{k}_pct"] = slip
    hub.on_estimates(EstimateBatch.of([("w", four)], FOUR_WHEEL))
    v = FleetViewer(hub, ViewerSettings(host="127.0.0.1", port=_free_port()))
    v.open()
    try:
        v.update()
        assert v.frame is not None and v._wheels is not None
        # "r" runs only an estimator without a position: not drawn
        assert sorted(v.frame.ids) == ["m", "mr", "w"]
        by_vehicle: dict[str, list[list[int]]] = {}
        colors = np.asarray(v._wheels.batched_colors).tolist()
        for owner, rgb in zip(v.frame.wheel_owner.tolist(), colors, strict=True):
            by_vehicle.setdefault(v.frame.ids[owner], []).append(rgb)
        assert by_vehicle["mr"] == slip_rgb([3.0, 4.0]).tolist()
        assert by_vehicle["w"] == slip_rgb([5.0, 6.0, 7.0, 8.0]).tolist()
        v.follow("w")
        for step in range(1, 4):
            four["stamp_ns"] = T0 + step * 10**9
            four["x_m"] = 30.0 + step
            hub.on_estimates(EstimateBatch.of([("w", four)], FOUR_WHEEL))
        v.update()
        assert v._track is not None and np.asarray(v._track.points).shape == (3, 2, 3)
        assert np.asarray(v._track.colors)[0, 0].tolist() == slip_rgb(8.0).tolist()
    finally:
        v.stop()


def test_the_fleet_view_point_sees_every_vehicle() -> None:
    rng = np.random.default_rng(4)
    for _ in range(50):
        pts = rng.uniform(-2000, 2000, (rng.integers(1, 40), 3)) * [1, 1, 0.01]
        cam, look_at, _ = fleet_view_point(pts)
        axis = (look_at - cam) / np.linalg.norm(look_at - cam)
        rays = pts - cam
        angles = np.degrees(np.arccos(rays @ axis / np.linalg.norm(rays, axis=1)))
        # inside viser's 75° (vertical) view, with room to spare, on any landscape window
        assert angles.max() < 35.0
        assert cam[2] > pts[:, 2].max()  # from above


def test_the_cameras_are_aimed_again_only_when_the_fleet_outgrows_their_view() -> None:
    first = np.array([[0.0, 0.0, 0.0], [400.0, 300.0, 0.0]])  # span 500 m: margin 125 m
    box = (first.min(axis=0), first.max(axis=0))
    assert outgrown(None, first)  # never aimed
    assert not outgrown(box, first)
    assert not outgrown(box, first + np.array([100.0, -100.0, 0.0]))  # moving inside the view
    joined = np.vstack([first, [[2000.0, 0.0, 0.0]]])  # a vehicle joins 1.6 km off
    assert outgrown(box, joined)
    assert outgrown(box, first + np.array([0.0, 500.0, 0.0]))  # the fleet drove out of view
    lone = np.zeros((1, 3))  # one vehicle: the box's span is the minimum, not zero
    assert not outgrown((lone[0], lone[0]), lone + np.array([5.0, 5.0, 0.0]))


def test_legend_names_every_colour() -> None:
    html = legend_html()
    for _, (r, g, b) in SLIP_COLOR_STOPS:
        assert f"rgb({r},{g},{b})" in html
    assert "rgb({},{},{})".format(*SLIP_COLOR_NONE) in html and "no value" in html
    for status, (r, g, b) in STATUS_RGB.items():
        assert f"rgb({r},{g},{b})" in html and status in html


def test_vehicles_without_a_position_are_not_drawn_at_the_origin(
    viewer: tuple[FleetViewer, LiveHub],
) -> None:
    v, hub = viewer
    lost = _row(0, 0, 0, 0.0, 1.0, 1.0)
    lost["east_m"] = lost["north_m"] = np.nan
    hub.on_estimates([("lost", lost)])
    v.update()
    assert v._bodies is None and v._pins is None
    assert v._count is not None and v._count.value == "0 (1 without a position)"
    hub.on_estimates([("a", _row(0, 10, 20, 0.0, 2.0, 8.0))])
    v.update()
    assert v.frame is not None and v.frame.ids == ["a"]
    assert np.asarray(v._bodies.batched_positions).shape == (1, 3)  # type: ignore[union-attr]
    assert v._pins is not None and np.asarray(v._pins.points).shape == (1, 2, 3)
    assert v._count.value == "1 (1 without a position)"
