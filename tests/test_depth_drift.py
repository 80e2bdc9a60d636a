"""The depth's drift: the depth-free estimates' disagreement with the 3D-3D estimate along the
depth-scale response (docs/derivation.md, "The depth's drift")."""

import gtsam
import numpy as np
import pytest

from covo_gtsam.camera import Camera
from covo_gtsam.config import OdometryConfig
from covo_gtsam.depth_drift import DepthDrift, drift_along
from covo_gtsam.estimator import estimate_relative_pose
from covo_gtsam.frame_errors import depth_scale_basis, transfer_gains
from covo_gtsam.integrity import depth_free_check


def _pair(scale_error: float, seed: int = 0):
    """Noise-free points of a pair turning 1 deg and moving 8 mm, the current frame's depths scaled
    by ``1 + scale_error``: the true T_ref,cur, the 3D-3D estimate and the points with covariances."""
    rng = np.random.default_rng(seed)
    cam = Camera.preset("fr3")
    uv = rng.uniform([40, 40], [600, 440], size=(300, 2))
    z = rng.uniform(1.0, 4.0, size=300)
    X_cur = cam.backproject(uv, z)
    T = gtsam.Pose3(gtsam.Rot3.Rodrigues(np.deg2rad([0.3, 0.9, 0.2])), np.array([0.004, -0.002, 0.007]))
    X_ref = X_cur @ T.rotation().matrix().T + T.translation()
    noise = OdometryConfig().noise_model()
    Q_ref = noise.point_covariances(cam, cam.project(X_ref), X_ref[:, 2])
    Q_cur = noise.point_covariances(cam, uv, z)
    X_cur = X_cur * (1.0 + scale_error)  # a depth scale error moves each point along its ray
    res = estimate_relative_pose(X_ref, X_cur, Q_ref, Q_cur)
    return T, res, X_ref, X_cur, Q_ref, Q_cur, cam


def _translation_error(T_est: gtsam.Pose3, T: gtsam.Pose3) -> float:
    return float(np.linalg.norm(gtsam.Pose3.Logmap(T_est.between(T))[3:]))


def test_drift_along_moves_the_3d3d_estimate_back_by_the_current_frames_depth_scale():
    """A 0.5 % depth scale error of the current frame moves the 3D-3D estimate by millimetres; the
    depth-free estimates do not see it, and their disagreement along ``b`` takes the estimate back
    to the true translation (the truth is the oracle)."""
    T, res, X_ref, X_cur, Q_ref, Q_cur, cam = _pair(0.005)
    M = res.pose.matrix()
    _, G_cur = transfer_gains(M[:3, :3], M[:3, 3], X_ref, X_cur, Q_ref, Q_cur)
    b = depth_scale_basis(G_cur, X_cur)
    check = depth_free_check(M, X_ref, X_cur, Q_ref, Q_cur, cam.fx, cam.fy, 1.0)
    v = drift_along(0.5 * (check.delta_forward + check.delta_backward), b, res.covariance)
    before = _translation_error(res.pose, T)
    after = _translation_error(res.pose.compose(gtsam.Pose3.Expmap(v)), T)
    assert before > 5e-3  # millimetres: the error is there to be removed
    assert after < 0.1 * before
    assert np.all(v[:3] == 0)  # the rotation is left alone
    # no depth error: nothing to move
    T, res, X_ref, X_cur, Q_ref, Q_cur, cam = _pair(0.0)
    M = res.pose.matrix()
    check = depth_free_check(M, X_ref, X_cur, Q_ref, Q_cur, cam.fx, cam.fy, 1.0)
    v = drift_along(0.5 * (check.delta_forward + check.delta_backward),
                    depth_scale_basis(transfer_gains(M[:3, :3], M[:3, 3], X_ref, X_cur, Q_ref, Q_cur)[1], X_cur),
                    res.covariance)
    assert np.linalg.norm(v) < 1e-4


def test_depth_drift_starts_from_the_second_vector_and_scales_with_the_intervals():
    drift = DepthDrift(4)
    step = np.array([0, 0, 0, 0.0, 0.0, 1e-3])
    drift.add(step)
    assert not np.any(drift.correction()[0])  # one vector has no spread to judge its mean by
    drift.add(3 * step)
    xi, C = drift.correction()  # the window not yet full: the mean so far, its spread / 2
    np.testing.assert_allclose(xi, 2 * step)
    np.testing.assert_allclose(C[5, 5], np.var([1e-3, 3e-3], ddof=1) / 2)
    xi3, C3 = drift.correction(3)  # over 3 intervals: 3 times the move, 9 times its covariance
    np.testing.assert_allclose(xi3, 3 * xi)
    np.testing.assert_allclose(C3, 9 * C)
    for _ in range(4):
        drift.add(2 * step, intervals=2)  # a pair over two intervals: per interval the same
    xi, C = drift.correction(3)  # the full window holds the last 4
    np.testing.assert_allclose(xi, 3 * step)
    np.testing.assert_allclose(C, 0.0, atol=1e-20)
    drift.clear()
    assert not np.any(drift.correction()[0])
    off = DepthDrift(0)
    off.add(step)
    assert not off.enabled and not np.any(off.correction()[0])


