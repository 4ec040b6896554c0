"""PostgreSQL store (psycopg 3), selected by a ``postgresql://`` URL.

Connections come from a small internal pool: any thread checks one out for a statement or a
transaction and gives it back; a connection that broke (server restart, network) is discarded
and the next use reconnects, so an outage surfaces as :class:`StorageError` and heals by itself.

Bulk paths avoid per-row Python objects:

* writes build the binary ``COPY`` stream with numpy (big-endian fields and length words laid out
  as a structured array), copy it into a temporary staging table, then
  ``INSERT … SELECT … ON CONFLICT (vkey, stamp_ns) DO NOTHING`` (idempotent replays);
* series reads run ``COPY (SELECT …) TO STDOUT (FORMAT BINARY)`` and view the stream as a
  structured array (no NULLs are possible: every column is ``NOT NULL``, NaN is a float value).
"""

from __future__ import annotations

import contextlib
import threading
import weakref
from collections.abc import Iterable, Iterator, Mapping, Sequence
from typing import Any

import numpy as np
import psycopg
from psycopg.types.json import Jsonb

from estimator.spec import EstimatorSpec
from estimator.types import EstimateBatch
from server.storage import migrations
from server.storage._columns import (
    DEFAULT_ESTIMATOR,
    SpecTables,
    as_batches,
    fields_dtype,
    registered_rows,
    select_fields,
    spec_fields,
)
from server.storage._queries import SharedQueries
from server.storage.base import (
    Anchor,
    StorageDataError,
    StorageError,
    VehicleRecord,
)

__all__ = ["PostgresStore"]

_COPY_SIGNATURE = b"PGCOPY\n\xff\r\n\x00"
_COPY_HEADER = _COPY_SIGNATURE + b"\x00\x00\x00\x00" + b"\x00\x00\x00\x00"  # flags, ext length
_COPY_TRAILER = b"\xff\xff"
_WIDTH = {"f8": 8, "i8": 8, "i4": 4}


def _copy_dtype(columns: Sequence[tuple[str, str]]) -> np.dtype:
    """Binary COPY tuple layout: int16 field count, then per field int32 length + value."""
    parts: list[tuple[str, str]] = [("_nfields", ">i2")]
    for name, kind in columns:
        parts += [(f"_len_{name}", ">i4"), (name, ">" + kind)]
    return np.dtype(parts)


class _PgTable:
    """One estimator's table (``vkey`` and the spec's fields as columns, in field order), its
    per-connection temporary staging table and its binary COPY row layout."""

    def __init__(self, spec: EstimatorSpec, table: str) -> None:
        self.spec = spec
        self.table = table
        self.stage = f"{table}_stage"
        columns = (("vkey", "i4"), *spec_fields(spec))
        self.copy_dtype = _copy_dtype(columns)
        # a COPY tuple with its field count and every field's length set (the values are
        # filled per batch): one fill per batch instead of an assignment per field
        self.copy_template = np.zeros((), dtype=self.copy_dtype)
        self.copy_template["_nfields"] = len(columns)
        for name, kind in columns:
            self.copy_template[f"_len_{name}"] = _WIDTH[kind]


def _wrap(exc: psycopg.Error) -> StorageError:
    # Only errors about the data itself are final; everything else (connection, privileges,
    # missing table) may heal, so the writer retries it.
    if isinstance(exc, psycopg.IntegrityError | psycopg.DataError):
        return StorageDataError(f"postgresql: {exc}")
    return StorageError(f"postgresql: {exc}")


