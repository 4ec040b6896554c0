"""Fuzz the decoder and the pipeline with mutated and random packets.

Valid packets of simulated vehicles are mutated (bit flips, truncation, garbage, field deletion
or replacement, type swaps, NaN/±inf and huge values in scalars and packed arrays, timestamp
jumps and shuffles, sequence numbers, keys) or replaced by random bytes. Hypothesis draws the
seed and the mutation rate of each batch; a seeded generator builds the batch, so every failure
replays from the seed hypothesis prints.

* Decoder: every payload either decodes to a packet that respects the protocol's limits or
  raises :class:`DecodeError`; nothing else escapes.
* Pipeline (``session=None``, fed by ``submit``, the real registry with the real ``MdsfFleet``):
  no error is swallowed by the pipeline (its error counters stay 0), no row carries ±inf, stamps
  and flags are sane, every initialised filter state stays finite (checked on the pipeline
  thread after every advance), and every packet is accounted for:
  ``received == accepted + late + duplicate + rejected`` per vehicle and in total.
"""

from __future__ import annotations

import math
import random
import struct
import threading
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from estimator.mdsf import MdsfFleet
from estimator.sim import simulate
from estimator.types import GnssSample
from server.estimation import EstimatorRegistry
from server.ingest import Pipeline
from server.ingest.subscriber import IngestItem
from server.protocol import LIMITS, DecodeError, Packet, Stream, decode, sensor_key
from server.settings import IngestSettings, Settings
from server.tooling.fleet_sim import SimPacket, packetize

pytestmark = pytest.mark.slow

T0 = 1_763_700_000 * 10**9 - (1_763_700_000 * 10**9) % 100_000_000
PREFIX = "fleet"
MAX_PAYLOAD = 64 * 1024
VEHICLES = ("fz-1", "fz-2", "fz-3", "fz-4")

DECODER_BATCHES = 150  # x DECODER_BATCH packets through the decoder alone
DECODER_BATCH = 500
PIPELINE_BATCHES = 125  # x PIPELINE_BATCH packets through decoder and pipeline
PIPELINE_BATCH = 800

_JUMPS_NS = (
    1,
    10**6,
    10**8,
    10**9,
    30 * 10**9,
    600 * 10**9,
    3_600 * 10**9,
    86_400 * 10**9,
    400 * 86_400 * 10**9,
    2**62,
)
_WILD_FLOATS = (
    math.nan,
    math.inf,
    -math.inf,
    1e308,
    -1e308,
    1e-320,
    0.0,
    -0.0,
    101.0,
    1e6,
    -7.0,
)
_WILD_INTS = (0, -1, 1, 2**63 - 1, -(2**63), 2**64 - 1, 2**31, 4, 5, 3, 255)


# ------------------------------------------------------------------------------------ source


@dataclass
class Source:
    """Valid packets of one simulated run, replayable with shifted stamps (like FleetSim)."""

    packets: list[SimPacket]
    period_ns: int

    def encoded(self, index: int, seq: dict[Stream, int]) -> tuple[Stream, bytes, int]:
        loop, i = divmod(index, len(self.packets))
        p = self.packets[i]
        shift = loop * self.period_ns
        payload = p.encode(seq[p.stream], shift)
        seq[p.stream] += 1
        first = p.measurements[0]
        if isinstance(first, GnssSample):
            stamp = first.stamp_ns
        elif len(first.stamp_ns):
            stamp = int(first.stamp_ns[-1])
        else:  # a wheel heartbeat
            assert p.until_ns is not None
            stamp = p.until_ns
        return p.stream, payload, int(stamp) + shift


_SOURCE: Source | None = None


def source() -> Source:
    global _SOURCE
    if _SOURCE is None:
        run = simulate("field_work", seed=5, start_ns=T0, duration_s=60.0)
        pk = packetize(run.sent_in_arrival_order(), run.start_ns)
        _SOURCE = Source(pk, run.end_ns - run.start_ns + 100_000_000)
    return _SOURCE


# ------------------------------------------------------------------------------------ mutations


