"""``/vehicles/{id}/series``: one estimator's series as JSON columns, CSV, Parquet or GeoJSON,
optionally decimated. Fields are those of the estimator's spec (``?estimator=``, default the
vehicle's primary); GeoJSON places rows by the spec's position channel.

Rows are read from the store in chunks (``ApiLimits.query_chunk_ns``) so a long range never sits
in memory at full rate. With ``max_points`` >= 2 and more rows than that, every chunk is decimated
by :func:`server.analytics.downsample.downsample_minmax` (per time bucket the min and max of each
field, for charts) or :func:`server.analytics.downsample.thin_first` (per time bucket its first
row, whole, for positions and GeoJSON). The buckets are sized on the span of the stored rows in
the range (first to last), not on the requested range; chunks are whole numbers of buckets, so
chunking does not change the result.
"""

from __future__ import annotations

import csv
import io
import json
import math
import re
from collections.abc import Iterator, Sequence
from typing import Annotated, Literal

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from fastapi import APIRouter, Query, Response
from fastapi.responses import StreamingResponse

from estimator.geo import EnuFrame
from estimator.spec import EstimatorSpec, FieldSpec, PositionChannel
from server.analytics.downsample import bucket_width_ns, downsample_minmax, thin_first
from server.api.deps import (
    ApiLimits,
    EstimatorDep,
    LimitsDep,
    StoreDep,
    TimeRange,
    TimeRangeDep,
    VehicleDep,
)
from server.api.errors import BadRequest, RangeTooLarge, Unprocessable, error_responses
from server.api.models import AnchorPublic, SeriesFormat, SeriesPublic, fields_doc
from server.storage.base import Anchor, Store

__all__ = [
    "GEOJSON_MEDIA_TYPE",
    "PARQUET_MEDIA_TYPE",
    "encode_columns_json",
    "export_filename",
    "export_names",
    "flag_names_column",
    "iso_times",
    "router",
]

router = APIRouter(prefix="/vehicles", tags=["series"])

PARQUET_MEDIA_TYPE = "application/vnd.apache.parquet"
_CSV_ROWS_PER_WRITE = 5000


def _parse_fields(fields: str | None, spec: EstimatorSpec) -> list[str]:
    """The fields asked for (all of ``spec``'s when none), ``stamp_ns`` first; 422 naming the
    estimator and the fields it does not have."""
    if fields is None or not fields.strip():
        return list(spec.field_names)
    wanted = [f.strip() for f in fields.split(",") if f.strip()]
    unknown = sorted({f for f in wanted if not spec.has_field(f)})
    if unknown:
        raise Unprocessable(
            f"estimator {spec.name!r} has no field(s) {unknown}; its fields: "
            f"{list(spec.field_names)}"
        )
    out = ["stamp_ns"]
    for f in wanted:
        if f not in out:
            out.append(f)
    return out


Decimation = Literal["minmax", "first"]
"""``minmax``: per time bucket the min and max of each field (:func:`downsample_minmax`, for
charts); ``first``: per time bucket its first row, whole (:func:`thin_first`, for positions)."""

_PROBE_NS = 1_000_000_000  # first probe window when looking for the data's edges


