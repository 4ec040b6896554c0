"""The 3D view of a crawler and a steered four-wheel vehicle, from their specs: the crawler's hull
between two track boxes coloured by each track's slip, the steered vehicle's four tyres coloured
by the share of the grip each uses (drawn where its position puts it; parked in a row where its
spec gives none), beside a tractor; the pure scene maps and a real viser server."""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest

from estimator.config import VehicleGeometry
from estimator.friction_spec import FRICTION_SPEC, FrictionFlag
from estimator.tracked_spec import TRACKED_SPEC, TrackedFlag
from estimator.types import EstimateBatch, empty_estimates
from server.live.hub import LiveHub
from server.live.viewer.colors import grip_rgb, slip_rgb
from server.live.viewer.fleet_view import FleetViewer, legend_html
from server.live.viewer.scene import (
    BODY_CENTRE_M,
    CRAWLER_BODY_CENTRE_M,
    TRACK_SIZE_M,
    fleet_frame,
    is_crawler,
    positioned,
    rotate,
    rotation_matrix_from_wxyz,
    wxyz_from_attitude,
)
from server.settings import ViewerSettings
from tests.support import free_port

GRIP_PCT = (20.0, 55.0, 85.0, 120.0)  # fl, fr, rl, rr
# the friction spec as a steered vehicle without GNSS position would have it: nothing to place
UNPLACED = dataclasses.replace(FRICTION_SPEC, position=None)


def _crawler(east_m: float, north_m: float) -> np.ndarray:
    r = TRACKED_SPEC.empty_rows(1)
    r["stamp_ns"] = time.time_ns()
    r["east_m"], r["north_m"], r["up_m"] = east_m, north_m, 0.0
    r["heading_rad"] = np.pi / 2  # facing east
    r["speed_mps"] = 3.0
    r["slip_left_pct"], r["slip_right_pct"] = -12.0, 4.0
    r["flags"] = int(TrackedFlag.GNSS_OK)
    return r


def _steered() -> np.ndarray:
    r = FRICTION_SPEC.empty_rows(1)
    r["stamp_ns"] = time.time_ns()
    r["vx_mps"] = 10.0
    for key, pct in zip(("fl", "fr", "rl", "rr"), GRIP_PCT, strict=True):
        r[f"util_{key}_pct"] = pct
        r[f"slip_{key}_pct"] = 30.0  # a slip colour would be dark red on every tyre
    r["flags"] = int(FrictionFlag.INFORMED)
    return r


def _tractor(east_m: float, north_m: float) -> np.ndarray:
    r = empty_estimates(1)
    r["stamp_ns"] = time.time_ns()
    r["east_m"], r["north_m"], r["up_m"] = east_m, north_m, 2.6
    r["heading_rad"] = 0.0
    r["vg_mps"] = 2.0
    r["slip_left_pct"] = r["slip_right_pct"] = 1.0
    return r


def test_a_crawler_is_a_hull_between_two_tracks_coloured_by_their_slip() -> None:
    g = VehicleGeometry(h0_m=1.0, h1_m=1.0, track_width_m=2.0)
    f = fleet_frame(["c"], _crawler(10.0, 20.0), TRACKED_SPEC, g)
    assert is_crawler(TRACKED_SPEC) and f.crawler.tolist() == [True]
    assert f.wheel_is_track.tolist() == [True, True]
    assert f.wheel_rgb.tolist() == slip_rgb([-12.0, 4.0]).tolist()
    # facing east: the left track north of the right one, track width apart, half a track
    # high above the ground point (the antenna 2 m above it), under the hull's centre
    ground = np.array([10.0, 20.0, -2.0])
    np.testing.assert_allclose(
        f.wheel_position_m,
        [
            ground + np.array([BODY_CENTRE_M[1], 1.0, TRACK_SIZE_M[2] / 2]),
            ground + np.array([BODY_CENTRE_M[1], -1.0, TRACK_SIZE_M[2] / 2]),
        ],
        atol=1e-12,
    )
    np.testing.assert_allclose(
        f.body_position_m[0],
        ground + np.array([CRAWLER_BODY_CENTRE_M[1], 0.0, CRAWLER_BODY_CENTRE_M[2]]),
    )


