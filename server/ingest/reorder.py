"""Per-vehicle reorder buffer: hand packets to the estimators in sensor-time order.

Packets of one vehicle arrive on several streams (:mod:`server.protocol.streams`), each possibly
reordered by the network. The buffer holds them in a heap keyed by the packet's first sample
time and releases them once the *horizon* has passed them::

    horizon = newest sample time seen (any stream) - lateness

so a packet may arrive up to ``lateness`` (sensor time) after newer data and still be fed in
order. When the vehicle goes quiet for ``idle`` of wall time (monotonic clock, an argument;
default ``max(2 * lateness, 1 s)``: a publisher stalled for a moment must not look like a
vehicle that stopped), the horizon jumps to the newest sample time so the tail is released too.

With ``watermarks`` (the server's default) the horizon does not wait the whole window when it
need not: each stream has a *watermark*, the last sample time (or the packet's ``until_ns``,
the end of its batch window, when the sender gives it) of its longest run of consecutive
sequence numbers (everything of that stream up to it has arrived, whatever the arrival order
inside the stream), and ::

    horizon = max(newest - lateness, min over the vehicle's streams of their watermarks)

A packet that is missing (lost, or still on its way) holds its stream's watermark until the
fixed window passes it; then the run resumes after the gap. The watermarks gate the release only
once every stream the vehicle is expected to send (``streams``: GNSS, IMU and wheels by
default) has one,
and not before ``max(lateness, WATERMARK_START_NS)`` of sensor time after the vehicle's first
packet (a stream's first packet arrives only once its batch is complete): a vehicle standing
still sends no wheel edges, and a horizon driven by its IMU and GNSS alone would make the first
wheel packet late once it moves. Until then the fixed window applies. ``newest`` is always a
sample time, never a sender's ``until_ns`` (which may lie ahead of the arrival: a GNSS epoch
covers up to the next one), so the fixed window keeps its full margin. Sensor-to-estimate
latency drops from ``lateness`` to the spread between the vehicle's streams (down to the
batch ends, with ``until_ns``), without making more packets late.

While the watermarks gate, falling idle does not move the horizon: the lowest watermark already
says how far every stream is complete, and past it a stream's data may still be on its way. A
link that stalls for longer than ``idle`` (a cellular drop-out, a starved host) would otherwise
look like a vehicle that stopped: the horizon would jump to the newest sample, the estimators
would compute the wheels' speed over edges not yet received (a row of about −70 % slip, seen on
every demo vehicle after a 1.5 s stall), and the stalled wheel packet, when it came, would be
late and dropped. A vehicle that really stopped sending keeps back at most the part after its
lowest watermark (a batch window, the streams' last ``until_ns`` permitting) until it sends
again.

Between packets the horizon moves only when the vehicle falls idle (and no watermarks gate). A
packet moves it only when it moves the last of the watermarks that held it at the last release
(the lowest one, or several that tie: streams whose batches end together; a packet after a
gap the fixed window already passed moves its watermark too, as the missing one is given up
on), or when its samples push the fixed window past what was released;
:attr:`ReorderBuffer.may_release` says so, and the pipeline visits a buffer only then (or when
it fell idle): the packets of the streams ahead of a lagging one wait without a release each.

Data missing on a *cumulative* stream (``StreamSpec.cumulative``: edges count an angle, so no
edge up to a time reads as something turning slower, true only if none is on its way): when
the horizon passes the watermark of such an expected stream (it is later than the fixed
window), :meth:`ReorderBuffer.take_gaps` names the span from the watermark to the horizon, due
without that stream's data. The stream's data is *lost* when one of its sequence numbers is
missing while later packets came (told once a loss, as soon as the horizon passes the
watermark), or when one of its packets is refused late. Each :class:`StreamGap` names the first
released packet after the watermark; what an estimator is told is the pipeline's adapter's
business (:mod:`server.ingest.adapter`).

A stream that *stops* is told, not left silent: once the start-up window has passed, an
expected stream whose watermark the fixed window has passed (``newest - lateness``; sent
nothing, or nothing since) is *stalled*. :meth:`ReorderBuffer.take_stalls` names each
stall once when it begins (the pipeline counts it, ``stalled_<stream>``);
:attr:`ReorderBuffer.stalled` holds the streams stalled now. A stream is stalled no more once
its watermark is within the window again.

The expected streams are the ones the vehicle's estimators read (their specs' ``inputs``: a
crawler's odometer and sprockets, a steered vehicle's CAN wheel speeds and steering, no wheel
edges); :meth:`ReorderBuffer.expect` changes them when the vehicle's estimators change.

A *heartbeat* (a packet without data, only ``until_ns``: nothing happened up to it) moves the
stream's watermark and its sequence tracking and is never late; it is not queued.

A packet whose first sample time is at or before the horizon already released is **late**: it
is counted and never fed (feeding it would break the estimators' time order). Sequence numbers
are tracked per stream: an already-seen number is a **duplicate**; a jump forward counts the
skipped numbers as **lost** (taken back if they arrive later); a jump back, or forward, by more
than :data:`SEQ_WINDOW` is taken as a restart of the vehicle's counter (a gap that large cannot be
told from a reset or corrupted counter, so it is not counted lost).

Boot ids (``Packet.boot``, picked by the sender once per start): a packet whose boot differs from
the last one seen from the vehicle starts every stream's sequence tracking afresh (a counter
from 0 after a reboot is not a run of duplicates), counted as one restart when the boot is new
and the vehicle had been tracked; each stream's watermark run restarts at its next packet. The
tracking of the last :data:`BOOTS_KEPT` boots is kept: a packet of an earlier boot arriving
after the new one is checked against its own boot's numbers (a replay of it is still a
duplicate) and then by time like any other (usually late: the vehicle's time line has moved on).
Packets without a boot are tracked as before, by the numbers of the boot last seen.

Clock jumps (when ``clock_jump_ns`` is given): sensor time is compared with the wall time that
passed between arrivals. A packet whose first sample is more than ``clock_jump_ns`` ahead of the
newest sample time, by more than the wall time since the previous arrival allows, or whose last
sample is more than ``clock_jump_ns`` behind the released horizon, is a **clock jump**: refused,
so one wild stamp cannot drag the horizon with it (which would make every later packet late).
When ``reanchor_after`` such packets in a row agree with each other (within ``clock_jump_ns``)
the vehicle's clock really moved: the last one is answered :attr:`Verdict.REANCHOR` and the
caller starts the vehicle's time base afresh (:meth:`ReorderBuffer.reanchor`). A packet ahead by
more than ``clock_jump_ns`` that the wall time does explain (the vehicle was quiet) is answered
``REANCHOR`` at once: the estimators restart instead of stepping through the silence.

Time is always an argument; nothing here reads a clock.
"""

