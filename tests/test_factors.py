"""Residuals, Jacobians and GTSAM factors of the two-way point transfer."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from covo_gtsam.factors import (
    pair_between_factor,
    pair_factor,
    residual_covariances,
    transfer_between_factor,
    transfer_factor,
    transfer_jacobians,
    transfer_residuals,
    whitened_system,
    whitening,
)

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


@pytest.mark.parametrize("weighting", ["thesis", "consistent"])
def test_unary_factor_jacobians_numerically(weighting):
    T, X_k, X_k1, Q_k, Q_k1 = random_problem(n=5)
    C_b, C_f = residual_covariances(Q_k, Q_k1, weighting, T.rotation().matrix())
    for f in (transfer_factor(K0, X_k, X_k1, C_b, C_f), pair_factor(K0, X_k[0], X_k1[0], C_b[0], C_f[0])):
        vals = gtsam.Values()
        vals.insert(K0, T)
        A, _ = factor_jacobians(f, vals)

        def err(P, f=f):
            v = gtsam.Values()
            v.insert(K0, P)
            return whitened_error(f, v)

        np.testing.assert_allclose(A, numerical_jacobian(err, T), rtol=1e-6, atol=1e-5)


@pytest.mark.parametrize("weighting", ["thesis", "consistent"])
def test_binary_factor_jacobians_numerically(weighting):
    T, X_k, X_k1, Q_k, Q_k1 = random_problem(n=5)
    rng = np.random.default_rng(3)
    x0 = gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3)), rng.normal(size=3))
    x1 = x0.compose(T)
    C_b, C_f = residual_covariances(Q_k, Q_k1, weighting, T.rotation().matrix())
    for f in (
        transfer_between_factor(K0, K1, X_k, X_k1, C_b, C_f),
        pair_between_factor(K0, K1, X_k[0], X_k1[0], C_b[0], C_f[0]),
    ):
        vals = gtsam.Values()
        vals.insert(K0, x0)
        vals.insert(K1, x1)
        A, _ = factor_jacobians(f, vals)

        def err0(P, f=f):
            v = gtsam.Values()
            v.insert(K0, P)
            v.insert(K1, x1)
            return whitened_error(f, v)

        def err1(P, f=f):
            v = gtsam.Values()
            v.insert(K0, x0)
            v.insert(K1, P)
            return whitened_error(f, v)

        num = np.hstack([numerical_jacobian(err0, x0), numerical_jacobian(err1, x1)])
        np.testing.assert_allclose(A, num, rtol=1e-6, atol=1e-5)
        # the binary factor at x0^-1 x1 = T equals the unary factor at T
        v = gtsam.Values()
        v.insert(K0, T)
        unary = transfer_factor(K0, X_k, X_k1, C_b, C_f) if f.dim() > 6 else pair_factor(
            K0, X_k[0], X_k1[0], C_b[0], C_f[0])
        np.testing.assert_allclose(whitened_error(f, vals), whitened_error(unary, v), atol=1e-9)


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
