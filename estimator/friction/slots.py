"""The friction fleet's per-vehicle numbers and state as rows of arrays indexed by slot.

A round of :class:`~.fleet.FrictionFleet` reads its vehicles' constants (tyres, chassis,
axles), filter states and informed windows by one fancy index ``[slots]`` and writes them
back the same way, instead of stacking and splitting per vehicle. Rows grow by doubling as
slots are added; :meth:`FleetSlots.reset` gives a slot a vehicle's constants and no state.

The informed window (``method.md`` §5's warning, see :mod:`.fleet`) is a ring ``(S, W)`` of
each tick's "conditions met" and μ, with the count of ticks pushed ``(S,)``.
"""

from __future__ import annotations

import math

import numpy as np

from estimator._arrays import BoolArray, FloatArray, IntArray
from estimator.config import Wheeled4wdSteeredConfig
from estimator.friction.axle import AxleArrays
from estimator.friction.filter import FilterState, TyreArrays
from estimator.friction.model import Chassis

__all__ = ["FleetSlots"]


def _grown(a: np.ndarray, rows: int) -> np.ndarray:
    """``a`` with ``rows`` rows, the new ones zero."""
    out = np.zeros((rows, *a.shape[1:]), dtype=a.dtype)
    out[: a.shape[0]] = a
    return out


class FleetSlots:
    """Per slot: constants ``tyres``, ``chassis``, ``axles`` (their arrays' first axis is the
    slot), filter mean ``x`` ``(S, n)``, root ``s`` ``(S, n, n)``, last loads ``(S, 4)``,
    smoothed NIS ``(S,)``, ``has_state`` ``(S,)``, the last informed μ ``held_mu`` ``(S,)``
    and the informed window ``recent_ok``, ``recent_mu`` ``(S, W)``, ``recent_n`` ``(S,)``."""

    def __init__(self, n_state: int, window: int) -> None:
        self.window = window
        self.tyres = TyreArrays(*(np.zeros((0, 1)) for _ in range(4)))
        self.chassis = Chassis(np.zeros(0), np.zeros(0), np.zeros((0, 4)), np.zeros((0, 4)))
        self.axles = AxleArrays(np.zeros((0, 1)), np.zeros(0), np.zeros((0, 2)))
        self.x = np.zeros((0, n_state))
        self.s = np.zeros((0, n_state, n_state))
        self.fz_prev_n = np.zeros((0, 4))
        self.nis = np.zeros(0)
        self.has_state = np.zeros(0, dtype=bool)
        self.held_mu = np.zeros(0)
        self.recent_ok = np.zeros((0, window), dtype=bool)
        self.recent_mu = np.zeros((0, window))
        self.recent_n = np.zeros(0, dtype=np.int64)

    def _ensure(self, slot: int) -> None:
        if slot < self.x.shape[0]:
            return
        rows = max(slot + 1, 2 * self.x.shape[0], 8)
        for name in ("x", "s", "fz_prev_n", "nis", "has_state", "held_mu"):
            setattr(self, name, _grown(getattr(self, name), rows))
        for name in ("recent_ok", "recent_mu", "recent_n"):
            setattr(self, name, _grown(getattr(self, name), rows))
        self.tyres = TyreArrays(*(_grown(a, rows) for a in _fields(self.tyres)))
        self.chassis = Chassis(*(_grown(a, rows) for a in _fields(self.chassis)))
        self.axles = AxleArrays(*(_grown(a, rows) for a in _fields(self.axles)))

    def reset(self, slot: int, config: Wheeled4wdSteeredConfig) -> None:
        """Slot ``slot`` holds a new vehicle of ``config``: its constants, no filter state,
        no informed μ, an empty window."""
        self._ensure(slot)
        ty = config.tyre
        tyre_row = (ty.kz_npm, ty.unloaded_radius_m, ty.c_px_npm2, ty.c_py_npm2)
        for a, value in zip(_fields(self.tyres), tyre_row, strict=True):
            a[slot] = value
        for a, row in zip(_fields(self.chassis), _fields(Chassis.of([config])), strict=True):
            a[slot] = row[0]
        for a, row in zip(_fields(self.axles), _fields(AxleArrays.of([config])), strict=True):
            a[slot] = row[0]
        self.has_state[slot] = False
        self.held_mu[slot] = math.nan
        self.recent_n[slot] = 0

    def constants(self, slots: IntArray, kz_npm: FloatArray) -> tuple[TyreArrays, Chassis]:
        """The round's tyres (vertical stiffness ``kz_npm`` ``(B, 4)`` as the front end learnt
        it) and chassis, rows in the order of ``slots``."""
        tyres = TyreArrays(
            kz_npm,
            self.tyres.radius_m[slots],
            self.tyres.c_px_npm2[slots],
            self.tyres.c_py_npm2[slots],
        )
        return tyres, Chassis(*(a[slots] for a in _fields(self.chassis)))

    def axles_of(self, slots: IntArray) -> AxleArrays:
        return AxleArrays(*(a[slots] for a in _fields(self.axles)))

    def states(self, slots: IntArray, prior: FilterState, fresh: BoolArray) -> FilterState:
        """The filter states of ``slots`` ``(B, ·)``; the ``fresh`` rows (no state yet) from
        ``prior`` (its rows are those of ``fresh``, in order)."""
        x, s = self.x[slots], self.s[slots]
        fz, nis = self.fz_prev_n[slots], self.nis[slots]
        x[fresh], s[fresh], fz[fresh], nis[fresh] = prior.x, prior.s, prior.fz_prev_n, prior.nis
        return FilterState(x, s, fz, nis)

    def keep(self, slots: IntArray, st: FilterState) -> None:
        """Store the stepped states ``st`` (rows in the order of ``slots``)."""
        self.x[slots], self.s[slots] = st.x, st.s
        self.fz_prev_n[slots], self.nis[slots] = st.fz_prev_n, st.nis
        self.has_state[slots] = True

    def informed(self, slots: IntArray, ok: BoolArray, mu: FloatArray, spread: float) -> BoolArray:
        """Push this tick's conditions ``ok`` and ``mu`` ``(B,)`` into the windows; True where
        the window is full, every tick in it met the conditions and μ moved less than
        ``spread`` of the current μ over it (``(max − min)/μ``)."""
        at = self.recent_n[slots] % self.window
        self.recent_ok[slots, at] = ok
        self.recent_mu[slots, at] = mu
        self.recent_n[slots] += 1
        mus = self.recent_mu[slots]
        moved = (mus.max(axis=1) - mus.min(axis=1)) / mu
        full = self.recent_n[slots] >= self.window
        informed: BoolArray = full & self.recent_ok[slots].all(axis=1) & (moved < spread)
        return informed


def _fields(obj: object) -> list[np.ndarray]:
    """A slotted dataclass's arrays in field order."""
    return [getattr(obj, name) for name in obj.__slots__]  # type: ignore[attr-defined]
