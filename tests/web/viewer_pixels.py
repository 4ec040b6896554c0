"""Where a vehicle of the 3D view is on screen, and whether a screenshot shows it there.

WebGL draws nothing a DOM query could read, so a browser test projects each vehicle's pin (a
vertical segment above the body, in the body's colour) through the browser's own camera and
looks for its colour in a screenshot around that pixel. At a whole fleet's zoom a body is a
pixel or two; the pin is what shows.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from server.live.viewer.fleet_view import FleetViewer
from server.live.viewer.scene import BODY_SIZE_M

__all__ = ["missing_vehicles", "project_px", "screenshot_until_shown"]

#: Half the side of the square around a vehicle's projected pin searched for its colour (px).
NEAR_PX = 16
#: Tinted pixels that square must hold: a pin's foot is a few pixels wide and ten or more tall.
MIN_TINTED_PX = 8


def project_px(points_m: np.ndarray, camera: Any, width_px: float, height_px: float) -> np.ndarray:
    """Pixel ``(n, 2)`` (x right, y down, from the canvas' top left) of world points ``(n, 3)``
    through a viser client's perspective camera (``position``, ``look_at``, ``up_direction``,
    vertical ``fov`` in radians); NaN for points behind the camera."""
    eye = np.asarray(camera.position, dtype=float)
    forward = np.asarray(camera.look_at, dtype=float) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, np.asarray(camera.up_direction, dtype=float))
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    d = points_m - eye
    depth = d @ forward
    tan_half = np.tan(float(camera.fov) / 2)
    ndc_x = (d @ right) / (depth * tan_half * (width_px / height_px))
    ndc_y = (d @ up) / (depth * tan_half)
    px = np.stack([(ndc_x + 1) / 2 * width_px, (1 - ndc_y) / 2 * height_px], axis=-1)
    px[depth <= 0] = np.nan
    return px


def _tinted(rgb: np.ndarray) -> np.ndarray:
    """Mask of pixels with a colour: the background, the grid and its lines are grey or white
    (channel spread under 10), a pin in the palest body colour (live blue) spreads about 35."""
    c = rgb.astype(np.int16)
    return (c.max(axis=2) - c.min(axis=2)) > 20


def missing_vehicles(viewer: FleetViewer, png: bytes, box: dict[str, float]) -> list[str]:
    """The vehicles of the viewer's frame whose pin is outside the canvas or not drawn in the
    screenshot ``png`` (``box``: the canvas' rectangle in the page, px)."""
    import imageio.v3 as iio

    assert viewer.server is not None and viewer.frame is not None
    (client,) = viewer.server.get_clients().values()
    frame = viewer.frame
    lift_m = BODY_SIZE_M[2] / 2 + viewer._pin_height_m / 2
    pins_m = frame.body_position_m + np.array([0.0, 0.0, lift_m])
    pixels = project_px(pins_m, client.camera, box["width"], box["height"])
    tinted = _tinted(np.asarray(iio.imread(png))[..., :3])
    missing = []
    for vid, (x, y) in zip(frame.ids, pixels, strict=True):
        if not (0 <= x < box["width"] and 0 <= y < box["height"]):
            missing.append(f"{vid} outside the view")
            continue
        col, row = int(box["x"] + x), int(box["y"] + y)
        near = tinted[max(row - NEAR_PX, 0) : row + NEAR_PX, max(col - NEAR_PX, 0) : col + NEAR_PX]
        if near.sum() < MIN_TINTED_PX:
            missing.append(f"{vid} not drawn at ({col}, {row}) px")
    return missing


def screenshot_until_shown(page: Any, viewer: FleetViewer, path: Path) -> list[str]:
    """Screenshots of ``page`` (the viewer open, its camera aimed) into ``path`` until every
    vehicle of the viewer's frame shows, for at most 90 s (the camera's move and the scene's
    fade-in on a loaded machine); the vehicles still missing in the last one."""
    box = page.eval_on_selector("canvas", "c => c.getBoundingClientRect().toJSON()")
    deadline = time.monotonic() + 90
    missing = ["(no screenshot)"]
    while missing and time.monotonic() < deadline:
        page.wait_for_timeout(1000)
        png = page.screenshot(path=str(path), timeout=120_000)
        missing = missing_vehicles(viewer, png, box)
    return missing
