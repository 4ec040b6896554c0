"""The fleet table as a person sees it: what the filter leaves on screen, the phone layout, stale
and offline vehicles, and number formatting, in a real headless Chromium against the live stack.

Visibility is measured (computed style and bounding boxes), not read from the ``hidden``
attribute: a class rule can override that attribute, which is how rows left over from a longer
list once stayed on screen with frozen numbers.
"""

from __future__ import annotations

import re
import time
from contextlib import AbstractContextManager
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from server.tooling.bench.live import SyntheticFleet
from tests.web.conftest import N_VEHICLES, LiveStack, checked_page

pytestmark = pytest.mark.browser

PHONE = {"width": 390, "height": 844}
ALIGN_PX = 2.0

# Every pool row of the table: id, computed display, box, and whether any of it is on screen
# inside the rows' scroll box.
_ROWS_JS = """
() => {
  const box = document.getElementById('fleet-rows').getBoundingClientRect();
  return [...document.querySelectorAll('.vrows .vrow')].map((r) => {
    const b = r.getBoundingClientRect();
    return {
      id: r.querySelector('.c-id a').textContent,
      display: getComputedStyle(r).display,
      w: b.width, h: b.height,
      onScreen: b.width > 0 && b.height > 0 && b.bottom > box.top && b.top < box.bottom
        && b.right > box.left && b.left < box.right,
    };
  });
}
"""

# Box of each listed cell of the header and of the first row on screen (topmost), in viewport px,
# with the box of the cell's text and whether the cell is displayed.
_CELLS_JS = """
(keys) => {
  const rows = [...document.querySelectorAll('.vrows .vrow')]
    .filter((r) => getComputedStyle(r).display !== 'none')
    .sort((a, b) => a.getBoundingClientRect().top - b.getBoundingClientRect().top);
  const box = (e) => {
    const b = e.getBoundingClientRect();
    return { left: b.left, right: b.right, top: b.top, bottom: b.bottom, width: b.width };
  };
  const cell = (row, k) => {
    const c = row.querySelector('.c-' + k);
    const btn = c.querySelector('button');
    const text = btn || c.lastElementChild || c;
    const clipped = c.scrollWidth > c.clientWidth || (btn && btn.scrollWidth > btn.clientWidth);
    return { ...box(c), display: getComputedStyle(c).display, text: box(text), clipped };
  };
  const head = document.querySelector('.vhead');
  return {
    head: Object.fromEntries(keys.map((k) => [k, cell(head, k)])),
    row: Object.fromEntries(keys.map((k) => [k, cell(rows[0], k)])),
    rowId: rows[0].querySelector('.c-id a').textContent,
  };
}
"""

_ROW_OF_JS = """
(vid) => {
  const r = [...document.querySelectorAll('.vrows .vrow')]
    .find((r) => getComputedStyle(r).display !== 'none'
      && r.querySelector('.c-id a').textContent === vid);
  if (!r) return null;
  const cs = (e) => getComputedStyle(e);
  const slip = (k) => {
    const c = r.querySelector('.c-' + k);
    return { cls: c.className, bg: cs(c).backgroundColor, color: cs(c.lastElementChild).color,
             dotBg: cs(c.firstElementChild).backgroundColor, text: c.lastElementChild.textContent };
  };
  return {
    cls: r.className,
    status: r.querySelector('.c-status .pill').textContent,
    speedColor: cs(r.querySelector('.c-speed_mps')).color,
    speedStyle: cs(r.querySelector('.c-speed_mps')).fontStyle,
    gnssCls: r.querySelector('.c-quality').className,
    age: r.querySelector('.c-age_s').textContent,
    left: slip('slip-left'),
    right: slip('slip-right'),
  };
}
"""


def _open_fleet(page: Any, base_url: str) -> None:
    page.goto(base_url + "/#/fleet")
    page.wait_for_function(
        "(p) => document.getElementById('fleet-summary').textContent.startsWith(p)",
        arg=f"{N_VEHICLES} vehicles —",
        timeout=15000,
    )


def _shown_ids(page: Any) -> list[str]:
    rows = page.evaluate(_ROWS_JS)
    for r in rows:
        # a row is either really gone (display none, no box) or fully laid out on screen
        assert (r["display"] == "none") == (r["w"] == 0 and r["h"] == 0), r
    return [r["id"] for r in rows if r["onScreen"]]


def _set_filter(page: Any, text: str, summary_prefix: str) -> None:
    page.fill("#fleet-filter", text)
    page.wait_for_function(
        "(p) => document.getElementById('fleet-summary').textContent.startsWith(p)",
        arg=summary_prefix,
        timeout=5000,
    )
    page.wait_for_timeout(700)  # at least one more live update re-renders the rows


