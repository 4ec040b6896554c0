"""The dashboard in a real headless Chromium against a real app streaming live data."""

from __future__ import annotations

import json
import math
import time
import urllib.request
from pathlib import Path
from typing import Any

import pytest

from estimator.mdsf_spec import MDSF_SPEC
from estimator.types import EstimateBatch, empty_estimates
from estimator.types import EstimateFlag as F
from tests.web.conftest import N_VEHICLES, SENSITIVE, LiveStack, history_loaded

pytestmark = pytest.mark.browser

VID = SENSITIVE
JS_NS_RESOLUTION = 1024  # ns: an int64 stamp read by JavaScript is a double (53-bit mantissa)

# Pixels of a canvas that are clearly coloured (not white, grey or black): slip-scale ink.
_COLOURED_PIXELS_JS = """
(id) => {
  const c = document.getElementById(id);
  const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
  let n = 0;
  for (let i = 0; i < d.length; i += 4) {
    const mx = Math.max(d[i], d[i + 1], d[i + 2]);
    const mn = Math.min(d[i], d[i + 1], d[i + 2]);
    if (mx - mn > 60) n++;
  }
  return n;
}
"""


def _get(url: str) -> Any:
    with urllib.request.urlopen(url, timeout=10) as resp:
        return json.loads(resp.read())


def _page_latest(page: Any) -> tuple[int, float]:
    """Stamp and shown left slip, read together (an update may land between two reads)."""
    stamp, text = page.evaluate(
        "() => { const e = document.getElementById('v-mdsf-slip-left');"
        " return [e.dataset.stampNs, e.textContent]; }"
    )
    return int(stamp), float("nan") if text == "–" else float(text)


def _assert_cells_banded_by_their_values(page: Any, base_url: str) -> None:
    """Each live slip cell's band class is the band of the value it shows (edges per vehicle).

    A cell whose channel has no value this tick (shown "–") carries no band (``band--1``);
    a shown value within the display's rounding of an edge may sit in either band.
    """
    edges = {
        v["vehicle_id"]: v["config"]["slip"]["band_edges_pct"]
        for v in _get(base_url + "/api/v1/vehicles")["data"]
    }
    cells = page.eval_on_selector_all(
        ".vrows .vrow:not([hidden])",
        """rows => rows.flatMap(r => [...r.querySelectorAll('.slip')].map(c =>
            [r.querySelector('.c-id a').textContent, c.className,
             c.querySelector('span:last-child').textContent]))""",
    )
    assert len(cells) == 2 * N_VEHICLES
    shown = 0
    for vid, cls, text in cells:
        band = int(cls.rsplit("band-", 1)[1])
        if text == "–":
            assert band == -1, (vid, cls, text)
            continue
        shown += 1
        v = abs(float(text))
        e = edges[vid]
        allowed = {_styled_band(v - 0.05, e), _styled_band(v + 0.05, e)}
        assert band in allowed, (vid, cls, text, e)
    assert shown >= N_VEHICLES  # most channels read a value on a moving fleet


def _styled_band(slip_pct: float, edges: list[float]) -> int:
    """The dashboard's styled band: 0 below the first edge, 2 above the last, 1 between."""
    b = sum(1 for e in edges if abs(slip_pct) >= e)
    return 0 if b == 0 else 2 if b == len(edges) else 1


def test_fleet_overview_lists_every_vehicle_and_sorts(
    live_stack: LiveStack, page: Any, screenshots: Path
) -> None:
    page.goto(live_stack.base_url + "/#/fleet")
    page.wait_for_function(
        "(p) => document.getElementById('fleet-summary').textContent.startsWith(p)",
        arg=f"{N_VEHICLES} vehicles",
        timeout=15000,
    )
    ids = page.eval_on_selector_all(
        ".vrows .vrow:not([hidden]) .c-id a", "els => els.map(e => e.textContent)"
    )
    assert sorted(ids) == live_stack.runtime.fleet.ids
    assert page.inner_text("#fleet-summary").startswith(
        f"{N_VEHICLES} vehicles — {N_VEHICLES} live"
    )
    # sort by left slip, largest first
    page.click("text=Slip rear left wheel (%)")
    page.wait_for_timeout(700)  # next update re-renders
    sorted_attr = page.get_attribute(".vhead .c-slip-left", "aria-sort")
    assert sorted_attr in ("ascending", "descending")
    if sorted_attr == "ascending":
        page.click("text=Slip rear left wheel (%)")
    page.wait_for_function(
        "document.querySelector('.vhead .c-slip-left').getAttribute('aria-sort') === 'descending'"
    )
    vals = page.eval_on_selector_all(
        ".vrows .vrow:not([hidden])",
        """rows => rows
            .map(r => [parseFloat(r.style.transform.match(/\\d+/)[0]),
                       parseFloat(r.querySelector('.c-slip-left span:last-child').textContent)])
            .sort((a, b) => a[0] - b[0]).map(x => x[1])""",
    )
    assert vals == sorted(vals, key=abs, reverse=True)
    _assert_cells_banded_by_their_values(page, live_stack.base_url)
    page.screenshot(path=str(screenshots / "fleet.png"))


