"""Wheel angular speed from encoder edges (``method.md`` §2) and direct wheel speeds."""

from estimator.wheel_speed.bank import (
    DirectWheelSpeed,
    WheelBank,
    WheelSpeedConfig,
    WheelSpeedMethod,
    WheelSpeedResult,
    WheelTracker,
    edge_angles,
    gather_bank,
    omega_at,
    omega_frequency,
    omega_k_tooth,
    query_many,
    stop_bound,
)

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
