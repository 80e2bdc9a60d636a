"""Quaternion order and conversions against GTSAM and evo (independent readers and writers)."""

import gtsam
import numpy as np
import pytest

from covo_gtsam.datasets.tum import interpolate_poses
from covo_gtsam.geometry import adjoint, make_pose, matrix_to_quat, pose_to_tum, quat_to_matrix
from covo_gtsam.io import load_tum_trajectory, write_tum_trajectory

#: 120 deg about (1, 2, 3)/|.|: every quaternion component differs, so any swap of order shows
AXIS = np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)
ROT = gtsam.Rot3.AxisAngle(AXIS, np.deg2rad(120.0))
XYZW = np.array([*(np.sin(np.deg2rad(60.0)) * AXIS), np.cos(np.deg2rad(60.0))])


def _rotations(n=300, seed=0):
    rng = np.random.default_rng(seed)
    scales = np.repeat([1e-9, 1e-3, 0.5, 2.0, 3.1], n // 5)
    return np.array([gtsam.Rot3.Expmap(rng.normal(size=3) * s).matrix() for s in scales])


def test_quaternion_order_is_x_y_z_w():
    np.testing.assert_allclose(matrix_to_quat(ROT.matrix()), XYZW, atol=1e-15)
    np.testing.assert_allclose(quat_to_matrix(XYZW), ROT.matrix(), atol=1e-15)
    q = ROT.toQuaternion()  # gtsam (Eigen) quaternion, scalar w separate
    np.testing.assert_allclose(XYZW, [q.x(), q.y(), q.z(), q.w()], atol=1e-15)


def test_conversions_agree_with_gtsam():
    R = _rotations()
    q = matrix_to_quat(R)
    assert np.all(q[:, 3] >= 0)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-15)
    ref = np.array([gtsam.Rot3(m).toQuaternion().coeffs() for m in R])  # Eigen coeffs: x y z w
    ref *= np.where(ref[:, 3:] < 0, -1.0, 1.0)
    np.testing.assert_allclose(q, ref, atol=4e-16)
    np.testing.assert_allclose(quat_to_matrix(q), R, atol=1e-15)
    # not normalised on input: scaled quaternions give the same rotation
    np.testing.assert_allclose(quat_to_matrix(2.5 * q[:5]), R[:5], atol=1e-15)
    assert quat_to_matrix(q.reshape(3, -1, 4)).shape == (3, len(q) // 3, 3, 3)
    assert matrix_to_quat(R[0]).shape == (4,)


def test_evo_reads_the_order_we_write(tmp_path):
    from evo.tools import file_interface

    T = make_pose(ROT.matrix(), np.array([0.1, -0.2, 0.3]))
    write_tum_trajectory(tmp_path / "t.txt", np.array([1.5]), T[None])
    line = next(ln for ln in (tmp_path / "t.txt").read_text().splitlines() if not ln.startswith("#"))
    np.testing.assert_allclose([float(v) for v in line.split()[4:]], XYZW, atol=1e-9)
    traj = file_interface.read_tum_trajectory_file(str(tmp_path / "t.txt"))
    np.testing.assert_allclose(traj.orientations_quat_wxyz[0], XYZW[[3, 0, 1, 2]], atol=1e-9)
    np.testing.assert_allclose(traj.poses_se3[0], T, atol=1e-9)


def test_we_read_the_order_evo_writes(tmp_path):
    from evo.core.trajectory import PoseTrajectory3D
    from evo.tools import file_interface

    R = _rotations(20, seed=3)
    poses = make_pose(R, np.arange(60.0).reshape(20, 3))
    traj = PoseTrajectory3D(poses_se3=list(poses), timestamps=np.arange(20.0))
    file_interface.write_tum_trajectory_file(str(tmp_path / "e.txt"), traj)
    _, read = load_tum_trajectory(tmp_path / "e.txt")
    np.testing.assert_allclose(read, poses, atol=1e-12)
    wxyz = traj.orientations_quat_wxyz * np.where(traj.orientations_quat_wxyz[:, :1] < 0, -1.0, 1.0)
    np.testing.assert_allclose(pose_to_tum(read)[:, 3:], wxyz[:, [1, 2, 3, 0]], atol=1e-12)


@pytest.mark.parametrize("s", [0.0, 0.25, 0.5, 0.9])
def test_slerp_matches_gtsam(s):
    R = _rotations(10, seed=5)
    P = make_pose(R, np.zeros((10, 3)))
    ts = np.arange(10.0) * 0.05
    out, ok = interpolate_poses(ts, P, ts[:-1] + s * 0.05)
    assert ok.all()
    for k in range(9):
        ref = gtsam.Rot3(R[k]).slerp(s, gtsam.Rot3(R[k + 1])).matrix()
        # slerp takes the shorter arc, which gtsam's geodesic also does below 180 deg apart
        if np.arccos(np.clip((np.trace(R[k].T @ R[k + 1]) - 1) / 2, -1, 1)) < np.pi - 1e-3:
            np.testing.assert_allclose(out[k, :3, :3], ref, atol=1e-12)


def test_adjoint_is_gtsams():
    rng = np.random.default_rng(3)
    poses = [gtsam.Pose3.Expmap(rng.normal(scale=[1.0] * 3 + [2.0] * 3)) for _ in range(5)]
    batch = adjoint(np.array([P.matrix() for P in poses]))
    for P, A in zip(poses, batch):
        np.testing.assert_allclose(A, P.AdjointMap(), atol=1e-12)


def test_rotation_matrices_agree_with_gtsams_exponential():
    """Rodrigues' formula, vectorised, against ``gtsam.Rot3.Expmap``: zero, tiny, ordinary and near-pi
    rotation vectors."""
    from covo_gtsam.geometry import rotation_matrices

    rng = np.random.default_rng(3)
    axes = rng.normal(size=(5, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    w = np.vstack([np.zeros(3), 1e-12 * axes[0], 1e-6 * axes[1], 0.3 * axes[2], 2.0 * axes[3],
                   (np.pi - 1e-6) * axes[4]])
    for wi, R in zip(w, rotation_matrices(w)):
        np.testing.assert_allclose(R, gtsam.Rot3.Expmap(wi).matrix(), atol=1e-12)
