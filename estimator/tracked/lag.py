"""Fixed-lag output of the tracked estimator: a state change reported at its estimated instant.

A lever thrown at ``t0`` shows in the sprocket windows a few ticks later (the windows read a
ratio about half a window late, and the recogniser waits for the ratio to cross its band), so
the state the filter gives on the tick changes late. Each vehicle's last rows are held
(:class:`HeldRows`); when a held row's successor changes state, :func:`backdate` moves the
change back over the ticks that still show the old state while the change was already under
way (``onset`` of the tick after: a ratio moving, a sprocket settling, the yaw acceleration
out of its band), at most ``lag`` ticks. Only rows a later change can still reach are held:
the last one, and while a change is under way up to ``lag`` (a fixed lag of one tick in
steady driving, of at most ``lag`` ticks through a change). Every row keeps its own stamp.

A braked track's −100 % is given only once no release can reach it: a sprocket starting
from rest shows its first edge only after turning up to one tooth pitch, which a lever
crossing its travel may take most of that travel to do, so the ticks just before the
first edge may already have the track turning. While a track is braked its last
``reach`` rows are held; when a row shows it released, :func:`release` takes the −100 %
back from the braked rows before it (at most ``reach``): they give no slip for that track.
"""

from __future__ import annotations

import numpy as np

from estimator._arrays import BoolArray
from estimator.tracked.model import MotionState
from estimator.tracked_spec import TRACKED_SPEC, TrackedFlag

__all__ = ["BRAKED_BITS", "HeldRows", "backdate", "release"]

_F = TrackedFlag
_SLIP_BITS = int(_F.SLIP_LEFT_VALID | _F.SLIP_RIGHT_VALID | _F.BRAKED_LEFT | _F.BRAKED_RIGHT)
_BRAKED = (int(_F.BRAKED_LEFT), int(_F.BRAKED_RIGHT))
BRAKED_BITS = int(_F.BRAKED_LEFT | _F.BRAKED_RIGHT)
_STOP = int(MotionState.STOP)
_SLIP_FIELDS = ("slip_left_pct", "slip_right_pct", "slip_left_std_pct", "slip_right_std_pct")


def backdate(
    rows: np.ndarray, onset: BoolArray, first: int, max_back: int, conf_min: float
) -> BoolArray:
    """Backdate the state changes of ``rows[first:]`` (rows of ``TRACKED_SPEC``, ``(m,)``; in
    place) and return which rows were relabelled ``(m,)``.

    For a change ``A → B`` at row ``t``: rows ``j = t−1, t−2, …`` (no further back than
    ``t − max_back``) take ``B`` and the confidence of ``t`` while row ``j`` shows ``A`` and
    row ``j + 1`` shows the change under way (``onset[j + 1]``). A relabelled row gives no
    slip (its filter step used ``A``'s odometer model) and carries ``STATE_BACKDATED``;
    ``STATE_UNCERTAIN`` follows its new confidence against ``conf_min``; one relabelled away
    from ``stop`` loses ``STANDSTILL`` (its tracks were turning)."""
    state = rows["motion_state"]
    conf = rows["state_confidence"]
    moved = np.zeros(state.size, dtype=bool)
    if max_back <= 0 or state.size < 2:
        return moved
    lo = max(first, 1)
    for t in (np.flatnonzero(state[lo:] != state[lo - 1 : -1]) + lo).tolist():
        old, j = state[t - 1], t - 1
        while j >= max(t - max_back, 0) and state[j] == old and onset[j + 1]:
            state[j], conf[j] = state[t], conf[t]
            moved[j] = True
            j -= 1
    if moved.any():
        unsure = int(_F.STATE_UNCERTAIN)
        started = np.where(state[moved] != _STOP, int(_F.STANDSTILL), 0)
        flags = rows["flags"][moved] & ~(_SLIP_BITS | unsure | started) | int(_F.STATE_BACKDATED)
        rows["flags"][moved] = np.where(conf[moved] < conf_min, flags | unsure, flags)
        for name in _SLIP_FIELDS:
            rows[name][moved] = np.nan
    return moved


def release(rows: np.ndarray, first: int, reach: int) -> BoolArray:
    """Take back the −100 % of braked rows a release reaches (``rows`` of ``TRACKED_SPEC``
    ``(m,)``, in place) and return which tracks lost it ``(m, 2)`` (left, right).

    For a track braked on row ``t − 1`` and not on row ``t`` (``t ≥ first``; row ``t`` not a
    stop, where the other track stopped instead), rows ``t − 1, t − 2, …`` (at most
    ``reach``) showing it braked lose ``BRAKED_*`` and give no slip for it (NaN): its first
    edge may have come a pitch's turn after it started."""
    flags = rows["flags"]
    out = np.zeros((rows.size, 2), dtype=bool)
    lo = max(first, 1)
    if reach <= 0 or rows.size <= lo:
        return out
    going = rows["motion_state"][lo:] != _STOP
    for side, bit in enumerate(_BRAKED):
        braked = (flags & bit) != 0
        for t in (np.flatnonzero(braked[lo - 1 : -1] & ~braked[lo:] & going) + lo).tolist():
            j = t - 1
            while j >= max(t - reach, 0) and braked[j]:
                out[j, side] = True
                j -= 1
    for side, name in enumerate(("left", "right")):
        taken = out[:, side]
        if taken.any():
            flags[taken] &= ~_BRAKED[side]
            rows[f"slip_{name}_pct"][taken] = np.nan
            rows[f"slip_{name}_std_pct"][taken] = np.nan
    return out


