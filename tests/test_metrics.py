"""RPE / ATE cross-checked against evo, Umeyama, NEES, chi-square without scipy, relative-pose NEES vs GTSAM."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from covo_gtsam.datasets.tum import TumSequence
from covo_gtsam.errors import InputError
from covo_gtsam.geometry import invert_pose, make_pose
from covo_gtsam.metrics import (
    anees,
    ate,
    chi2_cdf,
    chi2_pdf,
    chi2_quantile,
    nees,
    relative_pose_errors,
    relative_pose_nees,
    rpe,
    se3_log,
    umeyama_alignment,
)

#: random-walk step of the synthetic trajectories (rad, m)
STEP = [0.02, 0.02, 0.02, 0.03, 0.03, 0.03]


def perturb(poses, seed=1, scale=0.01):
    """Noisy copy: independent right perturbations plus a rigid offset of the whole trajectory."""
    rng = np.random.default_rng(seed)
    offset = gtsam.Pose3.Expmap(np.array([0.3, -0.2, 0.5, 1.0, -2.0, 0.5])).matrix()
    return np.array([offset @ P @ gtsam.Pose3.Expmap(rng.normal(scale=scale, size=6)).matrix() for P in poses])


def evo_metrics(poses_gt, poses_est, stamps, deltas=(1, 30)):
    from evo.core import metrics
    from evo.core.trajectory import PoseTrajectory3D

    ref = PoseTrajectory3D(poses_se3=list(poses_gt), timestamps=stamps)
    est = PoseTrajectory3D(poses_se3=list(poses_est), timestamps=stamps)
    out = {}
    for delta in deltas:
        for all_pairs in (False, True):
            for name, rel in (("t", metrics.PoseRelation.translation_part),
                              ("r", metrics.PoseRelation.rotation_angle_deg)):
                m = metrics.RPE(rel, delta, metrics.Unit.frames, all_pairs=all_pairs)
                m.process_data((ref, est))
                out[name, delta, all_pairs] = m.get_statistic(metrics.StatisticsType.rmse)
    est.align(ref, correct_scale=False)
    m = metrics.APE(metrics.PoseRelation.translation_part)
    m.process_data((ref, est))
    out["ate"] = {k: m.get_statistic(getattr(metrics.StatisticsType, k)) for k in ("rmse", "mean", "median", "max")}
    return out


def check_against_evo(gt, est, stamps):
    ev = evo_metrics(gt, est, stamps)
    for delta in (1, 30):
        tr, rot = relative_pose_errors(gt, est, delta)
        # evo's all_pairs=False uses the non-overlapping pairs (0, d), (d, 2d), ...: every delta-th error
        assert np.sqrt(np.mean(tr[::delta] ** 2)) == pytest.approx(ev["t", delta, False], rel=1e-6, abs=1e-12)
        assert np.rad2deg(np.sqrt(np.mean(rot[::delta] ** 2))) == pytest.approx(ev["r", delta, False], rel=1e-6)
        # the TUM benchmark's RPE (what rpe() reports) uses every pair (i, i + delta): evo's all_pairs=True
        r = rpe(gt, est, delta)
        assert r["n"] == len(gt) - delta
        assert r["trans_rmse"] == pytest.approx(ev["t", delta, True], rel=1e-6, abs=1e-12)
        assert r["rot_rmse_deg"] == pytest.approx(ev["r", delta, True], rel=1e-6)
    a = ate(gt, est)
    for k in ("rmse", "mean", "median", "max"):
        assert a[k] == pytest.approx(ev["ate"][k], rel=1e-6, abs=1e-12)
    assert a["n"] == len(gt)


def test_rpe_ate_against_evo_synthetic(random_trajectory):
    stamps, gt = random_trajectory(90, step_sigma=STEP, t0=1000.0)
    check_against_evo(gt, perturb(gt), stamps)


@pytest.mark.realdata
def test_rpe_ate_against_evo_fr1_rpy_groundtruth(fr1_rpy_dir):
    seq = TumSequence(fr1_rpy_dir)
    gt = seq.groundtruth[seq.gt_valid]
    check_against_evo(gt, perturb(gt, scale=0.005), seq.timestamps[seq.gt_valid])


def test_rpe_hand_example_and_zero_cases(random_trajectory):
    gt = np.array([make_pose(np.eye(3), [x, 0, 0]) for x in (0.0, 1.0, 2.0)])
    est = gt.copy()
    est[2, :3, 3] = [2.0, 0.3, 0.4]  # second step off by 0.5 m
    tr, rot = relative_pose_errors(gt, est, 1)
    np.testing.assert_allclose(tr, [0.0, 0.5], atol=1e-15)
    np.testing.assert_allclose(rot, [0.0, 0.0], atol=1e-7)
    r = rpe(gt, est, 1)
    assert r["trans_rmse"] == pytest.approx(np.sqrt(0.125)) and r["trans_median"] == pytest.approx(0.25)
    # a rigidly moved copy has zero RPE and zero ATE
    stamps, P = random_trajectory(30, step_sigma=STEP, t0=1000.0)
    X = gtsam.Pose3.Expmap(np.array([1.0, 2.0, -0.5, 3.0, 4.0, 5.0])).matrix()
    assert rpe(P, X @ P, 5)["trans_rmse"] < 1e-9
    assert ate(P, X @ P)["rmse"] < 1e-9
    with pytest.raises(InputError):
        rpe(P, P, 30)
    with pytest.raises(InputError):
        rpe(P, P[:-1], 1)


def test_umeyama_recovers_known_transform():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(50, 3))
    R = gtsam.Rot3.Expmap(np.array([0.2, -0.4, 2.9])).matrix()
    t = np.array([1.0, 2.0, 3.0])
    for s_true, with_scale in ((1.0, False), (1.5, True)):
        dst = s_true * src @ R.T + t
        R2, t2, s2 = umeyama_alignment(src, dst, with_scale=with_scale)
        np.testing.assert_allclose(R2, R, atol=1e-10)
        np.testing.assert_allclose(t2, t, atol=1e-10)
        assert s2 == pytest.approx(s_true, rel=1e-12)
        assert np.linalg.det(R2) == pytest.approx(1.0)
    # a reflection is not returned: planar points mirrored through z
    flat = src * [1, 1, 0]
    R3, _, _ = umeyama_alignment(flat, flat * [1, 1, -1])
    assert np.linalg.det(R3) == pytest.approx(1.0)


def test_nees_hand_example():
    err = np.array([[1.0, 2.0], [3.0, 0.0]])
    cov = np.array([np.diag([1.0, 4.0]), [[2.0, 1.0], [1.0, 2.0]]])
    # second: inv([[2,1],[1,2]]) = [[2,-1],[-1,2]]/3 -> 9*2/3 = 6
    np.testing.assert_allclose(nees(err, cov), [2.0, 6.0])
    assert anees(nees(err, cov)) == pytest.approx(4.0)
    with pytest.raises(InputError):
        nees(err, cov[:, :1, :1])


def test_chi2_against_scipy():
    from scipy.stats import chi2

    assert chi2_quantile(0.975, 3) == pytest.approx(9.348, abs=1e-3)
    for p in (1e-6, 0.001, 0.025, 0.05, 0.5, 0.95, 0.975, 0.995, 0.999, 1 - 1e-7):
        for dof in (1, 2, 3, 6, 12, 30, 100):
            assert chi2_quantile(p, dof) == pytest.approx(chi2.ppf(p, dof), rel=1e-4), (p, dof)
            assert chi2_quantile(p, dof) == pytest.approx(chi2.ppf(p, dof), rel=1e-9), (p, dof)
    for x in (0.01, 0.5, 3.0, 9.35, 40.0):
        for dof in (1, 3, 6):
            assert chi2_cdf(x, dof) == pytest.approx(chi2.cdf(x, dof), rel=1e-10)
    x = np.linspace(0.01, 30, 50)
    for dof in (1, 2, 3, 6):
        np.testing.assert_allclose(chi2_pdf(x, dof), chi2.pdf(x, dof), rtol=1e-10)
    assert chi2_pdf(-1.0, 3) == 0.0 and chi2_pdf(0.0, 2) == 0.5
    for bad in (0.0, 1.0, -0.1):
        with pytest.raises(ValueError):
            chi2_quantile(bad, 3)


def test_se3_log_matches_gtsam():
    rng = np.random.default_rng(0)
    Ts = [gtsam.Pose3.Expmap(rng.normal(scale=s, size=6)) for s in (0.0, 1e-9, 1e-6, 1e-3, 0.01, 0.1, 0.5, 1.0, 1.5)]
    axis = np.array([0.6, 0.0, 0.8])
    Ts.append(gtsam.Pose3(gtsam.Rot3.Expmap(axis * (np.pi - 1e-6)), np.array([1.0, 2.0, 3.0])))
    xi = se3_log(np.array([T.matrix() for T in Ts]))
    np.testing.assert_allclose(xi[:-1], np.array([gtsam.Pose3.Logmap(T) for T in Ts[:-1]]), atol=1e-12)
    np.testing.assert_allclose(xi[-1][:3], gtsam.Rot3.Logmap(Ts[-1].rotation()), atol=1e-9)
    for x, T in zip(xi, Ts):  # Exp(Log(T)) = T everywhere, also close to pi
        np.testing.assert_allclose(gtsam.Pose3.Expmap(x).matrix(), T.matrix(), atol=1e-9)


def test_relative_pose_nees_matches_direct_gtsam():
    rng = np.random.default_rng(4)
    n = 12
    T_est = [gtsam.Pose3.Expmap(rng.normal(scale=0.5, size=6)) for _ in range(n)]
    T_true = [T.compose(gtsam.Pose3.Expmap(rng.normal(scale=[0.01] * 3 + [0.02] * 3))) for T in T_est]
    A = rng.normal(size=(n, 6, 6)) * 0.01
    cov = A @ np.swapaxes(A, 1, 2) + np.diag([1e-4] * 3 + [4e-4] * 3)
    nr, nt = relative_pose_nees(np.array([T.matrix() for T in T_est]), np.array([T.matrix() for T in T_true]), cov)
    for i in range(n):
        xi = gtsam.Pose3.Logmap(T_est[i].between(T_true[i]))  # T_true = T_est * Exp(xi)
        assert nr[i] == pytest.approx(xi[:3] @ np.linalg.solve(cov[i][:3, :3], xi[:3]), rel=1e-8)
        assert nt[i] == pytest.approx(xi[3:] @ np.linalg.solve(cov[i][3:, 3:], xi[3:]), rel=1e-8)


def test_relative_pose_nees_is_chi2_when_consistent():
    """Errors drawn from the stated covariance (right perturbation) give ANEES ~ 3 per block."""
    rng = np.random.default_rng(7)
    n = 4000
    cov = np.diag([1e-4, 2e-4, 3e-4, 1e-3, 2e-3, 4e-3])
    xi = rng.multivariate_normal(np.zeros(6), cov, size=n)
    T_est = np.array([gtsam.Pose3.Expmap(rng.normal(size=6)).matrix() for _ in range(n)])
    T_true = T_est @ np.array([gtsam.Pose3.Expmap(x).matrix() for x in xi])
    nr, nt = relative_pose_nees(T_est, T_true, np.tile(cov, (n, 1, 1)))
    assert anees(nr) == pytest.approx(3.0, abs=0.15) and anees(nt) == pytest.approx(3.0, abs=0.15)
    np.testing.assert_allclose(invert_pose(T_est[:3]) @ T_est[:3], np.tile(np.eye(4), (3, 1, 1)), atol=1e-12)


# -- run evaluation across restarts -----------------------------------------------------------

def _steps_with_restart(gt: np.ndarray, stamps: np.ndarray, restart_at: int):
    """Steps whose poses equal the ground truth inside each segment; the restart frame keeps the
    last tracked pose (as the odometry does), so the estimate jumps by the unknown gap motion."""
    from types import SimpleNamespace

    from covo_gtsam.odometry import OdometryStep

    steps, offset = [], np.eye(4)
    for i, (t, g) in enumerate(zip(stamps, gt)):
        if i == restart_at:
            offset = steps[-1].pose.matrix() @ np.linalg.inv(g)
            status = "restart"
        else:
            status = "first" if i == 0 else "tracked"
        steps.append(OdometryStep(float(t), status, pose=gtsam.Pose3(offset @ g)))
    seq = SimpleNamespace(name="synthetic", timestamps=stamps, groundtruth=gt, gt_valid=np.ones(len(gt), bool))
    return steps, seq


def test_run_metrics_do_not_span_a_restart(random_trajectory):
    from covo_gtsam.evaluation import evaluate_run

    stamps, gt = random_trajectory(n=60, seed=3)
    steps, seq = _steps_with_restart(gt, stamps, restart_at=20)
    m = evaluate_run(steps, seq, 1.0)
    assert m.segments == 2
    # exact inside each segment: no pair crosses the gap, each segment is aligned on its own
    assert m.rpe[1]["trans_rmse"] < 1e-9 and m.rpe[1]["n"] == 19 + 39
    assert m.rpe[30]["trans_rmse"] < 1e-9 and m.rpe[30]["n"] == 10  # only the 40-frame segment
    assert m.ate["rmse"] < 1e-9 and m.ate["n"] == 60
    # the same poses read as one segment do show the jump (the check above can fail)
    from covo_gtsam.metrics import rpe

    assert rpe(gt, np.array([s.pose.matrix() for s in steps]), 1)["trans_rmse"] > 1e-3


def test_run_metrics_say_none_when_no_pair_is_far_enough_apart(random_trajectory):
    from covo_gtsam.evaluation import evaluate_run

    stamps, gt = random_trajectory(n=25, seed=4)
    steps, seq = _steps_with_restart(gt, stamps, restart_at=10)
    m = evaluate_run(steps, seq, 1.0)
    assert m.rpe[30] is None and m.rpe[1]["n"] == 9 + 14
    assert m.rpe_errors[30][0].size == 0 and "rpe_30" in m.not_computed
