"""The viser fleet view in a real headless Chromium: a client connects and its camera follows."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from server.live.hub import LiveHub
from server.live.viewer.fleet_view import FleetViewer
from server.settings import ViewerSettings
from server.tooling.bench.live import FeedThread, SyntheticFleet
from tests.support import free_port
from tests.web.viewer_pixels import screenshot_until_shown

pytestmark = pytest.mark.browser


def test_viewer_client_follows_a_vehicle(browser: Any, screenshots: Path) -> None:
    port = free_port()
    hub = LiveHub()
    feed = FeedThread(SyntheticFleet(30, seed=3), [hub], rate_hz=10.0)
    feed.backfill(60.0)
    feed.start()
    viewer = FleetViewer(hub, ViewerSettings(host="127.0.0.1", port=port, update_hz=5.0))
    viewer.start()
    ctx = browser.new_context(viewport={"width": 1400, "height": 900})
    try:
        page = ctx.new_page()
        page.goto(f"http://127.0.0.1:{port}/")
        viewer.follow("veh-004")
        assert viewer.server is not None
        deadline = time.monotonic() + 30
        near = False
        while time.monotonic() < deadline and not near:
            time.sleep(0.5)
            frame = viewer.frame
            clients = list(viewer.server.get_clients().values())
            if frame is None or not clients:
                continue
            target = frame.body_position_m[frame.ids.index("veh-004")]
            try:
                look_at = np.asarray(clients[0].camera.look_at)
            except AssertionError:  # camera not reported yet
                continue
            near = float(np.linalg.norm(look_at - target)) < 3.0  # one frame of travel at most
        assert near, "the camera does not follow the vehicle"
        assert viewer._track is not None and viewer._arrow is not None
        page.wait_for_timeout(1500)
        page.screenshot(path=str(screenshots / "viewer.png"))
    finally:
        ctx.close()
        viewer.stop()
        feed.stop()


def test_viewer_opens_on_the_whole_fleet_with_a_legend(browser: Any, screenshots: Path) -> None:
    """Nobody followed: a browser that connects sees every vehicle (the fleet's frame lies far
    from the origin, as with the server's anchors), a colour legend, and a vehicle without a
    position is left out instead of drawn at the origin."""
    fleet = SyntheticFleet(6, seed=5)
    offsets = {vid: (350.0 + 40.0 * k, 420.0 - 25.0 * k, 0.0) for k, vid in enumerate(fleet.ids)}
    offsets["no-fix"] = (0.0, 0.0, 0.0)
    hub = LiveHub()
    feed = FeedThread(fleet, [hub], rate_hz=10.0)
    feed.backfill(20.0)
    feed.start()
    nofix = fleet.rows_at(time.time_ns())[0][1].copy()
    nofix["east_m"] = nofix["north_m"] = np.nan
    hub.on_estimates([("no-fix", nofix)])
    viewer = FleetViewer(
        hub,
        ViewerSettings(host="127.0.0.1", port=free_port(), update_hz=5.0),
        origin_offset_m=offsets.get,
    )
    viewer.start()
    ctx = browser.new_context(viewport={"width": 1400, "height": 900})
    try:
        page = ctx.new_page()
        page.goto(f"http://127.0.0.1:{viewer.port}/")
        deadline = time.monotonic() + 30
        while not viewer._cam_fitted and time.monotonic() < deadline:
            time.sleep(0.2)
        assert viewer._cam_fitted, "no client camera was aimed at the fleet"
        assert viewer.frame is not None and sorted(viewer.frame.ids) == fleet.ids
        assert viewer._count is not None and viewer._count.value == "6 (1 without a position)"
        page.wait_for_function("() => document.body.innerText.includes('no value')", timeout=20000)
        text = page.inner_text("body")
        assert "Wheels" in text and "Bodies" in text and "offline" in text
        missing = screenshot_until_shown(page, viewer, screenshots / "viewer-fleet.png")
        assert not missing, f"the 3D view does not show: {missing}"
    finally:
        ctx.close()
        viewer.stop()
        feed.stop()
