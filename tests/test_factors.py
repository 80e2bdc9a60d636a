"""Residuals, Jacobians and GTSAM factors of the two-way point transfer."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from covo_gtsam.factors import (
    compress_system,
    pair_between_factor,
    pair_factor,
    transfer_between_factor,
    transfer_factor,
)
from covo_gtsam.transfer import (
    residual_covariances,
    transfer_jacobians,
    transfer_residuals,
    whitened_system,
    whitening,
)
from covo_gtsam.transfer import whitened_error as numpy_whitened_error

K0, K1 = gtsam.symbol("x", 0), gtsam.symbol("x", 1)


def random_problem(n=12, seed=0):
    rng = np.random.default_rng(seed)
    T = gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(scale=0.4, size=3)), rng.normal(scale=0.5, size=3))
    X_k1 = rng.uniform([-1, -1, 1], [1, 1, 4], size=(n, 3))
    X_k = X_k1 @ T.rotation().matrix().T + T.translation() + rng.normal(scale=0.01, size=(n, 3))
    A = rng.normal(scale=0.02, size=(n, 3, 3))
    Q_k = A @ A.transpose(0, 2, 1) + 1e-4 * np.eye(3)
    B = rng.normal(scale=0.02, size=(n, 3, 3))
    Q_k1 = B @ B.transpose(0, 2, 1) + 1e-4 * np.eye(3)
    return T, X_k, X_k1, Q_k, Q_k1


def numerical_jacobian(f, pose: gtsam.Pose3, h=1e-6):
    cols = []
    for i in range(6):
        d = np.zeros(6)
        d[i] = h
        cols.append((f(pose.retract(d)) - f(pose.retract(-d))) / (2 * h))
    return np.stack(cols, axis=-1)


def test_jacobians_match_central_differences():
    T, X_k, X_k1, _, _ = random_problem()
    J_b, J_f = transfer_jacobians(T.rotation().matrix(), T.translation(), X_k, X_k1)

    def rb(P):
        return transfer_residuals(P.rotation().matrix(), P.translation(), X_k, X_k1)[0]

    def rf(P):
        return transfer_residuals(P.rotation().matrix(), P.translation(), X_k, X_k1)[1]

    np.testing.assert_allclose(J_b, numerical_jacobian(rb, T), atol=1e-7)
    np.testing.assert_allclose(J_f, numerical_jacobian(rf, T), atol=1e-7)


def test_forward_residual_is_rotated_backward_residual():
    T, X_k, X_k1, _, _ = random_problem()
    R = T.rotation().matrix()
    r_b, r_f = transfer_residuals(R, T.translation(), X_k, X_k1)
    np.testing.assert_allclose(r_f, -(r_b @ R), atol=1e-12)  # r_f = -R^T r_b


@pytest.mark.skipif(not hasattr(gtsam, "KnownLandmarkFactorPose3"),
                    reason="GTSAM < 4.3 has no KnownLandmarkFactor*Pose3 to compare with")
def test_residuals_against_gtsam_native_factors():
    """GTSAM's KnownLandmarkFactor*Pose3 (landmark X_k known in frame k, measured X_k1 in frame k+1)
    compute -r_b and -r_f of the same pair on the pose T_k,k1."""
    T, X_k, X_k1, _, _ = random_problem(n=4)
    r_b, r_f = transfer_residuals(T.rotation().matrix(), T.translation(), X_k, X_k1)
    vals = gtsam.Values()
    vals.insert(K0, T)
    noise = gtsam.noiseModel.Unit.Create(3)
    for i in range(4):
        f_fwd = gtsam.KnownLandmarkFactorPose3(K0, X_k[i], X_k1[i], noise)
        f_bwd = gtsam.KnownLandmarkFactor2Pose3(K0, X_k1[i], X_k[i], noise)
        np.testing.assert_allclose(f_fwd.unwhitenedError(vals), -r_f[i], atol=1e-12)
        np.testing.assert_allclose(f_bwd.unwhitenedError(vals), -r_b[i], atol=1e-12)


@pytest.mark.parametrize("weighting", ["thesis", "consistent"])
def test_whitened_system_equals_whitened_residuals(weighting):
    T, X_k, X_k1, Q_k, Q_k1 = random_problem()
    R, t = T.rotation().matrix(), T.translation()
    C_b, C_f = residual_covariances(Q_k, Q_k1, weighting, R)
    W_b, W_f = whitening(C_b), whitening(C_f)
    np.testing.assert_allclose(W_b.transpose(0, 2, 1) @ W_b, np.linalg.inv(C_b), rtol=1e-9, atol=1e-6)
    e, J = whitened_system(R, t, X_k, X_k1, W_b, W_f)
    r_b, r_f = transfer_residuals(R, t, X_k, X_k1)
    J_b, J_f = transfer_jacobians(R, t, X_k, X_k1)
    e_ref = np.concatenate([np.einsum("nij,nj->ni", W_b, r_b), np.einsum("nij,nj->ni", W_f, r_f)], 1).ravel()
    J_ref = np.concatenate([W_b @ J_b, W_f @ J_f], 1).reshape(-1, 6)
    np.testing.assert_allclose(e, e_ref, atol=1e-9)
    np.testing.assert_allclose(J, J_ref, atol=1e-9)


def test_consistent_cost_equals_one_way_mahalanobis():
    T, X_k, X_k1, Q_k, Q_k1 = random_problem()
    R, t = T.rotation().matrix(), T.translation()
    C_b, C_f = residual_covariances(Q_k, Q_k1, "consistent", R)
    e, _ = whitened_system(R, t, X_k, X_k1, whitening(C_b), whitening(C_f))
    r_b, _ = transfer_residuals(R, t, X_k, X_k1)
    S_b = Q_k + R @ Q_k1 @ R.T
    one_way = np.einsum("ni,ni->", r_b, np.linalg.solve(S_b, r_b[..., None])[..., 0])
    assert e @ e == pytest.approx(one_way, rel=1e-9)


def factor_jacobians(factor, values):
    """Whitened error and Jacobians of a GTSAM factor via its linearisation (A, b: A dx = b = -e)."""
    lin = factor.linearize(values)
    A, b = lin.jacobian()
    return A, -b


def whitened_error(factor, values):
    lin = factor.linearize(values)
    return -lin.jacobian()[1]


def stacked_error(X_k, X_k1, C_b, C_f):
    """Pose -> the 6N whitened two-way error in numpy (:func:`transfer.whitened_error`, the
    vectorised factors' model; differentiated numerically, never through the analytic Jacobian)."""
    W_b, W_f = whitening(C_b), whitening(C_f)
    return lambda P: numpy_whitened_error(P.rotation().matrix(), P.translation(), X_k, X_k1, W_b, W_f)


def assert_linearisation(factor, values, A, e, J_num, e_num):
    """The factor's linear system (A, e) has the normal equations of the numerical one of the
    stacked error (J_num, e_num): A^T A = J^T J, A^T e = J^T e, and the same error |e|^2. (A
    per-pair factor's rows differ from J_num by GTSAM's choice of square-root information, an
    orthogonal transform; a vectorised factor hands GTSAM 7 compressed rows.)"""
    H_num, g_num = J_num.T @ J_num, J_num.T @ e_num
    np.testing.assert_allclose(A.T @ A, H_num, rtol=1e-6, atol=1e-6 * np.abs(H_num).max())
    np.testing.assert_allclose(A.T @ e, g_num, rtol=1e-6, atol=1e-6 * np.abs(g_num).max())
    assert factor.error(values) == pytest.approx(0.5 * e_num @ e_num, rel=1e-9)


@pytest.mark.parametrize("weighting", ["thesis", "consistent"])
def test_unary_factor_jacobians_numerically(weighting):
    T, X_k, X_k1, Q_k, Q_k1 = random_problem(n=5)
    C_b, C_f = residual_covariances(Q_k, Q_k1, weighting, T.rotation().matrix())
    for f, m in ((transfer_factor(K0, X_k, X_k1, C_b, C_f), 5), (pair_factor(K0, X_k[0], X_k1[0], C_b[0], C_f[0]), 1)):
        vals = gtsam.Values()
        vals.insert(K0, T)
        A, e = factor_jacobians(f, vals)
        err = stacked_error(X_k[:m], X_k1[:m], C_b[:m], C_f[:m])
        assert_linearisation(f, vals, A, e, numerical_jacobian(err, T), err(T))
        if m == 1:  # per pair: the rows themselves against the factor's own whitened error

            def own(P, f=f):
                v = gtsam.Values()
                v.insert(K0, P)
                return whitened_error(f, v)

            np.testing.assert_allclose(A, numerical_jacobian(own, T), rtol=1e-6, atol=1e-5)


@pytest.mark.parametrize("weighting", ["thesis", "consistent"])
def test_binary_factor_jacobians_numerically(weighting):
    T, X_k, X_k1, Q_k, Q_k1 = random_problem(n=5)
    rng = np.random.default_rng(3)
    x0 = gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3)), rng.normal(size=3))
    x1 = x0.compose(T)
    C_b, C_f = residual_covariances(Q_k, Q_k1, weighting, T.rotation().matrix())
    for f, m in (
        (transfer_between_factor(K0, K1, X_k, X_k1, C_b, C_f), 5),
        (pair_between_factor(K0, K1, X_k[0], X_k1[0], C_b[0], C_f[0]), 1),
    ):
        vals = gtsam.Values()
        vals.insert(K0, x0)
        vals.insert(K1, x1)
        A, e = factor_jacobians(f, vals)
        err = stacked_error(X_k[:m], X_k1[:m], C_b[:m], C_f[:m])
        num = np.hstack([numerical_jacobian(lambda P, err=err: err(P.between(x1)), x0),
                         numerical_jacobian(lambda P, err=err: err(x0.between(P)), x1)])
        assert_linearisation(f, vals, A, e, num, err(T))
        if m == 1:  # per pair: the rows themselves against the factor's own whitened error

            def own(P0, P1, f=f):
                v = gtsam.Values()
                v.insert(K0, P0)
                v.insert(K1, P1)
                return whitened_error(f, v)

            num_own = np.hstack([numerical_jacobian(lambda P: own(P, x1), x0),
                                 numerical_jacobian(lambda P: own(x0, P), x1)])
            np.testing.assert_allclose(A, num_own, rtol=1e-6, atol=1e-5)
        # the binary factor at x0^-1 x1 = T equals the unary factor at T
        v = gtsam.Values()
        v.insert(K0, T)
        unary = transfer_factor(K0, X_k, X_k1, C_b, C_f) if m > 1 else pair_factor(
            K0, X_k[0], X_k1[0], C_b[0], C_f[0])
        A_u, e_u = factor_jacobians(unary, v)
        np.testing.assert_allclose(e, e_u, atol=1e-9)
        np.testing.assert_allclose(A[:, 6:], A_u, atol=1e-9)


