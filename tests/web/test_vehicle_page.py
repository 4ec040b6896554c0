"""The live vehicle page in headless Chromium: phone width, unknown, silent and degraded vehicles.

Runs against the same live stack as ``test_dashboard.py`` (12 synthetic vehicles at 20 Hz). The
silent and degraded vehicles are vehicles of their own, registered over REST and fed straight into
the hub (as the pipeline would), so the synthetic fleet stays untouched.
"""

from __future__ import annotations

import math
import threading
import time
import urllib.request
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

from estimator.mdsf_spec import MDSF_SPEC
from estimator.types import EstimateBatch, empty_estimates
from estimator.types import EstimateFlag as F
from tests.web.conftest import SENSITIVE, LiveStack, checked_page, history_loaded

pytestmark = pytest.mark.browser

PHONE = {"width": 390, "height": 844}
DESKTOP = {"width": 1400, "height": 900}
_OK = int(F.GNSS_OK | F.SLIP_LEFT_VALID | F.SLIP_RIGHT_VALID)

# document width; each chart box's width against the column it sits in (main's content box),
# and the chart's width against the box's content box
_LAYOUT_JS = """
() => {
  const inner = (e) => {
    const cs = getComputedStyle(e);
    return e.clientWidth - parseFloat(cs.paddingLeft) - parseFloat(cs.paddingRight);
  };
  const column = inner(document.getElementById('main'));
  const charts = [...document.querySelectorAll('.chart')].map((box) => (
    {id: box.id, chart: box._uplot.width, content: inner(box), box: box.offsetWidth}));
  return {scroll: document.documentElement.scrollWidth,
          client: document.documentElement.clientWidth, column, charts};
}
"""


@pytest.fixture
def phone(browser: Any) -> Iterator[Any]:
    with checked_page(browser, viewport=PHONE) as pg:
        yield pg


def _call(stack: LiveStack, method: str, path: str, body: bytes | None = None) -> int:
    req = urllib.request.Request(f"{stack.base_url}{path}", data=body, method=method)
    req.add_header("Content-Type", "application/json")
    with urllib.request.urlopen(req, timeout=10) as resp:
        return int(resp.status)


@contextmanager
def _own_vehicle(stack: LiveStack, vid: str) -> Iterator[Callable[[int], None]]:
    """A registered vehicle the synthetic feed does not touch; yields ``send(flags)``, which
    pushes one estimate stamped now into the hub."""
    hub = stack.runtime.live_hub

    def send(flags: int) -> None:
        row = empty_estimates(1)
        row["stamp_ns"] = time.time_ns()
        for k in ("vg_mps", "vl_mps", "vr_mps"):
            row[k] = 2.0
        row["rim_left_mps"] = row["rim_right_mps"] = 2.2
        row["slip_left_pct"] = row["slip_right_pct"] = 9.0
        row["flags"] = flags
        hub.on_estimates(EstimateBatch.of([(vid, row)], MDSF_SPEC))

    assert _call(stack, "PUT", f"/api/v1/vehicles/{vid}", b"{}") in (200, 201)
    try:
        yield send
    finally:
        hub.forget(vid)
        _call(stack, "DELETE", f"/api/v1/vehicles/{vid}")


def _wait_updates(page: Any, n: int, check: Callable[[], None]) -> None:
    """Wait for ``n`` new estimates drawn on the page, calling ``check`` after each."""
    last = None
    for _ in range(n):
        last = page.wait_for_function(
            "(prev) => { const s = document.getElementById('v-mdsf-slip-left')?.dataset.stampNs;"
            " return s && s !== prev ? s : false; }",
            arg=last,
            timeout=10000,
        ).json_value()
        page.evaluate("() => new Promise((r) => requestAnimationFrame(() => r()))")  # drawn
        check()


def test_phone_vehicle_page_keeps_to_the_viewport(
    live_stack: LiveStack, phone: Any, screenshots: Path
) -> None:
    """At 390 px the page does not grow with each redraw (it did by ~8 px per update)."""
    phone.goto(live_stack.base_url + f"/#/vehicle/{SENSITIVE}")
    phone.wait_for_selector("#v-mdsf-slip-left[data-stamp-ns]", timeout=15000)
    seen: list[dict[str, Any]] = []

    def check() -> None:
        lay = phone.evaluate(_LAYOUT_JS)
        seen.append(lay)
        assert lay["scroll"] <= PHONE["width"], lay
        for c in lay["charts"]:
            assert c["box"] <= lay["column"], lay
            assert 0 < c["chart"] <= c["content"], lay

    _wait_updates(phone, 30, check)
    # the charts still fill their boxes (no 320 px floor, no shrinking either)
    assert all(c["content"] - c["chart"] <= 2 for c in seen[-1]["charts"]), seen[-1]
    # the map is as wide as its column, not wider
    map_w = phone.evaluate("() => document.getElementById('live-map').clientWidth")
    assert map_w <= PHONE["width"] - 2 * 16
    phone.screenshot(path=str(screenshots / "vehicle-phone.png"), full_page=True)


