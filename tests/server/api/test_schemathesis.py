"""Property-based run of the OpenAPI schema against the app: no 5xx, answers match the schema.

Bounded (few examples per operation) so it stays a unit test. Two runs:

* against the app in process: schemathesis runs its lifespan; the runtime is the test runtime
  on a real SQLite file holding one vehicle;
* against a real ``slipfleet serve`` (real pipeline, embedded Zenoh router on loopback, SQLite),
  over HTTP, while simulated vehicles stream to it over Zenoh: every answer below 500.

Access tokens are on (the default): every call carries a real admin token, re-issued whenever a
generated ``DELETE /tokens/{id}`` happened to revoke it; calls schemathesis makes without it must
be refused.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import schemathesis
from hypothesis import HealthCheck, settings

from server.api import create_app
from server.settings import Settings, StorageSettings
from server.storage import Store, open_store
from server.tokens import Role, issue_token
from tests.server.faults._harness import Publisher, ServerProcess

from ._data import hand_series
from .conftest import FakeRuntime, make_settings


class AdminAuth:
    """An admin token in the app's database, replaced when a test call revoked it."""

    def __init__(self, store: Store) -> None:
        self.store = store
        self.token = ""

    def headers(self) -> dict[str, str]:
        """A token of its own for every call: a case may revoke the token it was given (the
        token routes are under test too), and this connection's read of the tokens table
        must not be trusted to have seen that yet."""
        self.token, _ = issue_token(self.store, "schemathesis", Role.ADMIN, time.time_ns())
        return {"Authorization": f"Bearer {self.token}"}


@pytest.fixture(scope="module")
def app_settings(tmp_path_factory: pytest.TempPathFactory) -> Settings:
    return make_settings(Path(tmp_path_factory.mktemp("schemathesis")), require_auth=True)


_CURRENT: list[AdminAuth] = []  # the module's AdminAuth while its fixture is active


class _BearerFromStore:
    """Schemathesis auth provider: each call gets the (current) admin token, so schemathesis
    knows the Authorization header is handled and does not count it as generated data."""

    def get(self, case: Any, ctx: Any) -> str:
        return _CURRENT[-1].headers()["Authorization"]

    def set(self, case: Any, data: str, ctx: Any) -> None:
        case.headers = {**(case.headers or {}), "Authorization": data}


@pytest.fixture(scope="module")
def admin_auth(app_settings: Settings) -> Iterator[AdminAuth]:
    store = open_store(app_settings.storage)
    auth = AdminAuth(store)
    _CURRENT.append(auth)
    try:
        yield auth
    finally:
        _CURRENT.remove(auth)
        store.close()


@pytest.fixture(scope="module")
def api_schema(app_settings: Settings, admin_auth: AdminAuth) -> Any:
    admin_auth.store.upsert_vehicle("tractor-1", {}, 0)
    admin_auth.store.write_estimates([("tractor-1", hand_series())])
    app = create_app(app_settings, FakeRuntime(app_settings))
    loaded = schemathesis.openapi.from_asgi("/openapi.json", app)
    loaded.auth(refresh_interval=None)(_BearerFromStore)
    return loaded


schema = schemathesis.pytest.from_fixture("api_schema")


@schema.parametrize()
@settings(max_examples=25, deadline=None, suppress_health_check=list(HealthCheck))
def test_api_conforms(case: Any, admin_auth: AdminAuth) -> None:
    # Every check except "schema-valid request accepted": some rules cannot be said in JSON
    # Schema (end after start, slip band edges > 0, h0_m > 0, …) and are answered 422 on purpose.
    assert _CURRENT[-1] is admin_auth
    response = case.call_and_validate(
        excluded_checks=[schemathesis.checks.positive_data_acceptance]
    )
    # the auth provider is in use: valid cases are never refused for lack of a token; negative
    # cases may drop the header on purpose and must then be refused (401, or 400/422 when the
    # body cannot even be parsed, which FastAPI checks first)
    mode = getattr(case.meta.generation.mode, "value", None) if case.meta else None
    if mode == "positive":
        assert response.status_code != 401, response.text
    elif "Authorization" not in (case.headers or {}):
        assert response.status_code in (400, 401, 422), response.text


# ----------------------------------------------------------------------------- a real server


@pytest.fixture(scope="module")
def live_admin_auth(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[AdminAuth, Path]]:
    """An admin token source on the SQLite file a real server will use (its ``tmp_path``)."""
    root = Path(tmp_path_factory.mktemp("schemathesis-live"))
    store = open_store(StorageSettings(data_dir=root / "data"))
    auth = AdminAuth(store)
    _CURRENT.append(auth)
    try:
        yield auth, root
    finally:
        _CURRENT.remove(auth)
        store.close()


@pytest.fixture(scope="module")
def live_schema(live_admin_auth: tuple[AdminAuth, Path]) -> Iterator[Any]:
    """The schema of a real ``slipfleet serve`` with tokens on, two simulated vehicles
    streaming to it over Zenoh for the whole run."""
    _, root = live_admin_auth
    server = ServerProcess(root, extra_env={"SLIPFLEET_API__REQUIRE_AUTH": "true"})
    server.start()
    publisher = Publisher(server.zenoh_listen, n_vehicles=2, duration_s=600.0, rate=1.0)
    try:
        server.wait_ready()
        publisher.start()
        loaded = schemathesis.openapi.from_url(f"{server.base_url}/openapi.json")
        loaded.auth(refresh_interval=None)(_BearerFromStore)
        yield loaded
    finally:
        publisher.stop()
        server.stop()
    print(f"real server: {sum(_LIVE_STATUSES.values())} calls, by status {dict(_LIVE_STATUSES)}")
    assert publisher.error is None, publisher.error


_LIVE_STATUSES: Counter[int] = Counter()  # every status the real server answered


live_schema_fixture = schemathesis.pytest.from_fixture("live_schema")


@pytest.mark.zenoh
@live_schema_fixture.parametrize()
@settings(max_examples=15, deadline=None, suppress_health_check=list(HealthCheck))
def test_real_server_answers_no_5xx(case: Any, live_admin_auth: tuple[AdminAuth, Path]) -> None:
    assert _CURRENT[-1] is live_admin_auth[0]
    response = case.call(timeout=60)
    _LIVE_STATUSES[response.status_code] += 1
    assert response.status_code < 500, f"{case.method} {case.formatted_path}: {response.text}"
    mode = getattr(case.meta.generation.mode, "value", None) if case.meta else None
    if mode == "positive":  # the token is sent and taken: the calls reach the handlers
        assert response.status_code != 401, response.text
