"""The rigid and similarity fits of point sets against evo's Umeyama alignment and known transforms.

``geometry.similarity_fit`` is the package's one point-set alignment: ``geometry.rigid_fit`` (the
RANSAC and the initial guess) and ``metrics.umeyama_alignment`` (the ATE) call it.
"""

import gtsam
import numpy as np
import pytest

from covo_gtsam.geometry import rigid_fit, similarity_fit
from covo_gtsam.metrics import ate, umeyama_alignment


def _problem(n=60, seed=0, noise=0.01, scale=1.0):
    rng = np.random.default_rng(seed)
    src = rng.normal(size=(n, 3)) * [2.0, 1.0, 0.5]
    R = gtsam.Rot3.Expmap(rng.normal(size=3)).matrix()
    t = rng.normal(size=3)
    dst = scale * src @ R.T + t + rng.normal(scale=noise, size=(n, 3))
    return src, dst, R, t


@pytest.mark.parametrize("with_scale", [False, True])
@pytest.mark.parametrize("seed", range(5))
def test_umeyama_matches_evo(seed, with_scale):
    from evo.core.geometry import umeyama_alignment as evo_umeyama

    src, dst, _, _ = _problem(seed=seed, noise=0.05, scale=1.3 if with_scale else 1.0)
    R, t, s = umeyama_alignment(src, dst, with_scale=with_scale)
    R_evo, t_evo, s_evo = evo_umeyama(src.T, dst.T, with_scale)
    np.testing.assert_allclose(R, R_evo, atol=1e-12)
    np.testing.assert_allclose(t, t_evo, atol=1e-12)
    assert s == pytest.approx(s_evo, rel=1e-12)


@pytest.mark.parametrize("seed", range(5))
def test_rigid_fit_matches_evo(seed):
    from evo.core.geometry import umeyama_alignment as evo_umeyama

    src, dst, _, _ = _problem(seed=seed, noise=0.05)
    R, t = rigid_fit(dst, src)
    R_evo, t_evo, _ = evo_umeyama(src.T, dst.T, False)
    np.testing.assert_allclose(R, R_evo, atol=1e-12)
    np.testing.assert_allclose(t, t_evo, atol=1e-12)


def test_rigid_fit_weights_are_repeated_points():
    src, dst, _, _ = _problem(n=30, seed=7, noise=0.1)
    counts = np.random.default_rng(1).integers(1, 5, size=30)
    R, t = rigid_fit(dst, src, counts.astype(float))
    R_rep, t_rep = rigid_fit(np.repeat(dst, counts, axis=0), np.repeat(src, counts, axis=0))
    np.testing.assert_allclose(R, R_rep, atol=1e-12)
    np.testing.assert_allclose(t, t_rep, atol=1e-12)


def test_rigid_fit_batch_equals_one_by_one():
    problems = [_problem(n=10, seed=s, noise=0.02) for s in range(4)]
    A = np.array([p[1] for p in problems])
    B = np.array([p[0] for p in problems])
    R, t = rigid_fit(A, B)
    for k in range(4):
        R1, t1 = rigid_fit(A[k], B[k])
        np.testing.assert_allclose(R[k], R1, atol=1e-14)
        np.testing.assert_allclose(t[k], t1, atol=1e-14)


def test_known_transform_recovered_within_the_noise():
    src, dst, R_true, t_true = _problem(n=2000, seed=3, noise=1e-3, scale=0.7)
    R, t, s = umeyama_alignment(src, dst, with_scale=True)
    assert np.rad2deg(np.arccos(np.clip((np.trace(R.T @ R_true) - 1) / 2, -1, 1))) < 5e-3
    np.testing.assert_allclose(t, t_true, atol=2e-4)
    assert s == pytest.approx(0.7, abs=1e-4)  # about 10 sigma of the estimate
    src, dst, R_true, t_true = _problem(n=2000, seed=4, noise=1e-3)
    R, t = rigid_fit(dst, src)
    assert np.rad2deg(np.arccos(np.clip((np.trace(R.T @ R_true) - 1) / 2, -1, 1))) < 5e-3
    np.testing.assert_allclose(t, t_true, atol=2e-4)


def test_no_reflection_for_mirrored_planar_points():
    src, _, _, _ = _problem(seed=5)
    flat = src * [1, 1, 0]
    for R in (umeyama_alignment(flat, flat * [1, 1, -1])[0], rigid_fit(flat * [1, 1, -1], flat)[0]):
        assert np.linalg.det(R) == pytest.approx(1.0)


def test_ate_matches_evo_on_a_noisy_trajectory(random_trajectory):
    from evo.core import metrics
    from evo.core.trajectory import PoseTrajectory3D

    stamps, gt = random_trajectory(n=50, seed=2, step_sigma=0.1)
    rng = np.random.default_rng(0)
    offset = gtsam.Pose3.Expmap(np.array([0.3, -0.2, 0.5, 1.0, -2.0, 0.5])).matrix()
    est = np.array([offset @ P @ gtsam.Pose3.Expmap(rng.normal(scale=0.01, size=6)).matrix() for P in gt])
    ref_t = PoseTrajectory3D(poses_se3=list(gt), timestamps=stamps)
    est_t = PoseTrajectory3D(poses_se3=list(est), timestamps=stamps)
    est_t.align(ref_t, correct_scale=False)
    m = metrics.APE(metrics.PoseRelation.translation_part)
    m.process_data((ref_t, est_t))
    ours = ate(gt, est)
    for key in ("rmse", "mean", "median", "max"):
        assert ours[key] == pytest.approx(m.get_statistic(getattr(metrics.StatisticsType, key)), rel=1e-10)


def test_batched_similarity_fit_matches_evo():
    from evo.core.geometry import umeyama_alignment as evo_umeyama

    problems = [_problem(n=20, seed=s, noise=0.05, scale=0.5 + s) for s in range(3)]
    R, t, s = similarity_fit(np.array([p[1] for p in problems]), np.array([p[0] for p in problems]))
    for k, (src, dst, _, _) in enumerate(problems):
        R_evo, t_evo, s_evo = evo_umeyama(src.T, dst.T, True)
        np.testing.assert_allclose(R[k], R_evo, atol=1e-12)
        np.testing.assert_allclose(t[k], t_evo, atol=1e-12)
        assert s[k] == pytest.approx(s_evo, rel=1e-12)
