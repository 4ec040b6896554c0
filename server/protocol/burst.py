"""Decode a burst of sensor packets together: the array checks of a stream in one numpy pass.

The ingest thread takes packets off the Zenoh channel in bursts. Decoding them one by one
(:func:`server.protocol.codec.decode`) costs about fifteen small numpy calls per array packet
and a Python check per field; here

* every payload is decoded by msgspec into the struct of its stream
  (:mod:`server.protocol.wire`), which checks the fields' names and types in C while it
  decodes;
* the packed arrays of all packets of one layout (:mod:`server.protocol.layouts`: IMU, wheel
  edges, wheel speeds, ...; ``StreamSpec.batch`` says which) are joined and checked at once
  (finite, within the limits, stamps monotonic inside each packet), and split again into
  per-packet read-only views of the joined buffer; GNSS fixes are checked one by one
  (``StreamSpec.single``, a few comparisons).

Anything unusual sends a packet to the codec's per-packet rules, which give the reason it is
refused, or accept it: a payload that is not a struct of :mod:`~server.protocol.wire` (a field
missing, of another type, an extra one), lengths that disagree, an empty batch, ``until_ns``
out of range, and a packet whose arrays fail a batch check (the checks find *which* packets,
one numpy call per check), and a ``boot`` of 2**63 or more. The other packets of the burst
are unaffected, so
:func:`decode_burst` returns, item for item, what ``decode`` returns or raises.
"""

from __future__ import annotations

import itertools
import operator
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import msgspec
import numpy as np

from estimator.base import Measurement
from server.protocol.base import (
    LIMITS,
    LITTLE_ENDIAN,
    SCHEMA_VERSION,
    Body,
    DecodeError,
    Limits,
    Packet,
    new_packet,
)
from server.protocol.codec import decode
from server.protocol.keys import Stream, parse_key
from server.protocol.layouts import Edges, Sampled
from server.protocol.streams import STREAMS, Layout
from server.protocol.wire import DECODER as _DECODER

__all__ = ["MIN_BATCHED", "BurstItem", "decode_burst"]

#: The result for one packet: the decoded packet, or why it was refused.
BurstItem = Packet | DecodeError

_I8_BYTES = 8  # a packed int64 stamp
_F8_BYTES = 8  # a packed float64 value
_NO_FIRST_NS = 2**63 - 1  # start of the min() over a packet's first sample times
_NO_LAST_NS = -(2**63)  # start of the max() over its last ones
_SEQ_END = 2**63  # sequence numbers and boot ids lie in [0, 2**63)


class _Route(NamedTuple):
    """What the burst decoder does with a decoded struct of one stream: its declaration's
    parts, looked up once per packet by the struct's type."""

    stream: Stream
    single: Callable[[Any, Limits], Body | None] | None  #: ``StreamSpec.single``
    layout: Layout | None  #: ``StreamSpec.layout`` (None: ``batch`` decides per packet)
    batch: Callable[[Any], Layout | None]  #: ``StreamSpec.batch``


#: Each wire struct's route, derived from the stream declarations at import.
_ROUTES: dict[type, _Route] = {
    s.wire: _Route(s.stream, s.single, s.layout, s.batch) for s in STREAMS.values()
}


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
        packet = _packet(self.vehicle_id, self.stream, self.p, ms, first_ns, last_ns, opts.limits)
        return self.alone(opts) if packet is None else packet


def _until(p: Any) -> int | None:
    """The packet's ``until_ns``; None when it has none."""
    return p.until_ns if isinstance(p.until_ns, int) else None  # or UNSET


def _packet(
    vehicle_id: str,
    stream: Stream,
    p: Any,
    ms: tuple[Measurement, ...],
    first_ns: int,
    last_ns: int,
    lim: Limits,
) -> Packet | None:
    """The packet of the struct ``p`` and its checked measurements; None when its
    ``until_ns`` is out of range (the per-packet rules then decide)."""
    until_ns = p.until_ns
    if type(until_ns) is not int:  # UNSET
        until_ns = None
    elif not last_ns <= until_ns <= last_ns + lim.max_until_ahead_ns:
        return None
    boot = p.boot
    if type(boot) is not int:  # UNSET
        boot = None
    elif boot >= _SEQ_END:  # below 0 the struct refuses it
        return None
    return new_packet(
        vehicle_id=vehicle_id,
        stream=stream,
        seq=p.seq,
        schema_version=SCHEMA_VERSION,
        measurements=ms,
        first_stamp_ns=first_ns,
        last_stamp_ns=last_ns,
        until_ns=until_ns,
        boot=boot,
    )


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
    """Rows (values of a one-dimensional ``a``) all within ``±bound`` (NaN passes, ``±inf``
    does not); None: all."""
    bad = np.abs(a) > bound
    if not bad.any():
        return None
    ok: np.ndarray = ~(bad if bad.ndim == 1 else bad.any(axis=1))
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


