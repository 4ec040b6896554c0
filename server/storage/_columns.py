"""Column names and array helpers shared by both stores (no SQL dialect specifics here)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from estimator.types import ESTIMATE_DTYPE, ESTIMATE_FIELDS

FIELD_NAMES: tuple[str, ...] = tuple(name for name, _ in ESTIMATE_FIELDS)
FIELD_KIND: dict[str, str] = dict(ESTIMATE_FIELDS)
FLOAT_FIELDS: frozenset[str] = frozenset(n for n, k in ESTIMATE_FIELDS if k == "f8")


def check_rows(rows: np.ndarray) -> np.ndarray:
    """Return ``rows`` as a 1-d array of ``ESTIMATE_DTYPE`` or raise ``TypeError``."""
    if not isinstance(rows, np.ndarray) or rows.dtype != ESTIMATE_DTYPE:
        got = getattr(rows, "dtype", type(rows).__name__)
        raise TypeError(f"estimate rows must be a structured array of ESTIMATE_DTYPE, got {got}")
    if rows.ndim != 1:
        raise TypeError(f"estimate rows must be 1-d, got shape {rows.shape}")
    return rows


def select_fields(fields: Sequence[str] | None) -> tuple[str, ...]:
    """Validated field list in the caller's order, ``stamp_ns`` first, no duplicates."""
    if fields is None:
        return FIELD_NAMES
    if isinstance(fields, str):
        raise TypeError("fields must be a sequence of field names, not a string")
    out = ["stamp_ns"]
    for f in fields:
        if f not in FIELD_KIND:
            raise ValueError(f"unknown estimate field {f!r}")
        if f not in out:
            out.append(f)
    return tuple(out)


def fields_dtype(names: Sequence[str]) -> np.dtype:
    """Structured dtype holding ``names`` (native byte order), a subset of ESTIMATE_DTYPE."""
    if tuple(names) == FIELD_NAMES:
        return ESTIMATE_DTYPE
    return np.dtype([(n, FIELD_KIND[n]) for n in names])