def test_vehicle_page_streams_slip_matching_the_server(
    live_stack: LiveStack, page: Any, screenshots: Path
) -> None:
    page.goto(live_stack.base_url + f"/#/vehicle/{VID}")
    page.wait_for_selector("#v-mdsf-slip-left[data-stamp-ns]", timeout=15000)
    hub = live_stack.runtime.live_hub
    fleet = live_stack.runtime.fleet
    i = fleet.ids.index(VID)

    seen: list[tuple[int, float]] = []
    for _ in range(3):
        stamp, shown = _page_latest(page)
        got = hub.latest(VID)
        assert got is not None
        hub_stamp = int(got[0]["stamp_ns"])
        # within one update (the page gets 4 updates a second; the feed runs at 20 Hz); the page
        # holds stamps as JS doubles, exact to about 256 ns at today's epoch
        assert -JS_NS_RESOLUTION <= hub_stamp - stamp < 1_000_000_000
        # the value shown is the value of that very estimate, rounded for display
        truth = float(fleet.rows_at(stamp)[i][1]["slip_left_pct"][0])
        assert math.isclose(shown, round(truth, 1), abs_tol=0.051)
        store_latest = _get(f"{live_stack.base_url}/api/v1/vehicles/{VID}/latest")
        assert abs(store_latest["stamp_ns"] - stamp) < 1_500_000_000
        seen.append((stamp, shown))
        page.wait_for_timeout(1200)
    assert len({s for s, _ in seen}) == 3, "the page stopped updating"
    assert len({v for _, v in seen}) >= 2, "slip did not change over time"

    # charts: uPlot rendered both, with units on the axes and data in them
    for box, y_label, n_series in (
        ("chart-mdsf-slip", "wheel slip (%)", 2),
        ("chart-mdsf-speed", "speeds (m/s)", 5),
    ):
        info = page.evaluate(
            """(id) => { const u = document.getElementById(id)._uplot;
                return {labels: u.axes.map(a => a.label), series: u.series.length - 1,
                        threshold: u._threshold,
                        points: u.data[0].length}; }""",
            box,
        )
        assert info["labels"] == ["time (UTC)", y_label]
        assert info["threshold"] == (
            12.0 if box == "chart-mdsf-slip" else None
        )  # the vehicle's config
        assert info["series"] == n_series
        assert info["points"] > 50
    # the map drew the track in slip colours
    page.wait_for_function(f"({_COLOURED_PIXELS_JS})('live-map') > 500", timeout=10000)
    # latency sensor -> page is measured and small on loopback
    lat = page.evaluate("() => window.slipfleetStats.latencyMs.slice()")
    assert lat and sorted(lat)[len(lat) // 2] < 1000
    # a longer window comes as a new snapshot from the coarse tier
    page.click("button[data-window='1800']")
    page.wait_for_timeout(800)
    page.screenshot(path=str(screenshots / "vehicle.png"), full_page=True)


def test_history_replays_charts_and_map_in_sync(
    live_stack: LiveStack, page: Any, screenshots: Path
) -> None:
    page.goto(live_stack.base_url + f"/#/vehicle/{VID}/history")
    n = history_loaded(page)
    assert n > 100
    page.wait_for_function(f"({_COLOURED_PIXELS_JS})('h-map') > 500", timeout=10000)
    # scrub to the middle: the cursor time and values follow
    page.eval_on_selector(
        "#h-scrub",
        "(e) => { e.value = String(Math.floor(Number(e.max) / 2));"
        " e.dispatchEvent(new Event('input')); }",
    )
    mid_at = page.inner_text("#h-at")
    assert mid_at.endswith("UTC")
    page.check("#h-heat")
    page.select_option("#h-speed", "10")
    page.click("#h-play")
    page.wait_for_timeout(1500)
    page.click("#h-play")  # pause
    after = page.inner_text("#h-at")
    assert after > mid_at, "replay did not advance"
    assert page.inner_text("#h-play").endswith("Play")
    # the charts' replay cursor is at the same time as the map's position
    cursor_s = page.evaluate("() => document.getElementById('h-chart-slip')._uplot._cursorT")
    assert after.startswith(time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(cursor_s)))
    page.screenshot(path=str(screenshots / "history.png"), full_page=True)