class _Pool:
    """Idle connections kept for reuse; broken ones are dropped."""

    def __init__(self, url: str, max_idle: int, connect_timeout_s: float) -> None:
        self._url = url
        self._max_idle = max_idle
        self._connect_timeout_s = connect_timeout_s
        self._idle: list[psycopg.Connection[Any]] = []
        self._lock = threading.Lock()
        self._closed = False

    def _connect(self) -> psycopg.Connection[Any]:
        return psycopg.connect(
            self._url,
            autocommit=True,  # transactions are explicit: `with conn.transaction()`
            connect_timeout=max(1, round(self._connect_timeout_s)),
            application_name="slipfleet",
        )

    @contextlib.contextmanager
    def connection(self) -> Iterator[psycopg.Connection[Any]]:
        with self._lock:
            if self._closed:
                raise StorageError("postgresql: store is closed")
            conn = self._idle.pop() if self._idle else None
        try:
            if conn is None:
                conn = self._connect()
            yield conn
        except psycopg.Error as exc:
            if conn is not None and (conn.broken or conn.closed):
                conn.close()
                conn = None
            raise _wrap(exc) from exc
        except BaseException:
            if conn is not None:
                conn.close()
                conn = None
            raise
        finally:
            if conn is not None:
                keep = False
                with self._lock:
                    if not self._closed and not conn.closed and len(self._idle) < self._max_idle:
                        self._idle.append(conn)
                        keep = True
                if not keep:
                    conn.close()

    def close(self) -> None:
        with self._lock:
            self._closed = True
            idle, self._idle = self._idle, []
        for conn in idle:
            conn.close()


