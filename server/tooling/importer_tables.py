"""CSV and Parquet logs for ``slipfleet import`` (the column mapping: ``docs/import.md``).

One table holds every stream, one sample a row: a ``stream`` column says which (``imu``,
``gnss``, ``wheels``), a time column (``stamp_ns``: integer UTC nanoseconds, or ``time``: ISO
8601 text with an offset) says when, and each stream reads its own columns (:data:`COLUMNS`;
optional ones may be missing or empty). A mapping file (``--map``, TOML or JSON) renames the
columns and the stream names for a table of another system::

    [columns]            # product name = the table's column
    stamp_ns = "t_ns"
    accel_x_mps2 = "ax"
    [streams]            # product stream = the table's value
    imu = "IMU"

A value that is not a number, an empty required cell or an unknown stream is a LogError naming
the row (1 = the first data row) and the column.
"""

from __future__ import annotations

import csv
import json
import math
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from estimator.types import GnssFix, GnssSample
from server.timeparse import TimeParseError, parse_time_ns
from server.tooling.importer_log import ImportedLog, LogBuilder, LogError

__all__ = ["COLUMNS", "OPTIONAL", "ColumnMap", "read_table"]

#: Each stream's columns, in the product's units and body frame (X right, Y forward, Z up).
COLUMNS: Mapping[str, tuple[str, ...]] = {
    "imu": (
        "accel_x_mps2",
        "accel_y_mps2",
        "accel_z_mps2",
        "gyro_x_radps",
        "gyro_y_radps",
        "gyro_z_radps",
    ),
    "gnss": (
        "lat_deg",
        "lon_deg",
        "height_m",
        "vel_east_mps",
        "vel_north_mps",
        "vel_up_mps",
        "heading_rad",
        "pitch_rad",
        "roll_rad",
        "fix",
        "vel_std_mps",
    ),
    "wheels": ("omega_left_radps", "omega_right_radps"),
}
#: Columns that may be missing or empty, with the value they then take.
OPTIONAL: Mapping[str, float] = {
    "heading_rad": math.nan,
    "pitch_rad": math.nan,
    "roll_rad": math.nan,
    "fix": float(GnssFix.RTK_FIXED),
    "vel_std_mps": math.nan,
}


@dataclass(frozen=True)
class ColumnMap:
    """Product column and stream names → the table's (identity where not given)."""

    columns: Mapping[str, str] = field(default_factory=dict)
    streams: Mapping[str, str] = field(default_factory=dict)

    @classmethod
    def load(cls, path: Path | None) -> ColumnMap:
        """The mapping of a TOML or JSON file (``[columns]``, ``[streams]``); none: identity."""
        if path is None:
            return cls()
        try:
            text = path.read_text()
            data = tomllib.loads(text) if path.suffix != ".json" else json.loads(text)
        except (OSError, ValueError) as exc:
            raise LogError(f"cannot read the column map {path}: {exc}") from None
        known = {"stamp_ns", "time", "stream", *(c for cols in COLUMNS.values() for c in cols)}
        columns = {str(k): str(v) for k, v in dict(data.get("columns", {})).items()}
        unknown = sorted(set(columns) - known)
        if unknown:
            raise LogError(f"{path}: unknown column name(s) {unknown}; known: {sorted(known)}")
        streams = {str(k): str(v) for k, v in dict(data.get("streams", {})).items()}
        if set(streams) - set(COLUMNS):
            raise LogError(f"{path}: [streams] names one of {sorted(COLUMNS)}")
        return cls(columns, streams)

    def column(self, name: str) -> str:
        return self.columns.get(name, name)

    def stream_of(self) -> dict[str, str]:
        """The table's stream value → product stream."""
        return {self.streams.get(s, s): s for s in COLUMNS}