def test_depth_drift_covariance_is_the_spread_of_the_window_mean():
    """Monte Carlo: over many windows of independent vectors, the spread of the correction matches
    the covariance it reports (on average)."""
    rng = np.random.default_rng(1)
    n, windows = 10, 4000
    sd = np.array([0, 0, 0, 1e-3, 2e-3, 3e-3])
    means, reported = [], []
    for _ in range(windows):
        drift = DepthDrift(n)
        for v in rng.normal(size=(n, 6)) * sd:
            drift.add(v)
        xi, C = drift.correction()
        means.append(xi)
        reported.append(np.diag(C))
    np.testing.assert_allclose(np.var(means, axis=0)[3:], np.mean(reported, axis=0)[3:], rtol=0.1)


@pytest.mark.parametrize("held", [2, 3, 5])
def test_a_filling_windows_covariance_is_the_spread_of_its_mean(held):
    """The same for a window of 10 that holds only ``held`` vectors yet (a run's first pairs): the
    mean of fewer vectors spreads more, and the covariance reported says by as much."""
    rng = np.random.default_rng(2)
    sd = np.array([0, 0, 0, 1e-3, 2e-3, 3e-3])
    means, reported = [], []
    for _ in range(6000):
        drift = DepthDrift(10)
        for v in rng.normal(size=(held, 6)) * sd:
            drift.add(v)
        xi, C = drift.correction()
        means.append(xi)
        reported.append(np.diag(C))
    np.testing.assert_allclose(np.var(means, axis=0)[3:], sd[3:] ** 2 / held, rtol=0.1)
    np.testing.assert_allclose(np.mean(reported, axis=0)[3:], sd[3:] ** 2 / held, rtol=0.1)


@pytest.mark.slow
@pytest.mark.realdata
def test_the_drift_correction_shortens_fr1_rpys_chains(fr1_rpy_dir):
    """On frames 1-119 of fr1_rpy the 3D-3D estimates drift along the optical axis for tens of
    frames: with the correction the 30-pair chains' translation ANEES falls from about 10 to 3 and
    RPE30 from 0.032 to 0.027 m (default terms, fitted with the correction on frames 0-119)."""
    import tempfile

    from covo_gtsam.datasets.tum import TumSequence
    from covo_gtsam.evaluation import chain_nees, ground_truth_lookup, reference_covariances
    from covo_gtsam.pipeline import run_sequence

    seq = TumSequence(fr1_rpy_dir)
    lookup = ground_truth_lookup(seq)
    first_half = {t for t in seq.timestamps[:120]}
    out = {}
    for window in (0, 10):
        with tempfile.TemporaryDirectory() as tmp:
            run = run_sequence(seq, tmp, config=OdometryConfig().replace(sensor={"depth_drift_pairs": window}),
                               plots=False, progress=False)
        steps = [s for s in run.steps if s.timestamp in first_half]
        nees_rot, nees_tr = chain_nees(steps, lookup, jitter=reference_covariances(seq.gt_samples))
        out[window] = (float(np.mean(nees_tr)), run.metrics["rpe_30"]["trans_rmse"])
    assert out[10][0] < 4.0 < 6.0 < out[0][0]
    assert out[10][1] < out[0][1] - 0.003


def test_the_odometry_moves_the_translation_and_adds_the_estimates_covariance(sample_dir):
    """With and without the correction the runs agree on the first pair; the second, the first
    corrected (the window then holds two pairs' vectors), keeps its rotation, moves its
    translation, and its covariance grows in the translation block only (positive semidefinite,
    nonzero). The latency term's look-ahead is off:
    the next pair, solved from a moved prediction, would settle the two runs' latency terms apart."""
    from covo_gtsam.datasets.tum import TumSequence
    from covo_gtsam.odometry import VisualOdometry

    seq = TumSequence(sample_dir)
    frames = [(*seq.load(i), seq.timestamps[i], seq.depth_timestamps[i]) for i in range(16)]
    runs = {}
    for window in (0, 5):
        vo = VisualOdometry(seq.camera_name, OdometryConfig().replace(
            sensor={"depth_drift_pairs": window, "latency_look_ahead": False}))
        runs[window] = [vo.register_frame(c, d, t, depth_timestamp=dt) for c, d, t, dt in frames]
    off, on = runs[0], runs[5]
    tracked = [i for i, s in enumerate(off) if s.has_relative_pose]
    first = tracked[1]  # the second pair's vector makes two in the window
    for i in tracked[:1]:
        np.testing.assert_array_equal(on[i].relative.matrix(), off[i].relative.matrix())
        np.testing.assert_array_equal(on[i].covariance, off[i].covariance)
    a, b = on[first], off[first]
    np.testing.assert_allclose(a.relative.rotation().matrix(), b.relative.rotation().matrix(), atol=1e-12)
    assert np.linalg.norm(a.relative.translation() - b.relative.translation()) > 1e-6
    D = a.covariance - b.covariance
    np.testing.assert_allclose(D[:3, :], 0.0, atol=1e-18)
    assert np.linalg.eigvalsh(D[3:, 3:]).min() > -1e-15 and np.trace(D[3:, 3:]) > 0
    # keyframe mode has no correction: the same poses with and without
    poses = []
    for window in (0, 5):
        vo = VisualOdometry(seq.camera_name, OdometryConfig().replace(tracking={"keyframes": True},
                                                                      sensor={"depth_drift_pairs": window}))
        poses.append([vo.register_frame(c, d, t, depth_timestamp=dt).pose.matrix() for c, d, t, dt in frames])
    np.testing.assert_array_equal(poses[0], poses[1])