def test_the_map_title_fits_a_phone(live_stack: LiveStack, phone: Any) -> None:
    """The live map's title ("Track (window) coloured by max |slip| of the wheels") ran past a
    390 px canvas, then was cut with an ellipsis; it is a heading above the canvas now, whole,
    wrapping inside the screen."""
    phone.goto(live_stack.base_url + f"/#/vehicle/{SENSITIVE}")
    phone.wait_for_selector("#live-map-title", timeout=15000)
    got = phone.evaluate(
        """() => {
          const t = document.getElementById('live-map-title');
          const b = t.getBoundingClientRect();
          return { text: t.textContent, title: document.getElementById('live-map')._slipmap.title,
                   sw: t.scrollWidth, cw: t.clientWidth, left: b.left, right: b.right,
                   lines: Math.round(b.height / parseFloat(getComputedStyle(t).lineHeight)) };
        }"""
    )
    assert got["text"] == got["title"] and "…" not in got["text"], got
    assert got["sw"] <= got["cw"], got
    assert got["left"] >= 0 and got["right"] <= PHONE["width"], got


def test_phone_history_charts_fit_and_have_time_ticks(
    live_stack: LiveStack, phone: Any, screenshots: Path
) -> None:
    phone.goto(live_stack.base_url + f"/#/vehicle/{SENSITIVE}/history")
    history_loaded(phone)
    lay = phone.evaluate(_LAYOUT_JS)
    assert lay["scroll"] <= PHONE["width"], lay
    for c in lay["charts"]:
        assert c["box"] <= lay["column"], lay
        assert 0 <= c["content"] - c["chart"] <= 2, lay  # neither clipped nor narrower
    # time labels at this width: a 4-minute span had one ("23:20"), so had 30 minutes; they must
    # not overlap either (uPlot keeps the ticks drawn in axes[0]._splits / _values)
    labels, gaps = phone.evaluate(
        """async (spans) => {
            const u = document.getElementById('h-chart-slip')._uplot;
            const ctx = document.createElement('canvas').getContext('2d');
            ctx.font = '12px system-ui, sans-serif';
            const hi = u.scales.x.max;
            const out = {}, gaps = {};
            for (const s of spans) {
                u.setScale('x', {min: hi - s, max: hi});
                await new Promise((r) => requestAnimationFrame(() => r()));
                const a = u.axes[0];
                const shown = a._splits.map((v, i) => [u.valToPos(v, 'x'), a._values[i]])
                    .filter(([, t]) => t);
                out[s] = shown.map(([, t]) => t);
                gaps[s] = shown.slice(1).map(([x, t], i) => x - shown[i][0]
                    - (ctx.measureText(t).width + ctx.measureText(shown[i][1]).width) / 2);
            }
            return [out, gaps];
        }""",
        [60, 240, 1800],
    )
    for span, shown in labels.items():
        assert len(shown) >= 3, (span, shown)
        assert len(set(shown)) == len(shown), (span, shown)
        assert min(gaps[span]) >= 4, (span, shown, gaps[span])
    assert all(len(v) == 8 for v in labels["60"]), labels  # HH:MM:SS under a minute per step
    assert all(len(v) == 5 for v in labels["1800"]), labels  # HH:MM
    phone.screenshot(path=str(screenshots / "history-phone.png"), full_page=True)


def test_unknown_vehicle_says_so_and_stops_asking(
    live_stack: LiveStack, browser: Any, screenshots: Path
) -> None:
    vid = "nope"

    def about_vehicle(url: str) -> bool:
        return f"/vehicles/{vid}" in url

    # the one refusal the page has to ask for (GET /api/v1/vehicles/nope -> 404) is logged by
    # Chromium as a console error; nothing else may be
    with checked_page(
        browser,
        allowed=lambda m: "404" in m.text and about_vehicle(m.location.get("url", "")),
        viewport=DESKTOP,
    ) as pg:
        asked: list[str] = []
        pg.on("request", lambda r: asked.append(r.url) if about_vehicle(r.url) else None)
        pg.on("websocket", lambda ws: asked.append(ws.url) if about_vehicle(ws.url) else None)
        pg.goto(live_stack.base_url + f"/#/vehicle/{vid}")
        msg = pg.wait_for_selector("#v-unknown", timeout=10000)
        text = msg.inner_text()
        assert "Unknown vehicle" in text and vid in text, text
        back = pg.get_attribute("#v-unknown a", "href")
        assert back == "#/fleet"
        # no charts, map or "no data yet" left behind
        assert pg.locator(".chart, canvas.map").count() == 0
        assert "no data yet" not in pg.inner_text("main")
        n = len(asked)
        assert n >= 1
        pg.wait_for_timeout(6000)  # longer than the ingest poll (5 s) and the socket's back-off
        assert asked[n:] == [], f"requests after the vehicle was reported unknown: {asked[n:]}"
        # the socket was closed too
        assert pg.evaluate("() => document.getElementById('v-status')?.textContent") in (
            None,
            "unknown vehicle",
        )
        pg.screenshot(path=str(screenshots / "vehicle-unknown.png"))