@pytest.mark.parametrize("rank", [6, 5])
def test_compressed_system_keeps_normal_equations_and_error(rank):
    rng = np.random.default_rng(rank)
    J = rng.normal(size=(60, 6))
    if rank < 6:  # degenerate geometry: one direction exactly unobserved (Cholesky fails, eigen fallback)
        J[:, 5] = 0.0
    e = rng.normal(size=60)
    if rank < 6:
        with pytest.raises(np.linalg.LinAlgError):
            np.linalg.cholesky(J.T @ J)
    e7, R7 = compress_system(e, J)
    assert e7.shape == (7,) and R7.shape == (7, 6) and np.all(R7[6] == 0)
    np.testing.assert_allclose(R7.T @ R7, J.T @ J, atol=1e-9)
    np.testing.assert_allclose(R7.T @ e7, J.T @ e, atol=1e-9)
    assert e7 @ e7 == pytest.approx(e @ e, rel=1e-12)
    # the same Gauss-Newton model: |e + J d|^2 == |e7 + R7 d|^2 for any step d
    d = rng.normal(size=6)
    assert np.sum((e7 + R7 @ d) ** 2) == pytest.approx(np.sum((e + J @ d) ** 2), rel=1e-9)


def solve(graph, init):
    vals = gtsam.Values()
    vals.insert(K0, init)
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-14)
    params.setAbsoluteErrorTol(1e-15)
    params.setMaxIterations(100)
    res = gtsam.LevenbergMarquardtOptimizer(graph, vals, params).optimize()
    return res.atPose3(K0), gtsam.Marginals(graph, res).marginalCovariance(K0)


@pytest.mark.parametrize("weighting", ["thesis", "consistent"])
def test_per_pair_graph_equals_vectorized_factor(weighting):
    T, X_k, X_k1, Q_k, Q_k1 = random_problem(n=40, seed=5)
    C_b, C_f = residual_covariances(Q_k, Q_k1, weighting, T.rotation().matrix())
    g_pairs = gtsam.NonlinearFactorGraph()
    for i in range(len(X_k)):
        g_pairs.add(pair_factor(K0, X_k[i], X_k1[i], C_b[i], C_f[i]))
    g_vec = gtsam.NonlinearFactorGraph()
    g_vec.add(transfer_factor(K0, X_k, X_k1, C_b, C_f))
    init = T.retract(np.full(6, 0.02))
    p1, c1 = solve(g_pairs, init)
    p2, c2 = solve(g_vec, init)
    assert np.abs(gtsam.Pose3.Logmap(p1.between(p2))).max() <= 1e-9
    np.testing.assert_allclose(c1, c2, rtol=1e-9, atol=1e-15)
