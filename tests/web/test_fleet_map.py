"""The fleet page's map in a real Chromium: every placed vehicle's last position and track
coloured by slip, on latitude/longitude axes through each vehicle's stored anchor; a click on a
vehicle opens its page; no request leaves the server unless a basemap is configured, and then
the basemap's tiles are fetched and drawn."""

from __future__ import annotations

import http.server
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any, ClassVar

import pytest

from tests.support import free_port
from tests.web.conftest import N_VEHICLES, LiveRuntime, LiveStack, checked_page, serve_live_stack

pytestmark = pytest.mark.browser

LAT0_DEG, LON0_DEG = 48.1, 11.5
SPACING_DEG = 0.002  # ≈ 220 m north between neighbouring vehicles' anchors
UNPLACED = "veh-011"  # no anchor stored: not drawn


class AnchoredRuntime(LiveRuntime):
    """The live stack with an anchor stored for every vehicle but :data:`UNPLACED`, vehicle
    ``k`` ``k`` spacings north of the first."""

    def open(self) -> None:
        super().open()
        anchors = {
            vid: (LAT0_DEG + k * SPACING_DEG, LON0_DEG, 500.0)
            for k, vid in enumerate(self.fleet.ids)
            if vid != UNPLACED
        }
        assert self.writer is not None
        self.writer.call(lambda store: store.put_anchors(anchors, time.time_ns()))


@pytest.fixture(scope="module")
def anchored(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveStack]:
    with serve_live_stack(
        tmp_path_factory.mktemp("store"), require_auth=False, runtime_class=AnchoredRuntime
    ) as stack:
        yield stack


_MAP_JS = """
() => {
  const c = document.getElementById('fleet-map');
  const m = c._geomap;
  const ctx = c.getContext('2d');
  const img = ctx.getImageData(0, 0, c.width, c.height).data;
  // saturated pixels above the legend: slip colours, not the grey and black of the axes
  let coloured = 0;
  const plotEnd = 4 * c.width * Math.floor(c.height - 72 * devicePixelRatio);
  for (let i = 0; i < plotEnd; i += 4) {
    const rgb = [img[i], img[i + 1], img[i + 2]];
    if (Math.max(...rgb) - Math.min(...rgb) > 80) coloured++;
  }
  const r = c.getBoundingClientRect();
  return {markers: m.markers, ticks: m.ticks, coloured, tiles: m.tilesDrawn,
          points: m.vehicles.map((v) => v.points.length),
          box: {left: r.left, top: r.top}};
}
"""


def _wait_placed(page: Any, n: int) -> list[dict[str, Any]]:
    """Wait for ``n`` vehicle markers on the map; their ids and positions (CSS px)."""
    page.wait_for_function(
        "(n) => document.getElementById('fleet-map')?._geomap?.markers.length === n",
        arg=n,
        timeout=20000,
    )
    markers: list[dict[str, Any]] = page.evaluate(
        "document.getElementById('fleet-map')._geomap.markers"
    )
    return markers


def test_the_map_places_every_anchored_vehicle_by_its_anchor(
    anchored: LiveStack, browser: Any, screenshots: Path
) -> None:
    with checked_page(browser, viewport={"width": 1400, "height": 900}) as page:
        outside: list[str] = []
        page.on(
            "request",
            lambda r: None if r.url.startswith(anchored.base_url) else outside.append(r.url),
        )
        page.goto(anchored.base_url + "/#/fleet")
        _wait_placed(page, N_VEHICLES - 1)
        got = page.evaluate(_MAP_JS)
        ids = [m["id"] for m in got["markers"]]
        assert sorted(ids) == sorted(v for v in anchored.runtime.fleet.ids if v != UNPLACED)
        # north is up: each anchor lies 220 m north of the previous one, so higher on the map
        ys = {m["id"]: m["y"] for m in got["markers"]}
        order = sorted(ys, key=lambda vid: -ys[vid])
        assert order == sorted(ys), f"markers bottom to top: {order}"
        # the axes are latitude and longitude around the anchors
        lat_ticks, lon_ticks = got["ticks"]["lat"], got["ticks"]["lon"]
        assert len(lat_ticks) >= 2 and len(lon_ticks) >= 2
        assert min(lat_ticks) > LAT0_DEG - 0.01 and max(lat_ticks) < LAT0_DEG + 0.035
        assert all(abs(v - LON0_DEG) < 0.06 for v in lon_ticks)
        assert min(lon_ticks) < LON0_DEG < max(lon_ticks)
        # markers and tracks drawn in slip colours above the legend (11 markers: ≈ 2,200 px);
        # each track holds the vehicle's stored rows of the last minutes, not one point
        page.locator("#fleet-map").scroll_into_view_if_needed()
        page.locator("#fleet-map").screenshot(path=str(screenshots / "fleet-map.png"))
        assert got["coloured"] > 1500, got["coloured"]
        assert min(got["points"]) >= 20, got["points"]
        assert page.inner_text("#fleet-map-note").startswith(f"{N_VEHICLES - 1} of {N_VEHICLES}")
        assert got["tiles"] == 0
        assert outside == [], f"requests beyond the server without a basemap: {outside}"


