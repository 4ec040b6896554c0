"""A second synthetic source for the browser tests: a crawler (``tracked`` rows) and a steered
four-wheel vehicle (``friction`` rows), pushed into sinks (the live hub, the store's writer) at
20 Hz, stamped with the wall clock, as the pipeline would (one batch per estimator per tick).

The rows follow the wall clock so a test can say what the page must show at any moment:

* crawler: drives east at 5 m/s; its motion state steps through the spec's states every
  :data:`STATE_S` seconds; every other :data:`CARRIED_S`-second stretch is dead-reckoned
  (``DEAD_RECKONING``, position 1-σ growing 0.5 m a second), the others fused with GNSS
  (``GNSS_OK``, 1-σ :data:`FIX_STD_M`); every third state is flagged ``STATE_UNCERTAIN``;
  its odometer factor is 0.95 + 0.04·sin(east / 50 m) (a map layer informed while GNSS is);
  its gyro's angle random walk measured standing is :data:`GYRO_ARW_DEG_RT_H` and its
  receiver's clock :data:`GNSS_CLOCK_S` (both converged); it
  climbs a steady grade (pitch :data:`PITCH_RAD`) across a side slope rolling
  :func:`crawler_roll_rad` (within ±0.1 rad, under the side-slope alert).
* steered vehicle: μ is informed (``INFORMED``, 0.8 ± 0.02) in every other :data:`MU_S`-second
  stretch and held at 0.8 (``HELD``, 1-σ 0.15: the filter at 0.65 now) in the others; grip
  used per wheel is :data:`GRIP_PCT`.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from estimator.friction_spec import FRICTION_SPEC, WHEEL_KEYS, FrictionFlag
from estimator.tracked_spec import TRACKED_SPEC, TrackedFlag
from estimator.types import EstimateBatch

CRAWLER = "crawler-1"
STEERED = "steered-1"
STATE_S = 2
CARRIED_S = 4
MU_S = 3
FIX_STD_M = 0.3
GRIP_PCT = {"fl": 20.0, "fr": 45.0, "rl": 70.0, "rr": 95.0}
GYRO_ARW_DEG_RT_H = (0.4, 0.03)  # the crawler's gyro noise measured standing, converged (< 10 %)
GNSS_CLOCK_S = (0.065, 0.004)  # its receiver's clock less the IMU's, converged (< 10 ms)
PITCH_RAD = 0.06
ATTITUDE_STD_RAD = 0.003
_NS = 1_000_000_000
_STATES = len(TRACKED_SPEC.states[0].states)


def crawler_state(stamp_ns: int) -> int:
    """The motion state value the crawler's row of ``stamp_ns`` carries."""
    return (stamp_ns // (STATE_S * _NS)) % _STATES


def crawler_carried(stamp_ns: int) -> bool:
    """Whether the crawler's row of ``stamp_ns`` is dead-reckoned."""
    return bool((stamp_ns // (CARRIED_S * _NS)) % 2)


def crawler_sigma_m(stamp_ns: int) -> float:
    """East and north 1-σ (each) of the crawler's row of ``stamp_ns``, metres."""
    if not crawler_carried(stamp_ns):
        return FIX_STD_M
    return FIX_STD_M + 0.5 * (stamp_ns % (CARRIED_S * _NS)) / _NS


def crawler_roll_rad(t_s: np.ndarray) -> np.ndarray:
    """The crawler's roll at ``t_s`` (seconds into the hour), rad."""
    return 0.1 * np.sin(t_s / 10.0)


def mu_informed(stamp_ns: int) -> bool:
    """Whether the steered vehicle's row of ``stamp_ns`` informs μ."""
    return not (stamp_ns // (MU_S * _NS)) % 2


def tracked_rows(stamps_ns: np.ndarray) -> np.ndarray:
    """The crawler's rows at ``stamps_ns`` (int64, shape (n,))."""
    r = TRACKED_SPEC.empty_rows(stamps_ns.shape[0])
    r["stamp_ns"] = stamps_ns
    t_s = (stamps_ns % (3600 * _NS)) / _NS
    state = np.array([crawler_state(int(t)) for t in stamps_ns], dtype=np.int32)
    carried = np.array([crawler_carried(int(t)) for t in stamps_ns])
    sigma = np.array([crawler_sigma_m(int(t)) for t in stamps_ns])
    r["motion_state"] = state
    r["state_confidence"] = 0.9
    r["speed_mps"] = r["odometer_mps"] = 5.0
    r["track_left_mps"], r["track_right_mps"] = 4.6, 5.4
    r["slip_left_pct"], r["slip_right_pct"] = -6.0, 8.0
    r["east_m"] = 5.0 * (t_s % 120.0)
    r["odometer_scale"] = 0.95 + 0.04 * np.sin(r["east_m"] / 50.0)
    r["north_m"] = 20.0 * np.sin(t_s / 10.0)
    r["up_m"] = 0.0
    r["heading_rad"] = np.pi / 2
    r["east_std_m"] = r["north_std_m"] = sigma
    r["gyro_arw_deg_rt_h"], r["gyro_arw_std_deg_rt_h"] = GYRO_ARW_DEG_RT_H
    r["gnss_clock_offset_s"], r["gnss_clock_offset_std_s"] = GNSS_CLOCK_S
    r["pitch_rad"], r["roll_rad"] = PITCH_RAD, crawler_roll_rad(t_s)
    r["pitch_std_rad"] = r["roll_std_rad"] = ATTITUDE_STD_RAD
    flags = TrackedFlag.SLIP_LEFT_VALID | TrackedFlag.SLIP_RIGHT_VALID
    bits = np.where(
        carried, int(flags | TrackedFlag.DEAD_RECKONING), int(flags | TrackedFlag.GNSS_OK)
    )
    bits = bits | np.where(state % 3 == 2, int(TrackedFlag.STATE_UNCERTAIN), 0)
    r["flags"] = bits.astype(np.int32)
    return r


def friction_rows(stamps_ns: np.ndarray) -> np.ndarray:
    """The steered vehicle's rows at ``stamps_ns`` (int64, shape (n,))."""
    r = FRICTION_SPEC.empty_rows(stamps_ns.shape[0])
    r["stamp_ns"] = stamps_ns
    informed = np.array([mu_informed(int(t)) for t in stamps_ns])
    r["mu"] = 0.8
    r["mu_std"] = np.where(informed, 0.02, 0.15)
    r["mu_filter"] = np.where(informed, 0.8, 0.65)
    r["vx_mps"] = 12.0
    r["vy_mps"] = 0.1
    t_s = (stamps_ns % (3600 * _NS)) / _NS
    r["east_m"] = -300.0 + 12.0 * (t_s % 50.0)  # a farm track, south of the crawler's field
    r["north_m"] = -200.0
    r["up_m"] = 0.0
    r["heading_rad"] = 0.0
    for key in WHEEL_KEYS:
        r[f"util_{key}_pct"] = GRIP_PCT[key]
        r[f"slip_{key}_pct"] = 2.0
        r[f"fz_{key}_n"] = 4000.0
    r["flags"] = np.where(informed, int(FrictionFlag.INFORMED), int(FrictionFlag.HELD))
    return r


class CrawlerFeed:
    """Both vehicles' rows into ``sinks`` (each with ``on_estimates``) every 50 ms on a thread
    until :meth:`stop`; :meth:`backfill` first pushes the last ``seconds`` at 20 Hz, as the
    pipeline would after a start."""

    def __init__(self, sinks: Sequence[Any]) -> None:
        self.sinks = list(sinks)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="crawler-feed", daemon=True)

    def push(self, stamps_ns: np.ndarray) -> None:
        crawler = EstimateBatch.of([(CRAWLER, tracked_rows(stamps_ns))], TRACKED_SPEC)
        steered = EstimateBatch.of([(STEERED, friction_rows(stamps_ns))], FRICTION_SPEC)
        for sink in self.sinks:
            sink.on_estimates(crawler)
            sink.on_estimates(steered)

    def backfill(self, seconds: float) -> None:
        now = time.time_ns()
        self.push(np.arange(now - int(seconds * _NS), now, _NS // 20, dtype=np.int64))

    def start(self) -> CrawlerFeed:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)

    def _run(self) -> None:
        while not self._stop.wait(0.05):
            self.push(np.array([time.time_ns()], dtype=np.int64))
