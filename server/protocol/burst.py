"""Decode a burst of sensor packets together: the array checks of a stream in one numpy pass.

The ingest thread takes packets off the Zenoh channel in bursts. Decoding them one by one
(:func:`server.protocol.codec.decode`) costs about fifteen small numpy calls per array packet
and a Python check per field; here

* every payload is decoded by msgspec into the struct of its stream
  (:mod:`server.protocol.wire`), which checks the fields' names and types in C while it
  decodes;
* the packed arrays of all IMU, wheel-edge and wheel-speed packets of the burst are joined per
  stream and checked at once (finite, within the limits, stamps monotonic inside each packet),
  and split again into per-packet read-only views of the joined buffer; GNSS fixes are checked
  one by one (a few comparisons).

Anything unusual sends a packet to the codec's per-packet rules, which give the reason it is
refused, or accept it: a payload that is not a struct of :mod:`~server.protocol.wire` (a field
missing, of another type, an extra one), lengths that disagree, an empty batch, ``until_ns``
out of range, and a packet whose arrays fail a batch check (the checks find *which* packets,
one numpy call per check). The other packets of the burst are unaffected, so
:func:`decode_burst` returns, item for item, what ``decode`` returns or raises.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from typing import Any, NamedTuple

import msgspec
import numpy as np

from estimator._frozen import builder
from estimator.base import Measurement
from estimator.types import ImuBatch, Wheel, WheelEdges, WheelSpeeds
from server.protocol.codec import (
    _GNSS_FIX,
    _LITTLE_ENDIAN,
    _WHEEL,
    LIMITS,
    SCHEMA_VERSION,
    DecodeError,
    Limits,
    Packet,
    _gnss_within,
    _new_packet,
    decode,
)
from server.protocol.keys import Stream, parse_key
from server.protocol.wire import DECODER as _DECODER
from server.protocol.wire import EdgesEntry, GnssPacket, ImuPacket, WheelsPacket

__all__ = ["BurstItem", "decode_burst"]

#: The result for one packet: the decoded packet, or why it was refused.
BurstItem = Packet | DecodeError

_I8_BYTES = 8  # a packed int64 stamp
_F8_BYTES = 8  # a packed float64 value
_NO_FIRST_NS = 2**63 - 1  # start of the min() over a packet's first sample times
_NO_LAST_NS = -(2**63)  # start of the max() over its last ones
# the streams as module constants: an enum member looked up on its class costs ~70 ns
_GNSS, _IMU, _WHEELS = Stream.GNSS, Stream.IMU, Stream.WHEELS
# a packet's measurements are built without the frozen classes' __init__ (estimator._frozen)
_new_imu = builder(ImuBatch)
_new_speeds = builder(WheelSpeeds)
_new_edges = builder(WheelEdges)
_SEQ_END = 2**63  # sequence numbers lie in [0, 2**63)
_STREAM_OF: dict[type, Stream] = {GnssPacket: _GNSS, ImuPacket: _IMU, WheelsPacket: _WHEELS}


class _Opened:
    """A packet whose payload fitted a valid packet's shape (:mod:`server.protocol.wire`),
    waiting for its stream's batch check."""

    __slots__ = ("index", "p", "received", "stream", "vehicle_id")

    def __init__(
        self, index: int, received: tuple[str, bytes], vehicle_id: str, stream: Stream, p: Any
    ):
        self.index = index
        self.received = received
        self.vehicle_id = vehicle_id
        self.stream = stream
        self.p = p

    def alone(self, opts: _Options) -> BurstItem:
        """Decode this packet by the per-packet rules (the reason when it is refused)."""
        return opts.alone(*self.received)

    def packet(
        self, ms: tuple[Measurement, ...], first_ns: int, last_ns: int, opts: _Options
    ) -> BurstItem:
        """The packet of checked measurements; per-packet rules if ``until_ns`` is refused."""
        until_ns = _until(self.p)
        if (
            until_ns is not None
            and not last_ns <= until_ns <= last_ns + opts.limits.max_until_ahead_ns
        ):
            return self.alone(opts)
        return _new_packet(
            self.vehicle_id,
            self.stream,
            self.p.seq,
            SCHEMA_VERSION,
            ms,
            first_ns,
            last_ns,
            until_ns,
        )


def _until(p: GnssPacket | ImuPacket | WheelsPacket) -> int | None:
    """The packet's ``until_ns``; None when it has none."""
    return p.until_ns if isinstance(p.until_ns, int) else None  # or UNSET


