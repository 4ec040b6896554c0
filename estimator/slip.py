"""Wheel slip, ``method.md`` §1 source eq. (8)(9), vectorised, with a standstill rule.

    S = (r·W − V) / max(r·W, V) × 100 %

``r·W`` is the wheel's rim speed (effective radius times measured angular speed), ``V`` the ground
speed of its contact point (MDSF eq. (4)/(5)). Positive while driving, negative while braking.

Choices the source leaves open (stated here, tested in ``tests/estimator/test_slip.py``):

* **Standstill.** When both ``|r·W|`` and ``|V|`` are below ``SlipConfig.min_ground_speed_mps``
  there is no slip value (NaN, ``valid`` false, flagged STANDSTILL by the caller). Otherwise the
  denominator is at least that threshold, so the ratio never blows up.
* **Reverse.** The formula is applied to the direction of travel: with ``s`` the sign of ``V``
  (of ``r·W`` when ``V`` is near zero), ``S = s·(r·W − V)/max(|r·W|, |V|)``. Driving backwards
  with the wheel turning faster than the ground passes is positive slip, as forwards.
  ``|S| ≤ 200 %`` (reached only when the wheel turns against the direction of travel).
* **Settling.** Starting and stopping, the wheel's speed comes from a fit over the last few
  encoder edges, which at low speed span long enough for the speed to change a lot within them:
  the fit lags, and the slip error reached 30-80 pp below 0.4 m/s in the simulated scenarios,
  with a reported std of 2-5 pp. :func:`unsettled` marks the rows where the ground speed changes
  by more than a set fraction of itself over the fit's span; the caller gives no slip value there
  (flag SETTLING).
* **Uncertainty.** First-order propagation from ``σ_V``, ``σ_rW`` and their covariance ``c``
  (zero for independent inputs; a filter that estimates both speeds correlates them): on the
  branch ``|r·W| ≥ |V|``, ``|∂S/∂(rW)| = |V|/(rW)²``, ``|∂S/∂V| = 1/|rW|``; on the other branch
  ``|∂S/∂(rW)| = 1/|V|``, ``|∂S/∂V| = |rW|/V²`` (times 100 %). The two partials have opposite
  signs, so ``σ_S² = (∂_rW·σ_rW)² + (∂_V·σ_V)² − 2·|∂_rW|·|∂_V|·c``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from estimator._arrays import FloatArray

__all__ = ["SlipResult", "fit_span_s", "slip_pct", "unsettled"]


@dataclass(frozen=True, slots=True)
class SlipResult:
    """Slip values; all arrays have the broadcast shape of the inputs.

    Attributes
    ----------
    slip_pct : ndarray
        Slip in percent; NaN where not valid.
    std_pct : ndarray
        1-sigma slip uncertainty in percent; NaN where not valid or where an input
        uncertainty is not finite.
    valid : ndarray, bool
        A value was given (finite inputs, not at standstill).
    standstill : ndarray, bool
        Both speeds below the threshold (finite inputs).
    """

    slip_pct: FloatArray
    std_pct: FloatArray
    valid: npt.NDArray[np.bool_]
    standstill: npt.NDArray[np.bool_]


def slip_pct(
    rim_speed_mps: npt.ArrayLike,
    ground_speed_mps: npt.ArrayLike,
    min_ground_speed_mps: float | npt.ArrayLike,
    rim_std_mps: npt.ArrayLike = 0.0,
    ground_std_mps: npt.ArrayLike = 0.0,
    rim_ground_cov_mps2: npt.ArrayLike = 0.0,
) -> SlipResult:
    """Slip of a wheel, ``method.md`` §1 eq. (8)(9), with standstill rule and std.

    Parameters
    ----------
    rim_speed_mps : array_like
        ``r·W``, signed (forward positive).
    ground_speed_mps : array_like
        ``V`` of the wheel's contact point, signed.
    min_ground_speed_mps : float or array_like
        Standstill threshold (``SlipConfig.min_ground_speed_mps``), > 0; broadcasts.
    rim_std_mps, ground_std_mps : array_like
        1-sigma uncertainties of the two speeds.
    rim_ground_cov_mps2 : array_like
        Their covariance [(m/s)²] (default 0: independent).

    Returns
    -------
    SlipResult
    """
    a = np.asarray(rim_speed_mps, dtype=np.float64)
    v = np.asarray(ground_speed_mps, dtype=np.float64)
    sa = np.asarray(rim_std_mps, dtype=np.float64)
    sv = np.asarray(ground_std_mps, dtype=np.float64)
    cov = np.asarray(rim_ground_cov_mps2, dtype=np.float64)
    thr = np.asarray(min_ground_speed_mps, dtype=np.float64)
    a, v, sa, sv, cov, thr = np.broadcast_arrays(a, v, sa, sv, cov, thr)
    finite = np.isfinite(a) & np.isfinite(v)
    abs_a = np.abs(np.where(finite, a, 0.0))
    abs_v = np.abs(np.where(finite, v, 0.0))
    standstill = finite & (abs_a < thr) & (abs_v < thr)
    valid = finite & ~standstill
    denom = np.maximum(np.maximum(abs_a, abs_v), thr)
    direction = np.where(abs_v >= 0.5 * thr, np.sign(v), np.sign(a))
    direction = np.where(direction == 0, 1.0, direction)
    s = direction * (np.where(finite, a, 0.0) - np.where(finite, v, 0.0)) / denom * 100.0
    rim_branch = abs_a >= abs_v
    d_a = np.where(rim_branch, abs_v / denom**2, 1.0 / denom)
    d_v = np.where(rim_branch, 1.0 / denom, abs_a / denom**2)
    with np.errstate(over="ignore", invalid="ignore"):
        var = (d_a * sa) ** 2 + (d_v * sv) ** 2 - 2.0 * d_a * d_v * cov
        std = 100.0 * np.sqrt(np.maximum(var, 0.0))
    # an infinite input uncertainty (a degenerate encoder fit) says nothing: unknown, not inf
    std = np.where(np.isfinite(std), std, np.nan)
    return SlipResult(
        slip_pct=np.where(valid, s, np.nan),
        std_pct=np.where(valid, std, np.nan),
        valid=valid,
        standstill=standstill,
    )


def fit_span_s(
    ground_speed_mps: npt.ArrayLike, tooth_arc_m: npt.ArrayLike, min_edges: int
) -> FloatArray:
    """Time the wheel takes to pass the fewest edges a wheel-speed fit uses [s].

        τ = min_edges · arc / |V|

    ``arc = 2π·r / Ns`` is the rim travel from one encoder edge to the next; ``min_edges`` is
    :class:`~estimator.wheel_speed.WheelSpeedConfig`'s (a fit never takes fewer edges, so it
    spans at least ``τ``); ``V`` stands in for the rim speed, which differs from it by the slip.
    ``inf`` at ``V = 0``; 0 where ``arc`` is 0 (wheel speeds given directly: no fit).

    Parameters
    ----------
    ground_speed_mps, tooth_arc_m : array_like
        Broadcast together; the result has their shape.
    min_edges : int
    """
    v = np.abs(np.asarray(ground_speed_mps, dtype=np.float64))
    arc = np.asarray(tooth_arc_m, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        span = np.where(arc > 0, min_edges * arc / v, 0.0)
    return np.asarray(np.nan_to_num(span, nan=np.inf, posinf=np.inf))


def unsettled(
    ground_speed_mps: npt.ArrayLike,
    accel_mps2: npt.ArrayLike,
    span_s: npt.ArrayLike,
    max_change: float | npt.ArrayLike,
) -> npt.NDArray[np.bool_]:
    """Where the speed changes too fast for a fit of span ``τ`` to follow.

        |a| · τ > max_change · |V|

    A fit over ``τ`` seconds is centred about ``τ/2`` in the past. The wheel-speed fit's
    quadratic term removes that lag under a steady acceleration, but not when the acceleration
    itself changes within the span, as it does at a start or a stop; at low speed the span is
    long and the slip (a difference of two speeds over one of them) takes the error in full.
    Rows with a non-finite ``a`` or ``V`` are not marked (nothing to judge by).

    Parameters
    ----------
    ground_speed_mps : array_like
        ``V`` of the wheel's contact point.
    accel_mps2 : array_like
        Forward acceleration of the vehicle.
    span_s : array_like
        ``τ`` (:func:`fit_span_s`); 0 where no fit is involved.
    max_change : float or array_like
        Largest allowed relative change of ``V`` over ``τ`` (``SlipConfig.settle_max_change``).

    Returns
    -------
    ndarray of bool
        The broadcast shape of the inputs.
    """
    v = np.abs(np.asarray(ground_speed_mps, dtype=np.float64))
    a = np.abs(np.asarray(accel_mps2, dtype=np.float64))
    span = np.asarray(span_s, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        change = a * span  # inf * 0 (no fit at standstill) is NaN: not marked
        return np.asarray(np.isfinite(v) & (change > np.asarray(max_change) * v))
