"""GTSAM factors of the two-way point transfer.

The residuals ``r_b``, ``r_f``, their Jacobians (right perturbation ``[omega, v]``) and the
weightings that assign them covariances are numpy maths in :mod:`covo_gtsam.transfer`; this module
hands them to GTSAM.

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
  :func:`covo_gtsam.transfer.whitened_system` for those).

Unary factors act on a relative-pose key holding ``T_k,k1``; binary factors on two absolute pose
keys ``x_k``, ``x_k1`` (world-from-camera) with ``T = x_k^-1 x_k1``.
"""

from __future__ import annotations

from typing import Sequence

import gtsam
import numpy as np

from .transfer import whitened_error, whitened_system, whitening


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
