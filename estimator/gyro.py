"""A yaw gyro's data-sheet figures and what a filter makes of them.

A MEMS gyro's white rate noise integrates to an angle random walk (ARW); its bias wanders
in-run. Data sheets print the ARW in °/√h, the rate noise density in °/s/√Hz and the in-run
bias stability (the Allan deviation's floor) in °/h. The heading's process noise of a
filter is the ARW as rad/√s (variance ``ARW²·Δt`` a tick); a rate sampled at ``f`` Hz
carries white noise of ``ARW·√f`` rad/s a sample. The in-run bias is modelled as a random
walk that reaches the bias stability over ``BIAS_STABILITY_S`` (the length of a long GNSS
outage, the span over which the bias matters to dead reckoning):
``walk = stability/√BIAS_STABILITY_S`` rad/s per √s.

:data:`GYRO_PARTS` holds the parts a vehicle config may name (``gyro.part``); a config may
instead give a part's three figures itself (:class:`estimator.config.GyroConfig`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["ADIS16470", "BIAS_STABILITY_S", "GYRO_PARTS", "GyroPart"]

#: Span (s) over which the in-run bias walks by the part's bias stability.
BIAS_STABILITY_S = 300.0
_DEG = math.pi / 180.0


@dataclass(frozen=True, slots=True)
class GyroPart:
    """Data-sheet figures of one gyro (z axis): angle random walk (°/√h), in-run bias
    stability (°/h), rate noise density (°/s/√Hz; ARW ≈ density·60/√2 for a one-sided
    density, a cross-check of the two printed figures)."""

    name: str
    angle_random_walk_deg_rt_h: float
    bias_stability_deg_h: float
    noise_density_dps_rt_hz: float

    @property
    def arw_rad_rt_s(self) -> float:
        """The angle random walk in rad/√s (°/√h ÷ 60 √s/√h)."""
        return self.angle_random_walk_deg_rt_h * _DEG / 60.0

    @property
    def bias_stability_radps(self) -> float:
        return self.bias_stability_deg_h * _DEG / 3600.0

    @property
    def bias_walk_radps_rt_s(self) -> float:
        """The in-run bias as a random walk, rad/s per √s (module docstring)."""
        return self.bias_stability_radps / math.sqrt(BIAS_STABILITY_S)

    def sample_noise_radps(self, rate_hz: float) -> float:
        """White rate noise (1-sigma, rad/s) of one sample at ``rate_hz``."""
        return self.arw_rad_rt_s * math.sqrt(rate_hz)

    def scaled(self, grade: float) -> GyroPart:
        """This part with every figure ``grade`` times its own (a worse unit of its kind)."""
        return GyroPart(
            f"{self.name}x{grade:.2f}",
            grade * self.angle_random_walk_deg_rt_h,
            grade * self.bias_stability_deg_h,
            grade * self.noise_density_dps_rt_hz,
        )


#: Analog Devices ADIS16470, an industrial MEMS IMU (ADIS16470 data sheet, Analog Devices):
#: angle random walk 0.34 °/√h, in-run bias stability 8 °/h, rate noise density
#: 0.008 °/s/√Hz.
ADIS16470 = GyroPart("ADIS16470", 0.34, 8.0, 0.008)

#: The parts a vehicle config may name, by name.
GYRO_PARTS: dict[str, GyroPart] = {part.name: part for part in (ADIS16470,)}
