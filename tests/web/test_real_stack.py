"""The dashboard on the whole server: simulated vehicles publish over Zenoh on loopback → embedded
router → pipeline (MDSF; the last vehicle also the reference speed) → LiveHub / store → WebSocket
and REST → headless Chromium.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from estimator.catalog import spec_of
from estimator.spec import EstimatorSpec
from server.live.hub import LiveHub
from server.tooling.estimator_mix import EstimatorMix
from server.tooling.fleet_sim import FleetSim
from tests.server.fleet_stack import stack_settings, streaming_fleet
from tests.support import poll_until
from tests.web.test_dashboard import _COLOURED_PIXELS_JS, JS_NS_RESOLUTION, _page_latest
from tests.web.test_estimator_panels import _CHART_JS

pytestmark = [pytest.mark.browser, pytest.mark.zenoh, pytest.mark.slow]

N_VEHICLES = 3
#: The last vehicle (sim-0003) runs the reference speed beside MDSF; the others MDSF only.
MIXED_ESTIMATORS = ("mdsf", "reference_speed")


@pytest.fixture(scope="module")
def real_stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, LiveHub, FleetSim]]:
    settings = stack_settings(tmp_path_factory.mktemp("data"), None, 0)
    with streaming_fleet(
        settings,
        N_VEHICLES,
        scenario="figure_eight",
        seed=5,
        loop=True,
        distinct_runs=N_VEHICLES,
        estimator_mix=EstimatorMix(N_VEHICLES, MIXED_ESTIMATORS),
    ) as (app, server, sim):
        hub = app.state.runtime.live_hub
        assert isinstance(hub, LiveHub)
        poll_until(lambda: len(hub.vehicle_ids()) >= N_VEHICLES, "estimates from the pipeline")
        yield f"http://127.0.0.1:{server.port}", hub, sim


def _stored_slip_left(client: httpx.Client, vid: str, stamp: int) -> float | None:
    """The stored row's ``slip_left_pct`` at ``stamp`` (as the page knows it: to within the
    resolution of a JS double) — waits for the writer's commit."""
    deadline = time.monotonic() + 120  # s: the writer commits every 0.2 s, slower when loaded
    while True:
        body = client.get(
            f"/api/v1/vehicles/{vid}/series",
            params={
                "start": stamp - JS_NS_RESOLUTION,
                "end": stamp + JS_NS_RESOLUTION + 1,
                "fields": "slip_left_pct",
            },
        ).json()
        if body["rows"]:
            cols = body["columns"]
            i = min(range(body["rows"]), key=lambda j: abs(cols["stamp_ns"][j] - stamp))
            value: float | None = cols["slip_left_pct"][i]
            return value
        assert time.monotonic() < deadline, f"row {stamp} never stored"
        time.sleep(0.2)


def test_dashboard_on_the_real_stack(
    real_stack: tuple[str, LiveHub, FleetSim], page: Any, screenshots: Path
) -> None:
    base, hub, sim = real_stack
    page.goto(base + "/#/fleet")
    page.wait_for_function(
        "(n) => document.getElementById('fleet-summary').textContent.startsWith(n + ' vehicles')",
        arg=N_VEHICLES,
    )
    ids = page.eval_on_selector_all(
        ".vrows .vrow:not([hidden]) .c-id a", "els => els.map(e => e.textContent)"
    )
    assert sorted(ids) == sim.vehicle_ids
    page.screenshot(path=str(screenshots / "real_fleet.png"))

    vid = sim.vehicle_ids[0]
    page.goto(base + f"/#/vehicle/{vid}")
    page.wait_for_selector("#v-mdsf-slip-left[data-stamp-ns]")
    # let the vehicle get moving (slip needs ground speed) and the window fill
    page.wait_for_function(
        "() => document.getElementById('chart-mdsf-slip')?._uplot?.data[0].length > 100",
    )
    stamps: list[int] = []
    values: list[float] = []
    with httpx.Client(base_url=base, timeout=60) as client:
        for _ in range(4):
            stamp, shown = _page_latest(page)
            got = hub.latest(vid)
            assert got is not None
            row = got[0]
            # within one update of the hub (4 updates a second; JS holds stamps as doubles)
            assert -JS_NS_RESOLUTION <= int(row["stamp_ns"]) - stamp < 1_000_000_000
            stored = client.get(f"/api/v1/vehicles/{vid}/latest").json()
            assert abs(stored["stamp_ns"] - stamp) < 2_000_000_000  # the writer commits each 0.2 s
            # the shown slip is the stored estimate's value at that stamp, rounded for display
            stored_value = _stored_slip_left(client, vid, stamp)
            if stored_value is None:
                assert math.isnan(shown)
            else:
                assert abs(shown - stored_value) <= 0.051
            stamps.append(stamp)
            values.append(shown)
            page.wait_for_timeout(1000)
    assert len(set(stamps)) == 4, "the page stopped updating"
    assert len({v for v in values if not math.isnan(v)}) >= 2, "slip did not change over time"
    page.wait_for_function(f"({_COLOURED_PIXELS_JS})('live-map') > 300")
    # the packet accounting panel shows the server's counters for this vehicle
    page.wait_for_selector("#v-ingest tr[data-counter=received]")
    shown_counts = {
        name: int(page.inner_text(f'#v-ingest tr[data-counter="{name}"] td'))
        for name in ("received", "accepted", "rejected")
    }
    assert shown_counts["received"] > 100 and shown_counts["rejected"] == 0, shown_counts
    assert shown_counts["accepted"] <= shown_counts["received"]
    page.screenshot(path=str(screenshots / "real_vehicle.png"), full_page=True)


