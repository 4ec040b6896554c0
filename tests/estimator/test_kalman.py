"""Batched Kalman functions: hand-computed cases, masks, Joseph form, agreement with filterpy."""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter
from hypothesis import given, settings
from hypothesis import strategies as st

from estimator import kalman


def test_predict_scalar_by_hand() -> None:
    # x = [v, a], dt = 0.5: v' = 2 + 0.5*1 = 2.5; P' = F P Fᵀ + Q
    x = np.array([[2.0, 1.0]])
    P = np.array([[[1.0, 0.0], [0.0, 4.0]]])
    F = np.array([[1.0, 0.5], [0.0, 1.0]])
    Q = np.diag([0.1, 0.2])
    xp, Pp = kalman.predict(x, P, F, Q)
    assert xp[0] == pytest.approx([2.5, 1.0])
    # [[1 + 0.25*4 + 0.1, 0.5*4], [0.5*4, 4 + 0.2]]
    assert Pp[0] == pytest.approx(np.array([[2.1, 2.0], [2.0, 4.2]]))


def test_predict_with_control_term() -> None:
    x = np.zeros((2, 2))
    P = np.tile(np.eye(2), (2, 1, 1))
    u = np.array([[1.0, 0.0], [0.0, -2.0]])
    xp, _ = kalman.predict(x, P, np.eye(2), np.zeros((2, 2)), u)
    assert xp == pytest.approx(u)


def test_update_scalar_by_hand() -> None:
    # prior v ~ N(1, 4), measurement 3 with variance 1: K = 0.8, v = 2.6, P = 0.8
    res = kalman.update(
        np.array([[1.0]]), np.array([[[4.0]]]), np.array([[3.0]]), np.eye(1), np.eye(1)
    )
    assert res.x[0, 0] == pytest.approx(2.6)
    assert res.P[0, 0, 0] == pytest.approx(0.8)
    assert res.y[0, 0] == pytest.approx(2.0)
    assert res.S[0, 0, 0] == pytest.approx(5.0)
    assert res.nis[0] == pytest.approx(4.0 / 5.0)
    assert res.dof[0] == 1


def test_masked_row_equals_reduced_update() -> None:
    rng = np.random.default_rng(3)
    n, m = 4, 3
    A = rng.normal(size=(n, n))
    P = (A @ A.T + np.eye(n))[None]
    x = rng.normal(size=(1, n))
    H = rng.normal(size=(m, n))
    B = rng.normal(size=(m, m))
    R = B @ B.T + np.eye(m)
    z = rng.normal(size=(1, m))
    z_nan = z.copy()
    z_nan[0, 1] = np.nan  # masked rows may hold NaN
    mask = np.array([[True, False, True]])
    full = kalman.update(x, P, z_nan, H, R, mask)
    keep = [0, 2]
    reduced = kalman.update(x, P, z[:, keep], H[keep], R[np.ix_(keep, keep)])
    assert np.allclose(full.x, reduced.x, atol=1e-12)
    assert np.allclose(full.P, reduced.P, atol=1e-12)
    assert full.nis[0] == pytest.approx(reduced.nis[0])
    assert full.dof[0] == 2
    assert np.all(full.K[0, :, 1] == 0.0)


def test_all_rows_masked_leaves_state() -> None:
    x = np.array([[1.0, 2.0]])
    P = np.array([[[2.0, 0.3], [0.3, 1.0]]])
    res = kalman.update(x, P, np.full((1, 2), np.nan), np.eye(2), np.eye(2), np.zeros((1, 2), bool))
    assert np.allclose(res.x, x)
    assert np.allclose(res.P, P)
    assert res.nis[0] == 0.0 and res.dof[0] == 0


def test_batched_agrees_with_filterpy() -> None:
    rng = np.random.default_rng(7)
    n, m, N = 4, 3, 5
    xs = rng.normal(size=(N, n))
    Ps = np.empty((N, n, n))
    for i in range(N):
        A = rng.normal(size=(n, n))
        Ps[i] = A @ A.T + np.eye(n)
    F = np.eye(n) + 0.1 * rng.normal(size=(n, n))
    Q = np.diag(rng.uniform(0.01, 0.1, n))
    H = rng.normal(size=(m, n))
    R = np.diag(rng.uniform(0.1, 1.0, m))
    u = rng.normal(size=(N, n))
    z = rng.normal(size=(N, m))
    xp, Pp = kalman.predict(xs, Ps, F, Q, u)
    res = kalman.update(xp, Pp, z, H, R)
    for i in range(N):
        kf = KalmanFilter(dim_x=n, dim_z=m)
        kf.x = xs[i].reshape(n, 1).copy()
        kf.P = Ps[i].copy()
        kf.F, kf.Q, kf.H, kf.R, kf.B = F, Q, H, R, np.eye(n)
        kf.predict(u=u[i].reshape(n, 1))
        kf.update(z[i].reshape(m, 1))
        assert np.allclose(res.x[i], kf.x.ravel(), atol=1e-12, rtol=0)
        assert np.allclose(res.P[i], kf.P, atol=1e-12, rtol=0)
        assert res.nis[i] == pytest.approx(float(kf.mahalanobis) ** 2, rel=1e-10)


