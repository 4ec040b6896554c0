"""The ingest benchmark runs (tiny sizes) and accounts for every packet."""

from __future__ import annotations

import pytest

from server.ingest.bench import bench_codec, bench_ingest


def test_bench_codec_reports_every_stream() -> None:
    result = bench_codec()
    assert set(result) == {"all", "gnss", "imu", "wheels"}
    assert all(r["decode_us"] > 0 and r["bytes"] > 0 for r in result.values())


@pytest.mark.zenoh
def test_bench_ingest_counts_every_packet() -> None:
    result = bench_ingest(vehicles=3, n_packets=40)
    assert result["received"] == result["accepted"] == result["packets"] == 120
    assert result["lost_by_seq_gap"] == 0 and result["ingest_packets_per_s"] > 0