class PostgresStore(SharedQueries):
    """:class:`server.storage.base.Store` on PostgreSQL.

    Parameters
    ----------
    url : str
        ``postgresql://user:password@host:port/dbname`` (take it from ``StorageSettings.url``).
    max_idle : int
        Connections kept open between uses (one per concurrently reading thread is plenty).
    connect_timeout_s : float
        Give up connecting after this long (rounded to whole seconds, at least 1).
    """

    dialect = "postgresql"

    def __init__(
        self,
        url: str,
        *,
        max_idle: int = 8,
        connect_timeout_s: float = 5.0,
        specs: Iterable[EstimatorSpec] | None = None,
    ) -> None:
        self._pool = _Pool(url, max_idle, connect_timeout_s)
        # connections holding the staging tables of every served estimator
        self._staged: weakref.WeakSet[psycopg.Connection[Any]] = weakref.WeakSet()
        # the served specs' tables (read from the database on first use, again after migrate)
        self._tables = SpecTables(self.dialect, specs, _PgTable, lambda sql: self._read(sql, ()))

    # ------------------------------------------------------------------ lifecycle

    def migrate(self) -> int:
        with self._pool.connection() as conn, conn.transaction():
            conn.execute("SELECT pg_advisory_xact_lock(%s)", (migrations.ADVISORY_LOCK_KEY,))

            def execute(sql: str, params: tuple[Any, ...]) -> list[tuple[Any, ...]]:
                cur = conn.execute(sql.encode(), params)  # bytes: no client-side formatting
                return cur.fetchall() if cur.description is not None else []

            version = migrations.migrate_to_latest(execute, self.dialect)
        self._tables.reload()  # refuses a spec its table no longer fits, at start
        return version

    def close(self) -> None:
        self._pool.close()

    def ping(self) -> bool:
        try:
            with self._pool.connection() as conn:
                row = conn.execute("SELECT 1").fetchone()
            return row == (1,)
        except StorageError:
            return False

    def maintain(self, *, everything: bool = False) -> bool:
        """Nothing to do: rows go straight to their tables (no staging as in SQLite)."""
        return False

    def schema_version(self) -> int:
        """Highest applied migration (0 on an empty database)."""
        with self._pool.connection() as conn:
            row = conn.execute("SELECT to_regclass('schema_version') IS NOT NULL").fetchone()
            if not row or not row[0]:
                return 0
            row = conn.execute("SELECT coalesce(max(version), 0) FROM schema_version").fetchone()
        return int(row[0]) if row else 0

    def table_columns(self, table: str) -> list[str]:
        """Column names of ``table`` in order (empty when it does not exist)."""
        rows = self._read(
            "SELECT column_name FROM information_schema.columns "
            "WHERE table_schema = current_schema() AND table_name = %s ORDER BY ordinal_position",
            (table,),
        )
        return [str(r[0]) for r in rows]

    # ------------------------------------------------------------------ vehicles

    param_marker = "%s"

    @staticmethod
    def _config_of(raw: Any) -> dict[str, Any]:
        return dict(raw)

    def upsert_vehicle(self, vehicle_id: str, config: dict[str, Any], now_ns: int) -> VehicleRecord:
        cols = "vehicle_id, config, created_ns, updated_ns"
        with self._pool.connection() as conn, conn.transaction():
            # UPDATE first: an INSERT … ON CONFLICT would burn an identity value on every call.
            row = conn.execute(
                f"UPDATE vehicles SET config = %s, updated_ns = %s WHERE vehicle_id = %s "
                f"RETURNING {cols}",
                (Jsonb(config), int(now_ns), vehicle_id),
            ).fetchone()
            if row is None:
                row = conn.execute(
                    f"INSERT INTO vehicles ({cols}) VALUES (%s, %s, %s, %s) "
                    "ON CONFLICT (vehicle_id) DO UPDATE SET "
                    f"config = excluded.config, updated_ns = excluded.updated_ns RETURNING {cols}",
                    (vehicle_id, Jsonb(config), int(now_ns), int(now_ns)),
                ).fetchone()
        assert row is not None
        return self._record(row)

    def delete_vehicle(self, vehicle_id: str) -> bool:
        with self._pool.connection() as conn, conn.transaction():
            conn.execute("DELETE FROM ingest_counters WHERE vehicle_id = %s", (vehicle_id,))
            conn.execute("DELETE FROM raw_packets WHERE vehicle_id = %s", (vehicle_id,))
            conn.execute("DELETE FROM vehicle_anchors WHERE vehicle_id = %s", (vehicle_id,))
            # the estimates of every estimator go by ON DELETE CASCADE
            cur = conn.execute("DELETE FROM vehicles WHERE vehicle_id = %s", (vehicle_id,))
            return cur.rowcount > 0

    # ------------------------------------------------------------------ estimates

    @staticmethod
    def _vkeys(conn: psycopg.Connection[Any], vehicle_ids: Sequence[str]) -> dict[str, int]:
        rows = conn.execute(
            # FOR KEY SHARE: a concurrent delete_vehicle waits for this transaction (then
            # cascades over the new rows) instead of failing our foreign-key check.
            "SELECT vehicle_id, vkey FROM vehicles WHERE vehicle_id = ANY(%s) FOR KEY SHARE",
            (list(vehicle_ids),),
        ).fetchall()
        return {str(v): int(k) for v, k in rows}

    def write_estimates(self, *batches: EstimateBatch | Sequence[tuple[str, np.ndarray]]) -> int:
        """Insert the rows of one or more estimators in one transaction; rows of unregistered
        vehicles are not written. Returns the rows inserted (duplicates and unknown vehicles
        excluded)."""
        parts = [(self._tables.of(b), b) for b in as_batches(batches)]
        if not parts:
            return 0
        with self._pool.connection() as conn:
            if conn not in self._staged:
                # Outside the write transaction, so a rolled-back write cannot undo it.
                for t in self._tables.load().values():
                    conn.execute(
                        f"CREATE TEMPORARY TABLE IF NOT EXISTS {t.stage} "
                        f"(LIKE {t.table}) ON COMMIT DELETE ROWS"
                    )
                self._staged.add(conn)
            with conn.transaction():
                keys = self._vkeys(conn, sorted({vid for _, b in parts for vid in b.ids}))
                written = 0
                for t, batch in parts:
                    payload = _copy_in_payload(t, batch, keys)
                    if payload is None:
                        continue
                    with conn.cursor() as cur:
                        with cur.copy(f"COPY {t.stage} FROM STDIN (FORMAT BINARY)") as cp:
                            cp.write(payload)
                        cur.execute(
                            f"INSERT INTO {t.table} SELECT * FROM {t.stage} "
                            "ON CONFLICT (vkey, stamp_ns) DO NOTHING"
                        )
                        written += max(cur.rowcount, 0)
                return written

    def query_series(
        self,
        vehicle_id: str,
        start_ns: int,
        end_ns: int,
        fields: Sequence[str] | None = None,
        estimator: str = DEFAULT_ESTIMATOR,
    ) -> np.ndarray:
        t = self._tables.served(estimator)
        names = select_fields(t.spec, fields)
        wire = _copy_dtype([(n, t.spec.field(n).kind) for n in names])
        chunks = bytearray()
        with (
            self._pool.connection() as conn,
            conn.cursor() as cur,
            cur.copy(
                f"COPY (SELECT {', '.join(names)} FROM {t.table} "
                "WHERE vkey = (SELECT vkey FROM vehicles WHERE vehicle_id = %s) "
                "AND stamp_ns >= %s AND stamp_ns < %s ORDER BY stamp_ns) "
                "TO STDOUT (FORMAT BINARY)",
                (vehicle_id, int(start_ns), int(end_ns)),
            ) as cp,
        ):
            for data in cp:
                chunks += data
        return _decode_copy(bytes(chunks), wire, fields_dtype(t.spec, names))

    def _read(self, sql: str, params: Sequence[Any] = ()) -> list[Any]:
        with self._pool.connection() as conn:
            return conn.execute(sql, params).fetchall()

    @contextlib.contextmanager
    def _write(self) -> Iterator[psycopg.Connection[Any]]:
        with self._pool.connection() as conn, conn.transaction():
            yield conn

    def latest(self, vehicle_id: str, estimator: str = DEFAULT_ESTIMATOR) -> np.ndarray | None:
        t = self._tables.served(estimator)
        rows = self._read(
            f"SELECT {', '.join(t.spec.field_names)} FROM {t.table} "
            "WHERE vkey = (SELECT vkey FROM vehicles WHERE vehicle_id = %s) "
            "ORDER BY stamp_ns DESC LIMIT 1",
            (vehicle_id,),
        )
        if not rows:
            return None
        return np.array(rows, dtype=t.spec.dtype).reshape(())

    def latest_all(self, estimator: str = DEFAULT_ESTIMATOR) -> dict[str, np.ndarray]:
        t = self._tables.served(estimator)
        rows = self._read(
            f"SELECT v.vehicle_id, {', '.join('e.' + n for n in t.spec.field_names)} "
            f"FROM vehicles v JOIN {t.table} e ON e.vkey = v.vkey "
            f"AND e.stamp_ns = (SELECT max(stamp_ns) FROM {t.table} WHERE vkey = v.vkey)",
            (),
        )
        return {r[0]: np.array([tuple(r[1:])], dtype=t.spec.dtype).reshape(()) for r in rows}

    def estimators_with_rows(self, vehicle_id: str) -> list[str]:
        tables = self._tables.load()
        if not tables:
            return []
        exists = " UNION ALL ".join(
            f"SELECT %s WHERE EXISTS (SELECT 1 FROM {t.table} WHERE vkey = "
            "(SELECT vkey FROM vehicles WHERE vehicle_id = %s))"
            for t in tables.values()
        )
        params = [p for name in tables for p in (name, vehicle_id)]
        found = {str(r[0]) for r in self._read(exists, params)}
        return [name for name in tables if name in found]

    def delete_older_than(self, stamp_ns: int) -> int:
        """Delete the estimates of every estimator (and raw packets) older than ``stamp_ns``;
        return estimates deleted."""
        self._tables.load()
        deleted = 0
        with self._pool.connection() as conn, conn.transaction():
            vkeys = conn.execute("SELECT vkey FROM vehicles").fetchall()
            for table in self._tables.every:
                for (vkey,) in vkeys:
                    # Per vehicle, so each delete is a primary-key range scan.
                    cur = conn.execute(
                        f"DELETE FROM {table} WHERE vkey = %s AND stamp_ns < %s",
                        (vkey, int(stamp_ns)),
                    )
                    deleted += max(cur.rowcount, 0)
            conn.execute("DELETE FROM raw_packets WHERE received_ns < %s", (int(stamp_ns),))
        return deleted

    # ------------------------------------------------------------------ counters

    def write_counters(self, counters: dict[str, dict[str, int]], now_ns: int) -> None:
        # One statement over three arrays: an upsert per counter (executemany) cost ~5x the
        # client CPU with a fleet's worth of counters (500 vehicles x 11 counters a second).
        vids: list[str] = []
        names: list[str] = []
        totals: list[int] = []
        for vid, named in counters.items():
            vids.extend([vid] * len(named))
            names.extend(named)
            totals.extend(int(total) for total in named.values())
        if not vids:
            return
        with self._pool.connection() as conn, conn.transaction():
            conn.execute(
                "INSERT INTO ingest_counters (vehicle_id, name, total, updated_ns) "
                "SELECT v, n, t, %s FROM unnest(%s::text[], %s::text[], %s::bigint[]) "
                "AS u(v, n, t) ON CONFLICT (vehicle_id, name) DO UPDATE SET "
                "total = excluded.total, updated_ns = excluded.updated_ns",
                (int(now_ns), vids, names, totals),
            )

    # ------------------------------------------------------------------ ENU anchors

    def put_anchors(self, anchors: Mapping[str, Anchor], now_ns: int) -> int:
        if not anchors:
            return 0
        vids = list(anchors)
        lat = [float(a[0]) for a in anchors.values()]
        lon = [float(a[1]) for a in anchors.values()]
        h = [float(a[2]) for a in anchors.values()]
        with self._pool.connection() as conn, conn.transaction():
            cur = conn.execute(
                "INSERT INTO vehicle_anchors (vehicle_id, lat_deg, lon_deg, height_m, set_ns) "
                "SELECT v, a, o, h, %s FROM unnest(%s::text[], %s::float8[], %s::float8[], "
                "%s::float8[]) AS u(v, a, o, h) ON CONFLICT (vehicle_id) DO NOTHING",
                (int(now_ns), vids, lat, lon, h),
            )
            return int(cur.rowcount)

    # ------------------------------------------------------------------ raw packets

    def write_raw_packets(self, packets: Sequence[tuple[str, int, str, bytes]]) -> int:
        """Store ``(vehicle_id, received_ns, key, payload)`` tuples (registered or not)."""
        if not packets:
            return 0
        params = [(vid, int(t), key, bytes(payload)) for vid, t, key, payload in packets]
        with self._pool.connection() as conn, conn.transaction(), conn.cursor() as cur:
            cur.executemany(
                "INSERT INTO raw_packets (vehicle_id, received_ns, key, payload) "
                "VALUES (%s, %s, %s, %s)",
                params,
            )
        return len(params)


