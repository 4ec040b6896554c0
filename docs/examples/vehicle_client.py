"""A minimal Slipfleet vehicle client, written from ``docs/protocol.md`` alone.

It needs only ``eclipse-zenoh``, ``msgpack`` and ``numpy`` (no Slipfleet code) and publishes a
fake tractor driving north at 2 m/s with 5 % slip on the left wheel:

* ``<prefix>/<id>/config``          the vehicle config (JSON), once at start
* ``<prefix>/<id>/sensors/gnss``    10 Hz, one epoch per packet
* ``<prefix>/<id>/sensors/imu``     100 Hz, 10 samples per packet (every 100 ms)
* ``<prefix>/<id>/sensors/wheels``  encoder edges of both wheels, one packet per 100 ms

Run it against a server (or its embedded router)::

    python docs/examples/vehicle_client.py --connect tcp/127.0.0.1:7447 \
        --vehicle-id demo-1 --seconds 5
"""

from __future__ import annotations

import argparse
import json
import math
import secrets
import time

import msgpack
import numpy as np
import zenoh

SCHEMA_VERSION = 1
G = 9.80665
TEETH_PER_REV = 120
WHEEL_RADIUS_M = 0.85
SPEED_MPS = 2.0
SLIP_LEFT = 0.05  # the left wheel turns 5 % faster than the ground moves
PACKET_NS = 100_000_000  # 100 ms


def open_client(endpoint: str) -> zenoh.Session:
    """A Zenoh client session to the server's router (no multicast scouting, no shared memory)."""
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps("client"))
    config.insert_json5("connect/endpoints", json.dumps([endpoint]))
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("transport/shared_memory/enabled", "false")
    return zenoh.open(config)


def i64(a: np.ndarray) -> bytes:
    """int64 array as packed little-endian bytes."""
    return np.ascontiguousarray(a, dtype="<i8").tobytes()


def f64(a: np.ndarray) -> bytes:
    """float64 array (row-major) as packed little-endian bytes."""
    return np.ascontiguousarray(a, dtype="<f8").tobytes()


def pack(sensor: str, seq: int, boot: int, body: dict[str, object]) -> bytes:
    return msgpack.packb(
        {"v": SCHEMA_VERSION, "sensor": sensor, "seq": seq, "boot": boot, **body},
        use_bin_type=True,
    )


class FakeTractor:
    """Sensor streams of a tractor driving north at constant speed on flat ground."""

    def __init__(self, start_ns: int) -> None:
        self.start_ns = start_ns
        self.next_edge_ns = [start_ns, start_ns + 3_000_000]  # left, right encoder phase
        self.rng = np.random.default_rng(7)

    def gnss(self, t_ns: int) -> dict[str, object]:
        north_m = SPEED_MPS * (t_ns - self.start_ns) * 1e-9
        return {
            "stamp_ns": t_ns,
            "vel_enu_mps": [0.0, SPEED_MPS + 0.02 * float(self.rng.standard_normal()), 0.0],
            "heading_rad": 0.0,
            "pitch_rad": 0.0,
            "roll_rad": 0.0,
            "lat_deg": 52.0 + north_m / 111_320.0,
            "lon_deg": 5.6,
            "height_m": 10.0,
            "fix": 4,  # RTK fixed
            "vel_std_mps": 0.02,
        }

    def imu(self, t0_ns: int, n: int = 10) -> dict[str, object]:
        stamps = t0_ns + np.arange(n, dtype=np.int64) * 10_000_000
        accel = np.tile([0.0, 0.0, G], (n, 1)) + 0.02 * self.rng.standard_normal((n, 3))
        gyro = 0.002 * self.rng.standard_normal((n, 3))
        return {"stamp_ns": i64(stamps), "accel_mps2": f64(accel), "gyro_radps": f64(gyro)}

    def wheels(self, window_end_ns: int) -> dict[str, object]:
        edges = []
        for wheel, slip in ((0, SLIP_LEFT), (1, 0.0)):
            omega_radps = SPEED_MPS * (1.0 + slip) / WHEEL_RADIUS_M
            period_ns = int(2 * math.pi / (TEETH_PER_REV * omega_radps) * 1e9)
            first = self.next_edge_ns[wheel]
            n = max(0, (window_end_ns - first + period_ns - 1) // period_ns)
            stamps = first + np.arange(n, dtype=np.int64) * period_ns
            self.next_edge_ns[wheel] = first + n * period_ns
            if n:
                edges.append({"wheel": wheel, "stamp_ns": i64(stamps)})
        return {"mode": "edges", "edges": edges}


def run(endpoint: str, vehicle_id: str, seconds: float, prefix: str = "fleet") -> dict[str, int]:
    """Publish ``seconds`` of the fake tractor in real time; return packets sent per stream."""
    sent = {"gnss": 0, "imu": 0, "wheels": 0}
    with open_client(endpoint) as session:
        base = zenoh.KeyExpr(prefix).join(vehicle_id)
        config = {"kind": "wheeled_rear_drive", "encoder": {"teeth_per_rev": TEETH_PER_REV}}
        session.put(
            base.join("config"),
            json.dumps(config).encode(),
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
        pubs = {
            s: session.declare_publisher(
                base.join("sensors").join(s),
                congestion_control=zenoh.CongestionControl.BLOCK,
                reliability=zenoh.Reliability.RELIABLE,
            )
            for s in sent
        }
        now = time.time_ns()
        start_ns = now - now % PACKET_NS
        tractor = FakeTractor(start_ns)
        seq = dict.fromkeys(sent, 0)
        # picked once per start: the server then knows numbers from 0 again are a restart,
        # not duplicates of the previous run's (docs/protocol.md §5)
        boot = secrets.randbits(63)
        for k in range(int(seconds * 1e9) // PACKET_NS):
            window_start = start_ns + k * PACKET_NS
            window_end = window_start + PACKET_NS
            # wait until the 100 ms window is over: a vehicle sends what it has measured
            time.sleep(max(0.0, (window_end - time.time_ns()) / 1e9))
            packets = {
                "imu": tractor.imu(window_start),
                "wheels": tractor.wheels(window_end),
                "gnss": tractor.gnss(window_start),
            }
            for stream, body in packets.items():
                # the stream is complete up to the window's end: the server need not wait (a
                # wheels packet without edges is a heartbeat: the wheels stood still)
                body["until_ns"] = window_end - 1
                pubs[stream].put(pack(stream, seq[stream], boot, body))
                seq[stream] += 1
                sent[stream] += 1
        for pub in pubs.values():
            pub.undeclare()
    return sent


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--connect", default="tcp/127.0.0.1:7447", help="router endpoint")
    parser.add_argument("--vehicle-id", default="demo-1")
    parser.add_argument("--prefix", default="fleet")
    parser.add_argument("--seconds", type=float, default=5.0)
    args = parser.parse_args()
    sent = run(args.connect, args.vehicle_id, args.seconds, args.prefix)
    print(json.dumps(sent))


if __name__ == "__main__":
    main()
