"""A crawler's packets: one per stream and 100 ms window, encoded with the server's stream
declarations (edge windows without an edge sent as heartbeats), the encoded schedule patching
their stamps and sequence numbers byte for byte as the per-packet encoding does, over loops;
and ``slipfleet demo`` runs one crawler among the tractors."""

from __future__ import annotations

import threading
from collections import defaultdict
from pathlib import Path

import httpx
import numpy as np
import pytest

from estimator.geo import EnuFrame
from estimator.sim.tracked import TrackedRun, simulate_route
from estimator.types import OdometerEdges, SprocketEdges
from server.protocol import Stream, decode, sensor_key
from server.tooling.fleet_commands import demo
from server.tooling.fleet_sim import SimPacket
from server.tooling.tracked_fleet import demo_route, tracked_packets
from tests.server.fleet_stack import stack_settings
from tests.server.tooling.schedule_check import assert_schedule_patches_like_encoding
from tests.support import free_port, poll_until

T0 = 1_763_700_000 * 10**9
#: the demo's vehicles waited for: two tractors and the crawler, by their estimators
WANT = {"sim-0001": ["mdsf"], "sim-0002": ["mdsf", "reference_speed"], "sim-0004": ["tracked"]}
CRAWLER_STREAMS = {Stream.GNSS, Stream.IMU, Stream.ODOMETER, Stream.SPROCKETS}


@pytest.fixture(scope="module")
def run() -> TrackedRun:
    return simulate_route(demo_route(), 3, start_ns=T0, frame=EnuFrame(52.0, 5.6, 10.0))


def _edges(packets: list[SimPacket], side: int | None) -> np.ndarray:
    """Every edge stamp of the odometer (``side`` None) or one sprocket, in packet order."""
    out = []
    for p in packets:
        for m in p.measurements:
            if side is None and isinstance(m, OdometerEdges):
                out.append(m.stamp_ns)
            if isinstance(m, SprocketEdges) and int(m.side) == side:
                out.append(m.stamp_ns)
    return np.concatenate(out)


def test_packets_hold_every_edge_once_and_decode_as_sent(run: TrackedRun) -> None:
    packets = tracked_packets(run.measurements, run.start_ns)
    offsets = [p.arrival_offset_ns for p in packets]
    assert offsets == sorted(offsets) and {p.stream for p in packets} == CRAWLER_STREAMS
    windows = len({o for o in offsets})
    for stream in CRAWLER_STREAMS:  # one packet per stream and window, none left out
        assert sum(p.stream is stream for p in packets) == windows
    sent = [m for _, m in run.measurements]
    np.testing.assert_array_equal(
        _edges(packets, None),
        np.concatenate([m.stamp_ns for m in sent if isinstance(m, OdometerEdges)]),
    )
    for side in (0, 1):
        want = [m.stamp_ns for m in sent if isinstance(m, SprocketEdges) and int(m.side) == side]
        np.testing.assert_array_equal(_edges(packets, side), np.concatenate(want))
    heartbeats = [p for p in packets if not p.measurements]
    assert heartbeats and all(p.stream in (Stream.ODOMETER, Stream.SPROCKETS) for p in heartbeats)
    seq: dict[Stream, int] = defaultdict(int)
    for p in packets:
        got = decode(sensor_key("fleet", "sim-0009", p.stream), p.encode(seq[p.stream]))
        assert got.stream is p.stream and got.seq == seq[p.stream]
        assert got.until_ns == p.until_ns
        if p.stream in (Stream.ODOMETER, Stream.SPROCKETS):
            assert p.until_ns == T0 + p.arrival_offset_ns
        for back, m in zip(got.measurements, p.measurements, strict=True):
            assert type(back) is type(m)
            np.testing.assert_array_equal(np.asarray(back.stamp_ns), np.asarray(m.stamp_ns))
        seq[p.stream] += 1


def test_schedule_patches_crawler_packets_like_the_per_packet_encoding(run: TrackedRun) -> None:
    packets = tracked_packets(run.measurements, run.start_ns)[:400]  # 10 s of the route
    assert_schedule_patches_like_encoding(packets, T0, CRAWLER_STREAMS)


def test_demo_route_stops_at_both_ends_and_loses_gnss_in_its_turns() -> None:
    route = demo_route()
    assert route.segments[0].speed_mps == route.segments[-1].speed_mps == 0.0
    ((start_s, length_s),) = route.outages_s
    assert start_s > 0 and start_s + length_s < route.duration_s and length_s >= 30


@pytest.mark.zenoh
@pytest.mark.slow
def test_demo_runs_one_crawler_among_the_tractors(tmp_path: Path) -> None:
    """Two tractors (the second with a reference speed beside), then the steered vehicle
    (``sim-0003``, which joins once its slow simulation is done: not waited for here), then
    the crawler ``sim-0004``, registered with its config's kind and running ``tracked``; the
    demo ends once they are seen (``stop``), not after a fixed time."""
    settings = stack_settings(tmp_path, None, 0)
    settings.api.port = free_port()
    stop, done = threading.Event(), threading.Event()

    def run_demo() -> None:
        demo(settings, vehicles=2, stop=stop)
        done.set()

    runner = threading.Thread(target=run_demo, daemon=True)
    runner.start()
    base = f"http://127.0.0.1:{settings.api.port}"

    def estimators() -> dict[str, list[str]] | None:
        assert runner.is_alive(), "the demo ended before its vehicles were seen"
        try:
            body = httpx.get(f"{base}/api/v1/vehicles", timeout=5).json()
        except httpx.HTTPError:
            return None
        seen = {v["vehicle_id"]: v["estimators"] for v in body["data"]}
        return seen if WANT.items() <= seen.items() else None

    try:
        poll_until(estimators, f"vehicles {WANT}", timeout_s=120.0, poll_s=0.5)
        kind = httpx.get(f"{base}/api/v1/vehicles/sim-0004", timeout=5).json()["config"]["kind"]
    finally:
        stop.set()
        runner.join(60)
    assert done.is_set()
    assert kind == "tracked"
