"""Where a steered four-wheel vehicle is: its GNSS antenna in the vehicle's local ENU frame.

The frame is anchored at the first fix with a position (or the anchor the server restores,
:meth:`PositionTrack.set_anchor`); ``east``, ``north``, ``up`` are metres from it, heading
``ψ`` clockwise from north. The position is the antenna's; the speeds it is carried with are
the antenna's too (the fleet moves the CG's through the config's ``antenna_lever_arm_m``).

* **A fresh fix** (a new GNSS epoch with a position, at or before the tick) places the
  vehicle: its ENU position moved to the tick with its velocity, ``p = p_fix + v_enu·(t −
  t_fix)``. Its heading is the receiver's (dual antenna) or, without one and while moving
  (``|v| >= min_course_speed_mps``), the course over ground turned back by the side-slip,
  ``ψ = atan2(v_e, v_n) + atan2(v_y, v_x)`` (the velocity points ``β = atan2(v_y, v_x)`` left
  of the heading).
* **Between fixes and through outages** the position is dead-reckoned from the tick before
  with the body speeds and the gyro's yaw rate ``r`` (counter-clockwise):

      ψ(k) = ψ(k−1) − r·Δt,    ψ̄ = ψ(k−1) − r·Δt/2
      p(k) = p(k−1) + Δt·(v_x (sin ψ̄, cos ψ̄) + v_y (−cos ψ̄, sin ψ̄))        (east, north)

  the height held. Rows whose last fix is older than ``after_s`` are flagged dead-reckoned;
  after ``max_s`` without a fix there is no position (NaN) rather than a drifting one: the
  friction front end has no gyro-bias estimate, and a 0.003 rad/s bias turns the heading
  0.03 rad in 10 s (about 2 m across the track at 15 m/s).

Pure: no clock, no I/O. :class:`PositionTrack` is one vehicle's; :class:`FleetPositions` holds
every vehicle's by slot and places (the round's fresh fixes through the single track's
function, one call) and dead-reckons all vehicles of a round in one numpy pass.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from estimator._arrays import BoolArray, FloatArray, IntArray
from estimator.config import ConfigError
from estimator.geo import EnuFrame, enu_from_geodetic
from estimator.types import GnssFix, GnssSample

__all__ = ["FleetPositions", "PositionConfig", "PositionTick", "PositionTrack"]


@dataclass(frozen=True, slots=True)
class PositionConfig:
    """Settings of the position track.

    Attributes
    ----------
    after_s : float
        A tick whose last fix is older than this is flagged dead-reckoned [s].
    max_s : float
        Dead-reckon at most this long after the last fix; NaN after [s].
    min_course_speed_mps : float
        A fix without a receiver heading gives one from its course only at this speed or more.
    """

    after_s: float = 0.25
    max_s: float = 10.0
    min_course_speed_mps: float = 1.0

    def __post_init__(self) -> None:
        for name in ("after_s", "max_s", "min_course_speed_mps"):
            value = getattr(self, name)
            if not math.isfinite(value) or value < 0:
                raise ConfigError(f"position.{name} must be finite and >= 0, got {value!r}")


@dataclass(frozen=True, slots=True)
class PositionTick:
    """One tick's position: metres in the vehicle's ENU frame, heading clockwise from north
    (all NaN when unknown), and whether it was dead-reckoned past ``after_s``."""

    east_m: float
    north_m: float
    up_m: float
    heading_rad: float
    dead_reckoned: bool


_NONE = PositionTick(math.nan, math.nan, math.nan, math.nan, False)


def _has_position(g: GnssSample) -> bool:
    return g.fix != GnssFix.NONE and all(
        math.isfinite(v) for v in (g.lat_deg, g.lon_deg, g.height_m)
    )


class PositionTrack:
    """One vehicle's position, a tick at a time (:meth:`step`), from its GNSS epochs
    (:meth:`push`) and the friction front end's speeds and yaw rate."""

    def __init__(self, config: PositionConfig) -> None:
        self.config = config
        self.frame: EnuFrame | None = None
        self._fixes: deque[GnssSample] = deque()
        self._enu = [math.nan, math.nan, math.nan]
        self._heading_rad = math.nan
        self._fix_ns: int | None = None  # stamp of the last fix that placed the vehicle
        self._tick_ns: int | None = None

    def push(self, g: GnssSample) -> None:
        """Queue a GNSS epoch (sensor-time order); those without a position are skipped."""
        if _has_position(g):
            self._fixes.append(g)

    def anchor(self) -> tuple[float, float, float] | None:
        """``(lat_deg, lon_deg, height_m)`` of the ENU frame's origin; None before the first
        fix."""
        f = self.frame
        return None if f is None else (f.lat0_deg, f.lon0_deg, f.h0_m)

    def set_anchor(self, lat_deg: float, lon_deg: float, height_m: float) -> None:
        """Put the ENU frame's origin here instead of at the first fix (``ValueError`` for what
        is no geodetic position)."""
        if not all(math.isfinite(v) for v in (lat_deg, lon_deg, height_m)) or abs(lat_deg) > 90:
            raise ValueError(f"not a geodetic anchor: {(lat_deg, lon_deg, height_m)}")
        self.frame = EnuFrame(lat_deg, lon_deg, height_m)

    def step(self, t_ns: int, vx_mps: float, vy_mps: float, yaw_rate_radps: float) -> PositionTick:
        """The position at tick ``t_ns`` from the latest fix at or before it (when fresh) or
        carried from the tick before by ``v_x``, ``v_y`` (body, left +) and ``r``."""
        fix = None
        while self._fixes and self._fixes[0].stamp_ns <= t_ns:
            fix = self._fixes.popleft()
        dt_s = 0.0 if self._tick_ns is None else (t_ns - self._tick_ns) * 1e-9
        self._tick_ns = t_ns
        if fix is not None:
            self._place(fix, t_ns, vx_mps, vy_mps, yaw_rate_radps * dt_s)
        elif not self._carry(t_ns, dt_s, vx_mps, vy_mps, yaw_rate_radps):
            return _NONE
        assert self._fix_ns is not None  # placed or carried: there was a fix
        late = t_ns - self._fix_ns > round(self.config.after_s * 1e9)
        east, north, up = self._enu
        return PositionTick(east, north, up, self._heading_rad, late)

    def _place(self, g: GnssSample, t_ns: int, vx: float, vy: float, turn_rad: float) -> None:
        """Put the vehicle at the fix ``g`` moved to ``t_ns``, heading as the module says."""
        if self.frame is None:
            self.frame = EnuFrame(g.lat_deg, g.lon_deg, g.height_m)
        f = self.frame
        gyro = self._heading_rad - (turn_rad if math.isfinite(turn_rad) else 0.0)
        enu, heading = _placed(
            np.array([[f.lat0_deg, f.lon0_deg, f.h0_m]]),
            [g],
            np.array([t_ns], dtype=np.int64),
            np.array([[vx, vy]]),
            np.array([gyro]),
            self.config,
        )
        self._enu, self._heading_rad = enu[0].tolist(), float(heading[0])
        self._fix_ns = g.stamp_ns

    def _carry(self, t_ns: int, dt_s: float, vx: float, vy: float, r: float) -> bool:
        """Dead-reckon one tick (module docstring); False, and the track ended, when there is
        nothing to carry, no speed or heading, or the last fix is ``max_s`` old."""
        ok = (
            self._fix_ns is not None
            and t_ns - self._fix_ns <= round(self.config.max_s * 1e9)
            and math.isfinite(self._enu[0])
            and math.isfinite(self._heading_rad)
            and math.isfinite(vx)
            and math.isfinite(r)
        )
        if not ok:
            self._enu = [math.nan, math.nan, math.nan]
            return False
        vy = vy if math.isfinite(vy) else 0.0
        mid = self._heading_rad - 0.5 * r * dt_s
        s, c = math.sin(mid), math.cos(mid)
        self._enu[0] += dt_s * (vx * s - vy * c)
        self._enu[1] += dt_s * (vx * c + vy * s)
        self._heading_rad = (self._heading_rad - r * dt_s) % (2 * math.pi)
        return True


