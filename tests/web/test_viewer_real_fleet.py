"""The 3D view of the whole server with a real fleet: simulated tractors publish over Zenoh on
loopback → embedded router → pipeline → live hub → viser → headless Chromium. A browser that
opens the view, nobody followed, sees every vehicle: each one's body projects inside the canvas
through the browser's own camera, and the screenshot has the vehicle's colour there (WebGL draws
nothing a DOM query could read, so the pixels are the check). The demo's vehicles lie hundreds of
metres apart, so a body is a pixel or two at that zoom and its pin, in the body's colour, is what
shows.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from server.app_main import ServerThread, build_app
from server.live.viewer.fleet_view import FleetViewer
from server.live.viewer.scene import BODY_SIZE_M
from server.settings import Settings
from server.tooling.fleet_commands import demo_plans, vehicle_session
from server.tooling.fleet_sim import FleetSim
from tests.support import free_port

pytestmark = [pytest.mark.browser, pytest.mark.zenoh, pytest.mark.slow]

N_VEHICLES = 4
#: Half the side of the square around a vehicle's projected pin searched for its colour (px).
NEAR_PX = 16
#: Tinted pixels that square must hold: a pin's foot is a few pixels wide and ten or more tall.
MIN_TINTED_PX = 8


@pytest.fixture(scope="module")
def streaming_viewer(
    tmp_path_factory: pytest.TempPathFactory,
) -> Iterator[tuple[FleetViewer, list[str]]]:
    """A server with its 3D view on a free port and the demo's drives streaming, once every
    vehicle is drawn (its anchor known)."""
    settings = Settings(
        zenoh={"listen": [f"tcp/127.0.0.1:{free_port()}"]},
        storage={"data_dir": tmp_path_factory.mktemp("data"), "commit_interval_s": 0.2},
        api={"port": 0, "require_auth": False},
        viewer={"enabled": True, "port": free_port(), "update_hz": 5.0},
    )
    app = build_app(settings)
    server = ServerThread(app, "127.0.0.1", 0)
    server.start()
    try:
        with vehicle_session(list(settings.zenoh.listen)) as session:
            sim = FleetSim(
                session,
                N_VEHICLES,
                prefix=settings.zenoh.key_prefix,
                loop=True,
                plans=demo_plans(N_VEHICLES, "mix"),
            )
            sim.start()
            try:
                viewer = app.state.runtime.viewer
                assert isinstance(viewer, FleetViewer)
                deadline = time.monotonic() + 90
                while viewer.frame is None or sorted(viewer.frame.ids) != sim.vehicle_ids:
                    assert time.monotonic() < deadline, "the 3D view never drew every vehicle"
                    time.sleep(0.3)
                yield viewer, sim.vehicle_ids
            finally:
                sim.stop()
    finally:
        server.stop()


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


def _missing(viewer: FleetViewer, png: bytes, box: dict[str, float]) -> list[str]:
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


def test_viewer_shows_every_streaming_vehicle_on_open(
    browser: Any, screenshots: Path, streaming_viewer: tuple[FleetViewer, list[str]]
) -> None:
    viewer, ids = streaming_viewer
    ctx = browser.new_context(viewport={"width": 1400, "height": 900})
    try:
        page = ctx.new_page()
        page.goto(f"http://127.0.0.1:{viewer.port}/")
        page.wait_for_selector("canvas", timeout=20000)
        deadline = time.monotonic() + 30
        while not viewer._cam_fitted:
            assert time.monotonic() < deadline, "no client camera was aimed at the fleet"
            time.sleep(0.2)
        assert viewer.frame is not None and sorted(viewer.frame.ids) == ids
        box = page.eval_on_selector("canvas", "c => c.getBoundingClientRect().toJSON()")
        deadline = time.monotonic() + 90  # the camera's move and the scene's fade-in, loaded
        missing = ids
        while missing and time.monotonic() < deadline:
            page.wait_for_timeout(1000)
            png = page.screenshot(path=str(screenshots / "viewer-real-fleet.png"), timeout=120_000)
            missing = _missing(viewer, png, box)
    finally:
        ctx.close()
    assert not missing, f"the 3D view does not show: {missing}"
