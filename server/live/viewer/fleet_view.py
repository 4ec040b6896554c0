"""viser 3D fleet view: every vehicle at its pose, wheels coloured by slip, one followed.

Each vehicle is drawn from its primary estimator's rows, read through the spec
(:mod:`server.live.viewer.scene`), where that spec has a position. A vehicle whose primary has no
position but has wheels to colour (friction's four tyres by grip used) is drawn *parked*: level,
facing north, in a row 15 m south of the fleet, 8 m apart, so its tyres can be watched; one whose
primary has neither is not drawn.

Scene (world = local ENU metres, see :mod:`server.live.viewer.scene`):

``/fleet/bodies``   one batched mesh, a box per wheeled vehicle, coloured by status
                    (live/stale/offline)
``/fleet/crawlers`` one batched mesh, a low hull per crawler (a spec whose wheels are tracks)
``/fleet/wheels``   one batched mesh, a wheel per slip channel of the vehicle's spec, coloured
                    by that channel's slip, or by the grip used where the spec has it
``/fleet/tracks``   one batched mesh, a track box per track slip channel, coloured by its slip
``/fleet/pins``     a pin above each vehicle in its body's colour, a few pixels wide at any
                    distance, so a fleet spread over kilometres can be found at a glance
``/follow/track``   the followed vehicle's recent track, coloured by max |slip| of its channels
``/follow/velocity`` its velocity arrow (2 s of travel), above the body
``/follow/label``   its id
``/ground``         a grid under the fleet

A vehicle without a position (no fix yet, or its anchor in the fleet's frame not known yet) is
not drawn; the sidebar counts it. A browser that connects while nobody is followed gets its
camera aimed at the whole fleet (so the view never opens on an empty grid), and the sidebar
holds a legend of the colours (:func:`legend_html`).

The whole fleet is two batched meshes, so a frame for 1,000 vehicles is a handful of array
assignments inside one ``server.atomic()`` block (``server/tooling/bench/viewer.py`` compares it
with one handle per vehicle). Per-vehicle detail exists only for the followed vehicle, chosen in the
GUI dropdown ("Follow"); "Camera follows" keeps every client's camera looking at it.

:class:`FleetViewer` reads a :class:`server.live.hub.LiveHub` on its own thread at
``ViewerSettings.update_hz``; :meth:`FleetViewer.update` draws one frame and can be called
directly (tests, benchmarks).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Literal

import numpy as np
import viser

from estimator.config import VehicleGeometry
from estimator.spec import EstimatorSpec, PositionChannel
from server.live.hub import LiveHub
from server.live.viewer.colors import (
    GRIP_COLOR_STOPS,
    SLIP_COLOR_NONE,
    SLIP_COLOR_STOPS,
    slip_rgb,
)
from server.live.viewer.scene import (
    BODY_SIZE_M,
    CRAWLER_BODY_SIZE_M,
    STATUS_RGB,
    TRACK_SIZE_M,
    FleetFrame,
    box_mesh,
    concat_frames,
    cylinder_mesh_x,
    fleet_frame,
    positioned,
)
from server.settings import ViewerSettings

__all__ = [
    "ARROW_SECONDS",
    "NO_FOLLOW",
    "FleetViewer",
    "fleet_view_point",
    "legend_html",
    "outgrown",
]

_log = logging.getLogger(__name__)

NO_FOLLOW = "(none)"
_TRACK_WINDOW_S = 120.0
_WHEEL_WIDTH_M = 0.45
_CAMERA_OFFSET_M = (-14.0, -14.0, 10.0)
#: A follow camera aimed further than this off its vehicle is aimed again [m].
_AIM_TOLERANCE_M = 0.5
#: The velocity arrow of the followed vehicle shows this many seconds of travel.
ARROW_SECONDS = 2.0
#: Direction from the fleet's centre to a camera that shows all of it (from the south-west,
#: above), and the smallest span framed [m].
_FLEET_VIEW_DIR = np.array([-0.45, -0.75, 0.5]) / np.linalg.norm([-0.45, -0.75, 0.5])
_MIN_SPAN_M = 30.0
_GRID_MIN_M = 400.0
#: Pins rise this share of the framed span above the bodies (at least _PIN_MIN_M) [m].
_PIN_SHARE = 0.08
_PIN_MIN_M = 4.0
#: Vehicles without a position are parked in a row this far south of the fleet, this far apart.
_PARK_SOUTH_M = 15.0
_PARK_STEP_M = 8.0


def _swatch(rgb: tuple[int, int, int], text: str) -> str:
    r, g, b = rgb
    box = f"display:inline-block;width:12px;height:12px;background:rgb({r},{g},{b});"
    return f'<span style="white-space:nowrap"><span style="{box}"></span> {text}</span>'


def legend_html() -> str:
    """The colour legend of the sidebar: wheels by |slip| (the shared scale), bodies by status."""
    stops = [_swatch(c, f"{x:g} %") for x, c in SLIP_COLOR_STOPS]
    stops[-1] = _swatch(SLIP_COLOR_STOPS[-1][1], f"≥ {SLIP_COLOR_STOPS[-1][0]:g} %")
    wheels = " ".join([*stops, _swatch(SLIP_COLOR_NONE, "no value")])
    grip = " ".join(_swatch(c, f"{x:g} %") for x, c in GRIP_COLOR_STOPS)
    bodies = " ".join(_swatch(c, status) for status, c in STATUS_RGB.items())
    return (
        '<div style="font-size:12px;line-height:1.7">'
        f"<b>Wheels and tracks</b>: |slip|, shaded between {wheels}<br>"
        f"<b>Tyres with grip used</b>: shaded between {grip}<br>"
        f"<b>Bodies</b>: {bodies}</div>"
    )


def fleet_view_point(positions_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """``(camera position, look-at point, span)`` framing every point of ``(n, 3)``, n ≥ 1.

    The camera looks at the centre of the points' bounding box from :data:`_FLEET_VIEW_DIR`, at a
    distance that keeps the box's diagonal span (at least :data:`_MIN_SPAN_M`) well inside the
    browser's view (viser's 75° vertical field of view)."""
    lo, hi = positions_m.min(axis=0), positions_m.max(axis=0)
    centre = (lo + hi) / 2
    span = max(float(np.linalg.norm((hi - lo)[:2])), _MIN_SPAN_M)
    distance = 0.8 * span / (2 * math.tan(math.radians(25))) + 10.0
    return centre + distance * _FLEET_VIEW_DIR, centre, span


def outgrown(box_m: tuple[np.ndarray, np.ndarray] | None, positions_m: np.ndarray) -> bool:
    """Whether ``positions_m`` ``(n, 3)`` reach past the box ``(lo, hi)`` the cameras were aimed
    at by more than a quarter of its span (at least :data:`_MIN_SPAN_M`), or there is no box yet.

    A vehicle joining far off, or the fleet driving out of view, re-aims the cameras; a vehicle
    moving inside the view does not (that would take the camera from a user every frame)."""
    if box_m is None:
        return True
    lo, hi = box_m
    margin = 0.25 * max(float(np.linalg.norm((hi - lo)[:2])), _MIN_SPAN_M)
    xy = positions_m[:, :2]
    return bool(np.any(xy < lo[:2] - margin) or np.any(xy > hi[:2] + margin))


class FleetViewer:
    """The 3D fleet scene on its own port.

    Parameters
    ----------
    hub : LiveHub
        Source of the newest rows and of the followed vehicle's track.
    settings : ViewerSettings
        ``host`` (keep 127.0.0.1), ``port`` (0 picks a free one), ``update_hz``.
    geometry : VehicleGeometry, optional
        Drawn layout of every vehicle (default geometry).
    """

    def __init__(
        self,
        hub: LiveHub,
        settings: ViewerSettings,
        geometry: VehicleGeometry | None = None,
        *,
        origin_offset_m: Callable[[str], tuple[float, float, float] | None] | None = None,
        layout: Literal["shared", "grid"] = "shared",
        grid_spacing_m: float = 150.0,
    ) -> None:
        self.hub = hub
        self.settings = settings
        self.geometry = geometry or VehicleGeometry()
        self.origin_offset_m = origin_offset_m
        self.layout = layout
        self.grid_spacing_m = float(grid_spacing_m)
        self._offsets: dict[str, np.ndarray] = {}
        self.server: viser.ViserServer | None = None
        self._meshes: dict[str, viser.BatchedMeshHandle] = {}
        # the first body and wheel meshes (of self._meshes), None while there are none
        self._bodies: viser.BatchedMeshHandle | None = None
        self._wheels: viser.BatchedMeshHandle | None = None
        self._track: viser.LineSegmentsHandle | None = None
        self._arrow: viser.ArrowsHandle | None = None
        self._label: viser.LabelHandle | None = None
        self._follow: viser.GuiDropdownHandle[str] | None = None
        self._camera_follows: viser.GuiCheckboxHandle | None = None
        self._count: viser.GuiTextHandle | None = None
        self._grid: viser.GridHandle | None = None
        self._pins: viser.LineSegmentsHandle | None = None
        self._pin_height_m = _PIN_MIN_M
        self._cam_fitted: set[int] = set()  # clients whose camera was aimed at the fleet
        self._fitted_box_m: tuple[np.ndarray, np.ndarray] | None = None  # the fleet they saw
        self._n: tuple[int, ...] = ()  # instances of each part of the batched meshes
        self._ids: list[str] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._cam_follow: dict[int, str] = {}
        self._cam_last: np.ndarray | None = None
        self.frame: FleetFrame | None = None
        self.frames = 0
        self.last_frame_s = 0.0

    # ------------------------------------------------------------------ lifecycle
    @property
    def port(self) -> int:
        if self.server is None:
            raise RuntimeError("viewer not started")
        return self.server.get_port()

    def open(self) -> None:
        """Start the viser server and build the static scene and GUI (no update thread)."""
        if self.server is not None:
            return
        server = viser.ViserServer(
            host=self.settings.host, port=self.settings.port, label="Slipfleet", verbose=False
        )
        self.server = server
        server.scene.set_up_direction("+z")
        self._place_grid(np.zeros(3), _GRID_MIN_M)
        self._follow = server.gui.add_dropdown(
            "Follow", options=(NO_FOLLOW,), initial_value=NO_FOLLOW
        )
        self._camera_follows = server.gui.add_checkbox("Camera follows", initial_value=True)
        self._count = server.gui.add_text("Vehicles", initial_value="0", disabled=True)
        server.gui.add_html(legend_html())
        self._follow.on_update(lambda _event: self._on_follow_changed())
        server.on_client_disconnect(lambda client: self._cam_fitted.discard(client.client_id))

    def _place_grid(self, centre_m: np.ndarray, span_m: float) -> None:
        """The ground grid under ``centre_m``, wide enough for ``span_m`` (100 m steps), about
        40 cells across (10 m at least), a heavier line every 5 cells."""
        assert self.server is not None
        if self._grid is not None:
            self._grid.remove()
        width = max(_GRID_MIN_M, math.ceil(1.5 * span_m / 100.0) * 100.0)
        cell = max(10.0, 10.0 * round(width / 400.0))
        self._grid = self.server.scene.add_grid(
            "/ground",
            width=width,
            height=width,
            cell_size=cell,
            section_size=5.0 * cell,
            plane="xy",
            position=(float(centre_m[0]), float(centre_m[1]), 0.0),
            fade_distance=3.0 * width,
        )

    def start(self) -> None:
        """:meth:`open`, then redraw at ``settings.update_hz`` on a thread until :meth:`stop`."""
        self.open()
        if self._thread is not None:
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="fleet-viewer", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the update thread and the viser server."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        if self.server is not None:
            self.server.stop()
            self.server = None

    def _run(self) -> None:
        period = 1.0 / self.settings.update_hz
        next_t = time.monotonic()
        while not self._stop.is_set():
            try:
                self.update()
            except Exception:  # keep the view alive; the next frame retries
                _log.exception("viewer frame failed")
            next_t += period
            now = time.monotonic()
            if next_t < now:  # fell behind: skip frames rather than queue them
                next_t = now
            self._stop.wait(next_t - now)

    # ------------------------------------------------------------------ following
    @property
    def followed(self) -> str | None:
        if self._follow is None or self._follow.value == NO_FOLLOW:
            return None
        return self._follow.value

    def follow(self, vehicle_id: str | None) -> None:
        """Follow ``vehicle_id`` (None: nobody), as if picked in the dropdown."""
        if self._follow is None:
            raise RuntimeError("viewer not open")
        value = NO_FOLLOW if vehicle_id is None else vehicle_id
        if value not in self._follow.options:
            self._follow.options = (*self._follow.options, value)
        self._follow.value = value  # type: ignore[misc]  # viser's setter, untyped
        self._on_follow_changed()

    def _on_follow_changed(self) -> None:
        self._cam_follow.clear()
        self._cam_last = None
        if self.followed is None:
            self._cam_fitted.clear()  # back to the whole fleet
            for h in (self._track, self._arrow, self._label):
                if h is not None:
                    h.visible = False

    def _fit_cameras(self, frame: FleetFrame) -> None:
        """Aim every client not aimed yet at the whole fleet (while nobody is followed); aim
        them all again when the fleet has outgrown what they were aimed at (:func:`outgrown`)."""
        assert self.server is not None
        if self.followed is not None:
            return
        positions = frame.body_position_m
        if self._cam_fitted and outgrown(self._fitted_box_m, positions):
            self._cam_fitted.clear()
        clients = self.server.get_clients()
        todo = [c for cid, c in clients.items() if cid not in self._cam_fitted]
        if not todo:
            return
        position, look_at, span = fleet_view_point(positions)
        if not self._cam_fitted:
            self._fitted_box_m = (positions.min(axis=0), positions.max(axis=0))
            self._place_grid(look_at, span)
            self._pin_height_m = max(_PIN_MIN_M, _PIN_SHARE * span)
        for client in todo:
            try:
                client.camera.position = position
                client.camera.look_at = look_at
            except AssertionError:  # the client has not reported its camera yet
                continue
            self._cam_fitted.add(client.client_id)

    # ------------------------------------------------------------------ frames
    def _part_meshes(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        g = self.geometry
        r = (g.wheel_radius_left_m + g.wheel_radius_right_m) / 2
        return {
            "bodies": box_mesh(BODY_SIZE_M),
            "crawlers": box_mesh(CRAWLER_BODY_SIZE_M),
            "wheels": cylinder_mesh_x(r, _WHEEL_WIDTH_M),
            "tracks": box_mesh(TRACK_SIZE_M),
        }

    def _rebuild_fleet(self, parts: dict[str, _Part]) -> None:
        """(Re)create the batched meshes of every part that has instances."""
        for h in self._meshes.values():
            h.remove()
        self._meshes = {}
        meshes = self._part_meshes()
        for name, (wxyz, position_m, rgb) in parts.items():
            if wxyz.shape[0]:
                self._meshes[name] = self._batched(
                    f"/fleet/{name}", meshes[name], wxyz, position_m, rgb
                )
        self._bodies = self._meshes.get("bodies") or self._meshes.get("crawlers")
        self._wheels = self._meshes.get("wheels") or self._meshes.get("tracks")

    def _batched(
        self,
        path: str,
        mesh: tuple[np.ndarray, np.ndarray],
        wxyz: np.ndarray,
        position_m: np.ndarray,
        rgb: np.ndarray,
    ) -> viser.BatchedMeshHandle:
        """One batched mesh (an instance per vehicle part), flat-shaded, no shadows."""
        assert self.server is not None
        vertices, faces = mesh
        return self.server.scene.add_batched_meshes_simple(
            path,
            vertices=vertices,
            faces=faces,
            batched_wxyzs=wxyz,
            batched_positions=position_m,
            batched_colors=rgb,
            lod="off",
            flat_shading=True,
            cast_shadow=False,
            receive_shadow=False,
        )

    def _offsets_of(self, ids: list[str]) -> np.ndarray | None:
        """Per-vehicle shift ``(n, 3)`` from its own ENU frame into the scene, or None.

        Each vehicle's estimates are in its own local ENU frame (anchored at its first fix).
        With ``origin_offset_m`` (vehicle id → that anchor's ENU position in the fleet's frame)
        vehicles are drawn where they are relative to each other (NaN, not drawn, while a
        vehicle's anchor is unknown); the tangent planes' tilt
        between anchors (< 0.01° per km) is neglected. Otherwise ``layout="shared"`` draws every
        frame on one origin (right when the vehicles share an anchor) and ``"grid"`` puts each
        vehicle's origin on a grid ``grid_spacing_m`` apart, in id order, so none overlap.
        """
        if self.origin_offset_m is not None:
            out = np.full((len(ids), 3), np.nan)  # anchor unknown: not drawn (NaN position)
            for i, vid in enumerate(ids):
                off = self._offsets.get(vid)
                if off is None:
                    got = self.origin_offset_m(vid)
                    if got is None:
                        continue  # anchor unknown yet: ask again next frame
                    off = self._offsets[vid] = np.asarray(got, dtype=np.float64)
                out[i] = off
            return out
        if self.layout == "grid":
            order = {vid: k for k, vid in enumerate(sorted(ids))}
            cols = max(1, math.ceil(math.sqrt(len(ids))))
            k = np.array([order[v] for v in ids])
            return np.stack(
                [(k % cols) * self.grid_spacing_m, (k // cols) * self.grid_spacing_m, 0.0 * k], -1
            )
        return None

    def update(self) -> float:
        """Draw one frame from the hub; return its cost in seconds."""
        if self.server is None:
            raise RuntimeError("viewer not open")
        t0 = time.perf_counter()
        groups, parked = self._latest_primaries()
        all_ids = [v for g in groups for v in g[1]]
        n_parked = sum(len(g[1]) for g in parked)
        if not all_ids and not n_parked:
            return 0.0
        offsets = self._offsets_of(all_ids)
        offset_of = {} if offsets is None else dict(zip(all_ids, offsets, strict=True))
        frames, start = [], 0
        for spec, gids, rows, arrivals in groups:
            part = None if offsets is None else offsets[start : start + len(gids)]
            frames.append(self._frame_of(spec, gids, rows, arrivals, part))
            start += len(gids)
        frames += self._parked_frames(parked, frames)
        frame = concat_frames(frames)
        ids = frame.ids
        parts = _part_arrays(frame)
        with self._lock, self.server.atomic():
            self._show_count(len(ids), len(all_ids) + n_parked, n_parked)
            self._draw_fleet(ids, parts)
            self._offer_follow(ids)
            if ids:
                self._draw_pins(frame)
                self._fit_cameras(frame)
                self._draw_followed(frame, offset_of.get(self.followed or ""))
        self.frame = frame
        self.frames += 1
        self.last_frame_s = time.perf_counter() - t0
        return self.last_frame_s

    def _latest_primaries(self) -> tuple[list[_SpecRows], list[_SpecRows]]:
        """The newest primary rows per spec, ``(spec, ids, rows, arrivals)``: of the specs with
        a position (drawn where they are), and of those without one but with slip channels
        (parked)."""
        placed, parked = [], []
        for spec in self.hub.specs():
            if spec.position is not None:
                placed.append((spec, *self.hub.latest_all(spec.name, primary_only=True)))
            elif spec.slips:
                parked.append((spec, *self.hub.latest_all(spec.name, primary_only=True)))
        return placed, parked

    def _draw_fleet(self, ids: list[str], parts: dict[str, _Part]) -> None:
        """The batched meshes of ``parts``: removed without vehicles, rebuilt when their
        counts change, else moved and recoloured in place."""
        shape = tuple(p[0].shape[0] for p in parts.values())
        if not ids:
            self._clear_fleet()
        elif shape != self._n or not self._meshes:
            self._rebuild_fleet(parts)
            self._n = shape
        else:
            for name, (wxyz, position_m, rgb) in parts.items():
                handle = self._meshes.get(name)
                if handle is not None:
                    handle.batched_positions = position_m.astype(np.float32)
                    handle.batched_wxyzs = wxyz.astype(np.float32)
                    handle.batched_colors = rgb

    def _offer_follow(self, ids: list[str]) -> None:
        """The follow menu offers the drawn ``ids``; a followed vehicle no longer drawn is
        let go."""
        if ids == self._ids:
            return
        self._ids = list(ids)
        assert self._follow is not None
        current = self._follow.value
        self._follow.options = (NO_FOLLOW, *sorted(ids))
        self._follow.value = current if current in ids else NO_FOLLOW  # type: ignore[misc]

    def _show_count(self, drawn: int, total: int, parked: int = 0) -> None:
        assert self._count is not None
        text = str(drawn) if drawn == total else f"{drawn} ({total - drawn} without a position)"
        if parked:
            text += f", {parked} parked (no position)"
        if self._count.value != text:
            self._count.value = text  # type: ignore[misc]

    def _clear_fleet(self) -> None:
        """No vehicle to draw: remove the batched meshes and the pins."""
        for h in (*self._meshes.values(), self._pins):
            if h is not None:
                h.remove()
        self._meshes = {}
        self._bodies = self._wheels = None
        self._pins = None
        self._n = ()

    def _draw_pins(self, frame: FleetFrame) -> None:
        """A vertical segment ``(n, 2, 3)`` above each body, in the body's colour."""
        assert self.server is not None
        foot = frame.body_position_m + np.array([0.0, 0.0, BODY_SIZE_M[2] / 2])
        head = foot + np.array([0.0, 0.0, self._pin_height_m])
        points = np.stack([foot, head], axis=1).astype(np.float32)
        colors = np.repeat(frame.body_rgb[:, None, :], 2, axis=1)
        if self._pins is None or np.asarray(self._pins.points).shape != points.shape:
            if self._pins is not None:
                self._pins.remove()
            self._pins = self.server.scene.add_line_segments(
                "/fleet/pins", points=points, colors=colors, thickness=5.0, thickness_units="screen"
            )
        else:
            self._pins.points = points
            self._pins.colors = colors

    def _frame_of(
        self,
        spec: EstimatorSpec,
        ids: list[str],
        rows: np.ndarray,
        arrivals: np.ndarray,
        offsets: np.ndarray | None,
    ) -> FleetFrame:
        """The newest ``rows`` of ``spec`` of vehicles ``ids``, shifted by ``offsets`` (n, 3),
        of the vehicles that have a position (:func:`positioned`) only."""
        p = spec.position
        if offsets is not None and p is not None:
            rows = rows.copy()
            for k, name in enumerate((p.east_field, p.north_field, p.up_field)):
                if name is not None:
                    rows[name] += offsets[:, k]
        keep = positioned(rows, spec)
        ids = [vid for vid, k in zip(ids, keep, strict=True) if k]
        rows, arrivals = rows[keep], arrivals[keep]
        status = self.hub.status_of_rows(rows["stamp_ns"], arrivals)
        return fleet_frame(ids, rows, spec, self.geometry, status)

    def _parked_frames(
        self,
        groups: list[_SpecRows],
        placed: list[FleetFrame],
    ) -> list[FleetFrame]:
        """Frames of the vehicles whose primary gives no position, parked in a row
        :data:`_PARK_SOUTH_M` south of the placed vehicles' ground points (of the origin when
        none is placed), :data:`_PARK_STEP_M` apart from the westmost, in spec then id order."""
        grounds = [f.ground_m for f in placed if f.ids]
        ground = np.concatenate(grounds) if grounds else np.zeros((1, 3))
        east0, north0 = float(ground[:, 0].min()), float(ground[:, 1].min()) - _PARK_SOUTH_M
        out, k = [], 0
        for spec, ids, rows, arrivals in groups:
            n = len(ids)
            row_m = np.zeros((n, 3))
            row_m[:, 0] = east0 + _PARK_STEP_M * (k + np.arange(n))
            row_m[:, 1] = north0
            k += n
            status = self.hub.status_of_rows(rows["stamp_ns"], arrivals)
            out.append(fleet_frame(ids, rows, spec, self.geometry, status, ground_m=row_m))
        return out

    def _draw_followed(self, frame: FleetFrame, offset: np.ndarray | None) -> None:
        """The followed vehicle's arrow, label and track (``offset``: its frame's shift into
        the scene, None for none)."""
        assert self.server is not None
        vid = self.followed
        if vid is None or vid not in frame.ids:
            return
        i = frame.ids.index(vid)
        start = frame.body_position_m[i] + np.array([0.0, 0.0, BODY_SIZE_M[2] / 2 + 0.3])
        tip = start + ARROW_SECONDS * frame.velocity_mps[i]
        self._draw_arrow(np.stack([start, tip])[None, :, :])
        self._draw_label(vid, frame.antenna_m[i] + np.array([0.0, 0.0, 1.0]))
        self._draw_track(frame, i, offset)
        if self._camera_follows is not None and self._camera_follows.value:
            self._move_cameras(vid, frame.body_position_m[i])

    def _draw_arrow(self, points: np.ndarray) -> None:
        """The followed vehicle's velocity arrow, ``points`` (1, 2, 3): tail and tip."""
        assert self.server is not None
        if self._arrow is None:
            self._arrow = self.server.scene.add_arrows(
                "/follow/velocity",
                points=points,
                colors=(20, 20, 20),
                shaft_radius=0.08,
                head_radius=0.25,
                head_length=0.4,
            )
        else:
            self._arrow.points = points
            self._arrow.visible = True

    def _draw_label(self, vid: str, position: np.ndarray) -> None:
        """The followed vehicle's id at ``position`` (3,)."""
        assert self.server is not None
        if self._label is None:
            self._label = self.server.scene.add_label("/follow/label", text=vid, position=position)
        else:
            self._label.text = vid
            self._label.position = position
            self._label.visible = True

    def _draw_track(self, frame: FleetFrame, i: int, offset: np.ndarray | None) -> None:
        """Vehicle ``i``'s track of the last :data:`_TRACK_WINDOW_S` on the ground, segments
        coloured by the larger |slip| of their end; kept as it was without a window."""
        assert self.server is not None
        vid, estimator = frame.ids[i], frame.estimators[i]
        spec = self.hub.spec(estimator)
        win = self.hub.window(vid, _TRACK_WINDOW_S, estimator=estimator)
        if spec is None or spec.position is None or win is None:
            return
        drop = frame.antenna_m[i, 2] - frame.ground_m[i, 2]  # antenna height above ground
        slip_fields = [s.field for s in spec.slips]
        pts, metric = _track_points(win, spec.position, slip_fields, drop, offset)
        if pts.shape[0] < 2:
            return
        segs = np.stack([pts[:-1], pts[1:]], axis=1)
        cols = np.repeat(slip_rgb(metric[1:])[:, None, :], 2, axis=1)
        if self._track is not None:
            self._track.remove()
        self._track = self.server.scene.add_line_segments(
            "/follow/track", points=segs, colors=cols, thickness=4.0, thickness_units="screen"
        )

    def _move_cameras(self, vid: str, target: np.ndarray) -> None:
        """Carry every client's camera along with the followed vehicle.

        A client new to this vehicle gets a view from behind-left and above; after that the
        camera is translated by the vehicle's displacement, so the user can still orbit and zoom.
        (viser moves ``look_at`` along when ``position`` is assigned, so position goes first.)
        A ``look_at`` still off the vehicle afterwards (the browser's own camera message crossed
        ours, and the first aim was lost) is set again.
        """
        assert self.server is not None
        for client_id, client in self.server.get_clients().items():
            cam = client.camera
            try:
                if self._cam_follow.get(client_id) != vid:
                    cam.position = target + np.array(_CAMERA_OFFSET_M)
                    cam.look_at = target
                    self._cam_follow[client_id] = vid
                elif self._cam_last is not None:
                    delta = target - self._cam_last
                    if float(np.linalg.norm(delta)) > 1e-6:
                        cam.position = np.asarray(cam.position) + delta
                    if float(np.linalg.norm(np.asarray(cam.look_at) - target)) > _AIM_TOLERANCE_M:
                        cam.look_at = target
            except AssertionError:  # the client has not reported its camera yet
                continue
        self._cam_last = np.array(target, dtype=np.float64)


_Part = tuple[np.ndarray, np.ndarray, np.ndarray]
#: One spec's newest primary rows: ``(spec, ids, rows, arrivals)``.
_SpecRows = tuple[EstimatorSpec, list[str], np.ndarray, np.ndarray]


def _part_arrays(frame: FleetFrame) -> dict[str, _Part]:
    """``(wxyz, position, rgb)`` of each batched part's instances: wheeled bodies, crawler
    hulls, wheels, tracks."""
    body, wheel = ~frame.crawler, ~frame.wheel_is_track
    b = (frame.body_wxyz, frame.body_position_m, frame.body_rgb)
    w = (frame.wheel_wxyz, frame.wheel_position_m, frame.wheel_rgb)

    def pick(mask: np.ndarray, arrays: _Part) -> _Part:
        return arrays[0][mask], arrays[1][mask], arrays[2][mask]

    return {
        "bodies": pick(body, b),
        "crawlers": pick(~body, b),
        "wheels": pick(wheel, w),
        "tracks": pick(~wheel, w),
    }


def _col(win: dict[str, list[float | None]], name: str | None, n: int) -> np.ndarray:
    """A window column as floats (None → NaN); NaN throughout for no field."""
    if name is None:
        return np.full(n, np.nan)
    return np.array([np.nan if v is None else v for v in win[name]], dtype=np.float64)


def _track_points(
    win: dict[str, list[float | None]],
    p: PositionChannel,
    slip_fields: list[str],
    drop_m: float,
    offset: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray]:
    """The finite points of a window's positions (``p``'s fields; up 0 without one), lowered
    by ``drop_m`` less 5 cm and shifted by ``offset`` (3,) into the scene: shape (m, 3); and
    each point's larger |slip| over ``slip_fields`` (m,; NaN without any)."""
    n_pts = len(win["stamp_ns"])
    e, n = _col(win, p.east_field, n_pts), _col(win, p.north_field, n_pts)
    u = np.zeros(n_pts) if p.up_field is None else _col(win, p.up_field, n_pts)
    pts = np.stack([e, n, u - drop_m + 0.05], -1)
    if offset is not None:  # into the scene frame: the same shift as the vehicle's pose
        pts += offset
    ok = np.isfinite(pts).all(axis=1)
    mags = [np.abs(_col(win, name, n_pts)) for name in slip_fields]
    metric = np.fmax.reduce(mags) if mags else np.full(n_pts, np.nan)
    return pts[ok], metric[ok]