def _placed(
    anchors: FloatArray,
    fixes: list[GnssSample],
    t_ns: IntArray,
    body_mps: FloatArray,
    gyro_heading_rad: FloatArray,
    config: PositionConfig,
) -> tuple[FloatArray, FloatArray]:
    """ENU positions ``(F, 3)`` at ``t_ns`` ``(F,)`` of the ``F`` fixes, each in the frame
    anchored at its row of ``anchors`` ``(F, 3)`` (lat, lon [deg], height [m]), and headings
    ``(F,)`` (module docstring): the receiver's, else the course turned back by the side-slip
    of ``body_mps`` ``(F, 2)`` ``(v_x, v_y)``, else (standing) ``gyro_heading_rad`` ``(F,)``,
    the last heading turned by the gyro (NaN if none)."""
    fix = np.array([(g.lat_deg, g.lon_deg, g.height_m, g.heading_rad) for g in fixes])
    vel = np.array([g.vel_enu_mps for g in fixes], dtype=float)
    vel[~np.isfinite(vel)] = 0.0
    stamp_ns = np.array([g.stamp_ns for g in fixes], dtype=np.int64)
    at_fix = enu_from_geodetic(fix[:, 0], fix[:, 1], fix[:, 2], *anchors.T)
    enu = np.stack(at_fix, axis=1) + vel * ((t_ns - stamp_ns) * 1e-9)[:, None]
    vx, vy = body_mps.T
    ve, vn = vel[:, 0], vel[:, 1]
    course = np.arctan2(ve, vn) + np.arctan2(np.where(np.isfinite(vy), vy, 0.0), vx)
    moving = (np.hypot(ve, vn) >= config.min_course_speed_mps) & np.isfinite(vx)
    own = np.isfinite(fix[:, 3])
    heading = np.where(own, fix[:, 3], np.where(moving, course, gyro_heading_rad))
    return enu, heading % (2 * math.pi)


