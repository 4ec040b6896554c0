"""Simulated single-flow-transmission crawler: truth and raw sensor streams (``method.md`` §4).

Pure: numpy only, every draw from the seeded generator, no I/O, no clock.

>>> run = simulate_tracked("route_firm", seed=1)
>>> run.measurements[0]          # (key_ns, GnssSample | ImuBatch | OdometerEdges | SprocketEdges)
>>> run.truth.state              # MotionState per 100 Hz grid point

Named scenarios (:func:`estimator.sim.tracked.route.named_route`): ``route_firm`` and
``route_soft``, an 11-minute route with straights at 10-12 m/s, arc and separated turns both
ways, low-gear straights, pivots, a fast pivot and stops, with a 4-minute GNSS outage
covering more than 1 km. ``random``: a route drawn from
:data:`~estimator.sim.tracked.route.RANDOM_RANGES` (ground, manoeuvres, outage, gauge and
contact length, the gyro's grade, whether the config names the gyro's data sheet or the unit's
own figures) by the seed, over a terrain drawn from
:data:`~estimator.sim.tracked.terrain.TERRAIN_RANGES` (grades up to ±15 %, cross grades up to
±10 %; ``flat=True`` keeps it level). ``route_firm_hill`` is ``route_firm`` over hills.
Physics in
:mod:`~estimator.sim.tracked.physics`, sensors in :mod:`~estimator.sim.tracked.sensors`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from estimator._arrays import FloatArray, IntArray
from estimator.base import Measurement
from estimator.config import GyroConfig, TrackedConfig, TrackedGeometry
from estimator.geo import EnuFrame
from estimator.sim.tracked.physics import RATE_HZ, CrawlerTruth, integrate_route
from estimator.sim.tracked.route import (
    CLOCK_KEYS,
    CONFIG_NAMES_DATASHEET_SHARE,
    RANDOM_RANGES,
    Route,
    named_route,
    random_route,
    route_names,
)
from estimator.sim.tracked.sensors import CrawlerSensors, SensorErrors, draw_errors, emissions
from estimator.sim.tracked.terrain import FLAT, random_terrain

__all__ = [
    "CrawlerSensors",
    "CrawlerTruth",
    "Route",
    "TrackedRun",
    "simulate_route",
    "simulate_tracked",
    "tracked_scenarios",
]

START_NS = 1_700_000_000_000_000_000
ORIGIN = EnuFrame(52.0, 5.6, 10.0)


def tracked_scenarios() -> tuple[str, ...]:
    """Names :func:`simulate_tracked` takes (``random`` draws a route from the seed)."""
    return (*route_names(), "random")


@dataclass(frozen=True, slots=True)
class TrackedRun:
    """One simulated drive.

    ``measurements`` are ``(key_ns, measurement)`` sorted by key: after every packet keyed at
    or before ``T`` each stream is complete up to ``T``. ``truth`` is on the 100 Hz grid from
    ``start_ns``; ``frame`` is the ENU frame of its positions (the hull centre's);
    ``sensors`` the imperfections the sensors were drawn with.
    """

    name: str
    seed: int
    route: Route
    config: TrackedConfig
    truth: CrawlerTruth
    errors: SensorErrors
    start_ns: int
    frame: EnuFrame
    measurements: list[tuple[int, Measurement]]
    sensors: CrawlerSensors = field(default_factory=CrawlerSensors)

    @property
    def outages_ns(self) -> list[tuple[int, int]]:
        return [
            (self.start_ns + round(a * 1e9), self.start_ns + round((a + d) * 1e9))
            for a, d in self.route.outages_s
        ]

    def index_at(self, stamp_ns: IntArray) -> IntArray:
        """Truth grid index of each stamp (nearest grid point at or before it)."""
        k = (np.asarray(stamp_ns, dtype=np.int64) - self.start_ns) * RATE_HZ // 1_000_000_000
        return np.clip(k, 0, self.truth.t_s.size - 1)

    def distance_m(self) -> FloatArray:
        """Horizontal distance driven by the hull centre up to each grid point."""
        step = np.hypot(np.diff(self.truth.east_m), np.diff(self.truth.north_m))
        return np.concatenate([[0.0], np.cumsum(step)])


def _random_config(rng: np.random.Generator) -> TrackedConfig:
    geo = TrackedGeometry(
        track_gauge_m=float(rng.uniform(1.6, 3.0)), contact_length_m=float(rng.uniform(1.8, 4.0))
    )
    return TrackedConfig(geometry=geo)


def _random_sensors(seed: int) -> CrawlerSensors:
    """A random route's sensors: the gyro's grade, the receiver's up-over-horizontal
    velocity noise and the streams' clocks (each stream's offset from the IMU's, the
    receiver's epoch jitter) drawn from ``RANDOM_RANGES``, each by a generator of its own
    (the route, ground and every other draw stay those of the seed)."""
    rng = np.random.default_rng((seed, 1))
    up = np.random.default_rng((seed, 5))
    clocks = np.random.default_rng((seed, 7))
    gnss, odometer, sprocket, jitter = (
        float(clocks.uniform(*RANDOM_RANGES[k])) for k in CLOCK_KEYS
    )
    return CrawlerSensors(
        gyro_grade=float(rng.uniform(*RANDOM_RANGES["gyro_grade"])),
        gnss_up_vel_std_ratio=float(up.uniform(*RANDOM_RANGES["gnss_up_vel_std_ratio"])),
        gnss_clock_offset_s=gnss,
        odometer_clock_offset_s=odometer,
        sprocket_clock_offset_s=sprocket,
        gnss_epoch_jitter_s=jitter,
    )


def _random_config_gyro(seed: int, spec: CrawlerSensors) -> GyroConfig:
    """A random route's config gyro: with probability ``CONFIG_NAMES_DATASHEET_SHARE`` the
    data-sheet part (``spec.gyro_part``) while the unit is ``spec.gyro_grade`` times it
    (uniform over ``RANDOM_RANGES["gyro_grade"]``, so a unit 1-2x worse than its config
    says), otherwise the unit's own figures. Drawn by a generator of its own, independent of
    the grade and of every other draw of the seed."""
    rng = np.random.default_rng((seed, 2))
    names_datasheet = bool(rng.random() < CONFIG_NAMES_DATASHEET_SHARE)
    return GyroConfig.of(spec.gyro_part if names_datasheet else spec.gyro_fitted)


def simulate_tracked(
    name: str,
    seed: int,
    *,
    config: TrackedConfig | None = None,
    sensors: CrawlerSensors | None = None,
    start_ns: int = START_NS,
    flat: bool = False,
) -> TrackedRun:
    """Simulate scenario ``name`` (:func:`tracked_scenarios`) with ``seed``.

    A random route's terrain is drawn by a generator of its own (``(seed, 3)``), so its
    route, ground and every other draw are those of the seed whether it is level
    (``flat=True``, which levels a named route's hills too) or not; what the level-ground
    sensors never drew (the pitch and roll gyros' biases, the GNSS up velocity's noise)
    comes from another (``(seed, 4)``), their biases' in-run walk from a third
    (``(seed, 6)``), the receiver's epoch jitter from a fourth (``(seed, 8)``; a random
    route's clock figures are drawn by ``(seed, 7)``, :func:`_random_sensors`; a named
    route's are 0 unless ``sensors`` sets them).

    Without ``config``, a named route's config names the gyro its sensors have; a random
    route's names either the unit's own figures (the part's times its grade) or, with
    probability ``CONFIG_NAMES_DATASHEET_SHARE``, the part's data sheet while the unit is
    worse (:func:`_random_config_gyro`), as fleets' configs name the part each crawler carries.
    """
    rng = np.random.default_rng(seed)
    if name == "random":
        route = random_route(rng)
        terrain = FLAT if flat else random_terrain(np.random.default_rng((seed, 3)))
        route = replace(route, terrain=terrain)
        drawn = config or _random_config(rng)
        spec = sensors or _random_sensors(seed)
        gyro = _random_config_gyro(seed, spec)
    else:
        route = named_route(name)
        drawn = config or TrackedConfig()
        spec = sensors or CrawlerSensors()
        gyro = GyroConfig.of(spec.gyro_fitted)
    if flat:
        route = replace(route, terrain=FLAT)
    config = config or replace(drawn, gyro=gyro)
    extra = np.random.default_rng((seed, 4))
    walk = np.random.default_rng((seed, 6))
    jitter = np.random.default_rng((seed, 8))
    return simulate_route(
        route,
        seed,
        config=config,
        sensors=spec,
        start_ns=start_ns,
        rng=rng,
        extra_rng=extra,
        walk_rng=walk,
        jitter_rng=jitter,
    )


def simulate_route(
    route: Route,
    seed: int,
    *,
    config: TrackedConfig | None = None,
    sensors: CrawlerSensors | None = None,
    start_ns: int = START_NS,
    frame: EnuFrame = ORIGIN,
    rng: np.random.Generator | None = None,
    extra_rng: np.random.Generator | None = None,
    walk_rng: np.random.Generator | None = None,
    jitter_rng: np.random.Generator | None = None,
) -> TrackedRun:
    """The simulator's stages on a given ``route``: the crawler's motion, the sensors' errors,
    every packet from ``start_ns`` in ``frame``.

    ``rng`` (default: a generator seeded ``seed``) draws the motion, errors and packets in
    that order; ``extra_rng`` what the level-ground sensors never drew (without it the pitch
    and roll gyros' biases and the GNSS up velocity's noise are 0,
    :func:`~estimator.sim.tracked.sensors.emissions`), ``walk_rng`` the pitch and roll
    gyros' in-run bias walk (none without it), ``jitter_rng`` the receiver's epoch jitter
    (none without it; the streams' clock offsets are ``sensors``'). Defaults:
    :class:`TrackedConfig` and :class:`CrawlerSensors`.
    """
    rng = np.random.default_rng(seed) if rng is None else rng
    config = config or TrackedConfig()
    spec = sensors or CrawlerSensors()
    truth = integrate_route(route, config, rng)
    errors = draw_errors(rng, truth.t_s.size, spec)
    meas = emissions(
        truth,
        config,
        spec,
        errors,
        frame,
        route.outages_s,
        start_ns,
        rng,
        extra_rng,
        walk_rng,
        jitter_rng,
    )
    return TrackedRun(route.name, seed, route, config, truth, errors, start_ns, frame, meas, spec)
