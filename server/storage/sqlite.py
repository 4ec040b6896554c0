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
  read once. The column layout of versions 1-5 bound 28 values and the blob per row and cost
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
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from estimator.types import ESTIMATE_DTYPE, concat_estimates
from server.storage import migrations
from server.storage._columns import check_rows, fields_dtype, select_fields
from server.storage.base import (
    Anchor,
    StorageDataError,
    StorageError,
    TokenRecord,
    VehicleRecord,
)

__all__ = ["SqliteStore"]

_PAGE_SIZE_BYTES = 8192  # only takes effect when the file is created
_CACHE_KIB = 32 * 1024
_TOKEN_COLUMNS = "id, name, role, created_ns, last_used_ns, revoked_ns"


_ROW_BYTES = ESTIMATE_DTYPE.itemsize
# One row per parameter set of an ``executemany`` over the whole transaction (a commit carries
# one or two rows per vehicle, so a statement per vehicle would not pay), into the time-ordered
# ``estimates_recent``; :meth:`SqliteStore.maintain` moves them on. A row above the stamp
# bound of ``estimates`` (``estimates_horizon``, version 8: every new row in the server's
# pattern) cannot be there already and is staged as it is ...
_STAGE_SQL = (
    "INSERT INTO estimates_recent (stamp_ns, vkey, packed) VALUES (?, ?, ?) "
    "ON CONFLICT (stamp_ns, vkey) DO NOTHING"
)
# ... one at or below it is staged unless ``estimates`` has it already (a replay): that
# look-up cost ~2.5 µs of ~6 µs a row when every row took it (1,000 vehicles, 500 rows a
# commit, pattern script).
_INSERT_SQL = (
    "INSERT INTO estimates_recent (stamp_ns, vkey, packed) SELECT ?1, ?2, ?3 "
    "WHERE NOT EXISTS (SELECT 1 FROM estimates WHERE vkey = ?2 AND stamp_ns = ?1) "
    "ON CONFLICT (stamp_ns, vkey) DO NOTHING"
)
#: A row written straight to ``estimates`` (see ``SqliteStore.write_estimates``).
_INSERT_FINAL_SQL = (
    "INSERT INTO estimates (stamp_ns, vkey, packed) VALUES (?, ?, ?) "
    "ON CONFLICT (vkey, stamp_ns) DO NOTHING"
)
#: Rows newer than this behind the newest staged row stay in ``estimates_recent``; older ones
#: are moved once the staged rows span :data:`_MOVE_SPAN_NS` (so a vehicle moves ~20-30 rows
#: at a time: ~5-6 µs a row, against ~33 µs for one row per vehicle and commit written
#: straight into ``estimates``, 1,000 vehicles). Most of it is SQLite splitting a vehicle's
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
        # the move of staged rows in progress (maintain): (newest stamp_ns it moves, last
        # vkey copied)
        self._move: tuple[int, int] | None = None
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
            conn.execute("DELETE FROM vehicle_anchors WHERE vehicle_id = ?", (vehicle_id,))
            if row is None:
                return False
            # Explicit deletes, so correctness never depends on the foreign_keys pragma.
            self._vkey_of.pop(vehicle_id, None)
            conn.execute("DELETE FROM estimates WHERE vkey = ?", (row[0],))
            conn.execute("DELETE FROM estimates_recent WHERE vkey = ?", (row[0],))
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
            keys = self._vkey_of
            missing = {vid for vid, _ in checked if vid not in keys}
            if missing:
                keys.update(self._vkeys(conn, missing))
            known = [(keys[vid], rows) for vid, rows in checked if vid in keys]
            if not known:
                return 0
            rows = concat_estimates([r for _, r in known])
            blob = rows.tobytes()
            stamps = rows["stamp_ns"].astype(np.int64)
            vkeys = np.repeat([k for k, _ in known], [len(r) for _, r in known])
            packed = [blob[i : i + _ROW_BYTES] for i in range(0, len(blob), _ROW_BYTES)]
            (newest,) = conn.execute("SELECT newest_ns FROM estimates_horizon").fetchone()
            probe = stamps <= newest
            before = conn.total_changes
            if self._move is None and not probe.any():
                conn.executemany(
                    _STAGE_SQL, zip(stamps.tolist(), vkeys.tolist(), packed, strict=True)
                )
                return conn.total_changes - before
            # A move round is under way: a row of a vehicle it has copied already, not newer
            # than the round's rows (data a vehicle buffered offline), goes straight to
            # ``estimates``, so the round's closing delete only ever drops rows that were copied.
            direct = np.zeros(len(stamps), dtype=bool)
            if self._move is not None:
                upto, last = self._move
                direct = (stamps <= upto) & (vkeys <= last)
            for sql, sel in (
                (_STAGE_SQL, ~probe & ~direct),
                (_INSERT_SQL, probe & ~direct),
                (_INSERT_FINAL_SQL, direct),
            ):
                idx = np.flatnonzero(sel).tolist()
                if idx:
                    st, vk = stamps[idx].tolist(), vkeys[idx].tolist()
                    conn.executemany(sql, zip(st, vk, [packed[i] for i in idx], strict=True))
            return conn.total_changes - before

    def maintain(self, *, everything: bool = False) -> bool:
        """One step of moving rows from ``estimates_recent`` to ``estimates``; True while
        more steps are due (the writer calls this while it has nothing else to do).

        A round starts once the staged rows span :data:`_MOVE_SPAN_NS`: every row older than
        :data:`_KEEP_RECENT_NS` before the newest one (``everything``: every row) is copied,
        :data:`_MOVE_VEHICLES` vehicles per transaction, then deleted from the staging table
        in one range delete (rows in the round's range of vehicles already copied that come in
        during the round go straight to ``estimates``: see :meth:`write_estimates`). Between
        the copy and the delete a row is in both tables; reads keep one.
        """
        with self._write() as conn:
            if self._move is None:
                # One subquery each: ``min`` and ``max`` in one SELECT scan the whole table
                # (SQLite's min/max shortcut takes a lone aggregate only), ~3 µs per staged
                # row at 1,000 vehicles since this runs after every commit.
                lo, hi = conn.execute(
                    "SELECT (SELECT min(stamp_ns) FROM estimates_recent), "
                    "(SELECT max(stamp_ns) FROM estimates_recent)"
                ).fetchone()
                if lo is None or (not everything and hi - lo < _MOVE_SPAN_NS):
                    return False
                # ``everything``: the rows staged now (later ones are the next round's), so
                # the stamp bound below holds for every row the round copies
                upto = hi if everything else hi - _KEEP_RECENT_NS - 1
                # raised before any row of the round reaches ``estimates`` (copied, or written
                # straight there while the round runs: all at or below ``upto``)
                conn.execute("UPDATE estimates_horizon SET newest_ns = max(newest_ns, ?)", (upto,))
                after = -1
            else:
                upto, after = self._move
            keys = conn.execute(
                "SELECT vkey FROM vehicles WHERE vkey > ? ORDER BY vkey LIMIT ?",
                (after, _MOVE_VEHICLES),
            ).fetchall()
            if keys:
                last = int(keys[-1][0])
                conn.execute(
                    "INSERT INTO estimates (vkey, stamp_ns, packed) "
                    "SELECT r.vkey, r.stamp_ns, r.packed FROM estimates_recent r "
                    "JOIN vehicles v ON v.vkey = r.vkey "  # rows of a vehicle still there
                    "WHERE r.stamp_ns <= ? AND r.vkey > ? AND r.vkey <= ? "
                    "ORDER BY r.vkey, r.stamp_ns ON CONFLICT (vkey, stamp_ns) DO NOTHING",
                    (upto, after, last),
                )
                move: tuple[int, int] | None = (upto, last)
            else:  # every vehicle copied: drop the copies
                conn.execute("DELETE FROM estimates_recent WHERE stamp_ns <= ?", (upto,))
                move = None
        self._move = move
        return True

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
                pages = self._packed_pages(conn, "estimates", found[0], start_ns, end_ns)
                staged = self._packed_pages(conn, "estimates_recent", found[0], start_ns, end_ns)
            finally:
                if own:
                    conn.execute("COMMIT")
        except sqlite3.Error as exc:
            raise _wrap(exc) from exc
        if not pages and not staged:
            return np.empty(0, dtype=ESTIMATE_DTYPE)
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
        conn: sqlite3.Connection, table: str, vkey: int, start_ns: int, end_ns: int
    ) -> list[np.ndarray]:
        """``table``'s (``estimates`` or ``estimates_recent``) rows of ``vkey`` in the range."""
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
            if len(blob) != count * _ROW_BYTES:
                blob = SqliteStore._packed_rows(conn, table, vkey, start_ns, end_ns)
            page = np.frombuffer(blob, dtype=ESTIMATE_DTYPE)
            pages.append(page)
            if count < _READ_PAGE_ROWS:
                return pages
            start_ns = int(page["stamp_ns"].max()) + 1

    @staticmethod
    def _packed_rows(
        conn: sqlite3.Connection, table: str, vkey: int, start_ns: int, end_ns: int
    ) -> bytes:
        """One page the slow way, a blob per row: when the concatenation came out of the wrong
        length (a database in a UTF-16 encoding transcodes it)."""
        blobs = conn.execute(
            f"SELECT packed FROM {table} WHERE vkey = ? AND stamp_ns >= ? AND stamp_ns < ? "
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
            "SELECT stamp_ns, packed FROM ("
            " SELECT stamp_ns, packed FROM estimates WHERE vkey = (SELECT vkey FROM vehicles"
            " WHERE vehicle_id = ?1) ORDER BY stamp_ns DESC LIMIT 1) "
            "UNION ALL SELECT stamp_ns, packed FROM ("
            " SELECT stamp_ns, packed FROM estimates_recent WHERE vkey = (SELECT vkey FROM"
            " vehicles WHERE vehicle_id = ?1) ORDER BY stamp_ns DESC LIMIT 1) "
            "ORDER BY stamp_ns DESC LIMIT 1",
            (vehicle_id,),
        )
        return _unpack_one(rows[0][1]) if rows else None

    def latest_all(self) -> dict[str, np.ndarray]:
        rows = self._read(
            "SELECT v.vehicle_id, e.stamp_ns, e.packed FROM vehicles v JOIN estimates e "
            "ON e.vkey = v.vkey "
            "AND e.stamp_ns = (SELECT max(stamp_ns) FROM estimates WHERE vkey = v.vkey) "
            "UNION ALL SELECT v.vehicle_id, r.stamp_ns, r.packed FROM ("
            " SELECT vkey, max(stamp_ns) AS newest FROM estimates_recent GROUP BY vkey) m "
            "JOIN estimates_recent r ON r.stamp_ns = m.newest AND r.vkey = m.vkey "
            "JOIN vehicles v ON v.vkey = m.vkey"
        )
        newest: dict[str, tuple[int, bytes]] = {}
        for vid, stamp, packed in rows:
            if vid not in newest or stamp > newest[vid][0]:
                newest[vid] = (stamp, packed)
        return {vid: _unpack_one(packed) for vid, (_, packed) in newest.items()}

    def delete_older_than(self, stamp_ns: int) -> int:
        """Delete estimates (and raw packets) older than ``stamp_ns``; return estimates deleted."""
        deleted = 0
        with self._write() as conn:
            # Per vehicle, so each delete is a primary-key range scan.
            for (vkey,) in conn.execute("SELECT vkey FROM vehicles").fetchall():
                deleted += conn.execute(
                    "DELETE FROM estimates WHERE vkey = ? AND stamp_ns < ?", (vkey, int(stamp_ns))
                ).rowcount
            deleted += conn.execute(
                "DELETE FROM estimates_recent WHERE stamp_ns < ?", (int(stamp_ns),)
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

    def get_anchors(self, vehicle_id: str | None = None) -> dict[str, Anchor]:
        sql = "SELECT vehicle_id, lat_deg, lon_deg, height_m FROM vehicle_anchors"
        if vehicle_id is None:
            rows = self._read(sql)
        else:
            rows = self._read(f"{sql} WHERE vehicle_id = ?", (vehicle_id,))
        return {str(v): (float(a), float(b), float(c)) for v, a, b, c in rows}

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
