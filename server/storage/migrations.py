"""Versioned schema migrations for both dialects.

Each :class:`Migration` has a version number, a description and the steps for SQLite and for
PostgreSQL: SQL statements, or a Python function given the same ``execute`` (for data a
statement cannot convert, such as packing SQLite rows in version 6). Applied versions are
recorded in ``schema_version``. A migration is frozen once released: later schema changes are
new migrations, never edits. The field lists a migration makes tables from are frozen in it
(:data:`SQLITE_PACKED_FIELDS`, :data:`REFERENCE_SPEED_FIELDS_V10`,
:data:`FRICTION_FIELDS_V12`, :data:`TRACKED_FIELDS_V13`, :data:`MDSF_FIELDS_V15`,
:data:`FRICTION_FIELDS_V16`, :data:`TRACKED_FIELDS_V17`, :data:`TRACKED_FIELDS_V18`,
:data:`FRICTION_FIELDS_V19`, :data:`TRACKED_FIELDS_V20`); tests
compare them with today's specs, and the stores refuse a spec that no longer matches its
recorded table, so a spec change forces a new migration.

Applying is idempotent and safe when several processes start at once:

* PostgreSQL: everything runs in one transaction holding a transaction-scoped advisory lock
  (:data:`ADVISORY_LOCK_KEY`); DDL is transactional, so a failed migration leaves nothing behind.
* SQLite: everything runs in one ``BEGIN IMMEDIATE`` transaction (the database write lock);
  SQLite DDL is transactional too.

Schema (version 20):

``vehicles``
    ``vkey`` small integer surrogate key, ``vehicle_id`` (unique text), ``config`` (JSON text /
    ``jsonb``), ``created_ns``, ``updated_ns``. Since version 11 every config names its
    ``kind`` and has that kind's sections (:mod:`estimator.config`).
``estimator_tables`` (version 10)
    ``estimator`` (spec name) -> ``table_name``, ``fields`` (JSON ``[[name, kind], …]``): the
    tables of each estimator's rows and the field list they were made from; a store refuses a
    spec whose fields differ. MDSF's are ``estimates`` below; every other estimator's are made
    by :func:`estimator_table_steps` in the same layout, ``estimates_<name>`` (and on SQLite
    ``…_recent`` and ``…_horizon``, as ``estimates_recent`` and ``estimates_horizon``):
    ``reference_speed`` since version 10, ``friction`` since version 12 (its position
    appended by version 16, the speed's 1-sigma by 19), ``tracked`` since 13 (its online
    calibration appended by 17, the hull's attitude by 18, the receiver's clock by 20).
``estimates``
    MDSF's rows. Primary key ``(vkey, stamp_ns)`` so one vehicle-hour is a single index range
    read.
    PostgreSQL: ``vkey`` + a column per field of MDSF's spec, all ``NOT NULL`` (NaN is stored
    natively). SQLite (since version 6): ``vkey``, ``stamp_ns`` and ``packed``, the whole row as
    its bytes (layout :data:`MDSF_FIELDS_V15`, little-endian; :data:`SQLITE_PACKED_FIELDS`
    before version 15, which appended the online calibration's fields), in a
    clustered ``WITHOUT ROWID`` table; versions 1-5 had every field as a column (NaN as NULL)
    and, from version 3, ``packed`` beside them.
``estimates_recent`` (SQLite, version 7)
    New rows land here first, keyed ``(stamp_ns, vkey)`` so a commit of one row per vehicle
    appends to a few pages instead of touching one page per vehicle; the store moves them to
    ``estimates`` a few seconds later, many rows per vehicle at a time
    (:meth:`~server.storage.sqlite.SqliteStore.maintain`). Reads look at both.
``estimates_horizon`` (SQLite, version 8)
    One row: ``newest_ns``, at or above the ``stamp_ns`` of every row in ``estimates`` (raised
    before rows move there), so a new row above it is known not to be a replay of a moved one.
``ingest_counters``
    ``(vehicle_id, name) -> total``; keyed by the id text so counters of vehicles that were
    rejected (never registered) can be kept too.
``raw_packets`` (version 2; keyed by ``vehicle_id`` text since version 5)
    received payloads when ``StorageSettings.store_raw_packets`` is on, as they arrived, also
    from vehicles not (yet) registered; deleted with their vehicle and by retention.
``vehicle_anchors`` (version 9)
    ``vehicle_id`` (text key, like the counters) -> ``lat_deg``, ``lon_deg``, ``height_m``: the
    origin of the vehicle's local ENU frame (``east_m``, ``north_m``, ``up_m`` of its estimates),
    its first GNSS fix with a position; kept so that a restarted server goes on in the same
    frame. Written once; deleted with the vehicle.
``api_tokens`` (version 4; ``expires_ns`` version 14)
    REST bearer tokens: ``id``, ``name``, ``role`` (``viewer`` / ``operator`` / ``admin``),
    ``token_sha256`` (hex SHA-256 of the token, unique; the token itself is never stored),
    ``created_ns``, ``last_used_ns`` and ``revoked_ns`` (NULL while never used / not revoked),
    ``expires_ns`` (NULL: never expires; from then on the token is refused like a revoked one).
"""

from __future__ import annotations

import json
import re
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from estimator.config import VehicleKind, upgrade_legacy_config
from server.storage.base import StorageError

