"""Times in the browser's own zone by default, UTC on hover, and UTC by choice (kept across
reloads): the vehicle page, its charts and the alerts table, in a real Chromium whose zone is
Europe/Berlin (CET in November, CEST in summer)."""

from __future__ import annotations

from contextlib import AbstractContextManager
from datetime import UTC, datetime
from typing import Any
from zoneinfo import ZoneInfo

import pytest

from tests.web.conftest import LiveStack, checked_page

pytestmark = pytest.mark.browser

BERLIN = ZoneInfo("Europe/Berlin")


def _berlin_page(browser: Any) -> AbstractContextManager[Any]:
    return checked_page(
        browser,
        viewport={"width": 1400, "height": 900},
        timezone_id="Europe/Berlin",
        locale="en-GB",
    )


def _stamp(page: Any) -> tuple[int, str, str]:
    """The vehicle page's sensor time: stamp (ns), text, title."""
    page.wait_for_function("() => document.getElementById('v-stamp').dataset.stampNs")
    ns = int(page.get_attribute("#v-stamp", "data-stamp-ns"))
    return ns, page.inner_text("#v-stamp"), page.get_attribute("#v-stamp", "title") or ""


def _reading(ns: int, zone: Any, name: str) -> str:
    t = datetime.fromtimestamp(ns / 1e9, zone)
    return f"{t:%Y-%m-%d %H:%M:%S}.{t.microsecond // 1000:03d} {name}"


def _settled_stamp(page: Any) -> tuple[int, str, str]:
    """A reading whose text and title belong to one stamp (the page updates at up to 10 Hz)."""
    for _ in range(20):
        first = _stamp(page)
        if _stamp(page)[0] == first[0]:
            return first
    raise AssertionError("the sensor time never held still")


def test_times_are_local_with_utc_on_hover_or_utc_by_choice(
    live_stack: LiveStack, browser: Any
) -> None:
    with _berlin_page(browser) as page:
        page.goto(f"{live_stack.base_url}/#/vehicle/veh-000")
        name = datetime.now(BERLIN).tzname()
        assert name in ("CET", "CEST")
        assert page.inner_text("#tz-select option[value=local]") == f"Local ({name})"
        ns, text, title = _settled_stamp(page)
        assert text == _reading(ns, BERLIN, name) or text == _reading(ns + 1_000_000, BERLIN, name)
        assert title.endswith(" UTC") and title[:19] == _reading(ns, UTC, "UTC")[:19]
        page.wait_for_function(f"() => document.body.innerText.includes('time ({name})')")

        page.goto(f"{live_stack.base_url}/#/alerts")
        page.wait_for_selector("#alerts-body")
        headers = page.eval_on_selector_all("thead th", "(ths) => ths.map((t) => t.textContent)")
        assert f"Start ({name})" in headers and f"End ({name})" in headers

        page.goto(f"{live_stack.base_url}/#/vehicle/veh-000")
        page.select_option("#tz-select", "utc")
        ns, text, title = _settled_stamp(page)
        assert text.endswith(" UTC") and text[:19] == _reading(ns, UTC, "UTC")[:19]
        assert title.endswith(f" {name}") and title[:19] == _reading(ns, BERLIN, name)[:19]
        page.wait_for_function("() => document.body.innerText.includes('time (UTC)')")
        page.reload()  # the choice is kept
        assert page.input_value("#tz-select") == "utc"
        assert _settled_stamp(page)[1].endswith(" UTC")


def test_history_inputs_are_read_in_the_chosen_zone(live_stack: LiveStack, browser: Any) -> None:
    with _berlin_page(browser) as page:
        page.goto(f"{live_stack.base_url}/#/vehicle/veh-000/history")
        page.wait_for_function("() => document.getElementById('h-end').value")
        end_text = page.input_value("#h-end")
        # what the page shows as the end, read as Berlin time, is within a minute of now
        shown = datetime.strptime(end_text, "%Y-%m-%d %H:%M:%S").replace(tzinfo=BERLIN)
        assert abs(shown.timestamp() - datetime.now(UTC).timestamp()) < 60
        label = page.get_attribute("#h-start", "aria-label") or ""
        assert label.startswith("Start (CE")
