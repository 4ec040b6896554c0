"""Storage benchmark: one vehicle-hour in SQLite (and PostgreSQL when configured).

Run ``python -m server.tooling.bench.storage [--json out.json] [--postgres] [--rows 36000]``.

For each backend, on a fresh database:

* **insert, batched writer** — the vehicle-hour (36,000 rows at 10 Hz) goes through
  :class:`~server.storage.StoreWriter` in 1-second packets of 10 rows, as the pipeline submits
  them; rows/s from the first submit until ``flush`` returns, and µs per row;
* **insert, batched writer, fleet** — the same number of rows spread over ``--fleet-vehicles``
  vehicles (1-second packets round-robin, as a fleet's traffic interleaves), so a transaction
  carries a few rows of many vehicles;
* SQLite only, both inserts again into the **column layout** of schema versions 3-5 (every
  field a column plus the packed copy, the store's insert of version 5, kept in this module),
  each in a fresh database: the baseline for the packed-only layout of version 6, with the ratio
  of the two costs per row;
* **insert, one commit per row** — ``write_estimates`` with a single row, ``--baseline-rows``
  times; rows/s;
* **warm series query** — ``query_series`` over the full hour, all 27 fields and a few fields
  (``stamp_ns``, ``vg_mps``, ``slip_left_pct``, ``slip_right_pct``, ``flags``), after one
  warm-up call; median and best of ``--repeats`` calls in ms, twice: on a quiet interpreter and
  while another Python thread keeps the interpreter busy (as the pipeline thread does while it
  steps the estimators), with the ratio of the two medians. SQLite also reads the hour back
  column by column from the column-layout database (the read path before packed rows).

The issue's target is a vehicle-hour series query under 100 ms warm on SQLite; the result says
per query and per condition whether it holds. ``--postgres`` takes the server from the settings
(``SLIPFLEET_STORAGE__URL``); a temporary database is created on it when the role may, otherwise
the configured database is used with a throwaway vehicle.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import threading
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from estimator.types import (
    ESTIMATE_DTYPE,
    ESTIMATE_FIELDS,
    EstimateBatch,
    EstimateFlag,
    empty_estimates,
)
from server.settings import StorageSettings
from server.storage import Store, StoreWriter, migrations
from server.storage._columns import FIELD_NAMES, FLOAT_FIELDS, check_rows
from server.storage.sqlite import SqliteStore

__all__ = ["main", "run"]

VEHICLE_HOUR_ROWS = 36_000
RATE_HZ = 10
FLEET_VEHICLES = 1000
FEW_FIELDS = ("vg_mps", "slip_left_pct", "slip_right_pct", "flags")
TARGET_MS = 100.0
_T0_NS = 1_763_700_000_000_000_000
_S = TypeVar("_S", bound=SqliteStore)


def synthetic_hour(n: int = VEHICLE_HOUR_ROWS, seed: int = 0) -> np.ndarray:
    """``n`` plausible estimate rows at 10 Hz (random-walk speeds, slip with NaN gaps)."""
    rng = np.random.default_rng(seed)
    rows = empty_estimates(n)
    rows["stamp_ns"] = _T0_NS + np.arange(n, dtype=np.int64) * (1_000_000_000 // RATE_HZ)
    speed = np.clip(2.0 + np.cumsum(rng.normal(0, 0.02, n)), 0.0, 6.0)
    for name, kind in ESTIMATE_FIELDS[1:]:
        if kind == "f8":
            rows[name] = speed * (1 + rng.normal(0, 0.05, n))
    rows["slip_left_pct"] = rng.gamma(2.0, 3.0, n)
    rows["slip_right_pct"] = rng.gamma(2.0, 3.0, n)
    standstill = speed < 0.2
    rows["slip_left_pct"][standstill] = np.nan
    rows["slip_right_pct"][standstill] = np.nan
    rows["flags"] = np.where(standstill, EstimateFlag.STANDSTILL, EstimateFlag.GNSS_OK)
    return rows


def _rate(rows: int, seconds: float) -> float:
    return rows / seconds if seconds > 0 else float("inf")


class ColumnLayoutStore(SqliteStore):
    """The SQLite store's estimate layout and insert of schema version 5, as the baseline.

    Every field a column (NaN as NULL) plus the row's packed bytes, inserted with one tuple of
    28 values per row; reads through the columns. Opened on its own file, migrated to version 5.
    """

    def migrate(self) -> int:
        with self._write() as conn:
            version, _ = migrations.apply_pending(
                lambda sql, params: conn.execute(sql, params).fetchall(), self.dialect, target=5
            )

            # the later versions' (empty) tables, which the inherited deletes also clear:
            # staging (7), anchors (9), and every version from 10 on (the estimator tables,
            # the configs' shape, token expiry); not 6 and 8, the packed layout it stands for
            def execute(sql: str, params: Sequence[Any]) -> list[Any]:
                return conn.execute(sql, params).fetchall()

            # the fields MDSF's rows gained since (15: the calibration) as columns too
            for name, _ in migrations.MDSF_CALIBRATION_FIELDS_V15:
                conn.execute(f"ALTER TABLE estimates ADD COLUMN {name} REAL")
            later_versions = (7, 9, *(m.version for m in migrations.MIGRATIONS if m.version >= 10))
            for later in later_versions:
                for step in next(m for m in migrations.MIGRATIONS if m.version == later).sqlite:
                    if isinstance(step, str):
                        conn.execute(step)
                    else:
                        step(execute)
        return version

    def maintain(self, *, everything: bool = False) -> bool:
        """Version 5 writes straight into ``estimates``: nothing to move."""
        return False

    def write_estimates(self, *batches: EstimateBatch | Sequence[tuple[str, np.ndarray]]) -> int:
        checked = [(vid, check_rows(rows)) for b in batches for vid, rows in b if len(rows)]
        with self._write() as conn:
            before = conn.total_changes
            for vid, rows in checked:
                found = conn.execute(
                    "SELECT vkey FROM vehicles WHERE vehicle_id = ?", (vid,)
                ).fetchone()
                if found is None:
                    continue
                sql = (
                    f"INSERT INTO estimates (vkey, {', '.join(FIELD_NAMES)}, packed) "
                    f"VALUES ({int(found[0])}, {', '.join('?' * (len(FIELD_NAMES) + 1))}) "
                    "ON CONFLICT (vkey, stamp_ns) DO NOTHING"
                )
                buf, size = rows.tobytes(), ESTIMATE_DTYPE.itemsize
                conn.executemany(
                    sql,
                    [(*v, buf[i * size : (i + 1) * size]) for i, v in enumerate(rows.tolist())],
                )
            return conn.total_changes - before

    def query_series_columns(self, vehicle_id: str, start_ns: int, end_ns: int) -> np.ndarray:
        """Every field through the columns: one Python object per value."""
        select = ", ".join(f"coalesce({n}, 'nan')" if n in FLOAT_FIELDS else n for n in FIELD_NAMES)
        cur = self._conn().execute(
            f"SELECT {select} FROM estimates "
            "WHERE vkey = (SELECT vkey FROM vehicles WHERE vehicle_id = ?) "
            "AND stamp_ns >= ? AND stamp_ns < ? ORDER BY stamp_ns",
            (vehicle_id, start_ns, end_ns),
        )
        return np.fromiter(cur, dtype=ESTIMATE_DTYPE)


def _insert_through_writer(store: Store, rows: np.ndarray, vehicles: int) -> tuple[float, int]:
    """``rows`` through a :class:`StoreWriter` in 1-second packets, dealt round-robin to
    ``vehicles`` new vehicles (deleted again); seconds from first submit to flush, and the
    number of transactions."""
    ids = [f"bench-{uuid.uuid4().hex[:8]}" for _ in range(vehicles)]
    for vid in ids:
        store.upsert_vehicle(vid, {}, now_ns=time.time_ns())
    try:
        packets = [rows[i : i + RATE_HZ] for i in range(0, len(rows), RATE_HZ)]
        writer = StoreWriter(store, StorageSettings.model_validate({}))
        writer.start()
        t0 = time.perf_counter()
        for i, packet in enumerate(packets):
            # vehicle j gets packets j, j + vehicles, ...: each its own consecutive seconds
            writer.submit([(ids[i % vehicles], packet)])
        if not writer.flush(timeout=600):
            raise RuntimeError("writer did not flush within 10 minutes")
        seconds = time.perf_counter() - t0
        writer.close()
        wstats = writer.stats()
        if wstats.rows_written != len(rows):
            raise RuntimeError(f"writer wrote {wstats.rows_written} of {len(rows)} rows")
    finally:
        for vid in ids:
            store.delete_vehicle(vid)
    return seconds, wstats.transactions


def _timed_ms(fn: Callable[[], object], repeats: int) -> dict[str, float]:
    fn()  # warm-up: page cache, statement cache, connection
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        samples.append((time.perf_counter() - t0) * 1000.0)
    return {"median_ms": statistics.median(samples), "best_ms": min(samples)}


@contextmanager
def _busy_python_thread() -> Iterator[None]:
    """While active, another thread runs pure Python without pause.

    It holds the GIL except when the interpreter makes it hand over (every switch interval,
    5 ms by default), so a query path that releases and re-takes the GIL per row waits for it
    again and again, while one that works outside the GIL in long stretches hardly notices.
    """
    stop = threading.Event()

    def spin() -> None:
        n = 0
        while not stop.is_set():
            n += 1

    thread = threading.Thread(target=spin, name="bench-busy-python", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()


def _timed_query(fn: Callable[[], object], repeats: int) -> dict[str, Any]:
    """``fn`` timed on a quiet interpreter, then beside a busy Python thread."""
    quiet = _timed_ms(fn, repeats)
    with _busy_python_thread():
        busy = _timed_ms(fn, repeats)
    return {
        **quiet,
        "meets_target": quiet["median_ms"] < TARGET_MS,
        "busy_thread": {**busy, "meets_target": busy["median_ms"] < TARGET_MS},
        "busy_slowdown": busy["median_ms"] / quiet["median_ms"],
    }


_INSERT_CASES = ("insert_batched", "insert_batched_fleet")


def _bench_inserts(
    stores: dict[str, Store], rows: np.ndarray, fleet_vehicles: int, repeats: int
) -> dict[str, dict[str, dict[str, float]]]:
    """``{layout: {case: {rows_per_s, us_per_row, best_us_per_row, transactions}}}``: each
    case ``repeats`` times on every store, interleaved so a change in the machine's load hits
    all alike; rates from the median run."""
    vehicles = dict(zip(_INSERT_CASES, (1, fleet_vehicles), strict=True))
    runs: dict[tuple[str, str], list[tuple[float, int]]] = {}
    for _ in range(max(1, repeats)):
        for case in _INSERT_CASES:
            for layout, store in stores.items():
                runs.setdefault((layout, case), []).append(
                    _insert_through_writer(store, rows, vehicles[case])
                )
    out: dict[str, dict[str, dict[str, float]]] = {layout: {} for layout in stores}
    for (layout, case), samples in runs.items():
        seconds = statistics.median(s for s, _ in samples)
        out[layout][case] = {
            "rows_per_s": _rate(len(rows), seconds),
            "us_per_row": seconds / len(rows) * 1e6,
            "best_us_per_row": min(s for s, _ in samples) / len(rows) * 1e6,
            "transactions": samples[0][1],
        }
    return out


def _column_read(store: ColumnLayoutStore, rows: np.ndarray, repeats: int) -> dict[str, Any]:
    """The vehicle-hour read through the columns of the column layout."""
    hour_id = f"bench-{uuid.uuid4().hex[:8]}"
    store.upsert_vehicle(hour_id, {}, now_ns=time.time_ns())
    try:
        store.write_estimates([(hour_id, rows)])
        start_ns, end_ns = int(rows["stamp_ns"][0]), int(rows["stamp_ns"][-1]) + 1
        return _timed_query(lambda: store.query_series_columns(hour_id, start_ns, end_ns), repeats)
    finally:
        store.delete_vehicle(hour_id)


def _bench_store(
    store: Store,
    rows: np.ndarray,
    baseline_rows: int,
    repeats: int,
    fleet_vehicles: int,
    column_layout: ColumnLayoutStore | None = None,
) -> dict[str, Any]:
    """One backend's inserts (batched, per row), series queries over the hour and, with
    ``column_layout``, the same against the column layout; the vehicles it makes are deleted."""
    stores: dict[str, Store] = {"current": store}
    if column_layout is not None:
        stores["column_layout"] = column_layout
    inserts = _bench_inserts(stores, rows, fleet_vehicles, repeats)
    hour_id, base_id = f"bench-{uuid.uuid4().hex[:8]}", f"bench-{uuid.uuid4().hex[:8]}"
    store.upsert_vehicle(hour_id, {}, now_ns=time.time_ns())
    store.upsert_vehicle(base_id, {}, now_ns=time.time_ns())
    try:
        _write_hour(store, hour_id, rows)
        base = rows[:baseline_rows]
        baseline_rps = _rate(len(base), _per_row_insert_s(store, base_id, base))
        q_all, q_few = _hour_queries(store, hour_id, rows, repeats)
        out: dict[str, Any] = {
            "rows": len(rows),
            "fleet_vehicles": fleet_vehicles,
            "insert_one_commit_per_row_rows_per_s": baseline_rps,
            "insert_baseline_rows": len(base),
            "insert_speedup": inserts["current"]["insert_batched"]["rows_per_s"] / baseline_rps,
            "query_all_fields": q_all,
            "query_few_fields": q_few,
            "column_layout": None,
            "query_all_fields_column_read": None,
        }
        _add_insert_cases(out, inserts)
        if column_layout is not None:
            out["query_all_fields_column_read"] = _column_read(column_layout, rows, repeats)
        return out
    finally:
        store.delete_vehicle(hour_id)
        store.delete_vehicle(base_id)


def _write_hour(store: Store, hour_id: str, rows: np.ndarray) -> None:
    """Write the hour's rows and move them to where they stay."""
    store.write_estimates([(hour_id, rows)])
    # the hour read from where it stays: SQLite's staging table keeps only recent rows
    maintain = getattr(store, "maintain", None)
    while maintain is not None and maintain(everything=True):
        pass


