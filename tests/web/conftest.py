"""A real app with live data for the browser tests, and a headless Debian Chromium.

The app is the product's ``create_app`` (every API router) with the dashboard mounted, over a
runtime holding a real SQLite store (``tmp_path``), a :class:`LiveHub` and an
:class:`AlertEngine`. A :class:`FeedThread` pushes synthetic estimate rows (12 vehicles, 20 Hz,
stamped with the wall clock) into the hub, the alert engine and the store, after back-filling the
last two minutes, as the pipeline thread would.

Chromium: ``apt-get install -y chromium`` (``/usr/bin/chromium``); override with
``SLIPFLEET_CHROMIUM``. Without it the browser tests fail (they are never skipped).
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import uvicorn

from estimator.config import SlipConfig, WheeledRearDriveConfig
from server.analytics.alerts import AlertEngine
from server.api import NoVehicleEvents, create_app
from server.live.hub import LiveHub
from server.metrics.prometheus import MetricFamily
from server.settings import ApiSettings, Settings, StorageSettings
from server.storage import Store, open_store
from server.storage.writer import StoreWriter
from server.tooling.bench.live import CHROMIUM_ARGS, FeedThread, SyntheticFleet
from server.web import mount_web
from tests.support import free_port

REPO = Path(__file__).resolve().parents[2]
SCREENSHOTS = REPO / "artifacts" / "screenshots"
CHROMIUM = os.environ.get("SLIPFLEET_CHROMIUM", "/usr/bin/chromium")
N_VEHICLES = 12
SENSITIVE = "veh-003"  # configured with a 12 % slip alert threshold
#: How long a page may take to show what a test waits for, ms: the deadline of a page that never
#: does, not a pause (each wait returns once its condition holds). On a loaded 2-core host
#: Chromium's software rendering runs many times slower than on a quiet one.
PAGE_WAIT_MS = 120_000


class LiveRuntime:
    """Store and its writer thread + live hub + alert engine + synthetic feed, opened and closed
    by the app's lifespan; REST writes go through the writer as in the server."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.fleet = SyntheticFleet(N_VEHICLES, seed=7)
        self.live_hub = LiveHub()
        self.alert_engine = AlertEngine()
        self._store: Store | None = None
        self.writer: StoreWriter | None = None
        self.feed: FeedThread | None = None
        self.vehicle_events = NoVehicleEvents()

    @property
    def store(self) -> Store:
        assert self._store is not None
        return self._store

    def viewer_port(self) -> int | None:
        return None  # no 3D view

    def open(self) -> None:
        self._store = open_store(self.settings.storage)
        now = time.time_ns()
        for vid in self.fleet.ids:
            config = (
                WheeledRearDriveConfig(slip=SlipConfig(alert_threshold_pct=12.0))
                if vid == SENSITIVE
                else WheeledRearDriveConfig()
            )
            self._store.upsert_vehicle(vid, config.to_dict(), now)
            self.alert_engine.set_slip_config(vid, config.slip)
        self.writer = StoreWriter(self._store, self.settings.storage).start()
        self.feed = FeedThread(
            self.fleet, [self.live_hub, self.alert_engine, self.writer], rate_hz=20.0
        )
        self.feed.backfill(120.0, rate_hz=10.0)
        assert self.writer.flush(timeout=120.0), "the back-filled rows were not stored"
        self.feed.start()

    def close(self) -> None:
        if self.feed is not None:
            self.feed.stop()
        if self.writer is not None:
            self.writer.close()
        if self._store is not None:
            self._store.close()

    def health(self) -> Mapping[str, bool]:
        return {"storage": self.store.ping()}

    def metrics(self, by_vehicle: bool = True) -> Iterable[MetricFamily]:
        return ()


@dataclass
class LiveStack:
    base_url: str
    runtime: LiveRuntime