__all__ = [
    "ADVISORY_LOCK_KEY",
    "FRICTION_FIELDS_V12",
    "FRICTION_FIELDS_V16",
    "FRICTION_FIELDS_V19",
    "MDSF_FIELDS_V15",
    "MIGRATIONS",
    "REFERENCE_SPEED_FIELDS_V10",
    "SQLITE_PACKED_FIELDS",
    "TRACKED_FIELDS_V13",
    "TRACKED_FIELDS_V17",
    "TRACKED_FIELDS_V18",
    "TRACKED_FIELDS_V20",
    "Execute",
    "Migration",
    "Step",
    "estimator_table_steps",
    "fields_json",
    "latest_version",
]

#: Key of the PostgreSQL advisory lock that serialises migrations (ASCII "slipflt1").
ADVISORY_LOCK_KEY = 0x736C6970666C7431

#: ``execute(sql, params)`` runs one statement in the migration's transaction, returns its rows.
Execute = Callable[[str, tuple[Any, ...]], list[tuple[Any, ...]]]
#: A migration step: one SQL statement, or a function that runs statements through ``execute``.
Step = str | Callable[[Execute], None]


@dataclass(frozen=True, slots=True)
class Migration:
    """One schema step."""

    version: int
    description: str
    sqlite: tuple[Step, ...]
    postgresql: tuple[Step, ...]

    def statements(self, dialect: str) -> tuple[Step, ...]:
        if dialect == "sqlite":
            return self.sqlite
        if dialect == "postgresql":
            return self.postgresql
        raise ValueError(f"unknown dialect {dialect!r}")


_V1_SQLITE = (
    """
    CREATE TABLE vehicles (
        vkey INTEGER PRIMARY KEY,
        vehicle_id TEXT NOT NULL UNIQUE,
        config TEXT NOT NULL,
        created_ns INTEGER NOT NULL,
        updated_ns INTEGER NOT NULL
    )
    """,
    """
    CREATE TABLE estimates (
        vkey INTEGER NOT NULL REFERENCES vehicles (vkey) ON DELETE CASCADE,
        stamp_ns INTEGER NOT NULL,
        vg_mps REAL,
        v1_mps REAL,
        v0_mps REAL,
        vl_mps REAL,
        vr_mps REAL,
        rim_left_mps REAL,
        rim_right_mps REAL,
        omega_left_radps REAL,
        omega_right_radps REAL,
        slip_left_pct REAL,
        slip_right_pct REAL,
        vg_std_mps REAL,
        vl_std_mps REAL,
        vr_std_mps REAL,
        slip_left_std_pct REAL,
        slip_right_std_pct REAL,
        accel_mps2 REAL,
        pitch_rate_radps REAL,
        yaw_rate_radps REAL,
        east_m REAL,
        north_m REAL,
        up_m REAL,
        heading_rad REAL,
        pitch_rad REAL,
        roll_rad REAL,
        flags INTEGER NOT NULL,
        PRIMARY KEY (vkey, stamp_ns)
    ) WITHOUT ROWID
    """,
    """
    CREATE TABLE ingest_counters (
        vehicle_id TEXT NOT NULL,
        name TEXT NOT NULL,
        total INTEGER NOT NULL,
        updated_ns INTEGER NOT NULL,
        PRIMARY KEY (vehicle_id, name)
    ) WITHOUT ROWID
    """,
)

_V1_POSTGRESQL = (
    """
    CREATE TABLE vehicles (
        vkey integer GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
        vehicle_id text NOT NULL UNIQUE,
        config jsonb NOT NULL,
        created_ns bigint NOT NULL,
        updated_ns bigint NOT NULL
    )
    """,
    """
    CREATE TABLE estimates (
        vkey integer NOT NULL REFERENCES vehicles (vkey) ON DELETE CASCADE,
        stamp_ns bigint NOT NULL,
        vg_mps double precision NOT NULL,
        v1_mps double precision NOT NULL,
        v0_mps double precision NOT NULL,
        vl_mps double precision NOT NULL,
        vr_mps double precision NOT NULL,
        rim_left_mps double precision NOT NULL,
        rim_right_mps double precision NOT NULL,
        omega_left_radps double precision NOT NULL,
        omega_right_radps double precision NOT NULL,
        slip_left_pct double precision NOT NULL,
        slip_right_pct double precision NOT NULL,
        vg_std_mps double precision NOT NULL,
        vl_std_mps double precision NOT NULL,
        vr_std_mps double precision NOT NULL,
        slip_left_std_pct double precision NOT NULL,
        slip_right_std_pct double precision NOT NULL,
        accel_mps2 double precision NOT NULL,
        pitch_rate_radps double precision NOT NULL,
        yaw_rate_radps double precision NOT NULL,
        east_m double precision NOT NULL,
        north_m double precision NOT NULL,
        up_m double precision NOT NULL,
        heading_rad double precision NOT NULL,
        pitch_rad double precision NOT NULL,
        roll_rad double precision NOT NULL,
        flags integer NOT NULL,
        PRIMARY KEY (vkey, stamp_ns)
    )
    """,
    """
    CREATE TABLE ingest_counters (
        vehicle_id text NOT NULL,
        name text NOT NULL,
        total bigint NOT NULL,
        updated_ns bigint NOT NULL,
        PRIMARY KEY (vehicle_id, name)
    )
    """,
)

