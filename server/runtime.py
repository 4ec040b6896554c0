"""Every long-lived resource of one server process, opened and closed in order.

``Runtime.open`` builds, in this order: the store (migrated), the batching writer, the live hub
and alert engine, the Zenoh session, the estimator registry and pipeline (fed with every stored
vehicle), the counter flusher and the 3D viewer. ``close`` undoes it in reverse, so the pipeline
hands its last rows to the writer before the writer flushes and the store closes.

The app factory (:func:`server.api.app.create_app`) calls ``open``/``close`` from its lifespan;
the API reads ``store``, ``live_hub``, ``alert_engine``, ``metrics()`` and ``vehicle_events``
(this runtime: the vehicle events below).
"""

from __future__ import annotations

import functools
import json
import logging
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from typing import TYPE_CHECKING, Any

import zenoh

from estimator.config import (
    ConfigError,
    VehicleConfig,
    WheeledRearDriveConfig,
    vehicle_config_from_dict,
)
from estimator.geo import EnuFrame
from server.analytics.alerts import AlertEngine, AlertKind
from server.estimation.calibration import stored_calibrations
from server.estimation.registry import (
    RESET_CALIBRATION,
    EstimatorRegistry,
    UnknownEstimatorError,
    estimator_names_for,
)
from server.ingest.counters import PLAIN_COUNTERS
from server.ingest.pipeline import PHASES, EstimateSink, Pipeline
from server.ingest.subscriber import RawPacket
from server.ingest.workers import WorkerPool
from server.ingest.zenoh_session import open_session
from server.live.hub import LiveHub
from server.metrics.latency import LatencyProbe
from server.metrics.prometheus import MetricFamily, Sample
from server.metrics.thread_cpu import thread_cpu_seconds
from server.settings import Settings
from server.storage import open_store
from server.storage.base import Store
from server.storage.writer import StoreWriter, WriterStats

__all__ = ["Runtime"]

log = logging.getLogger(__name__)

#: How often per-vehicle ingest counters are handed to the writer (and health is checked).
COUNTER_FLUSH_S = 1.0

#: Key chunk under which server-wide alerts are published: ``<prefix>/_server/alerts``.
SERVER_ALERTS_CHUNK = "_server"

#: Health parts whose failure opens a server-wide alert.
_SYSTEM_ALERTS = {"storage": AlertKind.STORAGE_DOWN, "zenoh": AlertKind.ZENOH_DOWN}

if TYPE_CHECKING:
    from server.live.viewer.fleet_view import FleetViewer  # viser: imported when enabled


