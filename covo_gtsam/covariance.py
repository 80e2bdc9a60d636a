"""Conversions of a relative-pose covariance between parameterisations.

The package's covariance is GTSAM's: the 6x6 covariance of ``xi = [omega, v]`` (rotation first,
radians and metres) with the right (body-frame) perturbation ``T_true = T_est * Exp(xi)``.

The thesis parameterises a pose by ``(t, q_v)``: the translation ``t`` (metres) of ``T_k,k1`` and
the vector part ``q_v = (qx, qy, qz)`` of its unit quaternion (``qw >= 0``; a half-angle quantity,
dimensionless). To first order at ``T = (R, q)``::

    d t   = R v
    d q_v = 1/2 (qw I + [q_v]x) omega

so ``Q_tq = G Sigma G^T`` with ``G = [[0, R], [1/2 (qw I + [q_v]x), 0]]`` (rows ``t, q_v``,
columns ``omega, v``). ``G`` is invertible while ``qw > 0`` (rotation below 180 degrees).

ROS ``PoseWithCovariance`` (REP 103; ``robot_localization``, ``tf`` users) orders
``[x y z rot_x rot_y rot_z]``: the covariance of the position error ``dt = t_true - t`` (metres,
parent frame) and of the small rotation ``dtheta`` about the parent's fixed axes
(``R_true = Exp(dtheta) R``). For the right perturbation ``T_true = T * Exp([omega, v])``, to first
order ``dt = R v`` and ``dtheta = R omega``, so::

    Sigma_ros = B Sigma B^T,      B = [[0, R], [R, 0]]   (rows dt, dtheta; columns omega, v)

This is not the SE(3) adjoint: the left tangent ``Log(T_true T^-1)`` has the translation part
``dt - dtheta x t``, which is the position error only at the origin.

Every function takes 6x6 finite matrices and ``gtsam.Pose3`` poses and raises
:class:`~covo_gtsam.errors.InputError` for anything else (no NaN out of NaN in).
"""

from __future__ import annotations

import gtsam
import numpy as np

from .errors import InputError
from .geometry import adjoint, invert_pose, matrix_to_quat, skew