_V2_SQLITE = (
    """
    CREATE TABLE raw_packets (
        id INTEGER PRIMARY KEY,
        vkey INTEGER NOT NULL REFERENCES vehicles (vkey) ON DELETE CASCADE,
        received_ns INTEGER NOT NULL,
        key TEXT NOT NULL,
        payload BLOB NOT NULL
    )
    """,
    "CREATE INDEX raw_packets_vkey_received ON raw_packets (vkey, received_ns)",
)

_V2_POSTGRESQL = (
    """
    CREATE TABLE raw_packets (
        id bigint GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
        vkey integer NOT NULL REFERENCES vehicles (vkey) ON DELETE CASCADE,
        received_ns bigint NOT NULL,
        key text NOT NULL,
        payload bytea NOT NULL
    )
    """,
    "CREATE INDEX raw_packets_vkey_received ON raw_packets (vkey, received_ns)",
)

# SQLite only: every estimate row also as its packed ESTIMATE_DTYPE bytes, so a range read is
# one Python object per row instead of one per value (see server.storage.sqlite). PostgreSQL
# reads columns through binary COPY and needs no such copy.
_V3_SQLITE = ("ALTER TABLE estimates ADD COLUMN packed BLOB",)

_V4_SQLITE = (
    """
    CREATE TABLE api_tokens (
        id INTEGER PRIMARY KEY,
        name TEXT NOT NULL,
        role TEXT NOT NULL CHECK (role IN ('viewer', 'operator', 'admin')),
        token_sha256 TEXT NOT NULL UNIQUE,
        created_ns INTEGER NOT NULL,
        last_used_ns INTEGER,
        revoked_ns INTEGER
    )
    """,
)

_V4_POSTGRESQL = (
    """
    CREATE TABLE api_tokens (
        id bigint GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
        name text NOT NULL,
        role text NOT NULL CHECK (role IN ('viewer', 'operator', 'admin')),
        token_sha256 text NOT NULL UNIQUE,
        created_ns bigint NOT NULL,
        last_used_ns bigint,
        revoked_ns bigint
    )
    """,
)

# Raw packets are kept as they arrived, also before (or without) the vehicle's registration, so
# they are keyed by the vehicle id text like the ingest counters, not by the vehicles table.
_V5_SQLITE = (
    """
    CREATE TABLE raw_packets_by_id (
        id INTEGER PRIMARY KEY,
        vehicle_id TEXT NOT NULL,
        received_ns INTEGER NOT NULL,
        key TEXT NOT NULL,
        payload BLOB NOT NULL
    )
    """,
    "INSERT INTO raw_packets_by_id (vehicle_id, received_ns, key, payload) "
    "SELECT v.vehicle_id, r.received_ns, r.key, r.payload "
    "FROM raw_packets r JOIN vehicles v ON v.vkey = r.vkey ORDER BY r.id",
    "DROP TABLE raw_packets",
    "ALTER TABLE raw_packets_by_id RENAME TO raw_packets",
    "CREATE INDEX raw_packets_vehicle_received ON raw_packets (vehicle_id, received_ns)",
)

_V5_POSTGRESQL = (
    "ALTER TABLE raw_packets ADD COLUMN vehicle_id text",
    "UPDATE raw_packets r SET vehicle_id = v.vehicle_id FROM vehicles v WHERE v.vkey = r.vkey",
    "ALTER TABLE raw_packets ALTER COLUMN vehicle_id SET NOT NULL",
    "DROP INDEX raw_packets_vkey_received",
    "ALTER TABLE raw_packets DROP COLUMN vkey",
    "CREATE INDEX raw_packets_vehicle_received ON raw_packets (vehicle_id, received_ns)",
)

#: The field layout of MDSF's rows in its tables (SQLite: packed from version 6 on, without
#: padding, little-endian; PostgreSQL: the columns of version 1), ``(name, numpy kind)``. Frozen
#: with the migrations: when MDSF's spec changes, a new migration converts the rows (a test
#: compares the two).
SQLITE_PACKED_FIELDS: tuple[tuple[str, str], ...] = (
    ("stamp_ns", "i8"),
    *(
        (name, "f8")
        for name in (
            "vg_mps",
            "v1_mps",
            "v0_mps",
            "vl_mps",
            "vr_mps",
            "rim_left_mps",
            "rim_right_mps",
            "omega_left_radps",
            "omega_right_radps",
            "slip_left_pct",
            "slip_right_pct",
            "vg_std_mps",
            "vl_std_mps",
            "vr_std_mps",
            "slip_left_std_pct",
            "slip_right_std_pct",
            "accel_mps2",
            "pitch_rate_radps",
            "yaw_rate_radps",
            "east_m",
            "north_m",
            "up_m",
            "heading_rad",
            "pitch_rad",
            "roll_rad",
        )
    ),
    ("flags", "i4"),
)
_V6_PACKED_DTYPE = np.dtype([(name, "<" + kind) for name, kind in SQLITE_PACKED_FIELDS])
_V6_REPACK_PAGE_ROWS = 10_000