def test_a_crawler_on_a_side_slope_is_posed_by_its_pitch_and_roll() -> None:
    g = VehicleGeometry(h0_m=1.0, h1_m=1.0, track_width_m=2.0)
    rows = np.concatenate([_crawler(10.0, 20.0), _crawler(10.0, 20.0)])
    rows["pitch_rad"][0], rows["roll_rad"][0] = 0.1, 0.2  # nose up, right side down
    rows["pitch_std_rad"][0] = rows["roll_std_rad"][0] = 0.003
    f = fleet_frame(["c", "d"], rows, TRACKED_SPEC, g)  # "d": no attitude yet (NaN), level
    np.testing.assert_allclose(f.body_wxyz[0], wxyz_from_attitude(np.pi / 2, 0.1, 0.2))
    np.testing.assert_allclose(f.body_wxyz[1], wxyz_from_attitude(np.pi / 2, 0.0, 0.0))
    left, right = f.wheel_position_m[0], f.wheel_position_m[1]
    # the right track lies lower than the left by the gauge times the right axis's fall,
    # cos θ·sin φ (scene.py's R); level, side by side
    assert left[2] - right[2] == pytest.approx(2.0 * np.cos(0.1) * np.sin(0.2), rel=1e-9)
    assert f.wheel_position_m[2][2] == pytest.approx(f.wheel_position_m[3][2], abs=1e-12)
    # facing east, nose up: the hull's forward axis climbs east
    forward = rotate(rotation_matrix_from_wxyz(f.body_wxyz[:1]), (0.0, 1.0, 0.0))[0]
    np.testing.assert_allclose(forward, [np.cos(0.1), 0.0, np.sin(0.1)], atol=1e-12)


def test_tyres_of_a_spec_with_grip_are_coloured_by_it_where_placed() -> None:
    assert not is_crawler(FRICTION_SPEC)
    with pytest.raises(ValueError, match="no position"):
        fleet_frame(["s"], _steered(), UNPLACED)
    placed = _steered()
    placed["east_m"], placed["north_m"], placed["up_m"], placed["heading_rad"] = 3.0, 4.0, 0, 0
    assert positioned(placed, FRICTION_SPEC).tolist() == [True]
    assert np.isfinite(fleet_frame(["s"], placed, FRICTION_SPEC).ground_m).all()
    ground = np.array([[5.0, -7.0, 0.0]])
    f = fleet_frame(["s"], _steered(), UNPLACED, ground_m=ground)
    assert f.wheel_rgb.tolist() == grip_rgb(GRIP_PCT).tolist()
    # the grip scale: green, yellow at 50 %, orange at 80 %, dark red from 100 %
    assert grip_rgb([0.0, 50.0, 80.0, 100.0, 150.0]).tolist() == [
        [26, 152, 80],
        [240, 200, 40],
        [230, 85, 30],
        [140, 20, 30],
        [140, 20, 30],
    ]
    assert f.wheel_is_track.tolist() == [False] * 4 and f.crawler.tolist() == [False]
    np.testing.assert_allclose(f.ground_m, ground)
    np.testing.assert_allclose(f.velocity_mps, [[0.0, 10.0, 0.0]])  # level, facing north


def test_the_viewer_draws_crawler_tracks_and_parked_tyres() -> None:
    primaries = {"c": "tracked", "s": "friction", "t": "mdsf"}
    hub = LiveHub(primary_of=primaries.get)
    hub.on_estimates(EstimateBatch.of([("c", _crawler(40.0, 10.0))], TRACKED_SPEC))
    hub.on_estimates(EstimateBatch.of([("s", _steered())], UNPLACED))
    hub.on_estimates([("t", _tractor(0.0, 0.0))])
    v = FleetViewer(hub, ViewerSettings(host="127.0.0.1", port=free_port()))
    v.open()
    try:
        v.update()
        f = v.frame
        assert f is not None and sorted(f.ids) == ["c", "s", "t"]
        meshes = {name: h.name for name, h in v._meshes.items()}
        assert meshes == {
            "bodies": "/fleet/bodies",
            "crawlers": "/fleet/crawlers",
            "wheels": "/fleet/wheels",
            "tracks": "/fleet/tracks",
        }

        def colours(name: str) -> list[list[int]]:
            return np.asarray(v._meshes[name].batched_colors).tolist()

        assert colours("tracks") == slip_rgb([-12.0, 4.0]).tolist()
        assert colours("wheels") == [*slip_rgb([1.0, 1.0]).tolist(), *grip_rgb(GRIP_PCT).tolist()]
        assert np.asarray(v._meshes["crawlers"].batched_positions).shape == (1, 3)
        assert np.asarray(v._meshes["bodies"].batched_positions).shape == (2, 3)
        # the steered vehicle has no position: parked 15 m south of the fleet's ground points
        s = f.ids.index("s")
        south = min(f.ground_m[i, 1] for i in range(3) if i != s)
        west = min(f.ground_m[i, 0] for i in range(3) if i != s)
        np.testing.assert_allclose(f.ground_m[s], [west, south - 15.0, 0.0])
        assert v._count is not None and v._count.value == "3, 1 parked (no position)"
        # the grip changes: the same meshes, new colours
        row = _steered()
        row["util_rr_pct"] = 10.0
        hub.on_estimates(EstimateBatch.of([("s", row)], UNPLACED))
        before = dict(v._meshes)
        v.update()
        assert v._meshes == before
        assert colours("wheels")[-1] == grip_rgb(10.0).tolist()
        # following a parked vehicle draws its arrow and label, no track
        v.follow("s")
        v.update()
        assert v._label is not None and v._label.text == "s" and v._track is None
    finally:
        v.stop()


def test_the_legend_names_the_grip_scale() -> None:
    html = legend_html()
    assert "Tyres with grip used" in html and 'rgb(240,200,40);"></span> 50 %' in html
