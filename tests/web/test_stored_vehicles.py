"""After a restart the fleet page lists the stored vehicles, marked not live, with their newest
stored values, and each opens: the vehicle page says it is not live and when its newest stored
estimate was. Real Chromium; the server restarted on the same SQLite file with an empty live hub
(no vehicle has sent anything since)."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from server.storage import open_store
from server.storage.writer import StoreWriter
from server.timeparse import format_ns
from tests.web.conftest import N_VEHICLES, LiveRuntime, LiveStack, serve_live_stack

pytestmark = pytest.mark.browser


class RestartedRuntime(LiveRuntime):
    """The store as the last run left it; nothing live yet (no feed into the hub)."""

    def open(self) -> None:
        self._store = open_store(self.settings.storage)
        self.writer = StoreWriter(self._store, self.settings.storage).start()


@pytest.fixture(scope="module")
def restarted(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveStack]:
    data_dir = tmp_path_factory.mktemp("store")
    with serve_live_stack(data_dir, require_auth=False):
        pass  # the first run: 12 vehicles registered, two minutes of estimates stored
    with serve_live_stack(data_dir, require_auth=False, runtime_class=RestartedRuntime) as stack:
        yield stack


# status text, class and the cells' text of every row the table holds
_ROWS_JS = """
() => [...document.querySelectorAll('.vrows .vrow')].filter((r) => !r.hidden).map((r) => ({
  id: r.querySelector('.c-id a').textContent,
  href: r.querySelector('.c-id a').getAttribute('href'),
  status: r.querySelector('.c-status .pill').textContent,
  cls: r.className,
  title: r.title,
  speed: r.querySelector('.c-speed_mps').textContent,
  slips: [...r.querySelectorAll('.slip')].map((c) => c.textContent),
}))
"""


def test_stored_vehicles_are_listed_not_live_and_open(
    restarted: LiveStack, page: Any, screenshots: Path
) -> None:
    store = restarted.runtime.store
    ids = sorted(v.vehicle_id for v in store.list_vehicles())
    assert len(ids) == N_VEHICLES
    page.goto(f"{restarted.base_url}/#/fleet")
    want = f"{N_VEHICLES} vehicles — 0 live, 0 stale, 0 offline, {N_VEHICLES} stored, not live"
    page.wait_for_function(
        "(w) => document.getElementById('fleet-summary').textContent === w", arg=want
    )
    # the newest stored values arrive a few at a time
    page.wait_for_function(
        f"() => ({_ROWS_JS})().filter((r) => r.speed !== '–').length === {N_VEHICLES}",
        timeout=20000,
    )
    rows = page.evaluate(_ROWS_JS)
    assert sorted(r["id"] for r in rows) == ids
    for r in rows:
        assert r["status"] == "not live" and "row-old" in r["cls"] and "row-stored" in r["cls"]
        assert "nothing received since the server started" in r["title"]
        latest = store.latest(r["id"])
        assert latest is not None
        assert format_ns(int(latest["stamp_ns"]))[:19].replace("T", " ") in r["title"]
        assert float(r["speed"]) == pytest.approx(float(latest["vg_mps"]), abs=0.006)
        assert len(r["slips"]) == 2 and all(re.fullmatch(r"-?\d+\.\d|–", s) for s in r["slips"])
    page.screenshot(path=str(screenshots / "fleet-after-restart.png"))

    page.click(f"a[href='{rows[0]['href']}']")
    page.wait_for_selector("#v-parked")
    assert page.inner_text("#v-status") == "not live"
    page.wait_for_function("() => document.getElementById('v-parked-last').dataset.stampNs")
    stamp = int(page.get_attribute("#v-parked-last", "data-stamp-ns"))
    latest = store.latest(rows[0]["id"])
    # (a JSON number in the page: exact to a microsecond at today's epoch nanoseconds)
    assert latest is not None and abs(stamp - int(latest["stamp_ns"])) < 1_000
    assert page.get_attribute("#v-parked a", "href") == rows[0]["href"] + "/history"
    assert page.query_selector("#v-unknown") is None
    page.screenshot(path=str(screenshots / "vehicle-not-live.png"))
