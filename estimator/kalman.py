"""Batched linear Kalman filter: pure functions over a leading batch dimension ``N``.

The recursion is the standard one the MDSF filter uses (``method.md`` section 1, source eq. (7)):

    x⁻ = F·x + u                         P⁻ = F·P·Fᵀ + Q
    y  = z − H·x⁻                        S  = H·P⁻·Hᵀ + R
    K  = P⁻·Hᵀ·S⁻¹                       x⁺ = x⁻ + K·y
    P⁺ = (I − K·H)·P⁻·(I − K·H)ᵀ + K·R·Kᵀ     (Joseph form: stays symmetric positive definite)

``u`` is the already-multiplied control term ``B·u`` (the product MDSF filter drives the speed
with the measured acceleration through it). Measurement rows can be switched off per batch item
with a boolean ``mask``; a masked row is made exactly inert (zero row of ``H``, zero innovation,
unit variance decoupled from the other rows), so the result equals an update with the active rows
only. Everything here is allocation-light numpy; nothing loops over the batch in Python.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from functools import cache
from typing import cast

import numpy as np
import numpy.typing as npt

from estimator._arrays import BoolArray, FloatArray, IntArray

__all__ = [
    "IndependentUpdateResult",
    "UpdateResult",
    "innovation",
    "predict",
    "row_variances",
    "symmetrize",
    "update",
    "update_independent",
]


def symmetrize(P: FloatArray) -> FloatArray:
    """Return ``(P + Pᵀ)/2`` over the last two axes; shape ``(..., n, n)``."""
    return 0.5 * (P + P.swapaxes(-1, -2))


@cache
def _eye(n: int) -> FloatArray:
    """The identity ``(n, n)``, built once per size and shared (read-only)."""
    eye = np.eye(n)
    eye.flags.writeable = False
    return eye


def row_variances(H: FloatArray, P: FloatArray) -> FloatArray:
    """The diagonal of ``H·P·Hᵀ`` per batch item: each row's variance under ``P``.

    Parameters
    ----------
    H : ndarray, shape (N, m, n)
    P : ndarray, shape (N, n, n)

    Returns
    -------
    ndarray, shape (N, m)

    Notes
    -----
    ``((H @ P) * H).sum(-1)``: a batched product and a row sum, about twice as fast as the
    three-operand ``einsum("kmi,kij,kmj->km")`` (which loops over every index combination) for
    the MDSF sizes, four times for three rows.
    """
    return np.asarray(((H @ P) * H).sum(axis=-1))


def _batched(a: FloatArray, n_batch: int, ndim: int) -> FloatArray:
    """Broadcast a shared matrix ``(r, c)`` to ``(N, r, c)`` (no copy)."""
    a = np.asarray(a, dtype=np.float64)
    if a.ndim == ndim:
        return np.broadcast_to(a, (n_batch, *a.shape))
    return a


def predict(
    x: FloatArray,
    P: FloatArray,
    F: FloatArray,
    Q: FloatArray,
    u: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Time update, ``method.md`` §1 eq. (7) first line.

    Parameters
    ----------
    x : ndarray, shape (N, n)
        Posterior states.
    P : ndarray, shape (N, n, n)
        Posterior covariances.
    F : ndarray, shape (n, n) or (N, n, n)
        State transition (the source's ``A``).
    Q : ndarray, shape (n, n) or (N, n, n)
        Process noise covariance.
    u : ndarray, shape (N, n), optional
        Control term ``B·u`` added to the predicted state.

    Returns
    -------
    x_prior : ndarray, shape (N, n)
    P_prior : ndarray, shape (N, n, n)
    """
    n_batch = x.shape[0]
    Fb = _batched(F, n_batch, 2)
    x_prior = np.einsum("nij,nj->ni", Fb, x)
    if u is not None:
        x_prior = x_prior + u
    P_prior = Fb @ P @ Fb.swapaxes(-1, -2) + Q
    return x_prior, symmetrize(P_prior)