from __future__ import annotations

import heapq
import itertools
from collections.abc import Collection, Mapping
from dataclasses import dataclass
from enum import Enum

from server.protocol.base import Packet
from server.protocol.keys import Stream
from server.protocol.streams import STREAMS

__all__ = [
    "BOOTS_KEPT",
    "DEFAULT_STREAMS",
    "SEQ_WINDOW",
    "Offer",
    "ReorderBuffer",
    "SeqTracker",
    "StreamGap",
    "Verdict",
]

#: How far back (in sequence numbers) duplicates are recognised per stream.
SEQ_WINDOW = 4096
#: Boot ids per vehicle whose sequence tracking is kept (the current one and those before it).
BOOTS_KEPT = 4
#: Shortest start-up window (sensor time) before stream watermarks gate a vehicle's release.
WATERMARK_START_NS = 1_000_000_000
#: Shortest default idle time (wall clock) before a quiet vehicle's tail is released.
IDLE_MIN_NS = 1_000_000_000

#: The streams a vehicle is expected to send unless told otherwise.
DEFAULT_STREAMS: tuple[Stream, ...] = (Stream.GNSS, Stream.IMU, Stream.WHEELS)

_PRIORITY = {stream: spec.priority for stream, spec in STREAMS.items()}
_STREAM_NAMES: dict[Stream, str] = {stream: stream.value for stream in Stream}
# streams whose missing data is told (StreamGap), in priority order
_CUMULATIVE = tuple(
    sorted((s for s, spec in STREAMS.items() if spec.cumulative), key=_PRIORITY.__getitem__)
)