class _Options:
    """The decoding options of one burst, and the per-packet decode under them."""

    __slots__ = ("limits", "max_payload_bytes", "prefix")

    def __init__(self, prefix: str, max_payload_bytes: int, limits: Limits) -> None:
        self.prefix = prefix
        self.max_payload_bytes = max_payload_bytes
        self.limits = limits

    def alone(self, key: str, payload: bytes) -> BurstItem:
        """:func:`~server.protocol.codec.decode` of one packet, its refusal as the item."""
        try:
            return decode(
                key,
                payload,
                prefix=self.prefix,
                max_payload_bytes=self.max_payload_bytes,
                limits=self.limits,
            )
        except DecodeError as exc:
            return exc


def _sample_count(raw: object, lim: Limits) -> int:
    """Samples in the packed stamps ``raw``, or 0 when they are not a non-empty packed int64
    array within the batch limit (or not there: ``UNSET``)."""
    if type(raw) is not bytes:
        return 0
    n, rest = divmod(len(raw), _I8_BYTES)
    return n if not rest and n <= lim.max_batch else 0


def _joined(raws: list[bytes], dtype: str, width: int) -> np.ndarray:
    """One read-only array over the concatenated packed arrays, ``width`` values a row."""
    arr = np.frombuffer(b"".join(raws), dtype=dtype)
    return arr.reshape(-1, width) if width > 1 else arr


def _runs_ok(ok: np.ndarray, starts: list[int]) -> list[bool] | None:
    """Whether every element of each run (starting at ``starts``) is ok; None: all are."""
    if ok.all():
        return None
    flags: list[bool] = np.logical_and.reduceat(ok, starts).tolist()
    return flags


def _norm_ok(a: np.ndarray, bound: float) -> np.ndarray | None:
    """Rows without ``±inf`` whose norm is within ``bound`` (a NaN row passes); None: all.

    The rule of the per-packet ``_finite_rows``, on many packets' rows at once."""
    norm2 = np.einsum("ij,ij->i", a, a)
    if (norm2 <= bound * bound).all():
        return None
    ok: np.ndarray = ~((norm2 > bound * bound) | np.isinf(a).any(axis=1))
    return ok


def _abs_ok(a: np.ndarray, bound: float) -> np.ndarray | None:
    """Rows whose values are all within ``±bound`` (NaN passes, ``±inf`` does not); None: all."""
    bad = np.abs(a) > bound
    if not bad.any():
        return None
    ok: np.ndarray = ~bad.any(axis=1)
    return ok


def _run_bounds(counts: list[int]) -> tuple[list[int], list[int]]:
    """Start and end (exclusive) of each run of ``counts[k]`` samples in the joined array."""
    ends = list(itertools.accumulate(counts))
    return [e - n for e, n in zip(ends, counts, strict=True)], ends


def _steps_ok(t: np.ndarray, starts: list[int], *, strict: bool) -> np.ndarray:
    """Per sample: its stamp is after the previous one of its run (or not before it, unless
    ``strict``); a run's first sample always is."""
    ok = np.empty(t.shape[0], dtype=bool)
    ok[0] = True
    compare = np.greater if strict else np.greater_equal
    compare(t[1:], t[:-1], out=ok[1:])
    ok[starts] = True  # a run's first stamp follows another run's last
    return ok


class _Checked(NamedTuple):
    """The joined stamps of a group's runs and the verdict on each run."""

    t: np.ndarray  #: all runs' stamps (int64), joined
    starts: list[int]  #: each run's slice of ``t``
    ends: list[int]
    first_ns: list[int]  #: each run's first and last stamp
    last_ns: list[int]
    good: list[bool]  #: the run passed every check (else: decode its packet alone)


class _Runs:
    """Sample-time runs (one per packet, or per wheel entry) joined for one check."""

    __slots__ = ("counts", "raws", "strict")

    def __init__(self, *, strict: bool) -> None:
        self.strict = strict
        self.raws: list[bytes] = []
        self.counts: list[int] = []

    def add(self, raw: bytes, n: int) -> int:
        """Append a run of ``n`` stamps; return its index."""
        self.raws.append(raw)
        self.counts.append(n)
        return len(self.counts) - 1

    def check(self, lim: Limits, rows_ok: np.ndarray | None = None) -> _Checked:
        """Check every run's stamps, and ``rows_ok`` (a flag per sample, None: all ok), at once:
        a run is good when its stamps lie within the limits and increase (strictly, if
        ``strict``) and its rows are ok."""
        t = _joined(self.raws, "<i8", 1)
        starts, ends = _run_bounds(self.counts)
        steps_ok = _steps_ok(t, starts, strict=self.strict)
        runs_ok = _runs_ok(steps_ok if rows_ok is None else steps_ok & rows_ok, starts)
        first_ns: list[int] = t[starts].tolist()
        last_ns: list[int] = t[[e - 1 for e in ends]].tolist()
        # stamps that increase lie between their run's first and last
        lo, hi = lim.min_stamp_ns, lim.max_stamp_ns
        good = [
            lo <= first and last <= hi and (runs_ok is None or runs_ok[k])
            for k, (first, last) in enumerate(zip(first_ns, last_ns, strict=True))
        ]
        return _Checked(t, starts, ends, first_ns, last_ns, good)


