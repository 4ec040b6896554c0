"""Wheel angular speed from encoder edges (``method.md`` §2) and direct wheel speeds.

:mod:`~estimator.wheel_speed.methods`
    The period and frequency methods and the quadratic fit at the query time.
:mod:`~estimator.wheel_speed.bank`
    :class:`WheelBank`: the edges of many wheels in shared arrays, queried in one fit.
:mod:`~estimator.wheel_speed.tracker`
    :class:`WheelTracker`, one wheel's slot of a bank, and :class:`DirectWheelSpeed`.
"""

from estimator.wheel_speed.bank import WheelBank
from estimator.wheel_speed.methods import (
    WheelSpeedConfig,
    WheelSpeedMethod,
    WheelSpeedResult,
    edge_angles,
    omega_at,
    omega_frequency,
    omega_k_tooth,
    stop_bound,
)
from estimator.wheel_speed.tracker import DirectWheelSpeed, WheelTracker, gather_bank, query_many

__all__ = [
    "DirectWheelSpeed",
    "WheelBank",
    "WheelSpeedConfig",
    "WheelSpeedMethod",
    "WheelSpeedResult",
    "WheelTracker",
    "edge_angles",
    "gather_bank",
    "omega_at",
    "omega_frequency",
    "omega_k_tooth",
    "query_many",
    "stop_bound",
]