def test_a_click_on_a_vehicle_opens_its_page(anchored: LiveStack, browser: Any) -> None:
    with checked_page(browser, viewport={"width": 1400, "height": 900}) as page:
        page.goto(anchored.base_url + "/#/fleet")
        markers = _wait_placed(page, N_VEHICLES - 1)
        target = next(m for m in markers if m["id"] == "veh-004")
        page.locator("#fleet-map").scroll_into_view_if_needed()
        page.locator("#fleet-map").click(position={"x": target["x"], "y": target["y"]})
        page.wait_for_function("location.hash === '#/vehicle/veh-004'", timeout=5000)
        page.wait_for_selector("#v-status", timeout=5000)
        # a click away from every vehicle stays on the fleet page
        page.goto(anchored.base_url + "/#/fleet")
        _wait_placed(page, N_VEHICLES - 1)
        page.locator("#fleet-map").click(position={"x": 95, "y": 20})
        page.wait_for_timeout(300)
        assert page.evaluate("location.hash") == "#/fleet"


def test_vehicle_and_history_maps_have_latitude_longitude_axes(
    anchored: LiveStack, browser: Any
) -> None:
    """The track maps of the vehicle and history pages label their grid in degrees through the
    vehicle's anchor (metres east/north of the first fix before)."""
    k = 4
    vid = f"veh-{k:03d}"
    lat0 = LAT0_DEG + k * SPACING_DEG
    ticks_js = "(id) => document.getElementById(id)._slipmap.ticks"
    with checked_page(browser, viewport={"width": 1400, "height": 900}) as page:
        for route, canvas in (("", "live-map"), ("/history", "h-map")):
            page.goto(f"{anchored.base_url}/#/vehicle/{vid}{route}")
            page.wait_for_function(
                "(id) => document.getElementById(id)?._slipmap?.ticks.lat.length >= 2",
                arg=canvas,
                timeout=20000,
            )
            ticks = page.evaluate(ticks_js, canvas)
            # the figure of eight spans tens of metres: ticks within ~200 m of the anchor
            assert all(abs(v - lat0) < 0.002 for v in ticks["lat"]), (route, ticks)
            assert all(abs(v - LON0_DEG) < 0.004 for v in ticks["lon"]), (route, ticks)
            assert len(ticks["lon"]) >= 2, (route, ticks)


class _Tiles(http.server.BaseHTTPRequestHandler):
    """Every path is one 256 px PNG tile of a single colour; the paths asked are kept."""

    asked: ClassVar[list[str]] = []
    png = b""

    def do_GET(self) -> None:
        type(self).asked.append(self.path)
        self.send_response(200)
        self.send_header("Content-Type", "image/png")
        self.send_header("Content-Length", str(len(self.png)))
        self.end_headers()
        self.wfile.write(self.png)

    def log_message(self, *args: Any) -> None:
        pass


def _tile_png() -> bytes:
    import io

    from PIL import Image

    out = io.BytesIO()
    Image.new("RGB", (256, 256), (170, 210, 240)).save(out, "PNG")
    return out.getvalue()


@pytest.fixture(scope="module")
def tile_server() -> Iterator[str]:
    _Tiles.png = _tile_png()
    port = free_port()
    srv = http.server.ThreadingHTTPServer(("127.0.0.1", port), _Tiles)
    thread = threading.Thread(target=srv.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        srv.shutdown()
        srv.server_close()
        thread.join(timeout=5)


def test_a_configured_basemap_is_fetched_and_drawn(
    tmp_path: Path, browser: Any, tile_server: str, screenshots: Path
) -> None:
    template = tile_server + "/{z}/{x}/{y}.png"
    with (
        serve_live_stack(
            tmp_path, require_auth=False, runtime_class=AnchoredRuntime, map_tile_url=template
        ) as stack,
        checked_page(browser, viewport={"width": 1400, "height": 900}) as page,
    ):
        page.goto(stack.base_url + "/#/fleet")
        _wait_placed(page, N_VEHICLES - 1)
        page.wait_for_function(
            "document.getElementById('fleet-map')._geomap.tilesDrawn > 0", timeout=10000
        )
        # the tiles asked cover the anchors: the column of (LAT0, LON0) at the zoom asked
        z = int(_Tiles.asked[0].strip("/").split("/")[0])
        assert 14 <= z <= 19, _Tiles.asked
        n = 2**z
        x0 = int((LON0_DEG + 180) / 360 * n)
        xs = {int(p.strip("/").split("/")[1]) for p in _Tiles.asked}
        assert x0 in xs or x0 - 1 in xs or x0 + 1 in xs, (x0, sorted(xs))
        page.locator("#fleet-map").scroll_into_view_if_needed()
        page.locator("#fleet-map").screenshot(path=str(screenshots / "fleet-map-basemap.png"))
        # the history page's map draws the same basemap under the track
        page.goto(stack.base_url + "/#/vehicle/veh-002/history")
        page.wait_for_function(
            "document.getElementById('h-map')?._slipmap?.tilesDrawn > 0", timeout=20000
        )
        page.locator("#h-map").screenshot(path=str(screenshots / "history-map-basemap.png"))
