"""Ingest benchmarks: codec cost per packet and Zenoh → pipeline throughput.

::

    python -m server.tooling.bench.ingest codec [--vehicles 100] [--repeats 7] [--json] [--boot]
    python -m server.tooling.bench.ingest ingest --vehicles 200 --packets 300 [--estimator mdsf]

``codec`` decodes the packets of a simulated 5-minute ``field_work`` run, dealt to ``vehicles``
vehicles, two ways in one run: each packet on its own (``decode``, the old ingest path) and
``subscriber.BURST`` packets at a time (``decode_burst``, the ingest thread's path); it prints
the thread CPU time per packet of each (least of ``repeats`` interleaved passes) and their
ratio, per stream and overall. With ``--boot`` it times instead the same packets without and
with the header's ``boot`` field (a 63-bit boot id), both paths, interleaved in one run.
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
from collections.abc import Callable, Mapping

import numpy as np

from estimator.base import Pushed
from estimator.config import VehicleConfig
from estimator.mdsf_spec import MDSF_SPEC
from estimator.types import ESTIMATE_DTYPE
from server.tooling.ports import free_port as _free_port

__all__ = [
    "bench_boot",
    "bench_burst_sizes",
    "bench_codec",
    "bench_ingest",
    "format_boot_table",
    "format_burst_table",
    "format_codec_table",
    "main",
]

TICK_NS = 100_000_000


def _encoded(n_packets: int | None = None, boot: int | None = None) -> list[tuple[str, bytes]]:
    """``(stream, payload)`` of a simulated run, sequence numbers per stream (and ``boot``)."""
    from estimator.sim import simulate
    from server.tooling.fleet_sim import encode_packets, packetize

    now_ns = time.time_ns()  # stamps near the wall clock: the pipeline refuses far ones
    run = simulate("field_work", seed=1, start_ns=now_ns - now_ns % TICK_NS)
    return encode_packets(packetize(run.sent_in_arrival_order(), run.start_ns)[:n_packets], boot)


def _keyed(vehicles: int, boot: int | None = None) -> list[tuple[str, bytes]]:
    """``(key, payload)`` of a simulated run, the packets dealt to ``vehicles`` vehicles in turn
    (as a fleet's packets interleave in one burst)."""
    from server.protocol import sensor_key

    return [
        (sensor_key("fleet", f"bench-{i % vehicles:05d}", stream), payload)
        for i, (stream, payload) in enumerate(_encoded(boot=boot))
    ]


def _decode_alone(received: list[tuple[str, bytes]]) -> None:
    """The old ingest path: every packet of a burst decoded on its own, refusals kept."""
    from server.ingest.subscriber import BURST, IngestItem
    from server.protocol import DecodeError, decode

    for i in range(0, len(received), BURST):
        burst: list[IngestItem] = []
        for key, payload in received[i : i + BURST]:
            try:
                burst.append(decode(key, payload))
            except DecodeError as exc:
                burst.append(exc)


def _decode_bursts(received: list[tuple[str, bytes]], size: int | None = None) -> None:
    """The ingest path: the packets of a burst (``size``, default ``subscriber.BURST``)
    decoded together."""
    from server.ingest.subscriber import BURST
    from server.protocol.burst import decode_burst

    step = size or BURST
    for i in range(0, len(received), step):
        decode_burst(received[i : i + step])


def _cpu_us_per_packet(
    paths: Mapping[str, Callable[[list[tuple[str, bytes]]], None]],
    received: list[tuple[str, bytes]],
    repeats: int,
) -> dict[str, float]:
    """Least thread CPU time per packet of each path over ``repeats`` interleaved passes (µs)."""
    best = dict.fromkeys(paths, float("inf"))
    for _ in range(repeats):
        for name, path in paths.items():
            t0_ns = time.thread_time_ns()
            path(received)
            best[name] = min(best[name], (time.thread_time_ns() - t0_ns) / 1e3 / len(received))
    return best


def bench_codec(vehicles: int = 100, repeats: int = 7) -> dict[str, dict[str, float]]:
    """Decode CPU in µs per packet, per stream and overall: each packet on its own
    (``decode_us``, the old ingest path) and in bursts (``burst_decode_us``), their ratio, and
    the mean payload bytes."""
    enc = _keyed(vehicles)
    groups: dict[str, list[tuple[str, bytes]]] = {"all": enc}
    for key, payload in enc:
        groups.setdefault(key.rsplit("/", 1)[1], []).append((key, payload))
    paths = {"decode_us": _decode_alone, "burst_decode_us": _decode_bursts}
    out = {}
    for name, items in groups.items():
        cost = _cpu_us_per_packet(paths, items, repeats)
        out[name] = {
            **{k: round(v, 2) for k, v in cost.items()},
            "ratio": round(cost["decode_us"] / cost["burst_decode_us"], 2),
            "bytes": round(float(np.mean([len(p) for _, p in items])), 1),
            "packets": float(len(items)),
        }
    return out


def bench_boot(vehicles: int = 100, repeats: int = 7) -> dict[str, float]:
    """Decode CPU in µs per packet (all streams) of the same packets without and with the
    ``boot`` header field, each packet alone and in bursts, interleaved in one run."""
    plain = _keyed(vehicles)
    booted = _keyed(vehicles, boot=2**62 + 12_345)  # a 63-bit id: msgpack uint 64, 9 bytes
    paths: dict[str, Callable[[list[tuple[str, bytes]]], None]] = {
        "alone": lambda _: _decode_alone(plain),
        "alone_boot": lambda _: _decode_alone(booted),
        "burst": lambda _: _decode_bursts(plain),
        "burst_boot": lambda _: _decode_bursts(booted),
    }
    cost = _cpu_us_per_packet(paths, plain, repeats)
    return {k: round(v, 3) for k, v in cost.items()}


def format_boot_table(result: Mapping[str, float]) -> str:
    """The :func:`bench_boot` result as a table."""
    lines = [
        "decode CPU per packet (µs, least of interleaved passes), all streams",
        f"{'path':<8} {'no boot':>9} {'boot':>9} {'added':>9}",
    ]
    for path in ("alone", "burst"):
        base, boot = result[path], result[f"{path}_boot"]
        lines.append(f"{path:<8} {base:>9.3f} {boot:>9.3f} {boot - base:>+9.3f}")
    return "\n".join(lines)


#: Burst sizes of :func:`bench_burst_sizes`: a real-time server's bursts are as large as what
#: arrives in ``ingest.gather_ms`` (5 ms: ~45 packets at 300 vehicles, ~150 at 1,000).
BURST_SIZES = (1, 8, 32, 128, 512)


def bench_burst_sizes(
    vehicles: int = 100, repeats: int = 7, sizes: tuple[int, ...] = BURST_SIZES
) -> dict[int, float]:
    """Burst-decode CPU in µs per packet (all streams) by burst size, with the per-packet
    decode (size 0 in the result) as the baseline of the same run."""
    enc = _keyed(vehicles)

    def sized(n: int) -> Callable[[list[tuple[str, bytes]]], None]:
        return lambda received: _decode_bursts(received, n)

    paths: dict[str, Callable[[list[tuple[str, bytes]]], None]] = {"0": _decode_alone}
    paths.update({str(n): sized(n) for n in sizes})
    return {int(k): round(v, 2) for k, v in _cpu_us_per_packet(paths, enc, repeats).items()}


def format_burst_table(result: Mapping[int, float]) -> str:
    """The :func:`bench_burst_sizes` result as a table."""
    alone = result[0]
    lines = ["decode CPU per packet by burst size (all streams)", "burst    µs/packet  alone/burst"]
    lines.append(f"{'alone':<8} {alone:>10.2f} {1.0:>12.2f}")
    for n, us in result.items():
        if n:
            lines.append(f"{n:<8} {us:>10.2f} {alone / us:>12.2f}")
    return "\n".join(lines)


def format_codec_table(result: Mapping[str, Mapping[str, float]]) -> str:
    """The :func:`bench_codec` result as a table."""
    lines = [
        "decode CPU per packet (µs, least of interleaved passes)",
        f"{'stream':<8} {'packets':>8} {'bytes':>7} {'alone (old)':>12} {'burst (new)':>12} "
        f"{'old/new':>8}",
    ]
    for name, r in result.items():
        lines.append(
            f"{name:<8} {r['packets']:>8.0f} {r['bytes']:>7.1f} {r['decode_us']:>12.2f} "
            f"{r['burst_decode_us']:>12.2f} {r['ratio']:>8.2f}"
        )
    return "\n".join(lines)


class _NullFleet:
    """A FleetEstimator that does nothing (measures the ingest path alone)."""

    name = "mdsf"
    spec = MDSF_SPEC
    output_dtype = ESTIMATE_DTYPE

    def __init__(self) -> None:
        self._ids: set[str] = set()

    def add_vehicle(self, vehicle_id: str, config: VehicleConfig) -> None:
        self._ids.add(vehicle_id)

    def remove_vehicle(self, vehicle_id: str) -> None:
        self._ids.discard(vehicle_id)

    def vehicle_ids(self) -> list[str]:
        return list(self._ids)

    def push(self, vehicle_id: str, measurement: Pushed) -> None:
        return None

    def align_ticks(self, vehicle_id: str, stamp_ns: int) -> None:
        return None

    def advance(self, until_ns: Mapping[str, int]) -> list[tuple[str, np.ndarray]]:
        return []


_PUBLISHER = """
import json, sys, time, zenoh
from server.tooling.bench.ingest import _encoded
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
    from server.estimation import EstimatorRegistry
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
    parser = argparse.ArgumentParser(
        prog="python -m server.tooling.bench.ingest", description=__doc__
    )
    sub = parser.add_subparsers(dest="what", required=True)
    c = sub.add_parser("codec", help="decode CPU per packet: alone (old) and in bursts (new)")
    c.add_argument("--vehicles", type=int, default=100, help="vehicles the packets are dealt to")
    c.add_argument("--repeats", type=int, default=7, help="interleaved passes (least kept)")
    c.add_argument("--json", action="store_true", help="print JSON instead of the table")
    c.add_argument("--boot", action="store_true", help="without vs with the 'boot' field")
    p = sub.add_parser("ingest", help="Zenoh -> pipeline throughput")
    p.add_argument("--vehicles", type=int, default=100)
    p.add_argument("--packets", type=int, default=300, help="packets per vehicle")
    p.add_argument("--estimator", choices=("null", "mdsf"), default="null")
    args = parser.parse_args(argv)
    if args.what == "codec" and args.boot:
        boot = bench_boot(args.vehicles, args.repeats)
        print(json.dumps(boot, indent=2) if args.json else format_boot_table(boot))
        return
    if args.what == "codec":
        codec = bench_codec(args.vehicles, args.repeats)
        sizes = bench_burst_sizes(args.vehicles, args.repeats)
        if args.json:
            print(json.dumps({"streams": codec, "burst_sizes": sizes}, indent=2))
        else:
            print(format_codec_table(codec))
            print(format_burst_table(sizes))
        return
    print(json.dumps(bench_ingest(args.vehicles, args.packets, args.estimator), indent=2))


if __name__ == "__main__":
    main()
