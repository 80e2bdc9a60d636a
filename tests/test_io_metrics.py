"""TUM reader, trajectory / relative-pose files, and RPE / ATE / NEES cross-checked against evo."""

from __future__ import annotations

import shutil

import gtsam
import numpy as np
import pytest

from covo_gtsam.datasets.tum import TumSequence, associate, interpolate_poses
from covo_gtsam.errors import DatasetError
from covo_gtsam.geometry import invert_pose, make_pose, quat_to_matrix
from covo_gtsam.io import load_relative_poses, load_tum_trajectory, write_tum_trajectory, RelativePoseWriter
from covo_gtsam.metrics import ate, chi2_quantile, nees, relative_pose_nees, rpe, se3_log, umeyama_alignment


def random_trajectory(n=80, seed=0):
    rng = np.random.default_rng(seed)
    poses = [np.eye(4)]
    for _ in range(n - 1):
        step = gtsam.Pose3.Expmap(rng.normal(scale=[0.02, 0.02, 0.02, 0.03, 0.03, 0.03]))
        poses.append(poses[-1] @ step.matrix())
    return np.arange(n) * 0.033 + 1000.0, np.array(poses)


def perturb(poses, seed=1, scale=0.01):
    rng = np.random.default_rng(seed)
    return np.array([P @ gtsam.Pose3.Expmap(rng.normal(scale=scale, size=6)).matrix() for P in poses])


def test_associate_one_to_one_with_cut():
    rgb = np.array([0.0, 0.033, 0.066, 0.2])
    depth = np.array([0.001, 0.030, 0.036, 0.5])
    pairs = associate(rgb, depth, 0.02)
    assert pairs == [(0, 0), (1, 2), (2, 1)] or pairs == [(0, 0), (1, 2)]
    assert all(abs(rgb[i] - depth[j]) <= 0.02 for i, j in pairs)
    assert len({j for _, j in pairs}) == len(pairs)
    assert (3, 3) not in pairs


