"""Tracked vehicles (``method.md`` §4, source 002): motion state, track slip and skid, and
odometer-corrected dead reckoning through long GNSS outages.

:class:`TrackedFleet` is the batched ``FleetEstimator`` (rows of
:data:`estimator.tracked_spec.TRACKED_SPEC`), :class:`TrackedEstimator` the per-vehicle
reference; :class:`TrackedEstimatorConfig` picks the mode (:class:`TrackedMode`: the product,
the source as printed with and without its lateral term, or the raw odometer).
"""

from estimator.tracked.fleet import TrackedEstimator, TrackedFleet
from estimator.tracked.model import MotionState, TrackedMode, TrackedState
from estimator.tracked.settings import TrackedEstimatorConfig

__all__ = [
    "MotionState",
    "TrackedEstimator",
    "TrackedEstimatorConfig",
    "TrackedFleet",
    "TrackedMode",
    "TrackedState",
]
