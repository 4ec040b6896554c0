"""At 390 px nothing is clipped: every shown cell of the fleet table (header and rows, a
stored "not live" vehicle's status included: its pill once overflowed the status column) and
the map titles of the vehicle and history pages keep their text inside their box
(scrollWidth <= clientWidth), on a phone-sized Chromium against the live stack."""

from __future__ import annotations

import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.web.conftest import LiveStack, checked_page, history_loaded

pytestmark = pytest.mark.browser

PHONE = {"width": 390, "height": 844}
PARKED = "parked-07"  # registered, never sent anything: listed "not live"

# Every shown element of these selectors whose content is wider than its box.
_CLIPPED_JS = """
(selectors) => [...document.querySelectorAll(selectors.join(','))]
  .filter((e) => getComputedStyle(e).display !== 'none' && e.getClientRects().length)
  .filter((e) => e.scrollWidth > e.clientWidth)
  .map((e) => ({cls: e.className || e.id, text: e.textContent,
                sw: e.scrollWidth, cw: e.clientWidth}))
"""
_CELLS = [".vhead > div", ".vhead button", ".vrows .vrow > div", ".vrows .pill"]


def _vehicle(stack: LiveStack, vid: str, method: str) -> None:
    data = b"{}" if method == "PUT" else None
    req = urllib.request.Request(f"{stack.base_url}/api/v1/vehicles/{vid}", data, method=method)
    req.add_header("Content-Type", "application/json")
    with urllib.request.urlopen(req, timeout=10) as resp:
        assert resp.status in (200, 201, 204)


@pytest.fixture
def parked(live_stack: LiveStack) -> Iterator[str]:
    _vehicle(live_stack, PARKED, "PUT")
    try:
        yield PARKED
    finally:
        _vehicle(live_stack, PARKED, "DELETE")


@pytest.fixture
def phone(browser: Any) -> Iterator[Any]:
    # the parked vehicle has no stored estimate: its /latest answers 404, as it should
    with checked_page(
        browser,
        lambda msg: "/latest" in msg.location.get("url", ""),
        viewport=PHONE,
        is_mobile=True,
        has_touch=True,
    ) as pg:
        yield pg


def test_no_fleet_table_cell_is_clipped_on_a_phone(
    live_stack: LiveStack, parked: str, phone: Any, screenshots: Path
) -> None:
    phone.goto(live_stack.base_url + "/#/fleet")
    phone.fill("#fleet-filter", "parked")  # the not-live row on screen, with its pill
    phone.wait_for_function(
        "(vid) => [...document.querySelectorAll('.vrows .vrow')].some((r) => !r.hidden"
        " && r.querySelector('.c-id a').textContent === vid"
        " && r.querySelector('.pill').textContent === 'not live')",
        arg=parked,
        timeout=15000,
    )
    assert phone.evaluate(_CLIPPED_JS, _CELLS) == []
    phone.fill("#fleet-filter", "")  # the live rows
    phone.wait_for_timeout(1200)
    assert phone.evaluate(_CLIPPED_JS, _CELLS) == []
    last = phone.evaluate(
        "(() => { const h = [...document.querySelectorAll('.vhead > div')]"
        ".filter((e) => getComputedStyle(e).display !== 'none').pop().getBoundingClientRect();"
        " return h.right; })()"
    )
    assert last <= PHONE["width"], last  # the last column is on the screen
    phone.screenshot(path=str(screenshots / "fleet-phone-390.png"), full_page=True)


def test_no_map_title_is_clipped_on_a_phone(live_stack: LiveStack, phone: Any) -> None:
    phone.goto(live_stack.base_url + "/#/vehicle/veh-002")
    phone.wait_for_function(
        "document.getElementById('live-map-title')?.textContent.length > 0", timeout=15000
    )
    assert phone.evaluate(_CLIPPED_JS, ["#live-map-title", ".toolbar h1"]) == []
    phone.goto(live_stack.base_url + "/#/vehicle/veh-002/history")
    history_loaded(phone)
    assert phone.evaluate(_CLIPPED_JS, ["#h-map-title", "#h-shade-legend"]) == []
    phone.goto(live_stack.base_url + "/#/fleet")
    phone.wait_for_selector("#fleet-map-title", timeout=15000)
    assert phone.evaluate(_CLIPPED_JS, ["#fleet-map-title", "#fleet-map-note"]) == []