class Verdict(Enum):
    """What the buffer did with an offered packet."""

    ACCEPTED = "accepted"
    LATE = "late"
    DUPLICATE = "duplicate"
    CLOCK_JUMP = "clock_jump"  # refused: sensor time jumped (not yet confirmed)
    REANCHOR = "reanchor"  # not taken yet: flush, restart the estimators, then reanchor()


@dataclass(frozen=True, slots=True)
class Offer:
    """Outcome of :meth:`ReorderBuffer.offer`.

    Attributes
    ----------
    verdict : Verdict
    lost_delta : int
        Change of the lost-by-sequence-gap count (negative when a gap is filled).
    seq_restart : bool
        The stream's sequence number restarted with this packet.
    """

    verdict: Verdict
    lost_delta: int = 0
    seq_restart: bool = False


_ACCEPTED = Offer(Verdict.ACCEPTED)
_ACCEPTED_VERDICT = Verdict.ACCEPTED  # an enum member looked up on its class costs ~70 ns


@dataclass(frozen=True, slots=True)
class StreamGap:
    """Data of a cumulative stream missing where the release goes on without it.

    Attributes
    ----------
    stream : Stream
    after_ns : int
        Sensor time up to which the stream is complete.
    until_ns : int or None
        End of the released span due without the stream's data; None: the data is lost.
    before : Packet or None
        The first released packet starting after ``after_ns`` (None: none in that release):
        whoever must know is told before it is fed.
    """

    stream: Stream
    after_ns: int
    until_ns: int | None
    before: Packet | None


class _Missing:
    """One cumulative stream's missing data, found and not yet released."""

    __slots__ = ("lost_after_ns", "told_seq", "wait", "wait_told_ns")

    def __init__(self) -> None:
        self.told_seq: int | None = None  # the run's last number whose loss was told
        self.lost_after_ns: int | None = None  # a loss: the time the data was complete up to
        self.wait: tuple[int, int] | None = None  # a span due without the data
        self.wait_told_ns: int | None = None  # the end of the last span told

    def lost(self, after_ns: int, released_ns: int | None) -> None:
        """The data after ``after_ns`` is lost (told from what was released on, at least)."""
        if released_ns is not None and released_ns > after_ns:
            after_ns = released_ns  # what was released is done with
        if self.lost_after_ns is None or after_ns < self.lost_after_ns:
            self.lost_after_ns = after_ns

    def behind(self, skipped_ns: int, horizon_ns: int) -> None:
        """The horizon passes the stream's watermark: the span up to the horizon past the
        watermark after skipping missing packets (``skipped_ns``) is due without the stream."""
        told = self.wait_told_ns
        after = skipped_ns if told is None else max(skipped_ns, told)
        if horizon_ns > after:
            lo = after if self.wait is None else min(self.wait[0], after)
            self.wait = (lo, horizon_ns)
            self.wait_told_ns = horizon_ns

    def released(self, stream: Stream, out: list[Packet], gaps: list[StreamGap]) -> None:
        """Append the gaps found to ``gaps`` (the loss first), at a release of ``out``."""
        if self.lost_after_ns is not None:
            after, self.lost_after_ns = self.lost_after_ns, None
            gaps.append(StreamGap(stream, after, None, _first_after(out, after)))
        if self.wait is not None:
            (after, until), self.wait = self.wait, None
            gaps.append(StreamGap(stream, after, until, _first_after(out, after)))


def _first_after(packets: list[Packet], after_ns: int) -> Packet | None:
    """The first of ``packets`` that starts after ``after_ns`` (None: none does)."""
    return next((p for p in packets if p.first_stamp_ns > after_ns), None)