def test_interpolation_exact_and_midpoint():
    R0, R1 = np.eye(3), gtsam.Rot3.Expmap(np.array([0.0, 0.0, 0.4])).matrix()
    P = np.array([make_pose(R0, [0, 0, 0]), make_pose(R1, [1.0, 2.0, 0.0])])
    out, ok = interpolate_poses(np.array([0.0, 0.05]), P, np.array([0.0, 0.025, 0.05, 0.2]))
    assert ok.tolist() == [True, True, True, False]
    np.testing.assert_allclose(out[0], P[0], atol=1e-12)
    np.testing.assert_allclose(out[2], P[1], atol=1e-12)
    np.testing.assert_allclose(out[1][:3, 3], [0.5, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(out[1][:3, :3], gtsam.Rot3.Expmap(np.array([0, 0, 0.2])).matrix(), atol=1e-12)


def test_sample_sequence(sample_dir):
    seq = TumSequence(sample_dir)
    assert len(seq) == 40 and seq.camera_name == "fr1" and seq.gt_valid.all()


def test_shared_sequences(fr1_rpy_dir, fr1_desk_dir):
    assert 235 <= len(TumSequence(fr1_rpy_dir)) <= 240
    desk = TumSequence(fr1_desk_dir)
    assert len(desk) == 9 and desk.groundtruth is not None and desk.gt_valid.all()


def test_dataset_errors(tmp_path, sample_dir):
    with pytest.raises(DatasetError, match="does not exist"):
        TumSequence(tmp_path / "nope")
    with pytest.raises(DatasetError, match="rgb.txt"):
        TumSequence(tmp_path)
    seq = tmp_path / "rgbd_dataset_freiburg1_x"
    shutil.copytree(sample_dir, seq)
    lines = (seq / "rgb.txt").read_text().splitlines()
    (seq / "rgb.txt").write_text("\n".join(lines + ["1305031231.000000 rgb/missing.png"]) + "\n")
    (seq / "depth.txt").write_text((seq / "depth.txt").read_text() + "1305031231.000010 depth/x.png\n")
    with pytest.raises(DatasetError, match="missing.png"):
        TumSequence(seq)
    (seq / "rgb.txt").write_text("\n".join(lines + ["garbage"]) + "\n")
    with pytest.raises(DatasetError, match="rgb.txt:44"):
        TumSequence(seq)


def test_trajectory_and_relative_round_trip(tmp_path):
    stamps, poses = random_trajectory(20)
    write_tum_trajectory(tmp_path / "t.txt", stamps, poses)
    s2, p2 = load_tum_trajectory(tmp_path / "t.txt")
    np.testing.assert_allclose(s2, stamps, atol=1e-6)
    np.testing.assert_allclose(p2, poses, atol=1e-8)
    from evo.tools import file_interface

    traj = file_interface.read_tum_trajectory_file(str(tmp_path / "t.txt"))
    np.testing.assert_allclose(np.array(traj.poses_se3), poses, atol=1e-8)

    rng = np.random.default_rng(0)
    covs = np.array([(lambda A: A @ A.T)(rng.normal(size=(6, 6))) for _ in range(19)])
    rel = invert_pose(poses[:-1]) @ poses[1:]
    with RelativePoseWriter(tmp_path / "r.txt") as w:
        for i in range(19):
            w.write(stamps[i], stamps[i + 1], rel[i], covs[i])
    a, b, P, C = load_relative_poses(tmp_path / "r.txt")
    np.testing.assert_allclose(a, stamps[:-1], atol=1e-6)
    np.testing.assert_allclose(P, rel, atol=1e-8)
    np.testing.assert_allclose(C, covs, rtol=1e-8)


def _evo(poses_gt, poses_est, stamps):
    from evo.core import metrics, sync
    from evo.core.trajectory import PoseTrajectory3D

    ref = PoseTrajectory3D(poses_se3=list(poses_gt), timestamps=stamps)
    est = PoseTrajectory3D(poses_se3=list(poses_est), timestamps=stamps)
    out = {}
    # all_pairs=True: every (i, i + delta), as the TUM benchmark and thesis (5.2) define the RPE;
    # evo's all_pairs=False takes non-overlapping pairs (0, d), (d, 2d), ...
    for delta in (1, 30):
        m = metrics.RPE(metrics.PoseRelation.translation_part, delta, metrics.Unit.frames, all_pairs=True)
        m.process_data((ref, est))
        out[f"rpe{delta}"] = m.get_statistic(metrics.StatisticsType.rmse)
        m = metrics.RPE(metrics.PoseRelation.rotation_angle_deg, delta, metrics.Unit.frames, all_pairs=True)
        m.process_data((ref, est))
        out[f"rot{delta}"] = m.get_statistic(metrics.StatisticsType.rmse)
    est.align(ref, correct_scale=False)
    m = metrics.APE(metrics.PoseRelation.translation_part)
    m.process_data((ref, est))
    out["ate"] = m.get_statistic(metrics.StatisticsType.rmse)
    return out


def _check_against_evo(gt, est, stamps):
    ev = _evo(gt, est, stamps)
    for delta in (1, 30):
        r = rpe(gt, est, delta)
        assert r["trans_rmse"] == pytest.approx(ev[f"rpe{delta}"], rel=1e-6)
        assert r["rot_rmse_deg"] == pytest.approx(ev[f"rot{delta}"], rel=1e-5)
    assert ate(gt, est)["rmse"] == pytest.approx(ev["ate"], rel=1e-6)


def test_rpe_ate_against_evo_synthetic():
    stamps, gt = random_trajectory(90)
    _check_against_evo(gt, perturb(gt), stamps)


def test_rpe_ate_against_evo_real_groundtruth(fr1_rpy_dir):
    seq = TumSequence(fr1_rpy_dir)
    gt = seq.groundtruth[seq.gt_valid]
    _check_against_evo(gt, perturb(gt, scale=0.005), seq.timestamps[seq.gt_valid])


def test_umeyama_recovers_transform():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(50, 3))
    R = gtsam.Rot3.Expmap(np.array([0.2, -0.4, 0.9])).matrix()
    dst = 1.5 * src @ R.T + [1, 2, 3]
    R2, t2, s2 = umeyama_alignment(src, dst, with_scale=True)
    np.testing.assert_allclose(R2, R, atol=1e-10)
    np.testing.assert_allclose(t2, [1, 2, 3], atol=1e-10)
    assert s2 == pytest.approx(1.5)


def test_nees_and_chi2():
    assert nees(np.array([[1.0, 2.0]]), np.array([np.diag([1.0, 4.0])]))[0] == pytest.approx(2.0)
    from scipy.stats import chi2

    for p in (0.025, 0.5, 0.975, 0.999):
        for dof in (1, 3, 6):
            assert chi2_quantile(p, dof) == pytest.approx(chi2.ppf(p, dof), rel=1e-6)
    assert chi2_quantile(0.975, 3) == pytest.approx(9.348, abs=1e-3)


def test_se3_log_and_relative_nees_match_gtsam():
    rng = np.random.default_rng(0)
    Ts = [gtsam.Pose3.Expmap(rng.normal(scale=s, size=6)) for s in (1e-9, 0.01, 0.5, 1.0)]
    np.testing.assert_allclose(se3_log(np.array([T.matrix() for T in Ts])),
                               np.array([gtsam.Pose3.Logmap(T) for T in Ts]), atol=1e-9)
    T_est = np.array([T.matrix() for T in Ts])
    T_true = np.array([(T.compose(gtsam.Pose3.Expmap(rng.normal(scale=0.01, size=6)))).matrix() for T in Ts])
    cov = np.tile(np.diag([1e-4] * 3 + [4e-4] * 3), (4, 1, 1))
    nr, nt = relative_pose_nees(T_est, T_true, cov)
    for i in range(4):
        xi = gtsam.Pose3.Logmap(gtsam.Pose3(T_est[i]).between(gtsam.Pose3(T_true[i])))
        assert nr[i] == pytest.approx(xi[:3] @ xi[:3] / 1e-4, rel=1e-7)
        assert nt[i] == pytest.approx(xi[3:] @ xi[3:] / 4e-4, rel=1e-7)
