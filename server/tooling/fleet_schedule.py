"""Publish many simulated vehicles for a small fraction of a core: encode once, patch stamps.

:class:`server.tooling.fleet_sim.FleetSim` used to shift every measurement's stamps (new dataclass
objects), encode it with msgpack and pick the next packet from a heap, per packet, one thread
per scenario group: ≈ 100 µs of CPU a packet at 100 vehicles, more than the 2-core machine has
at 1,000. Here the work per packet in the sending loop is one ``Publisher.put``; everything
else is done once or in bulk (``slipfleet bench publisher``: 6–10 µs of CPU a packet at
1,000–3,000 vehicles, Zenoh's own threads included):

* **Encode once.** :class:`EncodedDrive` encodes each packet of a drive (a
  :func:`server.tooling.fleet_sim.packetize` list) once, with ``seq = 0``, into one byte buffer, and
  records where the sequence number and every timestamp sit. The stamps are the only bytes
  that change between vehicles and loops: IMU, wheel-edge and wheel-speed stamps are
  little-endian int64 arrays (msgpack ``bin``), the GNSS stamp a msgpack ``uint 64`` (``0xcf``
  + 8 bytes big-endian: fixed width for any stamp after 1970 + 4.3 s).
* **Render per window.** Every :data:`WINDOW_NS` of wall time, the packets of every vehicle due
  in the next window are selected (``searchsorted`` per drive), copied out of the templates,
  stamp-patched (numpy, one add per byte alignment), given their ``seq`` (packed as msgpack
  packs an int, shortest form) and sorted by due time into one merged schedule of ready
  payloads. Each payload is byte for byte what :func:`server.tooling.fleet_sim.encode_packet` makes
  of the shifted measurements (a test checks it over several loops), so the wire format is
  unchanged.
* **Send.** One thread sleeps until the next packet is due (at least :data:`MIN_WAKE_NS`
  apart, so thousands of vehicles cost a few hundred wake-ups a second, not one per packet),
  then puts every packet that is due, in due order, each on its vehicle's pre-declared
  publisher for that stream.

Time: a vehicle ``v`` with phase ``φ_v`` (its offset within the 100 ms tick, spreading vehicles
over it) publishes packet ``p`` of loop ``L`` at schedule time ``a_p + φ_v + L·T_v`` (``a_p``:
when the simulated vehicle sends it, after the drive start — a batch once its last sample is
in; ``T_v`` the loop period), at wall time ``that / rate`` after the start; its stamps are
shifted by ``shift_v + L·T_v``. Sequence numbers count per (vehicle, stream) from 0 across
loops. Memory: the drives, not the vehicles (≈4 MB per 5-minute drive; vehicles share them).
"""

from __future__ import annotations

import bisect
import itertools
import math
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import msgpack
import numpy as np

from estimator.base import Measurement
from estimator.types import GnssSample
from server.protocol.keys import Stream

__all__ = [
    "MIN_WAKE_NS",
    "STREAMS",
    "WINDOW_NS",
    "DrivePacket",
    "EncodedDrive",
    "ScheduleStats",
    "ScheduledVehicle",
    "Window",
    "lateness_quantiles",
    "publish_schedule",
    "render",
    "weighted_quantiles",
]

#: Shortest sleep between two sending rounds, ns (every packet due by then goes out together):
#: a wake-up costs ~50-100 µs of CPU on a busy 2-core host, so small fleets send a few packets
#: per round rather than one; 4 ms is well inside the 100 ms batching and 150 ms reorder window.
MIN_WAKE_NS = 4_000_000
#: Wall time rendered at once (packets selected, copied, stamp-patched, sorted), ns.
WINDOW_NS = 100_000_000