class Runtime:
    """The server's resources. Not thread-safe to open/close concurrently; everything else is."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self._store: Store | None = None
        self.writer: StoreWriter | None = None
        self.live_hub: LiveHub | None = None
        self.alert_engine: AlertEngine | None = None
        self.session: zenoh.Session | None = None
        self.registry: EstimatorRegistry | None = None
        self.pipeline: Pipeline | WorkerPool | None = None
        self.viewer: FleetViewer | None = None
        self._configs: dict[str, VehicleConfig] = {}
        self._stop = threading.Event()
        self._flusher: threading.Thread | None = None
        self._fleet_frame: EnuFrame | None = None
        #: sensor-time → live feed / stored latency histograms (``server.metrics.latency``)
        self.latency = LatencyProbe()

    # ------------------------------------------------------------------ lifecycle
    @property
    def store(self) -> Store:
        if self._store is None:
            raise RuntimeError("runtime is not open")
        return self._store

    def _registry_factory(self) -> Callable[[], EstimatorRegistry]:
        """A registry factory whose vehicles start from their newest stored calibrations
        (restored, not relearnt); picklable, for worker processes."""
        return functools.partial(EstimatorRegistry, calibrations=stored_calibrations(self.store))

    def open(self) -> None:
        s = self.settings
        self._store = open_store(s.storage)
        self.writer = StoreWriter(self.latency.wrap_store(self._store), s.storage).start()
        self.live_hub = LiveHub(primary_of=self._primary_estimator)
        self.alert_engine = AlertEngine(
            slip_config_for=lambda vid: self._config_of(vid).slip,
            publish=self._publish_alert,
            rule_limits=s.alerts.engine_limits(),
        )
        self.session = open_session(s.zenoh)
        registry_factory = self._registry_factory()
        self.registry = registry_factory()
        self.pipeline = self._new_pipeline(
            self.session,
            self.registry,
            registry_factory,
            [self.writer, self.live_hub, self.alert_engine, self.latency],
            self.writer.submit_raw_packets if s.storage.store_raw_packets else None,
        )
        self._restore_vehicles(self._store, self.pipeline)
        self.pipeline.start()
        self.alert_engine.start()
        self._stop.clear()
        self._flusher = threading.Thread(
            target=self._flush_loop, name="slipfleet-counters", daemon=True
        )
        self._flusher.start()
        if s.viewer.enabled:
            self._start_viewer(self.live_hub)
        log.info(
            "runtime open: %s storage, zenoh %s, %d stored vehicles",
            self._store.dialect,
            "client of " + ",".join(s.zenoh.connect)
            if s.zenoh.connect
            else "router on " + ",".join(s.zenoh.listen),
            len(self._configs),
        )

    def _new_pipeline(
        self,
        session: zenoh.Session,
        registry: EstimatorRegistry,
        registry_factory: Callable[[], EstimatorRegistry],
        sinks: list[EstimateSink],
        raw_sink: Callable[[list[RawPacket]], object] | None,
    ) -> Pipeline | WorkerPool:
        """The ingest pipeline: a pool of worker processes when settings ask for workers,
        else one pipeline thread on ``registry``."""
        s = self.settings
        if s.ingest.workers:
            return WorkerPool(
                s,
                session,
                sinks,
                self._on_new_vehicle,
                raw_sink=raw_sink,
                registry_factory=registry_factory,
                restart_registry_factory=self._registry_factory,
            )
        return Pipeline(
            s,
            session,
            registry,
            sinks=sinks,
            on_new_vehicle=self._on_new_vehicle,
            raw_sink=raw_sink,
        )

    def _restore_vehicles(self, store: Store, pipeline: Pipeline | WorkerPool) -> None:
        """Register every stored vehicle with its config, life counters and ENU anchor."""
        anchors = store.get_anchors()
        for rec in store.list_vehicles():
            try:
                config = vehicle_config_from_dict(rec.config)
            except ConfigError as exc:
                log.error(
                    "stored config of %s is invalid (%s); using defaults", rec.vehicle_id, exc
                )
                config = WheeledRearDriveConfig()
            self._configs[rec.vehicle_id] = config
            pipeline.register_vehicle(rec.vehicle_id, config)
            # counters are totals over the vehicle's life, not per process
            pipeline.restore_counters(rec.vehicle_id, store.get_counters(rec.vehicle_id))
            # its stored estimates' ENU frame: east/north go on in the same frame
            if rec.vehicle_id in anchors:
                pipeline.restore_anchor(rec.vehicle_id, anchors[rec.vehicle_id])

    def _start_viewer(self, live_hub: LiveHub) -> None:
        """Start the 3D fleet viewer on the live hub (imported only when enabled)."""
        from server.live.viewer.fleet_view import FleetViewer

        self.viewer = FleetViewer(
            live_hub, self.settings.viewer, origin_offset_m=self._origin_offset_m
        )
        self.viewer.start()

    def close(self) -> None:
        if self.viewer is not None:
            self.viewer.stop()
            self.viewer = None
        self._stop.set()
        if self._flusher is not None:
            self._flusher.join(5.0)
            self._flusher = None
        if self.alert_engine is not None:
            self.alert_engine.stop()
        if self.pipeline is not None:
            self.pipeline.stop()
            if self.writer is not None:
                self.writer.submit_counters(self.pipeline.restorable_counters())
                self.writer.submit_anchors(self.pipeline.anchors_snapshot())
        if self.writer is not None:
            self.writer.close()
        if self.session is not None:
            self.session.close()
            self.session = None
        if self._store is not None:
            self._store.close()
        log.info("runtime closed")

    # ------------------------------------------------------------------ vehicles
    def _config_of(self, vehicle_id: str) -> VehicleConfig:
        return self._configs.get(vehicle_id) or WheeledRearDriveConfig()

    def _primary_estimator(self, vehicle_id: str) -> str | None:
        """The vehicle's primary estimator (first of its config's), None if it runs none."""
        return next(iter(estimator_names_for(self._config_of(vehicle_id))), None)

    def _on_new_vehicle(self, vehicle_id: str, config: VehicleConfig) -> None:
        """Pipeline thread: a vehicle registered itself (auto or Zenoh config); store it."""
        self._configs[vehicle_id] = config
        if self.alert_engine is not None:
            self.alert_engine.set_slip_config(vehicle_id, config.slip)
        if self.writer is not None:
            # through the writer: stored before the vehicle's first rows are written
            self.writer.submit_vehicle(vehicle_id, config.to_dict(), time.time_ns())

    @property
    def vehicle_events(self) -> Runtime:
        """The API's listener of vehicle changes (:class:`server.api.deps.VehicleEvents`): this
        runtime, whose ``check_vehicle_config`` … ``on_vehicle_deleted`` follow."""
        return self

    def check_vehicle_config(self, vehicle_id: str, config: VehicleConfig) -> None:
        """Vehicle event: refuse configs naming estimators this server does not have."""
        registry = self.registry or EstimatorRegistry()
        try:
            registry.names_for(config)
        except UnknownEstimatorError as exc:
            raise ConfigError(str(exc)) from exc

    def on_vehicle_config(self, vehicle_id: str, config: VehicleConfig) -> None:
        """Vehicle event: a config was stored; the estimators pick it up."""
        self._configs[vehicle_id] = config
        if self.pipeline is not None:
            self.pipeline.register_vehicle(vehicle_id, config)
        if self.alert_engine is not None:
            self.alert_engine.set_slip_config(vehicle_id, config.slip)

    def on_estimator_command(self, vehicle_id: str, estimator: str, key: str, on: bool) -> None:
        """Vehicle event: an operator turned an estimator's command on or off for a vehicle."""
        if self.pipeline is not None:
            self.pipeline.send_command(vehicle_id, estimator, key, on)

    def on_calibration_reset(self, vehicle_id: str, estimator: str) -> None:
        """Vehicle event: an operator reset a vehicle's calibration in one of its estimators."""
        if self.pipeline is not None:
            self.pipeline.send_command(vehicle_id, estimator, RESET_CALIBRATION, True)

    def on_vehicle_deleted(self, vehicle_id: str) -> None:
        """Vehicle event: the store deleted the vehicle; forget it everywhere."""
        self._configs.pop(vehicle_id, None)
        if self.writer is not None:
            self.writer.forget_vehicle(vehicle_id)
        if self.pipeline is not None:
            self.pipeline.remove_vehicle(vehicle_id)
        if self.live_hub is not None:
            self.live_hub.forget(vehicle_id)
        if self.alert_engine is not None:
            self.alert_engine.forget(vehicle_id)

    def _origin_offset_m(self, vehicle_id: str) -> tuple[float, float, float] | None:
        """Where a vehicle's local ENU frame sits in the fleet's frame (the 3D view's), or None
        until its first GNSS fix. The fleet frame is anchored at the first anchor seen."""
        anchor = self.pipeline.anchors_snapshot().get(vehicle_id) if self.pipeline else None
        if anchor is None:
            return None
        if self._fleet_frame is None:
            self._fleet_frame = EnuFrame(*anchor)
        e, n, u = self._fleet_frame.to_enu(*anchor)
        return (float(e), float(n), float(u))

    # ------------------------------------------------------------------ background
    def _flush_loop(self) -> None:
        """Once a second: hand the ingest counters and new ENU anchors to the writer and raise
        or clear the server-wide alerts (database down or full, no Zenoh router)."""
        while not self._stop.wait(COUNTER_FLUSH_S):
            if self.pipeline is not None and self.writer is not None:
                self.writer.submit_counters(self.pipeline.restorable_counters())
                self.writer.submit_anchors(self.pipeline.anchors_snapshot())
            if self.alert_engine is not None:
                health = self.health()
                for part, kind in _SYSTEM_ALERTS.items():
                    self.alert_engine.set_system_condition(kind, not health.get(part, True))

    def _publish_alert(self, vehicle_id: str, event: dict[str, Any]) -> None:
        if self.session is None:
            return
        owner = vehicle_id or SERVER_ALERTS_CHUNK  # server-wide alerts have no vehicle
        # A plain put, no publisher declared per vehicle: each publisher a client session
        # declares makes every sample it receives cost more (eclipse-zenoh 1.10.2, a client
        # session receiving 10,000 samples/s from a router: 3.4 µs a sample with no publishers
        # declared, 17 µs with 100, 59 µs with 600). A server connected to a router with the
        # alerts of 600 vehicles declared spent 0.8 cores in Zenoh's receive thread at 600
        # vehicles; alerts are rare, a declared publisher saves them nothing that counts.
        self.session.put(f"{self.settings.zenoh.key_prefix}/{owner}/alerts", json.dumps(event))

    # ------------------------------------------------------------------ health and metrics
    def health(self) -> Mapping[str, bool]:
        storage_ok = False
        if self._store is not None and self.writer is not None:
            try:
                storage_ok = self._store.ping() and self.writer.stats().healthy
            except Exception:
                storage_ok = False
        zenoh_ok = self.session is not None and not self.session.is_closed()
        if zenoh_ok and self.session is not None and self.settings.zenoh.connect:
            # a client session stays open while its router is away: ask for a live router
            zenoh_ok = any(True for _ in self.session.info.routers_zid())
        pipeline_ok = self.pipeline is not None and bool(self.pipeline.stats()["running"])
        return {"zenoh": zenoh_ok, "storage": storage_ok, "pipeline": pipeline_ok}

    def viewer_port(self) -> int | None:
        """The running 3D view's port; None when it is off or not running."""
        if self.viewer is None or self.viewer.server is None:
            return None
        return self.viewer.port

    def metrics(self, by_vehicle: bool = True) -> Iterable[MetricFamily]:
        """Metric families for ``/metrics``; ``by_vehicle=False`` sums the per-vehicle counters
        to fleet totals (one sample per counter instead of one per vehicle)."""
        families: list[MetricFamily] = []
        if self.pipeline is not None:
            families.extend(_ingest_families(self.pipeline.counters_snapshot(), by_vehicle))
            families.append(
                _estimator_family(self.pipeline.estimator_counters_snapshot(), by_vehicle)
            )
            families.extend(_pipeline_families(self.pipeline.stats()))
        if self.writer is not None:
            families.extend(_writer_families(self.writer.stats()))
        families.extend(self.latency.families())
        families.append(self._thread_cpu_family())
        if self.alert_engine is not None:
            families.append(
                MetricFamily(
                    "slipfleet_alerts_open",
                    "gauge",
                    "Open alerts.",
                    [Sample(float(self.alert_engine.open_count()))],
                )
            )
        return families

    def _thread_cpu_family(self) -> MetricFamily:
        """CPU seconds by thread of the server process and of each ingest worker."""
        per_process = {"server": thread_cpu_seconds()}
        if isinstance(self.pipeline, WorkerPool):
            per_process.update(self.pipeline.thread_cpu_snapshot())
        return MetricFamily(
            "slipfleet_thread_cpu_seconds",
            "counter",
            "CPU seconds (user + system) of the live threads of the server and its ingest "
            "workers, by thread name.",
            [
                Sample(seconds, {"process": process, "thread": thread}, "_total")
                for process, threads in per_process.items()
                for thread, seconds in sorted(threads.items())
            ],
        )


