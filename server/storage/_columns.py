"""Estimator tables, field lists and row checks shared by both stores (no SQL dialect here).

Every estimator's rows live in tables of their own (see :mod:`server.storage.migrations`,
``estimator_tables``): :func:`resolve_tables` matches the specs a store serves with the tables
the database records, refusing a spec whose fields no longer match its table.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any, Generic, Protocol, TypeVar

import numpy as np

from estimator.catalog import SPECS, spec_of
from estimator.spec import EstimatorSpec
from estimator.types import EstimateBatch, concat_estimates
from server.storage.base import StorageDataError, StorageError

#: The estimator of rows handed over as plain ``[(vehicle_id, rows), …]`` and the default of
#: the read methods (what callers meant before there was more than one estimator).
DEFAULT_ESTIMATOR = "mdsf"


def spec_fields(spec: EstimatorSpec) -> tuple[tuple[str, str], ...]:
    """``(name, kind)`` of every field, as ``estimator_tables.fields`` records it."""
    return tuple((f.name, f.kind) for f in spec.fields)


def resolve_tables(
    records: Iterable[Sequence[Any]], specs: Iterable[EstimatorSpec]
) -> tuple[dict[str, str], list[str]]:
    """``({estimator: table}, every recorded table)`` from ``estimator_tables`` rows
    ``(estimator, table_name, fields JSON)``.

    Raises
    ------
    StorageError
        A spec has no table (a migration is missing) or its fields differ from the ones its
        table was made from (a migration must convert the table first).
    """
    recorded = {str(e): (str(t), json.loads(f)) for e, t, f in records}
    tables: dict[str, str] = {}
    for spec in specs:
        if spec.name not in recorded:
            raise StorageError(
                f"estimator {spec.name!r} has no table in this database: a migration is missing"
            )
        table, fields = recorded[spec.name]
        if [tuple(f) for f in fields] != list(spec_fields(spec)):
            raise StorageError(
                f"estimator {spec.name!r}: its fields no longer match table {table!r} "
                f"(made from {fields}); a migration must convert the table first"
            )
        tables[spec.name] = table
    return tables, sorted(t for t, _ in recorded.values())


class _Table(Protocol):
    spec: EstimatorSpec


_T = TypeVar("_T", bound=_Table)


class SpecTables(Generic[_T]):
    """The tables of the specs one store serves, read from ``estimator_tables`` on first use
    (again at :meth:`reload`) and checked by :func:`resolve_tables`; ``every`` names every
    estimator table the database records (deletes reach them all).

    ``make(spec, table)`` builds the store's own per-estimator table object; ``read(sql)``
    runs a query in the store's dialect.
    """

    def __init__(
        self,
        dialect: str,
        specs: Iterable[EstimatorSpec] | None,
        make: Callable[[EstimatorSpec, str], _T],
        read: Callable[[str], Iterable[Sequence[Any]]],
    ) -> None:
        self.specs = tuple(catalog_specs() if specs is None else specs)
        self.every: list[str] = []
        self._dialect = dialect
        self._make = make
        self._read = read
        self._tables: dict[str, _T] | None = None

    def reload(self) -> dict[str, _T]:
        """Read the tables again (the schema changed), refusing a spec its table no longer
        fits."""
        self._tables = None
        return self.load()

    def load(self) -> dict[str, _T]:
        """The served specs' tables by estimator name."""
        if self._tables is None:
            try:
                records = self._read("SELECT estimator, table_name, fields FROM estimator_tables")
            except StorageError as exc:
                raise StorageError(f"{exc} (is the database migrated?)") from exc
            tables, self.every = resolve_tables(records, self.specs)
            self._tables = {s.name: self._make(s, tables[s.name]) for s in self.specs}
        return self._tables

    def served(self, estimator: str) -> _T:
        """The table of ``estimator`` (``ValueError`` when this store does not serve it)."""
        t = self.load().get(estimator)
        if t is None:
            raise ValueError(
                f"unknown estimator {estimator!r}; known: {sorted(self._tables or ())}"
            )
        return t

    def of(self, batch: EstimateBatch) -> _T:
        """The table ``batch`` goes to (``StorageDataError`` when its rows fit none)."""
        t = self.load().get(batch.estimator)
        # the same dtype object in the common case: no comparison field by field (~3 µs)
        if t is None or (t.spec.dtype is not batch.spec.dtype and t.spec.dtype != batch.spec.dtype):
            raise StorageDataError(
                f"{self._dialect}: rows of estimator {batch.estimator!r} do not fit a table of "
                "this store"
            )
        return t


