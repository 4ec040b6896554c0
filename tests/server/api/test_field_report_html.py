"""``/vehicles/{id}/report?format=html``: one self-contained page (no script, nothing fetched)
with the report's figures, the slip map's cells coloured by slip, the track and the charts."""

from __future__ import annotations

import re

from server.analytics.field_report_html import slip_colour
from server.storage.base import Store

from ._data import T0, S
from .conftest import ApiClient
from .test_slipmap_api import ANCHOR, placed_series

Q = f"start={T0}&end={T0 + 10 * S}&format=html"


def _put(client: ApiClient, store: Store) -> None:
    assert client.put("/api/v1/vehicles/t1", json={}).status_code == 201
    store.write_estimates([("t1", placed_series())])
    store.put_anchors({"t1": ANCHOR}, T0)


def test_the_page_stands_alone_with_map_and_charts(client: ApiClient, store: Store) -> None:
    _put(client, store)
    r = client.get(f"/api/v1/vehicles/t1/report?{Q}")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    assert r.headers["content-disposition"].endswith('.html"')
    page = r.text
    assert page.startswith("<!DOCTYPE html>")
    for outside in ("<script", "src=", "href=", "url(", "@import", "http://", "https://"):
        assert outside not in page, outside
    # the hand map's three 10 m cells, mean |slip| 1, 20 and 5 %, coloured by it
    cells = re.findall(r'<rect [^>]*fill="(#[0-9a-f]{6})"><title>([^<]*)</title>', page)
    assert cells == [
        (slip_colour(1.0, (5.0, 15.0)), "1.0 %"),
        (slip_colour(20.0, (5.0, 15.0)), "20.0 %"),
        (slip_colour(5.0, (5.0, 15.0)), "5.0 %"),
    ]
    assert page.count('class="track"') == 1
    assert page.count('class="chart"') >= 2  # the spec's charts
    json_report = client.get(f"/api/v1/vehicles/t1/report?start={T0}&end={T0 + 10 * S}").json()
    left = json_report["report"]["slips"]["left"]
    assert f"mean {left['mean_pct']:.1f} %" in page
    top = left["bands"][-1]
    assert f"≥ 15 %: {100 * top['share']:.0f} %" in page
    assert f"{json_report['report']['distance_m']:.0f} m" in page


def test_colours_run_green_yellow_red() -> None:
    assert slip_colour(0.0, (5.0, 15.0)) == "#00c830"
    assert slip_colour(5.0, (5.0, 15.0)) == "#ffc830"
    assert slip_colour(15.0, (5.0, 15.0)) == slip_colour(40.0, (5.0, 15.0)) == "#ff0030"
    assert slip_colour(float("nan"), (5.0, 15.0)) == "#cccccc"


def test_a_vehicle_without_position_gets_a_page_without_map(
    client: ApiClient, store: Store
) -> None:
    assert client.put("/api/v1/vehicles/t2", json={}).status_code == 201
    rows = placed_series()
    rows["east_m"] = float("nan")
    rows["north_m"] = float("nan")
    store.write_estimates([("t2", rows)])
    page = client.get(f"/api/v1/vehicles/t2/report?{Q}").text
    assert "No position in the range: no map." in page
