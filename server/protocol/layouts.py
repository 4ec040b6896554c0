"""Payload layouts shared by several streams, each with its per-packet rules.

A stream of sampled values (IMU, wheel speeds, steering angles) is a :class:`Sampled` layout:
``stamp_ns`` strictly increasing and float64 row arrays of the same length, each bounded per
row (norm) or per value. A stream of encoder edges per member (wheels, sprockets) is an
:class:`Edges` layout: ``edges``, one entry per member with a non-decreasing edge run
(:func:`edge_run`). The codec decodes one packet by :meth:`Sampled.decode` /
:meth:`Edges.decode`; the burst decoder reads the same declarations to check many packets'
arrays at once (:mod:`server.protocol.burst`), so both paths apply one rule set.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any

import numpy as np

from estimator.base import Measurement
from server.protocol.base import (
    LITTLE_ENDIAN,
    Body,
    Ctx,
    Limits,
    array,
    int_field,
    stamp,
    stamps,
)

__all__ = ["Edges", "Rows", "Sampled", "edge_run", "heartbeat_until"]


@dataclass(frozen=True, slots=True)
class Rows:
    """A packed float64 array beside ``stamp_ns``: ``width`` values a sample (shape ``(n,)``
    for 1, else ``(n, width)``), within ``Limits.<bound>``: the row's Euclidean norm when
    ``norm``, else every value's magnitude. NaN passes ("not available"), ``±inf`` does not."""

    name: str
    width: int
    bound: str
    norm: bool = False

    def checked(self, ctx: Ctx, a: np.ndarray, n: int, lim: Limits) -> np.ndarray:
        """``a`` (this field, decoded) when it has ``n`` rows within the bound."""
        if a.shape[0] != n:
            raise ctx.fail("wrong_shape", f"{self.name} has {a.shape[0]} rows for {n} stamps")
        bound = getattr(lim, self.bound)
        if self.norm:
            norm2 = np.einsum("ij,ij->i", a, a)
            if not (norm2 <= bound * bound).all():  # fails on NaN, inf or too large
                if np.isinf(a).any():
                    raise ctx.fail("non_finite", self.name)
                if (norm2 > bound * bound).any():  # NaN rows compare False: they pass
                    raise ctx.fail("out_of_range", f"{self.name} norm exceeds {bound:g}")
        else:
            if np.isinf(a).any():
                raise ctx.fail("non_finite", self.name)
            if (np.abs(a) > bound).any():
                raise ctx.fail("out_of_range", f"|{self.name}| exceeds {bound:g}")
        return a if LITTLE_ENDIAN else a.astype(np.float64)


@dataclass(frozen=True, slots=True, eq=False)
class Sampled:
    """Samples at strictly increasing ``stamp_ns`` with :attr:`rows` beside them; one
    measurement a packet, ``build(stamp_ns=..., <rows name>=...)``. Hashed by identity (the
    burst decoder keys its groups by the layout)."""

    rows: tuple[Rows, ...]
    build: Callable[..., Measurement]

    def decode(self, ctx: Ctx, m: dict[str, Any], lim: Limits) -> Body:
        """The packet's measurement by the per-packet rules (the first broken one refuses)."""
        t, first_ns, last_ns = stamps(ctx, m, lim, strict=True)
        n = t.shape[0]
        values = {"stamp_ns": t}
        for r in self.rows:
            values[r.name] = r.checked(ctx, array(ctx, m, r.name, "<f8", r.width, lim), n, lim)
        return (self.build(**values),), first_ns, last_ns


def edge_run(
    ctx: Ctx, m: dict[str, Any], lim: Limits
) -> tuple[np.ndarray, np.ndarray | None, int, int]:
    """An edge run in ``m``: ``stamp_ns`` (non-decreasing) and the optional ``direction``
    (int8, +1 or -1 each); returns ``(stamp_ns, direction or None, first_ns, last_ns)``."""
    t, first_ns, last_ns = stamps(ctx, m, lim, strict=False)
    direction = None
    if "direction" in m:
        d = array(ctx, m, "direction", "i1", 1, lim)
        if d.shape[0] != t.shape[0]:
            raise ctx.fail("wrong_shape", "direction and stamp_ns lengths differ")
        if not (np.abs(d.astype(np.int16)) == 1).all():
            raise ctx.fail("out_of_range", "direction must be +1 or -1")
        direction = d
    return t, direction, first_ns, last_ns


def heartbeat_until(ctx: Ctx, m: dict[str, Any], lim: Limits) -> Body:
    """The body of a heartbeat (no edge up to ``until_ns``, which is its span)."""
    until_ns = stamp(ctx, int_field(ctx, m, "until_ns"), "until_ns", lim)
    return (), until_ns, until_ns


@dataclass(frozen=True, slots=True, eq=False)
class Edges:
    """``edges``: one entry per member that had edges, ``{key: member, stamp_ns, direction?}``
    (:func:`edge_run`), each member at most once; no entry at all only with ``until_ns`` (a
    heartbeat). Each entry is one measurement, ``build(<key>=member, stamp_ns=...,
    direction=...)``. Hashed by identity, as :class:`Sampled`."""

    key: str
    members: type[IntEnum]
    build: Callable[..., Measurement]
    #: Each member by its number (derived from ``members``).
    by_number: dict[object, IntEnum] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "by_number", {int(x): x for x in self.members})

    def decode(self, ctx: Ctx, m: dict[str, Any], lim: Limits) -> Body:
        """The packet's measurements by the per-packet rules (the first broken one refuses)."""
        items = m.get("edges")
        if isinstance(items, list) and not items and "until_ns" in m:
            return heartbeat_until(ctx, m, lim)
        if "edges" not in m:
            raise ctx.fail("missing_field", "edges")
        count = len(self.members)
        if not isinstance(items, list) or not 1 <= len(items) <= count:
            raise ctx.fail(
                "wrong_type",
                f"edges must be an array of 1 to {count} {self.key} entries (0 with until_ns)",
            )
        out: list[Measurement] = []
        seen: set[int] = set()
        first_ns, last_ns = 2**63 - 1, -(2**63)
        for item in items:
            if not isinstance(item, dict):
                raise ctx.fail("wrong_type", "each edges entry must be a map")
            number = int_field(ctx, item, self.key)
            member = self.by_number.get(number)
            if member is None or number in seen:
                raise ctx.fail(
                    "out_of_range",
                    f"{self.key} {number} is not one of {[int(x) for x in self.members]}, "
                    "or repeated",
                )
            seen.add(number)
            t, direction, lo_ns, hi_ns = edge_run(ctx, item, lim)
            first_ns, last_ns = min(first_ns, lo_ns), max(last_ns, hi_ns)
            out.append(self.build(**{self.key: member}, stamp_ns=t, direction=direction))
        return tuple(out), first_ns, last_ns