def _per_row_insert_s(store: Store, base_id: str, base: np.ndarray) -> float:
    """Seconds to write ``base`` one transaction per row (the baseline)."""
    t0 = time.perf_counter()
    for i in range(len(base)):
        store.write_estimates([(base_id, base[i : i + 1])])
    return time.perf_counter() - t0


def _hour_queries(
    store: Store, hour_id: str, rows: np.ndarray, repeats: int
) -> tuple[dict[str, Any], dict[str, Any]]:
    """The hour's series query timed with all fields and with ``FEW_FIELDS``, after checking
    that it returns every row."""
    end_ns = int(rows["stamp_ns"][-1]) + 1
    start_ns = int(rows["stamp_ns"][0])
    got = store.query_series(hour_id, start_ns, end_ns)
    if len(got) != len(rows):
        raise RuntimeError(f"series query returned {len(got)} of {len(rows)} rows")
    q_all = _timed_query(lambda: store.query_series(hour_id, start_ns, end_ns), repeats)
    q_few = _timed_query(lambda: store.query_series(hour_id, start_ns, end_ns, FEW_FIELDS), repeats)
    return q_all, q_few


def _add_insert_cases(out: dict[str, Any], inserts: dict[str, dict[str, dict[str, float]]]) -> None:
    """Put each insert case's figures into ``out`` as ``<case>_<key>``, and the column
    layout's (when measured) into ``out["column_layout"]`` with their cost ratios."""
    for case in _INSERT_CASES:
        for key, value in inserts["current"][case].items():
            out[f"{case}_{key}"] = value
    if "column_layout" in inserts:
        old = out["column_layout"] = {}
        for case in _INSERT_CASES:
            for key, value in inserts["column_layout"][case].items():
                old[f"{case}_{key}"] = value
            # how many times cheaper a row is now than in the column layout
            old[f"{case}_cost_ratio"] = old[f"{case}_us_per_row"] / out[f"{case}_us_per_row"]