def _wild_value(rng: random.Random) -> Any:
    kind = rng.randrange(9)
    if kind == 0:
        return rng.choice(_WILD_FLOATS)
    if kind == 1:
        return rng.choice(_WILD_INTS)
    if kind == 2:
        return "".join(rng.choice("abcimuwheelsgnss/\x00é") for _ in range(rng.randrange(12)))
    if kind == 3:
        return rng.randbytes(rng.randrange(0, 64))
    if kind == 4:
        return [rng.choice(_WILD_FLOATS) for _ in range(rng.randrange(5))]
    if kind == 5:
        return {"wheel": rng.choice(_WILD_INTS), "stamp_ns": rng.randbytes(8 * rng.randrange(3))}
    if kind == 6:
        return None
    if kind == 7:
        return rng.random() < 0.5
    return rng.uniform(-1e4, 1e4)


def _mutate_array(rng: random.Random, raw: bytes, name: str) -> bytes:
    if name == "direction":
        d = bytearray(raw)
        if d:
            d[rng.randrange(len(d))] = rng.choice((0, 2, 0x80, 0xFF, 1))
        return bytes(d)
    n = len(raw) // 8
    if n == 0 or len(raw) % 8:
        return raw
    if name == "stamp_ns" or name.endswith("stamp_ns"):
        t = np.frombuffer(raw, "<i8").copy()
        op = rng.randrange(4)
        if op == 0:
            rng_np = np.random.default_rng(rng.randrange(2**32))
            rng_np.shuffle(t)
        elif op == 1:
            with np.errstate(over="ignore"):  # a stamp near the int64 edge wraps: fed as is
                t[rng.randrange(n)] += rng.choice(_JUMPS_NS) * rng.choice((1, -1))
        elif op == 2:
            t = t[::-1].copy()
        else:
            t[:] = t[0]
        return t.astype("<i8").tobytes()
    a = np.frombuffer(raw, "<f8").copy()
    k = rng.randrange(1, min(n, 8) + 1)
    for _ in range(k):
        a[rng.randrange(n)] = rng.choice(_WILD_FLOATS) * rng.choice((1.0, 1e3))
    return a.astype("<f8").tobytes()


def _edge_maps(m: dict[str, Any]) -> list[dict[str, Any]]:
    edges = m.get("edges")
    return [e for e in edges if isinstance(e, dict)] if isinstance(edges, list) else []


def _shift_stamps(m: dict[str, Any], dt: int) -> None:
    def shift_bin(raw: bytes) -> bytes:
        if len(raw) % 8:
            return raw
        t = np.frombuffer(raw, "<i8").astype(object) + dt
        return b"".join(struct.pack("<q", max(min(int(x), 2**63 - 1), -(2**63))) for x in t)

    if isinstance(m.get("stamp_ns"), int):
        m["stamp_ns"] += dt
    elif isinstance(m.get("stamp_ns"), bytes):
        m["stamp_ns"] = shift_bin(m["stamp_ns"])
    for e in _edge_maps(m):
        if isinstance(e.get("stamp_ns"), bytes):
            e["stamp_ns"] = shift_bin(e["stamp_ns"])


