"""Databases written by the store of 020f4c3 (schema 9) upgrade with nothing lost.

The fixtures are made by ``fixtures/make_fixtures.py`` against that commit: a SQLite file with
rows both final and still staged, and a PostgreSQL ``pg_dump``. Each is upgraded by today's
``migrate()`` and read back whole: every row bit for bit, every vehicle with its config,
counter, anchor, token and raw packet; then the upgraded database takes new rows of every
estimator.
"""

from __future__ import annotations

import dataclasses
import gzip
import json
import shutil
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from estimator.catalog import SPECS
from estimator.reference_speed_spec import REFERENCE_SPEED_SPEC
from server.storage import Store
from server.storage.migrations import latest_version
from server.storage.postgres import PostgresStore
from server.storage.sqlite import SqliteStore
from tests.server.storage.conftest import DT_NS, batch_of, make_spec_rows
from tests.server.storage.fixtures.make_fixtures import (
    EXPECTED,
    FINAL_ROWS,
    PG_FIXTURE,
    SQLITE_FIXTURE,
    VEHICLES,
    fixture_rows,
)


def _check_content(store: Store) -> None:
    """Everything the old store wrote reads back equal."""
    expected: dict[str, Any] = json.loads(EXPECTED.read_text())
    assert [dataclasses.asdict(v) for v in store.list_vehicles()] == expected["vehicles"]
    assert {v["vehicle_id"] for v in expected["vehicles"]} == set(VEHICLES)
    assert any(
        v["config"]["slip"]["band_edges_pct"] == [3.0, 10.0, 25.0] for v in expected["vehicles"]
    )
    for vid, counters in expected["counters"].items():
        assert store.get_counters(vid) == counters
    assert {v: list(a) for v, a in store.get_anchors().items()} == expected["anchors"]
    tokens = store.list_tokens()
    assert [dataclasses.asdict(t) for t in tokens] == [
        {**{k: v for k, v in t.items() if k != "sha256"}, "expires_ns": None}  # version 14
        for t in expected["tokens"]
    ]
    for t in expected["tokens"]:
        found = store.get_token(t["sha256"])
        assert found is not None and found.id == t["id"]
    for vid, packets in expected["raw_packets"].items():
        got = store.query_raw_packets(vid, 0, 2**62)
        assert [[t, k, p.hex()] for t, k, p in got] == packets
    _check_rows(store)


def _today(rows: np.ndarray) -> np.ndarray:
    """Fixture rows as MDSF's rows are today: fields added since (15: the online calibration)
    NaN, as the migrations fill them."""
    out = SPECS["mdsf"].empty_rows(len(rows))
    for name in rows.dtype.names or ():
        out[name] = rows[name]
    return out


def _check_rows(store: Store) -> None:
    for vid in VEHICLES:
        want = _today(fixture_rows(vid))
        got = store.query_series(vid, 0, 2**62, estimator="mdsf")
        assert got.dtype.names == want.dtype.names and len(got) == len(want)
        assert got.tobytes() == want.tobytes(), vid  # bit for bit: NaN, inf, a denormal
        latest = store.latest(vid, estimator="mdsf")
        assert latest is not None and latest.tobytes() == want[-1].tobytes()
        assert store.estimators_with_rows(vid) == ["mdsf"]
    assert sorted(store.latest_all(estimator="mdsf")) == sorted(VEHICLES)


def _check_new_rows(store: Store) -> None:
    """The upgraded database keeps its keys (a replay is ignored) and takes every estimator."""
    old = {vid: _today(fixture_rows(vid)) for vid in VEHICLES}
    assert store.write_estimates(list(old.items())) == 0
    last = int(old["field-a"]["stamp_ns"][-1])
    newer = make_spec_rows(SPECS["mdsf"], 3, last + DT_NS, seed=4)
    ref = make_spec_rows(REFERENCE_SPEED_SPEC, 5, last, seed=5)
    assert (
        store.write_estimates(
            [("field-a", newer)], batch_of(REFERENCE_SPEED_SPEC, {"field-a": ref})
        )
        == 8
    )
    assert store.estimators_with_rows("field-a") == ["mdsf", "reference_speed"]
    got = store.query_series("field-a", 0, 2**62, estimator="reference_speed")
    assert got.tobytes() == ref.tobytes()
    assert len(store.query_series("field-a", 0, 2**62)) == VEHICLES["field-a"] + 3


def test_sqlite_database_of_schema_9_upgrades_with_nothing_lost(tmp_path: Path) -> None:
    path = tmp_path / "old.sqlite"
    path.write_bytes(gzip.decompress(SQLITE_FIXTURE.read_bytes()))
    store = SqliteStore(path)
    try:
        assert store.schema_version() == 9
        staged = sum(n - FINAL_ROWS for n in VEHICLES.values())
        assert store._read("SELECT count(*) FROM estimates_recent") == [(staged,)]
        assert store.migrate() == latest_version() > 9
        _check_content(store)
        while store.maintain(everything=True):  # the staged rows move on as before
            pass
        assert store._read("SELECT count(*) FROM estimates_recent") == [(0,)]
        _check_rows(store)
        _check_new_rows(store)
    finally:
        store.close()


def _psql() -> str:
    found = shutil.which("psql") or next(
        iter(sorted(Path("/usr/lib/postgresql").glob("*/bin/psql"), reverse=True)), None
    )
    if found is None:
        pytest.fail("psql (the PostgreSQL client) is needed to load the dump")
    return str(found)


@pytest.mark.postgres
def test_postgres_dump_of_schema_9_upgrades_with_nothing_lost(pg_database_url: str) -> None:
    subprocess.run(
        [_psql(), "-X", "-q", "-v", "ON_ERROR_STOP=1", "-d", pg_database_url],
        input=gzip.decompress(PG_FIXTURE.read_bytes()),
        check=True,
        capture_output=True,
    )
    store = PostgresStore(pg_database_url)
    try:
        assert store.schema_version() == 9
        assert store.migrate() == latest_version() > 9
        _check_content(store)
        _check_new_rows(store)
        # the identity sequences came along: a new vehicle and token get fresh keys
        store.upsert_vehicle("new-d", {}, now_ns=1)
        assert store.write_estimates([("new-d", _today(fixture_rows("field-b"))[:3])]) == 3
        assert store.create_token("new", "viewer", "e" * 64, 1).id == 4
    finally:
        store.close()
