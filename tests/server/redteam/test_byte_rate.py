"""One vehicle flooding its own key over real Zenoh is held to its byte rate: the excess is
refused (``rejected_over_rate``) while another vehicle's packets all get through."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
import zenoh

from tests.server.faults._harness import ServerProcess, wait_until
from tests.server.redteam._stack import client_session, rejected
from tests.support import run_vehicle_client

FLOOD = 200
FLOOD_BYTES = 200 * 1024


@pytest.mark.zenoh
def test_a_flooding_vehicle_is_held_to_its_byte_rate(tmp_path: Path) -> None:
    server = ServerProcess(
        tmp_path,
        extra_env={
            "SLIPFLEET_INGEST__VEHICLE_MAX_BYTES_PER_S": str(256 * 1024),
            "SLIPFLEET_INGEST__VEHICLE_BURST_BYTES": str(1024 * 1024),
        },
    )
    server.start()
    try:
        server.wait_ready()
        with client_session(server.zenoh_listen) as session, server.client() as client:
            pub = session.declare_publisher(
                "fleet/flood-1/sensors/imu", congestion_control=zenoh.CongestionControl.BLOCK
            )
            time.sleep(0.5)
            t0 = time.monotonic()
            for _ in range(FLOOD):
                pub.put(b"\x90" * FLOOD_BYTES)
            sent_s = time.monotonic() - t0
            honest = run_vehicle_client(server.zenoh_listen, "honest-1", 2)
            assert honest.returncode == 0, honest.stderr
            wait_until(
                lambda: sum(rejected(client, "flood-1").values()) == FLOOD, 30, "flood counted"
            )
            flood = rejected(client, "flood-1")
            assert rejected(client, "honest-1") == {}
    finally:
        server.stop()
    # the bucket (1 MiB) and the rate over the sending time let through at most this many
    allowed = (1024 * 1024 + 256 * 1024 * (sent_s + 1.0)) // FLOOD_BYTES
    assert flood.get("over_rate", 0) >= FLOOD - allowed
    assert flood.get("over_rate", 0) + flood.get("undecodable", 0) == FLOOD