@contextmanager
def _sqlite_store(name: str, cls: type[_S]) -> Iterator[_S]:
    with tempfile.TemporaryDirectory(prefix="slipfleet-bench-") as tmp:
        store = cls(Path(tmp) / name)
        try:
            store.migrate()
            yield store
        finally:
            store.close()


@contextmanager
def _postgres_store(url: str) -> Iterator[Store]:
    import psycopg

    from server.storage.postgres import PostgresStore
    from server.tooling.pgadmin import create_database, drop_database

    name = f"slipfleet_bench_{uuid.uuid4().hex[:10]}"
    try:
        db_url: str | None = create_database(url, name)
    except psycopg.Error:
        db_url = None  # no CREATEDB: use the configured database
    store = PostgresStore(db_url or url)
    try:
        store.migrate()
        yield store
    finally:
        store.close()
        if db_url is not None:
            drop_database(url, name)


def run(
    json_path: str | Path | None = None,
    *,
    postgres_url: str | None = None,
    rows: int = VEHICLE_HOUR_ROWS,
    baseline_rows: int = 2000,
    repeats: int = 7,
    fleet_vehicles: int = FLEET_VEHICLES,
) -> dict[str, Any]:
    """Run the benchmark; print a table; write JSON to ``json_path`` if given; return results."""
    data = synthetic_hour(rows)
    results: dict[str, Any] = {
        "rows": rows,
        "rate_hz": RATE_HZ,
        "few_fields": ["stamp_ns", *FEW_FIELDS],
        "target_ms": TARGET_MS,
        "backends": {},
    }
    fleet_vehicles = max(1, min(fleet_vehicles, len(data) // RATE_HZ))
    with (
        _sqlite_store("bench.sqlite", SqliteStore) as store,
        _sqlite_store("column-layout.sqlite", ColumnLayoutStore) as old,
    ):
        results["backends"]["sqlite"] = _bench_store(
            store, data, baseline_rows, repeats, fleet_vehicles, old
        )
    if postgres_url:
        with _postgres_store(postgres_url) as store:
            results["backends"]["postgresql"] = _bench_store(
                store, data, baseline_rows, repeats, fleet_vehicles
            )
    print(format_table(results))
    if json_path is not None:
        Path(json_path).write_text(json.dumps(results, indent=2) + "\n")
    return results


def _yes(ok: bool) -> str:
    return "yes" if ok else "NO"


def format_table(results: dict[str, Any]) -> str:
    """The results as fixed-width text tables: inserts, then series queries side by side."""
    lines = [
        f"storage benchmark: one vehicle-hour = {results['rows']} rows at {results['rate_hz']} Hz",
        f"{'backend':<11} {'metric':<42} {'value':>14}",
    ]
    for name, r in results["backends"].items():
        entries = [
            (
                "insert, one commit per row (rows/s)",
                f"{r['insert_one_commit_per_row_rows_per_s']:,.0f}",
            ),
            ("insert speed-up, batched / per-row", f"{r['insert_speedup']:,.1f}x"),
        ]
        for metric, value in entries:
            lines.append(f"{name:<11} {metric:<42} {value:>14}")
    lines += _writer_lines(results["backends"])
    lines += _query_lines(results)
    return "\n".join(lines)


def _writer_lines(backends: dict[str, Any]) -> list[str]:
    """The table of inserts through the batched writer, each backend against its column layout."""
    lines = [
        "",
        "insert through the batched writer (1-second packets of 10 rows); column layout = the"
        " SQLite schema before version 6",
        f"{'backend':<11} {'case':<24} {'rows/s':>10} {'us/row':>8} {'txns':>5}"
        f" {'column layout rows/s':>21} {'us/row':>8} {'cost ratio':>11}",
    ]
    for name, r in backends.items():
        old = r.get("column_layout")
        for label, key in (
            ("one vehicle", "insert_batched"),
            (f"{r['fleet_vehicles']} vehicles", "insert_batched_fleet"),
        ):
            line = (
                f"{name:<11} {label:<24} {r[key + '_rows_per_s']:>10,.0f}"
                f" {r[key + '_us_per_row']:>8.2f} {r[key + '_transactions']:>5}"
            )
            if old:
                line += (
                    f" {old[key + '_rows_per_s']:>21,.0f} {old[key + '_us_per_row']:>8.2f}"
                    f" {old[key + '_cost_ratio']:>10.2f}x"
                )
            lines.append(line)
    return lines


def _query_lines(results: dict[str, Any]) -> list[str]:
    """The table of series queries, quiet and beside a busy thread, and the column read's ratio."""
    lines = [
        "",
        f"series query over the hour, warm, median / best (ms); target < {results['target_ms']:.0f}"
        " ms median",
        f"{'backend':<11} {'fields':<31} {'quiet':>15} {'busy thread':>15} {'busy/quiet':>11}"
        f" {'target (quiet / busy)':>22}",
    ]
    for name, r in results["backends"].items():
        cases = [("all 27", r["query_all_fields"]), ("5", r["query_few_fields"])]
        if r.get("query_all_fields_column_read"):
            cases.append(("all 27, column read (baseline)", r["query_all_fields_column_read"]))
        for label, q in cases:
            busy = q["busy_thread"]
            lines.append(
                f"{name:<11} {label:<31} {q['median_ms']:>7.1f} / {q['best_ms']:<5.1f}"
                f" {busy['median_ms']:>7.1f} / {busy['best_ms']:<5.1f}"
                f" {q['busy_slowdown']:>10.1f}x"
                f" {_yes(q['meets_target']) + ' / ' + _yes(busy['meets_target']):>22}"
            )
    for name, r in results["backends"].items():
        base = r.get("query_all_fields_column_read")
        if base:
            ratio = base["median_ms"] / r["query_all_fields"]["median_ms"]
            lines.append(f"{name}: packed read is {ratio:.1f}x faster than the column read")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    parser.add_argument("--json", type=Path, help="write the results here")
    parser.add_argument(
        "--postgres", action="store_true", help="also PostgreSQL at SLIPFLEET_STORAGE__URL"
    )
    parser.add_argument("--rows", type=int, default=VEHICLE_HOUR_ROWS)
    parser.add_argument("--baseline-rows", type=int, default=2000)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument(
        "--fleet-vehicles", type=int, default=FLEET_VEHICLES, help="vehicles of the fleet insert"
    )
    args = parser.parse_args(argv)
    url: str | None = None
    if args.postgres:
        from server.settings import load_settings

        secret = load_settings().storage.url
        if secret is None:
            parser.error("--postgres needs SLIPFLEET_STORAGE__URL (or storage.url in the config)")
        url = secret.get_secret_value()
    run(
        args.json,
        postgres_url=url,
        rows=args.rows,
        baseline_rows=args.baseline_rows,
        repeats=args.repeats,
        fleet_vehicles=args.fleet_vehicles,
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