def _fleet_totals(per_vehicle: Mapping[str, Mapping[str, int]]) -> dict[str, dict[str, int]]:
    """``{"": {counter: sum over the vehicles}}``: the fleet as one unlabelled vehicle."""
    totals: dict[str, int] = {}
    for counts in per_vehicle.values():
        for name, n in counts.items():
            totals[name] = totals.get(name, 0) + int(n)
    return {"": totals}


def _vehicle_label(vehicle_id: str, by_vehicle: bool) -> dict[str, str]:
    return {"vehicle": vehicle_id} if by_vehicle else {}


def _estimator_family(
    counters: Mapping[str, Mapping[str, Mapping[str, int]]], by_vehicle: bool = True
) -> MetricFamily:
    """Estimator events per vehicle (MDSF: resets, gnss_gated, degraded_ticks, skipped_*, …),
    or their fleet totals."""
    samples = [
        Sample(
            float(n),
            {"estimator": name, **_vehicle_label(vid, by_vehicle), "event": event},
            "_total",
        )
        for name, per_vehicle in sorted(counters.items())
        for vid, events in sorted(
            (per_vehicle if by_vehicle else _fleet_totals(per_vehicle)).items()
        )
        for event, n in sorted(events.items())
    ]
    return MetricFamily(
        "slipfleet_estimator_events",
        "counter",
        "Estimator events per vehicle: filter resets, gated GNSS, degraded ticks, skipped input.",
        samples,
    )


