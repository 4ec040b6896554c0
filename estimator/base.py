"""The interface the server drives every estimator through.

An estimator is *fleet-wide*: one object holds every vehicle that runs it, so it can step them
in one numpy call. The server feeds each vehicle's measurements in sensor-time order (its reorder
buffer guarantees that) and then asks for every tick that the released data completes.

Its :class:`~estimator.spec.EstimatorSpec` says which wire streams it takes (``inputs``: the
server pushes it only those, see :func:`stream_of`) and what its rows are (``spec.dtype``).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Protocol, runtime_checkable

import numpy as np

from estimator.config import VehicleConfig
from estimator.spec import EstimatorSpec
from estimator.types import (
    GnssSample,
    ImuBatch,
    OdometerEdges,
    SprocketEdges,
    SteeringAngles,
    WheelEdges,
    WheelGap,
    WheelSpeeds,
    WheelSpeeds4,
)

__all__ = [
    "STREAMS",
    "Anchored",
    "FleetEstimator",
    "HoldsRows",
    "KeepsCounters",
    "Measurement",
    "Pushed",
    "TakesCommands",
    "held_rows",
    "stream_of",
]

#: A measurement of any sensor stream; an estimator is handed those of the streams it takes.
Measurement = (
    GnssSample
    | ImuBatch
    | WheelEdges
    | WheelSpeeds
    | OdometerEdges
    | SprocketEdges
    | SteeringAngles
    | WheelSpeeds4
)

#: What :meth:`FleetEstimator.push` takes: a measurement, or a notice of lost data.
Pushed = Measurement | WheelGap

#: Wire stream each pushed type comes from (the names a spec's ``inputs`` list); a wheel gap
#: is news of the ``wheels`` stream.
#: (The server's stream declarations, ``server.protocol.streams``, are checked against it.)
_STREAM_OF_TYPE: Mapping[type, str] = {
    GnssSample: "gnss",
    ImuBatch: "imu",
    WheelEdges: "wheels",
    WheelSpeeds: "wheels",
    WheelGap: "wheels",
    OdometerEdges: "odometer",
    SprocketEdges: "sprockets",
    SteeringAngles: "steering",
    WheelSpeeds4: "wheel_speeds4",
}

#: Every wire stream a spec's ``inputs`` may name.
STREAMS: tuple[str, ...] = tuple(dict.fromkeys(_STREAM_OF_TYPE.values()))


def stream_of(pushed: Pushed) -> str:
    """The wire stream ``pushed`` belongs to (``TypeError`` for anything else)."""
    try:
        return _STREAM_OF_TYPE[type(pushed)]
    except KeyError:
        raise TypeError(f"not a measurement: {type(pushed).__name__}") from None


@runtime_checkable
class FleetEstimator(Protocol):
    """Many vehicles' estimators behind one batched step.

    Attributes
    ----------
    name : str
        Registry name, the same as ``spec.name`` (``"mdsf"``, ``"reference_speed"``).
    spec : EstimatorSpec
        What it takes (``spec.inputs``: only those streams are pushed) and gives: the rows
        :meth:`advance` returns are of ``spec.dtype`` (``ESTIMATE_DTYPE`` for MDSF).
    """

    name: str
    spec: EstimatorSpec

    def add_vehicle(self, vehicle_id: str, config: VehicleConfig) -> None:
        """Start estimating ``vehicle_id``; replaces its config if it is already there."""

    def remove_vehicle(self, vehicle_id: str) -> None:
        """Forget ``vehicle_id`` (no error if unknown)."""

    def vehicle_ids(self) -> list[str]:
        """Vehicles currently held."""

    def push(self, vehicle_id: str, measurement: Pushed) -> None:
        """Hand over one measurement (or batch), or a notice of lost data (:class:`WheelGap`,
        before the first data after the gap). Per vehicle, calls come in sensor-time order.

        Raises ``KeyError`` for an unknown vehicle. Never raises on bad values: NaN/inf parts are
        skipped and counted by the estimator.
        """

    def align_ticks(self, vehicle_id: str, stamp_ns: int) -> None:
        """Put the vehicle's ticks on ``stamp_ns + k·tick`` from its first measurement on.

        The server aligns them with the ends of the vehicle's IMU batches, so a tick can be
        computed as soon as the batch holding it has arrived. An estimator without a tick grid
        ignores it. ``KeyError`` for an unknown vehicle.
        """

    def advance(self, until_ns: Mapping[str, int]) -> list[tuple[str, np.ndarray]]:
        """Emit every tick with ``stamp_ns <= until_ns[vehicle_id]``, stepping vehicles batched.

        Returns a list of ``(vehicle_id, rows)`` with ``rows`` of ``spec.dtype``, only for
        vehicles that produced at least one row.
        """


@runtime_checkable
class HoldsRows(Protocol):
    """An estimator that gives some of a vehicle's rows late (a fixed lag: a later tick may
    still change them) and can give them at once, as they stand, when the vehicle's state is
    about to be dropped (a new config starts it afresh)."""

    def flush(self, vehicle_id: str) -> np.ndarray:
        """The vehicle's rows not yet given (of ``spec.dtype``, oldest first; empty if none or
        the vehicle is unknown), given now and forgotten."""
        ...


@runtime_checkable
class KeepsCounters(Protocol):
    """An estimator that counts per-vehicle events beyond its rows (ticks, fixes fused and
    gated, resets, bad input dropped)."""

    def counters(self, vehicle_id: str) -> dict[str, int]:
        """``{event: n}`` since the vehicle was added; ``KeyError`` for an unknown vehicle."""
        ...


@runtime_checkable
class Anchored(Protocol):
    """An estimator that keeps each vehicle's local ENU frame on a geodetic origin."""

    def anchor(self, vehicle_id: str) -> tuple[float, float, float] | None:
        """``(lat_deg, lon_deg, height_m)`` of the frame's origin (the first GNSS fix unless
        set), to which the rows' ENU positions refer; None before it or for an unknown
        vehicle."""
        ...

    def set_anchor(self, vehicle_id: str, lat_deg: float, lon_deg: float, height_m: float) -> None:
        """Give the frame this origin instead of the next first fix (the one stored rows were
        given in before a restart); ``KeyError`` if unknown, ``ValueError`` if not geodetic."""
        ...


@runtime_checkable
class TakesCommands(Protocol):
    """An estimator whose spec declares ``commands`` (e.g. MDSF's calibration drive)."""

    def command(self, vehicle_id: str, key: str, on: bool) -> None:
        """Turn command ``key`` on or off; ``KeyError`` for an unknown vehicle or key."""
        ...


def held_rows(estimator: FleetEstimator, vehicle_id: str) -> np.ndarray | None:
    """:meth:`HoldsRows.flush` of ``estimator`` for the vehicle; None for an estimator that
    holds no rows back (the default: every row is given by the ``advance`` that made it)."""
    if isinstance(estimator, HoldsRows):
        return estimator.flush(vehicle_id)
    return None
