"""Square-root cubature filter against the full-covariance one; the MEE step both ways."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.friction.sckf import (
    ckf_predict,
    ckf_update,
    cubature_points,
    mee_measurement_sqrt,
    sckf_predict,
    sckf_update,
    tria,
)


def test_tria_is_a_lower_root() -> None:
    rng = np.random.default_rng(0)
    a = rng.normal(size=(5, 4, 9))
    t = tria(a)
    assert np.allclose(t @ np.swapaxes(t, -1, -2), a @ np.swapaxes(a, -1, -2), atol=1e-12)
    assert np.allclose(np.triu(t, 1), 0.0)
    assert np.all(np.diagonal(t, axis1=-2, axis2=-1) > 0)


def test_cubature_points_hold_mean_and_covariance() -> None:
    rng = np.random.default_rng(1)
    x = rng.normal(size=(2, 3))
    s = np.linalg.cholesky(np.array([[2.0, 0.3, 0.1], [0.3, 1.0, 0.2], [0.1, 0.2, 0.5]]))
    s = np.broadcast_to(s, (2, 3, 3))
    pts = cubature_points(x, s)
    assert pts.shape == (2, 6, 3)
    assert np.allclose(pts.mean(axis=1), x)
    dev = pts - x[:, None, :]
    assert np.allclose(np.einsum("bpi,bpj->bij", dev, dev) / 6, s @ np.swapaxes(s, -1, -2))


def test_sckf_equals_ckf_on_a_linear_case() -> None:
    """Twenty predict/update cycles of a linear system: the same posterior to 1e-9."""
    rng = np.random.default_rng(2)
    b, n, m = 4, 5, 3
    f_mat = np.eye(n) + 0.05 * rng.normal(size=(n, n))
    h_mat = rng.normal(size=(m, n))
    q = np.diag(rng.uniform(0.01, 0.1, n))
    r = np.diag(rng.uniform(0.05, 0.2, m))
    x_s = x_c = rng.normal(size=(b, n))
    p_c = np.broadcast_to(np.eye(n), (b, n, n)).copy()
    s_s = np.linalg.cholesky(p_c)
    sq_q, sq_r = np.linalg.cholesky(q), np.broadcast_to(np.linalg.cholesky(r), (b, m, m))

    def f(p: np.ndarray) -> np.ndarray:
        return p @ f_mat.T

    def h(p: np.ndarray) -> np.ndarray:
        return p @ h_mat.T

    for _ in range(20):
        z = rng.normal(size=(b, m))
        x_s, s_s = sckf_predict(x_s, s_s, f, sq_q)
        up = sckf_update(x_s, s_s, z, h, sq_r)
        x_s, s_s = up.x, up.s
        x_c, p_c = ckf_predict(x_c, p_c, f, q)
        x_c, p_c = ckf_update(x_c, p_c, z, h, r)
    assert np.max(np.abs(x_s - x_c)) < 1e-9
    assert np.max(np.abs(s_s @ np.swapaxes(s_s, -1, -2) - p_c)) < 1e-9


def test_linear_ckf_is_the_kalman_filter() -> None:
    """On a linear model the cubature rule is exact: the Kalman filter's own equations."""
    rng = np.random.default_rng(4)
    n, m = 3, 2
    h_mat = rng.normal(size=(m, n))
    x = rng.normal(size=(1, n))
    p = np.eye(n)[None] * 0.7
    r = np.eye(m) * 0.1
    z = rng.normal(size=(1, m))
    x_c, p_c = ckf_update(x, p, z, lambda pt: pt @ h_mat.T, r)
    s = h_mat @ p[0] @ h_mat.T + r
    k = p[0] @ h_mat.T @ np.linalg.inv(s)
    assert np.allclose(x_c[0], x[0] + k @ (z[0] - h_mat @ x[0]), atol=1e-12)
    assert np.allclose(p_c[0], (np.eye(n) - k @ h_mat) @ p[0], atol=1e-12)


def test_mee_covariance_positive_definite_for_consistent_innovations() -> None:
    sq_r = np.broadcast_to(np.diag([0.1, 0.1, 0.5]), (2, 3, 3)).copy()
    z_mean = np.zeros((2, 3))
    z = np.array([[0.05, -0.1, 0.3], [0.0, 0.0, 0.0]])
    mee = mee_measurement_sqrt(z, z_mean, 9, sq_r, kernel_sigma=2.0)
    assert mee.ok.all()
    r_bar = mee.sq_r @ np.swapaxes(mee.sq_r, -1, -2)
    np.linalg.cholesky(r_bar)  # positive definite
    # a zero innovation keeps R; a larger one is weighted down (R̄ grows)
    assert np.allclose(r_bar[1], sq_r[1] @ sq_r[1].T)
    assert r_bar[0, 2, 2] > (sq_r[0] @ sq_r[0].T)[2, 2]