def as_batches(batches: Sequence[Any]) -> list[EstimateBatch]:
    """The non-empty :class:`EstimateBatch` es of ``batches``; a plain ``[(vehicle_id, rows),
    …]`` is one batch of :data:`DEFAULT_ESTIMATOR` rows (``TypeError`` for rows of another
    dtype)."""
    out: list[EstimateBatch] = []
    for batch in batches:
        if not isinstance(batch, EstimateBatch):
            batch = _plain_batch(batch, spec_of(DEFAULT_ESTIMATOR))
        if batch.rows.shape[0]:
            out.append(batch)
    return out


def _plain_batch(pairs: Sequence[tuple[str, np.ndarray]], spec: EstimatorSpec) -> EstimateBatch:
    """``pairs`` as one batch of ``spec``, a dtype compared with the spec's only when it is
    not the object the previous rows had: two equal structured dtypes that are not one object
    compare field by field (~3 µs for MDSF's 28), and a fleet's commit holds one or two rows
    of each of hundreds of vehicles."""
    last = None
    for _, rows in pairs:
        if rows.__class__ is not np.ndarray or rows.dtype is not last or rows.ndim != 1:
            last = spec.check_rows(rows).dtype
    kept = [(vid, rows) for vid, rows in pairs if len(rows)]
    if not kept:
        return EstimateBatch([], [], spec.empty_rows(0), spec)
    return EstimateBatch(
        [vid for vid, _ in kept],
        [len(rows) for _, rows in kept],
        concat_estimates([rows for _, rows in kept]),
        spec,
    )


def registered_rows(batch: EstimateBatch, keys: Mapping[str, int]) -> tuple[np.ndarray, np.ndarray]:
    """The rows of ``batch`` whose vehicle has a key in ``keys``, and each row's key.

    Both stores write rows by vehicle key and drop those of unregistered vehicles (absent from
    ``keys``). Returns ``(rows, vkeys)``: the kept rows, shape (r,), and their keys, int64 (r,).
    """
    per_vehicle = np.fromiter((keys.get(v, -1) for v in batch.ids), np.int64, len(batch.ids))
    vkeys = np.repeat(per_vehicle, batch.counts)
    rows = batch.rows
    if (per_vehicle < 0).any():
        rows, vkeys = rows[vkeys >= 0], vkeys[vkeys >= 0]
    return rows, vkeys


def select_fields(spec: EstimatorSpec, fields: Sequence[str] | None) -> tuple[str, ...]:
    """Validated field list in the caller's order, ``stamp_ns`` first, no duplicates."""
    if fields is None:
        return spec.field_names
    if isinstance(fields, str):
        raise TypeError("fields must be a sequence of field names, not a string")
    out = ["stamp_ns"]
    for f in fields:
        if not spec.has_field(f):
            raise ValueError(f"estimator {spec.name!r} has no field {f!r}")
        if f not in out:
            out.append(f)
    return tuple(out)


def fields_dtype(spec: EstimatorSpec, names: Sequence[str]) -> np.dtype:
    """Structured dtype holding ``names`` (native byte order), a subset of ``spec.dtype``."""
    if tuple(names) == spec.field_names:
        return spec.dtype
    return np.dtype([(n, spec.field(n).kind) for n in names])


def catalog_specs() -> tuple[EstimatorSpec, ...]:
    """Every spec of the catalog (what a store serves unless told otherwise)."""
    return tuple(SPECS.values())


# The default estimator's row as the storage benchmark's column layout (the SQLite store of
# schema versions 1-5) binds it.
_DEFAULT_SPEC = spec_of(DEFAULT_ESTIMATOR)
FIELD_NAMES: tuple[str, ...] = _DEFAULT_SPEC.field_names
FLOAT_FIELDS: frozenset[str] = frozenset(f.name for f in _DEFAULT_SPEC.fields if f.kind == "f8")
check_rows = _DEFAULT_SPEC.check_rows