def innovation(
    x: FloatArray,
    P: FloatArray,
    z: FloatArray,
    H: FloatArray,
    R: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """Innovation ``y = z − H·x`` and its covariance ``S = H·P·Hᵀ + R`` (all rows).

    Parameters
    ----------
    x : ndarray, shape (N, n)
    P : ndarray, shape (N, n, n)
    z : ndarray, shape (N, m)
    H : ndarray, shape (m, n) or (N, m, n)
    R : ndarray, shape (m, m) or (N, m, m)

    Returns
    -------
    y : ndarray, shape (N, m)
    S : ndarray, shape (N, m, m)
    """
    Hb = _batched(H, x.shape[0], 2)
    y = z - np.einsum("nij,nj->ni", Hb, x)
    S = Hb @ P @ Hb.swapaxes(-1, -2) + R
    return y, S


@dataclass(frozen=True, slots=True)
class UpdateResult:
    """Result of :func:`update`.

    Attributes
    ----------
    x : ndarray, shape (N, n)
        Posterior state.
    P : ndarray, shape (N, n, n)
        Posterior covariance (Joseph form, symmetrised).
    y : ndarray, shape (N, m)
        Innovation; zero on masked rows.
    S : ndarray, shape (N, m, m)
        Innovation covariance of the active rows (masked rows decoupled with unit variance).
    K : ndarray, shape (N, n, m)
        Gain; zero columns on masked rows.
    nis : ndarray, shape (N,)
        Normalised innovation squared ``yᵀ·S⁻¹·y`` over the active rows; computed when read
        (a diagnostic: its solve costs a third of the update, and the filters do not use it).
    dof : ndarray, shape (N,), int
        Number of active rows (degrees of freedom of ``nis``).
    """

    x: FloatArray
    P: FloatArray
    y: FloatArray
    S: FloatArray
    K: FloatArray
    dof: npt.NDArray[np.int64]

    @property
    def nis(self) -> FloatArray:
        Sy = np.linalg.solve(self.S, self.y[:, :, None])[:, :, 0]
        return np.asarray(np.einsum("ni,ni->n", self.y, Sy))


def update(
    x: FloatArray,
    P: FloatArray,
    z: FloatArray,
    H: FloatArray,
    R: FloatArray,
    mask: BoolArray | None = None,
) -> UpdateResult:
    """Measurement update with a per-row mask, Joseph form, ``method.md`` §1 eq. (7).

    Parameters
    ----------
    x : ndarray, shape (N, n)
        Prior states.
    P : ndarray, shape (N, n, n)
        Prior covariances.
    z : ndarray, shape (N, m)
        Measurements; values on masked rows are ignored (they may be NaN).
    H : ndarray, shape (m, n) or (N, m, n)
        Observation matrix.
    R : ndarray, shape (m, m) or (N, m, m)
        Measurement noise covariance.
    mask : ndarray, shape (N, m), bool, optional
        ``True`` where the row is used. Default: every row.

    Returns
    -------
    UpdateResult
    """
    n_batch, n = x.shape
    Hb = _batched(H, n_batch, 2)
    Rb = _batched(R, n_batch, 2)
    m = Hb.shape[1]
    if mask is None:
        mask = np.ones((n_batch, m), dtype=bool)
    maskf = mask.astype(np.float64)
    Hm = Hb * maskf[:, :, None]
    # Decouple masked rows: keep R between active rows, unit variance on inactive ones.
    eye_m = _eye(m)
    Rm = Rb * (maskf[:, :, None] * maskf[:, None, :]) + eye_m * (1.0 - maskf)[:, None, :]
    y = np.where(mask, z - np.einsum("nij,nj->ni", Hm, x), 0.0)
    PHt = P @ Hm.swapaxes(-1, -2)  # (N, n, m)
    S = symmetrize(Hm @ PHt + Rm)
    # K = P Hᵀ S⁻¹  ⇔  S Kᵀ = H P  (S symmetric)
    K = cast(FloatArray, np.linalg.solve(S, PHt.swapaxes(-1, -2)).swapaxes(-1, -2))
    x_post = x + np.einsum("nij,nj->ni", K, y)
    IKH = _eye(n) - K @ Hm
    P_post = IKH @ P @ IKH.swapaxes(-1, -2) + K @ Rm @ K.swapaxes(-1, -2)
    return UpdateResult(
        x=x_post,
        P=symmetrize(P_post),
        y=y,
        S=S,
        K=K,
        dof=mask.sum(axis=1).astype(np.int64),
    )


@dataclass(frozen=True, slots=True)
class IndependentUpdateResult:
    """Result of :func:`update_independent`.

    Attributes
    ----------
    x : ndarray, shape (N, n)
        Posterior state.
    P : ndarray, shape (N, n, n)
        Posterior covariance (Joseph form, symmetrised).
    nis : ndarray, shape (N,)
        Normalised innovation squared over the active rows, the sum of the rows' ``y_j²/s_j``
        (equal to the joint update's ``yᵀ·S⁻¹·y``).
    dof : ndarray, shape (N,), int
        Number of active rows.
    """

    x: FloatArray
    P: FloatArray
    nis: FloatArray
    dof: npt.NDArray[np.int64]


def _row_terms(
    x: FloatArray, P: FloatArray, h: FloatArray, state: int | None
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``(P·hᵀ (N, n), h·P·hᵀ (N,), h·x (N,))`` of one observation row ``h`` (N, n); for a
    unit row (``state``: the state it measures) read off ``P`` and ``x``, the same numbers
    without the product and its sums (a non-finite ``P`` or ``x`` then stays non-finite where
    it was, instead of spreading through the row). ``P·hᵀ`` is then a view of ``P``: use it
    before ``P`` changes."""
    if state is None:
        Ph = (P @ h[:, :, None])[:, :, 0]
        return Ph, (h * Ph).sum(axis=1), (h * x).sum(axis=1)
    Ph = P[:, :, state]
    return Ph, Ph[:, state], x[:, state]


def update_independent(
    x: FloatArray,
    P: FloatArray,
    z: FloatArray,
    H: FloatArray,
    r: FloatArray,
    mask: BoolArray,
    rows: tuple[int, ...] | None = None,
    unit: Mapping[int, int] | None = None,
) -> IndependentUpdateResult:
    """Measurement update for rows with independent noises (diagonal ``R``), one row at a time.

    With ``R`` diagonal the joint update of :func:`update` equals the rows applied one after
    the other, each a scalar update of the previous row's posterior (:func:`_apply_row`: the
    Joseph form as two rank-one products), with the same ``x⁺`` and ``P⁺`` up to rounding and
    the rows' ``y_j²/s_j`` adding up to the joint ``yᵀ·S⁻¹·y``. No ``m × m`` solve, so it is
    cheaper than :func:`update` when few rows are active (``docs/perf/estimator.md``).

    Parameters
    ----------
    x, P : ndarray, shape (N, n) and (N, n, n)
        Prior states and covariances.
    z : ndarray, shape (N, m)
        Measurements; values on masked rows are ignored (they may be NaN).
    H : ndarray, shape (m, n) or (N, m, n)
        Observation matrix.
    r : ndarray, shape (N, m)
        Measurement noise variances (the diagonal of ``R``).
    mask : ndarray, shape (N, m), bool
        ``True`` where the row is used.
    rows : tuple of int, optional
        The rows to apply (default: every row); a row left out is treated as masked.
    unit : mapping of int to int, optional
        Rows ``j`` whose ``H`` row is the unit vector of state ``unit[j]`` for every item (a
        state measured directly; :func:`_row_terms`).

    Returns
    -------
    IndependentUpdateResult
    """
    Hb = _batched(H, x.shape[0], 2)
    x = np.array(x, dtype=np.float64)
    P = np.array(P, dtype=np.float64)
    nis, dof = _apply_rows(x, P, Hb, z, r, mask, rows, unit)
    return IndependentUpdateResult(x=x, P=P, nis=nis, dof=dof)


def _apply_rows(
    x: FloatArray,
    P: FloatArray,
    Hb: FloatArray,
    z: FloatArray,
    r: FloatArray,
    mask: BoolArray,
    rows: tuple[int, ...] | None,
    unit: Mapping[int, int] | None,
) -> tuple[FloatArray, IntArray]:
    """Rows ``rows`` (all of ``Hb``'s ``m`` if None) of :func:`update_independent` in turn into
    ``x`` ``(N, n)`` and ``P`` ``(N, n, n)`` in place; ``(nis (N,), dof (N,))``."""
    n_batch = x.shape[0]
    nis = np.zeros(n_batch)
    dof = np.zeros(n_batch, dtype=np.int64)
    for j in range(Hb.shape[1]) if rows is None else rows:
        active = mask[:, j]
        every = bool(active.all())
        if not every and not active.any():
            continue
        h_unit = None if unit is None else unit.get(j)
        y, inv = _apply_row(x, P, Hb[:, j, :], z[:, j], r[:, j], active, every, h_unit)
        nis += y * y * inv
        dof += active
    return nis, dof


def _apply_row(
    x: FloatArray,
    P: FloatArray,
    h: FloatArray,
    z_j: FloatArray,
    r_j: FloatArray,
    active: BoolArray,
    every: bool,
    h_unit: int | None,
) -> tuple[FloatArray, FloatArray]:
    """One scalar row of :func:`update_independent` into ``x`` and ``P`` in place; ``(y, 1/s)``.

    For the row ``h = H_j`` ``(N, n)`` of noise ``r_j`` ``(N,)``:

        s = h·P·hᵀ + r_j           k = P·hᵀ / s           x⁺ = x + k·(z_j − h·x)
        M = P·(I − k·h)ᵀ = P − (P·hᵀ)·kᵀ
        P⁺ = (I − k·h)·M + r_j·k·kᵀ = M − k·(h·M) + r_j·k·kᵀ

    (Joseph form, applied as two rank-one products so that ``I − k·h`` acts on the rounded
    ``M``: a row far more precise than its prior, ``r_j ≪ h·P·hᵀ``, keeps ``P⁺`` positive
    definite, where the expanded ``P − (P·hᵀ)·(P·hᵀ)ᵀ/s`` cancels to the rounding of ``P``).
    """
    Ph, s, y = _row_terms(x, P, h, h_unit)
    s = s + r_j
    y = z_j - y
    if every:  # the usual case: the same values without the masking
        inv = 1.0 / s
    else:
        inv = np.where(active, 1.0 / np.where(active, s, 1.0), 0.0)  # 0: the row is inert
        y = np.where(active, y, 0.0)
    k = Ph * inv[:, None]
    x += k * y[:, None]
    r_k = r_j if every else np.where(active, r_j, 0.0)  # an inert row adds nothing
    # Joseph form in two rank-one steps (the docstring); an inert row's
    # k = 0 leaves P as it was, bit for bit
    M = P - np.einsum("ni,nj->nij", Ph, k)  # P·(I − k·h)ᵀ (Ph is read before P changes)
    hM = M[:, h_unit, :] if h_unit is not None else (h[:, None, :] @ M)[:, 0, :]
    post = M - np.einsum("ni,nj->nij", k, hM)
    post += np.einsum("ni,nj->nij", k * r_k[:, None], k)
    P[...] = symmetrize(post)
    return y, inv
