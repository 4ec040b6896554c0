"""Series exports that stand on their own: ISO time and flag names in CSV and Parquet, units,
labels, vehicle and estimator in the Parquet metadata, all from the estimator's spec."""

from __future__ import annotations

import csv
import io
import json

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from estimator.catalog import SPECS
from estimator.reference_speed_spec import REFERENCE_SPEED_SPEC as REF
from estimator.types import EstimateBatch
from server.api.routes.series import flag_names_column, iso_times
from server.storage.base import Store
from server.timeparse import format_ns

from ._data import T0, S, hand_series, reference_series
from .conftest import ApiClient

U = "/api/v1/vehicles/t1/series"
ALL = f"start={T0}&end={T0 + 3600 * S}"
MDSF = SPECS["mdsf"]

# hand_series' flags by row: DEGRADED on 0-1, both slips valid on 2-4, left only on 5-7
HAND_FLAG_NAMES = [
    "DEGRADED",
    "DEGRADED",
    *["SLIP_LEFT_VALID|SLIP_RIGHT_VALID"] * 3,
    *["SLIP_LEFT_VALID"] * 3,
    "",
    "",
]


@pytest.fixture
def filled(client: ApiClient, store: Store) -> np.ndarray:
    assert client.put("/api/v1/vehicles/t1", json={}).status_code == 201
    rows = hand_series()
    store.write_estimates(EstimateBatch.of([("t1", rows)], MDSF))
    return rows


def test_csv_has_iso_time_and_flag_names(client: ApiClient, filled: np.ndarray) -> None:
    text = client.get(f"{U}?{ALL}&format=csv&fields=vg_mps,flags").text
    header = text.splitlines()[0]
    assert header == "stamp_ns,time,vg_mps,flags,flag_names"
    table = list(csv.DictReader(io.StringIO(text)))
    assert table[0]["time"] == "2024-05-01T12:00:00.000000000Z"
    assert [t["time"] for t in table] == [format_ns(s) for s in filled["stamp_ns"].tolist()]
    assert [t["flag_names"] for t in table] == HAND_FLAG_NAMES
    # without flags asked for, no flag names; time always
    header = client.get(f"{U}?{ALL}&format=csv&fields=vg_mps").text.splitlines()[0]
    assert header == "stamp_ns,time,vg_mps"


def test_parquet_carries_time_flag_names_and_metadata(
    client: ApiClient, filled: np.ndarray
) -> None:
    table = pq.read_table(io.BytesIO(client.get(f"{U}?{ALL}&format=parquet").content))
    names = list(MDSF.field_names)
    assert table.column_names == [
        "stamp_ns",
        "time",
        *names[1 : names.index("flags") + 1],
        "flag_names",
        *names[names.index("flags") + 1 :],
    ]
    assert table.schema.field("time").type == pa.timestamp("ns", tz="UTC")
    assert table["time"].cast(pa.int64()).to_pylist() == filled["stamp_ns"].tolist()
    assert table["flag_names"].to_pylist() == HAND_FLAG_NAMES
    meta = {k.decode(): v.decode() for k, v in (table.schema.metadata or {}).items()}
    assert meta["vehicle_id"] == "t1"
    assert meta["estimator"] == "mdsf"
    assert (int(meta["start_ns"]), int(meta["end_ns"])) == (T0, T0 + 3600 * S)
    assert json.loads(meta["flag_bits"])["SLIP_LEFT_VALID"] == 4
    for f in MDSF.fields:
        got = table.schema.field(f.name).metadata
        assert got == {
            b"unit": f.unit.encode(),
            b"label": f.label.encode(),
            b"description": f.description.encode(),
        }
    assert table.schema.field("vg_mps").metadata[b"unit"] == b"m/s"


def test_other_estimator_exports_by_its_own_spec(client: ApiClient, store: Store) -> None:
    assert client.put("/api/v1/vehicles/t1", json={}).status_code == 201
    store.write_estimates(EstimateBatch.of([("t1", reference_series())], REF))
    q = f"{ALL}&estimator={REF.name}&fields=speed_mps,flags"
    table = list(csv.DictReader(io.StringIO(client.get(f"{U}?{q}&format=csv").text)))
    assert [t["flag_names"] for t in table[:4]] == ["WHEEL_OK", "WHEEL_OK", "NO_WHEEL", "NO_WHEEL"]
    pt = pq.read_table(io.BytesIO(client.get(f"{U}?{q}&format=parquet").content))
    assert pt.schema.metadata[b"estimator"] == REF.name.encode()
    assert pt.schema.field("speed_mps").metadata[b"label"] == b"reference speed"
    assert pt["flag_names"].to_pylist()[2] == "NO_WHEEL"


def test_json_head_has_units_and_flag_bits(client: ApiClient, filled: np.ndarray) -> None:
    body = client.get(f"{U}?{ALL}&fields=vg_mps,slip_left_pct,flags").json()
    assert body["units"] == {"stamp_ns": "ns", "vg_mps": "m/s", "slip_left_pct": "%", "flags": ""}
    assert body["flag_bits"] == {f.name: f.bit for f in MDSF.flags}


def test_empty_exports_keep_their_columns(client: ApiClient, filled: np.ndarray) -> None:
    q = f"start={T0 + 100 * S}&end={T0 + 200 * S}"
    assert client.get(f"{U}?{q}&format=csv&fields=flags").text == "stamp_ns,time,flags,flag_names\n"
    table = pq.read_table(io.BytesIO(client.get(f"{U}?{q}&format=parquet").content))
    assert table.num_rows == 0
    assert "time" in table.column_names and "flag_names" in table.column_names


def test_column_helpers_match_the_scalar_forms() -> None:
    stamps = np.array([0, 1, T0 + 123_456_789, 2**62], dtype=np.int64)
    assert iso_times(stamps).tolist() == [format_ns(s) for s in stamps.tolist()]
    flags = np.array([0, 17, 17, 1, 48], dtype=np.int32)
    codes, names = flag_names_column(MDSF, flags)
    assert names[codes].tolist() == ["|".join(MDSF.flag_names(int(f))) for f in flags.tolist()]
    assert names[codes][1] == "GNSS_OK|SLIP_LEFT_VALID"
