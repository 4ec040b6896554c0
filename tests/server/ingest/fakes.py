"""Ingest test doubles: recording FleetEstimators (of any spec, optionally failing for some
vehicles), a capturing sink, loopback Zenoh sessions."""

from __future__ import annotations

import contextlib
import json
import threading
from collections.abc import Iterator, Mapping

import numpy as np
import zenoh

from estimator.base import Measurement, Pushed
from estimator.config import VehicleConfig
from estimator.mdsf_spec import MDSF_SPEC
from estimator.reference_speed_spec import REFERENCE_SPEED_SPEC
from estimator.spec import EstimatorSpec
from estimator.types import EstimateBatch, GnssSample
from server.estimation import DEFAULT_FACTORIES, EstimatorRegistry
from server.ingest.zenoh_session import open_session
from server.settings import ZenohSettings
from tests.support import free_port


class InjectedFaultError(RuntimeError):
    """What a failing :class:`RecordingFleet` raises."""


class RecordingFleet:
    """A FleetEstimator of ``spec`` that records every push and emits one row per advanced
    vehicle (``stamp_ns`` = the time advanced to, ``rows_emitted`` counts them). For the
    vehicles in ``fail_for`` it raises :class:`InjectedFaultError` on every push and on every
    advance that includes them (before touching any vehicle); it refuses (raises on) every
    config whose slip alert threshold is ``refuse_threshold_pct``."""

    def __init__(
        self,
        spec: EstimatorSpec = MDSF_SPEC,
        fail_for: frozenset[str] = frozenset(),
        refuse_threshold_pct: float | None = None,
    ) -> None:
        self.spec = spec
        self.name = spec.name
        self.fail_for = fail_for
        self.refuse_threshold_pct = refuse_threshold_pct
        self.rows_emitted: dict[str, int] = {}
        self.vehicles: dict[str, VehicleConfig] = {}
        self.pushed: dict[str, list[Measurement]] = {}
        self.until: dict[str, int] = {}
        self.advances: list[dict[str, int]] = []
        self.aligned: dict[str, int] = {}

    def add_vehicle(self, vehicle_id: str, config: VehicleConfig) -> None:
        if config.slip.alert_threshold_pct == self.refuse_threshold_pct:
            raise InjectedFaultError(f"config of {vehicle_id}")
        self.vehicles[vehicle_id] = config
        self.pushed.setdefault(vehicle_id, [])

    def remove_vehicle(self, vehicle_id: str) -> None:
        self.vehicles.pop(vehicle_id, None)

    def vehicle_ids(self) -> list[str]:
        return list(self.vehicles)

    def push(self, vehicle_id: str, measurement: Pushed) -> None:
        if vehicle_id not in self.vehicles:
            raise KeyError(vehicle_id)
        if vehicle_id in self.fail_for:
            raise InjectedFaultError(f"push {vehicle_id}")
        self.pushed[vehicle_id].append(measurement)

    def align_ticks(self, vehicle_id: str, stamp_ns: int) -> None:
        if vehicle_id not in self.vehicles:
            raise KeyError(vehicle_id)
        self.aligned[vehicle_id] = stamp_ns

    def advance(self, until_ns: Mapping[str, int]) -> list[tuple[str, np.ndarray]]:
        if self.fail_for & until_ns.keys():
            raise InjectedFaultError(f"advance {sorted(self.fail_for & until_ns.keys())}")
        out = []
        self.advances.append(dict(until_ns))
        for vid, t in until_ns.items():
            assert t >= self.until.get(vid, t), "advance went back in time"
            self.until[vid] = t
            row = self.spec.empty_rows(1)
            row["stamp_ns"] = t
            out.append((vid, row))
            self.rows_emitted[vid] = self.rows_emitted.get(vid, 0) + 1
        return out


#: The vehicle whose second estimator fails in :func:`mixed_registry`.
FAILING_VEHICLE = "w001"


def mixed_registry() -> EstimatorRegistry:
    """The real MDSF plus a reference-speed estimator (a :class:`RecordingFleet` of its spec)
    that fails for :data:`FAILING_VEHICLE`: what a worker process builds in the mixed-fleet
    tests (module level, so it can be handed to spawned workers)."""
    return EstimatorRegistry(
        factories={
            **DEFAULT_FACTORIES,
            "reference_speed": lambda: RecordingFleet(
                REFERENCE_SPEED_SPEC, frozenset({FAILING_VEHICLE})
            ),
        }
    )


def first_stamp(m: Measurement) -> int:
    return m.stamp_ns if isinstance(m, GnssSample) else int(m.stamp_ns[0])


class CapturingSink:
    """Collects every batch handed to ``on_estimates``: ``rows`` by vehicle (MDSF's, what most
    tests run), ``by_estimator`` by estimator and vehicle (every estimator's)."""

    def __init__(self) -> None:
        self.rows: dict[str, list[np.ndarray]] = {}
        self.by_estimator: dict[str, dict[str, list[np.ndarray]]] = {}
        self.lock = threading.Lock()

    def on_estimates(self, batch: EstimateBatch) -> None:
        assert isinstance(batch, EstimateBatch) and batch.rows.dtype == batch.spec.dtype
        with self.lock:
            mine = self.by_estimator.setdefault(batch.estimator, {})
            for vid, rows in batch:
                mine.setdefault(vid, []).append(rows)
                if batch.estimator == "mdsf":
                    self.rows.setdefault(vid, []).append(rows)


@contextlib.contextmanager
def embedded_router(**overrides: object) -> Iterator[tuple[zenoh.Session, ZenohSettings, str]]:
    """Open the server's embedded router on a free loopback port (retrying if the port is taken)."""
    last: Exception | None = None
    for _ in range(5):
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        settings = ZenohSettings.model_validate({"listen": [endpoint], **overrides})
        try:
            session = open_session(settings)
        except zenoh.ZError as exc:  # lost the port to another process: try another
            last = exc
            continue
        try:
            yield session, settings, endpoint
        finally:
            session.close()
        return
    raise RuntimeError(f"could not open an embedded router: {last}")


@contextlib.contextmanager
def client_session(endpoint: str) -> Iterator[zenoh.Session]:
    """A vehicle-side client session connected to ``endpoint``."""
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps("client"))
    config.insert_json5("connect/endpoints", json.dumps([endpoint]))
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("transport/shared_memory/enabled", "false")
    session = zenoh.open(config)
    try:
        yield session
    finally:
        session.close()