def test_mee_falls_back_when_not_positive_definite() -> None:
    """An innovation far from every other entry gets a zero kernel weight: R̄ is not
    positive definite, ``ok`` is False and the nominal root is handed back."""
    sq_r = np.broadcast_to(np.diag([0.1, 0.1, 0.5]), (1, 3, 3)).copy()
    z = np.array([[1e3, -2e3, 5e3]])
    mee = mee_measurement_sqrt(z, np.zeros((1, 3)), 9, sq_r, kernel_sigma=0.5)
    assert not mee.ok[0]
    assert np.array_equal(mee.sq_r, sq_r)


@pytest.mark.parametrize("sigma", [0.5, 2.0, 10.0])
def test_mee_root_is_a_root_of_the_reweighted_covariance(sigma: float) -> None:
    rng = np.random.default_rng(5)
    sq_r = np.broadcast_to(np.eye(3) * 0.2, (50, 3, 3)).copy()
    z = rng.normal(scale=0.5, size=(50, 3))
    mee = mee_measurement_sqrt(z, np.zeros((50, 3)), 5, sq_r, sigma)
    assert mee.ok.all() or sigma < 1.0  # a narrow kernel may leave an entry without weight
    ok = mee.ok
    assert np.all(np.isfinite(mee.weight[ok])) and np.all(mee.weight[ok] > 0)
    r_bar = mee.sq_r @ np.swapaxes(mee.sq_r, -1, -2)
    expected = 0.04 / mee.weight  # diagonal R = 0.2² I reweighted per component
    assert np.allclose(np.diagonal(r_bar, axis1=-2, axis2=-1)[ok], expected[ok])
    assert np.allclose(r_bar[~ok], sq_r[~ok] @ np.swapaxes(sq_r[~ok], -1, -2))


def test_masked_gain_leaves_considered_states_and_keeps_the_covariance_exact() -> None:
    """Schmidt update on a linear case: masked states keep their mean, and ``S⁺`` is the root of
    the general-gain covariance ``(I − K H) P (I − K H)ᵀ + K R Kᵀ`` with the masked gain."""
    rng = np.random.default_rng(5)
    b, n, m = 3, 4, 2
    h_mat = rng.normal(size=(m, n))
    a = rng.normal(size=(b, n, n))
    p = a @ np.swapaxes(a, -1, -2) + np.eye(n)
    s = np.linalg.cholesky(p)
    r = np.diag([0.1, 0.3])
    sq_r = np.broadcast_to(np.linalg.cholesky(r), (b, m, m))
    x = rng.normal(size=(b, n))
    z = rng.normal(size=(b, m))
    mask = np.ones((b, n))
    mask[:, 1] = 0.0
    mask[0, 3] = 0.0
    up = sckf_update(x, s, z, lambda pts: pts @ h_mat.T, sq_r, mask)
    assert np.array_equal(up.x[:, 1], x[:, 1]) and up.x[0, 3] == x[0, 3]
    assert np.all(up.x[:, 0] != x[:, 0])
    pzz = h_mat @ p @ h_mat.T + r
    k = np.swapaxes(np.linalg.solve(pzz, h_mat @ p), -1, -2) * mask[..., None]
    i_kh = np.eye(n) - k @ h_mat
    want = i_kh @ p @ np.swapaxes(i_kh, -1, -2) + k @ r @ np.swapaxes(k, -1, -2)
    assert np.max(np.abs(up.s @ np.swapaxes(up.s, -1, -2) - want)) < 1e-9
    assert np.allclose(up.gain, k, atol=1e-12)


def test_central_prediction_moves_only_the_innovation() -> None:
    """``z_centre`` at the points' mean changes nothing; shifted by ``d`` it moves the mean by
    ``−K d`` and leaves gain and root alone (a linear case: the points' mean is ``H x``)."""
    rng = np.random.default_rng(6)
    b, n, m = 2, 3, 2
    h_mat = rng.normal(size=(m, n))
    a = rng.normal(size=(b, n, n))
    s = np.linalg.cholesky(a @ np.swapaxes(a, -1, -2) + np.eye(n))
    sq_r = np.broadcast_to(np.diag([0.2, 0.4]), (b, m, m))
    x = rng.normal(size=(b, n))
    z = rng.normal(size=(b, m))

    def h(pts: np.ndarray) -> np.ndarray:
        return np.asarray(pts @ h_mat.T)

    plain = sckf_update(x, s, z, h, sq_r)
    same = sckf_update(x, s, z, h, sq_r, None, x @ h_mat.T)
    assert np.allclose(same.x, plain.x, atol=1e-12)
    d = np.array([[0.3, -0.1], [0.0, 0.5]])
    moved = sckf_update(x, s, z, h, sq_r, None, x @ h_mat.T + d)
    assert np.allclose(moved.x, plain.x - (plain.gain @ d[..., None])[..., 0], atol=1e-12)
    assert np.allclose(moved.s, plain.s, atol=1e-12)
