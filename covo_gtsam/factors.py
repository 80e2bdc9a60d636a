"""Two-way point-transfer residuals and the GTSAM factors built on them.

For a matched pair of camera-frame points ``X_k`` (frame k) and ``X_k1`` (frame k+1) and the
relative pose ``T = T_k,k1 = (R, t)`` that maps points of frame k+1 into frame k::

    backward  r_b = X_k  - (R X_k1 + t)          (4.11)-(4.13)
    forward   r_f = X_k1 - R^T (X_k - t)         (4.14)-(4.15)

Jacobians are taken with respect to GTSAM's right (body-frame) perturbation
``T' = T * Exp(xi)``, ``xi = [omega, v]`` (rotation first)::

    d r_b / d xi = [ R [X_k1]x ,  -R ]
    d r_f / d xi = [ -[Y]x     ,   I ]      with  Y = R^T (X_k - t)

Weightings (the covariance assigned to each residual, see ``docs/derivation.md``):

``thesis``
    exactly (4.16): ``r_b`` with ``Q_k1`` and ``r_f`` with ``Q_k``.
``consistent`` (default)
    The true first-order noise of ``r_b`` is ``S_b = Q_k + R Q_k1 R^T`` and, because
    ``r_f = -R^T r_b`` exactly, that of ``r_f`` is ``S_f = R^T S_b R = Q_k1 + R^T Q_k R``. The two
    residuals carry the same information, so each gets ``2 S``: the two-way cost then equals the
    one-way Mahalanobis cost ``r_b^T S_b^-1 r_b`` and ``(J^T W J)^-1`` is the right covariance.
    ``S`` depends on ``R``; it is evaluated at a fixed rotation ``R_w`` (the estimator re-evaluates
    it at the solution until it stops changing), so within one factor the noise is a fixed
    Gaussian and the Jacobians above are exact.

Factors come in two forms with the same residuals:

* per pair (:func:`pair_factor`, :func:`pair_between_factor`): 6-dim error ``[r_b, r_f]`` with a
  ``gtsam.noiseModel.Gaussian`` of covariance ``blockdiag(C_b, C_f)``;
* vectorised over all pairs of a frame pair (:func:`transfer_factor`,
  :func:`transfer_between_factor`): one Python callback per linearisation instead of N (the hot
  path). The 6N-dim pre-whitened error ``e`` and Jacobian ``J`` are handed to GTSAM compressed to
  7 rows (:func:`compress_system`): ``[Q^T e, sqrt(|e|^2 - |Q^T e|^2)]`` with Jacobian ``[R; 0]``
  for ``J = Q R``. That has the same error ``|e|^2``, the same normal equations
  (``R^T R = J^T J``, ``R^T Q^T e = J^T e``) and hence the same Levenberg-Marquardt steps and
  marginals, without GTSAM copying a 6N x 6 matrix per linearisation. What differs is visible
  only on the factor itself: ``dim()`` is 7, and ``unwhitenedError`` is a 7-vector of the right
  norm (``[|e|, 0, ...]`` when evaluated without Jacobians), not the 6N stacked residuals (use
  :func:`whitened_system` for those).

Unary factors act on a relative-pose key holding ``T_k,k1``; binary factors on two absolute pose
keys ``x_k``, ``x_k1`` (world-from-camera) with ``T = x_k^-1 x_k1``.
"""

from __future__ import annotations

from typing import Sequence

import gtsam
import numpy as np

from .errors import InputError
from .geometry import rigid_fit, skew

WEIGHTINGS = ("consistent", "thesis")


