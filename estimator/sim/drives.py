"""Random drives: the ``random_drive`` scenario with every condition drawn over a stated range.

A field user's drives are not the named scenarios; an estimator judged only on those can be tuned
to them. :func:`draw_drives` draws ``n`` drives from one seed (drive ``i`` from
``SeedSequence([seed, i])``, so a drive does not depend on ``n``). Per drive, independently:

============================  ===========================================================
knob                          distribution
============================  ===========================================================
speeds                        creeping (p = 0.25): 0.2-0.8 m/s; else 1.0 m/s to U(2.0, 4.5)
duration                      150 s, from rest to rest, stops with p = 0.15 a leg
turn rate max                 U(0.05, 0.35) rad/s (at most 0.55·V)
encoder ring                  one of 20, 30, 48, 60, 90, 120 teeth
IMU height h0, mast h1        U(0.8, 1.6) m, U(1.0, 3.5) m
IMU, antenna offsets (x, y)   U(−0.3, 0.3) m, U(−0.5, 0.5) m per axis
body sway                     p = 0.5: f ~ U(0.3, 3) Hz, pitch and roll amplitudes
                              U(0, 5)° / max(1, f/1 Hz) each (rates up to ≈ 0.55 rad/s)
slip steps                    0-3 at U(15, 135) s: ±U(2, 10) pp (cumulative within
                              −5..+20 pp), a jump (p = 1/3) or a ramp of U(0.5, 5) s
GNSS outage                   p = 0.4: length log-uniform 10-120 s (at most 110), start
                              U(10, 140 − length) s
GNSS velocity outliers        probability U(0, 0.02) an epoch, size U(0.2, 1.0) m/s (1σ)
GNSS epochs                   on whole tenths (p = 0.5) or phase U(0, 100) ms; jitter
                              U(0, 20) ms
receiver attitude             none (one antenna) with p = 0.3
clock offsets                 GNSS and wheels against the IMU: U(−100, 100) ms each
tyre radius                   true = configured × (1 + U(−3, 3) %) per wheel
IMU misalignment              yaw and pitch U(−3, 3)° each
soil, drawbar, heading        μ U(0.45, 0.8), drawbar U(0, 0.12), heading U(0, 360)°
============================  ===========================================================

Pure: numpy only, no I/O, no clock.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from estimator.config import EncoderConfig, VehicleGeometry, WheeledRearDriveConfig

__all__ = ["DrawnDrive", "draw_drive", "draw_drives"]

_TEETH = (20, 30, 48, 60, 90, 120)
_DURATION_S = 150.0


@dataclass(frozen=True, slots=True)
class DrawnDrive:
    """One drawn drive: what :func:`estimator.sim.simulate` and the vehicle config need.

    Attributes
    ----------
    index : int
        Its place in the draw.
    sim_seed : int
        Seed of the simulation (wobbles, slip texture, sensor noise).
    overrides : Mapping[str, Any]
        Keyword overrides of ``simulate("random_drive", ...)``.
    geometry : Mapping[str, Any]
        :class:`~estimator.config.VehicleGeometry` fields.
    teeth_per_rev : int
    """

    index: int
    sim_seed: int
    overrides: Mapping[str, Any]
    geometry: Mapping[str, Any]
    teeth_per_rev: int

    def config(self) -> WheeledRearDriveConfig:
        """The vehicle as configured (nominal radii: the true ones are off by the drawn error)."""
        return WheeledRearDriveConfig(
            geometry=VehicleGeometry(**dict(self.geometry)),
            encoder=EncoderConfig(teeth_per_rev=self.teeth_per_rev),
        )

    def knobs(self) -> dict[str, Any]:
        """Every drawn value in one flat mapping (for tables and JSON)."""
        return {**self.overrides, **self.geometry, "teeth_per_rev": self.teeth_per_rev}


def _slip_steps(rng: np.random.Generator) -> tuple[tuple[float, float, float], ...]:
    steps = []
    level = 0.0
    for t in np.sort(rng.uniform(15.0, _DURATION_S - 15.0, int(rng.integers(0, 4)))):
        size = rng.uniform(2.0, 10.0)
        delta = size if rng.random() < 0.5 else -size
        delta = float(np.clip(level + delta, -5.0, 20.0) - level)
        level += delta
        ramp = 0.0 if rng.random() < 1 / 3 else rng.uniform(0.5, 5.0)
        steps.append((round(float(t), 2), round(delta, 3), round(float(ramp), 2)))
    return tuple(steps)


def _outages(rng: np.random.Generator) -> tuple[tuple[float, float], ...]:
    if rng.random() >= 0.4:
        return ()
    length = min(math.exp(rng.uniform(math.log(10.0), math.log(120.0))), 110.0)
    start = rng.uniform(10.0, _DURATION_S - 10.0 - length)
    return ((round(start, 2), round(start + length, 2)),)


def _motion(rng: np.random.Generator) -> dict[str, Any]:
    creep = rng.random() < 0.25
    sway = rng.random() < 0.5
    f = float(rng.uniform(0.3, 3.0))
    amp = 5.0 / max(1.0, f)
    return {
        "duration_s": _DURATION_S,
        "speed_min_mps": 0.2 if creep else 1.0,
        "speed_max_mps": 0.8 if creep else round(float(rng.uniform(2.0, 4.5)), 3),
        "turn_rate_max_radps": round(float(rng.uniform(0.05, 0.35)), 3),
        "sway_hz": round(f, 3),
        "sway_pitch_deg": round(float(rng.uniform(0.0, amp)), 3) if sway else 0.0,
        "sway_roll_deg": round(float(rng.uniform(0.0, amp)), 3) if sway else 0.0,
        "slip_steps": _slip_steps(rng),
        "mu_soil": round(float(rng.uniform(0.45, 0.8)), 3),
        "drawbar": round(float(rng.uniform(0.0, 0.12)), 3),
        "heading0_deg": round(float(rng.uniform(0.0, 360.0)), 1),
    }


def _sensors(rng: np.random.Generator) -> dict[str, Any]:
    def u(lo: float, hi: float, digits: int = 3) -> float:
        return round(float(rng.uniform(lo, hi)), digits)

    return {
        "gnss_outages": _outages(rng),
        "gnss_outlier_prob": u(0.0, 0.02, 4),
        "gnss_outlier_mps": u(0.2, 1.0),
        "gnss_epoch_phase_ms": 0.0 if rng.random() < 0.5 else u(0.0, 100.0, 1),
        "gnss_epoch_jitter_ms": u(0.0, 20.0, 1),
        "gnss_attitude": bool(rng.random() >= 0.3),
        "clock_offset_ms": (u(-100.0, 100.0, 1), 0.0, u(-100.0, 100.0, 1)),
        "wheel_radius_error_rel": (u(-0.03, 0.03, 4), u(-0.03, 0.03, 4)),
        "imu_misalign_deg": (u(-3.0, 3.0, 2), u(-3.0, 3.0, 2)),
    }


def _geometry(rng: np.random.Generator) -> dict[str, Any]:
    def u(lo: float, hi: float) -> float:
        return round(float(rng.uniform(lo, hi)), 3)

    return {
        "h0_m": u(0.8, 1.6),
        "h1_m": u(1.0, 3.5),
        "imu_offset_m": (u(-0.3, 0.3), u(-0.3, 0.3)),
        "antenna_offset_m": (u(-0.5, 0.5), u(-0.5, 0.5)),
    }


def draw_drive(seed: int, index: int) -> DrawnDrive:
    """Drive ``index`` of the draw ``seed`` (the module docstring's distribution)."""
    knobs_ss, sim_ss = np.random.SeedSequence([seed, index]).spawn(2)
    rng = np.random.default_rng(knobs_ss)
    overrides = {**_motion(rng), **_sensors(rng)}
    geometry = _geometry(rng)
    teeth = int(_TEETH[int(rng.integers(0, len(_TEETH)))])
    sim_seed = int(sim_ss.generate_state(1, np.uint32)[0])
    return DrawnDrive(index, sim_seed, overrides, geometry, teeth)


def draw_drives(n: int, seed: int) -> list[DrawnDrive]:
    """Drives ``0 .. n−1`` of the draw ``seed``."""
    return [draw_drive(seed, i) for i in range(n)]
