"""One steered four-wheel vehicle's sensor buffers, read for a run of ticks at once.

:class:`SensorBuffers` holds a vehicle's IMU, CAN wheel-speed, steering and GNSS packets
(each stream in sensor-time order, as the server's reorder buffer hands them over) and turns
them into what the batched front end (:mod:`.fleetfront`) needs at each due tick ``t``:

* the mean specific force and rate over the IMU samples in ``(t − tick, t]`` (a tick without
  one is not ready);
* the latest wheel speeds and steering-wheel angle at or before ``t`` (held from earlier
  ticks; a tick before the first wheel speeds is not ready);
* the GNSS epoch: the latest one at or before ``t``; a new epoch is *fresh* until the first
  ready tick, which uses its body-frame velocity if it is at most ``gnss_timeout_s`` old and has
  a heading.

The rules are :class:`~.frontend.FrontEnd`'s (its ``_imu_window``, ``_latest`` and
``_gnss_velocity``), vectorised over one vehicle's ticks with ``searchsorted``: one read per
vehicle per ``advance`` call instead of a Python pass per tick. Samples at or before the last
tick read are dropped.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from estimator._arrays import BoolArray, FloatArray, IntArray
from estimator.types import GnssSample, ImuBatch, SteeringAngles, WheelSpeeds4

__all__ = ["SensedTicks", "SensorBuffers"]


@dataclass(frozen=True, slots=True)
class SensedTicks:
    """The ready ticks of one vehicle (or several, concatenated): ``K`` rows each.

    ``t_ns`` ``(K,)``; ``accel_mps2``, ``gyro_radps`` ``(K, 3)`` IMU means in the sensor's
    frame; ``omega_radps`` ``(K, 4)``; ``steer_rad`` ``(K,)`` (NaN before the first angle);
    ``gnss_vel_mps`` ``(K, 2)`` body-frame ``(v_x, v_y)`` of a fresh epoch (NaN without one);
    ``gnss_attitude`` ``(K, 3)`` that epoch's heading, pitch and roll [rad] and
    ``gnss_stamp_ns`` ``(K,)`` its time; ``gnss_recent`` ``(K,)`` whether the latest epoch
    (fresh or not) is at most ``gnss_timeout_s`` old.
    """

    t_ns: IntArray
    accel_mps2: FloatArray
    gyro_radps: FloatArray
    omega_radps: FloatArray
    steer_rad: FloatArray
    gnss_vel_mps: FloatArray
    gnss_attitude: FloatArray
    gnss_stamp_ns: IntArray
    gnss_recent: BoolArray

    @classmethod
    def concat(cls, parts: list[SensedTicks]) -> SensedTicks:
        """The rows of ``parts`` one after the other."""
        return cls(
            *(np.concatenate([getattr(p, f) for p in parts]) for f in cls.__dataclass_fields__)
        )

    def take(self, rows: IntArray) -> SensedTicks:
        """The rows ``rows``."""
        return SensedTicks(*(getattr(self, f)[rows] for f in self.__dataclass_fields__))


class _Stream:
    """Stamped samples of one stream ``(n,)`` stamps, ``(n, …)`` values, in time order; packets
    pushed since the last read are joined on the next one."""

    def __init__(self, width: int) -> None:
        self.stamps: IntArray = np.zeros(0, dtype=np.int64)
        self.values: FloatArray = np.zeros((0, width))
        self._pending: list[tuple[IntArray, FloatArray]] = []

    def push(self, stamps_ns: IntArray, values: FloatArray) -> None:
        self._pending.append((stamps_ns, values.reshape(stamps_ns.size, -1)))

    def joined(self) -> None:
        """Join the pending packets (a stable sort if one came out of time order)."""
        if not self._pending:
            return
        stamps = np.concatenate([self.stamps, *(s for s, _ in self._pending)])
        values = np.concatenate([self.values, *(v for _, v in self._pending)])
        self._pending.clear()
        if stamps.size > 1 and np.any(stamps[1:] < stamps[:-1]):
            order = np.argsort(stamps, kind="stable")
            stamps, values = stamps[order], values[order]
        self.stamps, self.values = stamps, values

    def last_ns(self) -> int | None:
        if self._pending:
            self.joined()
        return int(self.stamps[-1]) if self.stamps.size else None

    def drop(self, keep: int) -> None:
        """Forget the first ``keep`` samples (those at or before the last tick read)."""
        if keep:
            self.stamps, self.values = self.stamps[keep:], self.values[keep:]

    def latest(self, ticks_ns: IntArray, held: FloatArray) -> FloatArray:
        """The last sample at or before each tick ``(K, width)``, ``held`` before the first;
        the samples up to the last tick are dropped."""
        self.joined()
        end = np.searchsorted(self.stamps, ticks_ns, side="right")
        if end[0] > 0:  # the usual case: a sample at or before every tick
            out = self.values[end - 1]
        else:
            out = np.empty((ticks_ns.size, self.values.shape[1]))
            out[:] = held
            have = end > 0
            out[have] = self.values[end[have] - 1]
        self.drop(int(end[-1]))
        return out

    def window_means(self, ticks_ns: IntArray, span_ns: int) -> tuple[FloatArray, IntArray]:
        """Mean of the samples in ``(t − span, t]`` per tick ``(K, width)`` and their count;
        the samples up to the last tick are dropped."""
        self.joined()
        k = ticks_ns.size
        edges = np.searchsorted(
            self.stamps, np.concatenate([ticks_ns - span_ns, ticks_ns]), "right"
        )
        lo, hi = edges[:k], edges[k:]
        sums = np.zeros((self.stamps.size + 1, self.values.shape[1]))
        np.cumsum(self.values, axis=0, out=sums[1:])
        count = hi - lo
        means = (sums[hi] - sums[lo]) / np.maximum(count, 1)[:, None]
        self.drop(int(hi[-1]))
        return means, count


class SensorBuffers:
    """One vehicle's packets since the last tick read (see the module docstring)."""

    def __init__(self, tick_ns: int, gnss_timeout_s: float) -> None:
        self.tick_ns = tick_ns
        self.gnss_timeout_ns = gnss_timeout_s * 1e9
        self.imu = _Stream(6)  # [accel xyz, gyro xyz]
        self.wheels = _Stream(4)
        self.steering = _Stream(1)
        self.gnss_queue: deque[GnssSample] = deque()
        self.omega = np.full(4, np.nan)
        self.steer = np.full(1, np.nan)
        self.gnss: GnssSample | None = None
        self.gnss_fresh = False

    def push_imu(self, m: ImuBatch) -> None:
        stamps = np.atleast_1d(np.asarray(m.stamp_ns, dtype=np.int64))
        both = np.concatenate(
            [
                np.asarray(m.accel_mps2, float).reshape(-1, 3),
                np.asarray(m.gyro_radps, float).reshape(-1, 3),
            ],
            axis=1,
        )
        self.imu.push(stamps, both)

    def push_wheels(self, m: WheelSpeeds4) -> None:
        self.wheels.push(
            np.atleast_1d(np.asarray(m.stamp_ns, dtype=np.int64)), np.asarray(m.omega_radps, float)
        )

    def push_steering(self, m: SteeringAngles) -> None:
        self.steering.push(
            np.atleast_1d(np.asarray(m.stamp_ns, dtype=np.int64)), np.asarray(m.angle_rad, float)
        )

    def push_gnss(self, m: GnssSample) -> None:
        self.gnss_queue.append(m)

    def imu_until_ns(self) -> int | None:
        """The last IMU sample time held (ticks up to it can be computed)."""
        return self.imu.last_ns()

    def first_imu_ns(self) -> int | None:
        """The first IMU sample time held."""
        return int(self.imu.stamps[0]) if self.imu.last_ns() is not None else None

    def read(self, ticks_ns: IntArray) -> SensedTicks:
        """The ready ones of the ticks ``ticks_ns`` ``(K,)`` (increasing, ``tick_ns`` apart)."""
        imu, count = self.imu.window_means(ticks_ns, self.tick_ns)
        omega = self.wheels.latest(ticks_ns, self.omega)
        steer = self.steering.latest(ticks_ns, self.steer)[:, 0]
        self.omega, self.steer = omega[-1].copy(), steer[-1:].copy()
        ready = (count > 0) & np.isfinite(omega).all(axis=1)
        keep: slice | IntArray = slice(None) if ready.all() else np.flatnonzero(ready)
        gnss = self._gnss(ticks_ns, ready)
        return SensedTicks(
            t_ns=ticks_ns[keep],
            accel_mps2=imu[keep, :3],
            gyro_radps=imu[keep, 3:],
            omega_radps=omega[keep],
            steer_rad=steer[keep],
            gnss_vel_mps=gnss[0],
            gnss_attitude=gnss[1],
            gnss_stamp_ns=gnss[2],
            gnss_recent=gnss[3],
        )

    def _gnss(
        self, ticks_ns: IntArray, ready: BoolArray
    ) -> tuple[FloatArray, FloatArray, IntArray, BoolArray]:
        """The GNSS columns of :class:`SensedTicks` for the ready ticks."""
        n = int(ready.sum())
        vel = np.full((n, 2), np.nan)
        att = np.full((n, 3), np.nan)
        stamp = np.zeros(n, dtype=np.int64)
        recent = np.zeros(n, dtype=bool)
        k = 0
        for t, ok in zip(ticks_ns.tolist(), ready.tolist(), strict=True):
            while self.gnss_queue and self.gnss_queue[0].stamp_ns <= t:
                self.gnss = self.gnss_queue.popleft()
                self.gnss_fresh = True
            g = self.gnss
            if not ok or g is None:
                k += ok
                continue
            recent[k] = t - g.stamp_ns <= self.gnss_timeout_ns
            if self.gnss_fresh:
                self.gnss_fresh = False
                h = g.heading_rad
                if t - g.stamp_ns <= self.gnss_timeout_ns and math.isfinite(h):
                    ve, vn, _ = g.vel_enu_mps
                    vel[k] = (
                        ve * math.sin(h) + vn * math.cos(h),
                        -ve * math.cos(h) + vn * math.sin(h),
                    )
                    att[k] = h, g.pitch_rad, g.roll_rad
                    stamp[k] = g.stamp_ns
            k += 1
        return vel, att, stamp, recent
