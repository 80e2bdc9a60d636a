"""Small rigid-body helpers on numpy arrays.

Conventions used throughout the package:

* A pose is a 4x4 homogeneous matrix ``T_a_b`` (or a ``gtsam.Pose3``) that maps points
  expressed in frame *b* into frame *a*: ``X_a = R X_b + t``.
* Quaternions are stored in TUM / ROS order ``(qx, qy, qz, qw)`` (Hamilton convention,
  scalar last). ``gtsam.Rot3.Quaternion(w, x, y, z)`` takes the scalar first; conversions
  go through this module so the order is decided in one place.
* Tangent vectors of SE(3) follow GTSAM: ``xi = [omega, v]`` (rotation first, then
  translation), with the right (body-frame) perturbation ``T' = T * Exp(xi)``.
"""

from __future__ import annotations

import numpy as np


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices: ``skew(a) @ b == np.cross(a, b)``; (..., 3) -> (..., 3, 3)."""
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1] = -v[..., 2]
    out[..., 0, 2] = v[..., 1]
    out[..., 1, 0] = v[..., 2]
    out[..., 1, 2] = -v[..., 0]
    out[..., 2, 0] = -v[..., 1]
    out[..., 2, 1] = v[..., 0]
    return out


def cross(a: np.ndarray, b: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """``np.cross(a, b)`` of 3-vectors along the last axis (shapes that broadcast, e.g. (3,) and
    (N, 3)): the same products and differences, so the same values, without ``np.cross``'s axis
    handling (about half its time on a frame's points); into ``out`` when given (e.g. a view)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    out = np.empty(np.broadcast_shapes(a.shape, b.shape)) if out is None else out
    out[..., 0] = a1 * b2 - a2 * b1
    out[..., 1] = a2 * b0 - a0 * b2
    out[..., 2] = a0 * b1 - a1 * b0
    return out


def rotation_matrices(w: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 3, 3) of rotation vectors (N, 3) (the exponential map of SO(3), Rodrigues'
    formula; a test checks it against ``gtsam.Rot3.Expmap``)."""
    w = np.asarray(w, dtype=float).reshape(-1, 3)
    theta = np.linalg.norm(w, axis=1)
    k = w / np.where(theta > 0, theta, 1.0)[:, None]
    K = np.zeros((len(w), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K = K - K.transpose(0, 2, 1)
    st, ct = np.sin(theta)[:, None, None], np.cos(theta)[:, None, None]
    return np.eye(3) + st * K + (1 - ct) * (K @ K)


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices from quaternions ``(qx, qy, qz, qw)``; (..., 4) -> (..., 3, 3).

    The quaternion is normalised first (``gtsam.Rot3.Quaternion`` takes it as it is), then
    converted by ``gtsam.Rot3.Quaternion(qw, qx, qy, qz)``.
    """
    import gtsam

    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    wxyz = q.reshape(-1, 4)[:, [3, 0, 1, 2]].tolist()
    return np.array([gtsam.Rot3.Quaternion(*c).matrix() for c in wxyz]).reshape(q.shape[:-1] + (3, 3))


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(qx, qy, qz, qw)`` with ``qw >= 0`` from rotation matrices.

    (..., 3, 3) -> (..., 4). Shepperd's method: the branch of the largest of ``qw``, ``qx``,
    ``qy``, ``qz`` per element (``tests/test_geometry.py`` checks it against
    ``gtsam.Rot3.toQuaternion``, which agrees to a few ulp, and evo's reader).
    """
    R = np.asarray(R, dtype=float)
    shape = R.shape[:-2]
    m = R.reshape(-1, 3, 3)
    q = np.empty((m.shape[0], 4))
    tr = np.trace(m, axis1=1, axis2=2)
    m00, m11, m22 = m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]
    by_w = tr > 0
    by_x = ~by_w & (m00 > m11) & (m00 > m22)
    by_y = ~by_w & ~by_x & (m11 > m22)
    by_z = ~(by_w | by_x | by_y)
    # each branch: s = 4 * |its component|, the other components from sums and differences
    if by_w.any():
        a = m[by_w]
        s = 2.0 * np.sqrt(1.0 + tr[by_w])
        q[by_w] = np.stack([(a[:, 2, 1] - a[:, 1, 2]) / s, (a[:, 0, 2] - a[:, 2, 0]) / s,
                            (a[:, 1, 0] - a[:, 0, 1]) / s, 0.25 * s], axis=1)
    if by_x.any():
        a = m[by_x]
        s = 2.0 * np.sqrt(1.0 + a[:, 0, 0] - a[:, 1, 1] - a[:, 2, 2])
        q[by_x] = np.stack([0.25 * s, (a[:, 0, 1] + a[:, 1, 0]) / s, (a[:, 0, 2] + a[:, 2, 0]) / s,
                            (a[:, 2, 1] - a[:, 1, 2]) / s], axis=1)
    if by_y.any():
        a = m[by_y]
        s = 2.0 * np.sqrt(1.0 + a[:, 1, 1] - a[:, 0, 0] - a[:, 2, 2])
        q[by_y] = np.stack([(a[:, 0, 1] + a[:, 1, 0]) / s, 0.25 * s, (a[:, 1, 2] + a[:, 2, 1]) / s,
                            (a[:, 0, 2] - a[:, 2, 0]) / s], axis=1)
    if by_z.any():
        a = m[by_z]
        s = 2.0 * np.sqrt(1.0 + a[:, 2, 2] - a[:, 0, 0] - a[:, 1, 1])
        q[by_z] = np.stack([(a[:, 0, 2] + a[:, 2, 0]) / s, (a[:, 1, 2] + a[:, 2, 1]) / s, 0.25 * s,
                            (a[:, 1, 0] - a[:, 0, 1]) / s], axis=1)
    q *= np.where(q[:, 3:4] < 0, -1.0, 1.0)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return q.reshape(shape + (4,))


def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 homogeneous matrices from rotations (..., 3, 3) and translations (..., 3)."""
    R = np.asarray(R, dtype=float)
    t = np.asarray(t, dtype=float)
    T = np.zeros(R.shape[:-2] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def pose_from_tum(row: np.ndarray) -> np.ndarray:
    """4x4 poses from TUM rows ``(tx, ty, tz, qx, qy, qz, qw)``; (..., 7) -> (..., 4, 4)."""
    row = np.asarray(row, dtype=float)
    return make_pose(quat_to_matrix(row[..., 3:7]), row[..., 0:3])


def pose_to_tum(T: np.ndarray) -> np.ndarray:
    """TUM rows ``(tx, ty, tz, qx, qy, qz, qw)`` from 4x4 poses; (..., 4, 4) -> (..., 7)."""
    T = np.asarray(T, dtype=float)
    return np.concatenate([T[..., :3, 3], matrix_to_quat(T[..., :3, :3])], axis=-1)


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Inverse of 4x4 rigid transforms, (..., 4, 4)."""
    T = np.asarray(T, dtype=float)
    R = T[..., :3, :3]
    Rt = np.swapaxes(R, -1, -2)
    return make_pose(Rt, -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3]))


def adjoint(T: np.ndarray) -> np.ndarray:
    """Adjoints (..., 6, 6) of 4x4 rigid transforms (..., 4, 4) in GTSAM's tangent order
    ``[omega, v]``: ``[[R, 0], [[t]x R, R]]`` (``T Exp(xi) T^-1 = Exp(Ad(T) xi)``)."""
    T = np.asarray(T, dtype=float)
    R = T[..., :3, :3]
    out = np.zeros(T.shape[:-2] + (6, 6))
    out[..., :3, :3] = R
    out[..., 3:, 3:] = R
    out[..., 3:, :3] = skew(T[..., :3, 3]) @ R
    return out


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Rotation angle in radians of rotation matrices (..., 3, 3), in [0, pi]."""
    R = np.asarray(R, dtype=float)
    c = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.arccos(np.clip(c, -1.0, 1.0))


def rigid_fit(A: np.ndarray, B: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least-squares rigid transform with ``A ≈ R B + t``: :func:`similarity_fit`
    without scale. Returns ``R`` (..., 3, 3) with det +1 and ``t`` (..., 3)."""
    R, t, _ = similarity_fit(A, B, weights, with_scale=False)
    return R, t


def similarity_fit(
    A: np.ndarray, B: np.ndarray, weights: np.ndarray | None = None, with_scale: bool = True
) -> tuple[np.ndarray, np.ndarray, np.ndarray | float]:
    """Weighted least-squares ``(R, t, s)`` with ``A ≈ s R B + t`` (Kabsch; Umeyama 1991 for the scale).

    The package's one point-set alignment: the RANSAC hypotheses, the initial guess and the ATE.
    Works on one problem, A and B of shape (N, 3), or on a batch, (H, N, 3) each. ``R`` is a
    proper rotation (det +1, never a reflection); ``s`` is 1.0 unless ``with_scale``.
    """
    A = np.asarray(A, dtype=float)
    B = np.asarray(B, dtype=float)
    if weights is None:
        w = np.ones(A.shape[:-1])
    else:
        w = np.broadcast_to(np.asarray(weights, dtype=float), A.shape[:-1])
    w = w / np.sum(w, axis=-1, keepdims=True)
    ca = np.einsum("...n,...ni->...i", w, A)
    cb = np.einsum("...n,...ni->...i", w, B)
    H = np.einsum("...n,...ni,...nj->...ij", w, B - cb[..., None, :], A - ca[..., None, :])
    U, D, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.swapaxes(Vt, -1, -2) @ np.swapaxes(U, -1, -2)))
    d = np.where(d == 0, 1.0, d)
    S = np.zeros(H.shape)
    S[..., 0, 0] = 1.0
    S[..., 1, 1] = 1.0
    S[..., 2, 2] = d
    R = np.swapaxes(Vt, -1, -2) @ S @ np.swapaxes(U, -1, -2)
    if with_scale:  # trace(D S) / weighted variance of B
        var_b = np.einsum("...n,...n->...", w, np.sum((B - cb[..., None, :]) ** 2, axis=-1))
        s = (D[..., 0] + D[..., 1] + d * D[..., 2]) / var_b
        t = ca - s[..., None] * np.einsum("...ij,...j->...i", R, cb)
        return R, t, (float(s) if np.ndim(s) == 0 else s)
    t = ca - np.einsum("...ij,...j->...i", R, cb)
    return R, t, 1.0


def image_velocities(X: np.ndarray, twist: np.ndarray, fx: float, fy: float) -> np.ndarray:
    """Image-plane velocities (N, 2; px/s) of static points ``X`` (N, 3; camera frame, metres) seen
    by a camera moving with body twist ``[omega, v]`` (rad/s, m/s); pinhole, no distortion."""
    twist = np.asarray(twist, dtype=float).reshape(6)
    Xd = -(cross(twist[:3], X) + twist[3:])
    z = X[:, 2]
    return np.stack([fx * (Xd[:, 0] * z - X[:, 0] * Xd[:, 2]) / z**2,
                     fy * (Xd[:, 1] * z - X[:, 1] * Xd[:, 2]) / z**2], axis=1)
