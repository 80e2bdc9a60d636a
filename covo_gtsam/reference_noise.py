"""The ground truth's own noise, measured from its samples alone.

A motion-capture reference jitters from sample to sample; that jitter enters every error measured
against it, the NEES included. :func:`reference_jitter` measures it without any odometry: each
sample is predicted from its ``neighbours`` samples on either side by a quadratic in time (the
camera's smooth motion), and the prediction's residual is the sample's noise plus the
prediction's. For white noise of s.d. ``sigma`` per sample the residual's variance is
``sigma^2 (1 + v)``, with ``v = |w|^2`` from the prediction's weights ``w``; the median of the
residuals squared over ``1 + v``, divided by the median of chi2(1), estimates ``sigma^2`` per axis
(robust to the odd spike of the reference and to fast changes of the motion).

Rotation residuals are ``Log(R_i^T R_pred)`` about the sample's own axes (for TUM ground truth the
colour camera's: x right, y down, z forward), radians; translation residuals are rotated into the
same axes, metres. docs/derivation.md ("The reference's own noise") has the measurements.

:func:`axes_rotation` measures the other error a reference brings: a fixed rotation between its
axes and the camera's (a hand-eye calibration's, or a principal point's), which turns every pose
change it reports. :func:`twist_change_response` measures how the pairs' rotation errors follow
the change of the camera's angular velocity from pair to pair (a timing difference between the
images and the reference). Both need the odometry's estimates, and are checks, not corrections.
"""

from __future__ import annotations

import gtsam
import numpy as np

from .errors import InputError
from .geometry import invert_pose
from .metrics import relative_pose_tangent_errors, se3_log

#: median of chi2 with one degree of freedom
CHI2_1_MEDIAN = 0.454936423119572


def reference_jitter(stamps: np.ndarray, poses: np.ndarray, neighbours: int = 3) -> dict | None:
    """Per-axis s.d. of a reference trajectory's sample noise: ``{"rotation_rad": (3,),
    "translation_m": (3,), "samples": n}``, or None with fewer than ``4 neighbours + 1`` evenly
    spaced samples.

    ``stamps`` (N,) in s, ``poses`` (N, 4, 4) T_world,body at them (e.g. ``groundtruth.txt``).
    The samples are taken in time order (non-finite ones dropped). A sample is used when its
    ``2 neighbours`` neighbours lie within ``neighbours + 0.5`` median sample intervals of it on each
    side (no gap) at distinct times."""
    t = np.asarray(stamps, dtype=float).reshape(-1)
    P = np.asarray(poses, dtype=float)
    if P.shape != (t.shape[0], 4, 4):
        raise InputError(f"need poses ({t.shape[0]}, 4, 4) for {t.shape[0]} stamps, got {P.shape}")
    k = int(neighbours)
    if k < 2:
        raise InputError(f"neighbours must be at least 2 (a quadratic through them), got {neighbours}")
    finite = np.isfinite(t) & np.isfinite(P).all(axis=(1, 2))
    order = np.argsort(t[finite], kind="stable")
    t, P = t[finite][order], P[finite][order]
    if t.shape[0] < 4 * k + 1:
        return None
    dt = float(np.median(np.diff(t)))
    if not dt > 0:
        return None
    offsets = np.r_[np.arange(-k, 0), np.arange(1, k + 1)]  # (2k,)
    centre = np.arange(k, t.shape[0] - k)
    tt = t[centre[:, None] + offsets] - t[centre, None]  # (M, 2k) s
    # within reach on both sides, no repeated stamp (a quadratic needs three distinct times)
    ok = ((np.abs(tt) <= (k + 0.5) * dt).all(axis=1) & (np.sign(tt) == np.sign(offsets)).all(axis=1)
          & (np.diff(tt, axis=1) > 0).all(axis=1))
    centre, tt = centre[ok], tt[ok] / dt
    if centre.size < 2 * k:
        return None
    A = np.stack([np.ones_like(tt), tt, tt**2], axis=2)  # (M, 2k, 3)
    # weights of the neighbours in the fitted quadratic's value at the sample's own time
    w = (A @ np.linalg.inv(A.transpose(0, 2, 1) @ A))[:, :, 0]  # (M, 2k)
    scale = 1.0 + (w**2).sum(axis=1)
    Pi = P[centre]
    Rt = Pi[:, :3, :3].transpose(0, 2, 1)
    rel = np.einsum("mij,mnjk->mnik", invert_pose(Pi), P[centre[:, None] + offsets])  # T_i^-1 T_j
    rot = se3_log(rel.reshape(-1, 4, 4))[:, :3].reshape(len(centre), 2 * k, 3)
    r_rot = np.einsum("mn,mni->mi", w, rot)  # the sample itself is the identity in its own axes
    r_tr = np.einsum("mij,mj->mi", Rt, np.einsum("mn,mni->mi", w, P[centre[:, None] + offsets, :3, 3])
                     - Pi[:, :3, 3])

    def sd(r: np.ndarray) -> np.ndarray:
        return np.sqrt(np.median(r**2 / scale[:, None], axis=0) / CHI2_1_MEDIAN)

    return {"rotation_rad": sd(r_rot), "translation_m": sd(r_tr), "samples": int(centre.size)}


