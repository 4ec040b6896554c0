"""Ingest test doubles: a recording FleetEstimator, a capturing sink, loopback Zenoh sessions."""

from __future__ import annotations

import contextlib
import json
import threading
from collections.abc import Iterator, Mapping

import numpy as np
import zenoh

from estimator.base import Measurement, Pushed
from estimator.config import VehicleConfig
from estimator.types import ESTIMATE_DTYPE, GnssSample, empty_estimates
from server.ingest.zenoh_session import open_session
from server.settings import ZenohSettings
from tests.support import free_port


class RecordingFleet:
    """A FleetEstimator that records every push and emits one row per advanced vehicle."""

    name = "mdsf"
    output_dtype = ESTIMATE_DTYPE

    def __init__(self) -> None:
        self.vehicles: dict[str, VehicleConfig] = {}
        self.pushed: dict[str, list[Measurement]] = {}
        self.until: dict[str, int] = {}
        self.advances: list[dict[str, int]] = []
        self.aligned: dict[str, int] = {}

    def add_vehicle(self, vehicle_id: str, config: VehicleConfig) -> None:
        self.vehicles[vehicle_id] = config
        self.pushed.setdefault(vehicle_id, [])

    def remove_vehicle(self, vehicle_id: str) -> None:
        self.vehicles.pop(vehicle_id, None)

    def vehicle_ids(self) -> list[str]:
        return list(self.vehicles)

    def push(self, vehicle_id: str, measurement: Pushed) -> None:
        if vehicle_id not in self.vehicles:
            raise KeyError(vehicle_id)
        self.pushed[vehicle_id].append(measurement)

    def align_ticks(self, vehicle_id: str, stamp_ns: int) -> None:
        if vehicle_id not in self.vehicles:
            raise KeyError(vehicle_id)
        self.aligned[vehicle_id] = stamp_ns

    def advance(self, until_ns: Mapping[str, int]) -> list[tuple[str, np.ndarray]]:
        out = []
        self.advances.append(dict(until_ns))
        for vid, t in until_ns.items():
            assert t >= self.until.get(vid, t), "advance went back in time"
            self.until[vid] = t
            row = empty_estimates(1)
            row["stamp_ns"] = t
            out.append((vid, row))
        return out


def first_stamp(m: Measurement) -> int:
    return m.stamp_ns if isinstance(m, GnssSample) else int(m.stamp_ns[0])


class CapturingSink:
    """Collects every batch handed to ``on_estimates``."""

    def __init__(self) -> None:
        self.rows: dict[str, list[np.ndarray]] = {}
        self.lock = threading.Lock()

    def on_estimates(self, batch: list[tuple[str, np.ndarray]]) -> None:
        with self.lock:
            for vid, rows in batch:
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
