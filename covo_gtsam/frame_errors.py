"""Errors shared by all points of a frame, carried to the relative pose through the estimator.

The per-point model treats the points' errors as independent; an RGB-D frame also has errors that
move all of its points together. Each is a frame-level random variable ``z`` (a few numbers with
a physical unit) that displaces point ``i`` by ``dX_i = A_i z``. To first order the estimate moves
by ``dxi = sum_i G_i dX_i``, with ``G_i`` the estimator's gain (:func:`transfer_gains`), so the
pose covariance gains ``B Sigma_z B^T`` with ``B = sum_i G_i A_i`` (6 x dim z): a covariance with
the geometry of the pair, not an inflation of the per-point one.

Terms (tangent ``[omega, v]``, right perturbation; docs/derivation.md):

* depth scale: the depth image of a frame reads all depths ``1 + e`` times too long (the Kinect's
  depth calibration drifts with temperature), ``dX_i = X_i e``: ``B = sum_i G_i X_i``;
* colour-depth time: the depth image is taken ``offset_s`` after the colour image, so each point
  is moved along its ray by its depth rate, ``dX_i = (X_i / Z_i) dZ_i/dt * d``: a known ``d`` is
  compensated (:func:`depth_time_shift`); an error in it is this term;
* depth-period jump: the depth images of the pair's two frames are read a whole number of depth
  periods apart in time relative to their colour images (:func:`depth_period_jump`); a change ``J``
  of the offset moves the pair, beyond what a common offset does, as the current frame's depths read
  ``J/2`` later and the reference's ``J/2`` earlier would (:func:`depth_read_change`: each point's
  own depth change and the depth image's change at the fixed pixel), ``sum_f sum_i G_i (X_i/Z_i) dz_i``;
* rolling-shutter residual: the compensation uses the camera's twist at the frame; an error
  ``dtwist`` moves point ``i`` (captured ``d_i`` s after the stamp) by
  ``d_i (domega x X_i + dv) = d_i [-[X_i]x, I] dtwist``.
"""

from __future__ import annotations

import numpy as np

from .geometry import image_velocities, skew
from .noise import nearest_depth
from .transfer import backward_jacobians, rotate_covariances


