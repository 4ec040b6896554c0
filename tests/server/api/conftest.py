"""A test runtime (real SQLite store in tmp_path and its writer, no Zenoh) and a client for the
app."""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from contextlib import AbstractAsyncContextManager, contextmanager
from pathlib import Path
from typing import Any

import httpx
import pytest
from anyio.from_thread import BlockingPortal, start_blocking_portal
from fastapi import FastAPI

from estimator.config import ConfigError, VehicleConfig
from server.analytics.alerts import AlertEngine
from server.api import ApiLimits, create_app
from server.live.hub import LiveHub
from server.metrics.prometheus import MetricFamily, Sample
from server.settings import ApiSettings, Settings, StorageSettings
from server.storage import Store, StoreWriter, open_store


def open_test_store(settings: Settings) -> Store:
    """The real store the settings name (SQLite in ``settings.storage.data_dir``), migrated."""
    return open_store(settings.storage)


def make_settings(tmp_path: Path, *, url: str | None = None, **api: Any) -> Settings:
    """Settings with storage in ``tmp_path`` (or at the database ``url``); ``api`` overrides
    (tokens off unless given)."""
    storage: dict[str, Any] = {"data_dir": tmp_path}
    if url is not None:
        storage["url"] = url
    return Settings(
        storage=StorageSettings.model_validate(storage),
        api=ApiSettings.model_validate({"require_auth": False, **api}),
    )


class FakeRuntime:
    """What the API needs from the runtime: a real store and its writer, settable health,
    recorded hooks."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self._store: Store | None = None
        self.writer: StoreWriter | None = None
        self.zenoh_up = True
        self.config_calls: list[tuple[str, VehicleConfig]] = []
        self.config_checks: list[tuple[str, VehicleConfig]] = []
        self.refuse_configs = ""  # set: check_vehicle_config refuses every config with this
        self.deleted: list[str] = []
        self.commands: list[tuple[str, str, str, bool]] = []
        self.calibration_resets: list[tuple[str, str]] = []
        self.opened = 0
        self.closed = 0
        self.metrics_by_vehicle: list[bool] = []  # what each /metrics call asked for
        self.alert_engine = AlertEngine()
        self.live_hub: LiveHub | None = None  # a test that serves live views sets one

    @property
    def store(self) -> Store:
        assert self._store is not None, "runtime not open"
        return self._store

    def viewer_port(self) -> int | None:
        return None  # no 3D view

    def open(self) -> None:
        self._store = open_test_store(self.settings)
        self.writer = StoreWriter(self._store, self.settings.storage).start()
        self.opened += 1

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None
        if self._store is not None:
            self._store.close()
        self.closed += 1

    def health(self) -> Mapping[str, bool]:
        return {"zenoh": self.zenoh_up, "storage": self.store.ping()}

    @property
    def vehicle_events(self) -> FakeRuntime:
        return self

    def check_vehicle_config(self, vehicle_id: str, config: VehicleConfig) -> None:
        self.config_checks.append((vehicle_id, config))
        if self.refuse_configs:
            raise ConfigError(self.refuse_configs)

    def on_estimator_command(self, vehicle_id: str, estimator: str, key: str, on: bool) -> None:
        self.commands.append((vehicle_id, estimator, key, on))

    def on_calibration_reset(self, vehicle_id: str, estimator: str) -> None:
        self.calibration_resets.append((vehicle_id, estimator))

    def metrics(self, by_vehicle: bool = True) -> list[MetricFamily]:
        self.metrics_by_vehicle.append(by_vehicle)
        samples = []
        for rec in self.store.list_vehicles():
            for name, value in sorted(self.store.get_counters(rec.vehicle_id).items()):
                samples.append(Sample(value, {"vehicle": rec.vehicle_id, "reason": name}))
        return [
            MetricFamily(
                "slipfleet_ingest_packets",
                "counter",
                "Packets per vehicle and reason.",
                [Sample(s.value, s.labels, "_total") for s in samples],
            ),
            MetricFamily(
                "slipfleet_writer_backlog_rows",
                "gauge",
                "Rows waiting for the writer.",
                [Sample(0)],
            ),
        ]

    def on_vehicle_config(self, vehicle_id: str, config: VehicleConfig) -> None:
        self.config_calls.append((vehicle_id, config))

    def on_vehicle_deleted(self, vehicle_id: str) -> None:
        self.deleted.append(vehicle_id)


@pytest.fixture
def settings(tmp_path: Path) -> Settings:
    return make_settings(tmp_path)


@pytest.fixture
def runtime(settings: Settings) -> FakeRuntime:
    return FakeRuntime(settings)


@pytest.fixture
def app(settings: Settings, runtime: FakeRuntime) -> FastAPI:
    return create_app(settings, runtime, limits=ApiLimits())


class ApiClient:
    """Synchronous client over httpx's ASGI transport, with the app's lifespan running.

    (Starlette's TestClient is not used: it warns about its httpx dependency.)
    """

    def __init__(self, portal: BlockingPortal, client: httpx.AsyncClient) -> None:
        self._portal = portal
        self._client = client

    def request(self, method: str, url: str, **kwargs: Any) -> httpx.Response:
        return self._portal.call(lambda: self._client.request(method, url, **kwargs))

    def get(self, url: str, **kwargs: Any) -> httpx.Response:
        return self.request("GET", url, **kwargs)

    def post(self, url: str, **kwargs: Any) -> httpx.Response:
        return self.request("POST", url, **kwargs)

    def put(self, url: str, **kwargs: Any) -> httpx.Response:
        return self.request("PUT", url, **kwargs)

    def delete(self, url: str, **kwargs: Any) -> httpx.Response:
        return self.request("DELETE", url, **kwargs)

    def options(self, url: str, **kwargs: Any) -> httpx.Response:
        return self.request("OPTIONS", url, **kwargs)


@contextmanager
def running(app: FastAPI) -> Iterator[ApiClient]:
    """Run ``app``'s lifespan in a background event loop and yield a client for it."""
    with start_blocking_portal() as portal:
        lifespan: AbstractAsyncContextManager[Any] = app.router.lifespan_context(app)
        portal.call(lifespan.__aenter__)
        client = httpx.AsyncClient(
            transport=httpx.ASGITransport(app=app), base_url="http://testserver"
        )
        try:
            yield ApiClient(portal, client)
        finally:
            portal.call(client.aclose)
            portal.call(lifespan.__aexit__, None, None, None)


def error_of(response: httpx.Response, status_code: int) -> tuple[str, str]:
    """``(error, reason)`` of an error answer, which must have ``status_code``."""
    assert response.status_code == status_code, response.text
    body = response.json()
    return body["error"], body["reason"]


@contextmanager
def running_on(
    settings: Settings, limits: ApiLimits | None = None
) -> Iterator[tuple[ApiClient, FakeRuntime]]:
    """An app over a test runtime of ``settings`` (with ``limits``), running, and its runtime."""
    runtime = FakeRuntime(settings)
    with running(create_app(settings, runtime, limits=limits or ApiLimits())) as client:
        yield client, runtime


@pytest.fixture
def client(app: FastAPI) -> Iterator[ApiClient]:
    with running(app) as c:
        yield c


@pytest.fixture
def store(client: ApiClient, runtime: FakeRuntime) -> Store:
    return runtime.store