class _Reader:
    """Reads a range chunk by chunk and decimates once there are more rows than ``max_points``.

    Decimating, the buckets are sized on the data's own span in the range, from its first to
    its last stored row (:meth:`span`), and anchored at the first row: a short drive in a long
    range keeps its detail. Chunks are whole numbers of buckets, so chunking does not change
    the result.
    """

    def __init__(
        self,
        store: Store,
        vehicle_id: str,
        spec: EstimatorSpec,
        tr: TimeRange,
        fields: Sequence[str],
        max_points: int,
        limits: ApiLimits,
        decimation: Decimation = "minmax",
    ) -> None:
        self.store = store
        self.vehicle_id = vehicle_id
        self.spec = spec
        self.tr = tr
        self.fields = list(fields)
        self.max_points = max_points
        self.decimation = decimation
        self.limits = limits
        self.downsampled = False
        self.stored_rows = 0  # rows read from the store so far
        self.first_ns: int | None = None  # stamps of the first and last stored row in the range
        self.last_ns: int | None = None
        self.width_ns = 0  # bucket width once decimating is possible (0: full rate)

    def _stamps(self, lo: int, hi: int) -> np.ndarray:
        rows = self.store.query_series(
            self.vehicle_id, lo, hi, ["stamp_ns"], estimator=self.spec.name
        )
        return rows["stamp_ns"]

    def span(self) -> tuple[int, int] | None:
        """Stamps of the first and the last stored row in the range (None: no rows).

        Found by probing inward from each end with windows of 1 s, 2 s, 4 s, … (at most one
        query chunk): a range whose data reaches its ends costs two small reads; hours without
        rows before or after the data cost a few index look-ups more."""
        chunk = self.limits.query_chunk_ns
        lo, hi = self.tr.start_ns, self.tr.end_ns
        first = None
        t, w = lo, _PROBE_NS
        while t < hi:
            t_next = min(t + w, hi)
            stamps = self._stamps(t, t_next)
            if stamps.shape[0]:
                first = int(stamps[0])
                break
            t, w = t_next, min(2 * w, chunk)
        if first is None:
            return None
        t, w = hi, _PROBE_NS
        while t > first:  # ends at the latest on the row at ``first``
            t_prev = max(t - w, first)
            stamps = self._stamps(t_prev, t)
            if stamps.shape[0]:
                return first, int(stamps[-1])
            t, w = t_prev, min(2 * w, chunk)
        return None  # the row at ``first`` went in between (retention)

    def _read(self, lo: int, hi: int, chunk_ns: int) -> Iterator[np.ndarray]:
        t = lo
        while t < hi:
            t_next = min(t + chunk_ns, hi)
            rows = self.store.query_series(
                self.vehicle_id, t, t_next, self.fields, estimator=self.spec.name
            )
            if rows.shape[0]:
                self.stored_rows += rows.shape[0]
                if self.first_ns is None:
                    self.first_ns = int(rows["stamp_ns"][0])
                self.last_ns = int(rows["stamp_ns"][-1])
                yield rows
            t = t_next

    def chunks(self) -> Iterator[np.ndarray]:
        """Output rows, chunk by chunk (full rate until the row count passes ``max_points``)."""
        if self.max_points < 2:
            yield from self._read(self.tr.start_ns, self.tr.end_ns, self.limits.query_chunk_ns)
            return
        span = self.span()
        if span is None:
            return
        first, last = span
        per_bucket = 2 if self.decimation == "minmax" else 1
        width = bucket_width_ns(first, last + 1, self.max_points, rows_per_bucket=per_bucket)
        self.width_ns = width
        chunk_ns = max(self.limits.query_chunk_ns // width, 1) * width

        def decimate(rows: np.ndarray) -> np.ndarray:
            if self.decimation == "minmax":
                return downsample_minmax(rows, first, width)
            return thin_first(rows, first, width)

        held: list[np.ndarray] = []
        n_held = 0
        # rows stored after the probe beyond ``last`` would fall outside the buckets: not read
        for rows in self._read(first, last + 1, chunk_ns):
            if self.downsampled:
                yield decimate(rows)
                continue
            held.append(rows)
            n_held += rows.shape[0]
            if n_held > self.max_points:
                self.downsampled = True
                for h in held:
                    yield decimate(h)
                held = []
        yield from held

    def collect(self, max_rows: int) -> np.ndarray:
        """All output rows in one array; :class:`RangeTooLarge` past ``max_rows``."""
        parts: list[np.ndarray] = []
        n = 0
        for rows in self.chunks():
            n += rows.shape[0]
            if n > max_rows:
                raise RangeTooLarge(
                    f"more than {max_rows} rows; set max_points, narrow the range or use format=csv"
                )
            parts.append(rows)
        if not parts:
            return self.empty()
        return np.concatenate(parts) if len(parts) > 1 else parts[0]

    def empty(self) -> np.ndarray:
        """No rows, with the reader's fields."""
        return self.spec.empty_rows(0)[self.fields]


JSON_FLOAT_DIGITS = 9
"""Significant digits of floats in JSON answers (relative precision 1e-9, far below any sensor's;
CSV and Parquet keep every bit). Shortest round-trip formatting costs three times as much."""

_FLOAT_FMT = f"%.{JSON_FLOAT_DIGITS}g"


def _json_array(col: np.ndarray) -> str:
    n = col.shape[0]
    if n == 0:
        return "[]"
    if col.dtype.kind != "f":
        return "[" + ",".join(map(str, col.tolist())) + "]"
    text = ",".join([_FLOAT_FMT] * n) % tuple(col.tolist())
    if not np.isfinite(col).all():
        text = text.replace("-inf", "null").replace("inf", "null").replace("nan", "null")
    return "[" + text + "]"


def encode_columns_json(rows: np.ndarray) -> str:
    """``{"field": [values…], …}`` of a structured array; NaN and infinities become null.

    Floats carry :data:`JSON_FLOAT_DIGITS` significant digits; integers are exact.
    """
    names = rows.dtype.names or ()
    return "{" + ",".join(f"{json.dumps(n)}:{_json_array(rows[n])}" for n in names) + "}"


def iso_times(stamps_ns: np.ndarray) -> np.ndarray:
    """ISO 8601 UTC text with nanoseconds per stamp (as ``/latest``'s ``time``), vectorised."""
    text = np.datetime_as_string(stamps_ns.astype(np.int64).view("datetime64[ns]"), unit="ns")
    return np.char.add(text, "Z")


def flag_names_column(spec: EstimatorSpec, flags: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``flags`` decoded by ``spec`` as ``(codes, names)``: ``names[codes[i]]`` is row ``i``'s
    flags set, lowest bit first, joined by ``|`` (``"GNSS_OK|SLIP_LEFT_VALID"``; ``""`` for
    none). Decoded once per distinct value, so a long series costs one ``np.unique``."""
    values, codes = np.unique(flags, return_inverse=True)
    names = np.array(["|".join(spec.flag_names(int(v))) for v in values.tolist()], dtype=object)
    return codes.reshape(-1), names


def export_names(fields: Sequence[str]) -> list[str]:
    """Columns of a CSV or Parquet export of ``fields``: ``time`` after ``stamp_ns`` and
    ``flag_names`` after ``flags``."""
    out: list[str] = []
    for name in fields:
        out.append(name)
        if name in _DERIVED:
            out.append(_DERIVED[name])
    return out


_DERIVED = {"stamp_ns": "time", "flags": "flag_names"}


def _csv_columns(rows: np.ndarray, fields: Sequence[str], spec: EstimatorSpec) -> list[list]:
    """Per export column (:func:`export_names`) its values as Python objects, NaN as None."""
    cols: list[list] = []
    for name in fields:
        col = rows[name]
        values = col.tolist()
        if col.dtype.kind == "f":
            bad = ~np.isfinite(col)
            if bad.any():
                for i in np.flatnonzero(bad).tolist():
                    values[i] = None
        cols.append(values)
        if name == "stamp_ns":
            cols.append(iso_times(col).tolist())
        elif name == "flags":
            codes, names = flag_names_column(spec, col)
            cols.append(names[codes].tolist())
    return cols


def _csv_lines(reader: _Reader) -> Iterator[str]:
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(export_names(reader.fields))
    yield buf.getvalue()
    for rows in reader.chunks():
        cols = _csv_columns(rows, reader.fields, reader.spec)
        for i in range(0, rows.shape[0], _CSV_ROWS_PER_WRITE):
            buf.seek(0)
            buf.truncate()
            writer.writerows(zip(*(c[i : i + _CSV_ROWS_PER_WRITE] for c in cols), strict=True))
            yield buf.getvalue()


_TIME_META = {
    "unit": "",
    "label": "Time (UTC)",
    "description": "stamp_ns as a UTC timestamp (nanoseconds)",
}
_FLAG_NAMES_META = {
    "unit": "",
    "label": "Flag names",
    "description": "names of the flags set, lowest bit first, joined by '|'",
}


def _meta(field: FieldSpec) -> dict[str, str]:
    return {"unit": field.unit, "label": field.label, "description": field.description}


def _parquet_columns(rows: np.ndarray, spec: EstimatorSpec) -> Iterator[tuple[pa.Field, pa.Array]]:
    """Per export column its Arrow field (the spec's unit, label and description as field
    metadata) and values; NaN becomes null, ``time`` a UTC timestamp, ``flag_names`` a
    dictionary of the distinct flag sets."""
    for name in rows.dtype.names or ():
        values = pa.array(rows[name], from_pandas=True)
        yield pa.field(name, values.type, metadata=_meta(spec.field(name))), values
        if name == "stamp_ns":
            t = pa.array(rows[name].view("datetime64[ns]"), type=pa.timestamp("ns", tz="UTC"))
            yield pa.field("time", t.type, metadata=_TIME_META), t
        elif name == "flags":
            codes, names = flag_names_column(spec, rows[name])
            d = pa.DictionaryArray.from_arrays(
                pa.array(codes, type=pa.int32()), pa.array(names, type=pa.string())
            )
            yield pa.field("flag_names", d.type, metadata=_FLAG_NAMES_META), d


def _parquet_bytes(rows: np.ndarray, spec: EstimatorSpec, vehicle_id: str, tr: TimeRange) -> bytes:
    """The rows as one Parquet file; its schema metadata names the vehicle, the estimator,
    the range and the flag bits (JSON ``{name: bit}``)."""
    fields, arrays = zip(*_parquet_columns(rows, spec), strict=True)
    meta = {
        "vehicle_id": vehicle_id,
        "estimator": spec.name,
        "start_ns": str(tr.start_ns),
        "end_ns": str(tr.end_ns),
        "flag_bits": json.dumps({f.name: f.bit for f in spec.flags}),
    }
    table = pa.Table.from_arrays(list(arrays), schema=pa.schema(list(fields), metadata=meta))
    sink = io.BytesIO()
    pq.write_table(table, sink)
    return sink.getvalue()


GEOJSON_MEDIA_TYPE = "application/geo+json"


def _position_fields(spec: EstimatorSpec) -> tuple[PositionChannel, list[str]]:
    """The spec's position channel and its east, north (and up) fields; 400 without one."""
    p = spec.position
    if p is None:
        raise BadRequest(
            f"estimator {spec.name!r} gives no position: format=geojson needs one "
            "(use json, csv or parquet)"
        )
    return p, [f for f in (p.east_field, p.north_field, p.up_field) if f is not None]


def _geojson(
    vehicle_id: str,
    rows: np.ndarray,
    names: Sequence[str],
    position: PositionChannel,
    anchor: Anchor | None,
) -> str:
    """A FeatureCollection of one Point (WGS 84 longitude, latitude, ellipsoidal height) per
    row with a position (``position``'s fields), carrying the row's ``names`` fields (NaN as
    null); no features while the vehicle has no anchor (no fix yet)."""
    features: list[dict[str, object]] = []
    east, north = rows[position.east_field], rows[position.north_field]
    placed = np.isfinite(east) & np.isfinite(north)
    if anchor is not None and placed.any():
        rows = rows[placed]
        up = np.zeros(rows.shape[0])
        if position.up_field is not None:
            up = np.nan_to_num(rows[position.up_field], nan=0.0)
        lat, lon, h = EnuFrame(*anchor).to_geodetic(
            rows[position.east_field], rows[position.north_field], up
        )
        cols = {n: rows[n].tolist() for n in names}
        for i, (x, y, z) in enumerate(zip(lon.tolist(), lat.tolist(), h.tolist(), strict=True)):
            props = {
                n: (None if isinstance(v[i], float) and not math.isfinite(v[i]) else v[i])
                for n, v in cols.items()
            }
            features.append(
                {
                    "type": "Feature",
                    "geometry": {"type": "Point", "coordinates": [x, y, round(z, 3)]},
                    "properties": props,
                }
            )
    return json.dumps(
        {
            "type": "FeatureCollection",
            "vehicle_id": vehicle_id,
            "anchor": AnchorPublic.as_json(anchor),
            "features": features,
        }
    )


def export_filename(vehicle_id: str, tr: TimeRange, ext: str) -> str:
    """``<vehicle id, safe characters only>_<start_ns>_<end_ns>.<ext>`` for a download."""
    safe = re.sub(r"[^A-Za-z0-9_.-]", "_", vehicle_id)[:64] or "vehicle"
    return f"{safe}_{tr.start_ns}_{tr.end_ns}.{ext}"


SeriesFieldsQuery = Annotated[
    str | None,
    Query(
        description="Comma-separated fields of the estimator (default: all); `stamp_ns` is "
        "always included; a field the estimator does not have is a 422 naming it. "
        "Fields by estimator:\n\n" + fields_doc(),
        examples=["stamp_ns,flags"],
        max_length=2000,
    ),
]
MaxPointsQuery = Annotated[
    int | None,
    Query(
        ge=0,
        le=1_000_000,
        description="Decimate to at most this many rows; 0 or absent: full rate; 1 is refused.",
    ),
]
DecimationQuery = Annotated[
    Decimation | None,
    Query(
        description="How `max_points` decimates: `minmax` (default; per time bucket the min "
        "and max of each field, for charts) or `first` (per time bucket its first row, whole; "
        "for positions). `format=geojson` always thins with `first`.",
    ),
]


_SERIES_DESCRIPTION = (
    "Rows of one estimator (`estimator`, default the vehicle's primary) with "
    "`start <= stamp < end`, ordered by time; the fields are that estimator's "
    "(`GET /api/v1/estimators`):\n\n" + fields_doc() + "\n\n"
    "**Decimation**: with `max_points` >= 2 and more rows than that in the range, the "
    "span of the data itself, from its first to its last stored row in the range (not the "
    "requested range: a short drive in a long range keeps its detail), is cut into equal "
    "time buckets anchored at the first row, and each bucket gives:\n\n"
    "* `decimation=minmax` (default; for charts): `max_points // 2` buckets, each giving at "
    "most two rows holding, per field, the bucket's minimum and maximum in the order they "
    "occurred (NaN ignored); `stamp_ns` of the two rows is the bucket's first and last stamp "
    "and `flags` the OR of the bucket's flags. Spikes therefore survive, but one decimated "
    "row mixes values of several estimates (an east and a north of different rows "
    "are no position the vehicle had).\n"
    "* `decimation=first` (for positions and anything read row by row): `max_points` "
    "buckets, each giving its first row, whole: every row returned is a stored row.\n\n"
    "With `max_points` 0 or absent the series is full rate. A 12 h drive at 10 Hz (432 000 "
    "rows) with `max_points=2000` gives 43.2 s buckets with `minmax` and 21.6 s buckets with "
    "`first`. The JSON answer says what it holds: `rows` returned of `stored_rows` stored in "
    "the range, `first_ns` and `last_ns` of the stored rows, and `bucket_ns` (0 at full "
    "rate).\n\n"
    "**Map** (`format=geojson`, for an estimator with a `position`; 400 `bad_request` "
    "otherwise): a FeatureCollection with one Point per row that has a position, in WGS 84 "
    "(longitude, latitude, ellipsoidal height) from the vehicle's anchor and the row's "
    "position fields (east, north, up of the spec's `position`); the properties are the "
    "fields asked for. With `max_points` the rows are thinned as with `decimation=first` "
    "(a position is never mixed from several rows; `decimation=minmax` is refused). No "
    "features before the vehicle's first fix. The collection's `anchor` is that origin by "
    "name (`lat_deg`, `lon_deg`, `height_m`, as in the vehicle's answer), null before it."
    "\n\n"
    "**Exports** (`format=csv` and `parquet`): beside `stamp_ns` a `time` column, UTC "
    "(CSV: ISO 8601 text with nanoseconds, `2024-05-01T12:00:00.000000000Z`, as `/latest`; "
    "Parquet: a UTC timestamp in ns), and beside `flags` a `flag_names` column, the names "
    "of the flags set by the estimator's spec, lowest bit first, joined by `|` "
    "(`GNSS_OK|SLIP_LEFT_VALID`; empty for none). The Parquet schema metadata holds "
    "`vehicle_id`, `estimator`, `start_ns`, `end_ns` and `flag_bits` (JSON `{name: bit}`), "
    "and each column's field metadata its `unit`, `label` and `description` from the "
    "spec. JSON carries `units` (per field) and `flag_bits` in its head instead of extra "
    "columns.\n\n"
    "**Precision**: JSON floats carry 9 significant digits; CSV and Parquet are exact.\n\n"
    "**Limits** (server defaults): the range may span at most 31 days; a JSON or Parquet "
    "answer at most 200 000 rows (400 `range_too_large` otherwise); CSV is streamed."
)


@router.get(
    "/{vehicle_id}/series",
    response_model=SeriesPublic,
    responses={
        200: {
            "description": "The series: JSON columns, CSV (header row, empty cell for NaN) or "
            "Parquet (null for NaN).",
            "content": {
                "text/csv": {"schema": {"type": "string"}},
                PARQUET_MEDIA_TYPE: {"schema": {"type": "string", "format": "binary"}},
                GEOJSON_MEDIA_TYPE: {"schema": {"type": "object"}},
            },
        },
        **error_responses(400, 404, 422),
    },
    summary="Estimate series of one vehicle's estimator",
    description=_SERIES_DESCRIPTION,
)
def get_series(
    vehicle: VehicleDep,
    spec: EstimatorDep,
    tr: TimeRangeDep,
    store: StoreDep,
    limits: LimitsDep,
    fields: SeriesFieldsQuery = None,
    max_points: MaxPointsQuery = None,
    decimation: DecimationQuery = None,
    format: Annotated[SeriesFormat, Query(description="Answer format")] = "json",
) -> Response:
    names = _parse_fields(fields, spec)
    points = _checked_points(max_points, limits)
    tr.check_span(limits.series_max_range_ns)
    vehicle_id = vehicle.vehicle_id
    if format == "geojson":  # whole rows: a position is one row's east, north and up
        if decimation == "minmax":
            raise Unprocessable("format=geojson thins to whole rows: decimation=minmax is refused")
        return _geojson_answer(store, vehicle_id, spec, tr, names, points, limits)
    how: Decimation = decimation or "minmax"
    reader = _Reader(store, vehicle_id, spec, tr, names, points, limits, how)

    if format == "csv":
        return StreamingResponse(
            _csv_lines(reader),
            media_type="text/csv; charset=utf-8",
            headers=_attachment(export_filename(vehicle_id, tr, "csv")),
        )
    rows = reader.collect(limits.series_max_rows)
    if format == "parquet":
        return Response(
            _parquet_bytes(rows, spec, vehicle_id, tr),
            media_type=PARQUET_MEDIA_TYPE,
            headers=_attachment(export_filename(vehicle_id, tr, "parquet")),
        )
    return _json_answer(vehicle_id, spec, tr, names, points, how, reader, rows)


def _checked_points(max_points: int | None, limits: ApiLimits) -> int:
    """``max_points`` (0: full rate); 422 for 1 or above the limit."""
    points = max_points or 0
    if points == 1:
        raise Unprocessable("max_points must be 0 (full rate) or at least 2")
    if points > limits.series_max_points:
        raise Unprocessable(f"max_points must be at most {limits.series_max_points}")
    return points


def _attachment(filename: str) -> dict[str, str]:
    """The headers of a download named ``filename``."""
    return {"Content-Disposition": f'attachment; filename="{filename}"'}


def _geojson_answer(
    store: Store,
    vehicle_id: str,
    spec: EstimatorSpec,
    tr: TimeRange,
    names: list[str],
    points: int,
    limits: ApiLimits,
) -> Response:
    """The series as GeoJSON: whole rows (thinned to their first), placed by the spec's
    position in the vehicle's anchor frame."""
    position, placed_by = _position_fields(spec)
    read = [*names, *(f for f in placed_by if f not in names)]
    reader = _Reader(store, vehicle_id, spec, tr, read, points, limits, "first")
    rows = reader.collect(limits.series_max_rows)
    anchor = store.get_anchors(vehicle_id).get(vehicle_id)
    return Response(
        _geojson(vehicle_id, rows, names, position, anchor),
        media_type=GEOJSON_MEDIA_TYPE,
    )


def _json_answer(
    vehicle_id: str,
    spec: EstimatorSpec,
    tr: TimeRange,
    names: list[str],
    points: int,
    how: Decimation,
    reader: _Reader,
    rows: np.ndarray,
) -> Response:
    """The series as JSON: what was read and how, then the columns."""
    head = {
        "vehicle_id": vehicle_id,
        "estimator": spec.name,
        "start_ns": tr.start_ns,
        "end_ns": tr.end_ns,
        "fields": names,
        "units": {n: spec.field(n).unit for n in names},
        "flag_bits": {f.name: f.bit for f in spec.flags},
        "max_points": points,
        "decimation": how,
        "downsampled": reader.downsampled,
        "bucket_ns": reader.width_ns if reader.downsampled else 0,
        "rows": int(rows.shape[0]),
        "stored_rows": reader.stored_rows,
        "first_ns": reader.first_ns,
        "last_ns": reader.last_ns,
    }
    body = json.dumps(head)[:-1] + ',"columns":' + encode_columns_json(rows) + "}"
    return Response(body, media_type="application/json")
