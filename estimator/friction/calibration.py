"""A vehicle's tyre calibration: the product filter's stiffness factors, carried between drives.

The product filter (:mod:`.filter`) scales each axle's load-adaptive stiffness ``c = 2a²c_p``
by factors ``g = [g_x,front, g_x,rear, g_y,front, g_y,rear]`` and starts them at
``1 ± factor0_rel_std``. Ordinary driving (small slips in the tyres' linear range) teaches
them; μ near the limit is told apart from ``g`` only as well as ``g`` is known
(``F ≈ g c s (1 − λ + λ²/3)``, ``λ ∝ g c s / μ``). A :class:`TyreCalibration` is what one
drive learnt, ``(ĝ, P_g)``, inflated for the time until the next drive::

    P_carried = P_g + diag((ĝ · aging_rel_std)²)                                  (1)

``aging_rel_std`` stands for what changes a tyre's stiffness between drives and is not
modelled: inflation pressure and temperature (a few percent of ``c`` each) and wear. The next
drive's filter starts its factors from ``N(ĝ, P_carried)`` instead of the default prior (its
``ln μ`` and ``v_y`` as always), see :func:`start_factors`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from estimator._arrays import FloatArray
from estimator.config import ConfigError
from estimator.friction.filter import FilterState, ProductState

__all__ = ["AGING_REL_STD", "FACTOR_STATES", "TyreCalibration", "start_factors"]

FACTOR_STATES = (
    ProductState.GX_FRONT,
    ProductState.GX_REAR,
    ProductState.GY_FRONT,
    ProductState.GY_REAR,
)
"""The product state's stiffness factors, in the order a calibration holds them."""

AGING_REL_STD = 0.02
"""Default 1-σ [share of the factor] added to a carried calibration, eq. (1)."""

_N = len(FACTOR_STATES)
_IDX = np.array([int(i) for i in FACTOR_STATES])


@dataclass(frozen=True, slots=True)
class TyreCalibration:
    """Stiffness factors ``factor`` ``(4,)`` (:data:`FACTOR_STATES` order) and their covariance
    ``factor_cov`` ``(4, 4)`` as the next drive should start from (already inflated, eq. 1)."""

    factor: tuple[float, float, float, float]
    factor_cov: tuple[tuple[float, ...], ...]

    def __post_init__(self) -> None:
        f = np.asarray(self.factor, dtype=np.float64)
        p = np.asarray(self.factor_cov, dtype=np.float64)
        if f.shape != (_N,) or p.shape != (_N, _N):
            raise ConfigError(f"a tyre calibration holds {_N} factors and a {_N}×{_N} covariance")
        if not (np.all(np.isfinite(f)) and np.all(f > 0) and np.all(np.isfinite(p))):
            raise ConfigError("tyre calibration factors must be finite and positive")
        if not np.allclose(p, p.T, rtol=1e-9, atol=1e-15):
            raise ConfigError("tyre calibration covariance must be symmetric")
        try:
            np.linalg.cholesky(p)
        except np.linalg.LinAlgError:
            raise ConfigError("tyre calibration covariance must be positive definite") from None

    @staticmethod
    def from_state(
        x: FloatArray, s: FloatArray, aging_rel_std: float = AGING_REL_STD
    ) -> TyreCalibration:
        """The calibration one product filter state carries to the next drive, eq. (1).

        ``x`` ``(n,)`` the mean, ``s`` ``(n, n)`` its root (``P = S Sᵀ``) of one vehicle."""
        if not (aging_rel_std > 0 and math.isfinite(aging_rel_std)):
            raise ConfigError(f"aging_rel_std must be positive, got {aging_rel_std!r}")
        g = np.asarray(x, dtype=np.float64)[_IDX]
        root = np.asarray(s, dtype=np.float64)[_IDX]
        p = root @ root.T + np.diag((g * aging_rel_std) ** 2)
        p = 0.5 * (p + p.T)
        return TyreCalibration(
            (float(g[0]), float(g[1]), float(g[2]), float(g[3])),
            tuple(tuple(float(v) for v in row) for row in p),
        )

    @property
    def std(self) -> FloatArray:
        """The factors' 1-σ ``(4,)``."""
        return np.sqrt(np.diag(np.asarray(self.factor_cov)))

    def to_dict(self) -> dict[str, Any]:
        """Plain lists, for storing (``from_dict`` reads it back)."""
        return {"factor": list(self.factor), "factor_cov": [list(r) for r in self.factor_cov]}

    @staticmethod
    def from_dict(d: dict[str, Any]) -> TyreCalibration:
        f = [float(v) for v in d["factor"]]
        if len(f) != _N:
            raise ConfigError(f"a tyre calibration holds {_N} factors, got {len(f)}")
        return TyreCalibration(
            (f[0], f[1], f[2], f[3]),
            tuple(tuple(float(v) for v in row) for row in d["factor_cov"]),
        )


def start_factors(prior: FilterState, factor: FloatArray, factor_cov: FloatArray) -> FilterState:
    """``prior`` (a product filter's start, ``B`` vehicles) with its stiffness factors started
    from calibrations: mean ``factor`` ``(B, 4)``, covariance ``factor_cov`` ``(B, 4, 4)``;
    their root block is the Cholesky factor, uncorrelated with ``ln μ`` and ``v_y``."""
    x, s = prior.x.copy(), prior.s.copy()
    if x.shape[0]:
        x[:, _IDX] = factor
        s[:, _IDX, :] = 0.0
        s[:, :, _IDX] = 0.0
        s[:, _IDX[:, None], _IDX[None, :]] = np.linalg.cholesky(factor_cov)
    return FilterState(x, s, prior.fz_prev_n, prior.nis, prior.mee_ok, prior.updated)