def _v6_pack_remaining_rows(execute: Execute) -> None:
    """Pack the rows that have no packed bytes of the version-6 layout (rows written before
    version 3) from their columns into ``estimates_v6``, a page at a time (bounded memory)."""
    # NULL is how SQLite stored NaN: as the text 'nan' numpy parses it back while filling.
    select = ", ".join(
        f"coalesce({n}, 'nan')" if kind == "f8" else n for n, kind in SQLITE_PACKED_FIELDS
    )
    after = (-(2**63), -(2**63))
    while True:
        rows = execute(
            f"SELECT vkey, {select} FROM estimates "
            "WHERE (packed IS NULL OR length(packed) != ?) AND (vkey, stamp_ns) > (?, ?) "
            f"ORDER BY vkey, stamp_ns LIMIT {_V6_REPACK_PAGE_ROWS}",
            (_V6_PACKED_DTYPE.itemsize, *after),
        )
        if not rows:
            return
        buf = np.array([r[1:] for r in rows], dtype=_V6_PACKED_DTYPE).tobytes()
        size = _V6_PACKED_DTYPE.itemsize
        for i, row in enumerate(rows):
            execute(
                "INSERT INTO estimates_v6 (vkey, stamp_ns, packed) VALUES (?, ?, ?)",
                (row[0], row[1], buf[i * size : (i + 1) * size]),
            )
        after = (rows[-1][0], rows[-1][1])


# SQLite keeps each estimate row only packed: no column values to bind makes a write several
# times cheaper (server.storage.sqlite), and every read already used the blob. Rows that carry
# packed bytes move in SQL; older ones are packed from their columns in Python. The freed pages
# of the old table are reused by new rows (the file does not shrink without a VACUUM).
_V6_SQLITE: tuple[Step, ...] = (
    """
    CREATE TABLE estimates_v6 (
        vkey INTEGER NOT NULL REFERENCES vehicles (vkey) ON DELETE CASCADE,
        stamp_ns INTEGER NOT NULL,
        packed BLOB NOT NULL,
        PRIMARY KEY (vkey, stamp_ns)
    ) WITHOUT ROWID
    """,
    "INSERT INTO estimates_v6 (vkey, stamp_ns, packed) SELECT vkey, stamp_ns, packed "
    f"FROM estimates WHERE length(packed) = {_V6_PACKED_DTYPE.itemsize} ORDER BY vkey, stamp_ns",
    _v6_pack_remaining_rows,
    "DROP TABLE estimates",
    "ALTER TABLE estimates_v6 RENAME TO estimates",
)

_V7_SQLITE: tuple[Step, ...] = (
    """
    CREATE TABLE estimates_recent (
        stamp_ns INTEGER NOT NULL,
        vkey INTEGER NOT NULL,
        packed BLOB NOT NULL,
        PRIMARY KEY (stamp_ns, vkey)
    ) WITHOUT ROWID
    """,
)

# A staged row was checked against ``estimates`` one by one (a replay of a row moved already
# is not staged again), ~2.5 µs of the ~6 µs a row of a write at 1,000 vehicles; no row of
# ``estimates`` is newer than this bound, so rows above it skip that look-up. Seeded with the
# newest final row of every vehicle (a primary-key seek each; a foreign key ties every row to
# a vehicle).
_V8_SQLITE: tuple[Step, ...] = (
    """
    CREATE TABLE estimates_horizon (
        id INTEGER PRIMARY KEY CHECK (id = 0),
        newest_ns INTEGER NOT NULL
    )
    """,
    "INSERT INTO estimates_horizon (id, newest_ns) SELECT 0, coalesce(max("
    "(SELECT max(e.stamp_ns) FROM estimates e WHERE e.vkey = v.vkey)), -9223372036854775808) "
    "FROM vehicles v",
)

# Each vehicle's ENU anchor. Before this, a restarted server anchored the frame at the first
# fix it saw, so east/north of rows stored before and after a restart lay in different frames.
_V9_SQLITE: tuple[Step, ...] = (
    """
    CREATE TABLE vehicle_anchors (
        vehicle_id TEXT PRIMARY KEY,
        lat_deg REAL NOT NULL,
        lon_deg REAL NOT NULL,
        height_m REAL NOT NULL,
        set_ns INTEGER NOT NULL
    )
    """,
)
_V9_POSTGRESQL: tuple[Step, ...] = (
    """
    CREATE TABLE vehicle_anchors (
        vehicle_id text PRIMARY KEY,
        lat_deg double precision NOT NULL,
        lon_deg double precision NOT NULL,
        height_m double precision NOT NULL,
        set_ns bigint NOT NULL
    )
    """,
)

# --- one set of tables per estimator -------------------------------------------------------
# An estimator's rows live in tables of their own, named after it, laid out as MDSF's have been
# since versions 6-8: the SQLite write path (staging table, horizon, paced moves) and the
# PostgreSQL COPY path then serve every estimator unchanged. ``estimator_tables`` records which
# field list each table was made from; the stores refuse a spec whose fields differ (its rows
# would not fit), until a migration converts the table.

_IDENTIFIER = re.compile(r"[a-z][a-z0-9_]*")
_SQL_TYPE = {
    "sqlite": {"f8": "REAL", "i8": "INTEGER", "i4": "INTEGER"},
    "postgresql": {"f8": "double precision", "i8": "bigint", "i4": "integer"},
}


def fields_json(fields: tuple[tuple[str, str], ...]) -> str:
    """How ``estimator_tables.fields`` records a field list: ``[[name, numpy kind], …]``."""
    return json.dumps([list(f) for f in fields], separators=(",", ":"))


