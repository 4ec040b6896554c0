"""Per-vehicle ingest counters.

Every packet that reaches the pipeline is counted ``received`` and then exactly one of
``accepted`` (entered the reorder buffer and will be fed to the estimators), ``late`` (older than
the released horizon, dropped), ``duplicate`` (sequence number already seen) or
``rejected_<reason>`` (decode failures, ``unknown_vehicle``). Hence, at every snapshot::

    received == accepted + late + duplicate + rejected          (rejected = sum of rejected_*)

``lost_by_seq_gap`` counts sequence numbers that never arrived (a gap that is later filled by a
reordered packet is taken back), so it is not part of the sum. ``seq_restarts`` counts streams
whose sequence jumped far (a vehicle reboot), and ``clock_reanchors`` the times a vehicle's time
base was started afresh (a confirmed clock jump, or data resuming after a long silence; see
:mod:`server.ingest.reorder`), and ``wheel_gaps`` the times wheel data was lost before
a released wheel packet (the wheels' speed fits started afresh: ``estimator.types.WheelGap``),
and ``stalled_<stream>`` the times a stream the vehicle's estimators read stopped arriving
(the reorder window passed it: :meth:`server.ingest.reorder.ReorderBuffer.take_stalls`;
kept only once counted), all informational. ``estimator_errors`` counts the estimator calls
that raised for the vehicle (its rows of that call lost) and ``configs_refused`` the configs
an estimator refused (the vehicle kept its old one).

Only the pipeline thread writes; snapshots may be taken from any thread.
"""

from __future__ import annotations

import threading
from collections import defaultdict
from collections.abc import Mapping

__all__ = ["NO_VEHICLE", "PLAIN_COUNTERS", "IngestCounters"]

#: Bucket for packets whose key names no valid vehicle.
NO_VEHICLE = ""


#: The counters every vehicle has (beside ``rejected_<reason>`` and ``stalled_<stream>``).
PLAIN_COUNTERS = (
    "received",
    "accepted",
    "late",
    "duplicate",
    "lost_by_seq_gap",
    "seq_restarts",
    "clock_reanchors",
    "wheel_gaps",
    "estimator_errors",
    "configs_refused",
)


class _VehicleCounts:
    __slots__ = (
        "accepted",
        "clock_reanchors",
        "configs_refused",
        "duplicate",
        "estimator_errors",
        "late",
        "lost_by_seq_gap",
        "received",
        "rejected",
        "seq_restarts",
        "stalled",
        "wheel_gaps",
    )

    def __init__(self) -> None:
        self.received = 0
        self.accepted = 0
        self.late = 0
        self.duplicate = 0
        self.lost_by_seq_gap = 0
        self.seq_restarts = 0
        self.clock_reanchors = 0
        self.wheel_gaps = 0
        self.estimator_errors = 0
        self.configs_refused = 0
        self.rejected: dict[str, int] = defaultdict(int)
        self.stalled: dict[str, int] = defaultdict(int)

    def as_dict(self) -> dict[str, int]:
        # every vehicle's, once a second: the refusals and stalls most have none of are
        # summed and listed only when there are some
        rejected, stalled = self.rejected, self.stalled
        out = {
            "received": self.received,
            "accepted": self.accepted,
            "late": self.late,
            "duplicate": self.duplicate,
            "rejected": sum(rejected.values()) if rejected else 0,
            "lost_by_seq_gap": self.lost_by_seq_gap,
            "seq_restarts": self.seq_restarts,
            "clock_reanchors": self.clock_reanchors,
            "wheel_gaps": self.wheel_gaps,
            "estimator_errors": self.estimator_errors,
            "configs_refused": self.configs_refused,
        }
        if rejected:
            for reason, n in sorted(rejected.items()):
                out[f"rejected_{reason}"] = n
        if stalled:
            for stream, n in sorted(stalled.items()):
                out[f"stalled_{stream}"] = n
        return out


