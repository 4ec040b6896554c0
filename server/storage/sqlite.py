"""SQLite store: one file in WAL mode, the embedded default.

Connections: one per thread (``threading.local``), all registered so :meth:`SqliteStore.close`
closes every one. Reads run from any thread and do not block the writer (WAL). Writes take an
in-process lock and ``BEGIN IMMEDIATE`` (the database write lock), so the writer thread and the
occasional API write (vehicle registration) never deadlock; another process holding the lock
makes a write wait up to the busy timeout and then raise :class:`StorageError`.

Durability: ``synchronous=NORMAL`` — in WAL mode a power loss can lose the last commits but never
corrupts the file.

Rows are stored packed: table ``estimates`` holds ``(vkey, stamp_ns, packed)``, ``packed`` being
the row's ``ESTIMATE_DTYPE`` bytes (migration 6; NaN and infinities survive bit for bit). The
``sqlite3`` module creates one Python object per bound or fetched value, so

* a write binds three values per *vehicle*: its rows' bytes as one blob, their stamps as one
  JSON array, its key; one ``INSERT ... SELECT`` cuts the blob into rows inside SQLite, with no
  Python per row and the GIL released once per vehicle. The column layout of versions 1-5 bound
  28 values and the blob per row and cost ~3-6x as much per row;
* a read does not even fetch one object per row: SQLite concatenates a range's blobs into one
  (``group_concat``, at most :data:`_READ_PAGE_ROWS` rows per statement) that numpy views as a
  structured array, in one step that runs without the GIL. Reading a vehicle-hour column by
  column took ~120 ms on an idle core and several times that beside a busy Python thread.

``python -m server.bench.storage`` measures these paths against the column layout side by side.

One SQLite library per process: ``sqlite3`` uses the system's SQLite. Packages that carry their
own copy (the ADBC SQLite driver, apsw wheels) must not open this file in the same process while
the store is open, even only to read. POSIX file locks belong to the process, so neither copy
sees the other's locks: readers are invisible to this store's checkpoints, and when the other
copy closes its last connection it checkpoints and deletes the live ``-wal`` and ``-shm`` files
under this store's connections (the next connection then fails with "disk I/O error"). A
columnar read path through such a driver needs every connection of the process, writes
included, to go through that one library.
"""

from __future__ import annotations

import contextlib
import json
import sqlite3
import threading
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from estimator.types import ESTIMATE_DTYPE, concat_estimates
from server.storage import migrations
from server.storage._columns import check_rows, fields_dtype, select_fields
from server.storage.base import StorageDataError, StorageError, TokenRecord, VehicleRecord

__all__ = ["SqliteStore"]

_PAGE_SIZE_BYTES = 8192  # only takes effect when the file is created
_CACHE_KIB = 32 * 1024
_TOKEN_COLUMNS = "id, name, role, created_ns, last_used_ns, revoked_ns"


_ROW_BYTES = ESTIMATE_DTYPE.itemsize
# All rows of one vehicle in one statement: the rows' bytes as one blob and their stamps as one
# JSON array; SQLite cuts the blob (row i at byte 212 i) and walks the array, so no Python runs
# per row and the GIL is released once per vehicle, not once per row.
_INSERT_SQL = (
    "INSERT INTO estimates (vkey, stamp_ns, packed) "
    f"SELECT ?1, s.value, substr(?2, s.key * {_ROW_BYTES} + 1, {_ROW_BYTES}) "
    "FROM json_each(?3) s WHERE true "  # WHERE: the upsert clause after a SELECT needs one
    "ON CONFLICT (vkey, stamp_ns) DO NOTHING"
)
# A read concatenates at most this many rows per statement (21 MB), far below SQLite's 1 GB
# limit on one value; longer ranges take several statements in one read transaction.
_READ_PAGE_ROWS = 100_000
_VKEYS_PER_QUERY = 500  # below the oldest SQLite's 999 parameters per statement


def _unpack_one(packed: bytes) -> np.ndarray:
    """One stored row as a writable 0-d structured array."""
    if len(packed) != _ROW_BYTES:
        raise StorageDataError(f"sqlite: stored estimate row of {len(packed)} bytes")
    return np.frombuffer(packed, dtype=ESTIMATE_DTYPE).reshape(()).copy()


def _pick(rows: np.ndarray, names: Sequence[str]) -> np.ndarray:
    """The ``names`` fields of full rows as a compact structured array."""
    out = np.empty(len(rows), dtype=fields_dtype(names))
    for name in names:
        out[name] = rows[name]
    return out