_INGEST_HELP = {
    "wheel_gaps": "Times the estimators went on past a vehicle's wheel data (a wheel packet "
    "lost or late, the encoder silent): its wheel fits started afresh.",
    "estimator_errors": "Estimator calls that raised for a vehicle (its rows of that call lost).",
    "configs_refused": "Vehicle configs an estimator refused (the old config kept).",
}


def _ingest_families(
    counters: Mapping[str, Mapping[str, int]], by_vehicle: bool = True
) -> list[MetricFamily]:
    """Per-vehicle ingest counters (or their fleet totals) as Prometheus families (rejections
    labelled by reason)."""
    plain = PLAIN_COUNTERS
    samples: dict[str, list[Sample]] = {name: [] for name in plain}
    rejected: list[Sample] = []
    for vehicle_id, counts in sorted((counters if by_vehicle else _fleet_totals(counters)).items()):
        label = _vehicle_label(vehicle_id, by_vehicle)
        for name in plain:
            samples[name].append(Sample(float(counts.get(name, 0)), label, "_total"))
        for key, value in counts.items():
            if key.startswith("rejected_"):
                rejected.append(
                    Sample(
                        float(value),
                        {**label, "reason": key.removeprefix("rejected_")},
                        "_total",
                    )
                )
    families = [
        MetricFamily(
            f"slipfleet_packets_{name}",
            "counter",
            _INGEST_HELP.get(name, f"Sensor packets {name.replace('_', ' ')}."),
            samples[name],
        )
        for name in plain
    ]
    families.append(
        MetricFamily(
            "slipfleet_packets_rejected", "counter", "Sensor packets rejected, by reason.", rejected
        )
    )
    return families