def estimator_table_steps(
    estimator: str, table: str, fields: tuple[tuple[str, str], ...], dialect: str
) -> tuple[Step, ...]:
    """Create the tables of ``estimator``'s rows and record them in ``estimator_tables``.

    ``fields`` is the spec's ``(name, kind)`` list *frozen in the migration* (a later spec
    change is a later migration). SQLite: ``table (vkey, stamp_ns, packed)`` (the row's bytes,
    little-endian, no padding), ``table_recent`` (staging, keyed ``(stamp_ns, vkey)``) and
    ``table_horizon`` (the bound on the stamps in ``table``); PostgreSQL: ``table (vkey,
    <fields>)``, every column ``NOT NULL``. Both keyed ``(vkey, stamp_ns)``.
    """
    if fields[0] != ("stamp_ns", "i8"):
        raise ValueError(f"{estimator}: the first field must be stamp_ns (i8)")
    for name in (estimator, table, *(n for n, _ in fields)):
        if not _IDENTIFIER.fullmatch(name):
            raise ValueError(f"{estimator}: {name!r} is not a plain lower-case SQL identifier")
    record = (
        "INSERT INTO estimator_tables (estimator, table_name, fields) "
        f"VALUES ('{estimator}', '{table}', '{fields_json(fields)}')"
    )
    if dialect == "postgresql":
        columns = ",\n".join(f"{name} {_SQL_TYPE[dialect][kind]} NOT NULL" for name, kind in fields)
        return (
            f"CREATE TABLE {table} (\n"
            "vkey integer NOT NULL REFERENCES vehicles (vkey) ON DELETE CASCADE,\n"
            f"{columns},\nPRIMARY KEY (vkey, stamp_ns))",
            record,
        )
    return (
        f"CREATE TABLE {table} ("
        " vkey INTEGER NOT NULL REFERENCES vehicles (vkey) ON DELETE CASCADE,"
        " stamp_ns INTEGER NOT NULL, packed BLOB NOT NULL,"
        " PRIMARY KEY (vkey, stamp_ns)) WITHOUT ROWID",
        f"CREATE TABLE {table}_recent ("
        " stamp_ns INTEGER NOT NULL, vkey INTEGER NOT NULL, packed BLOB NOT NULL,"
        " PRIMARY KEY (stamp_ns, vkey)) WITHOUT ROWID",
        f"CREATE TABLE {table}_horizon ("
        " id INTEGER PRIMARY KEY CHECK (id = 0), newest_ns INTEGER NOT NULL)",
        f"INSERT INTO {table}_horizon (id, newest_ns) VALUES (0, -9223372036854775808)",
        record,
    )


_ESTIMATOR_TABLES = {
    "sqlite": (
        "CREATE TABLE estimator_tables ("
        " estimator TEXT PRIMARY KEY, table_name TEXT NOT NULL UNIQUE, fields TEXT NOT NULL)"
    ),
    "postgresql": (
        "CREATE TABLE estimator_tables ("
        " estimator text PRIMARY KEY, table_name text NOT NULL UNIQUE, fields text NOT NULL)"
    ),
}

#: The reference-speed row as version 10 made its table (``REFERENCE_SPEED_SPEC``'s fields).
REFERENCE_SPEED_FIELDS_V10: tuple[tuple[str, str], ...] = (
    ("stamp_ns", "i8"),
    ("speed_mps", "f8"),
    ("speed_std_mps", "f8"),
    ("rim_mps", "f8"),
    ("accel_mps2", "f8"),
    ("accel_bias_mps2", "f8"),
    ("flags", "i4"),
)


def _v10(dialect: str) -> tuple[Step, ...]:
    """The table registry; MDSF's existing tables (``estimates``, the layout of versions 1 and
    6, rows untouched) recorded as its own; the reference speed's tables created."""
    return (
        _ESTIMATOR_TABLES[dialect],
        "INSERT INTO estimator_tables (estimator, table_name, fields) "
        f"VALUES ('mdsf', 'estimates', '{fields_json(SQLITE_PACKED_FIELDS)}')",
        *estimator_table_steps(
            "reference_speed", "estimates_reference_speed", REFERENCE_SPEED_FIELDS_V10, dialect
        ),
    )


#: The friction row as version 12 made its table (``FRICTION_SPEC``'s fields).
FRICTION_FIELDS_V12: tuple[tuple[str, str], ...] = (
    ("stamp_ns", "i8"),
    ("mu", "f8"),
    ("mu_std", "f8"),
    ("mu_filter", "f8"),
    ("vx_mps", "f8"),
    ("vy_mps", "f8"),
    *(
        (f"{quantity}_{wheel}_{unit}", "f8")
        for wheel in ("fl", "fr", "rl", "rr")
        for quantity, unit in (("fz", "n"), ("slip", "pct"), ("alpha", "rad"), ("util", "pct"))
    ),
    ("flags", "i4"),
)


#: The tracked estimator's row as version 13 made its table (``TRACKED_SPEC``'s fields).
TRACKED_FIELDS_V13: tuple[tuple[str, str], ...] = (
    ("stamp_ns", "i8"),
    ("motion_state", "i4"),
    ("state_confidence", "f8"),
    ("speed_mps", "f8"),
    ("speed_std_mps", "f8"),
    ("lateral_mps", "f8"),
    ("yaw_rate_radps", "f8"),
    ("turn_radius_m", "f8"),
    ("track_left_mps", "f8"),
    ("track_right_mps", "f8"),
    ("track_std_mps", "f8"),
    ("sprocket_left_mps", "f8"),
    ("sprocket_right_mps", "f8"),
    ("slip_left_pct", "f8"),
    ("slip_right_pct", "f8"),
    ("slip_left_std_pct", "f8"),
    ("slip_right_std_pct", "f8"),
    ("odometer_raw_mps", "f8"),
    ("odometer_mps", "f8"),
    ("odometer_scale", "f8"),
    ("gyro_bias_radps", "f8"),
    ("east_m", "f8"),
    ("north_m", "f8"),
    ("up_m", "f8"),
    ("heading_rad", "f8"),
    ("lat_deg", "f8"),
    ("lon_deg", "f8"),
    ("east_std_m", "f8"),
    ("north_std_m", "f8"),
    ("east_north_cov_m2", "f8"),
    ("flags", "i4"),
)