def test_filter_leaves_exactly_the_matching_rows_on_screen(
    live_stack: LiveStack, page: Any, screenshots: Path
) -> None:
    ids = live_stack.runtime.fleet.ids
    _open_fleet(page, live_stack.base_url)
    assert sorted(_shown_ids(page)) == ids  # the pool now holds a row per vehicle

    _set_filter(page, "01", "3 of 12 vehicles shown")
    want = [v for v in ids if "01" in v]
    assert want == ["veh-001", "veh-010", "veh-011"]
    shown = _shown_ids(page)
    assert sorted(shown) == want, f"rows on screen for filter '01': {shown}"
    summary = page.inner_text("#fleet-summary")
    assert re.fullmatch(r"3 of 12 vehicles shown — \d+ live, \d+ stale, \d+ offline", summary)
    assert sum(int(n) for n in re.findall(r"(\d+) (?:live|stale|offline)", summary)) == 3
    assert not page.is_visible(".vempty")
    page.screenshot(path=str(screenshots / "fleet-filter-01.png"))

    _set_filter(page, "zzz", "No vehicle matches")
    assert _shown_ids(page) == []
    assert page.inner_text("#fleet-summary") == "No vehicle matches “zzz” (12 vehicles in all)"
    assert page.is_visible(".vempty")
    assert "zzz" in page.inner_text(".vempty")
    page.screenshot(path=str(screenshots / "fleet-filter-none.png"))

    _set_filter(page, "", f"{N_VEHICLES} vehicles —")
    assert sorted(_shown_ids(page)) == ids
    assert not page.is_visible(".vempty")


def test_desktop_header_and_rows_line_up(live_stack: LiveStack, page: Any) -> None:
    keys = ["id", "status", "speed_mps", "slip-left", "slip-right", "quality", "age_s"]
    _open_fleet(page, live_stack.base_url)
    got = page.evaluate(_CELLS_JS, keys)
    for k in keys:
        h, r = got["head"][k], got["row"][k]
        assert abs(h["left"] - r["left"]) <= ALIGN_PX, k
        assert abs(h["right"] - r["right"]) <= ALIGN_PX, k
        assert r["display"] != "none" and r["left"] >= 0 and r["right"] <= 1400, k
    # the full labels are shown on a wide screen
    assert page.inner_text(".vhead .c-slip-left") == "Slip rear left wheel (%)"  # its label


def _phone_page(browser: Any) -> AbstractContextManager[Any]:
    return checked_page(browser, viewport=PHONE, is_mobile=True, has_touch=True)


def _assert_phone_columns(got: dict[str, Any], keys: list[str]) -> None:
    for k in keys:
        h, r = got["head"][k], got["row"][k]
        for part, b in (("header", h), ("row", r)):
            assert b["display"] != "none" and b["width"] > 0, f"{part} {k} not shown"
            assert b["left"] >= 0 and b["right"] <= PHONE["width"], f"{part} {k} off screen: {b}"
            # the text itself is inside its cell, not cut off by the cell's edge
            t = b["text"]
            assert b["left"] - 0.5 <= t["left"] and t["right"] <= b["right"] + 0.5, (
                f"{part} {k} text outside its cell: {t} in {b}"
            )
            assert not b["clipped"], f"{part} {k}: content cut off"
        assert abs(h["left"] - r["left"]) <= ALIGN_PX, f"{k}: header {h['left']}, row {r['left']}"
        assert abs(h["right"] - r["right"]) <= ALIGN_PX, k


