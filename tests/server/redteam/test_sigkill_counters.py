"""Counters exact across a SIGKILL: a real ``slipfleet serve`` killed while two vehicles stream
over Zenoh and started again; over the vehicles' whole run every packet sent is counted once,
received or lost (``received + lost_by_seq_gap == sent``)."""

from __future__ import annotations

import re
import signal
import time
from pathlib import Path

import pytest

from tests.server.faults._harness import Publisher, ServerProcess, wait_until


def _counts(server: ServerProcess, name: str) -> dict[str, int]:
    with server.client() as c:
        text = c.get("/api/v1/metrics").text
    pattern = rf'^slipfleet_packets_{name}_total\{{vehicle="([^"]+)"\}} (\S+)$'
    return {m[1]: int(float(m[2])) for m in re.finditer(pattern, text, re.M)}


@pytest.mark.zenoh
@pytest.mark.slow
def test_received_plus_lost_equals_sent_across_a_sigkill(tmp_path: Path) -> None:
    server = ServerProcess(tmp_path)
    # real time: the downtime (kill to first packet taken, a few seconds) stays below
    # ingest.clock_jump_s of sensor time, past which the stream is taken up afresh (re-anchored)
    # and its gap is not counted lost
    pub = Publisher(server.zenoh_listen, n_vehicles=2, duration_s=40.0, rate=1.0)
    server.start()
    try:
        server.wait_ready()
        pub.start()
        wait_until(
            lambda: len(_counts(server, "received")) == 2, 30, "both vehicles counted", poll_s=0.2
        )
        time.sleep(3.0)  # registered and counters flushed (once a second), then more traffic
        server.signal(signal.SIGKILL)
        assert server.wait_exit(10) == -signal.SIGKILL
        time.sleep(1.0)
        server.start()
        server.wait_ready()
        pub.wait_done(120)
        sent = {
            vid: sum(1 for key, _ in pub.sent_order if key.split("/")[1] == vid)
            for vid in pub.vehicle_ids
        }

        def settled() -> bool:
            received, lost = _counts(server, "received"), _counts(server, "lost_by_seq_gap")
            return all(received.get(v, 0) + lost.get(v, 0) >= sent[v] for v in sent)

        wait_until(settled, 30, "every packet counted", poll_s=0.5)
        time.sleep(1.5)  # nothing counted twice arrives later
        received, lost = _counts(server, "received"), _counts(server, "lost_by_seq_gap")
    finally:
        pub.stop()
        server.stop()
    print({v: (received[v], lost[v], sent[v]) for v in sent})
    for vid, n in sent.items():
        assert lost[vid] > 0, f"{vid}: packets were sent while the server was down"
        assert received[vid] + lost[vid] == n, (vid, received[vid], lost[vid], n)
