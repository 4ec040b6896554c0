"""Memory is bounded in bytes: 100 payloads of 10 MB on a vehicle's own key, sent to a real
``slipfleet serve`` over real Zenoh, are refused from their length before they are copied, are
counted, are never stored raw, and leave the server's resident memory where it was."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
import zenoh

from server.settings import StorageSettings
from server.storage import open_store
from server.storage.sqlite import SqliteStore
from tests.server.faults._harness import ServerProcess, wait_until
from tests.server.redteam._stack import client_session, rejected, rss_bytes

PAYLOADS = 100
PAYLOAD_BYTES = 10 * 1024 * 1024
MB = 1024 * 1024


@pytest.mark.zenoh
@pytest.mark.slow
def test_oversize_payloads_do_not_grow_memory_nor_get_stored(tmp_path: Path) -> None:
    server = ServerProcess(tmp_path, extra_env={"SLIPFLEET_STORAGE__STORE_RAW_PACKETS": "true"})
    server.start()
    try:
        server.wait_ready()
        assert server.proc is not None
        pid = server.proc.pid
        start_rss, _ = rss_bytes(pid)
        payload = b"\x92" * PAYLOAD_BYTES
        with client_session(server.zenoh_listen) as session:
            pub = session.declare_publisher(
                "fleet/big-1/sensors/imu", congestion_control=zenoh.CongestionControl.BLOCK
            )
            time.sleep(0.5)  # the client learns of the server's subscription
            for _ in range(PAYLOADS):
                pub.put(payload)
            with server.client() as client:
                wait_until(
                    lambda: rejected(client, "big-1").get("oversize", 0) == PAYLOADS,
                    60,
                    f"{PAYLOADS} oversize refusals",
                )
                counts = rejected(client, "big-1")
        time.sleep(2.0)
        end_rss, peak_rss = rss_bytes(pid)
    finally:
        server.stop()
    print(
        f"RSS start {start_rss / MB:.0f} MB, peak {peak_rss / MB:.0f} MB, "
        f"after {end_rss / MB:.0f} MB"
    )
    assert counts == {"oversize": PAYLOADS}
    assert peak_rss - start_rss < 200 * MB
    assert end_rss - start_rss < 50 * MB
    store = open_store(StorageSettings(data_dir=tmp_path / "data"))
    assert isinstance(store, SqliteStore)
    try:
        assert store.query_raw_packets("big-1", 0, time.time_ns()) == []
    finally:
        store.close()
