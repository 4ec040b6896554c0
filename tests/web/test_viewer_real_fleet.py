"""The 3D view of the whole server with a real fleet: simulated tractors publish over Zenoh on
loopback → embedded router → pipeline → live hub → viser → headless Chromium. A browser that
opens the view, nobody followed, sees every vehicle: each one's body projects inside the canvas
through the browser's own camera, and the screenshot has the vehicle's colour there
(:mod:`tests.web.viewer_pixels`).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from server.app_main import ServerThread, build_app
from server.live.viewer.fleet_view import FleetViewer
from server.settings import ViewerSettings
from server.tooling.fleet_commands import demo_plans, vehicle_session
from server.tooling.fleet_sim import FleetSim
from tests.server.fleet_stack import stack_settings
from tests.support import free_port
from tests.web.viewer_pixels import screenshot_until_shown

pytestmark = [pytest.mark.browser, pytest.mark.zenoh, pytest.mark.slow]

N_VEHICLES = 4


@pytest.fixture(scope="module")
def streaming_viewer(
    tmp_path_factory: pytest.TempPathFactory,
) -> Iterator[tuple[FleetViewer, list[str]]]:
    """A server with its 3D view on a free port and the demo's drives streaming, once every
    vehicle is drawn (its anchor known)."""
    settings = stack_settings(tmp_path_factory.mktemp("viewer"), None, 0)
    settings.viewer = ViewerSettings(enabled=True, port=free_port(), update_hz=5.0)
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
        missing = screenshot_until_shown(page, viewer, screenshots / "viewer-real-fleet.png")
    finally:
        ctx.close()
    assert not missing, f"the 3D view does not show: {missing}"