def test_silent_vehicle_is_shown_stale_with_its_age_not_as_latency(
    live_stack: LiveStack, page: Any, screenshots: Path
) -> None:
    vid = "quiet-1"
    stop = threading.Event()
    with _own_vehicle(live_stack, vid) as send:

        def feed() -> None:
            while not stop.is_set():
                send(_OK)
                time.sleep(0.05)

        feeder = threading.Thread(target=feed, daemon=True)
        feeder.start()
        try:
            page.goto(live_stack.base_url + f"/#/vehicle/{vid}")
            page.wait_for_function(
                "document.getElementById('v-status').textContent === 'live'"
                " && window.slipfleetStats.latencyMs.length >= 5",
                timeout=15000,
            )
            assert page.text_content("#v-latency") != "–"
            assert page.get_attribute(".stats", "class") == "stats"
        finally:
            stop.set()
            feeder.join()
        silent_since = time.monotonic()
        # stale after 3 s without data
        page.wait_for_function(
            "document.getElementById('v-status').textContent === 'stale'", timeout=10000
        )
        n_lat = page.evaluate("() => window.slipfleetStats.latencyMs.length")
        page.wait_for_timeout(3000)  # heartbeats keep coming with the same old estimate
        silent_s = time.monotonic() - silent_since
        got = page.evaluate(
            """() => ({lat: window.slipfleetStats.latencyMs.slice(),
                       latText: document.getElementById('v-latency').textContent,
                       latNote: document.getElementById('v-latency-note').textContent,
                       age: document.getElementById('v-age').textContent,
                       ageVisible: !document.getElementById('v-age').hidden,
                       stats: document.querySelector('.stats').className,
                       opacity: getComputedStyle(document.querySelector('.stat-value')).opacity,
                       slip: document.getElementById('v-mdsf-slip-left')?.textContent})"""
        )
        # the data's age is not latency: no new sample, none of the samples as old as the data
        assert len(got["lat"]) == n_lat, got["lat"][n_lat:]
        assert max(got["lat"]) < 1000, got["lat"]
        assert got["latText"] == "–" and got["latNote"], got
        # the old values stay, dimmed, with their age
        assert got["slip"] == "9.0"
        assert "is-old" in got["stats"].split()
        assert float(got["opacity"]) < 1
        assert got["ageVisible"]
        age_s = int(got["age"].removeprefix("last data ").removesuffix(" s ago"))
        assert math.isclose(age_s, silent_s, abs_tol=1.6), (got["age"], silent_s)
        page.screenshot(path=str(screenshots / "vehicle-stale.png"), full_page=True)
        # data again: live, values no longer dimmed, the age goes
        send(_OK)
        page.wait_for_function(
            "document.getElementById('v-status').textContent === 'live'", timeout=10000
        )
        assert page.get_attribute(".stats", "class") == "stats"
        assert page.is_hidden("#v-age")


_DEGRADED_TEXT = next(f.description for f in MDSF_SPEC.flags if f.name == "DEGRADED")


def test_degraded_quality_is_marked_with_the_specs_words(live_stack: LiveStack, page: Any) -> None:
    vid = "gnss-lost-1"
    with _own_vehicle(live_stack, vid) as send:
        send(_OK)
        page.goto(live_stack.base_url + f"/#/vehicle/{vid}")
        page.wait_for_function(
            "document.getElementById('v-mdsf-quality')?.textContent === 'ok'", timeout=15000
        )
        plain = page.evaluate(
            "() => { const s = getComputedStyle(document.getElementById('v-mdsf-quality'));"
            " return [s.color, s.fontWeight]; }"
        )
        for flags, label in (
            (int(F.DEGRADED | F.SLIP_LEFT_VALID | F.SLIP_RIGHT_VALID), "degraded"),
            (int(F.SLIP_LEFT_VALID | F.SLIP_RIGHT_VALID), "none"),
        ):
            send(flags)
            page.wait_for_function(
                "(l) => document.getElementById('v-mdsf-quality')?.textContent === l",
                arg=label,
                timeout=10000,
            )
            marked = page.evaluate(
                """() => { const e = document.getElementById('v-mdsf-quality');
                    const s = getComputedStyle(e);
                    return {cls: e.className, color: s.color, weight: s.fontWeight,
                            note: document.getElementById('v-mdsf-quality-note')?.textContent}; }"""
            )
            # the fleet table's rule: the same class, so the same colour and weight
            assert marked["cls"] == f"quality-{label}", marked
            assert marked["color"] == "rgb(179, 38, 30)" and marked["color"] != plain[0], marked
            assert int(marked["weight"]) >= 600, marked
            assert marked["note"], marked  # said in words too, not by colour alone
            if label == "degraded":  # the degraded flag's own description
                assert marked["note"] == _DEGRADED_TEXT, marked
        send(_OK)
        page.wait_for_function(
            "document.getElementById('v-mdsf-quality')?.textContent === 'ok'", timeout=10000
        )
        assert (
            page.evaluate("() => document.getElementById('v-mdsf-quality-note')?.textContent") == ""
        )
