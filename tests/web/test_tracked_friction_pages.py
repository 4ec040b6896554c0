"""A crawler's and a steered four-wheel vehicle's live pages, drawn from their specs.

The crawler (``tracked``): its motion state as a tile and as a band of coloured stretches under
its charts (the spec's state channel), its track slip charts, and its track on the map with the
dead-reckoned stretches dashed and the position's 1-σ as circles. The steered vehicle
(``friction``): μ as a tile said "held" while the data do not inform it, its chart shaded over
those stretches, and a tile per wheel of the grip in use in the grip colour.

Rows come from :mod:`tests.web.crawler_feed`, pushed into the real test stack's live hub.
"""

from __future__ import annotations

import itertools
import json
import math
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from estimator.friction_spec import FRICTION_SPEC
from estimator.tracked_spec import TRACKED_SPEC
from tests.web.conftest import LiveStack, history_loaded
from tests.web.crawler_feed import (
    CRAWLER,
    FIX_STD_M,
    GNSS_CLOCK_S,
    GRIP_PCT,
    GYRO_ARW_DEG_RT_H,
    PITCH_RAD,
    STEERED,
    CrawlerFeed,
    crawler_sigma_m,
)

pytestmark = pytest.mark.browser


def _put(stack: LiveStack, vid: str, body: dict[str, Any] | None) -> None:
    req = urllib.request.Request(
        f"{stack.base_url}/api/v1/vehicles/{vid}",
        data=None if body is None else json.dumps(body).encode(),
        method="DELETE" if body is None else "PUT",
        headers={"Content-Type": "application/json"},
    )
    with urllib.request.urlopen(req, timeout=60) as resp:
        assert resp.status in (200, 201, 204)


@pytest.fixture(scope="module")
def feed(live_stack: LiveStack) -> Iterator[CrawlerFeed]:
    hub = live_stack.runtime.live_hub
    _put(live_stack, CRAWLER, {"kind": "tracked"})
    _put(live_stack, STEERED, {"kind": "wheeled_4wd_steered"})
    f = CrawlerFeed([hub, live_stack.runtime.writer])
    f.backfill(30.0)
    assert live_stack.runtime.writer is not None and live_stack.runtime.writer.flush(timeout=120)
    f.start()
    try:
        yield f
    finally:
        f.stop()
        for vid in (CRAWLER, STEERED):
            hub.forget(vid)
            _put(live_stack, vid, None)


_BAND_JS = """(id) => { const b = document.getElementById(id)._band;
    return {spans: b.spans, legend: [...document.getElementById(id)
        .querySelectorAll('.state-legend li')].map(li => li.dataset.state)}; }"""


