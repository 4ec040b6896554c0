"""The 3D view of the whole server with a real fleet: simulated tractors publish over Zenoh on
loopback → embedded router → pipeline → live hub → viser → headless Chromium. A browser that
opens the view, nobody followed, sees every vehicle: each one's body projects inside the canvas
through the browser's own camera, and the screenshot has the vehicle's colour there
(:mod:`tests.web.viewer_pixels`).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from server.live.viewer.fleet_view import FleetViewer
from server.settings import ViewerSettings
from server.tooling.fleet_commands import demo_plans
from tests.server.fleet_stack import stack_settings, streaming_fleet
from tests.support import free_port, poll_until
from tests.web.conftest import browser_page
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
    plans = demo_plans(N_VEHICLES, "mix")
    with streaming_fleet(settings, N_VEHICLES, loop=True, plans=plans) as (app, _, sim):
        viewer = app.state.runtime.viewer
        assert isinstance(viewer, FleetViewer)
        poll_until(
            lambda: viewer.frame is not None and sorted(viewer.frame.ids) == sim.vehicle_ids,
            "3D view drawing every vehicle",
        )
        yield viewer, sim.vehicle_ids


def test_viewer_shows_every_streaming_vehicle_on_open(
    browser: Any, screenshots: Path, streaming_viewer: tuple[FleetViewer, list[str]]
) -> None:
    viewer, ids = streaming_viewer
    with browser_page(browser, viewport={"width": 1400, "height": 900}) as page:
        page.goto(f"http://127.0.0.1:{viewer.port}/")
        page.wait_for_selector("canvas")
        frame = poll_until(lambda: viewer.frame if viewer._cam_fitted else None, "camera aimed")
        assert sorted(frame.ids) == ids
        missing = screenshot_until_shown(page, viewer, screenshots / "viewer-real-fleet.png")
    assert not missing, f"the 3D view does not show: {missing}"
