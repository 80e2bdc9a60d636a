"""Trajectory and consistency metrics: RPE, ATE, NEES (pure functions on numpy arrays).

Poses are 4x4 matrices T_world,cam. Rotational errors are in radians unless a name says deg.
"""

from __future__ import annotations

import math

import numpy as np

from .geometry import invert_pose, rotation_angle, skew


def relative_pose_errors(poses_gt: np.ndarray, poses_est: np.ndarray, delta: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """TUM-benchmark RPE over ``delta`` frames: ``E_i = (G_i^-1 G_i+d)^-1 (P_i^-1 P_i+d)`` (5.1).

    Returns translational errors ``||trans(E_i)||`` (m) and rotation angles of ``E_i`` (rad), (m,).
    """
    G = np.asarray(poses_gt, dtype=float)
    P = np.asarray(poses_est, dtype=float)
    rel_g = invert_pose(G[:-delta]) @ G[delta:]
    rel_p = invert_pose(P[:-delta]) @ P[delta:]
    E = invert_pose(rel_g) @ rel_p
    return np.linalg.norm(E[:, :3, 3], axis=1), rotation_angle(E[:, :3, :3])


def rpe(poses_gt: np.ndarray, poses_est: np.ndarray, delta: int = 1) -> dict:
    """RMSE (5.2) and summary of the RPE over ``delta`` frames."""
    tr, rot = relative_pose_errors(poses_gt, poses_est, delta)
    return {
        "delta_frames": int(delta),
        "trans_rmse": float(np.sqrt(np.mean(tr**2))),
        "trans_mean": float(np.mean(tr)),
        "trans_median": float(np.median(tr)),
        "rot_rmse_deg": float(np.rad2deg(np.sqrt(np.mean(rot**2)))),
        "rot_mean_deg": float(np.rad2deg(np.mean(rot))),
        "n": int(tr.shape[0]),
    }


def umeyama_alignment(src: np.ndarray, dst: np.ndarray, with_scale: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """``(R, t, s)`` minimising ``||dst - (s R src + t)||`` over points (N, 3) (Umeyama 1991)."""
    src = np.asarray(src, dtype=float)
    dst = np.asarray(dst, dtype=float)
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / src.shape[0]
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    s = float(np.trace(np.diag(D) @ S) / np.mean(np.sum(xs**2, 1))) if with_scale else 1.0
    t = mu_d - s * R @ mu_s
    return R, t, s


def ate(poses_gt: np.ndarray, poses_est: np.ndarray, with_scale: bool = False) -> dict:
    """Absolute trajectory error (m) of the positions after SE(3) (or Sim(3)) Umeyama alignment."""
    pg = np.asarray(poses_gt)[:, :3, 3]
    pe = np.asarray(poses_est)[:, :3, 3]
    R, t, s = umeyama_alignment(pe, pg, with_scale)
    err = np.linalg.norm(pg - (s * pe @ R.T + t), axis=1)
    return {
        "rmse": float(np.sqrt(np.mean(err**2))),
        "mean": float(np.mean(err)),
        "median": float(np.median(err)),
        "max": float(np.max(err)),
        "n": int(err.shape[0]),
    }


def nees(err: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """``e^T C^-1 e`` for errors (N, d) and covariances (N, d, d)."""
    err = np.asarray(err, dtype=float)
    return np.einsum("ni,ni->n", err, np.linalg.solve(cov, err[..., None])[..., 0])


def anees(values: np.ndarray) -> float:
    """Average NEES (5.5)."""
    return float(np.mean(values))


def se3_log(T: np.ndarray) -> np.ndarray:
    """GTSAM's ``Pose3.Logmap`` of 4x4 poses (N, 4, 4) -> (N, 6) ``[omega, v]``."""
    T = np.asarray(T, dtype=float).reshape(-1, 4, 4)
    R = T[:, :3, :3]
    theta = rotation_angle(R)
    W = 0.5 * (R - np.swapaxes(R, 1, 2))
    w_hat = np.stack([W[:, 2, 1], W[:, 0, 2], W[:, 1, 0]], 1)
    small = theta < 1e-8
    scale = np.where(small, 1.0, theta / np.where(small, 1.0, np.sin(theta)))
    near_pi = theta > np.pi - 1e-6
    omega = w_hat * scale[:, None]
    if np.any(near_pi):  # sin(theta) ~ 0: use the symmetric part
        import gtsam

        for i in np.flatnonzero(near_pi):
            omega[i] = gtsam.Rot3.Logmap(gtsam.Rot3(R[i]))
            theta[i] = np.linalg.norm(omega[i])
    # V^-1 = I - 1/2 [w] + (1/th^2)(1 - th sin th / (2(1 - cos th))) [w]^2
    Wx = skew(omega)
    th2 = theta**2
    safe = np.where(theta < 1e-5, 1.0, theta)
    coef = np.where(
        theta < 1e-5, 1.0 / 12.0, (1 - safe * np.sin(safe) / (2 * (1 - np.cos(safe)))) / np.where(theta < 1e-5, 1.0, th2)
    )
    Vinv = np.eye(3) - 0.5 * Wx + coef[:, None, None] * (Wx @ Wx)
    v = np.einsum("nij,nj->ni", Vinv, T[:, :3, 3])
    return np.concatenate([omega, v], 1)


def relative_pose_nees(T_est: np.ndarray, T_true: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """NEES of rotation and translation (3 dof each) of relative poses.

    The error is ``xi = Log(T_est^-1 T_true)`` in GTSAM's tangent ``[omega, v]`` (right
    perturbation, the convention of the covariance); the rotation NEES uses ``cov[:3, :3]``
    with ``xi[:3]``, the translation NEES ``cov[3:, 3:]`` with ``xi[3:]``.
    """
    xi = se3_log(invert_pose(T_est) @ np.asarray(T_true))
    cov = np.asarray(cov, dtype=float)
    return nees(xi[:, :3], cov[:, :3, :3]), nees(xi[:, 3:], cov[:, 3:, 3:])


def _gamma_p(a: float, x: float) -> float:
    """Regularised lower incomplete gamma P(a, x) (series / continued fraction, Numerical Recipes)."""
    if x <= 0:
        return 0.0
    gln = math.lgamma(a)
    if x < a + 1:
        ap, s, d = a, 1.0 / a, 1.0 / a
        for _ in range(1000):
            ap += 1
            d *= x / ap
            s += d
            if abs(d) < abs(s) * 1e-15:
                break
        return s * math.exp(-x + a * math.log(x) - gln)
    b = x + 1 - a
    c = 1.0 / 1e-300
    d = 1.0 / b
    h = d
    for i in range(1, 1000):
        an = -i * (i - a)
        b += 2
        d = an * d + b
        d = 1e-300 if abs(d) < 1e-300 else d
        c = b + an / c
        c = 1e-300 if abs(c) < 1e-300 else c
        d = 1.0 / d
        delta = d * c
        h *= delta
        if abs(delta - 1) < 1e-15:
            break
    return 1.0 - math.exp(-x + a * math.log(x) - gln) * h


def chi2_cdf(x: float, dof: int) -> float:
    return _gamma_p(dof / 2.0, x / 2.0)


def chi2_quantile(p: float, dof: int) -> float:
    """Quantile of the chi-square distribution (bisection on the CDF, 1e-12 relative)."""
    if not 0 < p < 1:
        raise ValueError("p must be in (0, 1)")
    lo, hi = 0.0, max(1.0, dof + 20 * math.sqrt(2 * dof))
    while chi2_cdf(hi, dof) < p:
        hi *= 2
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if chi2_cdf(mid, dof) < p:
            lo = mid
        else:
            hi = mid
        if hi - lo < 1e-12 * hi:
            break
    return 0.5 * (lo + hi)


def chi2_pdf(x: np.ndarray, dof: int) -> np.ndarray:
    """Chi-square density."""
    x = np.asarray(x, dtype=float)
    k = dof / 2.0
    with np.errstate(divide="ignore"):
        return np.where(x > 0, np.exp((k - 1) * np.log(np.where(x > 0, x, 1)) - x / 2 - k * math.log(2) - math.lgamma(k)), 0.0)
