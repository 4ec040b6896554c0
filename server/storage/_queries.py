"""The queries whose SQL SQLite and PostgreSQL both accept, written once.

Vehicles, counters, anchors and access tokens are small tables with the same columns on both
backends; their reads and single-row writes differ only in the parameter marker (``?`` against
``%s``) and in how the vehicle config column comes back (JSON text against a decoded ``jsonb``).
A backend mixes :class:`SharedQueries` in and supplies ``_read``, ``_write``, its marker and
``_config_of``; bulk writes (estimates, counters, anchors, raw packets) stay backend-specific,
since each uses its own fastest path (``executemany`` against ``unnest``/``COPY``).
"""

from __future__ import annotations

from collections.abc import Sequence
from contextlib import AbstractContextManager
from typing import Any

from server.storage.base import Anchor, TokenRecord, VehicleRecord

__all__ = ["SharedQueries"]

_TOKEN_COLUMNS = "id, name, role, created_ns, last_used_ns, revoked_ns, expires_ns"
_VEHICLE_COLUMNS = "vehicle_id, config, created_ns, updated_ns"


def _int_or_none(value: Any) -> int | None:
    return None if value is None else int(value)


def _token(row: Sequence[Any]) -> TokenRecord:
    return TokenRecord(
        id=int(row[0]),
        name=str(row[1]),
        role=str(row[2]),
        created_ns=int(row[3]),
        last_used_ns=_int_or_none(row[4]),
        revoked_ns=_int_or_none(row[5]),
        expires_ns=_int_or_none(row[6]),
    )


class SharedQueries:
    """Reads and one-row writes of the small tables, in ``?`` SQL translated per backend."""

    #: The backend's DB-API parameter marker.
    param_marker = "?"

    def _read(self, sql: str, params: Sequence[Any] = ()) -> list[Any]:
        raise NotImplementedError

    def _write(self) -> AbstractContextManager[Any]:
        raise NotImplementedError

    @staticmethod
    def _config_of(raw: Any) -> dict[str, Any]:
        raise NotImplementedError

    def _sql(self, sql: str) -> str:
        return sql if self.param_marker == "?" else sql.replace("?", self.param_marker)

    def _select(self, sql: str, params: Sequence[Any] = ()) -> list[Any]:
        return self._read(self._sql(sql), params)

    def _write_one(self, sql: str, params: Sequence[Any]) -> Any:
        """Run one statement in a write transaction; its first returned row (or None)."""
        with self._write() as conn:
            return conn.execute(self._sql(sql), params).fetchone()

    # ------------------------------------------------------------------ vehicles

    def _record(self, row: Sequence[Any]) -> VehicleRecord:
        return VehicleRecord(
            vehicle_id=str(row[0]),
            config=self._config_of(row[1]),
            created_ns=int(row[2]),
            updated_ns=int(row[3]),
        )

    def get_vehicle(self, vehicle_id: str) -> VehicleRecord | None:
        rows = self._select(
            f"SELECT {_VEHICLE_COLUMNS} FROM vehicles WHERE vehicle_id = ?", (vehicle_id,)
        )
        return self._record(rows[0]) if rows else None

    def list_vehicles(self) -> list[VehicleRecord]:
        rows = self._select(f"SELECT {_VEHICLE_COLUMNS} FROM vehicles ORDER BY vehicle_id")
        return [self._record(r) for r in rows]

    # ------------------------------------------------------------------ counters, anchors

    def get_counters(self, vehicle_id: str) -> dict[str, int]:
        rows = self._select(
            "SELECT name, total FROM ingest_counters WHERE vehicle_id = ? ORDER BY name",
            (vehicle_id,),
        )
        return {str(name): int(total) for name, total in rows}

    def get_anchors(self, vehicle_id: str | None = None) -> dict[str, Anchor]:
        sql = "SELECT vehicle_id, lat_deg, lon_deg, height_m FROM vehicle_anchors"
        if vehicle_id is None:
            rows = self._select(sql)
        else:
            rows = self._select(f"{sql} WHERE vehicle_id = ?", (vehicle_id,))
        return {str(v): (float(a), float(b), float(c)) for v, a, b, c in rows}

    # ------------------------------------------------------------------ raw packets

    def raw_packets_bytes(self) -> int:
        """Payload bytes of every stored raw packet (the writer's ``raw_packets_max_bytes``;
        ``length`` of a blob or ``bytea`` is its bytes on both backends)."""
        rows = self._select("SELECT coalesce(sum(length(payload)), 0) FROM raw_packets")
        return int(rows[0][0])

    def query_raw_packets(
        self, vehicle_id: str, start_ns: int, end_ns: int
    ) -> list[tuple[int, str, bytes]]:
        """``(received_ns, key, payload)`` with ``start_ns <= received_ns < end_ns``, in order."""
        rows = self._select(
            "SELECT received_ns, key, payload FROM raw_packets "
            "WHERE vehicle_id = ? AND received_ns >= ? AND received_ns < ? "
            "ORDER BY received_ns, id",
            (vehicle_id, int(start_ns), int(end_ns)),
        )
        return [(int(t), str(k), bytes(p)) for t, k, p in rows]

    # ------------------------------------------------------------------ access tokens

    def create_token(
        self, name: str, role: str, token_sha256: str, now_ns: int, expires_ns: int | None = None
    ) -> TokenRecord:
        row = self._write_one(
            "INSERT INTO api_tokens (name, role, token_sha256, created_ns, expires_ns) "
            f"VALUES (?, ?, ?, ?, ?) RETURNING {_TOKEN_COLUMNS}",
            (name, role, token_sha256, int(now_ns), _int_or_none(expires_ns)),
        )
        assert row is not None
        return _token(row)

    def get_token(self, token_sha256: str) -> TokenRecord | None:
        rows = self._select(
            f"SELECT {_TOKEN_COLUMNS} FROM api_tokens WHERE token_sha256 = ?", (token_sha256,)
        )
        return _token(rows[0]) if rows else None

    def list_tokens(self) -> list[TokenRecord]:
        rows = self._select(f"SELECT {_TOKEN_COLUMNS} FROM api_tokens ORDER BY id")
        return [_token(r) for r in rows]

    def touch_token(self, token_id: int, now_ns: int) -> None:
        with self._write() as conn:
            conn.execute(
                self._sql("UPDATE api_tokens SET last_used_ns = ? WHERE id = ?"),
                (int(now_ns), int(token_id)),
            )

    def revoke_token(self, token_id: int, now_ns: int) -> TokenRecord | None:
        row = self._write_one(
            "UPDATE api_tokens SET revoked_ns = coalesce(revoked_ns, ?) WHERE id = ? "
            f"RETURNING {_TOKEN_COLUMNS}",
            (int(now_ns), int(token_id)),
        )
        return _token(row) if row else None
