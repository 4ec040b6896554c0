"""WGS-84 geodetic coordinates to and from a local East-North-Up tangent plane.

Exact transformation through Earth-centred Earth-fixed (ECEF) coordinates, so it holds for any
field size. Shapes broadcast: scalars or arrays of the same shape.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

__all__ = ["WGS84_A_M", "WGS84_F", "EnuFrame", "enu_from_geodetic", "geodetic_from_enu"]

WGS84_A_M = 6_378_137.0  # semi-major axis (WGS-84 definition)
WGS84_F = 1.0 / 298.257223563  # flattening (WGS-84 definition)
_E2 = WGS84_F * (2.0 - WGS84_F)

ArrayLike = npt.ArrayLike
Array = npt.NDArray[np.float64]


def _to_ecef(lat_deg: ArrayLike, lon_deg: ArrayLike, h_m: ArrayLike) -> tuple[Array, Array, Array]:
    lat = np.radians(np.asarray(lat_deg, dtype=np.float64))
    lon = np.radians(np.asarray(lon_deg, dtype=np.float64))
    h = np.asarray(h_m, dtype=np.float64)
    n = WGS84_A_M / np.sqrt(1.0 - _E2 * np.sin(lat) ** 2)
    x = (n + h) * np.cos(lat) * np.cos(lon)
    y = (n + h) * np.cos(lat) * np.sin(lon)
    z = (n * (1.0 - _E2) + h) * np.sin(lat)
    return x, y, z


def enu_from_geodetic(
    lat_deg: ArrayLike,
    lon_deg: ArrayLike,
    h_m: ArrayLike,
    lat0_deg: ArrayLike,
    lon0_deg: ArrayLike,
    h0_m: ArrayLike,
) -> tuple[Array, Array, Array]:
    """Geodetic → ``(east_m, north_m, up_m)`` of the ENU frame anchored at ``(lat0, lon0, h0)``.

    Every argument broadcasts, anchors included: one call converts the points of many frames
    (a fleet's vehicles, each in its own frame).
    """
    x, y, z = _to_ecef(lat_deg, lon_deg, h_m)
    x0, y0, z0 = _to_ecef(lat0_deg, lon0_deg, h0_m)
    dx, dy, dz = x - x0, y - y0, z - z0
    lat = np.radians(np.asarray(lat0_deg, dtype=np.float64))
    lon = np.radians(np.asarray(lon0_deg, dtype=np.float64))
    sl, cl = np.sin(lat), np.cos(lat)
    so, co = np.sin(lon), np.cos(lon)
    east = -so * dx + co * dy
    north = -sl * co * dx - sl * so * dy + cl * dz
    up = cl * co * dx + cl * so * dy + sl * dz
    return east, north, up


def geodetic_from_enu(
    east_m: ArrayLike,
    north_m: ArrayLike,
    up_m: ArrayLike,
    lat0_deg: ArrayLike,
    lon0_deg: ArrayLike,
    h0_m: ArrayLike,
) -> tuple[Array, Array, Array]:
    """``(east_m, north_m, up_m)`` of the ENU frame anchored at ``(lat0, lon0, h0)`` → geodetic
    ``(lat_deg, lon_deg, h_m)``; the inverse of :func:`enu_from_geodetic`.

    ECEF = anchor + Rᵀ·[e, n, u] (R's rows: the east, north, up unit vectors), then Bowring's
    iteration for latitude (sub-millimetre after three rounds; four are run). Every argument
    broadcasts, anchors included: one call converts the rows of many frames.
    """
    e = np.asarray(east_m, dtype=np.float64)
    n_ = np.asarray(north_m, dtype=np.float64)
    u = np.asarray(up_m, dtype=np.float64)
    lat0 = np.radians(np.asarray(lat0_deg, dtype=np.float64))
    lon0 = np.radians(np.asarray(lon0_deg, dtype=np.float64))
    sl, cl = np.sin(lat0), np.cos(lat0)
    so, co = np.sin(lon0), np.cos(lon0)
    x0, y0, z0 = _to_ecef(lat0_deg, lon0_deg, h0_m)
    x = x0 - so * e - sl * co * n_ + cl * co * u
    y = y0 + co * e - sl * so * n_ + cl * so * u
    z = z0 + cl * n_ + sl * u
    lon = np.arctan2(y, x)
    p = np.hypot(x, y)
    lat = np.arctan2(z, p * (1.0 - _E2))
    for _ in range(4):
        n = WGS84_A_M / np.sqrt(1.0 - _E2 * np.sin(lat) ** 2)
        h = p / np.cos(lat) - n
        lat = np.arctan2(z, p * (1.0 - _E2 * n / (n + h)))
    n = WGS84_A_M / np.sqrt(1.0 - _E2 * np.sin(lat) ** 2)
    h = p / np.cos(lat) - n
    return np.degrees(lat), np.degrees(lon), h


@dataclass(frozen=True, slots=True)
class EnuFrame:
    """A local ENU frame anchored at ``(lat0_deg, lon0_deg, h0_m)``.

    ``to_enu`` maps geodetic coordinates to metres east, north, up of the anchor;
    ``to_geodetic`` inverts it (Bowring's iteration, sub-millimetre after three rounds).
    """

    lat0_deg: float
    lon0_deg: float
    h0_m: float = 0.0

    def to_enu(
        self, lat_deg: ArrayLike, lon_deg: ArrayLike, h_m: ArrayLike
    ) -> tuple[Array, Array, Array]:
        """Geodetic → ``(east_m, north_m, up_m)``."""
        return enu_from_geodetic(lat_deg, lon_deg, h_m, self.lat0_deg, self.lon0_deg, self.h0_m)

    def to_geodetic(
        self, east_m: ArrayLike, north_m: ArrayLike, up_m: ArrayLike
    ) -> tuple[Array, Array, Array]:
        """``(east_m, north_m, up_m)`` → geodetic ``(lat_deg, lon_deg, h_m)``."""
        return geodetic_from_enu(east_m, north_m, up_m, self.lat0_deg, self.lon0_deg, self.h0_m)
