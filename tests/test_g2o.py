"""graph.g2o: GTSAM's own reader is the oracle for poses, ordering and information matrices."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from covo_gtsam.datasets.tum import TumSequence
from covo_gtsam.errors import InputError
from covo_gtsam.g2o import format_edge
from covo_gtsam.io import load_relative_poses, load_tum_trajectory
from covo_gtsam.odometry import OdometryConfig
from covo_gtsam.pipeline import run_sequence


@pytest.mark.parametrize("keyframes", [False, True])
def test_read_g2o_gives_back_trajectory_and_relative_covariances(sample_dir, tmp_path, keyframes):
    seq = TumSequence(sample_dir)
    cfg = OdometryConfig().replace(tracking={"keyframes": keyframes})
    res = run_sequence(seq, tmp_path, config=cfg, max_frames=15, plots=False, progress=False)
    graph, values = gtsam.readG2o(str(tmp_path / "graph.g2o"), True)
    stamps, poses = load_tum_trajectory(tmp_path / "trajectory.txt")
    t_ref, t_cur, rel, covs = load_relative_poses(tmp_path / "relative.txt")
    index = {float(t): i for i, t in enumerate(seq.timestamps)}
    tracked = [i for i, s in enumerate(res.steps) if s.tracked]
    assert sorted(values.keys()) == tracked and len(tracked) == len(stamps) >= 10
    for t, P in zip(stamps, poses):  # vertices: T_world,cam of trajectory.txt (written there at 1e-9)
        np.testing.assert_allclose(values.atPose3(index[round(t, 6)]).matrix(), P, atol=2e-9)
    assert graph.size() == len(t_cur) >= 9
    for k in range(graph.size()):
        f = graph.at(k)
        i_ref, i_cur = f.keys()
        assert (i_ref, i_cur) == (index[round(t_ref[k], 6)], index[round(t_cur[k], 6)])
        np.testing.assert_allclose(f.measured().matrix(), rel[k], atol=2e-9)
        R = f.noiseModel().R()
        cov = np.linalg.inv(R.T @ R)
        # relative.txt keeps 10 significant digits; graph.g2o is exact
        np.testing.assert_allclose(cov, covs[k], rtol=1e-9, atol=1e-9 * np.abs(covs[k]).max())
    if keyframes:
        assert any(b - a > 1 for a, b in (f.keys() for f in (graph.at(k) for k in range(graph.size()))))


def test_g2o_edge_ordering_is_translation_first(tmp_path):
    """A covariance with distinct rotation and translation blocks and a cross term survives GTSAM's
    reader: the file's information is [x y z rx ry rz] and GTSAM swaps it back."""
    rng = np.random.default_rng(3)
    A = rng.normal(size=(6, 6)) * np.array([1e-3] * 3 + [1e-2] * 3)
    cov = A @ A.T + np.diag([1e-6] * 3 + [1e-4] * 3)
    T = gtsam.Pose3(gtsam.Rot3.RzRyRx(0.1, -0.3, 0.2), np.array([0.3, -0.1, 0.05]))
    path = tmp_path / "g.g2o"
    path.write_text("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 0 0 0 0 0 0 1\n"
                    + format_edge(0, 1, T.matrix(), cov))
    graph, _ = gtsam.readG2o(str(path), True)
    R = graph.at(0).noiseModel().R()
    np.testing.assert_allclose(np.linalg.inv(R.T @ R), cov, rtol=1e-9)
    assert graph.at(0).measured().equals(T, 1e-12)
    # the translation block leads the written information: its first value is Info_gtsam[3, 3]
    first = float(format_edge(0, 1, T.matrix(), cov).split()[10])
    assert first == pytest.approx(np.linalg.inv(cov)[3, 3], rel=1e-12)


def test_g2o_rejects_bad_covariance():
    with pytest.raises(InputError):
        format_edge(0, 1, np.eye(4), np.zeros((6, 6)))
    with pytest.raises(InputError):
        format_edge(0, 1, np.eye(4), np.eye(3))
