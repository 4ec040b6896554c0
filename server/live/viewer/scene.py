"""Pure maps from estimate rows to the 3D fleet scene: poses, wheel placement, colours.

World frame of the scene = the vehicles' local ENU frame: ``x`` east, ``y`` north, ``z`` up,
metres (``east_m``, ``north_m``, ``up_m`` of the estimates). Body frame (``estimator.types``):
X right, Y forward, Z up.

Attitude → rotation body → ENU. With heading ``ψ`` from north clockwise, pitch ``θ`` nose up
positive and roll ``φ`` right side down positive::

    R = Rz(-ψ) · Rx(θ) · Ry(φ)

so the forward axis is ``R·(0, 1, 0) = (sin ψ cos θ, cos ψ cos θ, sin θ)`` and the right axis
tips down for ``φ > 0`` (its up component is ``-cos θ sin φ``). Quaternions are scalar first
(``wxyz``), Hamilton product, as viser takes them.

Vehicle layout (from :class:`estimator.config.VehicleGeometry`): the estimate's position is the
antenna, ``h0 + h1`` above the origin ``O`` (ground under the rear-axle midpoint) plus its
horizontal ``antenna_offset_m``; the driven wheels sit at ``O + R·(±b/2, 0, r)``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from estimator.config import VehicleGeometry
from server.live.viewer.colors import slip_rgb

__all__ = [
    "BODY_CENTRE_M",
    "BODY_SIZE_M",
    "FleetFrame",
    "attitude_from_wxyz",
    "box_mesh",
    "cylinder_mesh_x",
    "fleet_frame",
    "quat_mul",
    "rotate",
    "rotation_matrix_from_wxyz",
    "wxyz_from_attitude",
]

FloatArray = npt.NDArray[np.float64]

#: Body box (width X, length Y, height Z) and its centre relative to ``O`` in the body frame.
BODY_SIZE_M = (1.3, 3.2, 1.1)
BODY_CENTRE_M = (0.0, 1.1, 1.35)

_STATUS_RGB = {
    "live": (70, 110, 170),
    "stale": (200, 150, 40),
    "offline": (110, 110, 110),
}


def quat_mul(a: FloatArray, b: FloatArray) -> FloatArray:
    """Hamilton product of ``wxyz`` quaternions, shapes ``(..., 4)``."""
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def _axis_quat(angle: FloatArray, axis: int) -> FloatArray:
    q = np.zeros((*np.shape(angle), 4))
    q[..., 0] = np.cos(np.asarray(angle) / 2)
    q[..., 1 + axis] = np.sin(np.asarray(angle) / 2)
    return q


def wxyz_from_attitude(
    heading_rad: npt.ArrayLike, pitch_rad: npt.ArrayLike, roll_rad: npt.ArrayLike
) -> FloatArray:
    """Unit quaternion of ``R = Rz(-ψ)·Rx(θ)·Ry(φ)``, shape ``(..., 4)``, ``w >= 0``."""
    psi = np.asarray(heading_rad, dtype=np.float64)
    q = quat_mul(
        quat_mul(_axis_quat(-psi, 2), _axis_quat(np.asarray(pitch_rad, dtype=np.float64), 0)),
        _axis_quat(np.asarray(roll_rad, dtype=np.float64), 1),
    )
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def rotation_matrix_from_wxyz(q: FloatArray) -> FloatArray:
    """Rotation matrices ``(..., 3, 3)`` of unit quaternions ``(..., 4)``."""
    w, x, y, z = np.moveaxis(np.asarray(q, dtype=np.float64), -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=-2,
    )


def attitude_from_wxyz(q: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Inverse of :func:`wxyz_from_attitude`: ``(heading, pitch, roll)`` in radians.

    Heading and roll in ``(-π, π]``, pitch in ``[-π/2, π/2]`` (gimbal lock at ±π/2).
    """
    R = rotation_matrix_from_wxyz(q)
    pitch = np.arcsin(np.clip(R[..., 2, 1], -1.0, 1.0))
    heading = np.arctan2(R[..., 0, 1], R[..., 1, 1])
    roll = np.arctan2(-R[..., 2, 0], R[..., 2, 2])
    return heading, pitch, roll


def rotate(R: FloatArray, v_body: npt.ArrayLike) -> FloatArray:
    """``R @ v`` for rotation matrices ``(n, 3, 3)`` and one body vector ``(3,)`` → ``(n, 3)``."""
    return np.einsum("nij,j->ni", R, np.asarray(v_body, dtype=np.float64))


@dataclass(frozen=True, slots=True)
class FleetFrame:
    """Everything the viewer draws for ``n`` vehicles, in world (local ENU) metres.

    Attributes
    ----------
    ids : list[str], length n
    body_position_m : (n, 3) centre of each body box
    body_wxyz : (n, 4) body → world rotation
    body_rgb : (n, 3) uint8, by status
    wheel_position_m : (2n, 3) wheel centres, left and right of vehicle 0, then vehicle 1, …
    wheel_wxyz : (2n, 4) the body's rotation, repeated per wheel
    wheel_rgb : (2n, 3) uint8, slip colour (``server.live.viewer.colors``) of that wheel
    velocity_mps : (n, 3) ``vg_mps`` along the forward axis
    antenna_m : (n, 3) the estimate's position
    ground_m : (n, 3) ``O``, the ground point under the rear-axle midpoint
    """

    ids: list[str]
    body_position_m: FloatArray
    body_wxyz: FloatArray
    body_rgb: npt.NDArray[np.uint8]
    wheel_position_m: FloatArray
    wheel_wxyz: FloatArray
    wheel_rgb: npt.NDArray[np.uint8]
    velocity_mps: FloatArray
    antenna_m: FloatArray
    ground_m: FloatArray