def test_alerts_panel_shows_alerts(live_stack: LiveStack, page: Any, screenshots: Path) -> None:
    engine = live_stack.runtime.alert_engine
    deadline = time.monotonic() + 20
    while not engine.alerts() and time.monotonic() < deadline:
        time.sleep(0.2)
    expected = engine.alerts()
    assert expected, "the synthetic fleet raised no alert"
    page.goto(live_stack.base_url + "/#/alerts")
    page.wait_for_selector("#alerts-body tr td a", timeout=10000)
    shown = page.eval_on_selector_all("#alerts-body tr td a", "els => els.map(e => e.textContent)")
    assert {a.vehicle_id for a in expected} <= set(shown) | {
        a.vehicle_id for a in expected[len(shown) :]
    }
    page.screenshot(path=str(screenshots / "alerts.png"), full_page=True)


def test_api_docs_render_offline(live_stack: LiveStack, page: Any, screenshots: Path) -> None:
    """Swagger UI at /docs renders every operation from files this server serves."""
    page.goto(live_stack.base_url + "/docs")
    page.wait_for_selector(".opblock", timeout=20000)
    operations = page.locator(".opblock").count()
    assert operations >= 10, operations
    assert "Slipfleet" in page.inner_text(".info .title")
    page.screenshot(path=str(screenshots / "api_docs.png"))


def test_vehicle_page_says_why_slip_is_missing(live_stack: LiveStack, page: Any) -> None:
    hub = live_stack.runtime.live_hub
    vid = "standing-1"  # a vehicle of its own: the synthetic feed does not touch it

    def send(flags: int, slip_pct: float) -> None:
        row = empty_estimates(1)
        row["stamp_ns"] = time.time_ns()
        row["vg_mps"] = 0.0 if flags & F.STANDSTILL else 0.3
        row["slip_left_pct"] = row["slip_right_pct"] = slip_pct
        row["flags"] = flags
        hub.on_estimates(EstimateBatch.of([(vid, row)], MDSF_SPEC))

    def call(method: str, body: bytes | None = None) -> int:
        url = f"{live_stack.base_url}/api/v1/vehicles/{vid}"
        req = urllib.request.Request(url, data=body, method=method)
        req.add_header("Content-Type", "application/json")
        with urllib.request.urlopen(req, timeout=10) as resp:
            return int(resp.status)

    note = "#v-mdsf-slip-left-note"
    assert call("PUT", b"{}") in (200, 201)  # registered, as the pipeline would
    try:
        send(int(F.STANDSTILL | F.GNSS_OK), math.nan)
        page.goto(live_stack.base_url + f"/#/vehicle/{vid}")
        page.wait_for_function(
            f"document.querySelector('{note}')?.textContent === 'no value: standstill'",
            timeout=15000,
        )
        assert page.text_content("#v-mdsf-slip-left") == "–"
        send(int(F.SETTLING | F.GNSS_OK), math.nan)
        page.wait_for_function(
            f"document.querySelector('{note}').textContent === 'no value: settling'", timeout=10000
        )
        send(int(F.GNSS_OK | F.SLIP_LEFT_VALID | F.SLIP_RIGHT_VALID), 7.0)
        page.wait_for_function(
            f"document.querySelector('{note}').textContent === ''", timeout=10000
        )
        assert page.text_content("#v-mdsf-slip-left") == "7.0"
        assert not page.is_visible(note)
    finally:
        hub.forget(vid)
        call("DELETE")