#: a simulated vehicle's streams (a tractor's first three; a steered four-wheel vehicle's
#: GNSS, IMU, steering and wheel speeds; a crawler's GNSS, IMU, odometer and sprockets)
STREAMS: tuple[Stream, ...] = (
    Stream.GNSS,
    Stream.IMU,
    Stream.WHEELS,
    Stream.STEERING,
    Stream.WHEEL_SPEEDS4,
    Stream.ODOMETER,
    Stream.SPROCKETS,
)
_STREAM_CODE = {s: i for i, s in enumerate(STREAMS)}
_STAMP_KEY = msgpack.packb("stamp_ns")
_SEQ_KEY = msgpack.packb("seq")
_UNTIL_KEY = msgpack.packb("until_ns")


@dataclass(frozen=True, slots=True)
class _Template:
    """Where the variable bytes of one encoded packet sit (offsets within the packet)."""

    seq_at: int  # the placeholder ``seq = 0`` byte (0x00)
    le_stamps: list[int]  # start of each little-endian int64 stamp
    be_stamps: list[int]  # start of each big-endian (msgpack uint 64) stamp


def _locate(
    payload: bytes, stamp_arrays: Sequence[np.ndarray], until_ns: int | None = None
) -> _Template:
    """Find the ``seq`` placeholder and every stamp in an encoded packet, and check them.

    The stamps follow each ``"stamp_ns"`` key in encoding order (one per measurement), then
    ``"until_ns"`` when given (a msgpack uint 64, patched like the GNSS stamp); each located
    value is compared with the stamp it must hold, so a codec change that moves them fails
    loudly here instead of publishing garbage.
    """
    seq_key = payload.find(_SEQ_KEY)
    if seq_key < 0 or payload[seq_key + len(_SEQ_KEY)] != 0:
        raise ValueError("encoded packet has no 'seq': 0 where expected")
    le: list[int] = []
    be: list[int] = []
    pos = 0
    for stamps in stamp_arrays:
        k = payload.find(_STAMP_KEY, pos)
        if k < 0:
            raise ValueError("encoded packet has fewer stamp fields than measurements")
        at = k + len(_STAMP_KEY)
        tag = payload[at]
        if stamps.ndim == 0:  # GNSS: msgpack uint 64
            if tag != 0xCF:
                raise ValueError(f"GNSS stamp packed as 0x{tag:02x}, not uint 64")
            start, n = at + 1, 1
            got = np.frombuffer(payload, ">i8", 1, start)
            be.append(start)
        else:
            width = {0xC4: 1, 0xC5: 2, 0xC6: 4}.get(tag)
            if width is None:
                raise ValueError(f"stamp array packed as 0x{tag:02x}, not bin")
            start = at + 1 + width
            n = int.from_bytes(payload[at + 1 : start], "big") // 8
            got = np.frombuffer(payload, "<i8", n, start)
            le.extend(range(start, start + 8 * n, 8))
        if n != stamps.size or not np.array_equal(got, stamps.reshape(-1)):
            raise ValueError("located stamps differ from the measurement's")
        pos = start + 8 * n
    if until_ns is not None:
        k = payload.find(_UNTIL_KEY, pos)
        at = k + len(_UNTIL_KEY)
        if k < 0 or payload[at] != 0xCF:
            raise ValueError("encoded packet has no 'until_ns' packed as uint 64")
        if int.from_bytes(payload[at + 1 : at + 9], "big") != until_ns:
            raise ValueError("located until_ns differs from the packet's")
        be.append(at + 1)
    return _Template(seq_key + len(_SEQ_KEY), le, be)


class DrivePacket(Protocol):
    """What the schedule reads of a packet of a drive (a
    :class:`server.tooling.fleet_sim.SimPacket`): when it arrives, on which stream, the
    measurements it holds and its wire bytes as sequence number ``seq``."""

    @property
    def arrival_offset_ns(self) -> int: ...
    @property
    def stream(self) -> Stream: ...
    @property
    def measurements(self) -> tuple[Measurement, ...]: ...
    @property
    def until_ns(self) -> int | None: ...
    def encode(self, seq: int, shift_ns: int = 0, boot: int | None = None) -> bytes: ...


