"""A drive's packets through the encoded schedule, checked against the per-packet encoding."""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable, Collection

from server.protocol import Stream
from server.tooling.fleet_schedule import STREAMS, EncodedDrive, ScheduledVehicle, _Fleet, render
from server.tooling.fleet_sim import TICK_NS, SimPacket, loop_period_ns

MS = 1_000_000


def assert_schedule_patches_like_encoding(
    packets: list[SimPacket], start_ns: int, streams: Collection[Stream]
) -> None:
    """Two vehicles (phases 0 and 37 ms, their own stamp shifts) play ``packets`` for two
    loops: each sends on ``streams`` only, every payload byte for byte what
    :meth:`SimPacket.encode` makes of the packet with that vehicle's sequence number and
    shift, over the loops."""
    period = loop_period_ns(start_ns, start_ns + packets[-1].arrival_offset_ns)
    calls: dict[tuple[int, int], list[bytes]] = defaultdict(list)

    def put(v: int, s: int) -> Callable[[bytes], None]:
        return lambda payload: calls[(v, s)].append(payload)

    vehicles = [
        ScheduledVehicle(
            0, ph, 7_000_000_011 * (i + 1), tuple(put(i, s) for s in range(len(STREAMS)))
        )
        for i, ph in enumerate([0, 37 * MS])
    ]
    fleet = _Fleet([EncodedDrive(packets, period)], vehicles)
    for t in range(0, 2 * period, TICK_NS):  # two loops
        w = render(fleet, t, t + TICK_NS, loop=True)
        for call, payload in zip(w.calls, w.payloads, strict=True):
            call(payload)
    assert calls.keys() == {(v, STREAMS.index(s)) for v in (0, 1) for s in streams}
    for (v, s), payloads in calls.items():
        mine = [p for p in packets if p.stream is STREAMS[s]]
        assert len(payloads) == 2 * len(mine)
        for seq, payload in enumerate(payloads):
            loop, i = divmod(seq, len(mine))
            assert payload == mine[i].encode(seq, vehicles[v].shift_ns + loop * period)
