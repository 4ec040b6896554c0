"""Where a steered four-wheel vehicle is: its GNSS antenna in the vehicle's local ENU frame.

The frame is anchored at the first fix with a position (or the anchor the server restores,
:meth:`PositionTrack.set_anchor`); ``east``, ``north``, ``up`` are metres from it, heading
``ψ`` clockwise from north. The steered config carries no antenna lever arm: the position is
the antenna's (on the four-wheel simulator it sits at the CG).

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

Pure: no clock, no I/O; one vehicle per object (the fleet steps each vehicle's own).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

from estimator.config import ConfigError
from estimator.geo import EnuFrame
from estimator.types import GnssFix, GnssSample

__all__ = ["PositionConfig", "PositionTick", "PositionTrack"]


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
        east, north, up = (float(c) for c in self.frame.to_enu(g.lat_deg, g.lon_deg, g.height_m))
        ve, vn, vu = (v if math.isfinite(v) else 0.0 for v in g.vel_enu_mps)
        age_s = (t_ns - g.stamp_ns) * 1e-9
        self._enu = [east + ve * age_s, north + vn * age_s, up + vu * age_s]
        if math.isfinite(g.heading_rad):
            heading = g.heading_rad
        elif math.hypot(ve, vn) >= self.config.min_course_speed_mps and math.isfinite(vx):
            heading = math.atan2(ve, vn) + math.atan2(vy if math.isfinite(vy) else 0.0, vx)
        else:  # standing, no receiver heading: the gyro's from the last one (NaN if none)
            heading = self._heading_rad - (turn_rad if math.isfinite(turn_rad) else 0.0)
        self._heading_rad = heading % (2 * math.pi)
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