class SeqTracker:
    """Duplicate and gap detection for one stream (a bit mask over the last SEQ_WINDOW numbers)."""

    __slots__ = ("_first", "_highest", "_mask")

    def __init__(self) -> None:
        self._highest = -1
        self._first = -1  # numbers below the first one seen were never counted lost
        self._mask = 0  # bit i set: sequence number highest - i was seen

    @property
    def highest(self) -> int:
        """Highest sequence number seen (-1 before the first)."""
        return self._highest

    def resume(self, highest: int) -> None:
        """Continue after ``highest`` (stored by a previous server run): numbers after it that
        never arrive count as lost, so packets sent while the server was down are accounted."""
        self._highest, self._first, self._mask = int(highest), int(highest), 1

    def observe(self, seq: int) -> tuple[bool, int, bool]:
        """Return ``(is_duplicate, lost_delta, restarted)`` and record ``seq``."""
        if self._highest < 0:
            self._highest, self._first, self._mask = seq, seq, 1
            return False, 0, False
        if seq > self._highest:
            step = seq - self._highest
            if step > SEQ_WINDOW:  # also keeps the mask shift bounded
                self._highest, self._first, self._mask = seq, seq, 1
                return False, 0, True
            self._mask = ((self._mask << step) | 1) & ((1 << SEQ_WINDOW) - 1)
            self._highest = seq
            return False, step - 1, False
        back = self._highest - seq
        if back >= SEQ_WINDOW:
            self._highest, self._first, self._mask = seq, seq, 1
            return False, 0, True
        bit = 1 << back
        if self._mask & bit:
            return True, 0, False
        self._mask |= bit
        return False, (-1 if seq > self._first else 0), False


class _StreamMark:
    """One stream's watermark: the time its run of consecutive sequence numbers covers.

    Packets ahead of a gap wait in ``ahead`` (``seq -> last stamp``) until the gap fills, or
    until the fixed window passes them (:meth:`skip_gaps`: the missing ones are given up on).
    """

    __slots__ = ("ahead", "seq", "stamp_ns")

    def __init__(self, seq: int, stamp_ns: int) -> None:
        self.seq = seq
        self.stamp_ns = stamp_ns
        self.ahead: dict[int, int] = {}

    def arrived(self, seq: int, last_stamp_ns: int) -> None:
        if seq == self.seq + 1:
            self.seq = seq
            if last_stamp_ns > self.stamp_ns:
                self.stamp_ns = last_stamp_ns
            if self.ahead:
                self._follow()
        elif seq > self.seq + 1:
            self.ahead[seq] = last_stamp_ns
        # seq <= self.seq: a gap filled behind the run (already skipped): nothing to move

    def _follow(self) -> None:
        ahead = self.ahead
        while (nxt := ahead.pop(self.seq + 1, None)) is not None:
            self.seq += 1
            self.stamp_ns = max(self.stamp_ns, nxt)

    def passes_gap(self, horizon_ns: int) -> bool:
        """Whether :meth:`skip_gaps` at ``horizon_ns`` would give up on a missing packet."""
        ahead = self.ahead
        return bool(ahead) and ahead[min(ahead)] <= horizon_ns

    def skip_gaps(self, horizon_ns: int) -> None:
        """Give up on the missing packets before every waiting one the fixed window passed."""
        ahead = self.ahead
        while ahead:
            first = min(ahead)
            if ahead[first] > horizon_ns:
                return
            self.seq = first
            self.stamp_ns = max(self.stamp_ns, ahead.pop(first))
            self._follow()