class EncodedDrive:
    """The packets of one drive, encoded once (``seq = 0``), with what changes located.

    Parameters
    ----------
    packets : list of DrivePacket
        In arrival order (:func:`server.tooling.fleet_sim.packetize`).
    period_ns : int
        Sensor-time length of one loop of the drive (last arrival + a tick).
    boot : int, optional
        The sender's boot id every packet carries (None: not sent).

    Attributes (``P`` packets)
    --------------------------
    arrival_ns : (P,) int64, non-decreasing — arrival after the drive start.
    stream : (P,) int8 — index into :data:`STREAMS`.
    stream_pos : (P,) int64 — number of earlier packets of the same stream (``seq`` in loop 0).
    stream_count : (len(STREAMS),) int64 — packets per stream in one loop.
    buf : (B,) uint8 — the packets back to back; ``off`` (P + 1,) their bounds.
    seq_at : (P,) int64 — offset of the ``seq`` byte within the packet.
    le_pos, be_pos : int64 — stamp offsets within ``buf``; ``le_off``, ``be_off`` (P + 1,)
        index them per packet.
    """

    def __init__(
        self, packets: Sequence[DrivePacket], period_ns: int, boot: int | None = None
    ) -> None:
        n = len(packets)
        self.period_ns = int(period_ns)
        self.arrival_ns = np.empty(n, np.int64)
        self.stream = np.empty(n, np.int8)
        self.seq_at = np.empty(n, np.int64)
        self.off = np.zeros(n + 1, np.int64)
        self.le_off = np.zeros(n + 1, np.int64)
        self.be_off = np.zeros(n + 1, np.int64)
        chunks: list[bytes] = []
        le: list[int] = []
        be: list[int] = []
        size = 0
        for i, p in enumerate(packets):
            payload = p.encode(0, boot=boot)  # the header's boot id is the same for every loop
            stamps = [
                np.asarray(int(m.stamp_ns), np.int64)
                if isinstance(m, GnssSample)
                else np.asarray(m.stamp_ns, np.int64)
                for m in p.measurements
            ]
            stamps = [t for t in stamps if t.size]  # a wheel without edges has no entry
            t = _locate(payload, stamps, p.until_ns)
            self.arrival_ns[i] = p.arrival_offset_ns
            self.stream[i] = _STREAM_CODE[p.stream]
            self.seq_at[i] = t.seq_at
            le.extend(size + x for x in t.le_stamps)
            be.extend(size + x for x in t.be_stamps)
            chunks.append(payload)
            size += len(payload)
            self.off[i + 1] = size
            self.le_off[i + 1] = len(le)
            self.be_off[i + 1] = len(be)
        if n and np.any(np.diff(self.arrival_ns) < 0):
            raise ValueError("packets must be in arrival order")
        self.buf = np.frombuffer(b"".join(chunks), np.uint8)
        self.le_pos = np.asarray(le, np.int64)
        self.be_pos = np.asarray(be, np.int64)
        self.stream_count = np.bincount(self.stream, minlength=len(STREAMS)).astype(np.int64)
        self.stream_pos = np.empty(n, np.int64)
        for s in range(len(STREAMS)):
            sel = self.stream == s
            self.stream_pos[sel] = np.arange(int(sel.sum()), dtype=np.int64)

    def __len__(self) -> int:
        return len(self.arrival_ns)


@dataclass(frozen=True, slots=True)
class ScheduledVehicle:
    """One vehicle of a schedule: which drive it plays and how it is placed in time.

    ``phase_ns``: schedule-time offset of its loop 0 (spreads vehicles over the tick);
    ``shift_ns``: added to the drive's stamps in loop 0 (``L·period`` more in loop ``L``);
    ``publishers``: one per :data:`STREAMS` entry (anything with ``put(bytes)``).
    """

    drive: int
    phase_ns: int
    shift_ns: int
    publishers: tuple[Callable[[bytes], object], ...]


