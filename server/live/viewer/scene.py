"""Pure maps from estimate rows to the 3D fleet scene: poses, wheel placement, colours.

Rows are read through their estimator's spec: position and heading from its
:class:`estimator.spec.PositionChannel`, one wheel (or track) per slip channel placed by
:class:`estimator.spec.WheelPosition` and coloured by that channel's value (or, where the spec
has a :class:`estimator.spec.WheelValueChannel` at that position, by the share of the grip it
uses, :func:`server.live.viewer.colors.grip_rgb`), the velocity arrow from its motion speed.
A spec whose slip channels are tracks (``track_left``, ``track_right``) is drawn as a crawler:
a low hull (:data:`CRAWLER_BODY_SIZE_M`) between two track boxes (:data:`TRACK_SIZE_M`). A spec
without a position is drawn only where the caller gives each vehicle a ground point
(``ground_m``: a parking row), level and facing north.

World frame of the scene = the vehicles' local ENU frame: ``x`` east, ``y`` north, ``z`` up,
metres. Body frame (``estimator.types``): X right, Y forward, Z up.

Attitude → rotation body → ENU. With heading ``ψ`` from north clockwise, pitch ``θ`` nose up
positive and roll ``φ`` right side down positive::

    R = Rz(-ψ) · Rx(θ) · Ry(φ)

so the forward axis is ``R·(0, 1, 0) = (sin ψ cos θ, cos ψ cos θ, sin θ)`` and the right axis
tips down for ``φ > 0`` (its up component is ``-cos θ sin φ``). Quaternions are scalar first
(``wxyz``), Hamilton product, as viser takes them.

Vehicle layout (from :class:`estimator.config.VehicleGeometry`): the estimate's position is the
antenna, ``h0 + h1`` above the origin ``O`` (ground under the rear-axle midpoint) plus its
horizontal ``antenna_offset_m``; rear wheels sit at ``O + R·(±b/2, 0, r)``, front wheels
:data:`FRONT_AXLE_M` ahead, tracks under the body's centre (:func:`wheel_offset_m`). Pitch and
roll are the position channel's ``pitch_field`` / ``roll_field`` (:func:`attitude_fields`),
level when it has none.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from estimator.config import VehicleGeometry
from estimator.spec import EstimatorSpec, WheelPosition
from server.live.viewer.colors import grip_rgb, slip_rgb

__all__ = [
    "BODY_CENTRE_M",
    "BODY_SIZE_M",
    "CRAWLER_BODY_CENTRE_M",
    "CRAWLER_BODY_SIZE_M",
    "FRONT_AXLE_M",
    "STATUS_RGB",
    "TRACK_SIZE_M",
    "FleetFrame",
    "attitude_fields",
    "attitude_from_wxyz",
    "box_mesh",
    "concat_frames",
    "cylinder_mesh_x",
    "fleet_frame",
    "is_crawler",
    "is_track",
    "positioned",
    "quat_mul",
    "rotate",
    "rotation_matrix_from_wxyz",
    "wheel_colours",
    "wheel_offset_m",
    "wxyz_from_attitude",
]

FloatArray = npt.NDArray[np.float64]

#: Body box (width X, length Y, height Z) and its centre relative to ``O`` in the body frame.
BODY_SIZE_M = (1.3, 3.2, 1.1)
BODY_CENTRE_M = (0.0, 1.1, 1.35)
#: Drawn front axle, ahead of ``O`` (the geometry has no wheelbase: for drawing only).
FRONT_AXLE_M = 2.3
#: A crawler's track (width X, length Y, height Z), its centre under the body's centre, and its
#: hull between the tracks (size and centre relative to ``O``): for drawing only.
TRACK_SIZE_M = (0.5, 3.6, 0.8)
CRAWLER_BODY_SIZE_M = (1.3, 4.0, 0.9)
CRAWLER_BODY_CENTRE_M = (0.0, BODY_CENTRE_M[1], 1.1)

#: Body colour by the vehicle's status (the live hub's).
STATUS_RGB = {
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
    psi_rad: npt.ArrayLike, theta_rad: npt.ArrayLike, phi_rad: npt.ArrayLike
) -> FloatArray:
    """Unit quaternion of ``R = Rz(-ψ)·Rx(θ)·Ry(φ)``, shape ``(..., 4)``, ``w >= 0``."""
    psi = np.asarray(psi_rad, dtype=np.float64)
    q = quat_mul(
        quat_mul(_axis_quat(-psi, 2), _axis_quat(np.asarray(theta_rad, dtype=np.float64), 0)),
        _axis_quat(np.asarray(phi_rad, dtype=np.float64), 1),
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
    estimators : list[str], length n, the estimator each vehicle is drawn from
    body_position_m : (n, 3) centre of each body box
    body_wxyz : (n, 4) body → world rotation
    body_rgb : (n, 3) uint8, by status
    wheel_position_m : (w, 3) wheel centres: vehicle 0's in its spec's slip channel order, then
        vehicle 1's, …
    wheel_owner : (w,) int, the vehicle (index into ``ids``) of each wheel
    wheel_wxyz : (w, 4) the body's rotation, repeated per wheel
    wheel_rgb : (w, 3) uint8, slip colour (``server.live.viewer.colors``) of that wheel's
        channel, or grip colour where the spec has a wheel value channel at its position
    velocity_mps : (n, 3) the motion speed along the forward axis
    antenna_m : (n, 3) the estimate's position
    ground_m : (n, 3) ``O``, the ground point under the rear-axle midpoint
    crawler : (n,) bool, drawn as a crawler (its spec's wheels are tracks)
    wheel_is_track : (w,) bool, a track rather than a wheel
    """

    ids: list[str]
    estimators: list[str]
    body_position_m: FloatArray
    body_wxyz: FloatArray
    body_rgb: npt.NDArray[np.uint8]
    wheel_position_m: FloatArray
    wheel_owner: npt.NDArray[np.int64]
    wheel_wxyz: FloatArray
    wheel_rgb: npt.NDArray[np.uint8]
    velocity_mps: FloatArray
    antenna_m: FloatArray
    ground_m: FloatArray
    crawler: npt.NDArray[np.bool_]
    wheel_is_track: npt.NDArray[np.bool_]


