"""Tyre–ground friction coefficient μ of a steered four-wheel vehicle (``method.md`` §5, 004).

* :mod:`.brush`: the combined-slip brush tyre with load-adaptive stiffness ``c = 2a²c_p``;
* :mod:`.sckf`: the square-root cubature Kalman filter (QR ``tria()``) and the MEE step;
* :mod:`.model`: the planar four-wheel measurement model ``[a_x, a_y, ṙ]``;
* :mod:`.filter`: the μ filters (fixed / load-adaptive CKF, the source's SCKF-MEE, product);
* :mod:`.frontend`: per-wheel κ, α, δ, Fz with their uncertainty from the sensors;
* :mod:`.position`: the vehicle's position from GNSS, dead-reckoned between fixes and through
  short outages;
* :mod:`.fleet`: :class:`FrictionFleet`, the batched ``FleetEstimator`` with the informed logic.
"""

from estimator.friction.filter import FilterConfig, FrictionMode
from estimator.friction.fleet import FrictionFleet, FrictionFleetConfig
from estimator.friction.frontend import FrontEndConfig
from estimator.friction.position import PositionConfig

__all__ = [
    "FilterConfig",
    "FrictionFleet",
    "FrictionFleetConfig",
    "FrictionMode",
    "FrontEndConfig",
    "PositionConfig",
]
