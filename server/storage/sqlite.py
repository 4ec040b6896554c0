"""SQLite store: one file in WAL mode, the embedded default.

Connections: one per thread (``threading.local``), all registered so :meth:`SqliteStore.close`
closes every one. Reads run from any thread and do not block the writer (WAL). Writes take an
in-process lock and ``BEGIN IMMEDIATE`` (the database write lock), so the writer thread and the
occasional API write (vehicle registration) never deadlock; another process holding the lock
makes a write wait up to the busy timeout and then raise :class:`StorageError`.

Durability: ``synchronous=NORMAL`` — in WAL mode a power loss can lose the last commits but never
corrupts the file.

Each estimator has its own tables (:mod:`server.storage.migrations`, version 10): MDSF the
``estimates`` tables it always had, every other one the same three named after it
(``estimates_<name>``, ``…_recent``, ``…_horizon``). One layout and one code path for all
(:class:`_Tables` holds an estimator's statements): the write path below was tuned for 1,000
vehicles and stays what it was for MDSF, and each further estimator gets it as it is, its rows
apart from the others' so that no read or move of one estimator walks another's rows. Below,
``estimates`` stands for any estimator's final table.

Rows are stored packed: table ``estimates`` holds ``(vkey, stamp_ns, packed)``, ``packed`` being
the row's bytes in its spec's dtype (migration 6; NaN and infinities survive bit for bit). The
``sqlite3`` module creates one Python object per bound or fetched value, so

* a write goes to ``estimates_recent`` (version 7), keyed ``(stamp_ns, vkey)``: a server
  commits every few tens of ms, each commit one or two rows per vehicle, and into the
  vehicle-ordered ``estimates`` each such row dirtied a page of its own (~33 µs of CPU a row at
  1,000 vehicles, most of it writing those pages to the WAL); appended in time order the rows
  of a commit share a few pages. One ``executemany`` binds ``(stamp, vkey, packed bytes)`` per
  row; only rows at or below ``estimates_horizon`` (version 8, a bound on the stamps in
  ``estimates``) are looked up there first, so a replay of a moved row is not staged again.
  :meth:`SqliteStore.maintain`, which the writer thread calls between writes, moves the
  rows older than the newest second to ``estimates`` once the staged rows span three seconds,
  ~20-30 rows per vehicle and 100 vehicles per transaction (≤ ~35 ms each at 1,000 vehicles,
  ≤ ~25 ms of it CPU): ~9-9.5 µs a row in all, ~3.6-4.1 staging and ~5.1-5.7 moving (1,000
  vehicles at 10 Hz, 250-1,000 rows a commit and ``maintain`` after each, CPU time, two runs
  each; ~13-17 µs before version 8 and the one-seek span query in ``maintain``). Reads,
  ``latest`` and deletes look at both tables; a row being moved is in both for a moment and is
  read once. Each estimator's move rounds run on their own, one step per ``maintain`` call.
  The column layout of versions 1-5 bound 28 values and the blob per row and cost
  ~3-6x as much per row as version 6's packed rows;
* a read does not even fetch one object per row: SQLite concatenates a range's blobs into one
  (``group_concat``, at most :data:`_READ_PAGE_ROWS` rows per statement) that numpy views as a
  structured array, in one step that runs without the GIL. Reading a vehicle-hour column by
  column took ~120 ms on an idle core and several times that beside a busy Python thread.

``python -m server.tooling.bench.storage`` measures these paths against the column layout
side by side.

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
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from estimator.spec import EstimatorSpec
from estimator.types import EstimateBatch, concat_estimates
from server.storage import migrations
from server.storage._columns import (
    DEFAULT_ESTIMATOR,
    SpecTables,
    as_batches,
    fields_dtype,
    registered_rows,
    select_fields,
)
from server.storage._queries import SharedQueries
from server.storage.base import (
    Anchor,
    StorageDataError,
    StorageError,
    VehicleRecord,
)

__all__ = ["SqliteStore"]

_PAGE_SIZE_BYTES = 8192  # only takes effect when the file is created
_CACHE_KIB = 32 * 1024
#: Rows newer than this behind the newest staged row stay in the staging table; older ones
#: are moved once the staged rows span :data:`_MOVE_SPAN_NS` (so a vehicle moves ~20-30 rows
#: at a time: ~5-6 µs a row, against ~33 µs for one row per vehicle and commit written
#: straight into the final table, 1,000 vehicles). Most of it is SQLite splitting a vehicle's
#: last page with its neighbours, ~5 pages written to the WAL per vehicle and round: a wider
#: span (5 s, 50 vehicles a transaction) saved ~0.5 µs a row but made the longest step ~30 ms
#: of CPU instead of ~20 (pattern runs, two each).
_KEEP_RECENT_NS = 1_000_000_000
_MOVE_SPAN_NS = 3_000_000_000
#: Vehicles whose rows one move transaction carries (a few ms at 1,000 vehicles, so estimate
#: commits are not held back).
_MOVE_VEHICLES = 100
# A read concatenates at most this many rows per statement (21 MB), far below SQLite's 1 GB
# limit on one value; longer ranges take several statements in one read transaction.
_READ_PAGE_ROWS = 100_000
_VKEYS_PER_QUERY = 500  # below the oldest SQLite's 999 parameters per statement


class _Tables:
    """One estimator's tables: final ``table`` keyed ``(vkey, stamp_ns)``, staging
    ``table_recent`` keyed ``(stamp_ns, vkey)``, ``table_horizon`` (the bound on the stamps in
    ``table``), with their statements and the move round in progress.

    Rows are the spec's dtype as bytes, ``row_bytes`` each.
    """

    def __init__(self, spec: EstimatorSpec, table: str) -> None:
        self.spec = spec
        self.final = table
        self.recent = f"{table}_recent"
        self.horizon = f"{table}_horizon"
        self.row_bytes = spec.dtype.itemsize
        # One row per parameter set of an ``executemany`` over the whole transaction (a
        # commit carries one or two rows per vehicle, so a statement per vehicle would not
        # pay), into the time-ordered staging table. A row above the horizon (every new row in
        # the server's pattern) cannot be in the final table already and is staged as it is;
        self.stage_sql = (
            f"INSERT INTO {self.recent} (stamp_ns, vkey, packed) VALUES (?, ?, ?) "
            "ON CONFLICT (stamp_ns, vkey) DO NOTHING"
        )
        # one at or below it is staged unless the final table has it already (a replay): that
        # look-up cost ~2.5 µs of ~6 µs a row when every row took it (1,000 vehicles, 500 rows
        # a commit, pattern script);
        self.insert_sql = (
            f"INSERT INTO {self.recent} (stamp_ns, vkey, packed) SELECT ?1, ?2, ?3 "
            f"WHERE NOT EXISTS (SELECT 1 FROM {self.final} WHERE vkey = ?2 AND stamp_ns = ?1) "
            "ON CONFLICT (stamp_ns, vkey) DO NOTHING"
        )
        # a row of a vehicle a move round has copied already goes straight to the final table.
        self.insert_final_sql = (
            f"INSERT INTO {self.final} (stamp_ns, vkey, packed) VALUES (?, ?, ?) "
            "ON CONFLICT (vkey, stamp_ns) DO NOTHING"
        )
        # the move in progress: (newest stamp_ns it moves, last vkey copied)
        self.move: tuple[int, int] | None = None


def _unpack_one(packed: bytes, dtype: np.dtype) -> np.ndarray:
    """One stored row as a writable 0-d structured array."""
    if len(packed) != dtype.itemsize:
        raise StorageDataError(f"sqlite: stored estimate row of {len(packed)} bytes")
    return np.frombuffer(packed, dtype=dtype).reshape(()).copy()


def _pick(rows: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """The fields of ``dtype`` of full rows as a compact structured array."""
    out = np.empty(len(rows), dtype=dtype)
    for name in dtype.names or ():
        out[name] = rows[name]
    return out


def _wrap(exc: sqlite3.Error) -> StorageError:
    # Only errors about the data itself are final; locks, I/O, a read-only file may heal.
    if isinstance(exc, sqlite3.IntegrityError | sqlite3.DataError):
        return StorageDataError(f"sqlite: {exc}")
    return StorageError(f"sqlite: {exc}")


class SqliteStore(SharedQueries):
    """:class:`server.storage.base.Store` on a SQLite file.

    Parameters
    ----------
    path : Path
        Database file; its directory is created if missing.
    busy_timeout_s : float
        How long a write waits for another process's lock before failing.
    """

    dialect = "sqlite"

    def __init__(
        self,
        path: Path | str,
        *,
        busy_timeout_s: float = 5.0,
        specs: Iterable[EstimatorSpec] | None = None,
    ) -> None:
        self.path = Path(path)
        self.busy_timeout_s = float(busy_timeout_s)
        self._local = threading.local()
        self._conns: list[sqlite3.Connection] = []
        self._conns_lock = threading.Lock()
        self._write_lock = threading.Lock()
        self._closed = False
        # the served specs' tables (read from the database on first use, again after migrate)
        self._tables = SpecTables(self.dialect, specs, _Tables, self._read)
        # vehicle_id -> vkey of registered vehicles (a vkey never changes; delete_vehicle
        # drops its entry in the same write transaction that deletes the vehicle)
        self._vkey_of: dict[str, int] = {}
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
            version = migrations.migrate_to_latest(execute, self.dialect)
        self._tables.reload()  # refuses a spec its table no longer fits, at start
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
    def _config_of(raw: Any) -> dict[str, Any]:
        return dict(json.loads(raw))

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

    def delete_vehicle(self, vehicle_id: str) -> bool:
        self._tables.load()
        with self._write() as conn:
            row = conn.execute(
                "SELECT vkey FROM vehicles WHERE vehicle_id = ?", (vehicle_id,)
            ).fetchone()
            conn.execute("DELETE FROM ingest_counters WHERE vehicle_id = ?", (vehicle_id,))
            conn.execute("DELETE FROM raw_packets WHERE vehicle_id = ?", (vehicle_id,))
            conn.execute("DELETE FROM vehicle_anchors WHERE vehicle_id = ?", (vehicle_id,))
            if row is None:
                return False
            # Explicit deletes, so correctness never depends on the foreign_keys pragma.
            self._vkey_of.pop(vehicle_id, None)
            for table in self._tables.every:
                conn.execute(f"DELETE FROM {table} WHERE vkey = ?", (row[0],))
                conn.execute(f"DELETE FROM {table}_recent WHERE vkey = ?", (row[0],))
            conn.execute("DELETE FROM vehicles WHERE vkey = ?", (row[0],))
        return True

    # ------------------------------------------------------------------ estimates

    def write_estimates(self, *batches: EstimateBatch | Sequence[tuple[str, np.ndarray]]) -> int:
        """Insert the rows of one or more estimators in one transaction; rows of unregistered
        vehicles are not written. Returns the rows inserted (duplicates and unknown vehicles
        excluded)."""
        parts = as_batches(batches)
        if not parts:
            return 0
        with self._write() as conn:
            keys = self._vkey_of
            missing = {vid for b in parts for vid in b.ids if vid not in keys}
            if missing:
                keys.update(self._vkeys(conn, missing))
            return sum(self._stage(conn, self._tables.of(b), b, keys) for b in parts)

    @staticmethod
    def _stage(
        conn: sqlite3.Connection, t: _Tables, batch: EstimateBatch, keys: Mapping[str, int]
    ) -> int:
        """Write one estimator's rows (see :meth:`write_estimates`); return rows inserted."""
        rows, vkeys = registered_rows(batch, keys)
        if not len(rows):  # batches are never empty (as_batches): all its vehicles unregistered
            return 0
        size = t.row_bytes
        blob = rows.tobytes()
        stamps = rows["stamp_ns"].astype(np.int64)
        packed = [blob[i : i + size] for i in range(0, len(blob), size)]
        (newest,) = conn.execute(f"SELECT newest_ns FROM {t.horizon}").fetchone()
        probe = stamps <= newest
        before = conn.total_changes
        if t.move is None and not probe.any():
            conn.executemany(t.stage_sql, zip(stamps.tolist(), vkeys.tolist(), packed, strict=True))
            return conn.total_changes - before
        # A move round is under way: a row of a vehicle it has copied already, not newer than
        # the round's rows (data a vehicle buffered offline), goes straight to the final table,
        # so the round's closing delete only ever drops rows that were copied.
        direct = np.zeros(len(stamps), dtype=bool)
        if t.move is not None:
            upto, last = t.move
            direct = (stamps <= upto) & (vkeys <= last)
        for sql, sel in (
            (t.stage_sql, ~probe & ~direct),
            (t.insert_sql, probe & ~direct),
            (t.insert_final_sql, direct),
        ):
            idx = np.flatnonzero(sel).tolist()
            if idx:
                st, vk = stamps[idx].tolist(), vkeys[idx].tolist()
                conn.executemany(sql, zip(st, vk, [packed[i] for i in idx], strict=True))
        return conn.total_changes - before

    def maintain(self, *, everything: bool = False) -> bool:
        """One step of moving staged rows to their final table, of the first estimator with a
        round under way or due; True while more steps are due (the writer calls this while it
        has nothing else to do).

        A round starts once an estimator's staged rows span :data:`_MOVE_SPAN_NS`: every row
        older than :data:`_KEEP_RECENT_NS` before the newest one (``everything``: every row)
        is copied, :data:`_MOVE_VEHICLES` vehicles per transaction, then deleted from the
        staging table in one range delete (rows in the round's range of vehicles already
        copied that come in during the round go straight to the final table: see
        :meth:`_stage`). Between the copy and the delete a row is in both tables; reads keep
        one.
        """
        tables = sorted(self._tables.load().values(), key=lambda t: t.move is None)
        with self._write() as conn:
            for t in tables:
                worked, move = self._move_step(conn, t, everything)
                if worked:
                    break
            else:
                return False
        t.move = move  # committed: the round goes on from here
        return True

    @staticmethod
    def _move_step(
        conn: sqlite3.Connection, t: _Tables, everything: bool
    ) -> tuple[bool, tuple[int, int] | None]:
        """One transaction's work of ``t``'s move round: ``(whether there was any, the
        round's next state)``."""
        if t.move is None:
            # One subquery each: ``min`` and ``max`` in one SELECT scan the whole table
            # (SQLite's min/max shortcut takes a lone aggregate only), ~3 µs per staged row at
            # 1,000 vehicles since this runs after every commit.
            lo, hi = conn.execute(
                f"SELECT (SELECT min(stamp_ns) FROM {t.recent}), "
                f"(SELECT max(stamp_ns) FROM {t.recent})"
            ).fetchone()
            if lo is None or (not everything and hi - lo < _MOVE_SPAN_NS):
                return False, None
            # ``everything``: the rows staged now (later ones are the next round's), so the
            # stamp bound below holds for every row the round copies
            upto = hi if everything else hi - _KEEP_RECENT_NS - 1
            # raised before any row of the round reaches the final table (copied, or written
            # straight there while the round runs: all at or below ``upto``)
            conn.execute(f"UPDATE {t.horizon} SET newest_ns = max(newest_ns, ?)", (upto,))
            after = -1
        else:
            upto, after = t.move
        keys = conn.execute(
            "SELECT vkey FROM vehicles WHERE vkey > ? ORDER BY vkey LIMIT ?",
            (after, _MOVE_VEHICLES),
        ).fetchall()
        if not keys:  # every vehicle copied: drop the copies
            conn.execute(f"DELETE FROM {t.recent} WHERE stamp_ns <= ?", (upto,))
            return True, None
        last = int(keys[-1][0])
        conn.execute(
            f"INSERT INTO {t.final} (vkey, stamp_ns, packed) "
            f"SELECT r.vkey, r.stamp_ns, r.packed FROM {t.recent} r "
            "JOIN vehicles v ON v.vkey = r.vkey "  # rows of a vehicle still there
            "WHERE r.stamp_ns <= ? AND r.vkey > ? AND r.vkey <= ? "
            "ORDER BY r.vkey, r.stamp_ns ON CONFLICT (vkey, stamp_ns) DO NOTHING",
            (upto, after, last),
        )
        return True, (upto, last)

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
        self,
        vehicle_id: str,
        start_ns: int,
        end_ns: int,
        fields: Sequence[str] | None = None,
        estimator: str = DEFAULT_ESTIMATOR,
    ) -> np.ndarray:
        t = self._tables.served(estimator)
        names = select_fields(t.spec, fields)
        rows = self._query_packed(t, vehicle_id, int(start_ns), int(end_ns))
        if names != t.spec.field_names:
            return _pick(rows, fields_dtype(t.spec, names))
        # a view of the fetched bytes is read-only; callers get their own array as before
        return rows if rows.flags.writeable else rows.copy()

    def _query_packed(self, t: _Tables, vehicle_id: str, start_ns: int, end_ns: int) -> np.ndarray:
        """All fields of the rows in ``[start_ns, end_ns)``, ordered by time (may be a
        read-only view of the fetched bytes)."""
        conn = self._conn()
        try:
            found = conn.execute(
                "SELECT vkey FROM vehicles WHERE vehicle_id = ?", (vehicle_id,)
            ).fetchone()
            if found is None:
                return t.spec.empty_rows(0)
            # Several statements see one snapshot (unless this thread is inside a write).
            own = not conn.in_transaction
            if own:
                conn.execute("BEGIN")
            try:
                pages = self._packed_pages(conn, t, t.final, found[0], start_ns, end_ns)
                staged = self._packed_pages(conn, t, t.recent, found[0], start_ns, end_ns)
            finally:
                if own:
                    conn.execute("COMMIT")
        except sqlite3.Error as exc:
            raise _wrap(exc) from exc
        if not pages and not staged:
            return t.spec.empty_rows(0)
        rows = concat_estimates(pages + staged)
        stamps = rows["stamp_ns"]
        if not np.all(stamps[1:] > stamps[:-1]):
            # group_concat's order follows the ordered subquery in practice, but SQLite does
            # not promise it; and a row being moved is in both tables: sort, keep one per stamp
            rows = rows[np.argsort(stamps, kind="stable")]
            stamps = rows["stamp_ns"]
            keep = np.empty(len(rows), dtype=bool)
            keep[0] = True
            np.not_equal(stamps[1:], stamps[:-1], out=keep[1:])
            if not keep.all():
                rows = rows[keep]
        return rows

    @staticmethod
    def _packed_pages(
        conn: sqlite3.Connection, t: _Tables, table: str, vkey: int, start_ns: int, end_ns: int
    ) -> list[np.ndarray]:
        """``table``'s (``t``'s final or staging table) rows of ``vkey`` in the range."""
        pages: list[np.ndarray] = []
        while True:
            count, blob = conn.execute(
                "SELECT count(*), CAST(group_concat(packed, x'') AS BLOB) FROM ("
                f" SELECT packed FROM {table} WHERE vkey = ? AND stamp_ns >= ? AND stamp_ns < ?"
                f" ORDER BY stamp_ns LIMIT {_READ_PAGE_ROWS})",
                (vkey, start_ns, end_ns),
            ).fetchone()
            if not count:
                return pages
            if len(blob) != count * t.row_bytes:
                blob = SqliteStore._packed_rows(conn, t, table, vkey, start_ns, end_ns)
            page = np.frombuffer(blob, dtype=t.spec.dtype)
            pages.append(page)
            if count < _READ_PAGE_ROWS:
                return pages
            start_ns = int(page["stamp_ns"].max()) + 1

    @staticmethod
    def _packed_rows(
        conn: sqlite3.Connection, t: _Tables, table: str, vkey: int, start_ns: int, end_ns: int
    ) -> bytes:
        """One page the slow way, a blob per row: when the concatenation came out of the wrong
        length (a database in a UTF-16 encoding transcodes it)."""
        blobs = conn.execute(
            f"SELECT packed FROM {table} WHERE vkey = ? AND stamp_ns >= ? AND stamp_ns < ? "
            f"ORDER BY stamp_ns LIMIT {_READ_PAGE_ROWS}",
            (vkey, start_ns, end_ns),
        ).fetchall()
        data = b"".join([b for (b,) in blobs])
        if len(data) != len(blobs) * t.row_bytes:
            raise StorageDataError(
                f"sqlite: estimate rows of vehicle key {vkey} in {table} are not "
                f"{t.row_bytes}-byte {t.spec.name} rows (a layout change without its migration?)"
            )
        return data

    def latest(self, vehicle_id: str, estimator: str = DEFAULT_ESTIMATOR) -> np.ndarray | None:
        t = self._tables.served(estimator)
        rows = self._read(
            "SELECT stamp_ns, packed FROM ("
            f" SELECT stamp_ns, packed FROM {t.final} WHERE vkey = (SELECT vkey FROM vehicles"
            " WHERE vehicle_id = ?1) ORDER BY stamp_ns DESC LIMIT 1) "
            "UNION ALL SELECT stamp_ns, packed FROM ("
            f" SELECT stamp_ns, packed FROM {t.recent} WHERE vkey = (SELECT vkey FROM"
            " vehicles WHERE vehicle_id = ?1) ORDER BY stamp_ns DESC LIMIT 1) "
            "ORDER BY stamp_ns DESC LIMIT 1",
            (vehicle_id,),
        )
        return _unpack_one(rows[0][1], t.spec.dtype) if rows else None

    def latest_all(self, estimator: str = DEFAULT_ESTIMATOR) -> dict[str, np.ndarray]:
        t = self._tables.served(estimator)
        rows = self._read(
            f"SELECT v.vehicle_id, e.stamp_ns, e.packed FROM vehicles v JOIN {t.final} e "
            "ON e.vkey = v.vkey "
            f"AND e.stamp_ns = (SELECT max(stamp_ns) FROM {t.final} WHERE vkey = v.vkey) "
            "UNION ALL SELECT v.vehicle_id, r.stamp_ns, r.packed FROM ("
            f" SELECT vkey, max(stamp_ns) AS newest FROM {t.recent} GROUP BY vkey) m "
            f"JOIN {t.recent} r ON r.stamp_ns = m.newest AND r.vkey = m.vkey "
            "JOIN vehicles v ON v.vkey = m.vkey"
        )
        newest: dict[str, tuple[int, bytes]] = {}
        for vid, stamp, packed in rows:
            if vid not in newest or stamp > newest[vid][0]:
                newest[vid] = (stamp, packed)
        return {vid: _unpack_one(packed, t.spec.dtype) for vid, (_, packed) in newest.items()}

    def estimators_with_rows(self, vehicle_id: str) -> list[str]:
        found = self._read("SELECT vkey FROM vehicles WHERE vehicle_id = ?", (vehicle_id,))
        if not found:
            return []
        return [
            name
            for name, t in self._tables.load().items()
            if self._read(
                f"SELECT EXISTS (SELECT 1 FROM {t.final} WHERE vkey = ?1) "
                f"OR EXISTS (SELECT 1 FROM {t.recent} WHERE vkey = ?1)",
                (found[0][0],),
            )[0][0]
        ]

    def delete_older_than(self, stamp_ns: int) -> int:
        """Delete the estimates of every estimator (and raw packets) older than ``stamp_ns``;
        return estimates deleted."""
        self._tables.load()
        deleted = 0
        with self._write() as conn:
            vkeys = conn.execute("SELECT vkey FROM vehicles").fetchall()
            for table in self._tables.every:
                # Per vehicle, so each delete is a primary-key range scan.
                for (vkey,) in vkeys:
                    deleted += conn.execute(
                        f"DELETE FROM {table} WHERE vkey = ? AND stamp_ns < ?",
                        (vkey, int(stamp_ns)),
                    ).rowcount
                deleted += conn.execute(
                    f"DELETE FROM {table}_recent WHERE stamp_ns < ?", (int(stamp_ns),)
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

    # ------------------------------------------------------------------ ENU anchors

    def put_anchors(self, anchors: Mapping[str, Anchor], now_ns: int) -> int:
        params = [(vid, *map(float, a), int(now_ns)) for vid, a in anchors.items()]
        if not params:
            return 0
        with self._write() as conn:
            before = conn.total_changes
            conn.executemany(
                "INSERT INTO vehicle_anchors (vehicle_id, lat_deg, lon_deg, height_m, set_ns) "
                "VALUES (?, ?, ?, ?, ?) ON CONFLICT (vehicle_id) DO NOTHING",
                params,
            )
            return int(conn.total_changes - before)

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
