"""The vehicle page's online calibration on the whole server: a simulated tractor with
free-rolling rear wheels (radius 2 % off, so MDSF learns it) publishes over Zenoh on loopback →
embedded router → pipeline → store → REST → headless Chromium, with tokens required.

The page shows each calibration with its std and converged / uncalibrated state from
``GET /vehicles/{id}/calibration``; an operator starts the calibration drive and resets the
calibration from it (the estimator takes both); a viewer's attempt is refused by the server and
the page says so.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from estimator.config import VehicleGeometry, WheeledRearDriveConfig
from estimator.mdsf import MdsfFleet
from estimator.mdsf_spec import MDSF_SPEC
from server.app_main import ServerThread, build_app
from server.settings import Settings
from server.tokens import Role, issue_token
from server.tooling.fleet_commands import vehicle_session
from server.tooling.fleet_sim import FleetSim
from tests.support import free_port
from tests.web.conftest import checked_page

pytestmark = [pytest.mark.browser, pytest.mark.zenoh, pytest.mark.slow]

VID = "sim-0001"


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, Any, dict[Role, str]]]:
    """The server (tokens required) with one free-rolling tractor driving in a loop: its URL,
    the app and a token per role."""
    settings = Settings(
        zenoh={"listen": [f"tcp/127.0.0.1:{free_port()}"]},
        storage={"data_dir": tmp_path_factory.mktemp("data"), "commit_interval_s": 0.2},
        api={"port": 0, "require_auth": True},
        viewer={"enabled": False},
    )
    app = build_app(settings)
    server = ServerThread(app, "127.0.0.1", 0)
    server.start()
    try:
        store = app.state.runtime.store
        tokens = {r: issue_token(store, f"t-{r}", r, time.time_ns())[0] for r in Role}
        free = VehicleGeometry(wheel_driven_left=False, wheel_driven_right=False)
        with vehicle_session(list(settings.zenoh.listen)) as session:
            sim = FleetSim(
                session,
                1,
                scenario="random_drive",
                prefix=settings.zenoh.key_prefix,
                seed=3,
                rate=2.0,
                loop=True,
                config=WheeledRearDriveConfig(geometry=free),
                free_rolling=(True, True),
                wheel_radius_error_rel=(0.02, 0.02),
                duration_s=60.0,
            )
            sim.start()
            try:
                yield f"http://127.0.0.1:{server.port}", app, tokens
            finally:
                sim.stop()
    finally:
        server.stop()


def _mdsf(app: Any) -> MdsfFleet:
    est = app.state.runtime.registry.estimator("mdsf")
    assert isinstance(est, MdsfFleet)
    return est


def _with_token(page: Any, token: str) -> None:
    page.add_init_script(f"sessionStorage.setItem('slipfleet.token', {token!r})")


def _radius_row(page: Any) -> Any:
    return page.locator("#v-calibration tr[data-calibration='radius_left']")


def test_operator_sees_the_calibration_converge_drives_and_resets_it(
    stack: tuple[str, Any, dict[Role, str]], browser: Any, screenshots: Path
) -> None:
    base, app, tokens = stack
    with checked_page(browser, viewport={"width": 1400, "height": 900}) as page:
        _with_token(page, tokens[Role.OPERATOR])
        page.goto(base + f"/#/vehicle/{VID}")
        page.wait_for_selector("#v-calibration:not([hidden]) .cal-part[data-estimator=mdsf]")
        keys = page.eval_on_selector_all(
            "#v-calibration tr[data-calibration]", "els => els.map(e => e.dataset.calibration)"
        )
        assert keys == [c.key for c in MDSF_SPEC.calibrations]
        # the free-rolling wheels teach the radius: converged, with its σ in mm-sized metres
        page.wait_for_selector(
            "#v-calibration tr[data-calibration='radius_left'][data-state=converged]",
            timeout=90000,
        )
        row = _radius_row(page)
        value_m = float(row.locator(".cal-value").inner_text().split()[0])
        assert (
            abs(value_m / (WheeledRearDriveConfig().geometry.wheel_radius_left_m * 1.02) - 1) < 0.01
        )
        assert row.locator(".cal-std").inner_text().startswith("± 0.00")
        page.locator("#v-calibration").screenshot(path=str(screenshots / "vehicle_calibration.png"))

        page.click("#v-calibration button[data-command=calibration_drive][data-on=true]")
        page.wait_for_function(
            "() => document.getElementById('v-calibration-msg').textContent"
            " === 'calibration drive started'"
        )
        _wait(lambda: _mdsf(app).calibration_drive_on(VID), "the drive never reached MDSF")

        converged_since = int(row.locator(".cal-since").get_attribute("data-since-ns"))
        page.once("dialog", lambda d: d.accept())
        page.click("#v-calibration button.cal-reset")
        page.wait_for_function(
            "() => document.getElementById('v-calibration-msg').textContent.startsWith("
            "'calibration reset')"
        )
        # the radius starts again from its prior: a new stretch (uncalibrated, then converged
        # again) begins after the one shown before the reset
        page.wait_for_function(
            '(t) => Number(document.querySelector("#v-calibration tr[data-calibration='
            "'radius_left'] .cal-since\")?.dataset.sinceNs) > t",
            arg=converged_since,
            timeout=30000,
        )
        with httpx.Client(base_url=base, timeout=10) as client:
            auth = {"Authorization": f"Bearer {tokens[Role.VIEWER]}"}
            _wait(
                lambda: (
                    'event="calibration_resets"' in client.get("/api/v1/metrics", headers=auth).text
                ),
                "the reset was not counted",
            )


def test_a_viewer_is_refused_and_told(
    stack: tuple[str, Any, dict[Role, str]], browser: Any
) -> None:
    base, app, tokens = stack
    refused = lambda msg: "403" in msg.text  # noqa: E731 (the browser logs the refused request)
    with checked_page(browser, refused, viewport={"width": 1400, "height": 900}) as page:
        _with_token(page, tokens[Role.VIEWER])
        page.goto(base + f"/#/vehicle/{VID}")
        page.wait_for_selector("#v-calibration:not([hidden]) tr[data-calibration='radius_left']")
        drive_before = _mdsf(app).calibration_drive_on(VID)
        page.click("#v-calibration button[data-command=calibration_drive][data-on=false]")
        page.wait_for_function(
            "() => document.getElementById('v-calibration-msg').textContent"
            " === 'refused: an operator token is needed'"
        )
        page.once("dialog", lambda d: d.accept())
        page.click("#v-calibration button.cal-reset")
        page.wait_for_function(
            "() => document.getElementById('v-calibration-msg').textContent"
            " === 'refused: an operator token is needed'"
        )
        assert _mdsf(app).calibration_drive_on(VID) == drive_before


def _wait(cond: Any, what: str, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, what
        time.sleep(0.2)