def _nan_to(a: npt.ArrayLike, value: float) -> FloatArray:
    arr = np.asarray(a, dtype=np.float64)
    return np.where(np.isfinite(arr), arr, value)


def wheel_offset_m(position: WheelPosition, geometry: VehicleGeometry) -> FloatArray:
    """Body-frame centre ``(3,)`` of the wheel or track at ``position``, relative to ``O``."""
    left = position.value.endswith("left")
    half = geometry.track_width_m / 2
    radius = geometry.wheel_radius_left_m if left else geometry.wheel_radius_right_m
    if is_track(position):
        radius = TRACK_SIZE_M[2] / 2
    ahead = {"rear": 0.0, "front": FRONT_AXLE_M, "track": BODY_CENTRE_M[1]}
    return np.array([-half if left else half, ahead[position.value.split("_")[0]], radius])


def is_track(position: WheelPosition) -> bool:
    """Whether ``position`` is a crawler's track rather than a wheel."""
    return position in (WheelPosition.TRACK_LEFT, WheelPosition.TRACK_RIGHT)


def wheel_colours(rows: np.ndarray, spec: EstimatorSpec) -> npt.NDArray[np.uint8]:
    """RGB ``(n, k)`` uint8 of the ``k`` wheels (slip channels) of ``rows`` ``(n,)``: the grip
    colour of the spec's wheel value channel at the wheel's position, else its slip colour."""
    grip = {w.position: w.field for w in spec.wheel_values}
    out = np.empty((rows.shape[0], len(spec.slips), 3), dtype=np.uint8)
    for j, channel in enumerate(spec.slips):
        field = grip.get(channel.position)
        out[:, j] = slip_rgb(rows[channel.field]) if field is None else grip_rgb(rows[field])
    return out


def attitude_fields(spec: EstimatorSpec) -> tuple[str | None, str | None]:
    """The spec's pitch and roll fields (rad), from its position channel (None: none)."""
    if spec.position is None:
        return None, None
    return spec.position.pitch_field, spec.position.roll_field


def _column(rows: np.ndarray, name: str | None, default: float) -> FloatArray:
    """``rows[name]`` with NaN as ``default``; all ``default`` when there is no such field."""
    if name is None:
        return np.full(rows.shape[0], default)
    return _nan_to(rows[name], default)


def positioned(rows: np.ndarray, spec: EstimatorSpec) -> npt.NDArray[np.bool_]:
    """Which rows ``(n,)`` have a position (finite east and north) to be drawn at; a row without
    one (no fix yet, dead reckoning given up) is not drawn rather than drawn at the origin."""
    if spec.position is None:
        return np.zeros(rows.shape[0], dtype=bool)
    p = spec.position
    return np.isfinite(rows[p.east_field]) & np.isfinite(rows[p.north_field])