def _compiled(source: str, build: Callable[..., Measurement]) -> Callable[..., Measurement]:
    """The function ``source`` defines, calling ``build``."""
    scope: dict[str, Any] = {"build": build}
    exec(source, scope)
    made: Callable[..., Measurement] = scope["made"]
    return made


#: Each layout's measurement maker (:func:`_maker`), compiled the first time it is met.
_MAKERS: dict[Layout, Callable[..., Measurement]] = {}


def _maker(layout: Layout) -> Callable[..., Measurement]:
    """The layout's ``build`` called with its fields named in the code, not by ``**``: a
    :class:`Sampled` layout's ``(t, arrays, a, b)`` (samples ``a:b`` of the joined arrays, in
    the order of ``rows``), an :class:`Edges` layout's ``(member, stamp_ns, direction)``.

    Generated from the declaration (its names are identifiers), because a call that unpacks a
    dict of keywords costs about 1 µs more a measurement than one naming them."""
    made = _MAKERS.get(layout)
    if made is not None:
        return made
    if isinstance(layout, Sampled):
        names = [r.name for r in layout.rows]
        rows = "".join(f", {n}=arrays[{k}][a:b]" for k, n in enumerate(names))
        source = f"def made(t, arrays, a, b):\n    return build(stamp_ns=t[a:b]{rows})\n"
    else:
        names = [layout.key]
        source = (
            "def made(member, stamp_ns, direction):\n"
            f"    return build({layout.key}=member, stamp_ns=stamp_ns, direction=direction)\n"
        )
    if not all(n.isidentifier() for n in names):
        raise ValueError(f"layout field names must be identifiers: {names}")
    made = _MAKERS[layout] = _compiled(source, layout.build)
    return made


class _SampledGroup:
    """Packets of one :class:`~server.protocol.layouts.Sampled` layout (a single stamp run and
    row arrays of the same length), checked together."""

    __slots__ = ("fields", "layout", "make", "opened", "row_bytes", "rows", "runs")
    heartbeats = False  #: its packets always carry samples

    def __init__(self, layout: Sampled) -> None:
        self.layout = layout
        self.make = _maker(layout)
        #: a struct's ``(stamp_ns, <row arrays>...)`` in one call
        self.fields = operator.attrgetter("stamp_ns", *(r.name for r in layout.rows))
        self.row_bytes = tuple(r.width * _F8_BYTES for r in layout.rows)
        self.opened: list[_Opened] = []
        self.runs = _Runs(strict=True)
        self.rows: list[list[bytes]] = [[] for _ in layout.rows]

    def add(self, op: _Opened, lim: Limits) -> bool:
        """Take ``op`` when its arrays have a valid packet's lengths."""
        stamps, *raws = self.fields(op.p)
        n = _sample_count(stamps, lim)
        if not n:
            return False
        for raw, row_bytes in zip(raws, self.row_bytes, strict=True):
            if type(raw) is not bytes or len(raw) != n * row_bytes:
                return False
        self.opened.append(op)
        self.runs.add(stamps, n)
        for joined, raw in zip(self.rows, raws, strict=True):
            joined.append(raw)
        return True

    def _rows_ok(self, arrays: list[np.ndarray], lim: Limits) -> np.ndarray | None:
        """Each row passes every row array's rule (``Rows``); None: every row does."""
        ok: np.ndarray | None = None
        for r, a in zip(self.layout.rows, arrays, strict=True):
            bound = getattr(lim, r.bound)
            this = _norm_ok(a, bound) if r.norm else _abs_ok(a, bound)
            if this is not None:
                ok = this if ok is None else ok & this
        return ok

    def finish(self, out: list[BurstItem | None], opts: _Options) -> None:
        """Check the group and put each packet's result at its index in ``out``."""
        if not self.opened:
            return
        lim = opts.limits
        arrays = [
            _joined(raws, "<f8", r.width)
            for raws, r in zip(self.rows, self.layout.rows, strict=True)
        ]
        c = self.runs.check(lim, self._rows_ok(arrays, lim))
        make, t = self.make, c.t
        for op, a, b, first, last, ok in zip(
            self.opened, c.starts, c.ends, c.first_ns, c.last_ns, c.good, strict=True
        ):
            if ok:
                out[op.index] = op.packet((make(t, arrays, a, b),), first, last, opts)
            else:
                out[op.index] = op.alone(opts)


