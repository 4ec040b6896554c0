"""Real Zenoh on loopback: embedded router ← client publishers → subscriber → pipeline → sink."""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import pytest
import zenoh

from estimator.config import VehicleConfig, WheeledRearDriveConfig
from estimator.types import GnssSample, ImuBatch, Wheel, WheelEdges
from server.estimation import EstimatorRegistry
from server.ingest import Pipeline, make_config
from server.protocol import (
    Stream,
    config_key,
    encode_config,
    encode_gnss,
    encode_imu,
    encode_wheel_edges,
    sensor_key,
)
from server.settings import IngestSettings, Settings, ZenohSettings
from tests.server.ingest.fakes import (
    CapturingSink,
    RecordingFleet,
    client_session,
    embedded_router,
    first_stamp,
)

pytestmark = pytest.mark.zenoh

MS = 1_000_000
T0 = 1_763_700_000 * 10**9


def wait_for(cond: Callable[[], object], timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError("condition not met in time")
        time.sleep(0.01)


def declare(session: zenoh.Session, key: str) -> zenoh.Publisher:
    pub = session.declare_publisher(
        key,
        congestion_control=zenoh.CongestionControl.BLOCK,
        reliability=zenoh.Reliability.RELIABLE,
    )
    # the stub says bool; the runtime object is a MatchingStatus
    wait_for(lambda: getattr(pub.matching_status, "matching", pub.matching_status), 10.0)
    return pub


def test_make_config_modes() -> None:
    router = make_config(ZenohSettings.model_validate({"listen": ["tcp/127.0.0.1:7999"]}))
    assert router.get_json("mode") == '"router"'
    assert router.get_json("transport/shared_memory/enabled") == "false"
    assert router.get_json("scouting/multicast/enabled") == "false"
    client = make_config(
        ZenohSettings.model_validate(
            {"connect": ["tcp/10.0.0.2:7447"], "username": "srv", "password": "s3cret"}
        )
    )
    assert client.get_json("mode") == '"client"'
    assert client.get_json("transport/auth/usrpwd/user") == '"srv"'
    with pytest.raises(ValueError):
        make_config(
            ZenohSettings.model_validate({"connect": ["tcp/10.0.0.2:7447"], "username": "srv"})
        )


def test_burst_is_not_lost_with_block_congestion_control() -> None:
    vehicles = [f"sim-{i:04d}" for i in range(8)]
    n_imu, n_wheels, n_gnss = 400, 400, 40
    fleet = RecordingFleet()
    sink = CapturingSink()
    with embedded_router(channel_capacity=64) as (router, zs, endpoint):
        settings = Settings(
            zenoh=zs,
            ingest=IngestSettings.model_validate({"lateness_ms": 200, "process_interval_ms": 10}),
        )
        pipe = Pipeline(
            settings,
            router,
            EstimatorRegistry({"mdsf": lambda: fleet}),
            [sink],
            wall_clock_ns=lambda: T0,
        )
        pipe.start()
        try:
            with client_session(endpoint) as client:
                pubs = {
                    (v, s): declare(client, sensor_key(zs.key_prefix, v, s))
                    for v in vehicles
                    for s in Stream
                }
                sent = 0
                t_start = time.perf_counter()
                # a burst: every vehicle's whole drive as fast as the link takes it
                for k in range(n_imu):
                    t = T0 + k * 10 * MS + np.arange(10, dtype=np.int64) * MS
                    imu = encode_imu(
                        ImuBatch(t, np.tile([0, 0, 9.81], (10, 1)), np.zeros((10, 3))), k
                    )
                    edges = encode_wheel_edges(
                        [WheelEdges(Wheel.LEFT, t[::2]), WheelEdges(Wheel.RIGHT, t[1::2])], k
                    )
                    for v in vehicles:
                        pubs[(v, Stream.IMU)].put(imu)
                        pubs[(v, Stream.WHEELS)].put(edges)
                        sent += 2
                        if k % (n_imu // n_gnss) == 0:
                            g = GnssSample(
                                int(t[0]), (0.0, 2.0, 0.0), 0.0, 0.0, 0.0, 48.0, 11.0, 500.0
                            )
                            pubs[(v, Stream.GNSS)].put(encode_gnss(g, k // (n_imu // n_gnss)))
                            sent += 1
                publish_s = time.perf_counter() - t_start
                wait_for(
                    lambda: (
                        pipe.counters_snapshot()
                        and sum(c["received"] for c in pipe.counters_snapshot().values()) >= sent
                    )
                )
                receive_s = time.perf_counter() - t_start
        finally:
            pipe.stop()
    snap = pipe.counters_snapshot()
    assert set(snap) == set(vehicles)
    for v in vehicles:
        c = snap[v]
        assert c["received"] == c["accepted"] == n_imu + n_wheels + n_gnss, c
        assert c["lost_by_seq_gap"] == 0 and c["duplicate"] == 0 and c["rejected"] == 0
        stamps = [first_stamp(m) for m in fleet.pushed[v]]
        assert stamps == sorted(stamps)
        assert len(fleet.pushed[v]) == n_imu + 2 * n_wheels + n_gnss  # two wheels per packet
        assert int(sink.rows[v][-1]["stamp_ns"][-1]) == T0 + (n_imu * 10 - 1) * MS
    print(
        f"\n{sent} packets: published in {publish_s:.2f} s, received in {receive_s:.2f} s "
        f"({sent / receive_s:.0f} packets/s)"
    )


def test_config_key_registers_vehicle() -> None:
    fleet = RecordingFleet()
    stored: list[tuple[str, VehicleConfig]] = []
    with embedded_router() as (router, zs, endpoint):
        settings = Settings(zenoh=zs)
        pipe = Pipeline(
            settings,
            router,
            EstimatorRegistry({"mdsf": lambda: fleet}),
            [],
            lambda v, c: stored.append((v, c)),
            wall_clock_ns=lambda: T0,
        )
        pipe.start()
        try:
            with client_session(endpoint) as client:
                cfg = WheeledRearDriveConfig(estimators=("mdsf",))
                cpub = declare(client, config_key(zs.key_prefix, "veh-7"))
                cpub.put(encode_config(cfg))
                bad = declare(client, config_key(zs.key_prefix, "veh-8"))
                bad.put(b'{"kind": "hovercraft"}')
                # its sensor packets may come before or after the config is applied
                t = T0 + np.arange(3, dtype=np.int64) * MS
                declare(client, sensor_key(zs.key_prefix, "veh-7", Stream.IMU)).put(
                    encode_imu(ImuBatch(t, np.zeros((3, 3)), np.zeros((3, 3))), 0)
                )
                wait_for(lambda: "veh-7" in fleet.vehicles, 10.0)
        finally:
            pipe.stop()
    assert fleet.vehicles["veh-7"] == cfg
    assert ("veh-7", cfg) in stored and all(v != "veh-8" for v, _ in stored)


def test_vehicle_filter_selects_vehicles() -> None:
    fleet = RecordingFleet()
    with embedded_router(vehicle_filter="keep-$*") as (router, zs, endpoint):
        pipe = Pipeline(
            Settings(zenoh=zs),
            router,
            EstimatorRegistry({"mdsf": lambda: fleet}),
            wall_clock_ns=lambda: T0,
        )
        pipe.start()
        try:
            with client_session(endpoint) as client:
                t = T0 + np.arange(3, dtype=np.int64) * MS
                payload = encode_imu(ImuBatch(t, np.zeros((3, 3)), np.zeros((3, 3))), 0)
                drop = client.declare_publisher(sensor_key(zs.key_prefix, "drop-1", Stream.IMU))
                drop.put(payload)
                declare(client, sensor_key(zs.key_prefix, "keep-1", Stream.IMU)).put(payload)
                wait_for(lambda: "keep-1" in pipe.counters_snapshot(), 10.0)
                time.sleep(0.2)
        finally:
            pipe.stop()
    assert list(pipe.counters_snapshot()) == ["keep-1"]


@pytest.mark.parametrize("gather_ms", [0, 40])
def test_ingest_gathers_packets_into_bursts(gather_ms: int) -> None:
    """With ``gather_ms`` the ingest thread waits after a burst's first packet, so packets
    published close together are decoded and delivered together; without it, as they come."""
    from server.ingest.subscriber import IngestSubscriber

    bursts: list[int] = []
    with embedded_router() as (router, zs, endpoint), client_session(endpoint) as client:
        ingest = IngestSettings.model_validate({"gather_ms": gather_ms})
        sub = IngestSubscriber(router, zs, ingest, lambda received: bursts.append(len(received)))
        sub.start()
        try:
            pub = declare(client, sensor_key("fleet", "sim-0001", Stream.IMU))
            for k in range(30):
                t = T0 + k * 100 * MS
                pub.put(
                    encode_imu(
                        ImuBatch(t + np.arange(10) * 10 * MS, np.zeros((10, 3)), np.zeros((10, 3))),
                        k,
                    )
                )
                time.sleep(0.004)  # 4 ms apart: 120 ms in all
            wait_for(lambda: sum(bursts) == 30, 10.0)
        finally:
            sub.stop()
    if gather_ms:
        assert len(bursts) <= 6  # a burst gathers ~40 ms of packets: about 3
    else:
        assert len(bursts) >= 10  # delivered nearly one by one: about 30


def test_stop_while_a_burst_gathers_delivers_it_and_ends_cleanly() -> None:
    """The subscriber is undeclared during the gather wait: the packets already taken are
    delivered and the thread ends without an error (an error there fails the test run)."""
    from server.ingest.subscriber import IngestSubscriber

    bursts: list[int] = []
    with embedded_router() as (router, zs, endpoint), client_session(endpoint) as client:
        ingest = IngestSettings.model_validate({"gather_ms": 50})
        sub = IngestSubscriber(router, zs, ingest, lambda received: bursts.append(len(received)))
        sub.start()
        pub = declare(client, sensor_key("fleet", "sim-0001", Stream.IMU))
        t = T0 + np.arange(10) * 10 * MS
        pub.put(encode_imu(ImuBatch(t, np.zeros((10, 3)), np.zeros((10, 3))), 0))
        time.sleep(0.02)  # taken by the thread, which now waits for more
        sub.stop()
        assert sub._thread is not None and not sub._thread.is_alive()
    assert bursts == [1]