def _spd(seed: int, n: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, n))
    return A @ A.T + 1e-3 * np.eye(n)


@pytest.mark.parametrize("independent", [False, True], ids=["joint", "row_by_row"])
@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    steps=st.integers(1, 30),
    scale=st.floats(1e-6, 1e3),
    mask_bits=st.integers(0, 7),
)
def test_covariance_stays_symmetric_positive_definite(
    independent: bool, seed: int, steps: int, scale: float, mask_bits: int
) -> None:
    """Both updates (``update_independent`` with the diagonal R it needs), noise variances from
    1e-6 to 10, covariances scaled from 1e-6 to 1e3."""
    rng = np.random.default_rng(seed)
    n, m = 4, 3
    x = rng.normal(size=(2, n))
    P = np.stack([_spd(seed, n), _spd(seed + 1, n)]) * scale
    F = np.eye(n) + np.diag(np.full(n - 1, 0.2), 1)
    Q = np.diag(rng.uniform(1e-8, 1e-2, n))
    H = rng.normal(size=(m, n))
    r = rng.uniform(1e-6, 10.0, m)
    R = np.diag(r) if independent else r[:, None] * r[None, :] * 0.1 + np.diag(r)
    mask = np.array([[(mask_bits >> j) & 1 == 1 for j in range(m)]] * 2)
    for _ in range(steps):
        x, P = kalman.predict(x, P, F, Q)
        z = rng.normal(size=(2, m)) * scale
        if independent:
            res: kalman.UpdateResult | kalman.IndependentUpdateResult = kalman.update_independent(
                x, P, z, H, np.tile(r, (2, 1)), mask
            )
        else:
            res = kalman.update(x, P, z, H, R, mask)
        x, P = res.x, res.P
        assert np.array_equal(P, np.swapaxes(P, 1, 2))
        assert np.all(np.linalg.eigvalsh(P) > 0.0)
        assert np.all(np.isfinite(res.nis)) and np.all(res.nis >= 0.0)


def _spd_batch(rng: np.random.Generator, batch: int, n: int) -> np.ndarray:
    A = rng.normal(size=(batch, n, n))
    return np.asarray(A @ A.swapaxes(1, 2) + np.eye(n))


@pytest.mark.parametrize("seed", range(5))
def test_independent_rows_one_at_a_time_equal_the_joint_update(seed: int) -> None:
    """With a diagonal R, rows applied one after the other give the joint update's posterior
    and NIS, masks and left-out rows included (the MDSF filter's 7 rows, 8 states)."""
    rng = np.random.default_rng(seed)
    N, n, m = 64, 8, 7
    x, P = rng.normal(size=(N, n)), _spd_batch(rng, N, n)
    H = rng.normal(size=(N, m, n))
    r = rng.uniform(0.05, 3.0, size=(N, m))
    z = rng.normal(size=(N, m))
    mask = rng.random((N, m)) < 0.6
    rows = (0, 2, 3, 6)
    mask_joint = np.zeros_like(mask)
    mask_joint[:, rows] = mask[:, rows]
    z[~mask] = np.nan  # masked values are never read
    R = np.zeros((N, m, m))
    R[:, np.arange(m), np.arange(m)] = r
    joint = kalman.update(x, P, z, H, R, mask_joint)
    seq = kalman.update_independent(x, P, z, H, r, mask, rows)
    assert np.allclose(seq.x, joint.x, rtol=0, atol=1e-10)
    assert np.allclose(seq.P, joint.P, rtol=0, atol=1e-10)
    assert np.allclose(seq.nis, joint.nis, rtol=1e-9, atol=1e-12)
    assert np.array_equal(seq.dof, joint.dof)
    assert np.array_equal(seq.P, seq.P.swapaxes(1, 2))
    assert np.all(np.linalg.eigvalsh(seq.P) > 0)


def test_independent_update_leaves_items_without_an_active_row_untouched() -> None:
    rng = np.random.default_rng(11)
    x, P = rng.normal(size=(3, 4)), _spd_batch(rng, 3, 4)
    H = np.eye(4)[:2]
    mask = np.array([[True, False], [False, False], [False, True]])
    res = kalman.update_independent(x, P, rng.normal(size=(3, 2)), H, np.ones((3, 2)), mask)
    assert np.array_equal(res.x[1], x[1]) and np.array_equal(res.P[1], P[1])  # bit for bit
    assert res.dof.tolist() == [1, 0, 1] and res.nis[1] == 0.0
    # by hand, item 0: v ~ N(x0, P00) measured z0 with unit variance
    assert not np.array_equal(res.x[0], x[0])
    assert res.x is not x and res.P is not P  # inputs are not written to


