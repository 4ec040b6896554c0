"""The storage interface: every query the product makes lives behind it.

Two implementations: :mod:`server.storage.sqlite` (embedded default, WAL) and
:mod:`server.storage.postgres` (selected by URL). Both are used from exactly one writer thread for
writes (:class:`server.storage.writer.StoreWriter`) and from any thread for reads.

Estimate rows travel as numpy structured arrays of their estimator's dtype
(``EstimatorSpec.dtype``), written as :class:`estimator.types.EstimateBatch` es (one estimator's
rows of several vehicles) and read per estimator by name. A store serves the specs it was built
with (default: the whole catalog), each in tables of its own made by a versioned migration.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from estimator.types import EstimateBatch

__all__ = ["Anchor", "StorageDataError", "StorageError", "Store", "TokenRecord", "VehicleRecord"]

#: A local ENU frame's origin: ``(lat_deg, lon_deg, height_m)``.
Anchor = tuple[float, float, float]


class StorageError(RuntimeError):
    """The database refused or is unreachable."""


class StorageDataError(StorageError):
    """The database rejected the data itself (constraint, type): retrying will not help."""


@dataclass(frozen=True, slots=True)
class VehicleRecord:
    """A registered vehicle."""

    vehicle_id: str
    config: dict[str, Any]  # VehicleConfig.to_dict()
    created_ns: int
    updated_ns: int


@dataclass(frozen=True, slots=True)
class TokenRecord:
    """A REST access token as stored: never the token itself, only its hash (not shown here).

    ``role`` is ``"viewer"``, ``"operator"`` or ``"admin"`` (:class:`server.tokens.Role`);
    ``last_used_ns`` and ``revoked_ns`` are None while the token was never used / not revoked;
    ``expires_ns`` is None for a token that does not expire.
    """

    id: int
    name: str
    role: str
    created_ns: int
    last_used_ns: int | None
    revoked_ns: int | None
    expires_ns: int | None = None

    @property
    def revoked(self) -> bool:
        return self.revoked_ns is not None

    def expired(self, now_ns: int) -> bool:
        """True once ``now_ns`` reached the expiry (never for a token without one)."""
        return self.expires_ns is not None and now_ns >= self.expires_ns

    def valid_at(self, now_ns: int) -> bool:
        """True while the token is neither revoked nor expired at ``now_ns``."""
        return not self.revoked and not self.expired(now_ns)


class Store(Protocol):
    """What the server needs from a database."""

    dialect: str  # "sqlite" | "postgresql"

    def migrate(self) -> int:
        """Apply pending versioned migrations (idempotent); return the schema version."""

    def close(self) -> None: ...

    def ping(self) -> bool:
        """True when the database answers."""

    def maintain(self, *, everything: bool = False) -> bool:
        """One step of the store's own upkeep, which the writer runs while it has nothing else
        to do (SQLite moves staged rows to their final table); True while more steps are due,
        False when none is (``everything``: the whole of it, e.g. before a close)."""

    # vehicles
    def upsert_vehicle(
        self, vehicle_id: str, config: dict[str, Any], now_ns: int
    ) -> VehicleRecord: ...

    def get_vehicle(self, vehicle_id: str) -> VehicleRecord | None: ...

    def list_vehicles(self) -> list[VehicleRecord]: ...

    def delete_vehicle(self, vehicle_id: str) -> bool:
        """Delete the vehicle with the estimates of every estimator, its counters and its
        anchor; False if it did not exist."""

    # estimates
    def write_estimates(self, *batches: EstimateBatch | Sequence[tuple[str, np.ndarray]]) -> int:
        """Insert the rows of one or more estimators in one transaction; return rows written.

        Rows whose ``(vehicle_id, stamp_ns)`` already exist in their estimator's table are
        ignored (idempotent replays), so are rows of unregistered vehicles. A plain
        ``[(vehicle_id, rows), …]`` is taken as rows of ``"mdsf"`` (callers of the single
        estimator era).
        """

    def query_series(
        self,
        vehicle_id: str,
        start_ns: int,
        end_ns: int,
        fields: Sequence[str] | None = None,
        estimator: str = "mdsf",
    ) -> np.ndarray:
        """Rows with ``start_ns <= stamp_ns < end_ns`` ordered by time (``stamp_ns`` always in),
        of the estimator's dtype or the subset ``fields``; ``ValueError`` for an estimator or
        field the store does not have."""

    def latest(self, vehicle_id: str, estimator: str = "mdsf") -> np.ndarray | None:
        """The newest row (a 0-d structured array) or None."""

    def latest_all(self, estimator: str = "mdsf") -> dict[str, np.ndarray]:
        """Newest row of every vehicle."""

    def estimators_with_rows(self, vehicle_id: str) -> list[str]:
        """The estimators (in the store's spec order) with stored rows of ``vehicle_id``."""

    def delete_older_than(self, stamp_ns: int) -> int:
        """Retention: delete estimates of every estimator older than ``stamp_ns``; return rows
        deleted."""

    # ingest counters
    def write_counters(self, counters: dict[str, dict[str, int]], now_ns: int) -> None:
        """Upsert per-vehicle counter totals: ``{vehicle_id: {counter_name: total}}``."""

    def get_counters(self, vehicle_id: str) -> dict[str, int]: ...

    # ENU anchors: (lat_deg, lon_deg, height_m) of each vehicle's local frame
    def put_anchors(self, anchors: Mapping[str, Anchor], now_ns: int) -> int:
        """Store the anchors of vehicles that have none yet (an anchor, once stored, stays:
        the rows in its frame rely on it); return how many were stored."""

    def get_anchors(self, vehicle_id: str | None = None) -> dict[str, Anchor]:
        """Stored anchors by vehicle id: every one, or only ``vehicle_id``'s."""

    # access tokens (see server.tokens; the store keeps the token's SHA-256 only)
    def create_token(
        self, name: str, role: str, token_sha256: str, now_ns: int, expires_ns: int | None = None
    ) -> TokenRecord:
        """Store a new token by its hash (``expires_ns`` None: it never expires); raises
        :class:`StorageDataError` on a duplicate hash."""

    def get_token(self, token_sha256: str) -> TokenRecord | None:
        """The token with this hash (revoked ones too), or None."""

    def list_tokens(self) -> list[TokenRecord]:
        """Every token, revoked ones included, by id."""

    def touch_token(self, token_id: int, now_ns: int) -> None:
        """Record a use of the token (sets ``last_used_ns``)."""

    def revoke_token(self, token_id: int, now_ns: int) -> TokenRecord | None:
        """Revoke the token (a second revoke keeps the first time); None if there is none."""

    # raw packets
    def write_raw_packets(self, packets: Sequence[tuple[str, int, str, bytes]]) -> int:
        """Store ``(vehicle_id, received_ns, key, payload)`` tuples (registered or not); the
        number written."""

    def raw_packets_bytes(self) -> int:
        """Payload bytes of every stored raw packet."""