#: The friction row as version 16 made its table: version 12's with the position appended.
FRICTION_FIELDS_V16: tuple[tuple[str, str], ...] = (
    *FRICTION_FIELDS_V12,
    ("east_m", "f8"),
    ("north_m", "f8"),
    ("up_m", "f8"),
    ("heading_rad", "f8"),
)


def _v16_friction_position(dialect: str) -> tuple[Step, ...]:
    """Append the friction row's position fields to its tables, NaN in the rows stored before
    (the estimator gave no position then). SQLite: NaN's little-endian bytes appended to each
    packed row, staged or final; PostgreSQL: ``NOT NULL`` columns filled with NaN."""
    added = FRICTION_FIELDS_V16[len(FRICTION_FIELDS_V12) :]
    record = (
        f"UPDATE estimator_tables SET fields = '{fields_json(FRICTION_FIELDS_V16)}' "
        "WHERE estimator = 'friction'"
    )
    if dialect == "postgresql":
        return (
            *(
                f"ALTER TABLE estimates_friction ADD COLUMN {name} double precision "
                "NOT NULL DEFAULT 'NaN'"
                for name, _ in added
            ),
            *(
                f"ALTER TABLE estimates_friction ALTER COLUMN {name} DROP DEFAULT"
                for name, _ in added
            ),
            record,
        )
    nan_bytes = np.full(len(added), np.nan, dtype="<f8").tobytes().hex().upper()
    return (
        *(
            f"UPDATE {table} SET packed = packed || X'{nan_bytes}'"
            for table in ("estimates_friction", "estimates_friction_recent")
        ),
        record,
    )


#: The tracked row as version 17 made its table: version 13's with the gyro's noise measured
#: standing appended (the online calibration, ``TRACKED_SPEC.calibrations``).
TRACKED_FIELDS_V17: tuple[tuple[str, str], ...] = (
    *TRACKED_FIELDS_V13,
    ("gyro_arw_deg_rt_h", "f8"),
    ("gyro_arw_std_deg_rt_h", "f8"),
)


def _append_f8_fields(
    estimator: str,
    table: str,
    before: tuple[tuple[str, str], ...],
    after: tuple[tuple[str, str], ...],
    dialect: str,
) -> tuple[Step, ...]:
    """Steps that append ``after``'s fields beyond ``before`` (all ``f8``) to an estimator's
    tables (``table`` and, on SQLite, ``table``'s staged ``…_recent``), NaN in the rows stored
    before, and record ``after`` as its field list. SQLite: NaN's little-endian bytes appended
    to each packed row, staged or final; PostgreSQL: ``NOT NULL`` columns filled with NaN, no
    default kept."""
    added = after[len(before) :]
    if after[: len(before)] != before or any(kind != "f8" for _, kind in added):
        raise ValueError(f"{estimator}: only f8 fields may be appended")
    record = (
        f"UPDATE estimator_tables SET fields = '{fields_json(after)}' "
        f"WHERE estimator = '{estimator}'"
    )
    if dialect == "postgresql":
        steps: list[Step] = []
        for name, _ in added:
            steps.append(
                f"ALTER TABLE {table} ADD COLUMN {name} double precision NOT NULL DEFAULT 'NaN'"
            )
            steps.append(f"ALTER TABLE {table} ALTER COLUMN {name} DROP DEFAULT")
        return (*steps, record)
    nan = "X'" + _NAN_F8_LE * len(added) + "'"
    return (
        # ``||`` yields text; the cast gives its bytes back unchanged as a blob
        *(
            f"UPDATE {t} SET packed = CAST(packed || {nan} AS BLOB)"
            for t in (table, f"{table}_recent")
        ),
        record,
    )


def _v17_tracked_calibration(dialect: str) -> tuple[Step, ...]:
    """Append the tracked row's calibration fields to its tables, NaN in the rows stored
    before (nothing was measured then, as far as the rows say)."""
    return _append_f8_fields(
        "tracked", "estimates_tracked", TRACKED_FIELDS_V13, TRACKED_FIELDS_V17, dialect
    )


#: The tracked row as version 18 made its table: version 17's with the hull's attitude
#: appended (pitch and roll and their 1-sigma, ``TRACKED_SPEC``'s position channel).
TRACKED_FIELDS_V18: tuple[tuple[str, str], ...] = (
    *TRACKED_FIELDS_V17,
    ("pitch_rad", "f8"),
    ("pitch_std_rad", "f8"),
    ("roll_rad", "f8"),
    ("roll_std_rad", "f8"),
)