def _pose(
    rows: np.ndarray,
    spec: EstimatorSpec,
    g: VehicleGeometry,
    ground_m: FloatArray | None,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """``(q, R, antenna, ground)`` of each row: from the spec's position channel, or level and
    facing north on the given ``ground_m`` (n, 3) (antenna above it by the geometry)."""
    ax, ay = g.antenna_offset_m
    lever = (ax, ay, g.h0_m + g.h1_m)
    if ground_m is not None:
        q = wxyz_from_attitude(*np.zeros((3, rows.shape[0])))
        R = rotation_matrix_from_wxyz(q)
        ground = np.asarray(ground_m, dtype=np.float64)
        return q, R, ground + rotate(R, lever), ground
    if spec.position is None:
        raise ValueError(f"estimator {spec.name!r} has no position to draw")
    pos = spec.position
    pitch, roll = attitude_fields(spec)
    q = wxyz_from_attitude(
        _column(rows, pos.heading_field, 0.0),
        _column(rows, pitch, 0.0),
        _column(rows, roll, 0.0),
    )
    R = rotation_matrix_from_wxyz(q)
    antenna = np.stack(
        [_column(rows, f, 0.0) for f in (pos.east_field, pos.north_field, pos.up_field)], -1
    )
    return q, R, antenna, antenna - rotate(R, lever)


def is_crawler(spec: EstimatorSpec) -> bool:
    """Whether the spec's wheels are tracks (drawn as a crawler)."""
    return bool(spec.slips) and all(is_track(s.position) for s in spec.slips)


def fleet_frame(
    ids: Sequence[str],
    rows: np.ndarray,
    spec: EstimatorSpec,
    geometry: VehicleGeometry | None = None,
    status: Sequence[str] | None = None,
    ground_m: FloatArray | None = None,
) -> FleetFrame:
    """Map the newest row of ``spec`` of each vehicle (``rows``, shape ``(n,)``) to the scene.

    ``spec`` must have a position unless ``ground_m`` (n, 3) places each vehicle (level,
    facing north). Missing attitude (NaN, or no such field) is taken as level; missing heading
    as north; missing position as the origin (callers draw only the rows :func:`positioned`
    keeps); a missing slip or grip colours the wheel grey.
    """
    g = geometry or VehicleGeometry()
    n = rows.shape[0]
    q, R, antenna, ground = _pose(rows, spec, g, ground_m)
    k = len(spec.slips)
    wheels = np.empty((k * n, 3))
    for j, channel in enumerate(spec.slips):
        wheels[j::k] = ground + rotate(R, wheel_offset_m(channel.position, g))
    vel = R[:, :, 1] * _column(rows, spec.motion_field, 0.0)[:, None]
    crawler = is_crawler(spec)
    centre = CRAWLER_BODY_CENTRE_M if crawler else BODY_CENTRE_M
    body_rgb = np.array(
        [STATUS_RGB.get(s, STATUS_RGB["live"]) for s in (status or ["live"] * n)], dtype=np.uint8
    ).reshape(n, 3)
    return FleetFrame(
        ids=list(ids),
        estimators=[spec.name] * n,
        body_position_m=ground + rotate(R, centre),
        body_wxyz=q,
        body_rgb=body_rgb,
        wheel_position_m=wheels,
        wheel_owner=np.repeat(np.arange(n, dtype=np.int64), k),
        wheel_wxyz=np.repeat(q, k, axis=0),
        wheel_rgb=wheel_colours(rows, spec).reshape(k * n, 3),
        velocity_mps=vel,
        antenna_m=antenna,
        ground_m=ground,
        crawler=np.full(n, crawler),
        wheel_is_track=np.tile([is_track(s.position) for s in spec.slips], n).astype(bool),
    )


def concat_frames(frames: Sequence[FleetFrame]) -> FleetFrame:
    """One frame of the vehicles of ``frames`` (e.g. one per estimator), in that order."""
    offsets = np.cumsum([0, *(len(f.ids) for f in frames[:-1])])

    def cat(name: str) -> np.ndarray:
        return np.concatenate([getattr(f, name) for f in frames])

    return FleetFrame(
        ids=[v for f in frames for v in f.ids],
        estimators=[e for f in frames for e in f.estimators],
        body_position_m=cat("body_position_m"),
        body_wxyz=cat("body_wxyz"),
        body_rgb=cat("body_rgb"),
        wheel_position_m=cat("wheel_position_m"),
        wheel_owner=np.concatenate(
            [f.wheel_owner + o for f, o in zip(frames, offsets.tolist(), strict=True)]
        ),
        wheel_wxyz=cat("wheel_wxyz"),
        wheel_rgb=cat("wheel_rgb"),
        velocity_mps=cat("velocity_mps"),
        antenna_m=cat("antenna_m"),
        ground_m=cat("ground_m"),
        crawler=cat("crawler"),
        wheel_is_track=cat("wheel_is_track"),
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
