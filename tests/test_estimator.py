"""Estimator: pose, covariance against an independent implementation, conventions, errors."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from covo_gtsam.covariance import (
    compose_chains,
    compose_covariance,
    ros_to_tangent,
    tangent_to_ros,
    tangent_to_tq,
    tq_to_tangent,
)
from covo_gtsam.errors import CovoError, DegenerateGeometryError, EstimationError, InputError, InsufficientPairsError
from covo_gtsam.estimator import POSE_KEY, estimate_relative_pose
from covo_gtsam.factors import transfer_factor
from covo_gtsam.geometry import matrix_to_quat
from covo_gtsam.noise import PixelNoise, PointNoiseModel
from covo_gtsam.simulation import SimulationConfig, make_scene, noisy_measurements


def sim_pairs(seed=0, n=200, px=2.0):
    rng = np.random.default_rng(seed)
    scene = make_scene(SimulationConfig(num_points=n), rng)
    model = PointNoiseModel(pixel=PixelNoise(px, px))
    X0, Q0 = noisy_measurements(scene.X0, scene.camera, model, rng)
    X1, Q1 = noisy_measurements(scene.X1, scene.camera, model, rng)
    return scene, X0, X1, Q0, Q1


def independent_information(pose: gtsam.Pose3, X_k, X_k1, C_b, C_f, param="tangent"):
    """Information J^T W J from finite differences of plain residuals, whitened by inv-Cholesky.

    ``param="tangent"``: perturbation pose.retract(xi); ``"tq"``: (t, q_v) with q_w = sqrt(1-|q_v|^2).
    """
    W_b = np.linalg.inv(np.linalg.cholesky(C_b))
    W_f = np.linalg.inv(np.linalg.cholesky(C_f))
    R0 = pose.rotation().matrix()
    t0 = pose.translation()
    q0 = matrix_to_quat(R0)

    def res(R, t):
        r_b = X_k - (X_k1 @ R.T + t)
        r_f = X_k1 - (X_k - t) @ R
        return np.concatenate([np.einsum("nij,nj->ni", W_b, r_b), np.einsum("nij,nj->ni", W_f, r_f)]).ravel()

    def at(d):
        if param == "tangent":
            P = pose.retract(d)
            return res(P.rotation().matrix(), P.translation())
        qv = q0[:3] + d[3:]
        qw = np.sqrt(1 - qv @ qv)
        R = gtsam.Rot3.Quaternion(qw, *qv).matrix()
        return res(R, t0 + d[:3])

    h = 1e-6
    J = np.stack([(at(np.eye(6)[i] * h) - at(-np.eye(6)[i] * h)) / (2 * h) for i in range(6)], 1)
    return J.T @ J


@pytest.mark.parametrize("weighting", ["consistent", "thesis"])
def test_covariance_equals_independent_inverse_information(weighting):
    _, X0, X1, Q0, Q1 = sim_pairs()
    res = estimate_relative_pose(X0, X1, Q0, Q1, weighting=weighting, scale=3.0)
    C_b, C_f = res.residual_covariances
    info = independent_information(res.pose, X0, X1, C_b, C_f)
    np.testing.assert_allclose(res.covariance, 3.0 * np.linalg.inv(info), rtol=1e-5)
    np.testing.assert_allclose(res.information, info, rtol=1e-5)


def test_pose_is_close_to_truth_and_convention():
    scene, X0, X1, Q0, Q1 = sim_pairs(px=0.5)
    res = estimate_relative_pose(X0, X1, Q0, Q1)
    # T_0,1 maps points of frame 1 into frame 0
    np.testing.assert_allclose(res.matrix, scene.T01, atol=0.02)
    np.testing.assert_allclose(X1 @ res.matrix[:3, :3].T + res.matrix[:3, 3], X0, atol=0.2)
    assert res.num_pairs == 200 and res.iterations >= 1 and np.isfinite(res.final_error)


def test_between_factor_noise_is_exactly_the_covariance():
    _, X0, X1, Q0, Q1 = sim_pairs()
    res = estimate_relative_pose(X0, X1, Q0, Q1)
    f = res.between_factor(gtsam.symbol("x", 0), gtsam.symbol("x", 1))
    np.testing.assert_allclose(f.noiseModel().covariance(), res.covariance, rtol=1e-10, atol=1e-18)
    assert f.measured().equals(res.pose, 1e-12)


def test_q_tq_round_trip_and_half_angle_convention():
    _, X0, X1, Q0, Q1 = sim_pairs()
    res = estimate_relative_pose(X0, X1, Q0, Q1)
    Qtq = res.covariance_tq
    np.testing.assert_allclose(tq_to_tangent(Qtq, res.pose), res.covariance, rtol=1e-9, atol=1e-18)
    np.testing.assert_allclose(tangent_to_tq(res.covariance, res.pose), Qtq, rtol=1e-12)
    # Q_tq is the propagated covariance over (t, q_v) computed independently of GTSAM
    C_b, C_f = res.residual_covariances
    info_tq = independent_information(res.pose, X0, X1, C_b, C_f, param="tq")
    np.testing.assert_allclose(Qtq, np.linalg.inv(info_tq), rtol=1e-4)
    # q_v is a half-angle quantity: its standard deviation is about half the rotation's
    assert np.sqrt(np.diag(Qtq)[3:]).sum() < 0.6 * np.sqrt(np.diag(res.covariance)[:3]).sum()


def test_ros_conversion_round_trip_and_monte_carlo():
    rng = np.random.default_rng(1)
    T = gtsam.Pose3(gtsam.Rot3.Expmap(np.array([0.3, -0.2, 0.5])), np.array([1.0, -2.0, 0.5]))
    A = rng.normal(scale=0.01, size=(6, 6))
    cov = A @ A.T + 1e-6 * np.eye(6)
    ros = tangent_to_ros(cov, T)
    np.testing.assert_allclose(ros_to_tangent(ros, T), cov, rtol=1e-9, atol=1e-15)
    # ROS: position error t_true - t and small rotation about the parent's fixed axes
    xs = rng.multivariate_normal(np.zeros(6), cov, size=20000)
    R_inv = T.rotation().inverse()
    err = []
    for x in xs:
        T_true = T.compose(gtsam.Pose3.Expmap(x))
        err.append(np.concatenate([T_true.translation() - T.translation(),
                                   gtsam.Rot3.Logmap(T_true.rotation().compose(R_inv))]))
    err = np.array(err)
    emp = err.T @ err / len(xs)
    np.testing.assert_allclose(emp, ros, atol=0.06 * np.abs(ros).max())


def test_compose_covariance_monte_carlo():
    rng = np.random.default_rng(2)
    Ta = gtsam.Pose3(gtsam.Rot3.Expmap(np.array([0.1, 0.2, -0.1])), np.array([0.5, 0.0, 0.2]))
    Tb = gtsam.Pose3(gtsam.Rot3.Expmap(np.array([-0.2, 0.1, 0.3])), np.array([0.1, 0.4, -0.3]))
    ca = np.diag([1e-4, 2e-4, 1e-4, 4e-4, 1e-4, 2e-4])
    cb = np.diag([2e-4, 1e-4, 3e-4, 1e-4, 3e-4, 1e-4])
    pred = compose_covariance(Ta, ca, Tb, cb)
    T = Ta.compose(Tb)
    xa = rng.multivariate_normal(np.zeros(6), ca, 20000)
    xb = rng.multivariate_normal(np.zeros(6), cb, 20000)
    e = np.array([gtsam.Pose3.Logmap(T.between(Ta.retract(a).compose(Tb.retract(b)))) for a, b in zip(xa, xb)])
    emp = e.T @ e / len(e)
    np.testing.assert_allclose(emp, pred, atol=0.06 * np.abs(pred).max())


def test_chains_of_poses_match_a_monte_carlo_and_pairwise_composition():
    """compose_chains: every window of 4 of 6 relative poses, against sampled perturbed chains (the
    poses' errors independent) and against compose_covariance (GTSAM's adjoint) along each chain."""
    rng = np.random.default_rng(7)
    T = np.array([gtsam.Pose3.Expmap(rng.normal(scale=[0.3] * 3 + [0.5] * 3)).matrix() for _ in range(6)])
    C = np.array([np.diag(rng.uniform(0.5, 3.0, 6)) * 1e-4 for _ in range(6)])
    Tc, Cc = compose_chains(T, C, 4)
    assert Tc.shape == (3, 4, 4) and Cc.shape == (3, 6, 6)
    for s in range(3):
        P, PC = gtsam.Pose3(T[s]), C[s]
        for k in range(s + 1, s + 4):
            PC = compose_covariance(P, PC, gtsam.Pose3(T[k]), C[k])
            P = P.compose(gtsam.Pose3(T[k]))
        np.testing.assert_allclose(Tc[s], P.matrix(), atol=1e-12)
        np.testing.assert_allclose(Cc[s], PC, rtol=1e-10, atol=1e-18)
    xs = [rng.multivariate_normal(np.zeros(6), C[k], 20000) for k in range(4)]
    chain = gtsam.Pose3(Tc[0])
    e = []
    for draw in zip(*xs):
        P = gtsam.Pose3()
        for k, x in enumerate(draw):
            P = P.compose(gtsam.Pose3(T[k]).retract(x))
        e.append(gtsam.Pose3.Logmap(chain.between(P)))
    e = np.array(e)
    np.testing.assert_allclose(e.T @ e / len(e), Cc[0], atol=0.06 * np.abs(Cc[0]).max())
    assert compose_chains(T, C, 7)[0].shape == (0, 4, 4)
    with pytest.raises(InputError):
        compose_chains(T, C[:-1], 2)
    # chains given by index: the same windows, and an index off the poses is an error
    Ti, Ci = compose_chains(T, C, np.arange(3)[:, None] + np.arange(4))
    np.testing.assert_array_equal(Ti, Tc)
    np.testing.assert_array_equal(Ci, Cc)
    with pytest.raises(InputError):
        compose_chains(T, C, np.array([[0, 6]]))


def test_scale_is_linear():
    _, X0, X1, Q0, Q1 = sim_pairs()
    a = estimate_relative_pose(X0, X1, Q0, Q1, scale=1.0)
    b = estimate_relative_pose(X0, X1, Q0, Q1, scale=16.0)
    np.testing.assert_allclose(b.covariance, 16.0 * a.covariance, rtol=1e-9)


def test_bad_inputs_raise_package_errors():
    _, X0, X1, Q0, Q1 = sim_pairs(n=20)
    with pytest.raises(InputError, match="shape"):
        estimate_relative_pose(X0[:, :2], X1, Q0, Q1)
    with pytest.raises(InputError, match="number of pairs"):
        estimate_relative_pose(X0[:-1], X1, Q0, Q1)
    bad = X0.copy()
    bad[3, 1] = np.nan
    with pytest.raises(InputError, match="NaN"):
        estimate_relative_pose(bad, X1, Q0, Q1)
    badq = Q0.copy()
    badq[2, 0, 1] += 1.0
    with pytest.raises(InputError, match="symmetric"):
        estimate_relative_pose(X0, X1, badq, Q1)
    with pytest.raises(InputError, match="positive definite"):
        estimate_relative_pose(X0, X1, Q0, -Q1)
    with pytest.raises(InsufficientPairsError):
        estimate_relative_pose(X0[:2], X1[:2], Q0[:2], Q1[:2])
    with pytest.raises(InputError, match="weighting"):
        estimate_relative_pose(X0, X1, Q0, Q1, weighting="magic")
    with pytest.raises(InputError, match="scale"):
        estimate_relative_pose(X0, X1, Q0, Q1, scale=-1.0)


@pytest.mark.parametrize("kind", ["collinear", "identical"])
def test_degenerate_geometry_raises(kind):
    n = 10
    if kind == "collinear":
        X1 = np.stack([np.linspace(-1, 1, n), np.zeros(n), np.full(n, 2.0)], 1)
    else:
        X1 = np.tile([0.1, 0.2, 2.0], (n, 1))
    X0 = X1 + [0.05, 0.0, 0.0]
    Q = np.tile(np.eye(3) * 1e-4, (n, 1, 1))
    with pytest.raises(EstimationError) as info:
        estimate_relative_pose(X0, X1, Q, Q)
    assert isinstance(info.value, (DegenerateGeometryError, CovoError))
    assert "degrees of freedom" in str(info.value) or "Marginal" in str(info.value) or "covariance" in str(info.value)


def test_robust_kernels_resist_gross_outliers_and_variance_factor():
    scene, X0, X1, Q0, Q1 = sim_pairs(n=300, px=2.0)
    X1 = X1.copy()
    X1[:40] += 0.3  # 40 gross outliers
    T_true = gtsam.Pose3(scene.T01)
    plain = estimate_relative_pose(X0, X1, Q0, Q1)
    for kernel in ("huber", "cauchy"):
        r = estimate_relative_pose(X0, X1, Q0, Q1, robust=kernel)
        err = np.abs(gtsam.Pose3.Logmap(r.pose.between(T_true))).max()
        assert err < 0.2 * np.abs(gtsam.Pose3.Logmap(plain.pose.between(T_true))).max()
    assert plain.chi2_per_dof > 3  # the outliers show in the a-posteriori variance factor
    vf = estimate_relative_pose(X0, X1, Q0, Q1, variance_factor=True)
    np.testing.assert_allclose(vf.covariance, plain.covariance * plain.chi2_per_dof, rtol=1e-9)
    with pytest.raises(InputError, match="robust"):
        estimate_relative_pose(X0, X1, Q0, Q1, robust="tukey")


def test_marginal_covariance_equals_gtsam_marginals_of_the_nonlinear_graph():
    rng = np.random.default_rng(11)
    X_k1 = rng.uniform([-1, -1, 1], [1, 1, 3], (80, 3))
    T = gtsam.Pose3(gtsam.Rot3.Rodrigues(0.05, -0.02, 0.1), np.array([0.1, 0.0, -0.05]))
    X_k = X_k1 @ T.rotation().matrix().T + T.translation()
    Q = np.tile(np.diag([1e-5, 2e-5, 5e-5]), (80, 1, 1))
    X_k = X_k + rng.standard_normal(X_k.shape) * 3e-3
    res = estimate_relative_pose(X_k, X_k1, Q, Q)
    graph = gtsam.NonlinearFactorGraph()
    graph.add(transfer_factor(POSE_KEY, X_k, X_k1, *res.residual_covariances))
    values = gtsam.Values()
    values.insert(POSE_KEY, res.pose)
    expected = gtsam.Marginals(graph, values).marginalCovariance(POSE_KEY)
    np.testing.assert_allclose(res.covariance, expected, rtol=1e-9)