def _v18_tracked_attitude(dialect: str) -> tuple[Step, ...]:
    """Append the tracked row's pitch and roll (and their 1-sigma) to its tables, NaN in the
    rows stored before (the rows gave no attitude then)."""
    return _append_f8_fields(
        "tracked", "estimates_tracked", TRACKED_FIELDS_V17, TRACKED_FIELDS_V18, dialect
    )


#: The friction row as version 19 made its table: version 16's with the speed's 1-sigma appended.
FRICTION_FIELDS_V19: tuple[tuple[str, str], ...] = (
    *FRICTION_FIELDS_V16,
    ("vx_std_mps", "f8"),
)


def _v19_friction_speed_std(dialect: str) -> tuple[Step, ...]:
    """Append the friction row's speed 1-sigma to its tables, NaN in the rows stored before
    (the rows stated none then)."""
    return _append_f8_fields(
        "friction", "estimates_friction", FRICTION_FIELDS_V16, FRICTION_FIELDS_V19, dialect
    )


#: The tracked row as version 20 made its table: version 18's with the GNSS receiver's clock
#: appended (its offset and 1-sigma, the second of ``TRACKED_SPEC.calibrations``).
TRACKED_FIELDS_V20: tuple[tuple[str, str], ...] = (
    *TRACKED_FIELDS_V18,
    ("gnss_clock_offset_s", "f8"),
    ("gnss_clock_offset_std_s", "f8"),
)


def _v20_tracked_clock(dialect: str) -> tuple[Step, ...]:
    """Append the tracked row's GNSS clock offset (and its 1-sigma) to its tables, NaN in the
    rows stored before (the rows gave no clock then)."""
    return _append_f8_fields(
        "tracked", "estimates_tracked", TRACKED_FIELDS_V18, TRACKED_FIELDS_V20, dialect
    )


def _v11_configs_by_kind(read_sql: str, write_sql: str) -> Callable[[Execute], None]:
    """Rewrite stored configs in the shape of their kind (``estimator.config``), ``kind`` set.

    Configs were written without ``kind`` (meaning a rear-drive vehicle) or, for every kind,
    with the rear-drive sections; :func:`upgrade_legacy_config` maps those. Values are kept
    as they are (a config out of range is still refused when read, as before).
    """

    def step(execute: Execute) -> None:
        for vkey, text in execute(read_sql, ()):
            old = json.loads(text)
            if not isinstance(old, dict):
                continue
            new = upgrade_legacy_config({"kind": VehicleKind.WHEELED_REAR_DRIVE.value, **old})
            if new != old:
                execute(write_sql, (json.dumps(new), vkey))

    return step


_V11_SQLITE: tuple[Step, ...] = (
    _v11_configs_by_kind(
        "SELECT vkey, config FROM vehicles", "UPDATE vehicles SET config = ? WHERE vkey = ?"
    ),
)
_V11_POSTGRESQL: tuple[Step, ...] = (
    _v11_configs_by_kind(
        "SELECT vkey, config::text FROM vehicles",
        "UPDATE vehicles SET config = %s::jsonb WHERE vkey = %s",
    ),
)

#: MDSF's row as version 15 made it: the version-6 layout with the online calibration's values
#: and stds appended (after ``flags``, so a stored row converts by appending bytes).
MDSF_CALIBRATION_FIELDS_V15: tuple[tuple[str, str], ...] = tuple(
    (name, "f8")
    for name in (
        "gnss_clock_offset_s",
        "gnss_clock_offset_std_s",
        "wheel_clock_offset_s",
        "wheel_clock_offset_std_s",
        "radius_left_m",
        "radius_left_std_m",
        "radius_right_m",
        "radius_right_std_m",
        "imu_pitch_mount_rad",
        "imu_pitch_mount_std_rad",
    )
)
MDSF_FIELDS_V15: tuple[tuple[str, str], ...] = (*SQLITE_PACKED_FIELDS, *MDSF_CALIBRATION_FIELDS_V15)

_NAN_F8_LE = "000000000000F87F"
"""A float64 NaN as little-endian bytes (hex): what rows stored before version 15 get for
each calibration field."""


def _v15(dialect: str) -> tuple[Step, ...]:
    """MDSF's rows gain the calibration fields (NaN in the rows stored before): SQLite appends
    their bytes to every packed row (``estimates`` and the staged ``estimates_recent``);
    PostgreSQL adds a ``NOT NULL`` column each (filled with NaN, no default kept)."""
    record = (
        f"UPDATE estimator_tables SET fields = '{fields_json(MDSF_FIELDS_V15)}' "
        "WHERE estimator = 'mdsf'"
    )
    if dialect == "sqlite":
        nan = "X'" + _NAN_F8_LE * len(MDSF_CALIBRATION_FIELDS_V15) + "'"
        return (
            # ``||`` yields text; the cast gives its bytes back unchanged as a blob
            f"UPDATE estimates SET packed = CAST(packed || {nan} AS BLOB)",
            f"UPDATE estimates_recent SET packed = CAST(packed || {nan} AS BLOB)",
            record,
        )
    steps: list[Step] = []
    for name, _ in MDSF_CALIBRATION_FIELDS_V15:
        steps.append(
            f"ALTER TABLE estimates ADD COLUMN {name} double precision NOT NULL DEFAULT 'NaN'"
        )
        steps.append(f"ALTER TABLE estimates ALTER COLUMN {name} DROP DEFAULT")
    return (*steps, record)


