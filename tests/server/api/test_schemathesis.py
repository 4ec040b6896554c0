"""Property-based run of the OpenAPI schema against the app: no 5xx, answers match the schema.

Bounded (few examples per operation) so it stays a unit test. Schemathesis runs the app's
lifespan itself; the runtime is the test runtime on a real SQLite file holding one vehicle.
"""

from __future__ import annotations

from typing import Any

import pytest
import schemathesis
from hypothesis import HealthCheck, settings

from server.api import create_app
from server.storage import open_store

from ._data import hand_series
from .conftest import FakeRuntime, make_settings


@pytest.fixture(scope="module")
def api_schema(tmp_path_factory: pytest.TempPathFactory) -> Any:
    app_settings = make_settings(tmp_path_factory.mktemp("schemathesis"))
    seed = open_store(app_settings.storage)
    try:
        seed.upsert_vehicle("tractor-1", {}, 0)
        seed.write_estimates([("tractor-1", hand_series())])
    finally:
        seed.close()
    app = create_app(app_settings, FakeRuntime(app_settings))
    return schemathesis.openapi.from_asgi("/openapi.json", app)


schema = schemathesis.pytest.from_fixture("api_schema")


@schema.parametrize()
@settings(max_examples=25, deadline=None, suppress_health_check=list(HealthCheck))
def test_api_conforms(case: Any) -> None:
    # Every check except "schema-valid request accepted": some rules cannot be said in JSON
    # Schema (end after start, slip band edges > 0, h0_m > 0, …) and are answered 422 on purpose.
    case.call_and_validate(excluded_checks=[schemathesis.checks.positive_data_acceptance])