def _wrap(exc: sqlite3.Error) -> StorageError:
    # Only errors about the data itself are final; locks, I/O, a read-only file may heal.
    if isinstance(exc, sqlite3.IntegrityError | sqlite3.DataError):
        return StorageDataError(f"sqlite: {exc}")
    return StorageError(f"sqlite: {exc}")


class SqliteStore:
    """:class:`server.storage.base.Store` on a SQLite file.

    Parameters
    ----------
    path : Path
        Database file; its directory is created if missing.
    busy_timeout_s : float
        How long a write waits for another process's lock before failing.
    """

    dialect = "sqlite"

    def __init__(self, path: Path | str, *, busy_timeout_s: float = 5.0) -> None:
        self.path = Path(path)
        self.busy_timeout_s = float(busy_timeout_s)
        self._local = threading.local()
        self._conns: list[sqlite3.Connection] = []
        self._conns_lock = threading.Lock()
        self._write_lock = threading.Lock()
        self._closed = False
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._conn()  # fail early on a bad path
        except OSError as exc:
            raise StorageError(f"sqlite: cannot create {self.path.parent}: {exc}") from exc

    # ------------------------------------------------------------------ connections

    def _conn(self) -> sqlite3.Connection:
        if self._closed:
            raise StorageError("sqlite: store is closed")
        conn: sqlite3.Connection | None = getattr(self._local, "conn", None)
        if conn is not None:
            return conn
        try:
            conn = sqlite3.connect(
                self.path,
                timeout=self.busy_timeout_s,
                isolation_level=None,  # we issue BEGIN/COMMIT ourselves
                check_same_thread=False,  # only so close() can close it from another thread
            )
            conn.execute(f"PRAGMA page_size = {_PAGE_SIZE_BYTES}")
            conn.execute("PRAGMA journal_mode = WAL")
            conn.execute("PRAGMA synchronous = NORMAL")
            conn.execute("PRAGMA foreign_keys = ON")
            conn.execute(f"PRAGMA cache_size = -{_CACHE_KIB}")
            conn.execute("PRAGMA temp_store = MEMORY")
        except sqlite3.Error as exc:
            raise _wrap(exc) from exc
        with self._conns_lock:
            self._conns.append(conn)
        self._local.conn = conn
        return conn

    @contextlib.contextmanager
    def _write(self) -> Iterator[sqlite3.Connection]:
        """A write transaction: in-process lock, ``BEGIN IMMEDIATE``, commit or roll back."""
        conn = self._conn()
        # Bounded like the lock of another process would be (busy timeout).
        if not self._write_lock.acquire(timeout=self.busy_timeout_s):
            raise StorageError("sqlite: database is locked (by this process)")
        try:
            try:
                conn.execute("BEGIN IMMEDIATE")
            except sqlite3.Error as exc:
                raise _wrap(exc) from exc
            try:
                yield conn
                conn.execute("COMMIT")
            except BaseException as exc:
                with contextlib.suppress(sqlite3.Error):
                    conn.execute("ROLLBACK")
                if isinstance(exc, sqlite3.Error):
                    raise _wrap(exc) from exc
                raise
        finally:
            self._write_lock.release()

    def _read(self, sql: str, params: Sequence[Any] = ()) -> list[Any]:
        try:
            return self._conn().execute(sql, params).fetchall()
        except sqlite3.Error as exc:
            raise _wrap(exc) from exc

    # ------------------------------------------------------------------ lifecycle

    def migrate(self) -> int:
        def execute(sql: str, params: tuple[Any, ...]) -> list[tuple[Any, ...]]:
            return conn.execute(sql, params).fetchall()

        with self._write() as conn:
            try:
                # the estimate insert walks a JSON array: built in since SQLite 3.38, and in
                # the usual builds of older versions
                conn.execute("SELECT json_array_length('[1]')")
            except sqlite3.OperationalError as exc:
                raise StorageError(f"sqlite {sqlite3.sqlite_version} lacks JSON: {exc}") from exc
            try:
                version, _ = migrations.apply_pending(execute, self.dialect)
            except RuntimeError as exc:
                raise StorageError(str(exc)) from exc
        return version

    def close(self) -> None:
        self._closed = True
        with self._conns_lock:
            conns, self._conns = self._conns, []
        for conn in conns:
            with contextlib.suppress(sqlite3.Error):
                conn.close()

    def ping(self) -> bool:
        try:
            return self._read("SELECT 1") == [(1,)]
        except StorageError:
            return False

    def schema_version(self) -> int:
        """Highest applied migration (0 on an empty database)."""
        rows = self._read(
            "SELECT name FROM sqlite_master WHERE type = 'table' AND name = 'schema_version'"
        )
        if not rows:
            return 0
        return int(self._read("SELECT coalesce(max(version), 0) FROM schema_version")[0][0])

    def table_columns(self, table: str) -> list[str]:
        """Column names of ``table`` in order (empty when it does not exist)."""
        rows = self._read("SELECT name FROM pragma_table_info(?) ORDER BY cid", (table,))
        return [str(r[0]) for r in rows]

    # ------------------------------------------------------------------ vehicles

    @staticmethod
    def _record(row: Sequence[Any]) -> VehicleRecord:
        return VehicleRecord(
            vehicle_id=row[0], config=json.loads(row[1]), created_ns=row[2], updated_ns=row[3]
        )

    def upsert_vehicle(self, vehicle_id: str, config: dict[str, Any], now_ns: int) -> VehicleRecord:
        with self._write() as conn:
            row = conn.execute(
                "INSERT INTO vehicles (vehicle_id, config, created_ns, updated_ns) "
                "VALUES (?, ?, ?, ?) "
                "ON CONFLICT (vehicle_id) DO UPDATE SET "
                "config = excluded.config, updated_ns = excluded.updated_ns "
                "RETURNING vehicle_id, config, created_ns, updated_ns",
                (vehicle_id, json.dumps(config), int(now_ns), int(now_ns)),
            ).fetchone()
        return self._record(row)

    def get_vehicle(self, vehicle_id: str) -> VehicleRecord | None:
        rows = self._read(
            "SELECT vehicle_id, config, created_ns, updated_ns FROM vehicles WHERE vehicle_id = ?",
            (vehicle_id,),
        )
        return self._record(rows[0]) if rows else None

    def list_vehicles(self) -> list[VehicleRecord]:
        rows = self._read(
            "SELECT vehicle_id, config, created_ns, updated_ns FROM vehicles ORDER BY vehicle_id"
        )
        return [self._record(r) for r in rows]

    def delete_vehicle(self, vehicle_id: str) -> bool:
        with self._write() as conn:
            row = conn.execute(
                "SELECT vkey FROM vehicles WHERE vehicle_id = ?", (vehicle_id,)
            ).fetchone()
            conn.execute("DELETE FROM ingest_counters WHERE vehicle_id = ?", (vehicle_id,))
            conn.execute("DELETE FROM raw_packets WHERE vehicle_id = ?", (vehicle_id,))
            if row is None:
                return False
            # Explicit deletes, so correctness never depends on the foreign_keys pragma.
            conn.execute("DELETE FROM estimates WHERE vkey = ?", (row[0],))
            conn.execute("DELETE FROM vehicles WHERE vkey = ?", (row[0],))
        return True

    # ------------------------------------------------------------------ estimates

    def write_estimates(self, batch: Sequence[tuple[str, np.ndarray]]) -> int:
        """Insert rows in one transaction; rows of unregistered vehicles are not written.

        Returns the number of rows inserted (duplicates and unknown vehicles excluded).
        """
        checked = [(vid, check_rows(rows)) for vid, rows in batch if len(rows)]
        if not checked:
            return 0
        with self._write() as conn:
            keys = self._vkeys(conn, {vid for vid, _ in checked})
            params = [
                (keys[vid], rows.tobytes(), json.dumps(rows["stamp_ns"].tolist()))
                for vid, rows in checked
                if vid in keys
            ]
            before = conn.total_changes
            conn.executemany(_INSERT_SQL, params)
            return conn.total_changes - before

    @staticmethod
    def _vkeys(conn: sqlite3.Connection, vehicle_ids: set[str]) -> dict[str, int]:
        """``{vehicle_id: vkey}`` of the registered ones among ``vehicle_ids``."""
        ids = sorted(vehicle_ids)
        out: dict[str, int] = {}
        for i in range(0, len(ids), _VKEYS_PER_QUERY):
            chunk = ids[i : i + _VKEYS_PER_QUERY]
            out.update(
                conn.execute(
                    "SELECT vehicle_id, vkey FROM vehicles "
                    f"WHERE vehicle_id IN ({', '.join('?' * len(chunk))})",
                    chunk,
                ).fetchall()
            )
        return out

    def query_series(
        self, vehicle_id: str, start_ns: int, end_ns: int, fields: Sequence[str] | None = None
    ) -> np.ndarray:
        names = select_fields(fields)
        rows = self._query_packed(vehicle_id, int(start_ns), int(end_ns))
        if names != ESTIMATE_DTYPE.names:
            return _pick(rows, names)
        # a view of the fetched bytes is read-only; callers get their own array as before
        return rows if rows.flags.writeable else rows.copy()

    def _query_packed(self, vehicle_id: str, start_ns: int, end_ns: int) -> np.ndarray:
        """All fields of the rows in ``[start_ns, end_ns)``, ordered by time (may be a
        read-only view of the fetched bytes)."""
        conn = self._conn()
        try:
            found = conn.execute(
                "SELECT vkey FROM vehicles WHERE vehicle_id = ?", (vehicle_id,)
            ).fetchone()
            if found is None:
                return np.empty(0, dtype=ESTIMATE_DTYPE)
            # Several statements see one snapshot (unless this thread is inside a write).
            own = not conn.in_transaction
            if own:
                conn.execute("BEGIN")
            try:
                pages = self._packed_pages(conn, found[0], start_ns, end_ns)
            finally:
                if own:
                    conn.execute("COMMIT")
        except sqlite3.Error as exc:
            raise _wrap(exc) from exc
        if not pages:
            return np.empty(0, dtype=ESTIMATE_DTYPE)
        rows = concat_estimates(pages)
        stamps = rows["stamp_ns"]
        if not np.all(stamps[1:] > stamps[:-1]):
            # group_concat's order follows the ordered subquery in practice, but SQLite does
            # not promise it; stamps are unique per vehicle, so sorting restores it.
            rows = rows[np.argsort(stamps, kind="stable")]
        return rows

    @staticmethod
    def _packed_pages(
        conn: sqlite3.Connection, vkey: int, start_ns: int, end_ns: int
    ) -> list[np.ndarray]:
        pages: list[np.ndarray] = []
        while True:
            count, blob = conn.execute(
                "SELECT count(*), CAST(group_concat(packed, x'') AS BLOB) FROM ("
                " SELECT packed FROM estimates WHERE vkey = ? AND stamp_ns >= ? AND stamp_ns < ?"
                f" ORDER BY stamp_ns LIMIT {_READ_PAGE_ROWS})",
                (vkey, start_ns, end_ns),
            ).fetchone()
            if not count:
                return pages
            if len(blob) != count * _ROW_BYTES:
                blob = SqliteStore._packed_rows(conn, vkey, start_ns, end_ns)
            page = np.frombuffer(blob, dtype=ESTIMATE_DTYPE)
            pages.append(page)
            if count < _READ_PAGE_ROWS:
                return pages
            start_ns = int(page["stamp_ns"].max()) + 1

    @staticmethod
    def _packed_rows(conn: sqlite3.Connection, vkey: int, start_ns: int, end_ns: int) -> bytes:
        """One page the slow way, a blob per row: when the concatenation came out of the wrong
        length (a database in a UTF-16 encoding transcodes it)."""
        blobs = conn.execute(
            "SELECT packed FROM estimates WHERE vkey = ? AND stamp_ns >= ? AND stamp_ns < ? "
            f"ORDER BY stamp_ns LIMIT {_READ_PAGE_ROWS}",
            (vkey, start_ns, end_ns),
        ).fetchall()
        data = b"".join([b for (b,) in blobs])
        if len(data) != len(blobs) * _ROW_BYTES:
            raise StorageDataError(
                f"sqlite: estimate rows of vehicle key {vkey} are not {_ROW_BYTES}-byte "
                "ESTIMATE_DTYPE rows (a layout change without its migration?)"
            )
        return data

    def latest(self, vehicle_id: str) -> np.ndarray | None:
        rows = self._read(
            "SELECT packed FROM estimates "
            "WHERE vkey = (SELECT vkey FROM vehicles WHERE vehicle_id = ?) "
            "ORDER BY stamp_ns DESC LIMIT 1",
            (vehicle_id,),
        )
        return _unpack_one(rows[0][0]) if rows else None

    def latest_all(self) -> dict[str, np.ndarray]:
        rows = self._read(
            "SELECT v.vehicle_id, e.packed FROM vehicles v JOIN estimates e ON e.vkey = v.vkey "
            "AND e.stamp_ns = (SELECT max(stamp_ns) FROM estimates WHERE vkey = v.vkey)"
        )
        return {vid: _unpack_one(packed) for vid, packed in rows}

    def delete_older_than(self, stamp_ns: int) -> int:
        """Delete estimates (and raw packets) older than ``stamp_ns``; return estimates deleted."""
        deleted = 0
        with self._write() as conn:
            # Per vehicle, so each delete is a primary-key range scan.
            for (vkey,) in conn.execute("SELECT vkey FROM vehicles").fetchall():
                deleted += conn.execute(
                    "DELETE FROM estimates WHERE vkey = ? AND stamp_ns < ?", (vkey, int(stamp_ns))
                ).rowcount
            conn.execute("DELETE FROM raw_packets WHERE received_ns < ?", (int(stamp_ns),))
        return deleted

    # ------------------------------------------------------------------ counters

    def write_counters(self, counters: dict[str, dict[str, int]], now_ns: int) -> None:
        params = [
            (vid, name, int(total), int(now_ns))
            for vid, named in counters.items()
            for name, total in named.items()
        ]
        if not params:
            return
        with self._write() as conn:
            conn.executemany(
                "INSERT INTO ingest_counters (vehicle_id, name, total, updated_ns) "
                "VALUES (?, ?, ?, ?) ON CONFLICT (vehicle_id, name) DO UPDATE SET "
                "total = excluded.total, updated_ns = excluded.updated_ns",
                params,
            )

    def get_counters(self, vehicle_id: str) -> dict[str, int]:
        rows = self._read(
            "SELECT name, total FROM ingest_counters WHERE vehicle_id = ? ORDER BY name",
            (vehicle_id,),
        )
        return {name: int(total) for name, total in rows}

    # ------------------------------------------------------------------ access tokens

    @staticmethod
    def _token(row: Sequence[Any]) -> TokenRecord:
        return TokenRecord(
            id=int(row[0]),
            name=str(row[1]),
            role=str(row[2]),
            created_ns=int(row[3]),
            last_used_ns=None if row[4] is None else int(row[4]),
            revoked_ns=None if row[5] is None else int(row[5]),
        )

    def create_token(self, name: str, role: str, token_sha256: str, now_ns: int) -> TokenRecord:
        with self._write() as conn:
            row = conn.execute(
                "INSERT INTO api_tokens (name, role, token_sha256, created_ns) "
                f"VALUES (?, ?, ?, ?) RETURNING {_TOKEN_COLUMNS}",
                (name, role, token_sha256, int(now_ns)),
            ).fetchone()
        return self._token(row)

    def get_token(self, token_sha256: str) -> TokenRecord | None:
        rows = self._read(
            f"SELECT {_TOKEN_COLUMNS} FROM api_tokens WHERE token_sha256 = ?", (token_sha256,)
        )
        return self._token(rows[0]) if rows else None

    def list_tokens(self) -> list[TokenRecord]:
        rows = self._read(f"SELECT {_TOKEN_COLUMNS} FROM api_tokens ORDER BY id")
        return [self._token(r) for r in rows]

    def touch_token(self, token_id: int, now_ns: int) -> None:
        with self._write() as conn:
            conn.execute(
                "UPDATE api_tokens SET last_used_ns = ? WHERE id = ?", (int(now_ns), int(token_id))
            )

    def revoke_token(self, token_id: int, now_ns: int) -> TokenRecord | None:
        with self._write() as conn:
            row = conn.execute(
                "UPDATE api_tokens SET revoked_ns = coalesce(revoked_ns, ?) WHERE id = ? "
                f"RETURNING {_TOKEN_COLUMNS}",
                (int(now_ns), int(token_id)),
            ).fetchone()
        return self._token(row) if row else None

    # ------------------------------------------------------------------ raw packets

    def write_raw_packets(self, packets: Sequence[tuple[str, int, str, bytes]]) -> int:
        """Store ``(vehicle_id, received_ns, key, payload)`` tuples (registered or not)."""
        if not packets:
            return 0
        params = [(vid, int(t), key, bytes(payload)) for vid, t, key, payload in packets]
        with self._write() as conn:
            conn.executemany(
                "INSERT INTO raw_packets (vehicle_id, received_ns, key, payload) "
                "VALUES (?, ?, ?, ?)",
                params,
            )
        return len(params)

    def query_raw_packets(
        self, vehicle_id: str, start_ns: int, end_ns: int
    ) -> list[tuple[int, str, bytes]]:
        """``(received_ns, key, payload)`` with ``start_ns <= received_ns < end_ns``, in order."""
        rows = self._read(
            "SELECT received_ns, key, payload FROM raw_packets "
            "WHERE vehicle_id = ? AND received_ns >= ? AND received_ns < ? "
            "ORDER BY received_ns, id",
            (vehicle_id, int(start_ns), int(end_ns)),
        )
        return [(int(t), str(k), bytes(p)) for t, k, p in rows]