def _pipeline_families(stats: Mapping[str, Any]) -> list[MetricFamily]:
    """The pipeline's rows produced, queued bursts, last tick and CPU by phase."""
    cpu = [
        Sample(float(stats.get(f"cpu_{phase}_s", 0.0)), {"phase": phase}, "_total")
        for phase in PHASES
    ]
    return [
        MetricFamily(
            "slipfleet_estimate_rows",
            "counter",
            "Estimate rows produced by the pipeline.",
            [Sample(float(stats["rows"]), suffix="_total")],
        ),
        MetricFamily(
            "slipfleet_pipeline_queue_bursts",
            "gauge",
            "Decoded bursts waiting for the pipeline thread.",
            [Sample(float(stats["queue_bursts"]))],
        ),
        MetricFamily(
            "slipfleet_pipeline_tick_seconds",
            "gauge",
            "Duration of the pipeline's last processing tick.",
            [Sample(float(stats["last_tick_ms"]) / 1000.0)],
        ),
        MetricFamily(
            "slipfleet_pipeline_cpu_seconds",
            "counter",
            "CPU seconds of the pipeline thread (every ingest worker's, added up) by "
            "phase: decode, reorder, release, estimate, deliver.",
            cpu,
        ),
    ]


#: The writer's counters: (``WriterStats`` field, help).
_WRITER_COUNTERS = (
    ("rows_written", "Estimate rows inserted."),
    ("rows_dropped_backlog_full", "Rows refused: backlog full."),
    ("rows_ignored", "Rows the store did not insert: stored already, or of an unknown vehicle."),
    ("rows_dropped_error", "Rows refused by the store."),
    ("transactions", "Committed estimate transactions."),
    ("vehicles_stored", "Vehicles the pipeline registered, stored."),
    ("vehicles_dropped_error", "Vehicle registrations refused by the store."),
)


def _writer_families(w: WriterStats) -> list[MetricFamily]:
    """The batching writer's counters and its backlog."""
    families = [
        MetricFamily(
            f"slipfleet_writer_{name}",
            "counter",
            help_,
            [Sample(float(getattr(w, name)), suffix="_total")],
        )
        for name, help_ in _WRITER_COUNTERS
    ]
    families.append(
        MetricFamily(
            "slipfleet_writer_backlog_rows",
            "gauge",
            "Rows waiting to be written.",
            [Sample(float(w.backlog_rows))],
        )
    )
    return families
