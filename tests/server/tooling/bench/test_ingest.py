"""The ingest benchmark runs (tiny sizes) and accounts for every packet."""

from __future__ import annotations

import pytest

from server.tooling.bench.ingest import bench_burst_sizes, bench_codec, bench_ingest


def test_bench_codec_reports_every_stream() -> None:
    result = bench_codec()
    assert set(result) == {"all", "gnss", "imu", "wheels"}
    assert all(r["decode_us"] > 0 and r["bytes"] > 0 for r in result.values())


@pytest.mark.zenoh
def test_bench_ingest_counts_every_packet() -> None:
    result = bench_ingest(vehicles=3, n_packets=40)
    assert result["received"] == result["accepted"] == result["packets"] == 120
    assert result["lost_by_seq_gap"] == 0 and result["ingest_packets_per_s"] > 0


def test_bench_burst_sizes_has_the_per_packet_baseline_and_every_size() -> None:
    from server.tooling.bench.ingest import format_burst_table

    result = bench_burst_sizes(vehicles=10, repeats=1, sizes=(1, 64))
    assert set(result) == {0, 1, 64} and all(us > 0 for us in result.values())
    table = format_burst_table(result)
    assert table.splitlines()[2].startswith("alone") and len(table.splitlines()) == 5
