"""The throughput bench's naive baseline over real Zenoh on loopback, real publisher processes
and a real SQLite file: every flooded packet handled, rows stepped from IMU time and committed."""

from __future__ import annotations

from server.tooling.bench.throughput import flood_naive, flood_payloads


def test_naive_baseline_handles_every_packet_and_stores_rows() -> None:
    vehicles, packets = 2, 120
    r = flood_naive(vehicles, packets)
    assert r["received"] == r["packets"] == vehicles * packets
    imu_packets = sum(stream == "imu" for stream, _ in flood_payloads(packets))
    # at least one tick stepped per IMU packet after each vehicle's first, all of them stored
    assert r["rows"] >= vehicles * (imu_packets - 1) > 0, r
