"""Estimator registry: names → FleetEstimator factories, vehicle kinds → default estimators."""

from server.estimation.registry import (
    DEFAULT_FACTORIES,
    KIND_DEFAULTS,
    ConfigRefusedError,
    ErrorHandler,
    EstimatorRegistry,
    UnknownEstimatorError,
    estimator_names_for,
)

__all__ = [
    "DEFAULT_FACTORIES",
    "KIND_DEFAULTS",
    "ConfigRefusedError",
    "ErrorHandler",
    "EstimatorRegistry",
    "UnknownEstimatorError",
    "estimator_names_for",
]
