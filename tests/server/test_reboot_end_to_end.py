"""End to end: a vehicle that reboots mid-day numbers its packets from 0 again under a new boot
id, and the server takes every packet of both drives.

A simulated tractor publishes a short drive over a real Zenoh session on loopback to the server
(embedded router, pipeline, MDSF, SQLite file), then "reboots": a new simulator start, its
sequence numbers from 0 again and a new boot id, and sends a second drive just after the first.
Without the boot id the second drive's first ~100 packets per stream had numbers the server had
just seen and were dropped as duplicates.
"""

from __future__ import annotations

import time
from pathlib import Path

import httpx
import pytest

from server.settings import Settings
from tests.server.fleet_stack import (
    publish_drive,
    running_server,
    stack_settings,
    stored_columns,
    wait_counted,
)

pytestmark = [pytest.mark.zenoh, pytest.mark.slow]

VID = "sim-0001"
S = 1_000_000_000
DRIVE_S = 20.0  # the shortest random drive


def _drive(settings: Settings, start_ns: int, seed: int) -> tuple[int, int]:
    """Publish one drive of ``DRIVE_S`` from ``start_ns`` (a fresh simulator start: sequence
    numbers from 0, a new boot id); ``(packets sent, end ns)``."""
    stats = publish_drive(settings, start_ns, DRIVE_S, seed)
    return stats.total_packets, start_ns + int(DRIVE_S * S)


def test_a_reboot_is_not_a_run_of_duplicates(tmp_path: Path) -> None:
    settings = stack_settings(tmp_path, None, 0)
    t0 = time.time_ns() - 60 * S
    window = {"start": t0 - S, "end": t0 + 60 * S}
    with (
        running_server(settings) as (_, server),
        httpx.Client(base_url=f"http://127.0.0.1:{server.port}", timeout=30) as client,
    ):
        sent_a, end_a = _drive(settings, t0, seed=3)
        start_b = end_a + S
        sent_b, end_b = _drive(settings, start_b, seed=5)
        ingest = wait_counted(client, 1, sent_a + sent_b, window)[VID]["ingest"]
        assert ingest["received"] == ingest["accepted"] == sent_a + sent_b, ingest
        assert ingest["duplicate"] == 0 and ingest["lost"] == 0, ingest
        assert ingest["other"].get("seq_restarts") == 1, ingest  # one reboot, told once
        rows_a = stored_columns(client, VID, t0, end_a, "flags")["stamp_ns"]
        rows_b = stored_columns(client, VID, start_b, end_b, "flags")["stamp_ns"]
    # both drives stored from their start to their end
    for rows, start, end in ((rows_a, t0, end_a), (rows_b, start_b, end_b)):
        assert rows[0] < start + 2 * S and rows[-1] > end - 2 * S, (rows[0], rows[-1])
    assert (rows_a < start_b).sum() > 0.9 * DRIVE_S * 10  # a row every 100 ms, nearly all
    assert (rows_b >= start_b).sum() > 0.9 * DRIVE_S * 10