class IngestCounters:
    """Counters keyed by vehicle id (see module docstring for the invariant)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._by_vehicle: dict[str, _VehicleCounts] = {}

    def _get(self, vehicle_id: str) -> _VehicleCounts:
        c = self._by_vehicle.get(vehicle_id)
        if c is None:
            c = self._by_vehicle[vehicle_id] = _VehicleCounts()
        return c

    def accepted(self, vehicle_id: str, lost_delta: int = 0) -> None:
        """One packet received and accepted; ``lost_delta`` adjusts ``lost_by_seq_gap``."""
        with self._lock:
            c = self._get(vehicle_id)
            c.received += 1
            c.accepted += 1
            c.lost_by_seq_gap += lost_delta

    def accepted_many(self, counts: Mapping[str, tuple[int, int]]) -> None:
        """Packets received and accepted, ``counts[vehicle_id] = (packets, lost_delta)`` (a
        burst's worth: one lock for all of them)."""
        with self._lock:
            for vehicle_id, (packets, lost_delta) in counts.items():
                c = self._get(vehicle_id)
                c.received += packets
                c.accepted += packets
                c.lost_by_seq_gap += lost_delta

    def late(self, vehicle_id: str, lost_delta: int = 0) -> None:
        """One packet received after its time was released."""
        with self._lock:
            c = self._get(vehicle_id)
            c.received += 1
            c.late += 1
            c.lost_by_seq_gap += lost_delta

    def duplicate(self, vehicle_id: str) -> None:
        """One packet whose sequence number was already seen."""
        with self._lock:
            c = self._get(vehicle_id)
            c.received += 1
            c.duplicate += 1

    def rejected(self, vehicle_id: str | None, reason: str, lost_delta: int = 0) -> None:
        """One packet refused for ``reason`` (a codec or pipeline reason)."""
        with self._lock:
            c = self._get(NO_VEHICLE if vehicle_id is None else vehicle_id)
            c.received += 1
            c.rejected[reason] += 1
            c.lost_by_seq_gap += lost_delta

    def seq_restart(self, vehicle_id: str) -> None:
        """A stream's sequence number restarted (informational)."""
        with self._lock:
            self._get(vehicle_id).seq_restarts += 1

    def clock_reanchor(self, vehicle_id: str) -> None:
        """A vehicle's time base was started afresh (informational)."""
        with self._lock:
            self._get(vehicle_id).clock_reanchors += 1

    def wheel_gap(self, vehicle_id: str) -> None:
        """Wheel data was lost before a released packet; the wheel fits started afresh."""
        with self._lock:
            self._get(vehicle_id).wheel_gaps += 1

    def stream_stalled(self, vehicle_id: str, stream: str) -> None:
        """A stream the vehicle's estimators read stopped arriving (informational)."""
        with self._lock:
            self._get(vehicle_id).stalled[stream] += 1

    def estimator_error(self, vehicle_id: str | None) -> None:
        """An estimator call raised for the vehicle (informational)."""
        with self._lock:
            self._get(NO_VEHICLE if vehicle_id is None else vehicle_id).estimator_errors += 1

    def config_refused(self, vehicle_id: str | None) -> None:
        """An estimator refused the vehicle's new config; the old one is kept."""
        with self._lock:
            self._get(NO_VEHICLE if vehicle_id is None else vehicle_id).configs_refused += 1

    def restore(self, vehicle_id: str, totals: Mapping[str, int]) -> None:
        """Carry on from stored totals (a restarted server); adds to what is counted so far.

        ``totals`` is a snapshot as :meth:`snapshot` gives it, so the invariant still holds.
        """
        with self._lock:
            c = self._get(vehicle_id)
            for name in PLAIN_COUNTERS:
                setattr(c, name, getattr(c, name) + int(totals.get(name, 0)))
            for key, value in totals.items():
                if key.startswith("rejected_"):
                    c.rejected[key.removeprefix("rejected_")] += int(value)
                elif key.startswith("stalled_"):
                    c.stalled[key.removeprefix("stalled_")] += int(value)

    def forget(self, vehicle_id: str) -> None:
        """Drop a vehicle's counters (after it is deleted)."""
        with self._lock:
            self._by_vehicle.pop(vehicle_id, None)

    def snapshot(self) -> dict[str, dict[str, int]]:
        """``{vehicle_id: {counter: value}}``, a consistent copy."""
        with self._lock:
            return {vid: c.as_dict() for vid, c in self._by_vehicle.items()}

    def totals(self) -> dict[str, int]:
        """Counters summed over every vehicle."""
        out: dict[str, int] = defaultdict(int)
        for counts in self.snapshot().values():
            for k, v in counts.items():
                out[k] += v
        return dict(out)
