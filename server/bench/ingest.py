"""``slipfleet bench ingest codec|ingest [OPTIONS…]``: the ingest benchmarks of
:mod:`server.ingest.bench` (decode CPU per packet, old and new path side by side; Zenoh →
pipeline throughput)."""

from __future__ import annotations

from server.ingest.bench import main

__all__ = ["main"]