def _copy_in_payload(t: _PgTable, batch: EstimateBatch, keys: Mapping[str, int]) -> bytes | None:
    """The binary COPY stream of ``t``'s rows of the registered vehicles of ``batch`` (None:
    there are none), laid out by numpy.

    Each column is laid out in one assignment over the whole batch: a transaction holds one or
    two rows of each of hundreds of vehicles, and a column assignment per vehicle cost ~20
    numpy calls per vehicle.
    """
    rows, vkeys = registered_rows(batch, keys)
    if not len(rows):
        return None
    buf = np.full(len(rows), t.copy_template)
    buf["vkey"] = vkeys
    for f in t.spec.fields:
        buf[f.name] = rows[f.name]  # byte-swapped to big-endian by the assignment
    return _COPY_HEADER + buf.tobytes() + _COPY_TRAILER


def _decode_copy(data: bytes, wire: np.dtype, out_dtype: np.dtype) -> np.ndarray:
    """View a binary COPY stream of fixed-width, non-NULL tuples as a structured array."""
    if not data:
        return np.empty(0, dtype=out_dtype)
    if not data.startswith(_COPY_SIGNATURE) or not data.endswith(_COPY_TRAILER):
        raise StorageError("postgresql: malformed binary COPY stream")
    ext_len = int.from_bytes(data[15:19], "big")
    body = memoryview(data)[19 + ext_len : len(data) - len(_COPY_TRAILER)]
    if len(body) % wire.itemsize:
        raise StorageError("postgresql: unexpected binary COPY tuple size")
    raw = np.frombuffer(body, dtype=wire)
    if len(raw) and (raw["_nfields"] != len(out_dtype.names or ())).any():
        raise StorageError("postgresql: unexpected field count in binary COPY stream")
    out = np.empty(len(raw), dtype=out_dtype)
    for name in out_dtype.names or ():
        if (raw[f"_len_{name}"] != out_dtype[name].itemsize).any():
            raise StorageError(f"postgresql: unexpected NULL or width in column {name}")
        out[name] = raw[name]
    return out
