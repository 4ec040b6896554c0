"""Ingest benchmarks: codec cost per packet and Zenoh → pipeline throughput.

::

    python -m server.ingest.bench codec
    python -m server.ingest.bench ingest --vehicles 200 --packets 300 [--estimator mdsf]

``codec`` decodes the packets of a simulated 5-minute ``field_work`` run (best of 7 passes).
``ingest`` starts an embedded router on a free loopback port and a pipeline, then a separate
publisher process sends ``packets`` simulated packets for each of ``vehicles`` vehicles as fast
as BLOCK congestion control lets it; it reports packets per second through decode, reorder and
(with ``--estimator mdsf``) the MDSF estimator. The default estimator is a no-op, to measure the
ingest path alone.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from collections import Counter
from collections.abc import Mapping

import numpy as np

from estimator.base import Measurement
from estimator.config import VehicleConfig
from estimator.types import ESTIMATE_DTYPE
from server.ports import free_port as _free_port

__all__ = ["bench_codec", "bench_ingest", "main"]

TICK_NS = 100_000_000


def _encoded(n_packets: int | None = None) -> list[tuple[str, bytes]]:
    """``(stream, payload)`` of a simulated run, sequence numbers per stream."""
    from estimator.sim import simulate
    from server.fleet_sim import encode_packets, packetize

    now_ns = time.time_ns()  # stamps near the wall clock: the pipeline refuses far ones
    run = simulate("field_work", seed=1, start_ns=now_ns - now_ns % TICK_NS)
    return encode_packets(packetize(run.sent_in_arrival_order(), run.start_ns)[:n_packets])


def bench_codec() -> dict[str, dict[str, float]]:
    """Decode cost in µs per packet and mean payload bytes, per stream and overall."""
    from server.protocol import decode, sensor_key

    enc = [(sensor_key("fleet", "bench-1", s), p) for s, p in _encoded()]
    groups: dict[str, list[tuple[str, bytes]]] = {"all": enc}
    for key, payload in enc:
        groups.setdefault(key.rsplit("/", 1)[1], []).append((key, payload))
    out = {}
    for name, items in groups.items():
        best = float("inf")
        for _ in range(7):
            t = time.perf_counter()
            for key, payload in items:
                decode(key, payload)
            best = min(best, (time.perf_counter() - t) / len(items))
        out[name] = {
            "decode_us": round(best * 1e6, 2),
            "bytes": round(float(np.mean([len(p) for _, p in items])), 1),
            "packets": float(len(items)),
        }
    return out


class _NullFleet:
    """A FleetEstimator that does nothing (measures the ingest path alone)."""

    name = "mdsf"
    output_dtype = ESTIMATE_DTYPE

    def __init__(self) -> None:
        self._ids: set[str] = set()

    def add_vehicle(self, vehicle_id: str, config: VehicleConfig) -> None:
        self._ids.add(vehicle_id)

    def remove_vehicle(self, vehicle_id: str) -> None:
        self._ids.discard(vehicle_id)

    def vehicle_ids(self) -> list[str]:
        return list(self._ids)

    def push(self, vehicle_id: str, measurement: Measurement) -> None:
        return None

    def align_ticks(self, vehicle_id: str, stamp_ns: int) -> None:
        return None

    def advance(self, until_ns: Mapping[str, int]) -> list[tuple[str, np.ndarray]]:
        return []


_PUBLISHER = """
import json, sys, time, zenoh
from server.ingest.bench import _encoded
from server.protocol import sensor_key
vehicles, n_packets, endpoint = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
enc = _encoded(n_packets)
config = zenoh.Config()
config.insert_json5("mode", '"client"')
config.insert_json5("connect/endpoints", json.dumps([endpoint]))
config.insert_json5("scouting/multicast/enabled", "false")
config.insert_json5("transport/shared_memory/enabled", "false")
with zenoh.open(config) as session:
    pubs = {
        (v, s): session.declare_publisher(
            sensor_key("fleet", f"bench-{v:05d}", s),
            congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE,
        )
        for v in range(vehicles)
        for s in {s for s, _ in enc}
    }
    time.sleep(0.5)
    t = time.perf_counter()
    for s, payload in enc:
        for v in range(vehicles):
            pubs[(v, s)].put(payload)
    print(json.dumps({"publish_s": time.perf_counter() - t}), flush=True)
    time.sleep(0.5)
"""


def bench_ingest(vehicles: int, n_packets: int, estimator: str = "null") -> dict[str, float]:
    """Packets per second from a publisher process through router, decode and pipeline."""
    from server.estimators import EstimatorRegistry
    from server.ingest.pipeline import Pipeline
    from server.ingest.zenoh_session import open_session
    from server.settings import Settings

    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    settings = Settings.model_validate({"zenoh": {"listen": [endpoint]}})
    registry = (
        EstimatorRegistry() if estimator == "mdsf" else EstimatorRegistry({"mdsf": _NullFleet})
    )
    total = vehicles * n_packets
    with open_session(settings.zenoh) as router:
        pipe = Pipeline(settings, router, registry)
        pipe.start()
        with subprocess.Popen(
            [sys.executable, "-c", _PUBLISHER, str(vehicles), str(n_packets), endpoint],
            stdout=subprocess.PIPE,
            text=True,
        ) as proc:
            first: float | None = None
            deadline = time.monotonic() + 600
            received = 0
            while received < total and time.monotonic() < deadline:
                received = sum(c["received"] for c in pipe.counters_snapshot().values())
                if received and first is None:
                    first = time.perf_counter()
                time.sleep(0.002)
            last = time.perf_counter()
            line = proc.stdout.readline() if proc.stdout else "{}"
            proc.wait(60)
        pipe.stop()
    totals: Counter[str] = Counter()
    for counts in pipe.counters_snapshot().values():
        totals.update(counts)
    publish_s = float(json.loads(line or "{}").get("publish_s", float("nan")))
    return {
        "vehicles": vehicles,
        "packets": total,
        "received": totals["received"],
        "accepted": totals["accepted"],
        "late": totals["late"],
        "lost_by_seq_gap": totals["lost_by_seq_gap"],
        "publish_packets_per_s": round(total / publish_s),
        "ingest_packets_per_s": round(received / (last - (first or last) + 1e-9)),
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m server.ingest.bench", description=__doc__)
    sub = parser.add_subparsers(dest="what", required=True)
    sub.add_parser("codec", help="decode cost per packet")
    p = sub.add_parser("ingest", help="Zenoh -> pipeline throughput")
    p.add_argument("--vehicles", type=int, default=100)
    p.add_argument("--packets", type=int, default=300, help="packets per vehicle")
    p.add_argument("--estimator", choices=("null", "mdsf"), default="null")
    args = parser.parse_args(argv)
    if args.what == "codec":
        result: object = bench_codec()
    else:
        result = bench_ingest(args.vehicles, args.packets, args.estimator)
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