class FleetPositions:
    """:class:`PositionTrack` for every vehicle by slot; :meth:`step` a round at once."""

    def __init__(self, config: PositionConfig) -> None:
        self.config = config
        self.frames: list[EnuFrame | None] = []
        self._fixes: list[deque[GnssSample]] = []
        self._enu = np.zeros((0, 3))
        self._heading_rad = np.zeros(0)
        self._fix_ns = np.zeros(0, dtype=np.int64)
        self._placed = np.zeros(0, dtype=bool)  # a fix has placed the vehicle
        self._tick_ns = np.zeros(0, dtype=np.int64)
        self._ticked = np.zeros(0, dtype=bool)

    def add(self, slot: int) -> None:
        """Start slot ``slot``'s track afresh."""
        if slot >= len(self.frames):
            more = slot + 1 - len(self.frames)
            self.frames += [None] * more
            self._fixes += [deque() for _ in range(more)]
            self._enu = np.concatenate([self._enu, np.zeros((more, 3))])
            self._heading_rad = np.concatenate([self._heading_rad, np.zeros(more)])
            self._fix_ns = np.concatenate([self._fix_ns, np.zeros(more, dtype=np.int64)])
            self._placed = np.concatenate([self._placed, np.zeros(more, dtype=bool)])
            self._tick_ns = np.concatenate([self._tick_ns, np.zeros(more, dtype=np.int64)])
            self._ticked = np.concatenate([self._ticked, np.zeros(more, dtype=bool)])
        self.frames[slot] = None
        self._fixes[slot].clear()
        self._enu[slot] = math.nan
        self._heading_rad[slot] = math.nan
        self._placed[slot] = self._ticked[slot] = False

    def push(self, slot: int, g: GnssSample) -> None:
        """Queue a GNSS epoch of slot ``slot`` (those without a position are skipped)."""
        if _has_position(g):
            self._fixes[slot].append(g)

    def anchor(self, slot: int) -> tuple[float, float, float] | None:
        """Slot ``slot``'s ENU origin (:meth:`PositionTrack.anchor`)."""
        f = self.frames[slot]
        return None if f is None else (f.lat0_deg, f.lon0_deg, f.h0_m)

    def set_anchor(self, slot: int, lat_deg: float, lon_deg: float, height_m: float) -> None:
        """Slot ``slot``'s ENU origin put here (:meth:`PositionTrack.set_anchor`)."""
        if not all(math.isfinite(v) for v in (lat_deg, lon_deg, height_m)) or abs(lat_deg) > 90:
            raise ValueError(f"not a geodetic anchor: {(lat_deg, lon_deg, height_m)}")
        self.frames[slot] = EnuFrame(lat_deg, lon_deg, height_m)

    def step(
        self, s: IntArray, t_ns: IntArray, vx_mps: FloatArray, vy_mps: FloatArray, r: FloatArray
    ) -> tuple[FloatArray, FloatArray, BoolArray]:
        """Positions of slots ``s`` ``(B,)`` at their ticks: ENU ``(B, 3)`` and heading ``(B,)``
        (NaN where none) and whether dead-reckoned past ``after_s`` (:meth:`PositionTrack.step`)."""
        dt_s = np.where(self._ticked[s], (t_ns - self._tick_ns[s]) * 1e-9, 0.0)
        self._tick_ns[s], self._ticked[s] = t_ns, True
        rows, fixes = [], []
        for i, (slot, t) in enumerate(zip(s.tolist(), t_ns.tolist(), strict=True)):
            queue = self._fixes[slot]
            if not queue or queue[0].stamp_ns > t:
                continue
            while queue and queue[0].stamp_ns <= t:
                fix = queue.popleft()
            rows.append(i)
            fixes.append(fix)
        fixed = np.zeros(s.size, dtype=bool)
        if fixes:
            at = np.array(rows)
            fixed[at] = True
            body = np.stack([vx_mps[at], vy_mps[at]], axis=1)
            self._place(s[at], fixes, t_ns[at], body, r[at] * dt_s[at])
        ok = fixed | self._carry(s, ~fixed, t_ns, dt_s, vx_mps, vy_mps, r)
        enu, heading = self._enu[s], self._heading_rad[s]
        enu[~ok], heading[~ok] = math.nan, math.nan
        late = ok & (t_ns - self._fix_ns[s] > round(self.config.after_s * 1e9))
        return enu, heading, late

    def _place(
        self,
        s: IntArray,
        fixes: list[GnssSample],
        t_ns: IntArray,
        body_mps: FloatArray,
        turn_rad: FloatArray,
    ) -> None:
        """Put the vehicles in slots ``s`` ``(F,)`` at their ``fixes`` moved to ``t_ns``
        (:func:`_placed`); a vehicle's first fix anchors its frame."""
        for slot, g in zip(s.tolist(), fixes, strict=True):
            if self.frames[slot] is None:
                self.frames[slot] = EnuFrame(g.lat_deg, g.lon_deg, g.height_m)
        frames = [self.frames[slot] for slot in s.tolist()]
        anchors = np.array([(f.lat0_deg, f.lon0_deg, f.h0_m) for f in frames if f is not None])
        gyro = self._heading_rad[s] - np.where(np.isfinite(turn_rad), turn_rad, 0.0)
        enu, heading = _placed(anchors, fixes, t_ns, body_mps, gyro, self.config)
        self._enu[s], self._heading_rad[s] = enu, heading
        self._fix_ns[s] = [g.stamp_ns for g in fixes]
        self._placed[s] = True

    def _carry(
        self,
        s: IntArray,
        rows: BoolArray,
        t_ns: IntArray,
        dt_s: FloatArray,
        vx: FloatArray,
        vy: FloatArray,
        r: FloatArray,
    ) -> BoolArray:
        """Dead-reckon the ``rows`` of ``s`` one tick; where there is nothing to carry, or the
        last fix is ``max_s`` old, the track ends (NaN). True where carried."""
        enu, heading = self._enu[s], self._heading_rad[s]
        ok = (
            rows
            & self._placed[s]
            & (t_ns - self._fix_ns[s] <= round(self.config.max_s * 1e9))
            & np.isfinite(enu[:, 0])
            & np.isfinite(heading)
            & np.isfinite(vx)
            & np.isfinite(r)
        )
        self._enu[s[rows & ~ok]] = math.nan
        c, dt, vx, r = s[ok], dt_s[ok], vx[ok], r[ok]
        vy = np.where(np.isfinite(vy[ok]), vy[ok], 0.0)
        heading, enu = heading[ok], enu[ok]
        mid = heading - 0.5 * r * dt
        sin, cos = np.sin(mid), np.cos(mid)
        enu[:, 0] += dt * (vx * sin - vy * cos)
        enu[:, 1] += dt * (vx * cos + vy * sin)
        self._enu[c], self._heading_rad[c] = enu, (heading - r * dt) % (2 * math.pi)
        return ok
