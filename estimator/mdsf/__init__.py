"""MDSF, multi-source data structured fusion (``method.md`` §1): per-wheel ground speed and slip.

Modules, from the equations outwards:

:mod:`~estimator.mdsf.model`
    The filter's states, observations, matrices and settings (:class:`MdsfConfig`), and
    :class:`MdsfFilter`, the per-vehicle reference on filterpy.
:mod:`~estimator.mdsf.frontend`
    Buffered measurements of many vehicles turned into per-tick filter inputs.
:mod:`~estimator.mdsf.calibration`
    Online calibration per vehicle (clock offsets, rolling radii, IMU mounting pitch), each
    with its std; :class:`MdsfCalibration` its state out and in.
:mod:`~estimator.mdsf.clock_shift`
    What the GNSS clock offset makes of a fix's speed and of the RTK distance (the body rates
    at the instant a fix describes).
:mod:`~estimator.mdsf.engine`
    :class:`MdsfEngine`: every vehicle's filter in slot arrays, stepped in batches.
:mod:`~estimator.mdsf.fleet`
    :class:`MdsfFleet`: the :class:`~estimator.base.FleetEstimator` the server runs.
"""

from estimator.mdsf.calibration import MdsfCalibration
from estimator.mdsf.engine import Counter, MdsfEngine, StepOutput, TickModel
from estimator.mdsf.fleet import MdsfFleet
from estimator.mdsf.frontend import COUNT_NAMES, FleetFrontEnd, FleetTicks, TickInputs
from estimator.mdsf.model import (
    GRAVITY_MPS2,
    MdsfConfig,
    MdsfFilter,
    MdsfMatrices,
    MdsfMode,
    MdsfObs,
    MdsfOut,
    MdsfState,
    gnss_vehicle_speed,
    mdsf_matrices,
    observation_matrix,
    output_matrix,
    structural_speeds,
    transition_matrix,
)

__all__ = [
    "COUNT_NAMES",
    "GRAVITY_MPS2",
    "Counter",
    "FleetFrontEnd",
    "FleetTicks",
    "MdsfCalibration",
    "MdsfConfig",
    "MdsfEngine",
    "MdsfFilter",
    "MdsfFleet",
    "MdsfMatrices",
    "MdsfMode",
    "MdsfObs",
    "MdsfOut",
    "MdsfState",
    "StepOutput",
    "TickInputs",
    "TickModel",
    "gnss_vehicle_speed",
    "mdsf_matrices",
    "observation_matrix",
    "output_matrix",
    "structural_speeds",
    "transition_matrix",
]