class _Fleet:
    """The vehicles as arrays, and the drives concatenated (global offsets)."""

    def __init__(self, drives: Sequence[EncodedDrive], vehicles: Sequence[ScheduledVehicle]):
        self.drives = list(drives)
        self.drive = np.array([v.drive for v in vehicles], np.int64)
        self.phase = np.array([v.phase_ns for v in vehicles], np.int64)
        self.shift = np.array([v.shift_ns for v in vehicles], np.int64)
        self.period = np.array([drives[d].period_ns for d in self.drive], np.int64)
        self.puts = [pub for v in vehicles for pub in v.publishers]  # vehicle * n_streams + s
        # drives back to back: packet g of the fleet's packet table
        self.pkt_base = np.cumsum([0] + [len(d) for d in drives])[:-1].astype(np.int64)
        byte_base = np.cumsum([0] + [d.buf.size for d in drives])[:-1]
        le_base = np.cumsum([0] + [d.le_pos.size for d in drives])[:-1]
        be_base = np.cumsum([0] + [d.be_pos.size for d in drives])[:-1]
        cat = np.concatenate
        self.arrival = cat([d.arrival_ns for d in drives])
        self.stream = cat([d.stream for d in drives]).astype(np.int64)
        self.stream_pos = cat([d.stream_pos for d in drives])
        self.seq_at = cat([d.seq_at for d in drives])
        self.off = cat([d.off[:-1] + b for d, b in zip(drives, byte_base, strict=True)])
        self.size = cat([np.diff(d.off) for d in drives])
        self.view = memoryview(cat([d.buf for d in drives]).tobytes())
        self.le_pos = cat([d.le_pos + b for d, b in zip(drives, byte_base, strict=True)])
        self.be_pos = cat([d.be_pos + b for d, b in zip(drives, byte_base, strict=True)])
        self.le_first = cat([d.le_off[:-1] + b for d, b in zip(drives, le_base, strict=True)])
        self.le_n = cat([np.diff(d.le_off) for d in drives])
        self.be_first = cat([d.be_off[:-1] + b for d, b in zip(drives, be_base, strict=True)])
        self.be_n = cat([np.diff(d.be_off) for d in drives])
        self.stream_count = np.stack([d.stream_count for d in drives])  # (drives, len(STREAMS))
        self.last_arrival = np.array(
            [int(d.arrival_ns[-1]) if len(d) else -1 for d in drives], np.int64
        )


def _expand(first: np.ndarray, count: np.ndarray) -> np.ndarray:
    """``concatenate([arange(f, f + c) for f, c in zip(first, count)])``, vectorised."""
    total = int(count.sum())
    if total == 0:
        return np.zeros(0, np.int64)
    starts = np.cumsum(count) - count
    return np.repeat(first - starts, count) + np.arange(total, dtype=np.int64)


@dataclass(slots=True)
class Window:
    """Rendered packets of one window, in due order, ready to ``put``."""

    due_ns: list[int]  # schedule time (sensor ns after the start)
    calls: list[Callable[[bytes], object]]  # the vehicle's publisher for the packet's stream
    payloads: list[bytes]
    stream: np.ndarray  # (n,) index into STREAMS
    bounds: list[int]  # packet k had bytes [bounds[k], bounds[k + 1]) of the window


def render(fleet: _Fleet, t0_ns: int, t1_ns: int, loop: bool) -> Window:
    """Every packet with schedule time in ``[t0_ns, t1_ns)``, patched, sorted by due time.

    ``t1_ns - t0_ns`` must not exceed the shortest period (a vehicle then touches at most two
    loops of its drive in the window).
    """
    veh, pkt, lps, due = _due_packets(fleet, t0_ns, t1_ns, loop)
    data, bounds = _copy_templates(fleet, pkt)
    total = int(bounds[-1])
    _shift_stamps(fleet, data, total, bounds, veh, pkt, lps)
    stream = fleet.stream[pkt]
    seq = lps * fleet.stream_count[fleet.drive[veh], stream] + fleet.stream_pos[pkt]
    data, bounds = _insert_seq(data[:total], bounds, bounds[:-1] + fleet.seq_at[pkt], seq)
    blob = data.tobytes()
    bl = bounds.tolist()
    return Window(
        due_ns=due.tolist(),
        calls=list(map(fleet.puts.__getitem__, (veh * len(STREAMS) + stream).tolist())),
        payloads=[blob[x:y] for x, y in itertools.pairwise(bl)],
        stream=stream.astype(np.intp),
        bounds=bl,
    )


