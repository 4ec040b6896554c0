"""A mixed fleet in the dashboard: a vehicle running MDSF and the reference speed shows a panel per
estimator, drawn from each spec (titles, labels, units, flags); a vehicle whose only estimator is
the reference speed is listed in the fleet table by its own speed channel and quality.

Rows are pushed into the live hub of the real test stack at 20 Hz, stamped with the wall clock,
as the pipeline would (one batch per estimator per tick).
"""

from __future__ import annotations

import threading
import time
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import pytest

from estimator.mdsf_spec import MDSF_SPEC
from estimator.reference_speed_spec import REFERENCE_SPEED_SPEC, ReferenceFlag
from estimator.types import EstimateBatch, EstimateFlag, empty_estimates
from tests.web.conftest import LiveStack

pytestmark = pytest.mark.browser

MIXED = "mixed-1"  # MDSF (primary) + reference speed
REF_ONLY = "ref-only-1"  # the reference speed only
_MDSF_OK = int(EstimateFlag.GNSS_OK | EstimateFlag.SLIP_LEFT_VALID | EstimateFlag.SLIP_RIGHT_VALID)


class _Feed:
    """Rows of both estimators every 50 ms until stopped; ``no_wheel`` flags the reference rows
    as computed without rim speed (its degraded flag)."""

    def __init__(self, hub: Any) -> None:
        self.hub = hub
        self.no_wheel = False
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _ref_rows(self, stamp_ns: int, speed_mps: float) -> Any:
        r = REFERENCE_SPEED_SPEC.empty_rows(1)
        r["stamp_ns"] = stamp_ns
        r["speed_mps"] = speed_mps
        r["rim_mps"] = speed_mps + 0.1
        r["accel_bias_mps2"] = 0.02
        flag = ReferenceFlag.NO_WHEEL if self.no_wheel else ReferenceFlag.WHEEL_OK
        r["flags"] = int(flag)
        return r

    def tick(self) -> None:
        now = time.time_ns()
        m = empty_estimates(1)
        m["stamp_ns"] = now
        m["vg_mps"] = m["vl_mps"] = m["vr_mps"] = 2.0
        m["slip_left_pct"], m["slip_right_pct"] = 4.0, 9.0
        m["east_m"], m["north_m"], m["up_m"] = (now % 10**10) / 1e9, 0.0, 2.6
        m["flags"] = _MDSF_OK
        self.hub.on_estimates(EstimateBatch.of([(MIXED, m)], MDSF_SPEC))
        ref = [(MIXED, self._ref_rows(now, 1.5)), (REF_ONLY, self._ref_rows(now, 3.25))]
        self.hub.on_estimates(EstimateBatch.of(ref, REFERENCE_SPEED_SPEC))

    def _run(self) -> None:
        while not self.stop.wait(0.05):
            self.tick()


def _call(stack: LiveStack, method: str, vid: str) -> None:
    req = urllib.request.Request(
        f"{stack.base_url}/api/v1/vehicles/{vid}", data=b"{}" if method == "PUT" else None
    )
    req.method = method
    req.add_header("Content-Type", "application/json")
    with urllib.request.urlopen(req, timeout=10) as resp:
        assert resp.status in (200, 201, 204)


@contextmanager
def _feeding(stack: LiveStack) -> Iterator[_Feed]:
    """Both vehicles registered (as the pipeline would) and fed until the block ends."""
    hub = stack.runtime.live_hub
    for vid in (MIXED, REF_ONLY):
        _call(stack, "PUT", vid)
    feed = _Feed(hub)
    feed.tick()  # MDSF reaches the hub first: the vehicle's primary
    feed.thread.start()
    try:
        yield feed
    finally:
        feed.stop.set()
        feed.thread.join(timeout=5)
        for vid in (MIXED, REF_ONLY):
            hub.forget(vid)
            _call(stack, "DELETE", vid)


_CHART_JS = """(id) => { const u = document.getElementById(id)._uplot;
    return {title: document.getElementById(id).querySelector('.u-title').textContent,
            y: u.axes[1].label, labels: u.series.slice(1).map(s => s.label),
            points: u.data[0].length, shade: u._shade.length}; }"""