MIGRATIONS: tuple[Migration, ...] = (
    Migration(1, "vehicles, estimates, ingest counters", _V1_SQLITE, _V1_POSTGRESQL),
    Migration(2, "raw packets", _V2_SQLITE, _V2_POSTGRESQL),
    Migration(3, "packed estimate rows (SQLite)", _V3_SQLITE, ()),
    Migration(4, "API access tokens (hashed)", _V4_SQLITE, _V4_POSTGRESQL),
    Migration(5, "raw packets keyed by vehicle id", _V5_SQLITE, _V5_POSTGRESQL),
    Migration(6, "estimate rows only packed (SQLite)", _V6_SQLITE, ()),
    Migration(7, "time-ordered table of new estimate rows (SQLite)", _V7_SQLITE, ()),
    Migration(8, "bound on the stamps of final estimate rows (SQLite)", _V8_SQLITE, ()),
    Migration(9, "ENU anchors of the vehicles", _V9_SQLITE, _V9_POSTGRESQL),
    Migration(
        10,
        "a table set per estimator, recorded with its fields",
        _v10("sqlite"),
        _v10("postgresql"),
    ),
    Migration(11, "vehicle configs by kind", _V11_SQLITE, _V11_POSTGRESQL),
    Migration(
        12,
        "the friction estimator's tables",
        estimator_table_steps("friction", "estimates_friction", FRICTION_FIELDS_V12, "sqlite"),
        estimator_table_steps("friction", "estimates_friction", FRICTION_FIELDS_V12, "postgresql"),
    ),
    Migration(
        13,
        "the tracked estimator's tables",
        estimator_table_steps("tracked", "estimates_tracked", TRACKED_FIELDS_V13, "sqlite"),
        estimator_table_steps("tracked", "estimates_tracked", TRACKED_FIELDS_V13, "postgresql"),
    ),
    Migration(
        14,
        "expiry of API access tokens",
        ("ALTER TABLE api_tokens ADD COLUMN expires_ns INTEGER",),
        ("ALTER TABLE api_tokens ADD COLUMN expires_ns bigint",),
    ),
    Migration(15, "MDSF rows carry the online calibration", _v15("sqlite"), _v15("postgresql")),
    Migration(
        16,
        "the friction estimator's position",
        _v16_friction_position("sqlite"),
        _v16_friction_position("postgresql"),
    ),
    Migration(
        17,
        "tracked rows carry the gyro's noise measured standing",
        _v17_tracked_calibration("sqlite"),
        _v17_tracked_calibration("postgresql"),
    ),
    Migration(
        18,
        "tracked rows carry the hull's pitch and roll",
        _v18_tracked_attitude("sqlite"),
        _v18_tracked_attitude("postgresql"),
    ),
    Migration(
        19,
        "friction rows carry the speed's 1-sigma",
        _v19_friction_speed_std("sqlite"),
        _v19_friction_speed_std("postgresql"),
    ),
    Migration(
        20,
        "tracked rows carry the GNSS receiver's clock offset",
        _v20_tracked_clock("sqlite"),
        _v20_tracked_clock("postgresql"),
    ),
)

_VERSION_TABLE = {
    "sqlite": (
        "CREATE TABLE IF NOT EXISTS schema_version ("
        " version INTEGER PRIMARY KEY, description TEXT NOT NULL, applied_ns INTEGER NOT NULL)"
    ),
    "postgresql": (
        "CREATE TABLE IF NOT EXISTS schema_version ("
        " version integer PRIMARY KEY, description text NOT NULL, applied_ns bigint NOT NULL)"
    ),
}


def latest_version() -> int:
    """The schema version this code writes."""
    return MIGRATIONS[-1].version


def migrate_to_latest(execute: Execute, dialect: str) -> int:
    """Apply every pending migration (:func:`apply_pending`) and return the schema version; a
    database newer than this code is a :class:`~server.storage.base.StorageError`."""
    try:
        version, _ = apply_pending(execute, dialect)
    except RuntimeError as exc:
        raise StorageError(str(exc)) from exc
    return version


def apply_pending(
    execute: Execute, dialect: str, *, target: int | None = None
) -> tuple[int, list[int]]:
    """Apply the migrations the database lacks, inside the caller's locked transaction.

    ``execute(sql, params)`` runs one statement and returns its rows; the placeholder style is
    the dialect's (``?`` for SQLite, ``%s`` for PostgreSQL). ``target`` stops at that version
    (default: the latest; tests and the storage benchmark build older schemas with it).
    Returns ``(version, applied)``.

    Raises
    ------
    RuntimeError
        When the database carries a version newer than this code knows.
    """
    ph = "?" if dialect == "sqlite" else "%s"
    target = latest_version() if target is None else target
    execute(_VERSION_TABLE[dialect], ())
    rows = execute("SELECT coalesce(max(version), 0) FROM schema_version", ())
    current = int(rows[0][0])
    if current > latest_version():
        raise RuntimeError(
            f"database schema version {current} is newer than this server's {latest_version()}"
        )
    applied: list[int] = []
    for m in MIGRATIONS:
        if m.version <= current or m.version > target:
            continue
        for step in m.statements(dialect):
            if isinstance(step, str):
                execute(step, ())
            else:
                step(execute)
        execute(
            "INSERT INTO schema_version (version, description, applied_ns) "
            f"VALUES ({ph}, {ph}, {ph})",
            (m.version, m.description, time.time_ns()),
        )
        applied.append(m.version)
        current = m.version
    return current, applied
