"""Two-way point-transfer residuals, their Jacobians and weightings (numpy only, no GTSAM).

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

Shared by the front end's RANSAC (:func:`transfer_mahalanobis`, :func:`weighted_rigid_fit`), the
estimator and the GTSAM factors of :mod:`covo_gtsam.factors` (:func:`whitening`,
:func:`whitened_system`).
"""

from __future__ import annotations

import numpy as np

from .errors import InputError
from .geometry import cross, rigid_fit, skew

WEIGHTINGS = ("consistent", "thesis")


def transfer_residuals(R: np.ndarray, t: np.ndarray, X_k: np.ndarray, X_k1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Backward and forward residuals ``(r_b, r_f)``, each (N, 3) metres."""
    r_b = X_k - (X_k1 @ R.T + t)
    r_f = X_k1 - (X_k - t) @ R
    return r_b, r_f


def transfer_jacobians(R: np.ndarray, t: np.ndarray, X_k: np.ndarray, X_k1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Jacobians (N, 3, 6) of ``r_b`` and ``r_f`` w.r.t. the right perturbation ``[omega, v]``."""
    J_f = np.zeros((X_k.shape[0], 3, 6))
    J_f[:, :, :3] = -skew((X_k - t) @ R)
    J_f[:, :, 3:] = np.eye(3)
    return backward_jacobians(R, X_k1), J_f


def backward_jacobians(R: np.ndarray, X_k1: np.ndarray) -> np.ndarray:
    """The Jacobians (N, 3, 6) of ``r_b`` alone (:func:`transfer_jacobians`), ``[R [X_k1]x, -R]``."""
    J_b = np.empty((X_k1.shape[0], 3, 6))
    J_b[:, :, :3] = R @ skew(X_k1)
    J_b[:, :, 3:] = -R
    return J_b


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
    S = Q_ref + rotate_covariances(R, Q_cur)
    return sym3_mahalanobis(tuple(S[:, i, j] for i, j in SYM6), (r[:, 0], r[:, 1], r[:, 2]))


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
    cross(M, P[..., None, :], out=J[..., :3])  # row i of M [P]x: m_i x P
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