class _SampledGroup:
    """Packets of one stream with a single stamp run and row arrays of the same length
    (IMU batches, wheel speeds), checked together."""

    __slots__ = ("opened", "rows", "runs")

    #: (field, values a row) of the row arrays beside ``stamp_ns``
    FIELDS: tuple[tuple[str, int], ...] = ()

    def __init__(self) -> None:
        self.opened: list[_Opened] = []
        self.runs = _Runs(strict=True)
        self.rows: list[list[bytes]] = [[] for _ in self.FIELDS]

    def add(self, op: _Opened, lim: Limits) -> bool:
        """Take ``op`` when its arrays have a valid packet's lengths."""
        p = op.p
        stamps = p.stamp_ns
        n = _sample_count(stamps, lim)
        if not n:
            return False
        raws: list[bytes] = []
        for raw, (_, width) in zip(self.row_arrays(p), self.FIELDS, strict=True):
            if not isinstance(raw, bytes) or len(raw) != n * width * _F8_BYTES:
                return False
            raws.append(raw)
        self.opened.append(op)
        self.runs.add(stamps, n)
        for joined, raw in zip(self.rows, raws, strict=True):
            joined.append(raw)
        return True

    def row_arrays(self, p: Any) -> tuple[object, ...]:
        """The packet's packed row arrays, in the order of :attr:`FIELDS`."""
        raise NotImplementedError

    def rows_ok(self, arrays: list[np.ndarray], lim: Limits) -> np.ndarray | None:
        """The per-row rule of the stream over the joined row arrays; None: every row is ok."""
        raise NotImplementedError

    def measurement(self, t: np.ndarray, arrays: list[np.ndarray], a: int, b: int) -> Measurement:
        """The measurement of one packet: samples ``a:b`` of the joined arrays."""
        raise NotImplementedError

    def finish(self, out: list[BurstItem | None], opts: _Options) -> None:
        """Check the group and put each packet's result at its index in ``out``."""
        if not self.opened:
            return
        lim = opts.limits
        arrays = [
            _joined(raws, "<f8", width)
            for raws, (_, width) in zip(self.rows, self.FIELDS, strict=True)
        ]
        c = self.runs.check(lim, self.rows_ok(arrays, lim))
        measurement = self.measurement
        for op, a, b, first, last, ok in zip(
            self.opened, c.starts, c.ends, c.first_ns, c.last_ns, c.good, strict=True
        ):
            if ok:
                out[op.index] = op.packet((measurement(c.t, arrays, a, b),), first, last, opts)
            else:
                out[op.index] = op.alone(opts)


class _ImuGroup(_SampledGroup):
    """IMU batches: accelerometer and gyroscope row norms within the limits."""

    __slots__ = ()
    FIELDS = (("accel_mps2", 3), ("gyro_radps", 3))

    def row_arrays(self, p: Any) -> tuple[object, ...]:
        return p.accel_mps2, p.gyro_radps

    def rows_ok(self, arrays: list[np.ndarray], lim: Limits) -> np.ndarray | None:
        accel_ok = _norm_ok(arrays[0], lim.max_accel_mps2)
        gyro_ok = _norm_ok(arrays[1], lim.max_gyro_radps)
        if accel_ok is None or gyro_ok is None:
            return gyro_ok if accel_ok is None else accel_ok
        return accel_ok & gyro_ok

    def measurement(self, t: np.ndarray, arrays: list[np.ndarray], a: int, b: int) -> Measurement:
        return _new_imu(t[a:b], arrays[0][a:b], arrays[1][a:b])


class _SpeedsGroup(_SampledGroup):
    """Wheel speeds: ``|omega|`` within the limit."""

    __slots__ = ()
    FIELDS = (("omega_radps", 2),)

    def row_arrays(self, p: Any) -> tuple[object, ...]:
        return (p.omega_radps,)

    def rows_ok(self, arrays: list[np.ndarray], lim: Limits) -> np.ndarray | None:
        return _abs_ok(arrays[0], lim.max_wheel_omega_radps)

    def measurement(self, t: np.ndarray, arrays: list[np.ndarray], a: int, b: int) -> Measurement:
        return _new_speeds(t[a:b], arrays[0][a:b])


