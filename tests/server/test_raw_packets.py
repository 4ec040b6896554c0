"""``storage.store_raw_packets``: every packet of a vehicle that the decoder accepted is kept as
it arrived; malformed ones are not."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
import zenoh
from fastapi import FastAPI

from server.app_main import ServerThread, build_app
from server.protocol import Stream, decode, sensor_key
from server.settings import Settings
from tests.server.redteam._stack import client_session, gnss_payload
from tests.support import free_port, run_vehicle_client


def _serve(
    tmp_path: Path, *, store_raw: bool, workers: int = 0
) -> tuple[str, FastAPI, ServerThread]:
    """The server app on a free loopback port, its Zenoh router on another, SQLite in
    ``tmp_path``: ``(zenoh endpoint, app, started server thread)``."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    settings = Settings(
        ingest={"workers": workers},
        zenoh={"listen": [endpoint]},
        storage={"data_dir": tmp_path, "commit_interval_s": 0.2, "store_raw_packets": store_raw},
        api={"port": 0, "require_auth": False},
        viewer={"enabled": False},
    )
    app = build_app(settings)
    server = ServerThread(app, "127.0.0.1", 0)
    server.start()
    return endpoint, app, server


@pytest.mark.zenoh
@pytest.mark.parametrize("store_raw", [True, False])
def test_raw_packets_are_stored_when_asked(tmp_path: Path, store_raw: bool) -> None:
    endpoint, app, server = _serve(tmp_path, store_raw=store_raw)
    try:
        t0 = time.time_ns()
        proc = run_vehicle_client(endpoint, "raw-1", 2)
        assert proc.returncode == 0, proc.stderr
        runtime = app.state.runtime
        deadline = time.monotonic() + 10
        while True:
            received = runtime.pipeline.counters_snapshot().get("raw-1", {}).get("received", 0)
            runtime.writer.flush(5)
            raw = runtime.store.query_raw_packets("raw-1", t0, time.time_ns())
            if received and (len(raw) == received or not store_raw):
                break
            assert time.monotonic() < deadline, (
                f"{len(raw)} raw packets of {received} received; {runtime.writer.stats()}"
            )
            time.sleep(0.2)
    finally:
        server.stop()
    if not store_raw:
        assert len(raw) == 0
        return
    assert len(raw) == received >= 50
    stamps = [r[0] for r in raw]
    assert stamps == sorted(stamps) and t0 <= stamps[0]
    for _, key, payload in raw:  # kept byte for byte: they decode again
        assert key.startswith("fleet/raw-1/sensors/")
        assert decode(key, payload).vehicle_id == "raw-1"


@pytest.mark.zenoh
@pytest.mark.parametrize("workers", [0, 1], ids=["pipeline", "worker"])
def test_only_packets_the_decoder_accepted_are_stored_raw(tmp_path: Path, workers: int) -> None:
    """Malformed payloads on a vehicle's sensor key (sent first) are refused by the decoder and
    never stored; the valid packets sent after them on the same link are, byte for byte (the
    decoder in the server's pipeline thread, or in a worker process)."""
    endpoint, app, server = _serve(tmp_path, store_raw=True, workers=workers)
    t0 = time.time_ns()
    key = sensor_key("fleet", "raw-2", Stream.GNSS)
    valid = [gnss_payload(t0 + k * 100_000_000, k) for k in range(20)]
    malformed = [b"", b"\x00" * 7, b"not a packet", valid[0][:-3], b"\xff" * 300]
    try:
        with client_session(endpoint) as vehicle:
            pub = vehicle.declare_publisher(
                key,
                congestion_control=zenoh.CongestionControl.BLOCK,
                reliability=zenoh.Reliability.RELIABLE,
            )
            deadline = time.monotonic() + 10
            while not getattr(pub.matching_status, "matching", False):
                assert time.monotonic() < deadline, "no subscriber"
                time.sleep(0.02)
            for payload in [*malformed, *valid]:
                pub.put(payload)
            runtime = app.state.runtime
            deadline = time.monotonic() + 10
            while True:
                runtime.writer.flush(5)
                raw = runtime.store.query_raw_packets("raw-2", t0, time.time_ns())
                if len(raw) >= len(valid):
                    break
                assert time.monotonic() < deadline, f"{len(raw)} raw packets stored"
                time.sleep(0.1)
            time.sleep(0.5)  # anything more would be stored by now
            runtime.writer.flush(5)
            raw = runtime.store.query_raw_packets("raw-2", t0, time.time_ns())
    finally:
        server.stop()
    assert [payload for _, _, payload in raw] == valid
    assert all(k == key for _, k, _ in raw)
