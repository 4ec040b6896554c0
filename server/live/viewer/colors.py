"""The slip colour scale, the same as the dashboard's (``web/js/colors.js``).

Colour is a function of ``|slip|`` in percent, linear in RGB between :data:`SLIP_COLOR_STOPS`
and clamped beyond the last stop; no slip value (NaN: standstill, invalid) is
:data:`SLIP_COLOR_NONE`. ``tests/server/live/viewer/test_colors.py`` checks that both files agree.

A tyre's share of the available grip in use (a spec's wheel value channels) has its own scale,
:data:`GRIP_COLOR_STOPS` (the dashboard's too): green 0 %, yellow 50 %, orange 80 %, dark red
100 % and beyond.

=========  ==========  =========
|slip| %   colour      hex
=========  ==========  =========
0          green       #1a9850
5          yellow      #f0c828
15         orange      #e6551e
>= 30      dark red    #8c141e
none       grey        #a0a0a0
=========  ==========  =========
"""

from __future__ import annotations

from typing import Final

import numpy as np
import numpy.typing as npt

__all__ = ["GRIP_COLOR_STOPS", "SLIP_COLOR_NONE", "SLIP_COLOR_STOPS", "grip_rgb", "slip_rgb"]

SLIP_COLOR_STOPS: Final[tuple[tuple[float, tuple[int, int, int]], ...]] = (
    (0.0, (26, 152, 80)),
    (5.0, (240, 200, 40)),
    (15.0, (230, 85, 30)),
    (30.0, (140, 20, 30)),
)
SLIP_COLOR_NONE: Final[tuple[int, int, int]] = (160, 160, 160)
GRIP_COLOR_STOPS: Final[tuple[tuple[float, tuple[int, int, int]], ...]] = (
    (0.0, (26, 152, 80)),
    (50.0, (240, 200, 40)),
    (80.0, (230, 85, 30)),
    (100.0, (140, 20, 30)),
)


def _ramp_rgb(
    stops: tuple[tuple[float, tuple[int, int, int]], ...], value: npt.ArrayLike
) -> npt.NDArray[np.uint8]:
    """RGB ``(..., 3)`` uint8 of ``|value|`` linear between ``stops``, clamped, NaN grey."""
    s = np.abs(np.asarray(value, dtype=np.float64))
    x = np.array([v for v, _ in stops])
    c = np.array([rgb for _, rgb in stops], dtype=np.float64)
    out = np.empty((*s.shape, 3), dtype=np.float64)
    for k in range(3):
        out[..., k] = np.interp(s, x, c[:, k])
    out[np.isnan(s)] = SLIP_COLOR_NONE
    return np.round(out).astype(np.uint8)


def slip_rgb(slip_pct: npt.ArrayLike) -> npt.NDArray[np.uint8]:
    """RGB ``(..., 3)`` uint8 of slip values in percent (sign ignored, NaN grey)."""
    return _ramp_rgb(SLIP_COLOR_STOPS, slip_pct)


def grip_rgb(share_pct: npt.ArrayLike) -> npt.NDArray[np.uint8]:
    """RGB ``(..., 3)`` uint8 of shares of the available grip in use, percent (NaN grey)."""
    return _ramp_rgb(GRIP_COLOR_STOPS, share_pct)