def test_phone_fleet_table_fits_and_lines_up(
    live_stack: LiveStack, browser: Any, screenshots: Path
) -> None:
    keys = ["id", "status", "speed_mps", "slip-left", "slip-right"]
    with _phone_page(browser) as pg:
        _open_fleet(pg, live_stack.base_url)
        pg.wait_for_timeout(600)
        # no sideways scrolling: neither the page nor the rows' box is wider than the screen
        doc_w = pg.evaluate("document.documentElement.scrollWidth")
        assert doc_w <= PHONE["width"], f"page is {doc_w} px wide"
        sw, cw = pg.evaluate(
            "(() => { const s = document.getElementById('fleet-rows');"
            " return [s.scrollWidth, s.clientWidth]; })()"
        )
        assert sw <= cw, f"rows are {sw} px wide in a {cw} px box"
        got = pg.evaluate(_CELLS_JS, keys)
        _assert_phone_columns(got, keys)
        # a sideways swipe on the rows cannot shift them against the header
        pg.evaluate("document.getElementById('fleet-rows').scrollLeft = 600")
        pg.wait_for_timeout(100)
        _assert_phone_columns(pg.evaluate(_CELLS_JS, keys), keys)
        # the values are the vehicle's own: a number (or "–") in each slip cell
        row_text = pg.evaluate(
            "(vid) => [...document.querySelectorAll('.vrows .vrow')]"
            ".find(r => r.querySelector('.c-id a').textContent === vid)"
            ".querySelector('.c-slip-right').textContent",
            got["rowId"],
        )
        assert re.fullmatch(r"-?\d+\.\d|–", row_text)
        # the nav: both links on one line, side by side, not overlapping the token button
        nav = pg.evaluate(
            """() => ['nav a[data-view=fleet]', 'nav a[data-view=alerts]', '#token-button']
                .map((s) => document.querySelector(s).getBoundingClientRect())
                .map((b) => ({ left: b.left, right: b.right, top: b.top, h: b.height }))"""
        )
        fleet_a, alerts_a, token = nav
        assert abs(fleet_a["top"] - alerts_a["top"]) <= 1, nav
        assert fleet_a["right"] <= alerts_a["left"], nav
        assert fleet_a["h"] < 40 and alerts_a["h"] < 40, nav  # one line each
        assert alerts_a["right"] <= token["left"] or token["top"] >= alerts_a["top"] + alerts_a["h"]
        assert token["right"] <= PHONE["width"]
        pg.screenshot(path=str(screenshots / "fleet-phone.png"))


def test_phone_alerts_table_scrolls_in_its_own_box(
    live_stack: LiveStack, browser: Any, screenshots: Path
) -> None:
    engine = live_stack.runtime.alert_engine
    deadline = time.monotonic() + 20
    while not engine.alerts() and time.monotonic() < deadline:
        time.sleep(0.2)
    assert engine.alerts(), "the synthetic fleet raised no alert"
    with _phone_page(browser) as pg:
        pg.goto(live_stack.base_url + "/#/alerts")
        pg.wait_for_selector("#alerts-body tr td a", timeout=10000)
        assert pg.evaluate("document.documentElement.scrollWidth") <= PHONE["width"]
        box = pg.evaluate(
            """() => { const s = document.getElementById('alerts-scroll');
                const b = s.getBoundingClientRect();
                return { left: b.left, right: b.right, sw: s.scrollWidth, cw: s.clientWidth,
                         ox: getComputedStyle(s).overflowX,
                         hasHead: !!s.querySelector('thead th') }; }"""
        )
        assert box["left"] >= 0 and box["right"] <= PHONE["width"], box
        assert box["hasHead"] and box["ox"] in ("auto", "scroll"), box
        # scrolled to its end, the last column's header still stands over its cells
        pg.evaluate(
            "(() => { const s = document.getElementById('alerts-scroll');"
            " s.scrollLeft = s.scrollWidth; })()"
        )
        pg.wait_for_timeout(100)
        th, td = pg.evaluate(
            """() => ['thead th:last-child', '#alerts-body tr:first-child td:last-child']
                .map((q) => document.querySelector('#alerts-scroll ' + q).getBoundingClientRect())
                .map((b) => [b.left, b.right])"""
        )
        assert abs(th[0] - td[0]) <= ALIGN_PX and abs(th[1] - td[1]) <= ALIGN_PX
        assert th[1] <= PHONE["width"] + ALIGN_PX
        pg.screenshot(path=str(screenshots / "alerts-phone.png"))


def test_fmt_never_prints_negative_zero(live_stack: LiveStack, page: Any) -> None:
    page.goto(live_stack.base_url + "/#/alerts")
    cases = [
        (-0.001, 2, "0.00"),
        (-0.004, 2, "0.00"),
        (-0.0, 2, "0.00"),
        (-0.04, 1, "0.0"),
        (-0.4, 0, "0"),
        (0.001, 2, "0.00"),
        (-0.006, 2, "-0.01"),
        (-0.06, 1, "-0.1"),
        (-1.234, 2, "-1.23"),
        (None, 1, "–"),
    ]
    got = page.evaluate(
        "async (cases) => { const { fmt } = await import('/js/util.js');"
        " return cases.map(([v, d]) => fmt(v, d)); }",
        [[v, d] for v, d, _ in cases],
    )
    assert got == [want for _, _, want in cases]


