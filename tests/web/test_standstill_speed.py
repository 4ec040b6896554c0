"""A standing vehicle's speed reads "0.00", not "-0.01": the estimate's noise below the
vehicle's standstill speed (SlipConfig.min_ground_speed_mps, where the product counts it as
standing) is shown as standing, on the fleet table and the vehicle page; a vehicle creeping
above it keeps its sign. Rows pushed into the live stack's hub; real Chromium."""

from __future__ import annotations

import json
import threading
import time
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import pytest

from estimator.mdsf_spec import MDSF_SPEC
from estimator.types import EstimateBatch, EstimateFlag, empty_estimates
from tests.web.conftest import LiveStack

pytestmark = pytest.mark.browser

STANDING = "veh-standing"
REVERSING = "veh-reversing"


def _put(stack: LiveStack, vid: str, method: str = "PUT") -> None:
    body = json.dumps({"slip": {"min_ground_speed_mps": 0.2}}).encode() if method == "PUT" else None
    url = f"{stack.base_url}/api/v1/vehicles/{vid}"
    req = urllib.request.Request(url, data=body, method=method)
    req.add_header("Content-Type", "application/json")
    with urllib.request.urlopen(req, timeout=10) as resp:
        assert resp.status in (200, 201, 204)


@contextmanager
def _pushing(stack: LiveStack, speeds: dict[str, float]) -> Iterator[None]:
    """Registered vehicles whose estimates (stamped now, 10 Hz) have these motion speeds."""
    hub = stack.runtime.live_hub
    stop = threading.Event()

    def run() -> None:
        while not stop.wait(0.1):
            for vid, v in speeds.items():
                row = empty_estimates(1)
                row["stamp_ns"] = time.time_ns()
                row["vg_mps"] = row["vl_mps"] = row["vr_mps"] = v
                row["east_m"] = row["north_m"] = 0.0
                row["flags"] = int(EstimateFlag.GNSS_OK | EstimateFlag.STANDSTILL)
                hub.on_estimates(EstimateBatch.of([(vid, row)], MDSF_SPEC))

    for vid in speeds:
        _put(stack, vid)
    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join(5)
        for vid in speeds:
            hub.forget(vid)
            _put(stack, vid, "DELETE")


def _speed_cell(page: Any, vid: str) -> str:
    handle = page.wait_for_function(
        """(vid) => {
          const r = [...document.querySelectorAll('.vrows .vrow')]
            .find((x) => x.querySelector('.c-id a').textContent === vid && !x.hidden);
          const t = r && r.querySelector('.c-speed_mps').textContent;
          return t && t !== '–' ? t : false;
        }""",
        arg=vid,
        timeout=15000,
    )
    text: str = handle.json_value()
    return text


def test_a_standing_vehicle_shows_zero_speed(live_stack: LiveStack, page: Any) -> None:
    with _pushing(live_stack, {STANDING: -0.012, REVERSING: -0.6}):
        page.goto(live_stack.base_url + "/#/fleet")
        page.fill("#fleet-filter", "veh-")
        page.wait_for_timeout(2500)  # the stored list (standstill speeds) and the feed
        assert _speed_cell(page, STANDING) == "0.00"
        assert _speed_cell(page, REVERSING) == "-0.60"
        page.goto(f"{live_stack.base_url}/#/vehicle/{STANDING}")
        page.wait_for_function(
            "document.getElementById('v-mdsf-speed')?.textContent === '0.00'", timeout=15000
        )
        page.wait_for_timeout(600)
        assert page.inner_text("#v-mdsf-speed") == "0.00"