@contextmanager
def serve_live_stack(
    data_dir: Path,
    *,
    require_auth: bool,
    runtime_class: type[LiveRuntime] = LiveRuntime,
    **api: Any,
) -> Iterator[LiveStack]:
    """The dashboard app over a :class:`LiveRuntime` (or ``runtime_class``) on a free port,
    until the block ends; ``api``: further :class:`ApiSettings` (``map_tile_url``)."""
    settings = Settings(
        storage=StorageSettings.model_validate({"data_dir": data_dir}),
        api=ApiSettings.model_validate({"require_auth": require_auth, **api}),
    )
    runtime = runtime_class(settings)
    app = create_app(settings, runtime)
    mount_web(app)
    port = free_port()
    server = uvicorn.Server(
        uvicorn.Config(
            app, host="127.0.0.1", port=port, log_level="warning", ws="websockets-sansio"
        )
    )
    thread = threading.Thread(target=server.run, name="uvicorn-test", daemon=True)
    thread.start()
    deadline = time.monotonic() + 120  # s: generous, a loaded host starts it slowly
    while not server.started:
        assert time.monotonic() < deadline, "uvicorn did not start"
        assert thread.is_alive(), "uvicorn exited"
        time.sleep(0.05)
    try:
        yield LiveStack(f"http://127.0.0.1:{port}", runtime)
    finally:
        server.should_exit = True
        thread.join(timeout=15)


@pytest.fixture(scope="module")
def live_stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveStack]:
    with serve_live_stack(tmp_path_factory.mktemp("store"), require_auth=False) as stack:
        yield stack


@pytest.fixture(scope="module")
def secured_stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveStack]:
    """The same stack with access tokens required (as ``slipfleet serve`` runs)."""
    with serve_live_stack(tmp_path_factory.mktemp("store"), require_auth=True) as stack:
        yield stack


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    from playwright.sync_api import sync_playwright

    if not Path(CHROMIUM).exists():
        pytest.fail(f"Chromium not found at {CHROMIUM}: apt-get install -y chromium", pytrace=False)
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=list(CHROMIUM_ARGS), headless=True)
        try:
            yield b
        finally:
            b.close()


@contextmanager
def browser_page(browser: Any, **context: Any) -> Iterator[Any]:
    """A page in a new browser context (``context``: Playwright's ``new_context`` options)
    whose waits, navigations included, time out after :data:`PAGE_WAIT_MS`; closed after."""
    ctx = browser.new_context(**context)
    ctx.set_default_timeout(PAGE_WAIT_MS)
    try:
        yield ctx.new_page()
    finally:
        ctx.close()


@contextmanager
def checked_page(
    browser: Any, allowed: Callable[[Any], bool] = lambda msg: False, **context: Any
) -> Iterator[Any]:
    """A :func:`browser_page` that fails the test on any page error, or console error other
    than the ``allowed`` ones (a predicate on Playwright's console message). The browser's time
    zone is UTC unless ``context`` names another (``timezone_id``): the dashboard shows times
    in it."""
    with browser_page(browser, **{"timezone_id": "UTC", **context}) as pg:
        errors = _page_errors(pg, allowed)
        yield pg
    assert errors == [], f"errors in the page: {errors}"


def _page_errors(pg: Any, allowed: Callable[[Any], bool]) -> list[str]:
    """The page's errors and not ``allowed`` console errors, as they come."""
    errors: list[str] = []
    pg.on("pageerror", lambda exc: errors.append(str(exc)))
    pg.on(
        "console",
        lambda msg: errors.append(msg.text) if msg.type == "error" and not allowed(msg) else None,
    )
    return errors


def history_loaded(page: Any) -> int:
    """Wait until the history page says it has drawn its points; return how many (read as it
    says so: a load started after it would change the words)."""
    said = page.wait_for_function(
        "() => /^(\\d+) points$/.exec(document.getElementById('h-msg').textContent)?.[1]"
    )
    return int(said.json_value())


@pytest.fixture
def page(browser: Any) -> Iterator[Any]:
    with checked_page(browser, viewport={"width": 1400, "height": 900}) as pg:
        yield pg


@pytest.fixture(scope="session")
def screenshots() -> Path:
    SCREENSHOTS.mkdir(parents=True, exist_ok=True)
    return SCREENSHOTS
