"""Position and heading carried through GNSS outages by dead reckoning, vectorised over vehicles.

While GNSS gives no position (no-fix epochs, or no epochs at all) the estimator still has the
vehicle's speed (the reference-speed filter, DEGRADED mode) and yaw rate, so the track and the
slip map need not break at every tree line. From the last position the GNSS gave, the
reference point ``O`` (rear-axle midpoint) moves along the heading and the antenna follows at
its lever arm:

    ψ(k+1) = ψ(k) − ω_z(k)·dT                       (heading clockwise from north; ω_z up)
    p_O(k+1) = p_O(k) + v0(k)·cos θ(k)·dT·(sin ψ̄, cos ψ̄),  ψ̄ = ψ(k) − ω_z(k)·dT/2   (east, north)
    p_ant = p_O + x·(cos ψ, −sin ψ) + y·(sin ψ, cos ψ)

with ``v0`` the forward speed of ``O`` (MDSF eq. (3), carried by the reference-speed filter
while GNSS is lost), ``θ`` the pitch (horizontal share of the speed on a slope), ``(x, y)`` the
antenna's offset right and forward of ``O`` (``GeometryConfig.antenna_offset_m``) and ``dT`` the
tick (the mid-step heading ``ψ̄`` makes a circle's chord exact to second order). The height is
held. Sideslip is not modelled.

Choices:

* **When a fix still places the vehicle.** A tick's position counts as measured when its fix
  has a position and is at most ``DeadReckoningConfig.after_s`` old (the front end moves it to
  the tick with the fix's velocity); older, or none: carried.
* **Heading.** Between fixes the heading is the gyro's integral; a fix resets it to the GNSS
  heading only while the vehicle moves (``|v0| >= min_course_speed_mps``): at a standstill a
  course over ground is noise.
* **How long.** The heading error grows with the gyro bias and the position error with the time
  (a 0.05 °/s bias: ~3 ° after a minute, ~3 m across the track at 2 m/s); after ``max_s``
  without a position the estimator gives none again (NaN) rather than a drifting one.

A carried row is flagged :attr:`~estimator.types.EstimateFlag.DEAD_RECKONED`. Nothing here
reads a clock or raises on NaN: a tick without a speed ends the carry (no position until the
next fix).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estimator._arrays import BoolArray, FloatArray, IntArray, nan_to_num
from estimator.config import ConfigError

__all__ = ["DeadReckoning", "DeadReckoningConfig"]


@dataclass(frozen=True, slots=True)
class DeadReckoningConfig:
    """Settings of the dead reckoning through GNSS outages.

    Attributes
    ----------
    after_s : float
        A fix older than this no longer places the vehicle; its ticks are carried [s].
    max_s : float
        Carry at most this long after the last position; NaN after [s]. 0 turns it off.
    min_course_speed_mps : float
        A fix resets the heading only while ``|v0|`` is at least this [m/s].
    """

    after_s: float = 0.25
    max_s: float = 60.0
    min_course_speed_mps: float = 0.5

    def __post_init__(self) -> None:
        for name in ("after_s", "max_s", "min_course_speed_mps"):
            value = getattr(self, name)
            if not np.isfinite(value) or value < 0:
                raise ConfigError(f"{name} must be finite and >= 0, got {value!r}")


class DeadReckoning:
    """Per-slot carry state; :meth:`step` fills one tick of several vehicles.

    Parameters
    ----------
    config : DeadReckoningConfig
    dt_s : float
        The tick ``dT`` [s].
    """

    def __init__(self, config: DeadReckoningConfig, dt_s: float) -> None:
        self.config = config
        self.dt_s = dt_s
        self.origin = np.zeros((0, 3))  # p_O at the last tick (east, north, up) [m]
        self.heading_rad = np.zeros(0)  # ψ at the last tick
        self.since_s = np.zeros(0)  # time since the last measured position [s]
        self.has = np.zeros(0, dtype=bool)  # origin and heading hold a value
        self.antenna_m = np.zeros((0, 2))  # antenna (x right, y forward) of O [m]
        self._any_lever = False  # some slot's antenna is off O (else the arm is skipped)

    def add(self, slot: int, antenna_offset_m: tuple[float, float]) -> None:
        """Start ``slot`` with nothing to carry (its first fix gives the origin)."""
        if slot >= self.has.shape[0]:
            cap = max(2 * self.has.shape[0], slot + 1)
            n = cap - self.has.shape[0]
            self.origin = np.concatenate([self.origin, np.zeros((n, 3))])
            self.heading_rad = np.concatenate([self.heading_rad, np.zeros(n)])
            self.since_s = np.concatenate([self.since_s, np.zeros(n)])
            self.has = np.concatenate([self.has, np.zeros(n, dtype=bool)])
            self.antenna_m = np.concatenate([self.antenna_m, np.zeros((n, 2))])
        self.has[slot] = False
        self.antenna_m[slot] = antenna_offset_m
        self._any_lever = self._any_lever or any(antenna_offset_m)

    def _lever(self, slots: IntArray, heading_rad: FloatArray) -> FloatArray:
        """Antenna minus ``O`` in (east, north), shape ``(n, 2)``, at headings ``heading_rad``."""
        if not self._any_lever:
            return np.zeros((slots.shape[0], 2))
        x, y = self.antenna_m[slots, 0], self.antenna_m[slots, 1]
        s, c = np.sin(heading_rad), np.cos(heading_rad)
        return np.stack([x * c + y * s, y * c - x * s], axis=1)

    def step(
        self,
        slots: IntArray,
        enu_m: FloatArray,
        fix_age_s: FloatArray,
        heading_rad: FloatArray,
        v0_mps: FloatArray,
        yaw_rate_radps: FloatArray,
        pitch_rad: FloatArray,
    ) -> tuple[FloatArray, FloatArray, BoolArray]:
        """One tick of the vehicles in ``slots`` (distinct): measured positions set the carry,
        the others are carried.

        Parameters
        ----------
        slots : ndarray, shape (n,), int
        enu_m : ndarray, shape (n, 3)
            Antenna position from GNSS (NaN: none) [m].
        fix_age_s : ndarray, shape (n,)
            Age of the fix ``enu_m`` was moved from [s].
        heading_rad : ndarray, shape (n,)
            Heading from GNSS (NaN: none), clockwise from north.
        v0_mps, yaw_rate_radps, pitch_rad : ndarray, shape (n,)
            The filter's speed of ``O``, yaw rate (ENU, counter-clockwise) and pitch this tick.

        Returns
        -------
        enu_m : ndarray, shape (n, 3)
            Positions: measured as given, carried ones filled.
        heading_rad : ndarray, shape (n,)
        carried : ndarray, shape (n,), bool
        """
        cfg, dt = self.config, self.dt_s
        measured = np.isfinite(enu_m).all(axis=1) & (fix_age_s <= cfg.after_s)
        speed = nan_to_num(v0_mps)
        moving = np.abs(speed) >= cfg.min_course_speed_mps
        has = self.has[slots]
        # the heading: a moving fix's, else the gyro's integral from the last one
        turn = nan_to_num(yaw_rate_radps) * dt
        before = self.heading_rad[slots]
        take = measured & np.isfinite(heading_rad) & (moving | ~has)
        psi = np.mod(np.where(take, heading_rad, before - turn), 2.0 * np.pi)
        if measured.all():  # the usual tick: every vehicle placed by its fix
            return self._place_all(slots, enu_m, heading_rad, psi)
        mid = before - 0.5 * turn
        carried = ~measured & has & np.isfinite(v0_mps) & (self.since_s[slots] + dt <= cfg.max_s)
        horiz = speed * np.cos(nan_to_num(pitch_rad)) * dt
        return self._carry(slots, enu_m, heading_rad, psi, (measured, carried), horiz, mid)

    def _place_all(
        self, slots: IntArray, enu_m: FloatArray, heading_rad: FloatArray, psi: FloatArray
    ) -> tuple[FloatArray, FloatArray, BoolArray]:
        """:meth:`step` when every vehicle has a fix: origins from the fixes, nothing carried."""
        origin = enu_m.copy()
        origin[:, :2] -= self._lever(slots, psi)
        self.origin[slots] = origin
        self.heading_rad[slots] = psi
        self.since_s[slots] = 0.0
        self.has[slots] = True
        return enu_m, heading_rad, np.zeros(slots.shape[0], dtype=bool)

    def _carry(
        self,
        slots: IntArray,
        enu_m: FloatArray,
        heading_rad: FloatArray,
        psi: FloatArray,
        masks: tuple[BoolArray, BoolArray],
        horiz: FloatArray,
        mid: FloatArray,
    ) -> tuple[FloatArray, FloatArray, BoolArray]:
        """:meth:`step` otherwise: ``carried`` moved ``horiz`` along the mid-tick heading."""
        measured, carried = masks
        dt = self.dt_s
        moved = self.origin[slots].copy()
        moved[:, 0] += horiz * np.sin(mid)
        moved[:, 1] += horiz * np.cos(mid)
        lever = self._lever(slots, psi)
        at_fix = enu_m.copy()
        at_fix[:, :2] -= lever
        origin = np.where(measured[:, None], at_fix, moved)
        out = enu_m.copy()
        out[carried, :2] = moved[carried, :2] + lever[carried]
        out[carried, 2] = moved[carried, 2]
        heading_out = np.where(carried, psi, heading_rad)
        keep = measured | carried
        self.origin[slots] = np.where(keep[:, None], origin, self.origin[slots])
        self.heading_rad[slots] = psi
        self.since_s[slots] = np.where(measured, 0.0, self.since_s[slots] + dt)
        self.has[slots] = keep
        return out, heading_out, carried