class _EdgesGroup:
    """Packets of one :class:`~server.protocol.layouts.Edges` layout (one run per entry,
    optional direction), checked together."""

    __slots__ = (
        "by_number",
        "directions",
        "entries",
        "entry",
        "key",
        "layout",
        "make",
        "most",
        "opened",
        "runs",
    )
    heartbeats = True  #: a packet without entries is a heartbeat (``until_ns`` alone)

    def __init__(self, layout: Edges) -> None:
        self.layout = layout
        self.key = layout.key
        self.by_number = layout.by_number  # the struct's number is an int already
        self.most = len(layout.by_number)  # entries in a packet
        self.make = _maker(layout)
        #: an entry's ``(member number, stamp_ns, direction)`` in one call
        self.entry = operator.attrgetter(layout.key, "stamp_ns", "direction")
        self.opened: list[_Opened] = []
        self.entries: list[list[tuple[Any, int]]] = []  # per packet: (member, run index)
        self.runs = _Runs(strict=False)
        self.directions: dict[int, bytes] = {}  # run index -> packed int8 directions

    def add(self, op: _Opened, lim: Limits) -> bool:
        """Take ``op`` when its ``edges`` entries have a valid packet's lengths."""
        items = op.p.edges
        if type(items) is not list or not 1 <= len(items) <= self.most:
            return False
        entries: list[tuple[Any, int]] = []
        members: list[Any] = []
        for item in items:
            entry = self._add_entry(item, lim)
            if entry is None or entry[0] in members:
                self._drop_runs(len(entries) + (entry is not None))
                return False
            entries.append(entry)
            members.append(entry[0])
        self.opened.append(op)
        self.entries.append(entries)
        return True

    def _add_entry(self, item: Any, lim: Limits) -> tuple[Any, int] | None:
        """Add one entry's run; None (nothing added) when the entry is not valid."""
        number, stamps, direction = self.entry(item)
        member = self.by_number.get(number)
        n = _sample_count(stamps, lim)
        if member is None or not n:
            return None
        if type(direction) is not bytes:  # UNSET
            direction = None
        elif len(direction) != n:
            return None
        run = self.runs.add(stamps, n)
        if direction is not None:
            self.directions[run] = direction
        return member, run

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
        make = self.make
        for op, entries in zip(self.opened, self.entries, strict=True):
            ms: list[Measurement] = []
            first, last = _NO_FIRST_NS, _NO_LAST_NS
            for member, r in entries:
                if not good[r] or r not in directions:
                    out[op.index] = op.alone(opts)
                    break
                ms.append(make(member, t[starts[r] : ends[r]], directions[r]))
                if first_ns[r] < first:
                    first = first_ns[r]
                if last_ns[r] > last:
                    last = last_ns[r]
            else:
                out[op.index] = op.packet(tuple(ms), first, last, opts)


class _Groups:
    """One burst's batch checks, one group per layout met."""

    __slots__ = ("by_layout",)

    def __init__(self) -> None:
        #: by layout object (layouts hash by identity): a dict look-up, no call, per packet
        self.by_layout: dict[Layout, _SampledGroup | _EdgesGroup] = {}

    def new(self, layout: Layout) -> _SampledGroup | _EdgesGroup:
        """The group checking ``layout``'s packets, the first of them in this burst."""
        group = _SampledGroup(layout) if isinstance(layout, Sampled) else _EdgesGroup(layout)
        self.by_layout[layout] = group
        return group

    def finish(self, out: list[BurstItem | None], opts: _Options) -> None:
        """Check every group and put each packet's result at its index in ``out``."""
        for group in self.by_layout.values():
            group.finish(out, opts)


#: Bursts shorter than this are decoded packet by packet: joining and splitting the arrays of a
#: few packets costs more than it saves (``slipfleet bench ingest codec``, burst-size table:
#: 15.4 µs per packet in bursts of 1, 9.2 in bursts of 8, 6.4 in bursts of 32; alone 9.3).
MIN_BATCHED = 8


