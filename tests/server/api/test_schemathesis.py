"""Property-based run of the OpenAPI schema against the app: no 5xx, answers match the schema.

Bounded (few examples per operation) so it stays a unit test. Schemathesis runs the app's
lifespan itself; the runtime is the test runtime on a real SQLite file holding one vehicle.
Access tokens are on (the default): every call carries a real admin token, re-issued whenever a
generated ``DELETE /tokens/{id}`` happened to revoke it; calls schemathesis makes without it must
be refused.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import schemathesis
from hypothesis import HealthCheck, settings

from server.api import create_app
from server.settings import Settings
from server.storage import Store, open_store
from server.tokens import Role, issue_token

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
    assert [admin_auth] == _CURRENT
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
