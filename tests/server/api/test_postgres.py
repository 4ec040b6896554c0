"""The REST API on the PostgreSQL store: same answers as on SQLite."""

from __future__ import annotations

import csv
import io
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from estimator.reference_speed_spec import REFERENCE_SPEED_SPEC
from estimator.types import EstimateBatch
from server.settings import ApiSettings, Settings, StorageSettings
from server.storage.base import Store

from ._data import T0, S, hand_series, reference_series
from .conftest import ApiClient

pytestmark = pytest.mark.postgres

Q = f"start={T0}&end={T0 + 10 * S}"


@pytest.fixture
def settings(tmp_path: Path, pg_database_url: str) -> Settings:
    return Settings(
        storage=StorageSettings.model_validate({"data_dir": tmp_path, "url": pg_database_url}),
        api=ApiSettings.model_validate({"require_auth": False}),
    )


def test_vehicles_series_report_on_postgres(client: ApiClient, store: Store) -> None:
    assert store.dialect == "postgresql"
    assert client.put("/api/v1/vehicles/t1", json={}).status_code == 201
    assert (
        client.put("/api/v1/vehicles/t1", json={"slip": {"band_edges_pct": [5, 15]}}).status_code
        == 200
    )
    rows = hand_series()
    store.write_estimates([("t1", rows)])
    store.write_counters({"t1": {"received": 3, "accepted": 2, "rejected_decode": 1}}, T0)

    body = client.get(f"/api/v1/vehicles/t1/series?{Q}&fields=vg_mps,slip_left_pct").json()
    assert body["columns"]["vg_mps"] == [0, 0, 2, 2, 2, 2, 4, 4, 0.1, 0]
    assert body["columns"]["slip_left_pct"][:3] == [None, None, 1.0]

    text = client.get(f"/api/v1/vehicles/t1/series?{Q}&format=csv&fields=flags").text
    assert [int(r["flags"]) for r in csv.DictReader(io.StringIO(text))] == rows["flags"].tolist()
    table = pq.read_table(
        io.BytesIO(client.get(f"/api/v1/vehicles/t1/series?{Q}&format=parquet").content)
    )
    assert table["stamp_ns"].to_pylist() == rows["stamp_ns"].tolist()

    rep = client.get(f"/api/v1/vehicles/t1/report?{Q}").json()
    assert rep["report"]["distance_m"] == pytest.approx(16.0)
    assert rep["report"]["slips"]["left"]["p95_pct"] == pytest.approx(17.5)
    assert rep["ingest"]["rejected_by_reason"] == {"decode": 1}

    # a second estimator's rows of the same vehicle, read by name
    store.write_estimates(EstimateBatch.of([("t1", reference_series())], REFERENCE_SPEED_SPEC))
    ref = client.get(f"/api/v1/vehicles/t1/report?{Q}&estimator=reference_speed").json()
    assert ref["report"]["distance_m"] == pytest.approx(12.0) and ref["report"]["slips"] == {}
    assert client.get(f"/api/v1/vehicles/t1/report?{Q}").json()["estimator"] == "mdsf"

    latest = client.get("/api/v1/vehicles/t1/latest").json()
    assert latest["stamp_ns"] == T0 + 9 * S
    assert latest["flag_names"] == []

    assert client.delete("/api/v1/vehicles/t1").status_code == 204
    assert client.get("/api/v1/vehicles/t1").status_code == 404
    assert client.get("/api/v1/health").json()["checks"]["storage"] is True


def test_access_tokens_on_postgres(tmp_path: Path, pg_database_url: str) -> None:
    import time

    from server.api import create_app
    from server.tokens import Role, issue_token

    from .conftest import FakeRuntime, running

    settings = Settings(
        storage=StorageSettings.model_validate({"data_dir": tmp_path, "url": pg_database_url}),
        api=ApiSettings.model_validate({"require_auth": True}),
    )
    runtime = FakeRuntime(settings)
    with running(create_app(settings, runtime)) as client:
        assert runtime.store.dialect == "postgresql"
        token, record = issue_token(runtime.store, "pg", Role.OPERATOR, time.time_ns())
        auth = {"Authorization": f"Bearer {token}"}
        assert client.get("/api/v1/vehicles").status_code == 401
        assert client.put("/api/v1/vehicles/t1", json={}, headers=auth).status_code == 201
        assert client.delete("/api/v1/vehicles/t1", headers=auth).status_code == 403
        runtime.store.revoke_token(record.id, time.time_ns())
        assert client.get("/api/v1/vehicles", headers=auth).status_code == 401
