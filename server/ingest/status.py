"""Tell each vehicle what the server refuses of it (``docs/protocol.md`` §6.2).

The ingest counters (:mod:`server.ingest.counters`) count refused packets by reason, totals over
the vehicle's life. Once a second :class:`StatusPublisher` takes a snapshot of them;
:class:`RefusalWindow` turns the totals into the counts of the last minute and decides:

* a status ``<prefix>/<vehicle_id>/status`` (JSON, see :func:`status_payload`) every
  ``PUBLISH_EVERY_NS`` while the vehicle has refusals in the last minute, and once more, with
  no counts, when it has none any more;
* a server log line on the first refusal of each reason of a vehicle, then at most one a
  minute per vehicle and reason, with the count since the previous line.

Refusals without a vehicle (a key naming none) are logged by nobody here: there is no one to
tell.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping

import zenoh

from server.ingest.counters import NO_VEHICLE

__all__ = [
    "LOG_EVERY_NS",
    "PUBLISH_EVERY_NS",
    "WINDOW_NS",
    "RefusalWindow",
    "StatusPublisher",
    "refused_of",
    "status_key",
    "status_payload",
]

log = logging.getLogger(__name__)

#: The span the status counts refusals over.
WINDOW_NS = 60 * 10**9
#: How often a refused vehicle's status is published.
PUBLISH_EVERY_NS = 5 * 10**9
#: At most one log line per vehicle and reason this often (the first refusal at once).
LOG_EVERY_NS = 60 * 10**9

_REJECTED = "rejected_"

Counts = dict[str, int]


def refused_of(counts: Mapping[str, int]) -> Counts:
    """``{reason: n}`` of a vehicle's counter snapshot (its ``rejected_<reason>`` entries)."""
    return {k[len(_REJECTED) :]: v for k, v in counts.items() if k.startswith(_REJECTED) and v}


def status_key(prefix: str, vehicle_id: str) -> str:
    """``<prefix>/<vehicle_id>/status``."""
    return f"{prefix}/{vehicle_id}/status"


def status_payload(vehicle_id: str, refused: Counts, stamp_ns: int) -> bytes:
    """The status message: ``vehicle_id``, ``stamp_ns`` (server UTC), ``window_s``,
    ``refused`` (``{reason: packets}`` over the window, empty once refusals stopped) and
    ``refused_total`` (their sum)."""
    body = {
        "vehicle_id": vehicle_id,
        "stamp_ns": stamp_ns,
        "window_s": WINDOW_NS // 10**9,
        "refused": dict(sorted(refused.items())),
        "refused_total": sum(refused.values()),
    }
    return json.dumps(body).encode()


