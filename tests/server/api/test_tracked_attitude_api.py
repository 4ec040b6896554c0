"""A crawler's pitch and roll over REST, from the tracked spec: the series (JSON, CSV, Parquet)
carries them with their 1-sigma, NaN as null; the estimators' description gives their units,
the chart that draws them, the position channel that poses the hull and the side-slope alert."""

from __future__ import annotations

import csv
import io

import numpy as np
import pyarrow.parquet as pq
import pytest

from estimator.tracked_spec import TRACKED_SPEC, TrackedFlag
from estimator.types import EstimateBatch
from server.storage.base import Store

from ._data import T0, S
from .conftest import ApiClient

U = "/api/v1/vehicles/c1/series"
ALL = f"start={T0}&end={T0 + 60 * S}&estimator=tracked"
ATTITUDE = ("pitch_rad", "pitch_std_rad", "roll_rad", "roll_std_rad")


def _crawler_on_a_side_slope() -> np.ndarray:
    """8 rows 1 s apart: no attitude on the first (NaN), then climbing a 10 % grade onto a
    side slope rolling 0.05 rad a second, right side down."""
    rows = TRACKED_SPEC.empty_rows(8)
    rows["stamp_ns"] = T0 + np.arange(8) * S
    rows["flags"] = int(TrackedFlag.GNSS_OK)
    i = np.arange(1, 8)
    rows["pitch_rad"][1:] = np.arctan(0.1)
    rows["pitch_std_rad"][1:] = 0.002
    rows["roll_rad"][1:] = 0.05 * i
    rows["roll_std_rad"][1:] = 0.003 - 0.0001 * i
    return rows


@pytest.fixture
def crawler(client: ApiClient, store: Store) -> np.ndarray:
    assert client.put("/api/v1/vehicles/c1", json={"kind": "tracked"}).status_code == 201
    rows = _crawler_on_a_side_slope()
    store.write_estimates(EstimateBatch.of([("c1", rows)], TRACKED_SPEC))
    return rows


def test_the_series_carries_the_attitude_as_json(client: ApiClient, crawler: np.ndarray) -> None:
    every = client.get(f"{U}?{ALL}").json()
    assert set(ATTITUDE) <= set(every["fields"])
    body = client.get(f"{U}?{ALL}&fields={','.join(ATTITUDE)}").json()
    assert body["estimator"] == "tracked" and body["fields"] == ["stamp_ns", *ATTITUDE]
    cols = body["columns"]
    for name in ATTITUDE:
        assert cols[name][0] is None, name  # no attitude yet: NaN → null
        # JSON floats carry 10 significant digits (encode_columns_json)
        assert cols[name][1:] == pytest.approx(crawler[name][1:].tolist(), rel=1e-9), name


def test_csv_and_parquet_exports_carry_the_attitude(client: ApiClient, crawler: np.ndarray) -> None:
    r = client.get(f"{U}?{ALL}&format=csv&fields=roll_rad,roll_std_rad")
    assert r.status_code == 200
    table = list(csv.DictReader(io.StringIO(r.text)))
    assert table[0]["roll_rad"] == "" and len(table) == 8
    assert [float(t["roll_rad"]) for t in table[1:]] == crawler["roll_rad"][1:].tolist()
    p = client.get(f"{U}?{ALL}&format=parquet")
    assert p.status_code == 200
    pt = pq.read_table(io.BytesIO(p.content))
    for name in ATTITUDE:
        assert pt[name].to_pylist()[1:] == crawler[name][1:].tolist(), name


def test_the_tracked_spec_describes_the_attitude(client: ApiClient) -> None:
    specs = {s["name"]: s for s in client.get("/api/v1/estimators").json()["data"]}
    tracked = specs["tracked"]
    fields = {f["name"]: f for f in tracked["fields"]}
    for name in ATTITUDE:
        assert fields[name]["unit"] == "rad" and fields[name]["label"], name
    assert tracked["position"]["pitch_field"] == "pitch_rad"
    assert tracked["position"]["roll_field"] == "roll_rad"
    charts = {c["key"]: c for c in tracked["charts"]}
    assert charts["attitude"]["fields"] == ["pitch_rad", "roll_rad"]
    assert charts["attitude"]["unit"] == "rad"
    alerts = {a["key"]: a for a in tracked["alerts"]}
    assert alerts["side_slope"]["field"] == "roll_rad"
    assert alerts["side_slope"]["above"] == pytest.approx(np.radians(15.0))
    assert alerts["side_slope"]["hold_s"] == 2.0
