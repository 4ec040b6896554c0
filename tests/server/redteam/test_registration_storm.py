"""A storm of new vehicle ids over real Zenoh (10,000 valid GNSS packets from 5,000 ids, as fast
as Zenoh takes them) against a real ``slipfleet serve`` with ``unknown_vehicle = auto``: at
most ``ingest.max_registrations_per_min`` vehicles register, the rest are refused and counted
(``rejected_registration_cap``), memory and ``/metrics`` stay bounded."""

from __future__ import annotations

import re
import time
from pathlib import Path

import pytest
import zenoh

from server.protocol import sensor_key
from server.protocol.keys import Stream
from server.settings import IngestSettings
from tests.server.faults._harness import ServerProcess, wait_until
from tests.server.redteam._stack import client_session, gnss_payload, rss_bytes

IDS = 5000
MB = 1024 * 1024
PER_MIN = IngestSettings().max_registrations_per_min


def _total(metrics: str, name: str, reason: str | None = None) -> int:
    """A counter's fleet total in ``/metrics?by_vehicle=false``."""
    label = "" if reason is None else f'{{reason="{reason}"}}'
    m = re.search(rf"^{re.escape(name + label)} (\S+)$", metrics, re.MULTILINE)
    return int(float(m.group(1))) if m else 0


@pytest.mark.zenoh
@pytest.mark.slow
def test_registration_storm_is_capped_and_counted(tmp_path: Path) -> None:
    server = ServerProcess(tmp_path)
    server.start()
    try:
        server.wait_ready()
        assert server.proc is not None
        start_rss, _ = rss_bytes(server.proc.pid)
        now = time.time_ns()
        with client_session(server.zenoh_listen) as session, server.client() as client:
            time.sleep(0.5)
            t0 = time.monotonic()
            for i in range(IDS):
                key = sensor_key("fleet", f"storm-{i:05d}", Stream.GNSS)
                for seq in range(2):
                    session.put(
                        key,
                        gnss_payload(now + seq * 100_000_000, seq),
                        congestion_control=zenoh.CongestionControl.BLOCK,
                    )
            sent_s = time.monotonic() - t0

            def fleet() -> str:
                return client.get("/api/v1/metrics?by_vehicle=false").text

            wait_until(
                lambda: _total(fleet(), "slipfleet_packets_received_total") == 2 * IDS,
                60,
                "every packet counted",
            )
            totals = fleet()
            wait_until(
                lambda: client.get("/api/v1/vehicles").json()["count"] == PER_MIN,
                30,
                "the registered vehicles stored",
            )
            time.sleep(1.0)
            registered = client.get("/api/v1/vehicles").json()["count"]
            metrics_bytes = len(client.get("/api/v1/metrics").content)
        end_rss, _ = rss_bytes(server.proc.pid)
    finally:
        server.stop()
    print(
        f"{2 * IDS} packets in {sent_s:.2f} s: {registered} registered, RSS "
        f"+{(end_rss - start_rss) / MB:.0f} MB, /metrics {metrics_bytes / 1e6:.2f} MB"
    )
    assert sent_s < 60  # the cap is per minute: the whole storm fell in one window
    assert registered == PER_MIN
    refused = 2 * (IDS - PER_MIN)
    assert _total(totals, "slipfleet_packets_rejected_total", "registration_cap") == refused
    assert _total(totals, "slipfleet_packets_accepted_total") == 2 * PER_MIN
    assert end_rss - start_rss < 600 * MB
    assert metrics_bytes < 3 * MB
