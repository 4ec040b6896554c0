"""The map's marker follows the charts' cursor, on the live vehicle page and on the history
page: hovering a chart at a moment puts the marker on the track point of that moment; leaving
the chart puts it back (newest point live, the replay position in the history). Real Chromium
against the live stack."""

from __future__ import annotations

from typing import Any

import pytest

from tests.web.conftest import LiveStack, history_loaded

pytestmark = pytest.mark.browser

VEHICLE = "veh-001"

# The chart's cursor (data index and time, s) and the map's marker (index and its point's time).
_STATE_JS = """
([chartId, mapId]) => {
  const u = document.getElementById(chartId)._uplot;
  const m = document.getElementById(mapId)._slipmap;
  const i = u.cursor.idx;
  return {idx: i, t: i == null ? null : u.data[0][i], cursor: m.cursor,
          mt: m.cursor == null ? null : m.stampsS[m.cursor], n: m.stampsS.length,
          first: m.stampsS[0], last: m.stampsS[m.stampsS.length - 1]};
}
"""


def _hover(page: Any, chart_id: str, frac: float) -> None:
    over = page.locator(f"#{chart_id} .u-over")
    box = over.bounding_box()
    page.mouse.move(box["x"] + frac * box["width"], box["y"] + box["height"] / 2)
    page.wait_for_timeout(150)


def test_the_live_map_marker_follows_the_chart_cursor(live_stack: LiveStack, page: Any) -> None:
    chart, canvas = "chart-mdsf-slip", "live-map"
    page.goto(f"{live_stack.base_url}/#/vehicle/{VEHICLE}")
    page.wait_for_function(
        "document.getElementById('live-map')?._slipmap?.stampsS?.length > 100", timeout=20000
    )
    page.locator(f"#{chart}").scroll_into_view_if_needed()
    times = []
    for frac in (0.25, 0.75):
        _hover(page, chart, frac)
        got = page.evaluate(_STATE_JS, [chart, canvas])
        assert got["idx"] is not None and got["cursor"] is not None, got
        # the marker's point is the chart's moment (the window moves on at 20 Hz meanwhile)
        assert abs(got["mt"] - got["t"]) < 0.2, got
        assert got["mt"] < got["last"] - 1.0, got  # not the newest point
        times.append(got["mt"])
    assert times[1] - times[0] > 10.0, times  # half the 60 s window apart
    page.mouse.move(5, 5)  # off the chart: the marker goes back to the newest point
    page.wait_for_timeout(200)
    assert page.evaluate(_STATE_JS, [chart, canvas])["cursor"] is None


def test_the_history_map_marker_follows_the_chart_cursor(live_stack: LiveStack, page: Any) -> None:
    chart, canvas = "h-chart-slip", "h-map"
    page.goto(f"{live_stack.base_url}/#/vehicle/{VEHICLE}/history")
    history_loaded(page)
    page.locator(f"#{chart}").scroll_into_view_if_needed()
    replay = page.evaluate(_STATE_JS, [chart, canvas])["cursor"]
    assert replay == page.evaluate(_STATE_JS, [chart, canvas])["n"] - 1  # the newest, loaded
    seen = []
    for frac in (0.2, 0.6):
        _hover(page, chart, frac)
        got = page.evaluate(_STATE_JS, [chart, canvas])
        # the marker sits on the last whole row at or before the chart's moment
        assert got["mt"] <= got["t"] + 1e-6, got
        assert got["t"] - got["mt"] < 1.0, got
        seen.append(got["cursor"])
    assert seen[0] < seen[1] < replay, seen
    page.mouse.move(5, 5)
    page.wait_for_timeout(200)
    assert page.evaluate(_STATE_JS, [chart, canvas])["cursor"] == replay