class _EdgesGroup:
    """Wheel-edge packets (one run per wheel entry, optional direction), checked together."""

    __slots__ = ("directions", "entries", "opened", "runs")

    def __init__(self) -> None:
        self.opened: list[_Opened] = []
        self.entries: list[list[tuple[Wheel, int]]] = []  # per packet: (wheel, run index)
        self.runs = _Runs(strict=False)
        self.directions: dict[int, bytes] = {}  # run index -> packed int8 directions

    def add(self, op: _Opened, lim: Limits) -> bool:
        """Take ``op`` when its ``edges`` entries have a valid packet's lengths."""
        items = op.p.edges
        if type(items) is not list or not 1 <= len(items) <= len(_WHEEL):
            return False
        entries: list[tuple[Wheel, int]] = []
        for item in items:
            entry = self._add_entry(item, lim)
            if entry is None or (entries and entries[0][0] is entry[0]):
                self._drop_runs(len(entries) + (entry is not None))
                return False
            entries.append(entry)
        self.opened.append(op)
        self.entries.append(entries)
        return True

    def _add_entry(self, item: EdgesEntry, lim: Limits) -> tuple[Wheel, int] | None:
        """Add one wheel entry's run; None (nothing added) when the entry is not valid."""
        wheel = _WHEEL.get(item.wheel)
        n = _sample_count(item.stamp_ns, lim)
        if wheel is None or not n:
            return None
        direction = item.direction if isinstance(item.direction, bytes) else None  # or UNSET
        if direction is not None and len(direction) != n:
            return None
        run = self.runs.add(item.stamp_ns, n)
        if direction is not None:
            self.directions[run] = direction
        return wheel, run

    def _drop_runs(self, count: int) -> None:
        """Take back the last ``count`` runs (of a packet that turned out not valid)."""
        for _ in range(count):
            self.directions.pop(len(self.runs.counts) - 1, None)
            self.runs.raws.pop()
            self.runs.counts.pop()

    def _direction_views(self) -> dict[int, np.ndarray | None]:
        """Each run's directions (None when it has none), checked: a run whose directions are
        not all +1 or -1 is left out."""
        views: dict[int, np.ndarray | None] = dict.fromkeys(range(len(self.runs.counts)))
        if not self.directions:
            return views
        d = _joined(list(self.directions.values()), "i1", 1)
        starts, ends = _run_bounds([self.runs.counts[r] for r in self.directions])
        ok = _runs_ok((d == 1) | (d == -1), starts)
        for k, r in enumerate(self.directions):
            if ok is None or ok[k]:
                views[r] = d[starts[k] : ends[k]]
            else:
                del views[r]
        return views

    def finish(self, out: list[BurstItem | None], opts: _Options) -> None:
        """Check the group and put each packet's result at its index in ``out``."""
        if not self.opened:
            return
        t, starts, ends, first_ns, last_ns, good = self.runs.check(opts.limits)
        directions = self._direction_views()
        for op, entries in zip(self.opened, self.entries, strict=True):
            ms: list[Measurement] = []
            first, last = _NO_FIRST_NS, _NO_LAST_NS
            for wheel, r in entries:
                if not good[r] or r not in directions:
                    out[op.index] = op.alone(opts)
                    break
                ms.append(_new_edges(wheel, t[starts[r] : ends[r]], directions[r]))
                if first_ns[r] < first:
                    first = first_ns[r]
                if last_ns[r] > last:
                    last = last_ns[r]
            else:
                out[op.index] = op.packet(tuple(ms), first, last, opts)


def _group(op: _Opened, groups: _Groups) -> _SampledGroup | _EdgesGroup:
    """The batch check ``op`` (an IMU or wheels packet) belongs to."""
    if op.stream is _IMU:
        return groups.imu
    return groups.wheels[op.p.mode]


class _Groups:
    """One burst's batch checks: IMU, and wheels by mode."""

    __slots__ = ("imu", "wheels")

    def __init__(self) -> None:
        self.imu = _ImuGroup()
        self.wheels: dict[str, _SampledGroup | _EdgesGroup] = {
            "edges": _EdgesGroup(),
            "speeds": _SpeedsGroup(),
        }

    def finish(self, out: list[BurstItem | None], opts: _Options) -> None:
        """Check every group and put each packet's result at its index in ``out``."""
        self.imu.finish(out, opts)
        for group in self.wheels.values():
            group.finish(out, opts)