def test_the_crawler_page_draws_its_state_band_from_the_spec(
    live_stack: LiveStack, feed: CrawlerFeed, page: Any
) -> None:
    page.goto(live_stack.base_url + f"/#/vehicle/{CRAWLER}")
    band_id = "band-tracked-motion"
    page.wait_for_function(f"document.getElementById('{band_id}')?._band?.spans.length > 5")
    channel = TRACKED_SPEC.states[0]
    band = page.evaluate(_BAND_JS, band_id)
    assert band["legend"] == [s.name for s in channel.states] + ["uncertain"]
    spans = band["spans"]
    # every stretch is one of the spec's states, the feed's: two seconds long (but the ends), to
    # a live bucket (the window keeps a bucket's newest row, 0.1 to 0.5 s); a stall of the feed
    # (a gap over 1 s) cuts a stretch short rather than stretching a state over it
    assert {v for _, _, v, _ in spans} <= {s.value for s in channel.states}
    assert len({v for _, _, v, _ in spans}) >= 5
    inner = sorted(t1 - t0 for t0, t1, _, _ in spans[1:-1])
    assert inner and all(d <= 2.55 for d in inner), f"{inner} {spans}"
    assert inner[len(inner) // 2] == pytest.approx(2.0, abs=0.11)
    assert all(b[0] >= a[1] for a, b in itertools.pairwise(spans))
    # an uncertain state (every third) is its own stretch, flagged
    assert any(unsure for *_, unsure in spans)
    # the state tile: the newest row's state in words, its confidence
    tile = page.inner_text("#v-tracked-state-motion")
    assert tile in {s.label for s in channel.states}
    assert "confidence 90 %" in page.inner_text("#v-tracked-state-motion-note")
    # the band lies under the charts, the track slip chart labelled per track
    order = page.evaluate(
        "() => [...document.querySelector('[data-estimator=tracked] .est-charts').children]"
        ".map(e => e.id)"
    )
    assert order[-1] == band_id and "chart-tracked-slip" in order
    labels = page.evaluate(
        "() => document.getElementById('chart-tracked-slip')._uplot.series.slice(1)"
        ".map(s => s.label)"
    )
    assert labels == ["left track slip", "right track slip"]


def test_the_crawler_page_charts_its_pitch_and_roll_from_the_spec(
    live_stack: LiveStack, feed: CrawlerFeed, page: Any
) -> None:
    """The tracked spec's attitude chart: pitch and roll, in radians with the unit on its axis,
    the feed's values (a steady grade across a side slope rolling ±0.1 rad)."""
    page.goto(live_stack.base_url + f"/#/vehicle/{CRAWLER}")
    chart = "document.getElementById('chart-tracked-attitude')?._uplot"
    page.wait_for_function(f"{chart}?.data[0].length > 20")
    got = page.evaluate(
        f"""() => {{ const u = {chart};
        const finite = (i) => u.data[i].filter(Number.isFinite);
        return {{labels: u.series.slice(1).map(s => s.label), axis: u.axes[1].label,
                 pitch: finite(1), roll: finite(2)}};
        }}"""
    )
    assert got["labels"] == ["pitch", "roll"]
    assert got["axis"] == "pitch and roll (rad)"
    assert len(got["pitch"]) > 20 and all(p == pytest.approx(PITCH_RAD) for p in got["pitch"])
    assert all(abs(r) <= 0.1 + 1e-9 for r in got["roll"]) and max(got["roll"]) > min(got["roll"])


def test_the_crawler_map_dashes_dead_reckoning_and_draws_its_uncertainty(
    live_stack: LiveStack, feed: CrawlerFeed, page: Any, screenshots: Path
) -> None:
    page.goto(live_stack.base_url + f"/#/vehicle/{CRAWLER}")
    page.wait_for_function("document.getElementById('live-map')?._slipmap?.drawn > 100")
    m = page.evaluate(
        """() => { const m = document.getElementById('live-map')._slipmap;
            return {drawn: m.drawn, carried: m.carriedDrawn, circles: m.sigmaDrawn,
                    flags: m.carried.filter(Boolean).length, n: m.carried.length}; }"""
    )
    # about half the window is dead-reckoned: dashed, the rest solid
    assert 0.3 < m["carried"] / m["drawn"] < 0.7, m
    assert 0 < len(m["circles"]) <= 40
    radii = [r for _, _, r in m["circles"]]
    # radial 1-σ = sqrt(σe² + σn²): √2 · 0.3 m with GNSS, up to √2 · 2.3 m dead-reckoned
    fix = math.sqrt(2) * FIX_STD_M
    assert min(radii) == pytest.approx(fix, rel=1e-3)
    assert fix * 2 < max(radii) <= math.sqrt(2) * crawler_sigma_m(8 * 10**9 - 1) * 1.001
    # the odometer factor's cells over the window, from the stored rows
    assert page.eval_on_selector_all("#live-layer option", "os => os.map(o => o.value)") == [
        "",
        "odometer_factor",
    ]
    page.select_option("#live-layer", "odometer_factor")
    page.wait_for_function(
        "document.getElementById('live-layer-msg').textContent.includes('informed samples')"
    )
    cells = page.evaluate("() => document.getElementById('live-map')._slipmap.heat")
    means = [c["mean"] for c in cells if c["samples"]]
    assert means and all(0.909 < v < 0.991 for v in means)
    page.screenshot(path=str(screenshots / "crawler-live.png"), full_page=True)
    page.select_option("#live-layer", "")
    page.wait_for_function("document.getElementById('live-map')._slipmap.heat === null")


_MU_TILE_JS = """(informed) => { const e = document.getElementById('v-friction-value-mu');
    return e?.dataset.informed === informed
        && [e.textContent, document.getElementById('v-friction-value-mu-note').textContent]; }"""


def _mu_tile_once(page: Any, *, informed: bool) -> list[str]:
    """The μ tile's value and note, both read the moment the tile says ``informed`` (the feed
    turns every ``MU_S`` seconds: read one after the other, they could be of two rows)."""
    return list(page.wait_for_function(_MU_TILE_JS, arg=str(informed).lower()).json_value())


def test_the_steered_page_shows_mu_held_and_the_grip_per_wheel(
    live_stack: LiveStack, feed: CrawlerFeed, page: Any, screenshots: Path
) -> None:
    page.goto(live_stack.base_url + f"/#/vehicle/{STEERED}")
    assert _mu_tile_once(page, informed=False) == ["0.800", "held: not informed now, ± 0.150 (1σ)"]
    assert _mu_tile_once(page, informed=True) == ["0.800", "± 0.020 (1σ)"]
    assert (
        page.evaluate(
            "() => document.getElementById('v-friction-value-mu').closest('.stat')"
            ".querySelector('.stat-label').textContent"
        )
        == FRICTION_SPEC.values[0].label
    )
    # the μ chart: the held stretches shaded
    page.wait_for_function(
        "document.getElementById('chart-friction-mu')?._uplot?._shade.some(s => s[2] === "
        "'degraded')"
    )
    # the grip tiles: each wheel's share, bordered in its grip colour (0 green … 100 red)
    grip = page.evaluate(
        """() => Object.fromEntries(['fl', 'fr', 'rl', 'rr'].map(k => {
            const e = document.getElementById('v-friction-wheel-' + k);
            return [k, [e.textContent, getComputedStyle(e).borderTopColor]]; }))"""
    )
    assert {k: v[0] for k, v in grip.items()} == {k: f"{v:.0f}" for k, v in GRIP_PCT.items()}
    assert grip["fl"][1] == "rgb(112, 171, 64)"  # 20 %: 2/5 of the way green → yellow
    assert grip["rr"][1] == "rgb(163, 36, 30)"  # 95 %: 3/4 of the way orange → dark red
    # its slip tiles say "slip" once; its map offers the μ layer (the spec maps it)
    assert (
        page.evaluate(
            "() => document.getElementById('v-friction-slip-fl').closest('.stat')"
            ".querySelector('.stat-label').textContent"
        )
        == "slip front left"
    )
    assert "No map" not in page.inner_text("#live-map-title")
    assert page.locator("#live-map").is_visible()
    mu = next(v.key for v in FRICTION_SPEC.values if v.mapped)
    assert page.eval_on_selector_all("#live-layer option", "os => os.map(o => o.value)") == [
        "",
        mu,
    ]
    page.screenshot(path=str(screenshots / "steered-live.png"), full_page=True)


def test_the_crawler_history_map_draws_its_odometer_factor_layer(
    live_stack: LiveStack, feed: CrawlerFeed, page: Any, screenshots: Path
) -> None:
    page.goto(live_stack.base_url + f"/#/vehicle/{CRAWLER}/history")
    history_loaded(page)
    # the stored rows too: the state band under the charts, the dead-reckoned stretches dashed
    page.wait_for_function("document.getElementById('h-band-motion')?._band?.spans.length > 5")
    m = page.evaluate(
        "() => { const m = document.getElementById('h-map')._slipmap;"
        " return [m.drawn, m.carriedDrawn, m.sigmaDrawn.length]; }"
    )
    assert 0.3 < m[1] / m[0] < 0.7 and m[2] > 0, m
    layers = page.eval_on_selector_all("#h-layer option", "os => os.map(o => [o.value, o.text])")
    assert layers == [["", "mean |slip|"], ["odometer_factor", "mean odometer factor (gnss_ok)"]]
    page.select_option("#h-layer", "odometer_factor")
    page.check("#h-heat")
    page.wait_for_function(
        "document.getElementById('h-heat-msg').textContent.includes('informed samples')"
    )
    heat = page.evaluate(
        """() => { const m = document.getElementById('h-map')._slipmap;
            return {title: m.title,
                    cells: m.heat.map(h => [h.mean, h.samples, m.heatColor(h.mean)])}; }"""
    )
    assert heat["title"].endswith("cells by time-weighted mean odometer factor")
    means = [mean for mean, samples, _ in heat["cells"] if samples]
    # the feed's factor, 0.95 ± 0.04, informed only while GNSS is (no mean without a sample)
    assert len(means) >= 3 and all(0.909 < v < 0.991 for v in means)
    assert all(mean is None for mean, samples, _ in heat["cells"] if not samples)
    lo, hi = min(means), max(means)
    colours = {mean: colour for mean, _, colour in heat["cells"]}
    assert colours[lo] == "rgb(140,20,30)" and colours[hi] == "rgb(26,152,80)"
    assert f"{lo:.3f} (red) … {hi:.3f} (green)" in page.inner_text("#h-heat-msg")
    page.screenshot(path=str(screenshots / "crawler-history-layer.png"), full_page=True)


def test_the_crawler_page_shows_its_gyro_calibration_through_the_generic_panel(
    live_stack: LiveStack, feed: CrawlerFeed, page: Any
) -> None:
    """The online calibration panel, MDSF's, shows the crawler's gyro noise and receiver clock
    from the tracked spec: their values and σ (°/√h; the clock in ms), converged, no
    uncalibrated flag claimed, and the reset."""
    page.goto(live_stack.base_url + f"/#/vehicle/{CRAWLER}")
    row = "#v-calibration tr[data-calibration='gyro_arw']"
    page.wait_for_selector(f"{row}[data-state=converged]", timeout=30_000)
    value, std = GYRO_ARW_DEG_RT_H
    assert page.inner_text(f"{row} .cal-value") == f"{value:.3f} °/√h"
    assert page.inner_text(f"{row} .cal-std") == f"± {std:.3f} °/√h"
    assert "angle random walk" in page.inner_text(f"{row} th")
    clock = "#v-calibration tr[data-calibration='gnss_clock_offset']"
    page.wait_for_selector(f"{clock}[data-state=converged]", timeout=30_000)
    value_s, std_s = GNSS_CLOCK_S
    assert page.inner_text(f"{clock} .cal-value") == f"{value_s * 1e3:.1f} ms"
    assert page.inner_text(f"{clock} .cal-std") == f"± {std_s * 1e3:.1f} ms"
    assert "GNSS clock offset" in page.inner_text(f"{clock} th")
    part = "#v-calibration .cal-part[data-estimator=tracked]"
    state = page.inner_text(f"{part} .cal-state")
    assert state.startswith("As of ") and "not flagged" in state, state
    assert page.get_attribute(f"{part} .cal-state", "data-uncalibrated") == "null"
    assert page.is_visible(f"{part} button.cal-reset")
