"""The history page (``#/vehicle/<id>/history``) against the REST endpoints it draws from.

A vehicle of its own holds one short drive (10 min at 10 Hz, a lawnmower pattern with a gap, a
standstill and one wheel's slip sometimes invalid) that ended a minute ago. Asked for the last
12 h, the page must show the drive's detail (buckets sized on the stored rows, not on the 12 h),
draw the track through stored positions only, take its heat grid from the REST slip map, and show
and accept its times as 24-hour UTC.
"""

from __future__ import annotations

import json
import math
import re
import time
import urllib.parse
import urllib.request
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from estimator.config import WheeledRearDriveConfig
from estimator.types import EstimateFlag as F
from estimator.types import empty_estimates
from tests.web.conftest import LiveStack, history_loaded

pytestmark = pytest.mark.browser

VID = "burst-1"
N_ROWS = 6000  # 10 min at 10 Hz: more than the charts' 4,000 points, fewer than the track's
CHART_POINTS = 4000
S = 1_000_000_000
TWELVE_H_NS = 12 * 3600 * S
UTC_24H = re.compile(r"^\d{4}-\d{2}-\d{2} \d{2}:\d{2}:\d{2}$")


def _drive(end_ns: int) -> np.ndarray:
    """A field drive ending at ``end_ns``: passes of 150 m north and south, 6 m apart, at
    2.5 m/s (turns included), a 20 s standstill, a 3 s hole in the data, the right wheel's slip
    marked invalid on every 7th row (its value left finite: only the flag says so; the REST
    slip map leaves it out, a plain mean of the values would not)."""
    rows = empty_estimates(N_ROWS)
    rows["stamp_ns"] = end_ns - (N_ROWS - 1 - np.arange(N_ROWS, dtype=np.int64)) * (S // 10)
    rows = np.delete(rows, np.s_[3000:3030])  # 3 s without rows
    n = rows.shape[0]
    t = (rows["stamp_ns"] - rows["stamp_ns"][0]) / 1e9
    d = 2.5 * t  # metres driven
    lane, along = np.divmod(d, 160.0)  # 150 m pass + 10 m turn
    north = np.where(lane % 2 == 0, np.minimum(along, 150.0), 150.0 - np.minimum(along, 150.0))
    east = 6.0 * lane + np.clip(along - 150.0, 0.0, 10.0) * 0.6
    stand = (t > 200.0) & (t < 220.0)
    rows["east_m"] = east + 0.3 * np.sin(t * 0.7)
    rows["north_m"] = north
    rows["up_m"] = 0.1
    rows["vg_mps"] = np.where(stand, 0.0, 2.5)
    rows["vl_mps"] = rows["vg_mps"] * 0.98
    rows["vr_mps"] = rows["vg_mps"] * 1.02
    rows["slip_left_pct"] = 6.0 + 9.0 * np.sin(t * 0.11) + 4.0 * np.sin(north * 0.2)
    rows["slip_right_pct"] = 5.0 + 8.0 * np.cos(t * 0.07) - 3.0 * np.sin(east * 0.9)
    flags = np.full(n, int(F.GNSS_OK | F.SLIP_LEFT_VALID | F.SLIP_RIGHT_VALID), dtype=np.int64)
    flags[::7] &= ~int(F.SLIP_RIGHT_VALID)
    rows["slip_right_pct"][::7] += 4.0
    flags[stand] = int(F.GNSS_OK | F.STANDSTILL)
    rows["slip_left_pct"][stand] = np.nan
    rows["slip_right_pct"][stand] = np.nan
    rows["flags"] = flags
    return rows


@pytest.fixture(scope="module")
def drive(live_stack: LiveStack) -> np.ndarray:
    store = live_stack.runtime.store
    store.upsert_vehicle(VID, WheeledRearDriveConfig().to_dict(), time.time_ns())
    rows = _drive(time.time_ns() - 60 * S)
    store.write_estimates([(VID, rows)])
    return rows


def _get(base: str, path: str, **params: Any) -> Any:
    url = f"{base}{path}?{urllib.parse.urlencode(params)}"
    with urllib.request.urlopen(url, timeout=60) as resp:
        return json.loads(resp.read())


def _parse_utc(text: str) -> int:
    """An input's time (the 24-hour form asked for; "T" as the old datetime-local inputs had)."""
    t = datetime.strptime(text.replace("T", " "), "%Y-%m-%d %H:%M:%S").replace(tzinfo=UTC)
    return int(t.timestamp()) * S


def _open_last_12h(page: Any, base: str) -> tuple[int, int]:
    """The history page of VID loaded over "last 12 h"; returns the range of its inputs."""
    page.goto(f"{base}/#/vehicle/{VID}/history")
    history_loaded(page)
    page.select_option("#h-preset", "43200")
    with page.expect_response(lambda r: "/series?" in r.url and "max_points=4000" in r.url):
        page.click("#h-load")
    history_loaded(page)
    return _parse_utc(page.input_value("#h-start")), _parse_utc(page.input_value("#h-end"))


def test_a_long_range_keeps_the_detail_of_a_short_drive(
    live_stack: LiveStack, drive: np.ndarray, page: Any, screenshots: Path
) -> None:
    base = live_stack.base_url
    s, e = _open_last_12h(page, base)
    shown = int(page.inner_text("#h-msg").split()[0])
    assert shown > 3500  # buckets on the 12 h gave 56 points: a zig-zag between extremes
    assert e - s == TWELVE_H_NS
    assert s <= int(drive["stamp_ns"][0]) and int(drive["stamp_ns"][-1]) < e
    # what the series endpoint gives for the stored rows: their detail, not 12 h / 2,000 buckets
    body = _get(
        base,
        f"/api/v1/vehicles/{VID}/series",
        start=s,
        end=e,
        max_points=CHART_POINTS,
        fields="slip_left_pct,slip_right_pct",
    )
    assert body["stored_rows"] == drive.shape[0]
    assert shown == body["rows"]
    drawn = page.evaluate("() => document.getElementById('h-chart-slip')._uplot.data[0].length")
    assert drawn == shown
    # and says what it shows: points of stored rows, bucket width, whole rows on the map
    detail = page.inner_text("#h-detail")
    assert f"of {drive.shape[0]} stored rows" in detail
    assert f"all {drive.shape[0]} rows" in detail  # the map and replay: every stored row
    span_s = (int(drive["stamp_ns"][-1]) - int(drive["stamp_ns"][0])) / 1e9
    bucket_s = body["bucket_ns"] / 1e9
    assert bucket_s == pytest.approx(span_s / (CHART_POINTS // 2), rel=1e-3)
    assert f"{bucket_s:.3f} s" in detail
    assert "of the 12 h range" in detail
    page.screenshot(path=str(screenshots / "history-12h-short-drive.png"))


def test_the_track_goes_through_stored_positions(
    live_stack: LiveStack, drive: np.ndarray, page: Any
) -> None:
    base = live_stack.base_url
    s, e = _open_last_12h(page, base)
    full = _get(
        base,
        f"/api/v1/vehicles/{VID}/series",
        start=s,
        end=e,
        fields="east_m,north_m,slip_left_pct,slip_right_pct,vg_mps",
    )["columns"]
    stored = set(zip(full["east_m"], full["north_m"], strict=True))
    track = page.evaluate(
        "() => { const m = document.getElementById('h-map')._slipmap; return [m.east, m.north]; }"
    )
    points = list(zip(*track, strict=True))
    phantom = [p for p in points if p not in stored]
    assert phantom == [], "track points that are no stored position"
    assert len(points) == len(full["stamp_ns"])  # fewer stored rows than the track's budget
    # the replay position and the values shown there are one stored row
    page.eval_on_selector(
        "#h-scrub",
        "(e) => { e.value = String(Math.floor(Number(e.max) / 3));"
        " e.dispatchEvent(new Event('input')); }",
    )
    i = int(page.input_value("#h-scrub"))
    at = page.inner_text("#h-at")
    stamp_ms = int(
        datetime.strptime(at, "%Y-%m-%d %H:%M:%S.%f UTC").replace(tzinfo=UTC).timestamp() * 1000
    )
    j = int(np.argmin(np.abs(np.asarray(full["stamp_ns"]) / 1e6 - stamp_ms)))
    assert abs(full["stamp_ns"][j] / 1e6 - stamp_ms) < 1
    assert points[i] == (full["east_m"][j], full["north_m"][j])
    assert page.inner_text("#h-slip-left") == f"{full['slip_left_pct'][j]:.1f}"
    assert page.inner_text("#h-motion") == f"{full['vg_mps'][j]:.2f}"


def test_the_heat_grid_is_the_rest_slip_map(
    live_stack: LiveStack, drive: np.ndarray, page: Any, screenshots: Path
) -> None:
    base = live_stack.base_url
    s, e = _open_last_12h(page, base)
    page.check("#h-heat")
    page.wait_for_function(
        "() => { const m = document.getElementById('h-map')._slipmap;"
        " return m && m.heat && m.heat.length > 0; }",
    )
    cell_m, heat = page.evaluate(
        "() => { const m = document.getElementById('h-map')._slipmap;"
        " return [m.heatCell, m.heat.map((h) => [h.e0, h.n0, h.mean])]; }"
    )
    rest = _get(base, f"/api/v1/vehicles/{VID}/slipmap", start=s, end=e, cell_m=cell_m)
    want = {(c["east_m"], c["north_m"]): c["mean_abs_slip_pct"] for c in rest["cells"]}
    got = {(e0, n0): mean for e0, n0, mean in heat}
    assert got == want
    assert len(got) == len(heat) == rest["count"] > 50
    # auto cell size: sensible for the extent (150 m by ~60 m: 5 m, about 30 cells across)
    extent = max(np.ptp(drive["east_m"]), np.ptp(drive["north_m"]))
    assert extent / cell_m <= 60 and extent / cell_m >= 10
    assert page.inner_text("#h-cell option[value='auto']") == f"auto ({cell_m:g} m)"
    # a chosen cell size gives the REST map of that size
    page.select_option("#h-cell", "10")
    page.wait_for_function("() => document.getElementById('h-map')._slipmap.heatCell === 10")
    page.wait_for_function(
        "() => document.getElementById('h-heat-msg').textContent.endsWith('cells')"
    )
    rest10 = _get(base, f"/api/v1/vehicles/{VID}/slipmap", start=s, end=e, cell_m=10)
    heat10 = page.evaluate(
        "() => document.getElementById('h-map')._slipmap.heat.map((h) => [h.e0, h.n0, h.mean])"
    )
    assert {(a, b): m for a, b, m in heat10} == {
        (c["east_m"], c["north_m"]): c["mean_abs_slip_pct"] for c in rest10["cells"]
    }
    assert any(m is not None and not math.isnan(m) for _, _, m in heat10)
    page.select_option("#h-cell", "auto")
    page.wait_for_function(f"() => document.getElementById('h-map')._slipmap.heatCell === {cell_m}")
    page.screenshot(path=str(screenshots / "history-heat-grid.png"))


def test_range_inputs_are_24_hour_utc_and_a_typed_range_is_custom(
    live_stack: LiveStack, drive: np.ndarray, page: Any, screenshots: Path
) -> None:
    base = live_stack.base_url
    s, e = _open_last_12h(page, base)
    assert e - s == TWELVE_H_NS
    for sel in ("#h-start", "#h-end"):
        assert page.get_attribute(sel, "type") == "text"  # shown as typed, no locale clock
        assert UTC_24H.match(page.input_value(sel)), page.input_value(sel)
    assert page.input_value("#h-preset") == "43200"
    # the end covers the newest row (rounded up to the second)
    assert int(drive["stamp_ns"][-1]) < e <= int(drive["stamp_ns"][-1]) + 2 * S
    # a typed range is loaded as typed, and the Range select says "custom"
    first = int(drive["stamp_ns"][0]) // S * S
    typed_start = datetime.fromtimestamp(first // S + 60, UTC).strftime("%Y-%m-%d %H:%M:%S")
    typed_end = datetime.fromtimestamp(first // S + 180, UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
    page.fill("#h-start", typed_start)
    page.fill("#h-end", typed_end)
    with page.expect_request(lambda r: "/series?" in r.url and "max_points=4000" in r.url) as req:
        page.click("#h-load")
    query = urllib.parse.parse_qs(urllib.parse.urlparse(req.value.url).query)
    assert int(query["start"][0]) == (first // S + 60) * S
    assert int(query["end"][0]) == (first // S + 180) * S
    history_loaded(page)
    assert page.input_value("#h-preset") == "custom"
    assert page.inner_text("#h-preset option:checked") == "custom"
    assert "2 min of the 2 min range" in page.inner_text("#h-detail")
    # a preset again: the inputs follow it, shown in 24-hour UTC
    page.select_option("#h-preset", "1800")
    assert _parse_utc(page.input_value("#h-end")) - _parse_utc(page.input_value("#h-start")) == (
        1800 * S
    )
    # an impossible time is refused, not loaded
    page.fill("#h-start", "2026-02-30 10:00:00")
    page.click("#h-load")
    assert page.get_attribute("#h-start", "aria-invalid") == "true"
    assert "YYYY-MM-DD HH:MM:SS" in page.inner_text("#h-msg")
    page.fill("#h-start", typed_start)
    page.screenshot(path=str(screenshots / "history-custom-range.png"))