class ReorderBuffer:
    """One vehicle's packets, released in order of first sample time.

    Parameters
    ----------
    lateness_ns : int
        Reorder window in sensor time (``IngestSettings.lateness_ms``).
    idle_ns : int, optional
        Wall time without arrivals after which everything pending is released (unless the
        watermarks gate: see the module docstring).
    clock_jump_ns : int, optional
        Sensor-time jump refused as a clock jump (see module docstring); None: no check.
    reanchor_after : int
        Consistent clock-jump packets in a row that move the vehicle's time base.
    watermarks : bool
        Release up to the streams' watermarks when they are ahead of the fixed window (see
        the module docstring); False: the fixed window alone.
    streams : collection of Stream
        The streams the vehicle is expected to send: watermarks gate only once each has one.
    """

    def __init__(
        self,
        lateness_ns: int,
        idle_ns: int | None = None,
        *,
        clock_jump_ns: int | None = None,
        reanchor_after: int = 5,
        watermarks: bool = False,
        streams: Collection[Stream] = DEFAULT_STREAMS,
    ) -> None:
        if lateness_ns < 0:
            raise ValueError("lateness_ns must be >= 0")
        if clock_jump_ns is not None and clock_jump_ns <= 0:
            raise ValueError("clock_jump_ns must be > 0")
        if reanchor_after < 1:
            raise ValueError("reanchor_after must be >= 1")
        self._jump_ns = clock_jump_ns
        self._reanchor_after = reanchor_after
        self._jumps_in_row = 0
        self._jump_newest_ns = 0
        self._jump_arrival_ns = 0
        self._lateness_ns = lateness_ns
        self._idle_ns = max(2 * lateness_ns, IDLE_MIN_NS) if idle_ns is None else idle_ns
        self._heap: list[tuple[int, int, int, int, Packet]] = []
        self._tie = itertools.count()
        self._seq: dict[Stream, SeqTracker] = {}  # the trackers of the current boot
        self._boot: int | None = None  # the boot id last seen (None: none yet)
        # each kept boot's trackers, the current one last (a packet's boot is looked up here)
        self._boots: dict[int, dict[Stream, SeqTracker]] = {}
        # streams whose watermark run starts afresh at their next packet (the boot changed)
        self._fresh: set[Stream] = set()
        self._newest_ns: int | None = None
        self._released_ns: int | None = None
        self._last_arrival_ns = 0
        self._watermarks: dict[Stream, _StreamMark] | None = {} if watermarks else None
        self._first_ns: int | None = None
        self._expected: tuple[Stream, ...] = ()
        self._watched: tuple[Stream, ...] = ()
        # the watermarks gate the release (every expected stream has one and the start-up
        # window has passed): once true it stays true until reanchor() or expect(), so it is kept
        self._gating = False
        self.expect(streams)
        # expected streams stalled now, and the stalls begun since the last take_stalls()
        self._stalled: set[Stream] = set()
        self._new_stalls: list[Stream] = []
        # cumulative streams' missing data not yet released, and the gaps released since the
        # last take_gaps()
        self._missing: dict[Stream, _Missing] = {}
        self._gaps: list[StreamGap] = []
        # the streams whose watermarks held the horizon at the last release (gating only; at
        # the lowest watermark, _low_ns): those whose marks moved past it since are taken out
        self._low_streams: list[Stream] | None = None
        self._low_ns = 0
        self._may_release = False

    def expect(self, streams: Collection[Stream]) -> None:
        """Expect ``streams`` from now on (the vehicle's estimators read them): the watermarks
        gate once each of them has one."""
        expected = tuple(sorted(frozenset(streams), key=_PRIORITY.__getitem__))
        if not expected:
            raise ValueError("streams must not be empty")
        if expected != self._expected:
            self._expected = expected
            # the expected cumulative streams, whose missing data is told (take_gaps)
            self._watched = tuple(s for s in _CUMULATIVE if s in expected)
            self._gating = False
            self._low_streams = None

    @property
    def expected(self) -> tuple[Stream, ...]:
        """The streams the vehicle is expected to send, in priority order."""
        return self._expected

    @property
    def stalled(self) -> frozenset[Stream]:
        """Expected streams the fixed window has passed (nothing of them, or nothing since)."""
        return frozenset(self._stalled)

    def take_stalls(self) -> tuple[Stream, ...]:
        """The streams that stalled since the last call (each stall told once)."""
        if not self._new_stalls:
            return ()
        out, self._new_stalls = tuple(self._new_stalls), []
        return out

    def _check_stalls(self, newest_ns: int, marks: Mapping[Stream, _StreamMark]) -> None:
        """Note the expected streams the fixed window passed (once the start-up window is
        over), and the ones back within it."""
        assert self._first_ns is not None
        window_ns = newest_ns - self._lateness_ns
        if newest_ns - self._first_ns < max(self._lateness_ns, WATERMARK_START_NS):
            return
        for s in self._expected:
            mark = marks.get(s)
            behind = mark is None or mark.stamp_ns < window_ns
            if behind and s not in self._stalled:
                self._stalled.add(s)
                self._new_stalls.append(s)
            elif not behind and s in self._stalled:
                self._stalled.discard(s)

    @property
    def pending(self) -> int:
        """Packets waiting for the horizon."""
        return len(self._heap)

    @property
    def drained(self) -> bool:
        """Nothing pending and released up to the newest sample: idle until the next packet."""
        return (
            not self._heap and self._newest_ns is not None and self._released_ns == self._newest_ns
        )

    @property
    def may_release(self) -> bool:
        """Packets taken since the last :meth:`release` may have moved the horizon (else only
        the idle time can: see :meth:`is_idle`).

        With watermarks gating, a packet moves the horizon only when it comes on the stream
        whose watermark held it, or its samples push the fixed window past what was released;
        a vehicle's other packets wait without costing a release each.
        """
        return self._may_release

    @property
    def released_ns(self) -> int | None:
        """Sensor time up to which everything has been released (None before the first release)."""
        return self._released_ns

    def offer(self, packet: Packet, now_ns: int) -> Offer:
        """Take one packet that arrived at monotonic time ``now_ns``."""
        boot = packet.boot
        new_boot = boot is not None and boot != self._boot and self._switch_boot(boot)
        tracker = self._seq.get(packet.stream)
        if tracker is None:
            tracker = self._seq[packet.stream] = SeqTracker()
        dup, lost_delta, restarted = tracker.observe(packet.seq)
        if dup:
            return Offer(Verdict.DUPLICATE)
        restarted = restarted or new_boot
        jump_ns, newest, released = self._jump_ns, self._newest_ns, self._released_ns
        if (
            jump_ns is not None
            and newest is not None
            # off the vehicle's time line (the check _clock_jump starts with, inline: the
            # common case costs no call)
            and (
                packet.first_stamp_ns - newest > jump_ns
                or (released is not None and packet.last_stamp_ns < released - jump_ns)
            )
        ):
            jump = self._clock_jump(packet, now_ns, jump_ns)
            if jump is not None:
                return Offer(jump, lost_delta, restarted)
        self._jumps_in_row = 0
        if (
            released is not None
            and packet.first_stamp_ns <= released
            and packet.measurements  # a heartbeat has nothing to feed: never late
        ):
            if packet.stream in _CUMULATIVE:  # its data is lost to the estimators from here on
                self._missing_of(packet.stream).lost(released, released)
            return Offer(Verdict.LATE, lost_delta, restarted)
        verdict = self._take(packet, now_ns, seq_restart=restarted)
        if lost_delta == 0 and not restarted:
            return _ACCEPTED  # the common case: no new (frozen) object per packet
        return Offer(verdict, lost_delta, restarted)

    def _switch_boot(self, boot: int) -> bool:
        """Track sequence numbers under ``boot`` from now on (a kept boot's trackers, else
        fresh ones); each stream's watermark run restarts at its next packet. Returns whether
        this counts as a restart: a boot not kept, when some stream had been tracked."""
        boots = self._boots
        known = boots.pop(boot, None)
        restarted = known is None and any(t.highest >= 0 for t in self._seq.values())
        self._seq = {} if known is None else known
        boots[boot] = self._seq  # the current boot last
        if len(boots) > BOOTS_KEPT:
            del boots[next(iter(boots))]  # the oldest
        self._boot = boot
        self._fresh = set(Stream)
        return restarted

    def _clock_jump(self, packet: Packet, now_ns: int, jump_ns: int) -> Verdict | None:
        """CLOCK_JUMP or REANCHOR when ``packet`` leaves the vehicle's time line, else None."""
        assert self._newest_ns is not None
        ahead_ns = packet.first_stamp_ns - self._newest_ns
        behind = (
            self._released_ns is not None and packet.last_stamp_ns < self._released_ns - jump_ns
        )
        if ahead_ns <= jump_ns and not behind:
            return None  # on the vehicle's time line (the common case)
        quiet_ns = max(0, now_ns - self._last_arrival_ns)
        if ahead_ns > jump_ns and ahead_ns <= jump_ns + quiet_ns:
            self._jumps_in_row = 0
            return Verdict.REANCHOR  # the vehicle was quiet that long: a gap, not a jump
        agrees = self._jumps_in_row > 0 and abs(
            packet.first_stamp_ns - self._jump_newest_ns
        ) <= jump_ns + max(0, now_ns - self._jump_arrival_ns)
        if agrees:
            self._jumps_in_row += 1
            self._jump_newest_ns = max(self._jump_newest_ns, packet.last_stamp_ns)
        else:
            self._jumps_in_row = 1
            self._jump_newest_ns = packet.last_stamp_ns
        self._jump_arrival_ns = now_ns
        if self._jumps_in_row >= self._reanchor_after:
            self._jumps_in_row = 0
            return Verdict.REANCHOR
        return Verdict.CLOCK_JUMP

    def reanchor(self, packet: Packet, now_ns: int) -> None:
        """Start a new time base with ``packet`` (after a REANCHOR verdict and a flush).

        Pending packets and the released horizon are forgotten (flush them first); sequence
        tracking carries on.
        """
        self._heap.clear()
        self._newest_ns = None
        self._released_ns = None
        self._jumps_in_row = 0
        self._first_ns = None
        self._gating = False
        self._low_streams = None
        self._missing.clear()  # the estimators restart
        self._stalled.clear()
        if self._watermarks is not None:
            self._watermarks.clear()
        self._take(packet, now_ns)

    def _take(self, packet: Packet, now_ns: int, *, seq_restart: bool = False) -> Verdict:
        # once per packet: the stream's watermark is moved here, not in a call of its own, and
        # _note_arrival is called only while the horizon is not known to move already
        self._last_arrival_ns = now_ns
        marks, stream = self._watermarks, packet.stream
        if marks is not None:
            mark = marks.get(stream)
            covers_ns = packet.covers_ns
            fresh = self._fresh
            if mark is None or seq_restart or (fresh and stream in fresh):
                fresh.discard(stream)
                marks[stream] = _StreamMark(packet.seq, covers_ns)
            else:
                mark.arrived(packet.seq, covers_ns)
        if not packet.measurements:  # a heartbeat moves its stream's watermark, nothing else
            if marks is not None and not self._may_release:
                self._note_arrival(stream)
            return _ACCEPTED_VERDICT
        last_ns = packet.last_stamp_ns
        if self._newest_ns is None or last_ns > self._newest_ns:
            self._newest_ns = last_ns
        if self._first_ns is None:
            self._first_ns = packet.first_stamp_ns
        heapq.heappush(
            self._heap,
            (packet.first_stamp_ns, _PRIORITY[stream], packet.seq, next(self._tie), packet),
        )
        if not self._may_release:
            self._note_arrival(stream)
        return _ACCEPTED_VERDICT

    def _note_arrival(self, stream: Stream) -> None:
        """Whether a packet of ``stream`` just taken may move the horizon (:attr:`may_release`):
        the released horizon is at least the lowest watermark, so while one of the streams at
        that watermark stays there and the fixed window does not pass it, the horizon does not
        move. Called only while :attr:`may_release` is False (once True it stays so until the
        next release)."""
        released, newest = self._released_ns, self._newest_ns
        lows, marks = self._low_streams, self._watermarks
        if lows and stream in lows and marks:
            mark = marks[stream]
            if mark.stamp_ns > self._low_ns or (
                # a packet after a gap that the fixed window already passed: the next
                # release gives up on the missing one and the watermark moves to it
                newest is not None and mark.passes_gap(newest - self._lateness_ns)
            ):
                lows.remove(stream)
        self._may_release = (
            not lows  # no watermark gating (or released at an idle time or a flush), or every
            # stream at the lowest watermark moved past it
            or released is None
            or newest is None
            or newest - self._lateness_ns > released
        )

    def _missing_of(self, stream: Stream) -> _Missing:
        missing = self._missing.get(stream)
        if missing is None:
            missing = self._missing[stream] = _Missing()
        return missing

    def take_gaps(self) -> tuple[StreamGap, ...]:
        """Data of cumulative streams missing at the releases since the last call, oldest
        first (per release: by stream priority, a loss before a span due)."""
        if not self._gaps:
            return ()
        gaps, self._gaps = tuple(self._gaps), []
        return gaps

    def is_idle(self, now_ns: int) -> bool:
        """No packet arrived for the idle time (the vehicle stopped sending, for now)."""
        return now_ns - self._last_arrival_ns >= self._idle_ns

    def seq_highest(self) -> dict[str, int]:
        """Highest sequence number seen per stream, ``{stream name: seq}`` (every vehicle's,
        once a second: the names are looked up, not read off the enum members)."""
        names = _STREAM_NAMES
        return {names[stream]: t.highest for stream, t in self._seq.items() if t.highest >= 0}

    @property
    def boot(self) -> int | None:
        """The boot id last seen from the vehicle (None: none yet)."""
        return self._boot

    def resume_seq(self, highest: Mapping[str, int], boot: int | None = None) -> None:
        """Continue each stream's sequence tracking after ``highest[stream name]``, under
        ``boot`` (the boot id they were seen with; None: none was)."""
        for stream in Stream:
            if stream.value in highest:
                tracker = self._seq[stream] = SeqTracker()
                tracker.resume(highest[stream.value])
        if boot is not None:
            self._boot = boot
            self._boots = {boot: self._seq}

    def horizon_ns(self, now_ns: int) -> int | None:
        """The sensor time that may be released at ``now_ns`` (None while nothing arrived)."""
        newest = self._newest_ns
        if newest is None:
            return None
        self._low_streams = None  # unless the watermarks gate below
        horizon = newest - self._lateness_ns
        marks = self._watermarks
        if marks is not None and self._first_ns is not None:
            self._check_stalls(newest, marks)
        if marks and self._first_ns is not None:
            # each cumulative stream's watermark before a gap is skipped, and its run's last
            # number when a packet is missing and later ones are here
            before: list[tuple[Stream, int, int | None]] = []
            for s in self._watched:
                watched = marks.get(s)
                if watched is not None:
                    before.append((s, watched.stamp_ns, watched.seq if watched.ahead else None))
            for mark in marks.values():
                if mark.ahead:
                    mark.skip_gaps(horizon)
            if self._gating or self._starts_gating(newest, marks):
                lowest = self._lowest(marks)
                if lowest > horizon:
                    horizon = lowest
                for s, mark_ns, run_seq in before:
                    if horizon > mark_ns:
                        self._behind(s, mark_ns, run_seq, marks[s].stamp_ns, horizon)
        if self._low_streams is None and now_ns - self._last_arrival_ns >= self._idle_ns:
            # idle, and no watermarks tell how far each stream is complete: release everything
            horizon = newest
        released = self._released_ns
        if released is not None and horizon < released:
            return released
        return horizon

    def _lowest(self, marks: dict[Stream, _StreamMark]) -> int:
        """The lowest watermark of the expected streams; the streams at it are kept
        (:meth:`_note_arrival`)."""
        expected = self._expected
        lowest = marks[expected[0]].stamp_ns
        lows = [expected[0]]
        for s in expected[1:]:
            stamp = marks[s].stamp_ns
            if stamp < lowest:
                lows, lowest = [s], stamp
            elif stamp == lowest:
                lows.append(s)
        self._low_streams, self._low_ns = lows, lowest
        return lowest

    def _behind(
        self, stream: Stream, mark_ns: int, run_seq: int | None, skipped_ns: int, horizon_ns: int
    ) -> None:
        """The horizon passes ``stream``'s watermark ``mark_ns``: lost data if a packet is
        missing and later ones came (``run_seq``, the run's last number; told once a loss);
        the span past the watermark after skipping the missing packets (``skipped_ns``) up to
        the horizon is due without the stream."""
        missing = self._missing_of(stream)
        if run_seq is not None and run_seq != missing.told_seq:
            missing.told_seq = run_seq
            missing.lost(mark_ns, self._released_ns)
        missing.behind(skipped_ns, horizon_ns)

    def _starts_gating(self, newest_ns: int, marks: dict[Stream, _StreamMark]) -> bool:
        """Whether the watermarks gate from now on (see :attr:`_gating`)."""
        assert self._first_ns is not None
        self._gating = all(
            s in marks for s in self._expected
        ) and newest_ns - self._first_ns >= max(self._lateness_ns, WATERMARK_START_NS)
        return self._gating

    def release(self, now_ns: int, *, flush: bool = False) -> tuple[list[Packet], int | None]:
        """Pop every packet at or before the horizon, in order.

        Returns ``(packets, released_ns)``: the packets to feed, and the sensor time the
        estimators may advance to (None before anything was released). ``flush`` releases
        everything (shutdown).
        """
        if flush:
            horizon, self._low_streams = self._newest_ns, None
        else:
            horizon = self.horizon_ns(now_ns)
        if horizon is None:
            return [], self._released_ns
        self._may_release = False
        out: list[Packet] = []
        heap = self._heap
        while heap and heap[0][0] <= horizon:
            out.append(heapq.heappop(heap)[-1])
        if self._missing:
            for stream in _CUMULATIVE:
                missing = self._missing.get(stream)
                if missing is not None:
                    missing.released(stream, out, self._gaps)
        if self._released_ns is None or horizon > self._released_ns:
            self._released_ns = horizon
        return out, self._released_ns
