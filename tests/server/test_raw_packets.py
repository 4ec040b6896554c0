"""``storage.store_raw_packets``: every packet of a vehicle is kept as it arrived."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from server.app_main import ServerThread, build_app
from server.protocol import decode
from server.settings import Settings
from tests.support import free_port, run_vehicle_client


@pytest.mark.zenoh
@pytest.mark.parametrize("store_raw", [True, False])
def test_raw_packets_are_stored_when_asked(tmp_path: Path, store_raw: bool) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    settings = Settings(
        zenoh={"listen": [endpoint]},
        storage={"data_dir": tmp_path, "commit_interval_s": 0.2, "store_raw_packets": store_raw},
        api={"port": 0, "require_auth": False},
        viewer={"enabled": False},
    )
    app = build_app(settings)
    server = ServerThread(app, "127.0.0.1", 0)
    server.start()
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