def _tile(page: Any, tile_id: str) -> list[str]:
    """A tile's label and unit as shown."""
    return list(
        page.evaluate(
            """(id) => { const s = document.getElementById(id).closest('.stat');
                const u = s.querySelector('.unit');
                const label = s.querySelector('.stat-label').textContent;
                return [label, u ? u.textContent.trim() : '']; }""",
            tile_id,
        )
    )


def _check_panel(page: Any, spec: EstimatorSpec) -> None:
    """The estimator's panel shows its spec: slip tiles and the motion tile by channel label and
    unit, one chart per ChartSpec with its title, unit and the fields' labels, filling."""
    fields = {f.name: f for f in spec.fields}
    for ch in spec.slips:
        assert _tile(page, f"v-{spec.name}-slip-{ch.key}") == [f"Slip {ch.label}", "%"]
    motion = next(c for c in spec.speeds if c.field == spec.motion_field)
    assert _tile(page, f"v-{spec.name}-speed") == [motion.label, fields[motion.field].unit]
    for chart in spec.charts:
        chart_id = f"chart-{spec.name}-{chart.key}"
        page.wait_for_function(
            f"document.getElementById('{chart_id}')?._uplot?.data[0].length > 20"
        )
        shown = page.evaluate(_CHART_JS, chart_id)
        y_label = f"{chart.title.lower()} ({chart.unit})" if chart.unit else chart.title.lower()
        assert (shown["title"], shown["y"]) == (chart.title, y_label)
        assert shown["labels"] == [fields[f].label for f in chart.fields]


def _last_point_is_stored(page: Any, client: httpx.Client, vid: str, spec: EstimatorSpec) -> None:
    """The first chart's newest point is the stored row of that estimator at that time (to the
    live feed's rounding, 0.001)."""
    chart = spec.charts[0]
    x_s, y = page.evaluate(
        """(id) => { const d = document.getElementById(id)._uplot.data;
            const i = d[0].length - 1; return [d[0][i], d[1][i]]; }""",
        f"chart-{spec.name}-{chart.key}",
    )
    stamp = round(x_s * 1e9)
    deadline = time.monotonic() + 120
    while True:  # the writer commits every 0.2 s
        body = client.get(
            f"/api/v1/vehicles/{vid}/series",
            params={
                "estimator": spec.name,
                "start": stamp - 1_000_000,
                "end": stamp + 1_000_000,
                "fields": chart.fields[0],
            },
        ).json()
        if body["rows"]:
            break
        assert time.monotonic() < deadline, f"{spec.name} row at {stamp} never stored"
        time.sleep(0.2)
    stored = body["columns"][chart.fields[0]][0]
    assert (y is None and stored is None) or abs(y - stored) <= 0.0005 + 1e-9, (y, stored)


def test_mixed_vehicle_shows_a_panel_per_estimator_on_the_real_stack(
    real_stack: tuple[str, LiveHub, FleetSim], page: Any, screenshots: Path
) -> None:
    base, _, sim = real_stack
    vid = sim.vehicle_ids[-1]
    specs = [spec_of(name) for name in MIXED_ESTIMATORS]
    with httpx.Client(base_url=base, timeout=60) as client:
        assert client.get(f"/api/v1/vehicles/{vid}").json()["estimators"] == list(MIXED_ESTIMATORS)
        page.goto(base + f"/#/vehicle/{vid}")
        page.wait_for_selector("[data-estimator=reference_speed] .u-title")
        panels = page.eval_on_selector_all(
            "section.est-panel",
            "els => els.map(e => [e.dataset.estimator, e.querySelector('h2').textContent])",
        )
        assert panels == [
            [specs[0].name, specs[0].title + "primary"],
            [specs[1].name, specs[1].title],
        ]
        for spec in specs:
            _check_panel(page, spec)
            _last_point_is_stored(page, client, vid, spec)
    page.screenshot(path=str(screenshots / "real_vehicle_mixed.png"), full_page=True)
