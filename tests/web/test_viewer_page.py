"""The viser fleet view in a real headless Chromium: a client connects and its camera follows."""

from __future__ import annotations

import time
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from server.live.hub import LiveHub
from server.live.viewer.fleet_view import FleetViewer
from server.settings import ViewerSettings
from server.tooling.bench.live import FeedThread, SyntheticFleet
from tests.support import free_port, poll_until
from tests.web.conftest import browser_page
from tests.web.viewer_pixels import screenshot_until_shown

pytestmark = pytest.mark.browser


#: A frame of travel at most, m: the camera is aimed at the vehicle of the frame being drawn.
AIM_M = 3.0
#: How far back the frames the camera may be aimed at go, s: a frame is published after the
#: cameras are aimed (a frame read beside the camera can be the one before), and a loaded host
#: takes longer to draw each.
RECENT_FRAMES_S = 2.0


def _aim_m(viewer: FleetViewer) -> np.ndarray | None:
    """Where the browser's camera looks, once it has reported its camera."""
    assert viewer.server is not None
    clients = list(viewer.server.get_clients().values())
    try:
        return np.asarray(clients[0].camera.look_at, dtype=float) if clients else None
    except AssertionError:  # camera not reported yet
        return None


def _wait_until_the_camera_follows(viewer: FleetViewer, vid: str, moved_m: float) -> None:
    """Until the camera has been aimed at ``vid`` (within :data:`AIM_M` of where a frame of
    the last :data:`RECENT_FRAMES_S` drew it) at two places ``moved_m`` apart: it moves along."""
    recent: deque[tuple[float, np.ndarray]] = deque()
    aims: list[np.ndarray] = []
    deadline = time.monotonic() + 120
    while (moved := float(np.linalg.norm(aims[-1] - aims[0])) if aims else 0.0) < moved_m:
        assert time.monotonic() < deadline, (
            f"the camera does not follow the vehicle: aimed at it {len(aims)} times, the first"
            f" and the last {moved:.2f} m apart"
        )
        time.sleep(0.05)
        now, frame = time.monotonic(), viewer.frame
        if frame is not None and vid in frame.ids:
            recent.append((now, frame.body_position_m[frame.ids.index(vid)]))
        while recent and recent[0][0] < now - RECENT_FRAMES_S:
            recent.popleft()
        aim = _aim_m(viewer)
        if aim is not None and any(np.linalg.norm(aim - p) < AIM_M for _, p in recent):
            aims.append(aim)


def test_viewer_client_follows_a_vehicle(browser: Any, screenshots: Path) -> None:
    port = free_port()
    hub = LiveHub()
    feed = FeedThread(SyntheticFleet(30, seed=3), [hub], rate_hz=10.0)
    feed.backfill(60.0)
    feed.start()
    viewer = FleetViewer(hub, ViewerSettings(host="127.0.0.1", port=port, update_hz=5.0))
    viewer.start()
    try:
        with browser_page(browser, viewport={"width": 1400, "height": 900}) as page:
            page.goto(f"http://127.0.0.1:{port}/")
            viewer.follow("veh-004")
            _wait_until_the_camera_follows(viewer, "veh-004", moved_m=2.0)  # ≥ 1.5 m/s
            assert viewer._track is not None and viewer._arrow is not None
            page.wait_for_timeout(1500)
            page.screenshot(path=str(screenshots / "viewer.png"))
    finally:
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
    try:
        with browser_page(browser, viewport={"width": 1400, "height": 900}) as page:
            page.goto(f"http://127.0.0.1:{viewer.port}/")
            frame = poll_until(lambda: viewer.frame if viewer._cam_fitted else None, "camera aimed")
            assert sorted(frame.ids) == fleet.ids
            assert viewer._count is not None and viewer._count.value == "6 (1 without a position)"
            page.wait_for_function("() => document.body.innerText.includes('no value')")
            text = page.inner_text("body")
            assert "Wheels" in text and "Bodies" in text and "offline" in text
            missing = screenshot_until_shown(page, viewer, screenshots / "viewer-fleet.png")
            assert not missing, f"the 3D view does not show: {missing}"
    finally:
        viewer.stop()
        feed.stop()