def pair_jitter_covariances(stamps: np.ndarray, rotation_sd: np.ndarray, ref_stamps: np.ndarray,
                            cur_stamps: np.ndarray) -> np.ndarray:
    """What the reference's rotation jitter (s.d. per axis, rad, e.g. :func:`reference_jitter`'s)
    adds (N, 6, 6; tangent ``[omega, v]``) to the error of each pair of frames at ``ref_stamps`` and
    ``cur_stamps`` (N,) measured against it: the reference at a frame is interpolated between its
    two samples ``a`` of the way (0..1), so it keeps ``(1 - a)^2 + a^2`` of a sample's variance,
    the pair the sum of its two frames'. Rotation block only (the translation jitter, a tenth of a
    millimetre on TUM's, is left out); the axes are the frames', as the pair's error's to first
    order. ``stamps`` (M,) are the reference's sample times, in any order."""
    t = np.sort(np.asarray(stamps, dtype=float).reshape(-1))

    def kept(q: np.ndarray) -> np.ndarray:
        hi = np.clip(np.searchsorted(t, q), 1, len(t) - 1)
        a = np.clip((q - t[hi - 1]) / np.maximum(t[hi] - t[hi - 1], 1e-12), 0.0, 1.0)
        return (1 - a) ** 2 + a**2

    share = kept(np.asarray(ref_stamps, dtype=float)) + kept(np.asarray(cur_stamps, dtype=float))
    out = np.zeros((share.shape[0], 6, 6))
    out[:, :3, :3] = np.diag(np.asarray(rotation_sd, dtype=float) ** 2) * share[:, None, None]
    return out