def _heartbeat(op: _Opened, lim: Limits) -> BurstItem | None:
    """The heartbeat of an edges packet without entries (no edge up to ``until_ns``); None
    when its ``until_ns`` is absent or out of range."""
    until_ns = _until(op.p)
    if until_ns is None or not lim.min_stamp_ns <= until_ns <= lim.max_stamp_ns:
        return None
    boot = op.p.boot
    if type(boot) is not int:  # UNSET
        boot = None
    elif boot >= _SEQ_END:
        return None
    return new_packet(
        vehicle_id=op.vehicle_id,
        stream=op.stream,
        seq=op.p.seq,
        schema_version=SCHEMA_VERSION,
        measurements=(),
        first_stamp_ns=until_ns,
        last_stamp_ns=until_ns,
        until_ns=until_ns,
        boot=boot,
    )


def _stream_of(key: str, prefix: str) -> tuple[str, Stream] | None:
    """``(vehicle_id, stream)`` of a sensor key; None for any other key."""
    try:
        vehicle_id, stream = parse_key(key, prefix)
    except ValueError:
        return None
    return None if stream is None else (vehicle_id, stream)


#: Keys seen, per prefix: ``key -> _stream_of(key, prefix)``, so that a packet's key costs a
#: dict look-up (a fleet repeats its vehicles' few keys); emptied when it holds more than
#: :data:`_KEYS_HELD` (random keys must not grow memory).
_KEYS: dict[str, dict[str, tuple[str, Stream] | None]] = {}
_KEYS_HELD = 65_536


def _keys_of(prefix: str) -> dict[str, tuple[str, Stream] | None]:
    """The keys seen under ``prefix`` (emptied first when too many)."""
    keys = _KEYS.get(prefix)
    if keys is None:
        if len(_KEYS) >= 16:  # prefixes: one or a few a server
            _KEYS.clear()
        keys = _KEYS[prefix] = {}
    elif len(keys) > _KEYS_HELD:
        keys.clear()
    return keys


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
    if len(received) < MIN_BATCHED or not LITTLE_ENDIAN:  # big-endian: plain Python
        return [opts.alone(key, payload) for key, payload in received]
    out: list[BurstItem | None] = [None] * len(received)
    groups = _Groups()
    _open_all(received, out, groups, opts)
    groups.finish(out, opts)
    items = [item for item in out if item is not None]
    assert len(items) == len(out), "every packet gets a result"
    return items


def _open_all(
    received: Sequence[tuple[str, bytes]],
    out: list[BurstItem | None],
    groups: _Groups,
    opts: _Options,
) -> None:
    """Decode each payload into its stream's struct: a packet checked on its own gets its
    result in ``out`` now, a batched one joins its layout's group in ``groups``, and anything
    unusual is decoded by the per-packet rules."""
    prefix, max_payload_bytes, limits = opts.prefix, opts.max_payload_bytes, opts.limits
    streams = _keys_of(prefix)
    typed, routes, by_layout = _DECODER.decode, _ROUTES, groups.by_layout
    for i, item in enumerate(received):
        key, payload = item
        try:
            vs = streams[key]
        except KeyError:  # the first packet of this key
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
        wired, single, layout, batch = routes[type(p)]
        if p.seq >= _SEQ_END or wired is not stream:
            out[i] = opts.alone(key, payload)
        elif single is not None:  # nothing to batch: checked on its own
            out[i] = _single(single, vehicle_id, stream, p, item, opts)
        elif layout is None and (layout := batch(p)) is None:
            out[i] = opts.alone(key, payload)
        else:
            group = by_layout.get(layout) or groups.new(layout)
            op = _Opened(i, item, vehicle_id, stream, p)
            if group.heartbeats and p.edges == []:
                out[i] = _heartbeat(op, limits) or op.alone(opts)
            elif not group.add(op, limits):
                out[i] = op.alone(opts)


def _single(
    single: Callable[[Any, Limits], Body | None],
    vehicle_id: str,
    stream: Stream,
    p: Any,
    received: tuple[str, bytes],
    opts: _Options,
) -> BurstItem:
    """The packet of a stream checked on its own (``StreamSpec.single``), or the per-packet
    rules' result when the check or its ``until_ns`` refuses it."""
    body = single(p, opts.limits)
    packet = None if body is None else _packet(vehicle_id, stream, p, *body, opts.limits)
    return opts.alone(*received) if packet is None else packet
