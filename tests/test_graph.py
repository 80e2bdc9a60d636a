"""covo_gtsam.graph: between factors from odometry steps and the ROS PoseWithCovariance export."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from covo_gtsam.errors import InputError
from covo_gtsam.graph import (
    between_factors,
    from_pose_with_covariance,
    step_keys,
    to_pose_with_covariance,
    unit_between_factors,
)
from covo_gtsam.odometry import OdometryStep


def random_pose(rng: np.random.Generator, rot: float = 0.5, trans: float = 1.0) -> gtsam.Pose3:
    return gtsam.Pose3.Expmap(np.concatenate([rng.normal(0, rot, 3), rng.normal(0, trans, 3)]))


def random_cov(rng: np.random.Generator, scale: float = 1e-3) -> np.ndarray:
    A = rng.normal(size=(6, 6))
    C = A @ A.T + 0.5 * np.eye(6)
    return scale**2 * C


def make_steps(rng: np.random.Generator, statuses=("lost", "first", "tracked", "lost", "tracked", "tracked", "lost")):
    """Steps like ``vo.steps``: each tracked one refers to the previous first/tracked step."""
    steps = []
    ref = None
    for i, status in enumerate(statuses):
        t = 100.0 + 0.033 * i
        if status == "lost":
            steps.append(OdometryStep(t, "lost", reason="test", ref_timestamp=None if ref is None else ref.timestamp))
            continue
        if status == "first":
            s = OdometryStep(t, "first", pose=gtsam.Pose3(), pose_covariance=np.zeros((6, 6)))
        else:
            rel = random_pose(rng, 0.1, 0.1)
            s = OdometryStep(t, "tracked", ref_timestamp=ref.timestamp, relative=rel, covariance=random_cov(rng),
                             pose=ref.pose.compose(rel))
        steps.append(s)
        ref = s
    return steps


# ------------------------------------------------------------------------------------------------
# between factors
# ------------------------------------------------------------------------------------------------
def test_keys_factor_count_noise_and_initial_values():
    rng = np.random.default_rng(1)
    steps = make_steps(rng)
    factors, initial = between_factors(steps)
    posed = [i for i, s in enumerate(steps) if s.status in ("first", "tracked")]
    tracked = [i for i, s in enumerate(steps) if s.status == "tracked"]
    assert posed == [1, 2, 4, 5]
    assert len(factors) == len(tracked) == 3
    assert set(initial.keys()) == {gtsam.symbol("x", i) for i in posed}
    # each factor links the previous posed step (lost frames skipped) to the current one
    expected_pairs = [(1, 2), (2, 4), (4, 5)]
    for f, (a, b), i in zip(factors, expected_pairs, tracked):
        assert list(f.keys()) == [gtsam.symbol("x", a), gtsam.symbol("x", b)]
        assert f.measured().equals(steps[i].relative, 1e-15)
        np.testing.assert_allclose(f.noiseModel().covariance(), steps[i].covariance, rtol=1e-9, atol=1e-18)
    for i in posed:
        assert initial.atPose3(gtsam.symbol("x", i)).equals(steps[i].pose, 1e-12)
    # the chain is consistent: zero error at the initial values
    graph = gtsam.NonlinearFactorGraph()
    for f in factors:
        graph.add(f)
    assert graph.error(initial) < 1e-20


def test_keyframe_steps_link_to_their_keyframe():
    """With keyframes several steps share one reference; each factor uses ``ref_timestamp``."""
    rng = np.random.default_rng(10)
    first = OdometryStep(0.0, "first", pose=gtsam.Pose3(), pose_covariance=np.zeros((6, 6)))
    steps = [first]
    for t, ref in ((1.0, 0), (2.0, 0), (3.0, 2), (4.0, 2)):
        rel = random_pose(rng, 0.1, 0.1)
        steps.append(OdometryStep(t, "tracked", ref_timestamp=steps[ref].timestamp, relative=rel,
                                  covariance=random_cov(rng), pose=steps[ref].pose.compose(rel)))
    factors, initial = between_factors(steps)
    X = lambda i: gtsam.symbol("x", i)  # noqa: E731
    assert [list(f.keys()) for f in factors] == [[X(0), X(1)], [X(0), X(2)], [X(2), X(3)], [X(2), X(4)]]
    for i, s in enumerate(steps):
        assert initial.atPose3(X(i)).equals(s.pose, 1e-12)


def test_initial_values_composed_when_poses_missing():
    rng = np.random.default_rng(2)
    steps = make_steps(rng)
    truth = [s.pose for s in steps]
    for s in steps:
        s.pose = None
    _, initial = between_factors(steps)
    for i, s in enumerate(steps):
        if s.status in ("first", "tracked"):
            assert initial.atPose3(gtsam.symbol("x", i)).equals(truth[i], 1e-12)


def test_custom_keys_and_prefix():
    rng = np.random.default_rng(3)
    steps = make_steps(rng)
    factors, initial = between_factors(steps, key=lambda i: 1000 + i)
    assert list(factors[0].keys()) == [1001, 1002]
    assert set(initial.keys()) == {1001, 1002, 1004, 1005}
    factors, initial = between_factors(steps, key=lambda t: int(round(t * 1000)), key_by="timestamp")
    assert list(factors[0].keys()) == [int(round(steps[1].timestamp * 1000)), int(round(steps[2].timestamp * 1000))]
    factors, initial = between_factors(steps, prefix="p")
    assert list(factors[-1].keys()) == [gtsam.symbol("p", 4), gtsam.symbol("p", 5)]
    assert step_keys(steps) == {i: gtsam.symbol("x", i) for i in (1, 2, 4, 5)}
    with pytest.raises(InputError):
        between_factors(steps, key=lambda i: 7)
    with pytest.raises(InputError):
        between_factors(steps, key_by="frame")


def test_unit_between_factors_share_everything_but_the_noise():
    rng = np.random.default_rng(4)
    steps = make_steps(rng)
    ref, ref_init = between_factors(steps)
    for kwargs, cov in [
        ({}, np.eye(6)),
        ({"sigma": 0.01}, 1e-4 * np.eye(6)),
        ({"sigma": [1, 2, 3, 4, 5, 6]}, np.diag(np.arange(1.0, 7.0) ** 2)),
        ({"covariance": steps[2].covariance}, steps[2].covariance),
    ]:
        factors, initial = unit_between_factors(steps, **kwargs)
        assert len(factors) == len(ref)
        assert initial.keys() == ref_init.keys()
        for f, g in zip(factors, ref):
            assert list(f.keys()) == list(g.keys())
            assert f.measured().equals(g.measured(), 0.0)
            np.testing.assert_allclose(f.noiseModel().covariance(), cov, rtol=1e-9)
    # a per-step callable override
    factors, _ = between_factors(steps, noise=lambda s: 4.0 * s.covariance)
    for f, i in zip(factors, [2, 4, 5]):
        np.testing.assert_allclose(f.noiseModel().covariance(), 4.0 * steps[i].covariance, rtol=1e-9)
    with pytest.raises(InputError):
        unit_between_factors(steps, sigma=0.1, covariance=np.eye(6))
    with pytest.raises(InputError):
        unit_between_factors(steps, sigma=-1.0)


def test_missing_reference_is_an_error():
    rng = np.random.default_rng(5)
    steps = make_steps(rng, ("first", "tracked", "tracked"))
    with pytest.raises(InputError, match="reference"):
        between_factors(steps[1:])  # the first frame is cut off


def test_between_factor_error_is_right_perturbation_of_the_covariance():
    """GTSAM's between error ``Log(T^-1 x_a^-1 x_b)`` is distributed N(0, step.covariance) when
    ``x_b = x_a T Exp(xi)``, ``xi ~ N(0, cov)``: 2 * factor error ~ chi2(6)."""
    rng = np.random.default_rng(6)
    steps = make_steps(rng, ("first", "tracked"))
    (f,), initial = between_factors(steps)
    k0, k1 = gtsam.symbol("x", 0), gtsam.symbol("x", 1)
    L = np.linalg.cholesky(steps[1].covariance)
    chi2 = []
    for _ in range(4000):
        xi = L @ rng.standard_normal(6)
        v = gtsam.Values()
        v.insert(k0, gtsam.Pose3())
        v.insert(k1, steps[1].relative.compose(gtsam.Pose3.Expmap(xi)))
        chi2.append(2.0 * f.error(v))
    assert abs(np.mean(chi2) - 6.0) < 0.3  # sd of the mean ~ sqrt(12 / 4000) = 0.055


def test_between_factors_from_real_odometry():
    """Steps of a short real run give exactly their own covariances as noise."""
    from pathlib import Path

    seq_dir = Path(__file__).resolve().parents[1] / "data" / "rgbd_dataset_freiburg1_rpy_head40"
    tum = pytest.importorskip("covo_gtsam.datasets.tum")
    if not seq_dir.is_dir():
        pytest.skip("sample sequence missing")
    from covo_gtsam.odometry import VisualOdometry
    from covo_gtsam.steps import StepHistory

    seq = tum.TumSequence(seq_dir)
    vo = VisualOdometry(seq.camera)
    history = StepHistory()
    for i in range(4):
        history.add(vo.register_frame(*seq.load(i), seq.timestamps[i]))
    factors, initial = between_factors(history.steps)
    tracked = [s for s in history if s.has_relative_pose]
    assert len(factors) == len(tracked) >= 1
    for f, s in zip(factors, tracked):
        np.testing.assert_allclose(f.noiseModel().covariance(), s.covariance, rtol=1e-8, atol=1e-20)
    assert initial.size() == len(history.posed_steps)


# ------------------------------------------------------------------------------------------------
# ROS PoseWithCovariance
# ------------------------------------------------------------------------------------------------
def test_ros_dict_layout_and_identity():
    rng = np.random.default_rng(7)
    cov = random_cov(rng)
    d = to_pose_with_covariance(gtsam.Pose3(), cov)
    assert set(d) == {"position", "orientation", "covariance"}
    assert len(d["position"]) == 3 and len(d["orientation"]) == 4 and len(d["covariance"]) == 36
    np.testing.assert_allclose(d["orientation"], [0, 0, 0, 1])
    C = np.array(d["covariance"]).reshape(6, 6)
    # at the identity only the order changes: ROS [x y z rx ry rz] vs GTSAM [rx ry rz x y z]
    np.testing.assert_allclose(C[:3, :3], cov[3:, 3:], rtol=1e-12)
    np.testing.assert_allclose(C[3:, 3:], cov[:3, :3], rtol=1e-12)
    np.testing.assert_allclose(C[:3, 3:], cov[3:, :3], rtol=1e-12)


def test_ros_round_trip_exact():
    rng = np.random.default_rng(8)
    for _ in range(20):
        T = random_pose(rng, 1.0, 3.0)
        cov = random_cov(rng, 10 ** rng.uniform(-4, -1))
        d = to_pose_with_covariance(T, cov)
        T2, cov2 = from_pose_with_covariance(d)
        assert T2.equals(T, 1e-12)
        np.testing.assert_allclose(cov2, cov, rtol=1e-9, atol=1e-14 * np.abs(cov).max())
        d2 = to_pose_with_covariance(T2, cov2)
        np.testing.assert_allclose(d2["covariance"], d["covariance"], rtol=1e-9, atol=1e-14 * np.abs(cov).max())
        np.testing.assert_allclose(d2["orientation"], d["orientation"], atol=1e-14)
        q = np.array(d["orientation"])
        assert abs(np.linalg.norm(q) - 1) < 1e-12 and q[3] >= 0
        np.testing.assert_allclose(d["position"], T.translation(), atol=0)


@pytest.mark.slow
def test_ros_covariance_matches_monte_carlo_position_and_fixed_axis_rotation():
    """Sample xi ~ N(0, cov), T_true = T Exp(xi) (GTSAM's right perturbation); measure the position
    error t_true - t and the small rotation about the parent's fixed axes Log(R_true R^T). Their
    empirical covariance in ROS order [trans, rot] is the converted matrix. The pose is 3.7 m from
    the origin and rotated: the SE(3) adjoint (left tangent) and the naive block swap both fail."""
    rng = np.random.default_rng(9)
    T = gtsam.Pose3(gtsam.Rot3.RzRyRx(0.4, -0.7, 1.1), np.array([2.0, -1.5, 2.7276]))
    assert abs(np.linalg.norm(T.translation()) - 3.7) < 1e-3
    cov = np.diag([0.02, 0.01, 0.03, 0.01, 0.02, 0.015]) ** 2
    cov[0, 4] = cov[4, 0] = 0.3 * 0.02 * 0.02
    d = to_pose_with_covariance(T, cov)
    C_ros = np.array(d["covariance"]).reshape(6, 6)
    L = np.linalg.cholesky(cov)
    n = 100_000
    errs = np.empty((n, 6))
    R_inv = T.rotation().inverse()
    t = T.translation()
    for k in range(n):
        T_true = T.compose(gtsam.Pose3.Expmap(L @ rng.standard_normal(6)))
        errs[k, :3] = T_true.translation() - t
        errs[k, 3:] = gtsam.Rot3.Logmap(T_true.rotation().compose(R_inv))
    emp = errs.T @ errs / n

    def whitened_eigs(C):
        Li = np.linalg.inv(np.linalg.cholesky(C))
        return np.linalg.eigvalsh(Li @ emp @ Li.T)

    eig = whitened_eigs(C_ros)
    assert np.all(np.abs(eig - 1) < 0.03), eig  # Monte Carlo sd ~ sqrt(2 / n) = 0.0045 per direction
    assert np.abs(emp - C_ros).max() < 0.02 * np.abs(C_ros).max()
    naive = np.block([[cov[3:, 3:], cov[3:, :3]], [cov[:3, 3:], cov[:3, :3]]])
    assert np.max(np.abs(whitened_eigs(naive) - 1)) > 0.5
    P = np.block([[np.zeros((3, 3)), np.eye(3)], [np.eye(3), np.zeros((3, 3))]])
    adjoint = P @ T.AdjointMap() @ cov @ T.AdjointMap().T @ P.T  # the left tangent Log(T_true T^-1)
    assert np.abs(emp - adjoint).max() > 3 * np.abs(emp).max()


def test_ros_bad_input():
    with pytest.raises(InputError):
        to_pose_with_covariance(gtsam.Pose3(), np.eye(3))
    with pytest.raises(InputError):
        from_pose_with_covariance({"position": [0, 0, 0], "orientation": [0, 0, 0, 0], "covariance": [0.0] * 36})
    with pytest.raises(InputError):
        from_pose_with_covariance({"position": [0, 0, 0]})