def _table(path: Path, fmt: str) -> dict[str, list[Any]]:
    """The file's columns as lists (CSV: every cell as text, empty cells None)."""
    import pyarrow as pa
    import pyarrow.csv as pacsv
    import pyarrow.parquet as pq

    try:
        if fmt == "parquet":
            table = pq.read_table(path)
        else:
            with open(path, newline="") as fh:
                header = next(csv.reader(fh), [])
            text = pacsv.ConvertOptions(
                column_types=dict.fromkeys(header, pa.string()), strings_can_be_null=True
            )
            table = pacsv.read_csv(path, convert_options=text)
    except (OSError, UnicodeDecodeError, pa.ArrowException) as exc:
        raise LogError(f"cannot read {path} as {fmt}: {exc}") from None
    return {name: table.column(name).to_pylist() for name in table.column_names}


def _number(value: Any, row: int, column: str) -> float:
    if value is None or value == "":
        raise LogError(f"row {row}: {column} is empty")
    try:
        return float(value)
    except (TypeError, ValueError):
        raise LogError(f"row {row}: {column} {value!r} is not a number") from None


def _stamp_reader(cols: dict[str, list[Any]], cmap: ColumnMap) -> Callable[[int], int]:
    """Row index → stamp in ns, from ``stamp_ns`` or else ISO 8601 ``time``."""
    stamp_col, time_col = cmap.column("stamp_ns"), cmap.column("time")
    if stamp_col in cols:
        values = cols[stamp_col]

        def stamp(i: int) -> int:
            v = values[i]
            try:
                return int(v) if isinstance(v, int) else int(str(v).strip())
            except ValueError:
                raise LogError(f"row {i + 1}: {stamp_col} {v!r} is not integer ns") from None

        return stamp
    if time_col in cols:
        texts = cols[time_col]

        def parsed(i: int) -> int:
            v = texts[i]
            if hasattr(v, "timestamp"):  # a Parquet timestamp column
                raise LogError(f"{time_col}: give ISO 8601 text or an integer stamp_ns column")
            try:
                return parse_time_ns(str(v))
            except TimeParseError as exc:
                raise LogError(f"row {i + 1}: {time_col} {v!r}: {exc}") from None

        return parsed
    raise LogError(f"no time column: {stamp_col!r} (integer ns) or {time_col!r} (ISO 8601)")


def _values(cols: dict[str, list[Any]], cmap: ColumnMap, stream: str, i: int) -> list[float]:
    out = []
    for name in COLUMNS[stream]:
        col = cmap.column(name)
        value = cols[col][i] if col in cols else None
        if name in OPTIONAL and (value is None or value == ""):
            out.append(OPTIONAL[name])
        elif col not in cols:
            raise LogError(f"row {i + 1}: a {stream} row needs the column {col!r}")
        else:
            out.append(_number(value, i + 1, col))
    return out


def _gnss(stamp_ns: int, v: list[float], row: int) -> GnssSample:
    lat, lon, h, ve, vn, vu, heading, pitch, roll, fix, vel_std = v
    try:
        fix_type = GnssFix(int(fix))
    except ValueError:
        raise LogError(
            f"row {row}: fix {fix:g} is not one of {[int(f) for f in GnssFix]}"
        ) from None
    return GnssSample(stamp_ns, (ve, vn, vu), heading, pitch, roll, lat, lon, h, fix_type, vel_std)


def read_table(path: Path, fmt: str, cmap: ColumnMap) -> ImportedLog:
    """The samples of a CSV or Parquet log (``fmt``: ``csv`` or ``parquet``)."""
    cols = _table(path, fmt)
    stream_col = cmap.column("stream")
    if stream_col not in cols:
        raise LogError(f"{path}: no {stream_col!r} column (imu, gnss or wheels per row)")
    stamp_of = _stamp_reader(cols, cmap)
    stream_of = cmap.stream_of()
    builder = LogBuilder()
    for i, raw in enumerate(cols[stream_col]):
        stream = stream_of.get(str(raw).strip())
        if stream is None:
            raise LogError(f"row {i + 1}: {stream_col} {raw!r} is not one of {sorted(stream_of)}")
        stamp, v, where = stamp_of(i), _values(cols, cmap, stream, i), f"row {i + 1}"
        if stream == "imu":
            builder.add_imu(stamp, (v[0], v[1], v[2]), (v[3], v[4], v[5]), where)
        elif stream == "wheels":
            builder.add_wheels(stamp, v[0], v[1], where)
        else:
            builder.add_gnss(_gnss(stamp, v, i + 1), where)
    return builder.build()
