"""The documented example client runs against an embedded router and its packets decode."""

from __future__ import annotations

import json
import time
from collections import Counter

import pytest
import zenoh

from estimator.types import GnssSample, ImuBatch, WheelEdges
from server.protocol import Stream, decode, decode_config
from tests.server.ingest.fakes import embedded_router
from tests.support import run_vehicle_client


@pytest.mark.zenoh
def test_example_client_publishes_decodable_packets() -> None:
    with embedded_router() as (router, zs, endpoint):
        sensors = router.declare_subscriber("fleet/*/sensors/**", zenoh.handlers.FifoChannel(4096))
        configs = router.declare_subscriber("fleet/*/config", zenoh.handlers.FifoChannel(16))
        proc = run_vehicle_client(endpoint, "doc-1", 1.5)
        assert proc.returncode == 0, proc.stderr
        sent = json.loads(proc.stdout.strip().splitlines()[-1])
        time.sleep(0.2)
        packets = []
        while (s := sensors.handler.try_recv()) is not None:
            packets.append(decode(str(s.key_expr), s.payload.to_bytes(), prefix=zs.key_prefix))
        cfg_sample = configs.handler.try_recv()
    assert cfg_sample is not None
    vid, cfg = decode_config(str(cfg_sample.key_expr), cfg_sample.payload.to_bytes())
    assert vid == "doc-1" and cfg.encoder.teeth_per_rev == 120
    per_stream = Counter(p.stream.value for p in packets)
    assert per_stream == Counter(sent) and sent["imu"] == 15
    for stream in Stream:
        seqs = [p.seq for p in packets if p.stream is stream]
        assert seqs == list(range(len(seqs)))
    imu = [m for p in packets for m in p.measurements if isinstance(m, ImuBatch)]
    assert all(b.stamp_ns.shape == (10,) for b in imu)
    gnss = [m for p in packets for m in p.measurements if isinstance(m, GnssSample)]
    assert all(abs(g.vel_enu_mps[1] - 2.0) < 0.2 for g in gnss)
    edges = [m for p in packets for m in p.measurements if isinstance(m, WheelEdges)]
    left = sum(len(e.stamp_ns) for e in edges if e.wheel == 0)
    right = sum(len(e.stamp_ns) for e in edges if e.wheel == 1)
    assert left > right > 0  # 5 % slip on the left wheel: more edges
