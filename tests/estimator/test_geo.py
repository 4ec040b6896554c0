"""Geodetic ↔ local ENU."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from estimator.geo import WGS84_A_M, EnuFrame, enu_from_geodetic, geodetic_from_enu


def test_anchor_is_the_origin_and_axes_point_east_north_up() -> None:
    f = EnuFrame(52.0, 5.6, 10.0)
    e, n, u = f.to_enu(52.0, 5.6, 10.0)
    assert abs(e) < 1e-9 and abs(n) < 1e-9 and abs(u) < 1e-9
    e, n, u = f.to_enu(52.0 + 1e-4, 5.6, 10.0)  # a little north
    assert n > 11.0 and abs(e) < 1e-6
    e, n, u = f.to_enu(52.0, 5.6 + 1e-4, 10.0)  # a little east
    assert e > 6.0 and abs(n) < 1e-3
    _, _, u = f.to_enu(52.0, 5.6, 15.0)  # straight up
    assert abs(u - 5.0) < 1e-9


def test_one_arc_minute_of_longitude_on_the_equator() -> None:
    # on the equator a degree of longitude is the semi-major axis times pi/180
    e, n, _ = EnuFrame(0.0, 0.0).to_enu(0.0, 1.0 / 60.0, 0.0)
    expected = WGS84_A_M * np.pi / 180.0 / 60.0
    assert abs(float(e) - expected) < 0.01 * 1e-3 * expected  # chord vs arc, < 10 ppm
    assert abs(float(n)) < 1e-6


@given(
    lat0=st.floats(-80, 80),
    lon0=st.floats(-180, 180),
    east=st.floats(-5_000, 5_000),
    north=st.floats(-5_000, 5_000),
    up=st.floats(-100, 500),
)
def test_round_trip(lat0: float, lon0: float, east: float, north: float, up: float) -> None:
    f = EnuFrame(lat0, lon0, 50.0)
    lat, lon, h = f.to_geodetic(east, north, up)
    e, n, u = f.to_enu(lat, lon, h)
    assert np.allclose([e, n, u], [east, north, up], atol=1e-6)


def test_points_of_many_frames_in_one_call() -> None:
    frames = [EnuFrame(52.0, 5.6, 10.0), EnuFrame(-33.9, 151.2, 40.0), EnuFrame(0.0, -179.9)]
    lat = np.array([52.001, -33.899, 0.0005])
    lon = np.array([5.602, 151.199, -179.9003])
    h = np.array([12.0, 35.0, 1.0])
    lat0, lon0, h0 = ([getattr(f, a) for f in frames] for a in ("lat0_deg", "lon0_deg", "h0_m"))
    e, n, u = enu_from_geodetic(lat, lon, h, lat0, lon0, h0)
    for i, f in enumerate(frames):
        one = f.to_enu(lat[i], lon[i], h[i])
        assert np.allclose([e[i], n[i], u[i]], one, rtol=0, atol=1e-9)


def test_geodetic_from_enu_converts_rows_of_many_frames_in_one_call() -> None:
    """Rows of three frames (different anchors) in one call give what each frame gives alone,
    and invert enu_from_geodetic."""
    anchors = [(52.1, 5.2, 10.0), (-33.9, 151.2, 40.0), (64.0, -21.9, 0.0)]
    rng = np.random.default_rng(3)
    e, n, u = rng.uniform(-3000, 3000, 9), rng.uniform(-3000, 3000, 9), rng.uniform(-5, 5, 9)
    lat0, lon0, h0 = (np.repeat([a[k] for a in anchors], 3) for k in range(3))
    lat, lon, h = geodetic_from_enu(e, n, u, lat0, lon0, h0)
    for k, anchor in enumerate(anchors):
        rows = slice(3 * k, 3 * k + 3)
        one = EnuFrame(*anchor).to_geodetic(e[rows], n[rows], u[rows])
        np.testing.assert_array_equal(lat[rows], one[0])
        np.testing.assert_array_equal(lon[rows], one[1])
        np.testing.assert_array_equal(h[rows], one[2])
    back = enu_from_geodetic(lat, lon, h, lat0, lon0, h0)
    for got, want in zip(back, (e, n, u), strict=True):
        np.testing.assert_allclose(got, want, atol=1e-6)
