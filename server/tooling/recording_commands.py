"""``slipfleet replay`` and ``slipfleet record --live``: recordings to and from a running fleet.

Replay publishes a recording (``docs/protocol.md`` §8) to a router, optionally under another
vehicle id (``--as``: beside the vehicle it came from, whose sequence numbers the server has
already seen) and with its stamps moved (``--shift``: to now, or by given seconds). Before and
after, it reads the server's packet counters for the vehicles it publishes
(:mod:`server.tooling.api_client`) and says what the server made of the packets — accepted,
duplicate, late, rejected — exiting 1 when not every packet was accepted, instead of reporting
a success the server never saw.

``record --live`` writes what the router delivers of the fleet's sensor packets and configs,
as the server receives them, until the duration passes or Ctrl-C.
"""

from __future__ import annotations

import signal
import threading
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from server.protocol.recording import RecordingError, read_recording
from server.settings import Settings
from server.tooling.api_client import (
    OUTCOMES,
    check_metrics_access,
    open_client,
    vehicle_packet_counts,
)
from server.tooling.fleet_commands import vehicle_session
from server.tooling.fleet_sim import record as record_session
from server.tooling.fleet_sim import replay as replay_recording
from server.tooling.fleet_sim import vehicle_of_key

if TYPE_CHECKING:
    import httpx

__all__ = ["ReplayTarget", "record_live", "recording_vehicles", "replay"]

#: How long replay waits for the server to count what it published.
SETTLE_S = 15.0


def recording_vehicles(path: Path) -> list[str]:
    """The vehicle ids a recording holds (sorted); SystemExit with one line if it is not one."""
    try:
        return sorted({vehicle_of_key(r.key) for r in read_recording(path)})
    except (RecordingError, OSError) as exc:
        raise SystemExit(f"cannot replay {path}: {exc}") from exc


@dataclass(frozen=True)
class ReplayTarget:
    """Where and how a recording is replayed: the router, the server's API, the renaming and
    the shift (None: the recording starts now)."""

    endpoints: Sequence[str]
    api: str
    api_given: bool
    token: str | None
    vehicle_as: str | None
    shift_ns: int | None
    rate: float


class _ServerCounts:
    """The server's packet counters of the replayed vehicles, read through its API."""

    def __init__(self, client: httpx.Client, api: str, vehicle_ids: Sequence[str]) -> None:
        self.client, self.api, self.vehicle_ids = client, api, vehicle_ids
        self.before = self.read()

    def read(self) -> Counter[str]:
        total: Counter[str] = Counter()
        for counts in vehicle_packet_counts(self.client, self.api, self.vehicle_ids).values():
            total.update(counts)
        return total

    def settle(self, published: int) -> Counter[str]:
        """What the server counted since :attr:`before`, once it counted ``published`` packets
        (or :data:`SETTLE_S` passed)."""
        deadline = time.monotonic() + SETTLE_S
        while True:
            delta = self.read()
            delta.subtract(self.before)
            if delta["received"] >= published or time.monotonic() > deadline:
                return delta
            time.sleep(0.2)


def _open_counts(target: ReplayTarget, vehicle_ids: Sequence[str]) -> _ServerCounts | None:
    client = open_client(target.token, timeout_s=10.0)
    try:
        check_metrics_access(client, target.api)
        return _ServerCounts(client, target.api, vehicle_ids)
    except SystemExit as exc:
        client.close()
        if target.api_given:
            raise
        print(f"not reading what the server accepts: {exc} (give --api URL)")
        return None


def _verdict(published: int, delta: Counter[str], vehicle_ids: Sequence[str]) -> list[str]:
    """Lines saying what the server made of ``published`` packets, with what to do about it."""
    counted = ", ".join(f"{delta[k]} {k}" for k in OUTCOMES[1:])
    ids = ", ".join(vehicle_ids)
    head = f"the server received {delta['received']} of them"
    if delta["received"] > published:  # the counters are per vehicle: its own traffic is in
        head = (
            f"the server received {delta['received']} packets of {ids} meanwhile, "
            f"{delta['received'] - published} more than were replayed (the vehicle is sending "
            "too, so these counts mix both)"
        )
    lines = [f"{head}: {counted}"]
    if delta["duplicate"]:
        lines.append(
            f"duplicate: the server had already seen these sequence numbers from {ids} (that "
            "vehicle is sending, or this recording was replayed before): replay beside it "
            "with --as NEW_ID"
        )
    if delta["late"]:
        lines.append(
            f"late: their stamps lie before what the server had already processed of {ids}: "
            "--shift auto moves the recording to now"
        )
    if delta["rejected"]:
        lines.append("rejected: see the server's log and /api/v1/metrics for the reasons")
    if delta["received"] < published:
        lines.append(f"{published - delta['received']} not counted within {SETTLE_S:.0f} s")
    return lines


def replay(path: Path, target: ReplayTarget) -> int:
    """Publish the recording at ``path`` as ``target`` says; print what the server made of it.

    Returns the exit status: 0 when the server accepted every packet (or could not be asked),
    1 otherwise."""
    recorded = recording_vehicles(path)
    if target.vehicle_as is not None and len(recorded) != 1:
        raise SystemExit(
            f"--as renames one vehicle, but {path} holds {len(recorded)}: {', '.join(recorded)}"
        )
    vehicle_ids = [target.vehicle_as] if target.vehicle_as else recorded
    counts = _open_counts(target, vehicle_ids)
    if counts is not None and counts.before["received"]:
        print(
            f"the server already has packets of {', '.join(vehicle_ids)}: those this recording "
            "overlaps count as duplicates (--as NEW_ID replays beside them)"
        )
    with vehicle_session(list(target.endpoints)) as session:
        stats = replay_recording(
            path,
            session,
            rate=target.rate,
            shift_ns=target.shift_ns,
            vehicle_as=target.vehicle_as,
        )
    published = stats.total_packets
    print(f"published {published} packets of {', '.join(vehicle_ids)} in {stats.wall_s:.1f} s")
    if counts is None:
        return 0
    delta = counts.settle(published)
    counts.client.close()
    print("\n".join(_verdict(published, delta, vehicle_ids)))
    return 0 if delta["accepted"] == published else 1


def record_live(settings: Settings, path: Path, duration_s: float | None) -> int:
    """Record the fleet's traffic on the configured router(s) to ``path`` until ``duration_s``
    passes (None: until Ctrl-C); return how many records were written."""
    endpoints = list(settings.zenoh.connect or settings.zenoh.listen)
    stop = threading.Event()
    previous = signal.signal(signal.SIGINT, lambda *_: stop.set())
    try:
        ready = f"recording {settings.zenoh.key_prefix}/** from {', '.join(endpoints)}" + (
            "; Ctrl-C stops" if duration_s is None else f" for {duration_s:g} s"
        )
        with vehicle_session(endpoints) as session:
            n = record_session(
                path,
                session,
                f"{settings.zenoh.key_prefix}/**",
                duration_s=duration_s,
                stop=stop,
                on_ready=lambda: print(ready, flush=True),
            )
    finally:
        signal.signal(signal.SIGINT, previous)
    print(f"wrote {n} records to {path}")
    return n
