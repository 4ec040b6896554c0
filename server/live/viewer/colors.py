"""The slip colour scale, the same as the dashboard's (``web/js/colors.js``).

Colour is a function of ``|slip|`` in percent, linear in RGB between :data:`SLIP_COLOR_STOPS`
and clamped beyond the last stop; no slip value (NaN: standstill, invalid) is
:data:`SLIP_COLOR_NONE`. ``tests/server/live/viewer/test_colors.py`` checks that both files agree.

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

__all__ = ["SLIP_COLOR_NONE", "SLIP_COLOR_STOPS", "slip_rgb"]

SLIP_COLOR_STOPS: Final[tuple[tuple[float, tuple[int, int, int]], ...]] = (
    (0.0, (26, 152, 80)),
    (5.0, (240, 200, 40)),
    (15.0, (230, 85, 30)),
    (30.0, (140, 20, 30)),
)
SLIP_COLOR_NONE: Final[tuple[int, int, int]] = (160, 160, 160)

_X = np.array([s for s, _ in SLIP_COLOR_STOPS])
_C = np.array([c for _, c in SLIP_COLOR_STOPS], dtype=np.float64)


def slip_rgb(slip_pct: npt.ArrayLike) -> npt.NDArray[np.uint8]:
    """RGB ``(..., 3)`` uint8 of slip values in percent (sign ignored, NaN grey)."""
    s = np.abs(np.asarray(slip_pct, dtype=np.float64))
    out = np.empty((*s.shape, 3), dtype=np.float64)
    for k in range(3):
        out[..., k] = np.interp(s, _X, _C[:, k])
    out[np.isnan(s)] = SLIP_COLOR_NONE
    return np.round(out).astype(np.uint8)
