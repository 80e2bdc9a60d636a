"""Trajectory and consistency metrics: RPE, ATE, NEES (pure numpy functions).

Poses are 4x4 matrices T_world,cam (translations in m). Rotational errors are in radians unless a
name says deg. Tangent vectors follow GTSAM: ``xi = [omega, v]`` with ``T' = T * Exp(xi)``. The
chi-square helpers (``chi2_cdf``, ``chi2_pdf``, ``chi2_quantile``) live in :mod:`covo_gtsam.chi2`
and are importable from here too.
"""

from __future__ import annotations

import numpy as np

from .chi2 import chi2_cdf, chi2_pdf, chi2_quantile
from .errors import InputError
from .geometry import invert_pose, rotation_angle, similarity_fit, skew

__all__ = [
    "anees",
    "ate",
    "block_traces",
    "block_shares",
    "ate_errors",
    "ate_statistics",
    "chi2_cdf",
    "chi2_pdf",
    "chi2_quantile",
    "nees",
    "relative_pose_errors",
    "relative_pose_nees",
    "relative_pose_tangent_errors",
    "rpe",
    "rpe_statistics",
    "se3_log",
    "umeyama_alignment",
]


def _pose_pair(poses_gt: np.ndarray, poses_est: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    G = np.asarray(poses_gt, dtype=float)
    P = np.asarray(poses_est, dtype=float)
    if G.ndim != 3 or G.shape[1:] != (4, 4) or G.shape != P.shape:
        raise InputError(f"need two pose arrays of the same shape (N, 4, 4), got {G.shape} and {P.shape}")
    return G, P


def relative_pose_errors(poses_gt: np.ndarray, poses_est: np.ndarray, delta: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """TUM-benchmark relative pose errors over ``delta`` frames, for every ``i`` with ``i + delta < N``.

    ``E_i = (G_i^-1 G_{i+delta})^-1 (P_i^-1 P_{i+delta})`` for ground truth ``G`` and estimate ``P``
    (N, 4, 4), both T_world,cam. Returns ``||trans(E_i)||`` (m) and ``angle(E_i)`` (rad), each (N - delta,).
    """
    G, P = _pose_pair(poses_gt, poses_est)
    delta = int(delta)
    if not 1 <= delta < G.shape[0]:
        raise InputError(f"delta must be in [1, {G.shape[0] - 1}] for {G.shape[0]} poses, got {delta}")
    rel_g = invert_pose(G[:-delta]) @ G[delta:]
    rel_p = invert_pose(P[:-delta]) @ P[delta:]
    E = invert_pose(rel_g) @ rel_p
    return np.linalg.norm(E[:, :3, 3], axis=1), rotation_angle(E[:, :3, :3])


def rpe(poses_gt: np.ndarray, poses_est: np.ndarray, delta: int = 1) -> dict:
    """RPE statistics over ``delta`` frames (all pairs ``(i, i + delta)``).

    Keys: ``trans_rmse``, ``trans_mean``, ``trans_median`` (m), ``rot_rmse_deg``, ``rot_mean_deg``,
    ``n`` (number of pairs), ``delta_frames``.
    """
    return rpe_statistics(*relative_pose_errors(poses_gt, poses_est, delta), delta)


def rpe_statistics(trans_err: np.ndarray, rot_err: np.ndarray, delta: int) -> dict:
    """The :func:`rpe` dictionary of translational (m) and rotational (rad) errors, e.g. pooled
    from several trajectory segments."""
    tr, rot = np.asarray(trans_err, dtype=float), np.asarray(rot_err, dtype=float)
    if tr.size == 0 or tr.shape != rot.shape:
        raise InputError(f"need equally many (>= 1) translational and rotational errors, got {tr.shape}, {rot.shape}")
    return {
        "delta_frames": int(delta),
        "trans_rmse": float(np.sqrt(np.mean(tr**2))),
        "trans_mean": float(np.mean(tr)),
        "trans_median": float(np.median(tr)),
        "rot_rmse_deg": float(np.rad2deg(np.sqrt(np.mean(rot**2)))),
        "rot_mean_deg": float(np.rad2deg(np.mean(rot))),
        "n": int(tr.shape[0]),
    }


def umeyama_alignment(
    src: np.ndarray, dst: np.ndarray, with_scale: bool = False
) -> tuple[np.ndarray, np.ndarray, float]:
    """``(R, t, s)`` minimising ``sum ||dst_i - (s R src_i + t)||^2`` over points (N, 3) (Umeyama 1991),
    by :func:`covo_gtsam.geometry.similarity_fit`.

    ``R`` is a proper rotation (det +1); ``s`` is 1.0 unless ``with_scale``.
    """
    src = np.asarray(src, dtype=float)
    dst = np.asarray(dst, dtype=float)
    if src.ndim != 2 or src.shape[1] != 3 or src.shape != dst.shape or src.shape[0] < 2:
        raise InputError(f"need two point arrays of the same shape (N>=2, 3), got {src.shape} and {dst.shape}")
    return similarity_fit(dst, src, with_scale=with_scale)


def ate(poses_gt: np.ndarray, poses_est: np.ndarray, with_scale: bool = False) -> dict:
    """Absolute trajectory error (m) of the positions after aligning the estimate to the ground truth.

    The alignment is SE(3) (Sim(3) with ``with_scale``) by :func:`umeyama_alignment` on the positions.
    Keys: ``rmse``, ``mean``, ``median``, ``max`` (m), ``n``, ``scale``.
    """
    err, s = ate_errors(poses_gt, poses_est, with_scale)
    return {**ate_statistics(err), "scale": float(s)}


def ate_errors(poses_gt: np.ndarray, poses_est: np.ndarray, with_scale: bool = False) -> tuple[np.ndarray, float]:
    """Position errors (N,) in m after :func:`umeyama_alignment` of the estimate, and the scale."""
    G, P = _pose_pair(poses_gt, poses_est)
    pg, pe = G[:, :3, 3], P[:, :3, 3]
    R, t, s = umeyama_alignment(pe, pg, with_scale)
    return np.linalg.norm(pg - (s * pe @ R.T + t), axis=1), s


def ate_statistics(err: np.ndarray) -> dict:
    """``rmse``, ``mean``, ``median``, ``max`` (m) and ``n`` of position errors (e.g. pooled from segments)."""
    err = np.asarray(err, dtype=float)
    if err.size == 0:
        raise InputError("need at least one position error")
    return {
        "rmse": float(np.sqrt(np.mean(err**2))),
        "mean": float(np.mean(err)),
        "median": float(np.median(err)),
        "max": float(np.max(err)),
        "n": int(err.shape[0]),
    }


def nees(err: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Normalised estimation error squared ``e_i^T C_i^-1 e_i`` of errors (N, d) and covariances (N, d, d) -> (N,)."""
    err = np.asarray(err, dtype=float)
    cov = np.asarray(cov, dtype=float)
    if err.ndim != 2 or cov.shape != err.shape + (err.shape[1],):
        raise InputError(f"need errors (N, d) and covariances (N, d, d), got {err.shape} and {cov.shape}")
    return np.einsum("ni,ni->n", err, np.linalg.solve(cov, err[..., None])[..., 0])


def block_traces(cov: np.ndarray) -> np.ndarray:
    """The rotation and translation variance (..., 2) of covariances (..., 6, 6), tangent ``[omega, v]``:
    the trace of each 3x3 block (rad^2, m^2)."""
    cov = np.asarray(cov, dtype=float)
    return np.stack([np.einsum("...ii->...", cov[..., :3, :3]), np.einsum("...ii->...", cov[..., 3:, 3:])], axis=-1)


def block_shares(part: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Share (N, 2) of each covariance's rotation and translation variance (:func:`block_traces`)
    that is ``part``: covariances (N, 6, 6), ``part`` (6, 6) or (N, 6, 6)."""
    return block_traces(part) / block_traces(cov)


def anees(values: np.ndarray) -> float:
    """Average NEES of NEES values (N,); divide by nothing (compare with the dof, e.g. 3)."""
    return float(np.mean(np.asarray(values, dtype=float)))


def se3_log(T: np.ndarray) -> np.ndarray:
    """GTSAM's ``Pose3.Logmap`` of 4x4 poses (..., 4, 4) -> (..., 6) ``[omega, v]`` (rad, m), vectorised.

    Rotations within 1e-4 rad of pi (rare) go through ``gtsam.Rot3.Logmap`` one by one.
    """
    T = np.asarray(T, dtype=float)
    shape = T.shape[:-2]
    T = T.reshape(-1, 4, 4)
    R = T[:, :3, :3]
    w_hat = 0.5 * np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    sin_t = np.linalg.norm(w_hat, axis=1)
    cos_t = 0.5 * (np.trace(R, axis1=1, axis2=2) - 1.0)
    theta = np.arctan2(sin_t, cos_t)
    tiny = sin_t < 1e-300
    scale = np.where(tiny, 1.0, theta / np.where(tiny, 1.0, sin_t))
    omega = w_hat * scale[:, None]
    near_pi = theta > np.pi - 1e-4
    if np.any(near_pi):  # sin(theta) ~ 0 loses the axis: use GTSAM's special case
        import gtsam

        for i in np.flatnonzero(near_pi):
            omega[i] = gtsam.Rot3.Logmap(gtsam.Rot3(R[i]))
        theta = np.where(near_pi, np.linalg.norm(omega, axis=1), theta)
    # v = V^-1 t, V^-1 = I - 1/2 [w] + c(theta) [w]^2, c = (1 - (theta/2) / tan(theta/2)) / theta^2
    small = theta < 1e-2
    th = np.where(small, 1.0, theta)
    half = 0.5 * th
    c = np.where(small, 1.0 / 12.0 + theta**2 / 720.0 + theta**4 / 30240.0, (1.0 - half / np.tan(half)) / th**2)
    W = skew(omega)
    Vinv = np.eye(3) - 0.5 * W + c[:, None, None] * (W @ W)
    v = np.einsum("nij,nj->ni", Vinv, T[:, :3, 3])
    return np.concatenate([omega, v], axis=1).reshape(shape + (6,))


def relative_pose_tangent_errors(T_est: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    """Errors ``xi = Log(T_est^-1 T_true)`` (N, 6) of estimated against true poses (N, 4, 4), in
    GTSAM's tangent ``[omega, v]`` (rad, m) with the right perturbation ``T_true = T_est * Exp(xi)``."""
    T_est, T_true = _pose_pair(T_est, T_true)
    return se3_log(invert_pose(T_est) @ T_true)


def relative_pose_nees(T_est: np.ndarray, T_true: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """NEES of the rotation and of the translation (3 dof each) of relative poses.

    ``T_est``, ``T_true``: (N, 4, 4) estimated and true T_ref,cur; ``cov``: (N, 6, 6) covariance of the
    estimate in GTSAM's tangent ``[omega, v]`` (rad, m) with the right perturbation
    ``T_true = T_est * Exp(xi)``. The error is ``xi = Log(T_est^-1 T_true)`` (GTSAM ``Pose3.Logmap``);
    ``nees_rot`` uses ``xi[:3]`` with ``cov[:3, :3]``, ``nees_trans`` uses ``xi[3:]`` with ``cov[3:, 3:]``.
    Returns ``(nees_rot (N,), nees_trans (N,))``.
    """
    xi = relative_pose_tangent_errors(T_est, T_true)
    cov = np.asarray(cov, dtype=float)
    if cov.shape != (xi.shape[0], 6, 6):
        raise InputError(f"need covariances ({xi.shape[0]}, 6, 6), got {cov.shape}")
    return nees(xi[:, :3], cov[:, :3, :3]), nees(xi[:, 3:], cov[:, 3:, 3:])