def transfer_residuals(R: np.ndarray, t: np.ndarray, X_k: np.ndarray, X_k1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Backward and forward residuals ``(r_b, r_f)``, each (N, 3) metres."""
    r_b = X_k - (X_k1 @ R.T + t)
    r_f = X_k1 - (X_k - t) @ R
    return r_b, r_f


def transfer_jacobians(R: np.ndarray, t: np.ndarray, X_k: np.ndarray, X_k1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Jacobians (N, 3, 6) of ``r_b`` and ``r_f`` w.r.t. the right perturbation ``[omega, v]``."""
    n = X_k.shape[0]
    J_b = np.empty((n, 3, 6))
    J_b[:, :, :3] = R @ skew(X_k1)
    J_b[:, :, 3:] = -R
    J_f = np.zeros((n, 3, 6))
    J_f[:, :, :3] = -skew((X_k - t) @ R)
    J_f[:, :, 3:] = np.eye(3)
    return J_b, J_f


def residual_covariances(
    Q_k: np.ndarray, Q_k1: np.ndarray, weighting: str = "consistent", R_w: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Covariances ``(C_b, C_f)`` (N, 3, 3) assigned to ``r_b`` and ``r_f`` by a weighting.

    ``R_w`` is the rotation at which the ``consistent`` weighting is evaluated (identity if None).
    """
    if weighting == "thesis":
        return Q_k1, Q_k
    if weighting == "consistent":
        R = np.eye(3) if R_w is None else np.asarray(R_w, dtype=float)
        S_b = Q_k + rotate_covariances(R, Q_k1)
        S_f = Q_k1 + rotate_covariances(R.T, Q_k)
        return 2.0 * S_b, 2.0 * S_f
    raise InputError(f"unknown weighting {weighting!r}; choose one of {WEIGHTINGS}")


def rotate_covariances(R: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """``R Q_i R^T`` for a stack of symmetric Q (N, 3, 3) and one rotation R (3, 3)."""
    n = Q.shape[0]
    RQ = (Q.reshape(-1, 3) @ R.T).reshape(n, 3, 3).transpose(0, 2, 1)  # (Q R^T)^T = R Q
    return (RQ.reshape(-1, 3) @ R.T).reshape(n, 3, 3)


SYM6 = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def sym3_mahalanobis(S6: tuple[np.ndarray, ...], r: tuple[np.ndarray, np.ndarray, np.ndarray]) -> np.ndarray:
    """``r^T S^-1 r`` for symmetric 3x3 ``S`` given by its 6 upper entries (any broadcastable
    shapes), by the adjugate; ``inf`` where ``S`` is not positive definite."""
    a, b, c, d, e, f = S6
    x, y, z = r
    A00 = d * f - e * e
    A01 = c * e - b * f
    A02 = b * e - c * d
    A11 = a * f - c * c
    A12 = b * c - a * e
    A22 = a * d - b * b
    det = a * A00 + b * A01 + c * A02
    q = A00 * x * x + A11 * y * y + A22 * z * z + 2.0 * (A01 * x * y + A02 * x * z + A12 * y * z)
    with np.errstate(divide="ignore", invalid="ignore"):
        m = q / det
    return np.where((det > 0) & (a > 0) & (A22 > 0), m, np.inf)


def transfer_mahalanobis(
    R: np.ndarray, t: np.ndarray, X_ref: np.ndarray, X_cur: np.ndarray, Q_ref: np.ndarray, Q_cur: np.ndarray
) -> np.ndarray:
    """Squared Mahalanobis norm (N,) of each pair's ``r_b = X_ref - (R X_cur + t)`` under its
    first-order covariance ``S = Q_ref + R Q_cur R^T`` (:func:`residual_covariances` returns
    ``2 S``); ``inf`` where ``S`` is not positive definite. 3 dof per pair."""
    r = X_ref - (X_cur @ R.T + t)
    C_b, _ = residual_covariances(Q_ref, Q_cur, "consistent", R)
    S6 = tuple(0.5 * C_b[:, i, j] for i, j in SYM6)
    return sym3_mahalanobis(S6, (r[:, 0], r[:, 1], r[:, 2]))


def weighted_rigid_fit(
    X_k: np.ndarray, X_k1: np.ndarray, Q_k: np.ndarray, Q_k1: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form ``(R, t)`` with ``X_k ≈ R X_k1 + t``, pairs weighted by ``1 / trace(Q_k + Q_k1)``
    (:func:`covo_gtsam.geometry.rigid_fit`): the initial guess and the RANSAC refit."""
    w = 1.0 / (np.trace(Q_k, axis1=1, axis2=2) + np.trace(Q_k1, axis1=1, axis2=2))
    return rigid_fit(X_k, X_k1, w)


def is_positive_definite(C: np.ndarray) -> np.ndarray:
    """Mask (N,) of symmetric 3x3 matrices that are positive definite (Sylvester's criterion)."""
    a, b, c = C[:, 0, 0], C[:, 0, 1], C[:, 0, 2]
    d, e, f = C[:, 1, 0], C[:, 1, 1], C[:, 1, 2]
    g, h, i = C[:, 2, 0], C[:, 2, 1], C[:, 2, 2]
    m2 = a * e - b * d
    det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
    return (a > 0) & (m2 > 0) & (det > 0)


def whitening(C: np.ndarray) -> np.ndarray:
    """Matrices ``W`` (N, 3, 3) with ``W^T W = C^-1`` for SPD ``C`` (N, 3, 3).

    ``W = L^-1`` with ``C = L L^T`` (lower Cholesky factor), in closed form for 3x3 blocks.
    """
    C = np.asarray(C, dtype=float)
    l00 = np.sqrt(C[:, 0, 0])
    l10 = C[:, 1, 0] / l00
    l20 = C[:, 2, 0] / l00
    d1 = C[:, 1, 1] - l10 * l10
    l11 = np.sqrt(d1)
    l21 = (C[:, 2, 1] - l20 * l10) / l11
    d2 = C[:, 2, 2] - l20 * l20 - l21 * l21
    l22 = np.sqrt(d2)
    if not (np.all(C[:, 0, 0] > 0) and np.all(d1 > 0) and np.all(d2 > 0)):
        raise InputError("a point covariance is not positive definite")
    W = np.zeros_like(C)
    W[:, 0, 0] = 1.0 / l00
    W[:, 1, 1] = 1.0 / l11
    W[:, 2, 2] = 1.0 / l22
    W[:, 1, 0] = -l10 / (l00 * l11)
    W[:, 2, 1] = -l21 / (l11 * l22)
    W[:, 2, 0] = (l10 * l21 - l11 * l20) / (l00 * l11 * l22)
    return W


def whitened_system(
    R: np.ndarray, t: np.ndarray, X_k: np.ndarray, X_k1: np.ndarray, W_b: np.ndarray, W_f: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Whitened stacked error (6N,) and Jacobian (6N, 6), pair-major ``[W_b r_b, W_f r_f]``.

    Same values as whitening :func:`transfer_residuals` and :func:`transfer_jacobians`, written
    for speed: row i of ``M [P]x`` is ``(m_i x P)^T`` for the rows ``m_i`` of ``M``.
    """
    n = X_k.shape[0]
    Y = (X_k - t) @ R
    e = _whitened_error(X_k - X_k1 @ R.T - t, X_k1 - Y, W_b, W_f)
    # J_b = W_b R [[X_k1]x, -I] = [(-W_b R) [-X_k1]x, -W_b R];  J_f = [W_f [-Y]x, W_f]
    J = np.empty((n, 2, 3, 6))
    M = J[..., 3:]
    M[:, 0] = (W_b.reshape(-1, 3) @ -R).reshape(n, 3, 3)
    M[:, 1] = W_f
    P = np.empty((n, 2, 3))
    np.negative(X_k1, out=P[:, 0])
    np.negative(Y, out=P[:, 1])
    _cross_rows(M, P, J[..., :3])
    return e, J.reshape(-1, 6)


def whitened_error(
    R: np.ndarray, t: np.ndarray, X_k: np.ndarray, X_k1: np.ndarray, W_b: np.ndarray, W_f: np.ndarray
) -> np.ndarray:
    """The error part of :func:`whitened_system` alone (6N,), for evaluations without Jacobians."""
    r_b, r_f = transfer_residuals(R, t, X_k, X_k1)
    return _whitened_error(r_b, r_f, W_b, W_f)


def _whitened_error(r_b: np.ndarray, r_f: np.ndarray, W_b: np.ndarray, W_f: np.ndarray) -> np.ndarray:
    e = np.empty((r_b.shape[0], 6))
    e[:, :3] = np.einsum("nij,nj->ni", W_b, r_b)
    e[:, 3:] = np.einsum("nij,nj->ni", W_f, r_f)
    return e.reshape(-1)


def _cross_rows(W: np.ndarray, P: np.ndarray, out: np.ndarray) -> None:
    """``out[..., i, :] = W[..., i, :] x P`` for W (..., 3, 3), P (..., 3), into ``out`` (..., 3, 3).

    That is ``W [P]x``: row i of ``W [P]x`` is ``(w_i x P)^T``.
    """
    px, py, pz = P[..., None, 0], P[..., None, 1], P[..., None, 2]
    wx, wy, wz = W[..., 0], W[..., 1], W[..., 2]
    out[..., 0] = wy * pz - wz * py
    out[..., 1] = wz * px - wx * pz
    out[..., 2] = wx * py - wy * px


def compress_system(e: np.ndarray, J: np.ndarray, rank_tol: float = 1e-12) -> tuple[np.ndarray, np.ndarray]:
    """``(e7, R7)``: a 7-row system with ``|e7| = |e|``, ``R7^T R7 = J^T J`` and ``R7^T e7 = J^T e``.

    ``R`` is the upper Cholesky factor of ``J^T J`` (6, 6) and ``Q^T e = R^-T J^T e``; the 7th row
    carries the part of ``e`` outside the range of ``J`` (its Jacobian row is zero). A rank-deficient
    ``J^T J`` (degenerate geometry) falls back to an eigen-decomposition square root, dropping
    directions with eigenvalue below ``rank_tol`` times the largest.
    """
    A = J.T @ J
    g = J.T @ e
    R7 = np.zeros((7, 6))
    e7 = np.empty(7)
    try:
        L = np.linalg.cholesky(A)
        R7[:6] = L.T
        e7[:6] = np.linalg.solve(L, g)
    except np.linalg.LinAlgError:
        lam, V = np.linalg.eigh(A)
        keep = lam > rank_tol * max(lam[-1], 1e-300)
        root = np.sqrt(np.where(keep, lam, 0.0))
        R7[:6] = root[:, None] * V.T
        e7[:6] = np.where(keep, (V.T @ g) / np.where(keep, root, 1.0), 0.0)
    e7[6] = np.sqrt(max(float(e @ e) - float(e7[:6] @ e7[:6]), 0.0))
    return e7, R7


def between_jacobian(T: gtsam.Pose3) -> np.ndarray:
    """d(x_k^-1 x_k1)/d(x_k) for right perturbations, i.e. ``-Ad(T^-1)`` with T = x_k^-1 x_k1."""
    return -T.inverse().AdjointMap()


def _custom_factor(
    keys: Sequence[int], noise: gtsam.noiseModel.Base | None, X_k: np.ndarray, X_k1: np.ndarray, W_b: np.ndarray,
    W_f: np.ndarray,
) -> gtsam.CustomFactor:
    """GTSAM factor of the whitened two-way residuals; ``noise=None``: pre-whitened and compressed
    to 7 rows (:func:`compress_system`) with a unit noise model."""
    X_k = np.ascontiguousarray(X_k, dtype=float)
    X_k1 = np.ascontiguousarray(X_k1, dtype=float)
    binary = len(keys) == 2
    k0 = keys[0]
    k1 = keys[-1]
    compressed = noise is None
    if compressed:
        noise = gtsam.noiseModel.Unit.Create(7)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        if binary:
            T = values.atPose3(k0).between(values.atPose3(k1))
        else:
            T = values.atPose3(k0)
        if H is None:
            e = whitened_error(T.rotation().matrix(), T.translation(), X_k, X_k1, W_b, W_f)
            if compressed:  # only the norm matters without Jacobians
                e7 = np.zeros(7)
                e7[0] = np.sqrt(e @ e)
                return e7
            return e
        e, J = whitened_system(T.rotation().matrix(), T.translation(), X_k, X_k1, W_b, W_f)
        if compressed:
            e, J = compress_system(e, J)
        if binary:
            H[0] = J @ between_jacobian(T)
            H[1] = J
        else:
            H[0] = J
        return e

    return gtsam.CustomFactor(noise, gtsam.KeyVector(list(keys)), error)


def transfer_factor(
    key: int, X_k: np.ndarray, X_k1: np.ndarray, C_b: np.ndarray, C_f: np.ndarray
) -> gtsam.CustomFactor:
    """Vectorised unary factor over all N pairs on the relative-pose key ``T_k,k1``."""
    return whitened_transfer_factor(key, X_k, X_k1, whitening(C_b), whitening(C_f))


def whitened_transfer_factor(
    key: int, X_k: np.ndarray, X_k1: np.ndarray, W_b: np.ndarray, W_f: np.ndarray
) -> gtsam.CustomFactor:
    """:func:`transfer_factor` with the whitening matrices ``W^T W = C^-1`` (:func:`whitening`) given."""
    return _custom_factor([key], None, X_k, X_k1, W_b, W_f)


def transfer_between_factor(
    key_k: int, key_k1: int, X_k: np.ndarray, X_k1: np.ndarray, C_b: np.ndarray, C_f: np.ndarray
) -> gtsam.CustomFactor:
    """Vectorised binary factor over all N pairs on absolute poses ``x_k``, ``x_k1``."""
    return _custom_factor([key_k, key_k1], None, X_k, X_k1, whitening(C_b), whitening(C_f))


def _pair_noise(C_b: np.ndarray, C_f: np.ndarray) -> gtsam.noiseModel.Gaussian:
    C = np.zeros((6, 6))
    C[:3, :3] = C_b
    C[3:, 3:] = C_f
    return gtsam.noiseModel.Gaussian.Covariance(C)


_EYE = np.eye(3)[None]


def pair_factor(key: int, X_k: np.ndarray, X_k1: np.ndarray, C_b: np.ndarray, C_f: np.ndarray) -> gtsam.CustomFactor:
    """Unary factor of one pair (points (3,), covariances (3, 3)) with per-point Gaussian noise."""
    return _custom_factor([key], _pair_noise(C_b, C_f), np.reshape(X_k, (1, 3)), np.reshape(X_k1, (1, 3)), _EYE, _EYE)


def pair_between_factor(
    key_k: int, key_k1: int, X_k: np.ndarray, X_k1: np.ndarray, C_b: np.ndarray, C_f: np.ndarray
) -> gtsam.CustomFactor:
    """Binary factor of one pair on absolute poses ``x_k``, ``x_k1`` with per-point Gaussian noise."""
    return _custom_factor(
        [key_k, key_k1], _pair_noise(C_b, C_f), np.reshape(X_k, (1, 3)), np.reshape(X_k1, (1, 3)), _EYE, _EYE
    )