def test_a_vehicle_running_two_estimators_shows_a_panel_of_each(
    live_stack: LiveStack, page: Any
) -> None:
    with _feeding(live_stack) as feed:
        page.goto(live_stack.base_url + f"/#/vehicle/{MIXED}")
        page.wait_for_selector("[data-estimator=reference_speed] .u-title", timeout=15000)
        panels = page.eval_on_selector_all(
            "section.est-panel",
            "els => els.map(e => [e.dataset.estimator, e.querySelector('h2').textContent])",
        )
        assert panels == [
            ["mdsf", MDSF_SPEC.title + "primary"],
            ["reference_speed", REFERENCE_SPEED_SPEC.title],
        ]
        # the reference panel: its motion speed with its label and unit, its quality; no slips
        page.wait_for_function(
            "document.getElementById('v-reference_speed-speed')?.textContent === '1.50'",
            timeout=10000,
        )
        tile = page.evaluate(
            """() => { const v = document.getElementById('v-reference_speed-speed');
                const s = v.closest('.stat');
                return [s.querySelector('.stat-label').textContent,
                        s.querySelector('.unit').textContent.trim()]; }"""
        )
        assert tile == ["reference speed", "m/s"]
        assert page.inner_text("#v-reference_speed-quality") == "ok"
        assert page.inner_text("#v-reference_speed-flags") == "WHEEL_OK"
        assert page.locator("[data-estimator=reference_speed] [id*='-slip-']").count() == 0
        # its charts: one per ChartSpec, titles, units and series labels from the spec
        page.wait_for_function(
            "document.getElementById('chart-reference_speed-bias')?._uplot?.data[0].length > 5",
            timeout=10000,
        )
        speed = page.evaluate(_CHART_JS, "chart-reference_speed-speed")
        bias = page.evaluate(_CHART_JS, "chart-reference_speed-bias")
        assert (speed["title"], speed["y"]) == ("Reference speed", "reference speed (m/s)")
        assert speed["labels"] == ["reference speed", "mean rim speed"]
        assert (bias["title"], bias["y"]) == ("Accelerometer bias", "accelerometer bias (m/s²)")
        assert bias["labels"] == ["accelerometer bias"] and bias["shade"] == 0
        # and MDSF's beside it, slip tiles by channel label
        assert page.inner_text("#v-mdsf-slip-right") == "9.0"
        label = page.evaluate(
            "() => document.getElementById('v-mdsf-slip-left')?.closest('.stat')"
            ".querySelector('.stat-label').textContent"
        )
        assert label == "Slip rear left wheel"
        # the reference speed loses its rim speed: degraded, said with the flag's description,
        # and the stretch shaded in its charts
        feed.no_wheel = True
        page.wait_for_function(
            "document.getElementById('v-reference_speed-quality')?.textContent === 'degraded'",
            timeout=10000,
        )
        note = page.inner_text("#v-reference_speed-quality-note")
        assert note == next(
            f.description for f in REFERENCE_SPEED_SPEC.flags if f.name == "NO_WHEEL"
        )
        page.wait_for_function(
            "document.getElementById('chart-reference_speed-speed')?._uplot?._shade?.length > 0",
            timeout=10000,
        )
        assert page.inner_text("#v-mdsf-quality") == "ok"  # the other estimator is unaffected


def test_the_fleet_table_lists_each_vehicle_by_its_primary(
    live_stack: LiveStack, page: Any
) -> None:
    with _feeding(live_stack) as feed:
        feed.no_wheel = True
        page.goto(live_stack.base_url + "/#/fleet")
        page.fill("#fleet-filter", "-1")
        row_js = """(vid) => { const r = [...document.querySelectorAll('.vrows .vrow')]
            .find(r => !r.hidden && r.querySelector('.c-id a').textContent === vid);
            return r && {speed: r.querySelector('.c-speed_mps').textContent,
                         left: r.querySelector('.c-slip-left').textContent,
                         quality: r.querySelector('.c-quality').textContent,
                         title: r.querySelector('.c-quality').title}; }"""
        page.wait_for_function(f"({row_js})('{REF_ONLY}')?.speed === '3.25'", timeout=15000)
        ref = page.evaluate(row_js, REF_ONLY)
        mixed = page.evaluate(row_js, MIXED)
        assert ref == {
            "speed": "3.25",
            "left": "–",  # no slip channel
            "quality": "degraded",
            "title": REFERENCE_SPEED_SPEC.title,
        }
        assert mixed == {"speed": "2.00", "left": "4.0", "quality": "ok", "title": MDSF_SPEC.title}