def check_matrix(cov, name: str = "covariance", size: int = 6) -> np.ndarray:
    """``cov`` as a finite float (size, size) array; :class:`InputError` otherwise."""
    try:
        a = np.asarray(cov, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a {size}x{size} numeric matrix, got {cov!r}") from None
    if a.shape != (size, size):
        raise InputError(f"{name} must be {size}x{size}, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError(f"{name} contains NaN or inf")
    return a


def check_covariance(cov, name: str = "covariance", size: int = 6) -> np.ndarray:
    """``cov`` as a valid covariance: finite, (size, size), symmetric (to 1e-9 of its largest entry)
    and positive definite (a Cholesky factor exists); :class:`InputError` naming the defect otherwise."""
    a = check_matrix(cov, name, size)
    asym = float(np.abs(a - a.T).max())
    if asym > 1e-9 * max(float(np.abs(a).max()), 1e-300):
        raise InputError(f"{name} is not symmetric (max asymmetry {asym:.3g})")
    try:
        np.linalg.cholesky(a)
    except np.linalg.LinAlgError:
        eig = np.linalg.eigvalsh(0.5 * (a + a.T))
        raise InputError(f"{name} is not positive definite (smallest eigenvalue {eig[0]:.3g})") from None
    return a


def _check_pose(pose) -> gtsam.Pose3:
    if not isinstance(pose, gtsam.Pose3):
        raise InputError(f"pose must be a gtsam.Pose3, got {type(pose).__name__}")
    return pose


def tq_jacobian(pose: gtsam.Pose3) -> np.ndarray:
    """``G = d(t, q_v) / d(omega, v)`` (6x6) at ``pose`` for the right perturbation."""
    R = _check_pose(pose).rotation().matrix()
    q = matrix_to_quat(R)
    qv, qw = q[:3], q[3]
    G = np.zeros((6, 6))
    G[:3, 3:] = R
    G[3:, :3] = 0.5 * (qw * np.eye(3) + skew(qv))
    return G


def tangent_to_tq(cov: np.ndarray, pose: gtsam.Pose3) -> np.ndarray:
    """Thesis ``Q_tq`` (order ``tx ty tz qx qy qz``) from a GTSAM tangent covariance."""
    cov = check_matrix(cov)
    G = tq_jacobian(pose)
    return G @ cov @ G.T


def tq_to_tangent(cov_tq: np.ndarray, pose: gtsam.Pose3) -> np.ndarray:
    """GTSAM tangent covariance from a thesis ``Q_tq``; inverse of :func:`tangent_to_tq`."""
    cov_tq = check_matrix(cov_tq, "cov_tq")
    G = tq_jacobian(pose)
    if not abs(np.linalg.det(G)) > 1e-12:
        raise InputError("the (t, q_v) parameterisation is singular at a rotation of 180 degrees (qw = 0)")
    Gi = np.linalg.inv(G)
    return Gi @ cov_tq @ Gi.T


def ros_jacobian(pose: gtsam.Pose3) -> np.ndarray:
    """``B = d(dt, dtheta) / d(omega, v) = [[0, R], [R, 0]]`` (6x6) at ``pose`` (module docstring)."""
    R = _check_pose(pose).rotation().matrix()
    B = np.zeros((6, 6))
    B[:3, 3:] = R
    B[3:, :3] = R
    return B


def tangent_to_ros(cov: np.ndarray, pose: gtsam.Pose3) -> np.ndarray:
    """ROS ``PoseWithCovariance`` covariance ``[x y z rot_x rot_y rot_z]``: position error and small
    rotations about the parent's fixed axes (see the module docstring)."""
    cov = check_matrix(cov)
    B = ros_jacobian(pose)
    return B @ cov @ B.T


def ros_to_tangent(cov_ros: np.ndarray, pose: gtsam.Pose3) -> np.ndarray:
    """GTSAM tangent covariance from a ROS ``PoseWithCovariance`` covariance; inverse of the above
    (``B^-1 = B^T``)."""
    cov_ros = check_matrix(cov_ros, "cov_ros")
    B = ros_jacobian(pose)
    return B.T @ cov_ros @ B


def compose_covariance(T_a: gtsam.Pose3, cov_a: np.ndarray, T_b: gtsam.Pose3, cov_b: np.ndarray) -> np.ndarray:
    """First-order covariance of ``T_a * T_b`` for independent ``T_a``, ``T_b`` (right perturbations).

    ``T_a Exp(a) T_b Exp(b) = T_a T_b Exp(Ad(T_b^-1) a + b)``.
    """
    cov_a, cov_b = check_matrix(cov_a, "cov_a"), check_matrix(cov_b, "cov_b")
    _check_pose(T_a)
    A = _check_pose(T_b).inverse().AdjointMap()
    return A @ cov_a @ A.T + cov_b


def compose_chains(T: np.ndarray, cov: np.ndarray, length: int | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Poses (M, 4, 4) and first-order covariances (M, 6, 6) of chains of relative poses ``T``
    (N, 4, 4) with covariances ``cov`` (N, 6, 6), the poses independent (as between factors are):
    :func:`compose_covariance` applied along each chain, all chains at once. ``length`` an int:
    every window ``T_i T_i+1 ... T_i+length-1`` (``M = N - length + 1``, 0 when ``N < length``);
    or an index array (M, L): chain ``m`` composes ``T[index[m, 0]] ... T[index[m, L-1]]``."""
    T, cov = np.asarray(T, dtype=float), np.asarray(cov, dtype=float)
    if np.ndim(length) == 0:
        if int(length) < 1:
            raise InputError(f"a chain needs a length >= 1, got {length!r}")
        index = np.arange(max(T.shape[0] - int(length) + 1, 0))[:, None] + np.arange(int(length))
    else:
        index = np.asarray(length)
    if (T.ndim != 3 or T.shape[1:] != (4, 4) or cov.shape != (T.shape[0], 6, 6) or index.ndim != 2
            or index.shape[1] < 1 or not np.issubdtype(index.dtype, np.integer)
            or (index.size and not (0 <= index.min() and index.max() < T.shape[0]))):
        raise InputError(f"need poses (N, 4, 4), covariances (N, 6, 6) and chains of indices into them, got "
                         f"{T.shape}, {cov.shape}, {index.shape}")
    if not index.shape[0]:
        return np.empty((0, 4, 4)), np.empty((0, 6, 6))
    T_chain, C_chain = T[index[:, 0]].copy(), cov[index[:, 0]].copy()
    for k in range(1, index.shape[1]):
        Tk = T[index[:, k]]
        A = adjoint(invert_pose(Tk))
        C_chain = A @ C_chain @ np.swapaxes(A, 1, 2) + cov[index[:, k]]
        T_chain = T_chain @ Tk
    return T_chain, C_chain