def axes_rotation(T_est: np.ndarray, T_true: np.ndarray, covs: np.ndarray) -> dict:
    """The fixed rotation ``d`` by which a reference's axes are turned against the estimates' that
    best explains the pairs' rotation errors: ``{"rotation_rad": d (3,), "standard_error_rad": (3,),
    "reduced_chi2": float, "pairs": n}``, ``d`` a rotation vector (rad) about the camera's axes.

    A reference whose poses are the camera's ``G`` times ``D^-1``, ``D = Exp(d)`` (its axes turned
    by ``D``, as an error of a hand-eye calibration turns them), reports each relative pose as
    ``D T D^-1``, so the rotation error of a pair (``Log(R_est^T R_true)``, rad, about the pair's
    reference frame's axes, right perturbation) is ``(R_true^T - I) d`` to first order in ``d`` and
    the pair's own error, about ``d x w`` for a turn ``w``. ``d`` is the generalized least-squares
    fit over the pairs ``T_est``, ``T_true`` (N, 4, 4) with the rotation blocks of ``covs`` (N, 6,
    6; tangent ``[omega, v]``); its standard errors take the pairs as independent and ``covs`` as
    right, scaled up by ``sqrt`` of the fit's reduced chi-square (``"reduced_chi2"``: the residuals'
    sum of squares under ``covs`` over ``3 n - 3``) where that exceeds 1, so covariances that
    understate the pairs' errors do not make ``d`` look surer than it is (never scaled down: a
    conservative ``covs`` keeps conservative errors). A component is observed only by turns
    about the other two axes: pairs that all turn about x leave ``d_x`` with a large standard
    error. The error a chain of ``k`` pairs gains from ``d`` grows with its net turn, while its
    covariance composed from independent pairs grows with ``sqrt(k)``. :class:`InputError` with
    fewer than two pairs or turns about one axis only."""
    T_est, T_true = np.asarray(T_est, dtype=float), np.asarray(T_true, dtype=float)
    covs = np.asarray(covs, dtype=float)
    if covs.shape != (T_est.shape[0], 6, 6) or T_est.shape[0] < 2:
        raise InputError(f"need two or more pairs with covariances (N, 6, 6), got {covs.shape} for {T_est.shape[0]}")
    e = relative_pose_tangent_errors(T_est, T_true)[:, :3]
    J = T_true[:, :3, :3].transpose(0, 2, 1) - np.eye(3)
    d, C, reduced = _rotation_gls(e, J, covs, "the pairs turn about one axis only: the rotation about it is not "
                                  "observed")
    return {"rotation_rad": d, "standard_error_rad": np.sqrt(np.diag(C)), "reduced_chi2": reduced,
            "pairs": int(T_est.shape[0])}


def _rotation_gls(e: np.ndarray, J: np.ndarray, covs: np.ndarray, unobserved: str
                  ) -> tuple[np.ndarray, np.ndarray, float]:
    """``(x, its covariance, reduced chi-square)`` of the generalized least-squares fit of the
    rotation errors ``e`` (N, 3) by ``J x`` (``J`` (N, 3, P)) under the rotation blocks of ``covs``
    (N, 6, 6); the covariance scaled up by the reduced chi-square where that exceeds 1, never
    down. :class:`InputError` (``unobserved``) for an ill-conditioned fit (its condition number
    taken as it is: the callers' parameters and regressors have sizes that keep it meaningful)."""
    W = np.linalg.inv(covs[:, :3, :3])
    H = np.einsum("nki,nkl,nlj->ij", J, W, J)
    g = np.einsum("nki,nkl,nl->i", J, W, e)
    with np.errstate(all="ignore"):
        observed = np.linalg.cond(H) <= 1e8  # not NaN (nothing observed) or large
    if not observed:
        raise InputError(unobserved)
    H_inv = np.linalg.inv(H)
    x = H_inv @ g
    r = e - np.einsum("nij,j->ni", J, x)
    reduced = float(np.einsum("ni,nij,nj->", r, W, r) / (e.size - x.size))
    return x, H_inv * max(1.0, reduced), reduced