#: Bursts shorter than this are decoded packet by packet: joining and splitting the arrays of a
#: few packets costs more than it saves (``slipfleet bench ingest codec``, burst-size table:
#: 15.4 µs per packet in bursts of 1, 9.2 in bursts of 8, 6.4 in bursts of 32; alone 9.3).
MIN_BATCHED = 8


def _gnss_packet(vehicle_id: str, p: GnssPacket, lim: Limits) -> Packet | None:
    """The packet of a GNSS fix within its limits; None: the codec's rules decide."""
    sample = _gnss_within(
        p.stamp_ns,
        p.vel_enu_mps,
        p.heading_rad,
        p.pitch_rad,
        p.roll_rad,
        p.lat_deg,
        p.lon_deg,
        p.height_m,
        _GNSS_FIX.get(p.fix),
        p.vel_std_mps,
        lim,
    )
    if sample is None:
        return None
    t = sample.stamp_ns
    until_ns = _until(p)
    if until_ns is not None and not t <= until_ns <= t + lim.max_until_ahead_ns:
        return None
    return _new_packet(vehicle_id, _GNSS, p.seq, SCHEMA_VERSION, (sample,), t, t, until_ns)


def _heartbeat(op: _Opened, lim: Limits) -> BurstItem | None:
    """The wheels heartbeat of a packet with no edges entry (no edge on either wheel up to
    ``until_ns``); None when its ``until_ns`` is absent or out of range."""
    until_ns = _until(op.p)
    if until_ns is None or not lim.min_stamp_ns <= until_ns <= lim.max_stamp_ns:
        return None
    return _new_packet(
        op.vehicle_id, _WHEELS, op.p.seq, SCHEMA_VERSION, (), until_ns, until_ns, until_ns
    )


def _stream_of(key: str, prefix: str) -> tuple[str, Stream] | None:
    """``(vehicle_id, stream)`` of a sensor key; None for any other key."""
    try:
        vehicle_id, stream = parse_key(key, prefix)
    except ValueError:
        return None
    return None if stream is None else (vehicle_id, stream)


def decode_burst(
    received: Sequence[tuple[str, bytes]],
    *,
    prefix: str = "fleet",
    max_payload_bytes: int = 256 * 1024,
    limits: Limits = LIMITS,
) -> list[BurstItem]:
    """Decode the sensor packets of a burst; item ``i`` is what ``decode(*received[i])`` would
    return, or the :class:`DecodeError` it would raise.

    Parameters
    ----------
    received : sequence of (key, payload)
        The packets in the order they arrived.
    prefix, max_payload_bytes, limits
        As for :func:`server.protocol.codec.decode`.

    Returns
    -------
    list of Packet or DecodeError
    """
    opts = _Options(prefix, max_payload_bytes, limits)
    if len(received) < MIN_BATCHED or not _LITTLE_ENDIAN:  # big-endian: plain Python
        return [opts.alone(key, payload) for key, payload in received]
    out: list[BurstItem | None] = [None] * len(received)
    groups = _Groups()
    streams: dict[str, tuple[str, Stream] | None] = {}
    typed = _DECODER.decode
    for i, item in enumerate(received):
        key, payload = item
        try:
            vs = streams[key]
        except KeyError:  # the first packet of this key in the burst
            vs = streams[key] = _stream_of(key, prefix)
        if vs is None or len(payload) > max_payload_bytes:
            out[i] = opts.alone(key, payload)
            continue
        try:
            p = typed(payload)
        except (msgspec.DecodeError, ValueError):  # ValidationError, or bad UTF-8 in a string
            out[i] = opts.alone(key, payload)  # its reason, or valid beyond the usual shape
            continue
        vehicle_id, stream = vs
        if p.seq >= _SEQ_END or _STREAM_OF[type(p)] is not stream:
            out[i] = opts.alone(key, payload)
            continue
        if stream is _GNSS:  # nothing to batch: checked on its own
            out[i] = _gnss_packet(vehicle_id, p, limits) or opts.alone(key, payload)
            continue
        op = _Opened(i, item, vehicle_id, stream, p)
        if stream is _WHEELS and p.mode == "edges" and p.edges == []:
            out[i] = _heartbeat(op, limits) or op.alone(opts)
            continue
        if not _group(op, groups).add(op, limits):
            out[i] = op.alone(opts)
    groups.finish(out, opts)
    items = [item for item in out if item is not None]
    assert len(items) == len(out), "every packet gets a result"
    return items
