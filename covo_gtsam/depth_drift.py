"""A translation error of the 3D-3D estimate that persists from pair to pair: the depth's drift.

The Kinect's depths drift: over tens of frames the depth of one frame against the next errs
persistently one way, and each pair's 3D-3D estimate moves along the pair's depth-scale response
``b`` (:func:`~covo_gtsam.frame_errors.depth_scale_basis`, mostly a translation along the optical
axis) by as much, pair after pair. The depth-free estimates of the integrity check
(:func:`~covo_gtsam.integrity.depth_free_check`) read each frame's depth only through the points
of one frame, whose depth scale moves them by the scale times the pair's translation (millimetres
per metre of motion, against metres of depth for the 3D-3D estimate), so they do not share that
drift. Their disagreement with the 3D-3D estimate along ``b`` is noisy pair by pair, but its mean
over the last pairs follows the drift (docs/derivation.md, "The depth's drift"):
:class:`DepthDrift` keeps it and the odometry moves each pair's translation by it.

Tangent ``[omega, v]`` (rad, m), right perturbation of ``T_ref,cur`` as everywhere in the package.
"""

from __future__ import annotations

from collections import deque

import numpy as np


def drift_along(delta: np.ndarray, b: np.ndarray, covariance: np.ndarray) -> np.ndarray:
    """The translation part (6,; rotation 0) of ``c b``, where ``c = b^T W delta / b^T W b`` is the
    component of a depth-free estimate's correction ``delta`` (6,) to ``T_ref,cur`` along the
    pair's depth-scale response ``b`` (6,), weighted by ``W = covariance^-1`` (the pair's reported
    covariance, 6x6). NaN (which :meth:`DepthDrift.add` skips) where ``b`` carries no weight or the
    covariance cannot be inverted."""
    out = np.zeros(6)
    try:
        Wb = np.linalg.solve(covariance, b)
    except np.linalg.LinAlgError:
        return out + np.nan
    norm = float(b @ Wb)
    if not (norm > 0 and np.isfinite(norm)):
        return out + np.nan
    out[3:] = (float(delta @ Wb) / norm) * b[3:]
    return out


class DepthDrift:
    """The mean of the last ``pairs`` drift vectors (:func:`drift_along`), each per frame interval:
    the correction ``k * mean`` of a pair over ``k`` intervals (right perturbation, the rotation 0)
    and its covariance ``k^2 S / n`` (``S`` the window's sample covariance, ``n`` the vectors it
    holds, at most ``pairs``). From the second vector on: while the window fills, the mean of the
    vectors so far, with its larger standard error (a run's first pairs would otherwise carry the
    drift uncorrected and unreported; docs/derivation.md, "The depth's drift"). ``pairs`` 0 turns
    it off; a window needs at least 2 (1 counts as 2)."""

    def __init__(self, pairs: int) -> None:
        self._window: deque[np.ndarray] = deque(maxlen=max(int(pairs), 2))
        self.enabled = pairs > 0

    def add(self, vector: np.ndarray, intervals: int = 1) -> None:
        """A kept pair's drift vector (6,) over its ``intervals`` frame intervals."""
        if self.enabled and np.all(np.isfinite(vector)):
            self._window.append(np.asarray(vector, dtype=float) / max(intervals, 1))

    def clear(self) -> None:
        """Forget the window (a new segment: the depth against a frame not matched)."""
        self._window.clear()

    def correction(self, intervals: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """``(xi, C)``: the move (6,) of a pair over ``intervals`` frame intervals, ``T Exp(xi)``, and
        the covariance (6, 6) of that estimate; zeros while the window holds fewer than 2 vectors."""
        n = len(self._window)
        if not self.enabled or n < 2:
            return np.zeros(6), np.zeros((6, 6))
        V = np.asarray(self._window)
        k = max(intervals, 1)
        return k * V.mean(axis=0), k**2 * np.cov(V, rowvar=False) / n
