"""benchmarks/peers.py scores only frames with valid ground truth."""

from __future__ import annotations

import importlib.util
import sys

import gtsam
import numpy as np
import pytest

from covo_gtsam.metrics import rpe
from tests.conftest import REPO

pytest.importorskip("cv2")


def _peers():
    sys.path.insert(0, str(REPO / "benchmarks"))
    try:
        spec = importlib.util.spec_from_file_location("peers", REPO / "benchmarks" / "peers.py")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
    finally:
        sys.path.remove(str(REPO / "benchmarks"))
    return mod


def test_frames_without_ground_truth_are_not_scored(random_trajectory):
    peers = _peers()
    _, gt = random_trajectory(n=40, seed=4, step_sigma=0.05)
    rng = np.random.default_rng(0)
    est = [gt[0]]
    for i in range(1, 40):  # an estimate with small per-step errors
        step_error = gtsam.Pose3.Expmap(rng.normal(scale=1e-3, size=6)).matrix()
        est.append(est[-1] @ np.linalg.inv(gt[i - 1]) @ gt[i] @ step_error)
    est = np.array(est)
    valid = np.ones(40, bool)
    valid[:6] = False  # motion capture starts after the first frames ...
    valid[20] = False  # ... and has one gap
    gt_seen = gt.copy()
    gt_seen[~valid] = np.eye(4)  # what interpolate_poses leaves there
    got = peers.valid_rpe(gt_seen, valid, est, 1)
    want_t = np.concatenate([peers.relative_pose_errors(gt[a:b], est[a:b], 1)[0] for a, b in ((6, 20), (21, 40))])
    assert got["n"] == len(want_t) == 13 + 18
    assert got["trans_rmse"] == pytest.approx(np.sqrt(np.mean(want_t**2)), rel=1e-12)
    assert got["trans_rmse"] < 5e-3
    # scoring the placeholders too (the old way) is nonsense
    assert rpe(gt_seen, est, 1)["trans_rmse"] > 10 * got["trans_rmse"]
    assert peers.valid_rpe(gt_seen, valid, est, 30) is None
