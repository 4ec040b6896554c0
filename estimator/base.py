"""The interface the server drives every estimator through.

An estimator is *fleet-wide*: one object holds every vehicle that runs it, so it can step them
in one numpy call. The server feeds each vehicle's measurements in sensor-time order (its reorder
buffer guarantees that) and then asks for every tick that the released data completes.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Protocol, runtime_checkable

import numpy as np

from estimator.config import VehicleConfig
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

__all__ = ["FleetEstimator", "Measurement", "Pushed"]

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


@runtime_checkable
class FleetEstimator(Protocol):
    """Many vehicles' estimators behind one batched step.

    Attributes
    ----------
    name : str
        Registry name (``"mdsf"``, later ``"tracked"``, ``"friction"``).
    output_dtype : numpy.dtype
        Structured dtype of the rows :meth:`advance` returns (``ESTIMATE_DTYPE`` for MDSF).
    """

    name: str
    output_dtype: np.dtype

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

        Returns a list of ``(vehicle_id, rows)`` with ``rows`` of :attr:`output_dtype`, only for
        vehicles that produced at least one row.
        """