def test_row_variances_are_the_diagonal_of_h_p_ht() -> None:
    rng = np.random.default_rng(5)
    H, P = rng.normal(size=(6, 3, 4)), _spd_batch(rng, 6, 4)
    full = H @ P @ H.swapaxes(1, 2)
    assert np.allclose(kalman.row_variances(H, P), np.diagonal(full, axis1=1, axis2=2))


def _rows_one_by_one(x, P, z, H, r, mask, rows):  # type: ignore[no-untyped-def]
    """The scalar Joseph-form rows written out plainly (``P·hᵀ`` by a product, the outer
    products by broadcasting): the oracle of ``update_independent``'s shortcuts."""
    x, P = x.copy(), P.copy()
    for j in rows:
        a = mask[:, j]
        if not a.any():
            continue
        h = H[:, j, :]
        Ph = (P @ h[:, :, None])[:, :, 0]
        s = (h * Ph).sum(axis=1) + r[:, j]
        inv = np.where(a, 1.0 / np.where(a, s, 1.0), 0.0)
        y = np.where(a, z[:, j] - (h * x).sum(axis=1), 0.0)
        k = Ph * inv[:, None]
        x += k * y[:, None]
        M = P - Ph[:, :, None] * k[:, None, :]  # P·(I − k·h)ᵀ
        post = M - k[:, :, None] * (h[:, None, :] @ M)[:, 0, None, :]  # (I − k·h)·M
        post += (k * np.where(a, r[:, j], 0.0)[:, None])[:, :, None] * k[:, None, :]
        P = 0.5 * (post + post.swapaxes(-1, -2))
    return x, P


@pytest.mark.parametrize("seed", range(4))
def test_unit_rows_read_off_p_give_the_same_numbers(seed: int) -> None:
    """Rows declared ``unit`` (H row = a state's unit vector, as MDSF's rate and distance rows)
    give the posterior of the general row path exactly, with and without masked items."""
    rng = np.random.default_rng(seed)
    N, n, m = 50, 8, 7
    x, P = rng.normal(size=(N, n)) * 10.0, _spd_batch(rng, N, n)
    H = np.tile(rng.normal(size=(m, n)), (N, 1, 1))
    unit = {2: 2, 3: 3, 6: 7}
    for j, i in unit.items():
        H[:, j, :] = np.eye(n)[i]
    r = rng.uniform(0.05, 3.0, size=(N, m))
    z = rng.normal(size=(N, m))
    mask = rng.random((N, m)) < (0.7 if seed % 2 else 1.0)
    rows = (0, 2, 3, 4, 6)
    plain = kalman.update_independent(x, P, z, H, r, mask, rows)
    fast = kalman.update_independent(x, P, z, H, r, mask, rows, unit)
    x_ref, P_ref = _rows_one_by_one(x, P, z, H, r, mask, rows)
    for res in (plain, fast):
        assert np.array_equal(res.x, x_ref) and np.array_equal(res.P, P_ref)
    assert np.array_equal(fast.nis, plain.nis) and np.array_equal(fast.dof, plain.dof)
    assert not np.array_equal(fast.x, x)  # the rows did move the state


@pytest.mark.parametrize("unit", [False, True], ids=["row", "unit_row"])
def test_precise_row_on_a_wide_prior_keeps_the_posterior_positive_definite(unit: bool) -> None:
    """A row far more precise than its prior (``r`` 1e-12..1e-6 on a variance 1e3..1e8, a state
    correlated with another): the posterior variance is about ``r``, far below the rounding of
    the prior. The Joseph form keeps it positive definite and close to the exact value; the
    expanded ``P − Ph·Phᵀ/s`` cancels to the prior's rounding and goes negative."""
    rng = np.random.default_rng(7)
    batch = 400
    p = 10.0 ** rng.uniform(3.0, 8.0, batch)
    r = 10.0 ** rng.uniform(-12.0, -6.0, batch)
    c = rng.uniform(-0.99, 0.99, batch) * np.sqrt(p)
    P = np.zeros((batch, 2, 2))
    P[:, 0, 0], P[:, 0, 1], P[:, 1, 0], P[:, 1, 1] = p, c, c, 1.0 + c * c / p
    H = np.array([[1.0, 0.0]])
    res = kalman.update_independent(
        np.zeros((batch, 2)),
        P,
        np.zeros((batch, 1)),
        H,
        r[:, None],
        np.ones((batch, 1), dtype=bool),
        unit={0: 0} if unit else None,
    )
    assert np.array_equal(res.P, np.swapaxes(res.P, 1, 2))
    assert np.all(np.linalg.eigvalsh(res.P) > 0.0)
    # exact: the measured state's variance p·r/(p + r) ≈ r
    assert np.allclose(res.P[:, 0, 0], p * r / (p + r), rtol=1e-3, atol=0)