def _still_open(onset: BoolArray, lag: int, braked: BoolArray, reach: int) -> int:
    """How many of the last rows a later change may still relabel: the last one (the tick
    before a change), and before it every row followed by an unbroken run of onsets to the
    end, at most ``lag`` rows (0 for no lag); and the last rows showing a braked track
    (``braked`` ``(m,)``), at most ``reach``, which a release may still reach."""
    held = min(1, lag, onset.size)
    while held < min(lag, onset.size) and onset[onset.size - held]:
        held += 1
    tail = 0
    while tail < min(reach, braked.size) and braked[braked.size - 1 - tail]:
        tail += 1
    return max(held, tail)


class HeldRows:
    """One vehicle's rows not yet given (at most ``lag`` ticks): their bytes, states, onsets
    and whether any shows a braked track (kept apart so that the common case, nothing to
    backdate or release, touches no record array field by field: per vehicle and call this
    runs on the server's hot path)."""

    __slots__ = ("braked", "data", "onset", "state")

    def __init__(self) -> None:
        self.data = b""
        self.state = np.zeros(0, dtype=TRACKED_SPEC.dtype["motion_state"])
        self.onset = np.zeros(0, dtype=bool)
        self.braked = False

    def give(
        self,
        rows: np.ndarray,
        onset: BoolArray,
        lag: int,
        conf_min: float,
        reach: int = 0,
        braked: bool | None = None,
    ) -> np.ndarray:
        """Add the rows of new ticks (``onset`` ``(m,)``), take back the −100 % a release
        reaches (:func:`release`, at most ``reach`` rows), backdate their changes over the
        held ones, and return (oldest first) every row a later change can no longer reach.
        ``braked``: whether any of ``rows`` shows a braked track (read from them if None)."""
        if lag <= 0 and not self.data:
            return rows
        if braked is None:
            braked = bool((rows["flags"] & BRAKED_BITS).any())
        braked = reach > 0 and (braked or self.braked)
        if lag > 0 and rows.size and not braked and not onset.any():
            return self._give_steady(rows, onset)
        first = self.state.size
        on = np.concatenate([self.onset, onset])
        buf = np.frombuffer(bytearray(self.data + rows.tobytes()), dtype=TRACKED_SPEC.dtype)
        if braked:
            release(buf, first, reach)
        state = np.concatenate([self.state, rows["motion_state"]])
        lo = max(first, 1)
        if ((state[lo:] != state[lo - 1 : -1]) & on[lo:]).any():  # a change that can go back
            backdate(buf, on, first, lag, conf_min)
            state = buf["motion_state"]
        held_braked = (buf["flags"] & BRAKED_BITS) != 0 if braked else np.zeros(buf.size, bool)
        cut = buf.size - _still_open(on, lag, held_braked, reach)
        self.braked = bool(held_braked[cut:].any())
        return self._keep(buf, state, on, cut)

    def _give_steady(self, rows: np.ndarray, onset: BoolArray) -> np.ndarray:
        """:meth:`give` when no new row has a change under way nor a braked track, nor any
        held row a braked track (most ticks): nothing can be backdated or released and only
        the newest row stays open, so the held rows and all new rows but the last are given
        as they are, without joining the states and onsets."""
        given = np.frombuffer(bytearray(self.data + rows[:-1].tobytes()), dtype=rows.dtype)
        self.data = rows[-1:].tobytes()
        self.state = rows["motion_state"][-1:].copy()
        self.onset = onset[-1:].copy()
        return given

    def flush(self) -> np.ndarray:
        """Every held row, as it stands (no later change will backdate it), oldest first."""
        buf = np.frombuffer(bytearray(self.data), dtype=TRACKED_SPEC.dtype)
        self.braked = False
        return self._keep(buf, self.state, self.onset, buf.size)

    def _keep(self, buf: np.ndarray, state: np.ndarray, on: BoolArray, cut: int) -> np.ndarray:
        """Hold ``buf[cut:]`` and return ``buf[:cut]``."""
        self.data = buf[cut:].tobytes()
        self.state, self.onset = state[cut:].copy(), on[cut:].copy()
        return buf[:cut]