def test_durations_round_once(live_stack: LiveStack, page: Any) -> None:
    """``fmtDuration`` (alerts, history): 599.6 s printed "9 min 60 s" before."""
    page.goto(live_stack.base_url + "/#/fleet")
    cases = [
        (0.3912, "0.391 s"),
        (4.25, "4.25 s"),
        (21.6, "21.6 s"),
        (599.6, "10 min"),
        (842.0, "14 min 2 s"),
        (3599.7, "1 h"),
        (5400.0, "1 h 30 min"),
        (43200.0, "12 h"),
        (None, "–"),
    ]
    got = page.evaluate(
        "async (cases) => { const { fmtDuration } = await import('/js/util.js');"
        " return cases.map((v) => fmtDuration(v)); }",
        [v for v, _ in cases],
    )
    assert got == [want for _, want in cases]


class _Silenced:
    """The synthetic fleet less one vehicle, as if that vehicle had stopped sending."""

    def __init__(self, fleet: SyntheticFleet, vehicle_id: str) -> None:
        self.fleet = fleet
        self.ids = fleet.ids
        self.vehicle_id = vehicle_id

    def rows_at(self, stamp_ns: int) -> list[tuple[str, np.ndarray]]:
        return [r for r in self.fleet.rows_at(stamp_ns) if r[0] != self.vehicle_id]


def _wait_row(page: Any, vid: str, status: str) -> dict[str, Any]:
    page.wait_for_function(
        "([vid, st]) => [...document.querySelectorAll('.vrows .vrow')].some((r) =>"
        " r.querySelector('.c-id a').textContent === vid"
        " && r.querySelector('.pill').textContent === st)",
        arg=[vid, status],
        timeout=20000,
    )
    row = page.evaluate(_ROW_OF_JS, vid)
    assert row is not None
    return row


def _assert_marked_old(row: dict[str, Any], live_row: dict[str, Any], status: str) -> None:
    assert row["status"] == status
    assert f"row-{status}" in row["cls"].split()
    for k in ("left", "right"):
        cell = row[k]
        # no slip-band shading: the cell is not coloured as a live low / moderate / high slip
        assert not re.search(r"\bband-[012]\b", cell["cls"]), cell
        assert cell["bg"] in ("rgba(0, 0, 0, 0)", "transparent"), cell
        assert cell["dotBg"] in ("rgba(0, 0, 0, 0)", "transparent"), cell  # no slip colour
        assert cell["color"] != live_row[k]["color"], cell  # greyed against a live row
    assert row["speedColor"] != live_row["speedColor"]
    assert row["speedStyle"] == "italic"
    assert not re.search(r"quality-", row["gnssCls"])  # "ok" not shown as current
    assert float(row["age"]) >= 3.0


def test_a_vehicle_that_stops_sending_is_marked_stale_then_offline(
    live_stack: LiveStack, page: Any, screenshots: Path
) -> None:
    runtime = live_stack.runtime
    hub = runtime.live_hub
    feed = runtime.feed
    assert feed is not None
    vid = "veh-004"
    other = "veh-005"
    real_fleet = feed.fleet
    offline_after_s = hub.offline_after_s
    _open_fleet(page, live_stack.base_url)
    live_row = _wait_row(page, other, "live")
    assert re.search(r"\bband-[012]\b", live_row["left"]["cls"])
    try:
        feed.fleet = _Silenced(real_fleet, vid)  # type: ignore[assignment]
        # stale after 3 s of silence (the hub's default); offline brought forward from 30 s to
        # 8 s so the test need not wait half a minute: the page only shows the server's status
        hub.offline_after_s = 8.0
        stale = _wait_row(page, vid, "stale")
        live_row = page.evaluate(_ROW_OF_JS, other)
        assert live_row["status"] == "live"
        _assert_marked_old(stale, live_row, "stale")
        assert re.search(r"11 live, 1 stale, 0 offline", page.inner_text("#fleet-summary"))
        page.screenshot(path=str(screenshots / "fleet-stale.png"))

        offline = _wait_row(page, vid, "offline")
        _assert_marked_old(offline, page.evaluate(_ROW_OF_JS, other), "offline")
        assert float(offline["age"]) >= 8.0
        assert re.search(r"11 live, 0 stale, 1 offline", page.inner_text("#fleet-summary"))
        page.screenshot(path=str(screenshots / "fleet-offline.png"))
    finally:
        feed.fleet = real_fleet
        hub.offline_after_s = offline_after_s
    # data again: the row is live and coloured again
    back = _wait_row(page, vid, "live")
    assert "row-old" not in back["cls"].split()
    assert re.search(r"\bband-[012]\b", back["left"]["cls"])