def mutate_map(rng: random.Random, payload: bytes) -> bytes:
    """Structural mutations of a valid payload's msgpack map."""
    m: dict[str, Any] = msgpack.unpackb(payload, raw=False)
    for _ in range(rng.choice((1, 1, 1, 2, 3))):
        op = rng.randrange(9)
        keys = list(m)
        if op == 0 and keys:
            del m[rng.choice(keys)]
        elif op == 1 and keys:
            m[rng.choice(keys)] = _wild_value(rng)
        elif op == 2:
            arrays = [k for k, v in m.items() if isinstance(v, bytes)]
            for e in _edge_maps(m):
                if isinstance(e, dict):
                    for k, v in e.items():
                        if isinstance(v, bytes):
                            e[k] = _mutate_array(rng, v, k)
            if arrays:
                k = rng.choice(arrays)
                m[k] = _mutate_array(rng, m[k], k)
        elif op == 3:
            _shift_stamps(m, rng.choice(_JUMPS_NS) * rng.choice((1, -1)))
        elif op == 4:
            m["seq"] = rng.choice((*_WILD_INTS, rng.randrange(0, 10_000)))
        elif op == 5:
            m["v"] = rng.choice((0, 2, "1", 1.0, None, -1))
        elif op == 6:
            m["sensor"] = rng.choice(("gnss", "imu", "wheels", "lidar", 3, b"imu"))
        elif op == 7:
            floats = [k for k, v in m.items() if isinstance(v, float)]
            if floats:
                m[rng.choice(floats)] = rng.choice(_WILD_FLOATS)
            elif isinstance(m.get("vel_enu_mps"), list) and m["vel_enu_mps"]:
                m["vel_enu_mps"][rng.randrange(len(m["vel_enu_mps"]))] = rng.choice(_WILD_FLOATS)
        else:
            arrays = [k for k, v in m.items() if isinstance(v, bytes) and len(v) >= 8]
            if arrays:  # lengths that disagree
                k = rng.choice(arrays)
                m[k] = m[k][: rng.randrange(len(m[k]))]
            m["extra_" + str(rng.randrange(3))] = _wild_value(rng)  # unknown fields: ignored
    try:
        packed: bytes = msgpack.packb(m, use_bin_type=True)
    except (OverflowError, ValueError, TypeError):
        packed = payload[: len(payload) // 2]
    return packed


def mutate_bytes(rng: random.Random, payload: bytes) -> bytes:
    """Byte-level damage: bit flips, truncation, garbage, oversize, random payloads."""
    op = rng.randrange(6)
    b = bytearray(payload)
    if op == 0:
        for _ in range(rng.randrange(1, 9)):
            i = rng.randrange(len(b))
            b[i] ^= 1 << rng.randrange(8)
        return bytes(b)
    if op == 1:
        return bytes(b[: rng.randrange(len(b))])
    if op == 2:
        return bytes(b) + rng.randbytes(rng.randrange(1, 32))
    if op == 3:
        return rng.randbytes(rng.randrange(0, 300))
    if op == 4:
        return bytes(b) * (MAX_PAYLOAD // max(len(b), 1) + 2)
    i = rng.randrange(len(b))
    b[i : i + 4] = rng.randbytes(4)
    return bytes(b)


def mutate_key(rng: random.Random, key: str, vid: str) -> str:
    op = rng.randrange(5)
    if op == 0:
        return key.replace(vid, rng.choice(VEHICLES))  # another vehicle's key
    if op == 1:
        return key.rsplit("/", 1)[0] + "/" + rng.choice(("imu", "gnss", "wheels", "lidar"))
    if op == 2:
        return f"{PREFIX}/{rng.choice(('-bad', 'x' * 70, 'ok'))}/sensors/imu"
    if op == 3:
        return f"{PREFIX}/{vid}/config"
    return f"{PREFIX}/rnd-{rng.randrange(5000)}/sensors/{rng.choice(('imu', 'gnss', 'wheels'))}"


# ------------------------------------------------------------------------------------ feeder


@dataclass
class Feeder:
    """Valid streams of several vehicles, with a share of each batch mutated."""

    index: dict[str, int] = field(default_factory=lambda: dict.fromkeys(VEHICLES, 0))
    seq: dict[str, dict[Stream, int]] = field(
        default_factory=lambda: {v: dict.fromkeys(Stream, 0) for v in VEHICLES}
    )
    newest_ns: int = T0
    kinds: Counter[str] = field(default_factory=Counter)
    sent: list[tuple[str, bytes]] = field(default_factory=list)

    def batch(self, rng: random.Random, n: int, mutation_rate: float) -> list[tuple[str, bytes]]:
        src = source()
        out: list[tuple[str, bytes]] = []
        for _ in range(n):
            vid = rng.choice(VEHICLES)
            stream, payload, stamp = src.encoded(self.index[vid], self.seq[vid])
            self.index[vid] += 1
            self.newest_ns = max(self.newest_ns, stamp)
            key = sensor_key(PREFIX, vid, stream)
            r = rng.random()
            if r >= mutation_rate:
                kind = "valid"
            elif r < mutation_rate * 0.45:
                kind, payload = "map", mutate_map(rng, payload)
            elif r < mutation_rate * 0.75:
                kind, payload = "bytes", mutate_bytes(rng, payload)
            elif r < mutation_rate * 0.85:
                kind, key = "key", mutate_key(rng, key, vid)
                if rng.random() < 0.5:  # new vehicles get bad first packets too
                    payload = mutate_map(rng, payload)
            elif r < mutation_rate * 0.95 and self.sent:
                kind, (key, payload) = "resend", rng.choice(self.sent[-50:])  # dup or late
            else:
                kind, payload = "random", rng.randbytes(rng.randrange(0, 200))
            self.kinds[kind] += 1
            out.append((key, payload))
        if len(out) > 2 and rng.random() < 0.3:  # reordering beyond the lateness window
            i, j = rng.randrange(len(out)), rng.randrange(len(out))
            out[i], out[j] = out[j], out[i]
        self.sent = (self.sent + out)[-200:]
        return out


def decode_checked(key: str, payload: bytes) -> IngestItem:
    """Decode; fail on anything but a sane packet or a DecodeError."""
    try:
        p = decode(key, payload, prefix=PREFIX, max_payload_bytes=MAX_PAYLOAD)
    except DecodeError as exc:
        return exc
    check_packet(p)
    return p


def check_packet(p: Packet) -> None:
    assert LIMITS.min_stamp_ns <= p.first_stamp_ns <= p.last_stamp_ns <= LIMITS.max_stamp_ns
    assert 0 <= p.seq < 2**63 and p.schema_version == 1
    for m in p.measurements:
        if isinstance(m, GnssSample):
            vals = np.array([*m.vel_enu_mps, m.heading_rad, m.pitch_rad, m.roll_rad, m.lat_deg])
        else:
            vals = np.concatenate(
                [np.asarray(getattr(m, f), dtype=float).ravel() for f in _ARRAY_FIELDS[type(m)]]
            )
            t = np.asarray(m.stamp_ns)
            assert t.dtype == np.int64 and t.size and (np.diff(t) >= 0).all()
        assert not np.isinf(vals).any()


_ARRAY_FIELDS: dict[type, tuple[str, ...]] = {}


def _array_fields() -> None:
    from estimator.types import ImuBatch, WheelEdges, WheelSpeeds

    _ARRAY_FIELDS.update(
        {
            ImuBatch: ("accel_mps2", "gyro_radps"),
            WheelSpeeds: ("omega_radps",),
            WheelEdges: ("stamp_ns",),
        }
    )


_array_fields()


# ------------------------------------------------------------------------------------ tests


@settings(
    max_examples=DECODER_BATCHES,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow],
)
@given(seed=st.integers(0, 2**32 - 1), rate=st.floats(0.3, 1.0))
def test_decoder_survives_mutated_packets(seed: int, rate: float) -> None:
    rng = random.Random(seed)
    feeder = Feeder()
    feeder.index = {v: rng.randrange(2000) for v in VEHICLES}
    for key, payload in feeder.batch(rng, DECODER_BATCH, rate):
        decode_checked(key, payload)
    DECODER_TOTALS.update(feeder.kinds)


DECODER_TOTALS: Counter[str] = Counter()


class StateCheckSink:
    """Runs on the pipeline thread after every advance: rows and filter states must be sane."""

    def __init__(self, fleet: Callable[[], MdsfFleet | None]) -> None:
        self._fleet = fleet
        self.problems: list[str] = []
        self.rows = 0
        self.checks = 0
        self.last_stamp: dict[str, int] = {}
        self.lock = threading.Lock()

    def on_estimates(self, batch: list[tuple[str, np.ndarray]]) -> None:
        for vid, rows in batch:
            self.rows += len(rows)
            stamps = rows["stamp_ns"]
            if not ((stamps > LIMITS.min_stamp_ns) & (stamps < LIMITS.max_stamp_ns)).all():
                self.problems.append(f"{vid}: stamp out of range")
            if len(stamps) > 1 and not (np.diff(stamps) > 0).all():
                self.problems.append(f"{vid}: stamps not increasing within a batch")
            if (rows["flags"] < 0).any():
                self.problems.append(f"{vid}: negative flags")
            for name in rows.dtype.names or ():
                col = rows[name]
                if col.dtype.kind == "f" and np.isinf(col).any():
                    self.problems.append(f"{vid}: {name} is infinite")
        fleet = self._fleet()
        if fleet is not None:
            self.checks += 1
            eng = fleet.engine
            live = eng.initialized[: eng.x.shape[0]]
            if not np.isfinite(eng.x[live]).all() or not np.isfinite(eng.P[live]).all():
                self.problems.append("a filter state is not finite")


def test_pipeline_survives_mutated_packets() -> None:
    registry = EstimatorRegistry()
    feeder = Feeder()
    fleet_ref: list[MdsfFleet] = []

    def fleet() -> MdsfFleet | None:
        if not fleet_ref and registry.vehicle_ids():  # every fuzz vehicle runs MDSF
            est = registry.estimator("mdsf")
            assert isinstance(est, MdsfFleet)
            fleet_ref.append(est)
        return fleet_ref[0] if fleet_ref else None

    sink = StateCheckSink(fleet)
    settings_ = Settings(
        ingest=IngestSettings(lateness_ms=150, process_interval_ms=5, max_payload_bytes=MAX_PAYLOAD)
    )
    pipe = Pipeline(settings_, None, registry, [sink], wall_clock_ns=lambda: feeder.newest_ns)
    pipe.start()
    submitted = 0
    outcomes: Counter[str] = Counter()

    @settings(
        max_examples=PIPELINE_BATCHES,
        deadline=None,
        derandomize=True,
        database=None,
        suppress_health_check=[HealthCheck.too_slow],
    )
    @given(seed=st.integers(0, 2**32 - 1), rate=st.floats(0.05, 0.6))
    def feed(seed: int, rate: float) -> None:
        nonlocal submitted
        rng = random.Random(seed)
        items = [decode_checked(k, p) for k, p in feeder.batch(rng, PIPELINE_BATCH, rate)]
        for it in items:
            outcomes["rejected_by_decoder" if isinstance(it, DecodeError) else "decoded"] += 1
        for i in range(0, len(items), 100):
            pipe.submit(items[i : i + 100])
        submitted += len(items)

    try:
        feed()
    finally:
        pipe.stop(timeout_s=60)
    stats = pipe.stats()
    snap = pipe.counters_snapshot()
    totals = Counter[str]()
    for vid, c in snap.items():
        assert c["received"] == c["accepted"] + c["late"] + c["duplicate"] + c["rejected"], vid
        totals.update(c)
    print(
        f"\nfuzz decoder-only: {sum(DECODER_TOTALS.values())} packets {dict(DECODER_TOTALS)}"
        f"\nfuzz pipeline: {submitted} packets {dict(feeder.kinds)}, {dict(outcomes)}"
        f"\n  received {totals['received']} = accepted {totals['accepted']} + late "
        f"{totals['late']} + duplicate {totals['duplicate']} + rejected {totals['rejected']}"
        f"; lost_by_seq_gap {totals['lost_by_seq_gap']}, seq_restarts {totals['seq_restarts']}"
        f", clock_reanchors {totals['clock_reanchors']}"
        f"\n  rejected by reason: "
        f"{ {k[9:]: v for k, v in sorted(totals.items()) if k.startswith('rejected_')} }"
        f"\n  rows {sink.rows}, state checks {sink.checks}, pipeline stats {stats}"
    )
    assert totals["received"] == submitted, "every packet is counted once"
    assert submitted >= 100_000
    assert stats["pipeline_errors"] == 0 and stats["estimator_errors"] == 0, stats
    assert stats["sink_errors"] == 0 and stats["dropped_not_running"] == 0, stats
    assert sink.problems == [], sink.problems[:10]
    assert sink.rows > 1000 and sink.checks > 10, "the estimators really ran"
    assert totals["accepted"] > submitted // 3
    f = fleet()
    assert f is not None
    for vid in VEHICLES:
        counts = f.counters(vid)
        assert counts["ticks"] > 0, (vid, counts)