def _nan_to(a: npt.ArrayLike, value: float) -> FloatArray:
    arr = np.asarray(a, dtype=np.float64)
    return np.where(np.isfinite(arr), arr, value)


def fleet_frame(
    ids: Sequence[str],
    rows: np.ndarray,
    geometry: VehicleGeometry | None = None,
    status: Sequence[str] | None = None,
) -> FleetFrame:
    """Map the newest estimate row of each vehicle (``rows``, shape ``(n,)``) to the scene.

    Missing attitude (NaN) is taken as level; missing heading as north; missing position as the
    origin; a missing slip colours the wheel grey.
    """
    g = geometry or VehicleGeometry()
    n = rows.shape[0]
    q = wxyz_from_attitude(
        _nan_to(rows["heading_rad"], 0.0),
        _nan_to(rows["pitch_rad"], 0.0),
        _nan_to(rows["roll_rad"], 0.0),
    )
    R = rotation_matrix_from_wxyz(q)
    antenna = np.stack(
        [_nan_to(rows["east_m"], 0.0), _nan_to(rows["north_m"], 0.0), _nan_to(rows["up_m"], 0.0)],
        -1,
    )
    ax, ay = g.antenna_offset_m
    ground = antenna - rotate(R, (ax, ay, g.h0_m + g.h1_m))
    body = ground + rotate(R, BODY_CENTRE_M)
    half = g.track_width_m / 2
    left = ground + rotate(R, (-half, 0.0, g.wheel_radius_left_m))
    right = ground + rotate(R, (half, 0.0, g.wheel_radius_right_m))
    wheels = np.empty((2 * n, 3))
    wheels[0::2] = left
    wheels[1::2] = right
    slip = np.empty(2 * n)
    slip[0::2] = rows["slip_left_pct"]
    slip[1::2] = rows["slip_right_pct"]
    forward = R[:, :, 1]
    vel = forward * _nan_to(rows["vg_mps"], 0.0)[:, None]
    body_rgb = np.array(
        [_STATUS_RGB.get(s, _STATUS_RGB["live"]) for s in (status or ["live"] * n)], dtype=np.uint8
    ).reshape(n, 3)
    return FleetFrame(
        ids=list(ids),
        body_position_m=body,
        body_wxyz=q,
        body_rgb=body_rgb,
        wheel_position_m=wheels,
        wheel_wxyz=np.repeat(q, 2, axis=0),
        wheel_rgb=slip_rgb(slip),
        velocity_mps=vel,
        antenna_m=antenna,
        ground_m=ground,
    )


def box_mesh(size_m: tuple[float, float, float]) -> tuple[FloatArray, npt.NDArray[np.uint32]]:
    """Vertices ``(8, 3)`` and outward triangles ``(12, 3)`` of a box centred on the origin."""
    sx, sy, sz = (s / 2 for s in size_m)
    v = np.array(
        [[x, y, z] for x in (-sx, sx) for y in (-sy, sy) for z in (-sz, sz)], dtype=np.float64
    )
    # vertex index = 4*ix + 2*iy + iz
    quads = [
        (0, 1, 3, 2),  # -x
        (4, 6, 7, 5),  # +x
        (0, 4, 5, 1),  # -y
        (2, 3, 7, 6),  # +y
        (0, 2, 6, 4),  # -z
        (1, 5, 7, 3),  # +z
    ]
    faces = []
    for a, b, c, d in quads:
        faces += [(a, b, c), (a, c, d)]
    return v, np.array(faces, dtype=np.uint32)


def cylinder_mesh_x(
    radius_m: float, width_m: float, segments: int = 20
) -> tuple[FloatArray, npt.NDArray[np.uint32]]:
    """A closed cylinder along X (a wheel on its axle), centred on the origin."""
    ang = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    ring = np.stack([np.cos(ang) * radius_m, np.sin(ang) * radius_m], -1)
    hw = width_m / 2
    verts = [np.column_stack([np.full(segments, x), ring[:, 0], ring[:, 1]]) for x in (-hw, hw)]
    centres = np.array([[-hw, 0.0, 0.0], [hw, 0.0, 0.0]])
    v = np.vstack([*verts, centres])
    c0, c1 = 2 * segments, 2 * segments + 1
    faces = []
    for i in range(segments):
        j = (i + 1) % segments
        a, b, c, d = i, j, segments + j, segments + i
        faces += [(a, b, c), (a, c, d)]  # side, outward
        faces.append((c0, j, i))  # -x cap
        faces.append((c1, segments + i, segments + j))  # +x cap
    return v, np.array(faces, dtype=np.uint32)
