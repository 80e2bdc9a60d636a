"""The cross-validation study's independent estimator (OpenCV's dense RGB-D odometry) reads its
pose in the direction covo reports, T_ref,cur: pinned against the ground truth of real frames."""

from __future__ import annotations

import importlib.util
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from covo_gtsam.datasets.tum import TumSequence
from covo_gtsam.evaluation import ground_truth_lookup
from covo_gtsam.geometry import invert_pose
from covo_gtsam.metrics import relative_pose_tangent_errors
from tests.conftest import REPO

cv2 = pytest.importorskip("cv2")
if not hasattr(cv2, "Odometry"):
    pytest.skip("this OpenCV has no cv2.Odometry (OpenCV 5's RGB-D odometry)", allow_module_level=True)


def _study():
    spec = importlib.util.spec_from_file_location("cross_validation", REPO / "studies" / "cross_validation.py")
    mod = importlib.util.module_from_spec(spec)
    path = list(sys.path)
    try:
        spec.loader.exec_module(mod)
    finally:
        sys.path[:] = path
    return mod


@pytest.mark.realdata
def test_opencv_pairs_are_T_ref_cur(fr1_desk_dir):
    seq = TumSequence(fr1_desk_dir)
    lookup = ground_truth_lookup(seq)
    pairs = _study().opencv_pairs(seq, lookup)
    assert len(pairs) >= 6
    ends = sorted(pairs)
    true = np.array([invert_pose(lookup[seq.timestamps[k - 1]]) @ lookup[seq.timestamps[k]] for k in ends])
    est = np.array([pairs[k] for k in ends])
    err = relative_pose_tangent_errors(est, true)
    flipped = relative_pose_tangent_errors(np.array([invert_pose(T) for T in est]), true)
    # the frames move 1-3 cm and 1-3 deg apart; the estimate is within a few mm and tenths of a degree
    assert np.degrees(np.abs(err[:, :3])).max() < 1.0 and np.abs(err[:, 3:]).max() < 0.01
    assert np.linalg.norm(flipped, axis=1).mean() > 3 * np.linalg.norm(err, axis=1).mean()


def test_persistence_ratios_count_only_chains_of_consecutive_pairs():
    study = _study()
    rng = np.random.default_rng(3)
    n, w = 40, 5
    true = np.array([np.eye(4) for _ in range(n)])
    for T in true:
        T[:3, 3] = rng.normal(scale=0.01, size=3)
    est = true.copy()
    est[:, 0, 3] += 1e-3  # one error repeated in every pair: a chain's error is w times a pair's
    ends = np.arange(1, n + 1)
    assert study.persistence(est, true, ends, w)[0] == pytest.approx(w, rel=1e-6)  # translation
    turned = true.copy()
    turned[:, :3, :3] = Rotation.from_rotvec([0.0, 0.0, 1e-3]).as_matrix()  # the same rotation error each pair
    assert study.persistence(turned, true, ends, w)[1] == pytest.approx(w, rel=1e-6)
    errors = np.tile([1e-3, 0.0, 0.0], (n, 1))
    assert study.persistence_of_sums(errors, ends, w) == pytest.approx(w)
    alternating = errors * np.where(np.arange(n) % 2, 1.0, -1.0)[:, None]  # each pair undoes the last
    assert study.persistence_of_sums(alternating, ends, w) == pytest.approx(1 / w)
    # a gap in the end frames: no window across it
    gapped = np.concatenate([np.arange(1, 4), np.arange(10, 10 + n - 3)])
    assert len(study._windows(gapped, w)) == n - 3 - w + 1
    assert np.isnan(study.persistence(est[:w + 1], true[:w + 1], gapped[:w + 1] * 3, w)).all()
