"""Benchmarks behind ``slipfleet bench <name> [--json PATH]``.

Each module has ``run(json_path=None) -> dict`` that prints a plain-text table and, given a path,
writes the same numbers as JSON.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

__all__ = ["int_list", "percentile"]


def int_list(text: str) -> list[int]:
    """``"1,2,3"`` → ``[1, 2, 3]`` (an argparse ``type``); ValueError if empty or not integers."""
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError as exc:
        raise ValueError(f"expected comma-separated integers, got {text!r}") from exc
    if not values:
        raise ValueError("expected at least one integer")
    return values


def percentile(values: Sequence[float], q: float) -> float:
    """The ``q``-th percentile (nearest rank) of ``values`` (not empty)."""
    s = sorted(values)
    return s[min(len(s) - 1, max(0, math.ceil(q / 100 * len(s)) - 1))]