def twist_change_response(T_est: np.ndarray, T_true: np.ndarray, covs: np.ndarray, ref_stamps: np.ndarray,
                          cur_stamps: np.ndarray) -> dict:
    """How the pairs' rotation errors follow the change of the camera's angular velocity:
    ``{"backward_s", "forward_s", "rotation_scale", "standard_error": (3,), "delay_s",
    "delay_standard_error_s", "reduced_chi2", "pairs", "changes", "errors"}``.

    ``w_k`` is pair ``k``'s true mean angular velocity (the rotation vector ``r_k`` of its
    ``T_true`` over its stamps' interval, rad/s). For each pair linked to a pair before it (ending
    at its reference frame) and after it (starting at its frame), the rotation error
    (``Log(R_est^T R_true)``, rad, about the pair's current frame's axes, as
    :func:`axes_rotation`'s) is fitted as ``a (w_k - R_k^T w_{k-1}) + c (w_{k+1} - w_k) + s r_k``
    (``R_k`` the pair's true rotation: every vector in the current frame) by generalized least
    squares under the rotation blocks of ``covs`` (N, 6, 6): ``a`` is ``"backward_s"``, ``c``
    ``"forward_s"`` (seconds), ``s`` ``"rotation_scale"`` (the share of each turn the estimates
    miss), standard errors (s, s, 1) as :func:`axes_rotation`'s.

    Images taken ``L`` seconds before their stamps (a delay against the reference) give ``a + c =
    L`` (``"delay_s"``, with its standard error), ``c`` about ``(dt - L) / (dt + L)`` of ``a``;
    turns estimated ``1 - s`` times their size give ``s`` alone (without its own term they would
    read as ``a = -c``). How ``a`` and ``c`` split is less sure than their sum: the reference's own
    jitter enters both the errors and the changes, raising ``a`` and lowering ``c`` by as much, and
    the split also depends on how rough the true motion is between the frames. ``"changes"``
    (n, 3) are the fitted pairs' changes of the angular velocity across them, ``(w_{k+1} - R_k^T
    w_{k-1}) / 2`` (rad/s), and ``"errors"`` (n, 3) their rotation errors (rad), for figures.
    :class:`InputError` with fewer than three linked pairs or changes about one axis only."""
    T_est, T_true = np.asarray(T_est, dtype=float), np.asarray(T_true, dtype=float)
    covs = np.asarray(covs, dtype=float)
    ref_stamps, cur_stamps = np.asarray(ref_stamps, dtype=float), np.asarray(cur_stamps, dtype=float)
    n = T_est.shape[0]
    if covs.shape != (n, 6, 6) or ref_stamps.shape != (n,) or cur_stamps.shape != (n,):
        raise InputError(f"need pairs (N, 4, 4) with covariances (N, 6, 6) and stamps (N,), got {covs.shape}, "
                         f"{ref_stamps.shape} and {cur_stamps.shape} for {n}")
    dt = cur_stamps - ref_stamps
    linked = np.zeros(n, bool)
    linked[1:-1] = (ref_stamps[1:-1] == cur_stamps[:-2]) & (cur_stamps[1:-1] == ref_stamps[2:])
    linked &= np.r_[False, dt[:-1] > 0] & (dt > 0) & np.r_[dt[1:] > 0, False]
    k = np.flatnonzero(linked)
    if len(k) < 3:
        raise InputError(f"need three or more pairs linked to a pair before and after them, got {len(k)}")
    r = se3_log(T_true)[:, :3]
    w = r / np.where(dt > 0, dt, 1.0)[:, None]
    before = np.einsum("nji,nj->ni", T_true[k, :3, :3], w[k - 1])  # R_k^T w_{k-1}: into the current frame
    e = relative_pose_tangent_errors(T_est[k], T_true[k])[:, :3]
    J = np.stack([w[k] - before, w[k + 1] - w[k], r[k]], axis=2)
    x, C, reduced = _rotation_gls(e, J, covs[k], "the angular velocity changes too little, or about one axis only")
    return {"backward_s": float(x[0]), "forward_s": float(x[1]), "rotation_scale": float(x[2]),
            "standard_error": np.sqrt(np.diag(C)), "delay_s": float(x[0] + x[1]),
            "delay_standard_error_s": float(np.sqrt(C[0, 0] + C[1, 1] + 2.0 * C[0, 1])),
            "reduced_chi2": reduced, "pairs": int(len(k)), "changes": 0.5 * (w[k + 1] - before), "errors": e}


def axes_transform(d: np.ndarray) -> np.ndarray:
    """``D`` (4, 4) of the rotation vector ``d`` (rad; :func:`axes_rotation`): a reference turned
    by ``d`` is turned back by taking its poses ``G`` to ``G D``, its relative poses ``T`` to
    ``D^-1 T D``."""
    D = np.eye(4)
    D[:3, :3] = gtsam.Rot3.Expmap(np.asarray(d, dtype=float)).matrix()
    return D
