"""Slot arrays: per-vehicle state stored as rows of arrays indexed by a slot number."""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["grow_slot_array"]


def grow_slot_array(owner: object, name: str, cap: int, shape: tuple[int, ...], fill: Any) -> None:
    """Set ``owner.<name>`` to an array of ``cap`` slots of ``shape`` each, keeping the rows it
    already has; new rows (and a new array) hold ``fill``, in ``fill``'s dtype when new."""
    a = getattr(owner, name, None)
    dtype = np.asarray(fill).dtype if a is None else a.dtype
    new = np.full((cap, *shape), fill, dtype=dtype)
    if a is not None:
        new[: a.shape[0]] = a
    setattr(owner, name, new)