def transfer_gains(R: np.ndarray, t: np.ndarray, X_ref: np.ndarray, X_cur: np.ndarray, Q_ref: np.ndarray,
                   Q_cur: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First-order gains ``(G_ref, G_cur)`` (N, 6, 3) of the relative-pose estimate
    ``T_ref,cur = (R, t)`` with respect to its input points (metres):
    ``dxi = sum_i G_ref[i] dX_ref[i] + G_cur[i] dX_cur[i]`` (right perturbation ``[omega, v]``).

    The estimate minimises ``sum r_i^T S_i^-1 r_i`` with ``r_i = X_ref,i - (R X_cur,i + t)`` and
    ``S_i = Q_ref,i + R Q_cur,i R^T`` (the consistent weighting; docs/derivation.md), so
    ``dxi = -H^-1 sum J_i^T S_i^-1 dr_i`` with ``dr_i = dX_ref,i - R dX_cur,i``. These are the
    gains of the default estimator; with the thesis weighting or a robust kernel they are those
    of the consistent, unweighted estimate, an approximation.
    """
    J = backward_jacobians(R, X_cur)
    JtW = J.transpose(0, 2, 1) @ np.linalg.inv(Q_ref + rotate_covariances(R, Q_cur))
    K = -np.linalg.inv((JtW @ J).sum(axis=0)) @ JtW
    return K, K @ -R


def shared_frame_covariance(idx_a: np.ndarray, G_a: np.ndarray, idx_b: np.ndarray, G_b: np.ndarray,
                            Q: np.ndarray) -> np.ndarray:
    """Cross-covariance (6, 6) of two estimates that share one frame's points: the earlier pair's
    gains ``G_a`` (N_a, 6, 3) for that frame's points (its current frame) and the later pair's ``G_b``
    (N_b, 6, 3) (its reference frame), the points named by their feature indices ``idx_a``/``idx_b``;
    ``sum_j G_a[j] Q[j] G_b[j]^T`` over the features in both (``Q`` (F, 3, 3): the frame's point
    covariances by feature index). Consecutive pairs' estimates are not independent: the middle
    frame's point noise moves the first as its current frame and the second as its reference."""
    common, ia, ib = np.intersect1d(np.asarray(idx_a), np.asarray(idx_b), assume_unique=True, return_indices=True)
    if common.size == 0:
        return np.zeros((6, 6))
    return np.einsum("nij,njk,nlk->il", G_a[ia], Q[common], G_b[ib])


def depth_scale_basis(G: np.ndarray, X: np.ndarray) -> np.ndarray:
    """``B`` (6,) of a frame's depth-scale error: ``sum_i G_i X_i`` (per unit relative scale error)."""
    return (G @ X[:, :, None]).sum(axis=0)[:, 0]


def depth_rates(X: np.ndarray, twist: np.ndarray) -> np.ndarray:
    """Rate of change (N,) of the depth of static points ``X`` (N, 3) seen by a camera moving with
    body twist ``[omega, v]`` (rad/s, m/s): the z row of ``-(omega x X + v)``, m/s."""
    twist = np.asarray(twist, dtype=float).reshape(6)
    return -((twist[0] * X[:, 1] - twist[1] * X[:, 0]) + twist[5])  # the z row of np.cross(omega, X)


def depth_time_shift(X: np.ndarray, twist: np.ndarray, offset_s: float) -> np.ndarray:
    """Points (N, 3) whose depths were read ``offset_s`` s after their bearings, moved along their rays
    to the bearings' time: ``X - (X / Z) dZ/dt offset_s``."""
    return X - (X / X[:, 2:3]) * (depth_rates(X, twist) * offset_s)[:, None]


def depth_time_basis(G: np.ndarray, X: np.ndarray, twist: np.ndarray) -> np.ndarray:
    """``B`` (6,) of an error in a frame's colour-depth time offset: ``sum_i G_i (X_i/Z_i) dZ_i/dt``
    (per second of offset error)."""
    return depth_change_basis(G, X, depth_rates(X, twist))


def depth_time_response(G: np.ndarray, X: np.ndarray) -> np.ndarray:
    """``A`` (6, 6) with ``depth_time_basis(G, X, twist) == A @ twist``: the pair's response to a
    frame's depths read one second late, per unit of the camera's body twist ``[omega, v]``
    (rad/s, m/s) at that frame."""
    X = np.asarray(X, dtype=float)
    g = (G @ (X / X[:, 2:3])[:, :, None])[:, :, 0]  # (N, 6): the response to each depth along its ray
    rates = np.stack([depth_rates(X, unit) for unit in np.eye(6)], axis=1)  # (N, 6): dZ/dt per unit twist
    return g.T @ rates


def depth_period_jump(offset_ref_s: float, offset_cur_s: float, period_s: float) -> float:
    """The change (s) of the colour-depth capture offset from a pair's reference frame to its current
    frame in whole depth-frame periods: ``period_s * round((offset_cur_s - offset_ref_s) / period_s)``
    (offsets: depth minus colour stamp, s). Two streams on clocks of slightly different periods drift
    apart, and where the offset nears half a period the nearest depth image of a colour image switches
    to its neighbour, from frame to frame as the stamps scatter: the depth is then read a whole period
    earlier or later. The stamps scatter by milliseconds around the captures, so only whole periods are
    certain; 0 for a camera whose depth and colour images come together."""
    if not period_s > 0:
        return 0.0
    return float(period_s * np.round((offset_cur_s - offset_ref_s) / period_s))


def depth_read_change(depth: np.ndarray, uv: np.ndarray, X: np.ndarray, twist: np.ndarray, shift_s: float,
                      fx: float, fy: float) -> np.ndarray:
    """Change (N,) of the depth read at pixels ``uv`` (N, 2) had the depth image ``depth`` (H, W;
    metres, 0 = none) been taken ``shift_s`` later, for a camera moving with body twist ``[omega, v]``
    (rad/s, m/s), metres: each point's own depth change ``dZ/dt shift_s`` plus the image's change at
    the fixed pixel, ``D(p - u' shift_s) - D(p)`` read from ``depth`` (``u'`` the point's image
    velocity, :func:`~covo_gtsam.geometry.image_velocities`; nearest pixel), which beside a depth edge
    is the jump to the other surface. The image part is 0 where either pixel has no depth. ``X``
    (N, 3): the points, camera frame at their image's time."""
    z0, ok0 = nearest_depth(depth, uv)
    z1, ok1 = nearest_depth(depth, uv - image_velocities(X, twist, fx, fy) * shift_s)
    return depth_rates(X, twist) * shift_s + np.where(ok0 & ok1, z1 - z0, 0.0)


def depth_change_basis(G: np.ndarray, X: np.ndarray, dz: np.ndarray) -> np.ndarray:
    """``B`` (6,) of a frame's depths each changed by ``dz`` (N,, metres) along their rays:
    ``sum_i G_i (X_i/Z_i) dz_i``."""
    return (G @ ((X / X[:, 2:3]) * dz[:, None])[:, :, None]).sum(axis=0)[:, 0]


def rolling_shutter_basis(G: np.ndarray, X: np.ndarray, row_offsets_s: np.ndarray) -> np.ndarray:
    """``B`` (6, 6) of an error in the twist used by the rolling-shutter compensation of a frame:
    ``sum_i G_i d_i [-[X_i]x, I]`` (``d_i``: capture time of point i's row after the stamp, s)."""
    Gd = G * row_offsets_s[:, None, None]
    return np.concatenate([-(Gd @ skew(X)).sum(axis=0), Gd.sum(axis=0)], axis=1)
