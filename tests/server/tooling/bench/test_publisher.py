"""``slipfleet bench publisher`` end to end on a tiny fleet: both paths publish, the bench's
subscriber receives everything sent, and the table names both paths."""

from __future__ import annotations

import argparse

import pytest

from server.tooling.bench import publisher

pytestmark = [pytest.mark.zenoh, pytest.mark.slow]


def test_both_paths_deliver_everything_they_send_and_are_tabulated() -> None:
    args = argparse.Namespace(
        vehicles=[10], paths=list(publisher.PATHS), warmup=0.5, window=1.5, sessions=1
    )
    rows = publisher.run(args)
    assert [r["path"] for r in rows] == ["per-packet", "encoded"]
    for r in rows:
        assert r["sent"] > 10 * 2 * 10  # ≈30 packets per vehicle-second over ≥ 2 s
        assert r["received"] == r["sent"]
        assert r["us_per_packet"] > 0 and r["cores"] > 0
        assert r["late_p50_ms"] <= r["late_p99_ms"] <= r["late_max_ms"]
        assert 0.5 * r["target_per_s"] < r["sent_per_s"] < 1.5 * r["target_per_s"]
    table = publisher.format_table(rows)
    assert "per-packet" in table and "encoded" in table and "less CPU per packet" in table