def _due_packets(
    fleet: _Fleet, t0_ns: int, t1_ns: int, loop: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(vehicle, fleet packet, loop, due time) of every packet due in ``[t0_ns, t1_ns)``, in
    due order."""
    veh_parts, pkt_parts, loop_parts = [], [], []
    rel0 = t0_ns - fleet.phase  # window in each vehicle's loop-0 time
    base_loop = np.maximum(rel0 // fleet.period, 0)
    for dl in (0, 1):
        lp = base_loop + dl
        if not loop:
            lp = np.where(lp == 0, 0, -1)
        lo = rel0 - lp * fleet.period
        first, count = _packets_in(fleet, lp >= 0, lo, lo + (t1_ns - t0_ns))
        veh_parts.append(np.repeat(np.arange(len(lp), dtype=np.int64), count))
        pkt_parts.append(_expand(first, count))
        loop_parts.append(np.repeat(lp, count))
    veh = np.concatenate(veh_parts)
    pkt = np.concatenate(pkt_parts)
    lps = np.concatenate(loop_parts)
    due = fleet.arrival[pkt] + fleet.phase[veh] + lps * fleet.period[veh]
    order = np.argsort(due, kind="stable")
    return veh[order], pkt[order], lps[order], due[order]


def _packets_in(
    fleet: _Fleet, ok: np.ndarray, lo: np.ndarray, hi: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per vehicle, the first fleet packet arriving in ``[lo, hi)`` of its drive and how many
    do (none where not ``ok``)."""
    first = np.zeros(len(ok), np.int64)
    count = np.zeros(len(ok), np.int64)
    for d, drive in enumerate(fleet.drives):
        sel = ok & (fleet.drive == d)
        if not sel.any():
            continue
        i0 = np.searchsorted(drive.arrival_ns, lo[sel], "left")
        i1 = np.searchsorted(drive.arrival_ns, hi[sel], "left")
        first[sel] = fleet.pkt_base[d] + i0
        count[sel] = i1 - i0
    return first, count


def _copy_templates(fleet: _Fleet, pkt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The templates of packets ``pkt`` back to back (8 spare bytes for the unaligned views),
    and their bounds."""
    size = fleet.size[pkt]
    bounds = np.zeros(len(pkt) + 1, np.int64)
    np.cumsum(size, out=bounds[1:])
    # copied by slices (memcpy per packet) rather than by a per-byte index (8 B of index per
    # byte: several times slower at a few MB per window)
    src = fleet.view
    starts = fleet.off[pkt]
    joined = bytearray().join(
        [src[x:y] for x, y in zip(starts.tolist(), (starts + size).tolist(), strict=True)]
    )
    joined.extend(bytes(8))
    return np.frombuffer(joined, np.uint8), bounds


def _shift_stamps(
    fleet: _Fleet,
    data: np.ndarray,
    total: int,
    bounds: np.ndarray,
    veh: np.ndarray,
    pkt: np.ndarray,
    lps: np.ndarray,
) -> None:
    """Add each packet's vehicle shift for its loop to every stamp it holds, in ``data``."""
    # stamps: template offset -> offset in data, plus the vehicle's shift for that loop
    delta = fleet.shift[veh] + lps * fleet.period[veh]
    rebase = bounds[:-1] - fleet.off[pkt]
    for positions, first_idx, n, dtype in (
        (fleet.le_pos, fleet.le_first, fleet.le_n, "<i8"),
        (fleet.be_pos, fleet.be_first, fleet.be_n, ">i8"),
    ):
        cnt = n[pkt]
        at = positions[_expand(first_idx[pkt], cnt)] + np.repeat(rebase, cnt)
        add = np.repeat(delta, cnt)
        for a in range(8):  # one int64 view per byte alignment of the stamps
            sel = (at & 7) == a
            if sel.any():
                view = data[a : a + 8 * ((total + 8 - a) // 8)].view(dtype)
                view[(at[sel] - a) >> 3] += add[sel]


def _insert_seq(
    data: np.ndarray, bounds: np.ndarray, seq_at: np.ndarray, seq: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Replace each packet's placeholder ``seq`` byte (0x00 at ``seq_at``) by ``seq`` packed as
    msgpack packs a non-negative int (shortest form: fixint, then ``uint 8/16/32/64``).

    Returns the new bytes and packet bounds.
    """
    data[seq_at] = np.where(seq < 0x80, seq, 0).astype(np.uint8)
    extra = np.zeros(len(seq), np.int64)
    at_parts, val_parts = [], []
    for lo, hi, tag, fmt in (
        (0x80, 0x100, 0xCC, ">u1"),
        (0x100, 0x1_0000, 0xCD, ">u2"),
        (0x1_0000, 0x1_0000_0000, 0xCE, ">u4"),
        (0x1_0000_0000, 1 << 63, 0xCF, ">u8"),
    ):
        sel = (seq >= lo) & (seq < hi)
        if not sel.any():
            continue
        width = np.dtype(fmt).itemsize
        data[seq_at[sel]] = tag
        extra[sel] = width
        at_parts.append(np.repeat(seq_at[sel] + 1, width))
        val_parts.append(seq[sel].astype(fmt).view(np.uint8))
    if not at_parts:
        return data, bounds
    at = np.concatenate(at_parts)
    order = np.argsort(at, kind="stable")  # packets in order, each one's bytes in order
    data = np.insert(data, at[order], np.concatenate(val_parts)[order])
    grown = bounds.copy()
    grown[1:] += np.cumsum(extra)
    return data, grown


@dataclass(slots=True)
class ScheduleStats:
    """What :func:`publish_schedule` sent (updated after every sending round)."""

    packets: list[int]  # per :data:`STREAMS` entry
    payload_bytes: int = 0
    loops: int = 0
    max_behind_ms: float = 0.0
    #: per sending round (with ``keep_lateness``): (``perf_counter_ns`` when it started, ms its
    #: first — earliest due — packet was late, packets sent)
    rounds: list[tuple[int, float, int]] | None = None
    #: packets sent, by how late their round's first packet was, in whole ms rounded up (an
    #: upper bound for the round's other packets): ``{ms: packets}``
    late_packets: dict[int, int] = field(default_factory=dict)

    @property
    def total(self) -> int:
        return sum(self.packets)

    def count_round(self, win: Window, k: int, j: int, wall_ns: int, behind_ms: float) -> None:
        """Count the sending round of ``win``'s packets ``k:j``, started at ``wall_ns`` with
        its first packet ``behind_ms`` late."""
        for s, n in enumerate(np.bincount(win.stream[k:j], minlength=len(STREAMS)).tolist()):
            self.packets[s] += n
        self.payload_bytes += win.bounds[j] - win.bounds[k]
        late_ms = max(0, math.ceil(behind_ms))
        self.late_packets[late_ms] = self.late_packets.get(late_ms, 0) + j - k
        if self.rounds is not None:
            self.rounds.append((wall_ns, behind_ms, j - k))


def weighted_quantiles(
    values: Sequence[float], weights: Sequence[int], qs: Sequence[float]
) -> list[float] | None:
    """The ``qs`` quantiles of ``values``, each counted ``weights`` times (a round's lateness
    once per packet it sent); None when nothing is counted."""
    w = np.asarray(weights, dtype=np.int64)
    kept = w > 0
    if not kept.any():
        return None
    v = np.asarray(values, dtype=np.float64)[kept]
    order = np.argsort(v, kind="stable")
    v, cum = v[order], np.cumsum(w[kept][order])
    at = np.minimum(np.searchsorted(cum, np.asarray(qs) * cum[-1]), v.size - 1)
    return [float(x) for x in v[at]]


def lateness_quantiles(late_packets: Mapping[int, int], qs: Sequence[float]) -> list[int | None]:
    """The ``qs`` quantiles (ms, rounded up) of a :attr:`ScheduleStats.late_packets` count;
    None each when it counts no packet."""
    q = weighted_quantiles(list(late_packets), list(late_packets.values()), qs)
    return [None] * len(qs) if q is None else [round(x) for x in q]


def publish_schedule(
    drives: Sequence[EncodedDrive],
    vehicles: Sequence[ScheduledVehicle],
    *,
    rate: float = 1.0,
    loop: bool = False,
    duration_s: float | None = None,
    stop: threading.Event | None = None,
    on_round: Callable[[ScheduleStats], None] | None = None,
    keep_lateness: bool = False,
    window_ns: int = WINDOW_NS,
    min_wake_ns: int = MIN_WAKE_NS,
    stamp_clock_ns: Callable[[], int] | None = None,
) -> ScheduleStats:
    """Publish ``vehicles`` in real time (``rate`` times faster) until the drives end (no
    ``loop``), ``duration_s`` passes or ``stop`` is set; see the module docstring.

    ``on_round`` is called after every sending round (progress); with ``keep_lateness`` each
    round's start, lateness and size are kept (``rounds``) for a distribution.

    With ``stamp_clock_ns`` the vehicles' ``shift_ns`` are relative, and that clock's reading
    is added to them at the moment the schedule's time starts, after the fleet's arrays are
    built: a packet then carries the stamps of a vehicle that sends it when it is due, not
    stamps older by the set-up's time.
    """
    if rate <= 0:
        raise ValueError("rate must be > 0")
    stop = stop or threading.Event()
    stats = ScheduleStats([0] * len(STREAMS), rounds=[] if keep_lateness else None)
    if not vehicles:
        return stats
    fleet = _Fleet(drives, vehicles)
    span = _window_span(fleet, window_ns, rate)
    if span is None:
        return stats
    if stamp_clock_ns is not None:
        fleet.shift = fleet.shift + stamp_clock_ns()
    wall0 = time.perf_counter_ns()
    end_wall = None if duration_s is None else wall0 + int(duration_s * 1e9)
    pacing = _Pacing(wall0, end_wall, rate, 1.0 / rate, min_wake_ns, stop)
    last_due = _send_windows(pacing, _Windows(fleet, span, loop), stats, on_round)
    if loop and last_due >= 0:
        stats.loops = max(0, int(((last_due - fleet.phase) // fleet.period).max()))
    return stats


def _window_span(fleet: _Fleet, window_ns: int, rate: float) -> int | None:
    """Schedule ns per rendered window: ``window_ns`` of wall time, at most the shortest period
    of a vehicle whose drive has packets; None when no drive has any."""
    periods = fleet.period[fleet.last_arrival[fleet.drive] >= 0]
    if periods.size == 0:
        return None
    return max(1, min(int(window_ns * rate), int(periods.min())))


def _send_windows(
    pacing: _Pacing,
    windows: _Windows,
    stats: ScheduleStats,
    on_round: Callable[[ScheduleStats], None] | None,
) -> int:
    """Send the windows' packets as they fall due, until the drives end, the run's end or
    stop; the schedule time of the last packet sent (-1: none)."""
    wall0, end_wall = pacing.wall0, pacing.end_wall
    last_due = -1
    while not pacing.stop.is_set():
        if not windows.turn():
            break
        cur, k = windows.cur, windows.k
        if cur is None or k == len(cur.due_ns):
            continue  # an empty window
        now = time.perf_counter_ns() - wall0
        due_wall = int(cur.due_ns[k] * pacing.inv_rate)
        if end_wall is not None and wall0 + due_wall > end_wall:
            break
        now = _wait_for(pacing, due_wall, now)
        j = _send_due(pacing, cur, k, due_wall, now, stats)
        if j == k:
            continue  # woke up early (the end of the run, or stop)
        last_due = cur.due_ns[j - 1]
        windows.k = j
        if on_round is not None:
            on_round(stats)
        windows.render_ahead()
    return last_due


@dataclass(frozen=True, slots=True)
class _Pacing:
    """The wall clock of a :func:`publish_schedule` run: its start and end (perf counter ns),
    the schedule's rate, the shortest wake-up and the stop event."""

    wall0: int
    end_wall: int | None
    rate: float
    inv_rate: float
    min_wake_ns: int
    stop: threading.Event


class _Windows:
    """The window being sent (``cur``, next packet ``k``) and the one rendered ahead of it."""

    def __init__(self, fleet: _Fleet, span: int, loop: bool) -> None:
        self.fleet, self.span, self.loop = fleet, span, loop
        # the last schedule time any packet has (no loop)
        self.end_sched = int((fleet.last_arrival[fleet.drive] + fleet.phase).max()) + 1
        self.nxt: Window | None = render(fleet, 0, span, loop)
        self.t_next = span
        self.cur: Window | None = None
        self.k = 0

    def turn(self) -> bool:
        """Make the next window current once this one is sent; False when the drives are over."""
        if self.cur is not None and self.k < len(self.cur.due_ns):
            return True
        if self.nxt is None:
            if not self.loop and self.t_next >= self.end_sched:
                return False
            self._render_next()
        self.cur, self.nxt = self.nxt, None
        self.k = 0
        return True

    def render_ahead(self) -> None:
        """Render the next window ahead of time, if there is one and it is not yet rendered."""
        if self.nxt is None and (self.loop or self.t_next < self.end_sched):
            self._render_next()

    def _render_next(self) -> None:
        """Render the window starting at ``t_next`` and move ``t_next`` past it."""
        self.nxt = render(self.fleet, self.t_next, self.t_next + self.span, self.loop)
        self.t_next += self.span


def _wait_for(pacing: _Pacing, due_wall: int, now: int) -> int:
    """Sleep until ``due_wall`` (wall ns after the start; at least the shortest wake-up, never
    past the end) if it is ahead of ``now``; the wall ns after the start then."""
    if due_wall <= now:
        return now
    wait_ns = max(due_wall - now, pacing.min_wake_ns)
    if pacing.end_wall is not None:
        wait_ns = max(0, min(wait_ns, pacing.end_wall - pacing.wall0 - now))
    # long waits on the stop event, so that a stop ends them at once
    (pacing.stop.wait if wait_ns > 50_000_000 else time.sleep)(wait_ns / 1e9)
    return time.perf_counter_ns() - pacing.wall0


def _send_due(
    pacing: _Pacing, cur: Window, k: int, due_wall: int, now: int, stats: ScheduleStats
) -> int:
    """Put every packet of ``cur`` from ``k`` due by ``now``, in due order, and count the
    round; the index after the last one sent (``k``: none)."""
    behind = (now - due_wall) / 1e6
    if behind > stats.max_behind_ms:
        stats.max_behind_ms = behind
    limit = now if pacing.end_wall is None else min(now, pacing.end_wall - pacing.wall0)
    j = bisect.bisect_right(cur.due_ns, limit * pacing.rate, k)
    if j == k:
        return k
    for put, payload in zip(cur.calls[k:j], cur.payloads[k:j], strict=True):
        put(payload)
    stats.count_round(cur, k, j, pacing.wall0 + now, behind)
    return j