class RefusalWindow:
    """Refusal counts over the last ``window_ns`` from snapshots of the totals, and which
    vehicles to tell (pure: the clock is the caller's).

    Each vehicle keeps ``(t_ns, totals)`` entries, one per change; the oldest kept entry is the
    totals as of the window's start, so the window's counts are ``totals - oldest``.
    """

    def __init__(
        self,
        window_ns: int = WINDOW_NS,
        every_ns: int = PUBLISH_EVERY_NS,
        log_every_ns: int = LOG_EVERY_NS,
    ) -> None:
        self._window_ns = window_ns
        self._every_ns = every_ns
        self._log_every_ns = log_every_ns
        self._history: dict[str, deque[tuple[int, Counts]]] = {}
        self._sent_ns: dict[str, int] = {}  # refused vehicle -> when its status last went out
        self._logged: dict[tuple[str, str], tuple[int, int]] = {}  # -> (next line ns, total)

    def prime(self, snapshot: Mapping[str, Mapping[str, int]], now_ns: int) -> None:
        """Take the totals present now (restored from a previous run) as old: they are neither
        in the window nor logged."""
        for vid, counts in snapshot.items():
            totals = refused_of(counts)
            self._history[vid] = deque([(now_ns - self._window_ns, totals)])
            for reason, n in totals.items():
                self._logged[(vid, reason)] = (now_ns, n)

    def update(
        self, snapshot: Mapping[str, Mapping[str, int]], now_ns: int
    ) -> list[tuple[str, Counts]]:
        """The ``(vehicle_id, refused over the window)`` statuses due now; logs as it goes."""
        due: list[tuple[str, Counts]] = []
        for vid, counts in snapshot.items():
            if vid == NO_VEHICLE:
                continue
            totals = refused_of(counts)
            window = self._window(vid, totals, now_ns)
            self._log(vid, totals, now_ns)
            if self._due(vid, bool(window), now_ns):
                due.append((vid, window))
        for gone in self._history.keys() - snapshot.keys():  # deleted vehicles
            self._history.pop(gone)
            self._sent_ns.pop(gone, None)
        return due

    def _window(self, vid: str, totals: Counts, now_ns: int) -> Counts:
        history = self._history.get(vid)
        if history is None:  # a vehicle new since the start: nothing refused before
            history = self._history[vid] = deque([(now_ns - self._window_ns, {})])
        if history[-1][1] != totals:
            history.append((now_ns, totals))
        start_ns = now_ns - self._window_ns
        while len(history) > 1 and history[1][0] <= start_ns:
            history.popleft()
        old = history[0][1]
        return {r: n - old.get(r, 0) for r, n in totals.items() if n > old.get(r, 0)}

    def _due(self, vid: str, refused: bool, now_ns: int) -> bool:
        sent_ns = self._sent_ns.get(vid)
        if not refused:  # once when the refusals stop
            return self._sent_ns.pop(vid, None) is not None
        if sent_ns is not None and now_ns < sent_ns + self._every_ns:
            return False
        self._sent_ns[vid] = now_ns
        return True

    def _log(self, vid: str, totals: Counts, now_ns: int) -> None:
        for reason, n in totals.items():
            next_ns, logged = self._logged.get((vid, reason), (None, 0))
            if n <= logged or (next_ns is not None and now_ns < next_ns):
                continue
            if next_ns is None:
                log.warning("vehicle %s: packets refused (%s): %d", vid, reason, n - logged)
            else:
                log.warning(
                    "vehicle %s: %d more packets refused (%s) since the last line",
                    vid,
                    n - logged,
                    reason,
                )
            self._logged[(vid, reason)] = (now_ns + self._log_every_ns, n)


class StatusPublisher:
    """Publishes the vehicles' statuses from ``snapshot`` (the ingest counters) once every
    ``poll_s`` on its own thread, as plain puts (as the alerts go)."""

    def __init__(
        self,
        session: zenoh.Session,
        prefix: str,
        snapshot: Callable[[], Mapping[str, Mapping[str, int]]],
        *,
        poll_s: float = 1.0,
        window: RefusalWindow | None = None,
        clock_ns: Callable[[], int] = time.monotonic_ns,
        wall_clock_ns: Callable[[], int] = time.time_ns,
    ) -> None:
        self._session = session
        self._prefix = prefix
        self._snapshot = snapshot
        self._poll_s = poll_s
        self._window = window if window is not None else RefusalWindow()
        self._clock = clock_ns
        self._wall_clock = wall_clock_ns
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        """Take the present totals as old, then publish from a daemon thread."""
        self._window.prime(self._snapshot(), self._clock())
        self._thread = threading.Thread(target=self._run, name="slipfleet-status", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    def step(self) -> int:
        """Publish the statuses due now; how many."""
        due = self._window.update(self._snapshot(), self._clock())
        stamp_ns = self._wall_clock()
        for vid, refused in due:
            self._session.put(status_key(self._prefix, vid), status_payload(vid, refused, stamp_ns))
        return len(due)

    def _run(self) -> None:
        while not self._stop.wait(self._poll_s):
            try:
                self.step()
            except Exception:  # a closed session at shutdown, a bug: ingest goes on regardless
                log.exception("vehicle status step failed")
