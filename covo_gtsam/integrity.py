"""Per-pair integrity check without ground truth: two depth-free estimates of the same pair.

A pair's 3D-3D estimate uses the depth images of both frames. Each point's bearing (its pixel)
does not depend on depth, so the pair can also be estimated twice from reprojection alone:

* forward: the reference points ``X_ref`` (reference depth) projected into the current image,
  against the current points' bearings;
* backward: the current points ``X_cur`` (current depth) projected into the reference image,
  against the reference points' bearings.

Each uses the depth of one frame only, so a depth image with a gross or systematic error (e.g.
taken at another instant than its colour image during a fast turn) pulls the two apart. Both are
one Gauss-Newton step from the 3D-3D estimate ``T = T_ref,cur`` (right perturbation
``T Exp(xi)``, tangent ``[omega, v]``), which is enough at the small corrections a consistent
pair has: ``delta = H^-1 J^T W r`` with ``H = J^T W J``, ``W`` the inverse of the pixel noise plus
the projected covariance of the projected point. The statistic is
``q = max(delta_f^T H_f delta_f, delta_b^T H_b delta_b)``: how far each depth-free estimate lies
from the 3D-3D one in its own uncertainty. It is not chi2-distributed (the 3D-3D estimate shares
the points, and a one-sided reprojection fit with noisy 3-D sources is biased, errors in
variables), so :class:`IntegrityScale` takes its scale from the run itself.
"""

from __future__ import annotations

import bisect
from collections import deque
from dataclasses import dataclass

import cv2
import numpy as np

from .chi2 import CHI2_2_99, CHI2_6_MEDIAN
from .geometry import invert_pose, make_pose, skew

#: Degrees of freedom of the integrity statistic.
INTEGRITY_DOF = 6
#: A pair is lost when fewer than this share of its matches agree on one rigid motion in 3-D (the
#: outlier rejection's inliers) and fewer than this share of those that agree on one motion with one
#: frame's depth left out (:func:`depth_free_consensus`): a majority. A depth image that belongs to
#: another instant leaves a small consensus in 3-D on a grossly wrong motion (17 % on a wrong pose of
#: 20 deg) while the other frame's depth and the bearings agree on the true one; a fast motion lowers
#: both counts alike (docs/derivation.md, "The integrity check"). A pair kept below the first
#: majority counts in ``metrics.json``'s ``weak_consensus_pairs``.
MIN_CONSENSUS = 0.5


def below_majority(agreeing: int, of: int) -> bool:
    """Whether ``agreeing`` matches are fewer than :data:`MIN_CONSENSUS` of ``of``."""
    return agreeing < MIN_CONSENSUS * of


def per_span(statistic: float, intervals: int) -> float:
    """The integrity statistic of a pair ``intervals`` frame intervals long on the scale of one
    interval, ``q / sqrt(k)``: the depth-free and 3D-3D estimates disagree more over more
    intervals. On the clean keyframe pairs of the shared fr1_rpy frames the statistic's 90th
    percentile grows about as ``k^0.4`` (``k^0.45`` on frames 0-119, ``k^0.35`` on 120-239; its
    median as ``k^0.8``), so a flag at a fixed quality raises about as many false alarms over any
    span (docs/derivation.md, "The integrity check")."""
    return statistic / np.sqrt(max(intervals, 1))


@dataclass(frozen=True)
class IntegrityResult:
    """``statistic`` q (its scale and tail: :class:`IntegrityScale`), the forward and backward corrections
    ``delta_forward``/``delta_backward`` (6,) to ``T_ref,cur`` (tangent ``[omega, v]``, rad and m)
    and their covariances (6, 6)."""

    statistic: float
    delta_forward: np.ndarray
    delta_backward: np.ndarray
    cov_forward: np.ndarray
    cov_backward: np.ndarray

    def inflate(self, covariance: np.ndarray, quality: float) -> np.ndarray:
        """The covariance of a flagged pair: scaled by ``quality / median chi2(6)`` (the pair
        disagrees that many times more than the run's typical pair), plus :meth:`inflation`."""
        return covariance * max(1.0, quality / CHI2_6_MEDIAN) + self.inflation()

    def inflation(self) -> np.ndarray:
        """6x6 covariance that covers the disagreement at two standard deviations:
        ``4 (delta_f delta_f^T + delta_b delta_b^T)``. A pair whose depth of one frame is wrong has
        its 3D-3D estimate off by about the correction of the estimate that does not use that
        depth; one Gauss-Newton step undershoots that correction, hence the margin."""
        return 4.0 * (np.outer(self.delta_forward, self.delta_forward)
                      + np.outer(self.delta_backward, self.delta_backward))


def projection_jacobian(Y: np.ndarray, fx: float, fy: float) -> np.ndarray:
    """d(pixel)/dY (N, 2, 3) of the pinhole projection ``(fx X/Z, fy Y/Z)`` at camera-frame points Y."""
    x, y, z = Y[:, 0], Y[:, 1], Y[:, 2]
    J = np.zeros((Y.shape[0], 2, 3))
    J[:, 0, 0] = fx / z
    J[:, 0, 2] = -fx * x / z**2
    J[:, 1, 1] = fy / z
    J[:, 1, 2] = -fy * y / z**2
    return J


def _pixels(Y: np.ndarray, fx: float, fy: float) -> np.ndarray:
    return np.stack([fx * Y[:, 0] / Y[:, 2], fy * Y[:, 1] / Y[:, 2]], axis=1)


def _into_destination(T: np.ndarray, X_src: np.ndarray, forward: bool) -> np.ndarray:
    """Source points (N, 3) in the destination camera's frame: reference points mapped by ``T^-1``
    into the current frame (``forward``), else current points mapped by ``T`` (4x4 T_ref,cur) into
    the reference frame."""
    R, t = T[:3, :3], T[:3, 3]
    return (X_src - t) @ R if forward else X_src @ R.T + t  # R^T (X - t), or R X + t


def reprojection_system(T: np.ndarray, X_src: np.ndarray, Q_src: np.ndarray, X_dst: np.ndarray,
                        fx: float, fy: float, pixel_sigma: float, forward: bool):
    """Residuals (N, 2), Jacobians (N, 2, 6) with respect to the right perturbation of ``T`` and
    residual covariances (N, 2, 2) of the reprojection of ``X_src`` against the bearings of ``X_dst``.

    ``forward``: ``X_src`` are reference points, mapped by ``T^-1`` into the current frame;
    otherwise current points, mapped by ``T`` into the reference frame. ``T`` is 4x4 T_ref,cur;
    pixels are ``(fx x/z, fy y/z)`` (the principal point cancels in the residual).
    """
    R = T[:3, :3]
    Y = _into_destination(T, X_src, forward)
    dY = np.empty((len(X_src), 3, 6))
    if forward:
        dY[:, :, :3] = skew(Y)
        dY[:, :, 3:] = -np.eye(3)
        M = R.T
    else:
        dY[:, :, :3] = -R @ skew(X_src)
        dY[:, :, 3:] = R
        M = R
    Jp = projection_jacobian(Y, fx, fy)
    JpM = Jp @ M                          # d(pixel)/d(X_src), up to the sign
    r = _pixels(X_dst, fx, fy) - _pixels(Y, fx, fy)
    S = JpM @ Q_src @ JpM.transpose(0, 2, 1)
    S[:, 0, 0] += pixel_sigma**2
    S[:, 1, 1] += pixel_sigma**2
    return r, Jp @ dY, S


def _inv2(S: np.ndarray) -> np.ndarray:
    """Inverses of symmetric 2x2 matrices (N, 2, 2), closed form."""
    a, b, d = S[:, 0, 0], S[:, 0, 1], S[:, 1, 1]
    det = a * d - b * b
    W = np.empty_like(S)
    W[:, 0, 0], W[:, 1, 1] = d / det, a / det
    W[:, 0, 1] = W[:, 1, 0] = -b / det
    return W


def _gauss_newton_step(r: np.ndarray, J: np.ndarray, S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The weighted Gauss-Newton step ``H^-1 J^T W r`` (6,) and ``H^-1`` (6, 6)."""
    JtW = J.transpose(0, 2, 1) @ _inv2(S)
    H = (JtW @ J).sum(axis=0)
    b = (JtW @ r[:, :, None]).sum(axis=0)[:, 0]
    cov = np.linalg.inv(H)
    return cov @ b, cov


def depth_free_check(T: np.ndarray, X_ref: np.ndarray, X_cur: np.ndarray, Q_ref: np.ndarray, Q_cur: np.ndarray,
                     fx: float, fy: float, pixel_sigma: float) -> IntegrityResult:
    """The integrity statistic of a pair (module docstring). ``T``: 4x4 T_ref,cur; points (N, 3)
    in metres with covariances (N, 3, 3) in m^2 (the estimator's inputs); ``fx, fy`` in pixels;
    ``pixel_sigma`` the keypoints' pixel noise (px). Needs N >= 3 points in front of both cameras."""
    d_f, C_f = _gauss_newton_step(*reprojection_system(T, X_ref, Q_ref, X_cur, fx, fy, pixel_sigma, True))
    d_b, C_b = _gauss_newton_step(*reprojection_system(T, X_cur, Q_cur, X_ref, fx, fy, pixel_sigma, False))
    # each depth-free estimate against the 3D-3D one: a wrong depth image of one frame moves the
    # 3D-3D estimate away from the estimate that does not use it (and a depth scale error, which
    # the bearings cannot see, away from both)
    q = float(max(d_f @ np.linalg.solve(C_f, d_f), d_b @ np.linalg.solve(C_b, d_b)))
    return IntegrityResult(q, d_f, d_b, C_f, C_b)


#: Hypotheses of each perspective-n-point RANSAC of :func:`depth_free_consensus` at most (OpenCV's
#: adaptive stop ends it earlier): 99.9 % confidence of an all-inlier 4-point sample down to an
#: inlier share of about 0.2.
PNP_ITERATIONS = 4000


def reprojection_consensus(T: np.ndarray, X_ref: np.ndarray, X_cur: np.ndarray, Q_ref: np.ndarray, Q_cur: np.ndarray,
                           fx: float, fy: float, pixel_sigma: float) -> int:
    """How many matches the pose ``T`` (4x4 T_ref,cur) explains through their bearings with one frame's
    depth: the larger count of forward (``X_ref`` projected into the current image) and backward
    (``X_cur`` into the reference image) reprojections with ``r^T S^-1 r`` below chi2(2)'s 99 %
    quantile, ``S`` the depth-free check's residual covariance (pixel noise ``pixel_sigma`` plus the
    source point's projected covariance, :func:`reprojection_system`); a point that lands behind
    the camera does not count. Points (N, 3) in metres, covariances (N, 3, 3) m^2, ``fx, fy`` px."""
    T = np.asarray(T, dtype=float)
    best = 0
    for forward, X_src, Q_src, X_dst in ((True, X_ref, Q_ref, X_cur), (False, X_cur, Q_cur, X_ref)):
        in_front = _into_destination(T, X_src, forward)[:, 2] > 0
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            r, _, S = reprojection_system(T, X_src, Q_src, X_dst, fx, fy, pixel_sigma, forward)
            d2 = np.einsum("ni,nij,nj->n", r, _inv2(S), r)
        best = max(best, int(np.count_nonzero(in_front & np.isfinite(d2) & (d2 < CHI2_2_99))))
    return best


def depth_free_consensus(X_ref: np.ndarray, X_cur: np.ndarray, Q_ref: np.ndarray, Q_cur: np.ndarray,
                         fx: float, fy: float, pixel_sigma: float) -> int:
    """How many of a pair's matches agree on one motion without one frame's depth: the larger
    :func:`reprojection_consensus` of two perspective-n-point RANSAC poses (OpenCV's
    ``solvePnPRansac`` with 4-point AP3P samples), forward (the reference points ``X_ref`` against
    the current bearings; the current depth unused) and backward (``X_cur`` against the reference
    bearings). Points (N, 3) of all matches in metres, covariances (N, 3, 3) m^2, ``fx, fy`` px. 0
    with fewer than 5 matches or where no solution is found.

    A depth image that belongs to another instant leaves few matches agreeing on one rigid motion in
    3-D, on a wrong one, while the other frame's depth and the bearings agree on the true motion;
    a fast motion (blur, mismatches) lowers the counts of both alike, on the same motion."""
    if len(X_ref) < 5:
        return 0
    K = np.array([[fx, 0.0, 0.0], [0.0, fy, 0.0], [0.0, 0.0, 1.0]])
    threshold = float(np.sqrt(2.0 * CHI2_2_99) * pixel_sigma)  # the two keypoints' pixel noise
    best = 0
    for forward, X_src, X_dst in ((True, X_ref, X_cur), (False, X_cur, X_ref)):
        try:
            ok, rvec, tvec, _ = cv2.solvePnPRansac(
                np.ascontiguousarray(X_src, dtype=np.float64), np.ascontiguousarray(_pixels(X_dst, fx, fy)), K, None,
                iterationsCount=PNP_ITERATIONS, reprojectionError=threshold, confidence=0.999,
                flags=cv2.SOLVEPNP_AP3P)
        except cv2.error:  # a degenerate sample set: no solution
            continue
        if not ok:
            continue
        T_dst_src = make_pose(cv2.Rodrigues(rvec)[0], np.asarray(tvec, dtype=float).reshape(3))
        T = invert_pose(T_dst_src) if forward else T_dst_src  # T_ref,cur
        best = max(best, reprojection_consensus(T, X_ref, X_cur, Q_ref, Q_cur, fx, fy, pixel_sigma))
    return best


class IntegrityScale:
    """Online scale of the integrity statistic, learnt from the run itself (no ground truth).

    On real data the depth-free and 3D-3D estimates disagree more than the per-point model says
    (its depth errors are partly systematic), by a factor that depends on the sensor. The typical
    pair is taken as consistent: the scale is the median of the statistics of the last ``window``
    pairs (each as the odometry gives it: on the scale of one frame interval, :func:`per_span`) over
    the median of chi2(6), and :meth:`normalise` divides by it, so a pair at the run's running median
    (of the pairs up to it) reads chi2(6)'s median and a pair whose depth-free estimates disagree far more than the run's usual
    stands out. The first pairs of a run set the scale and are not flagged. Its tail is heavier than
    chi2(6)'s by construction: ``H`` whitens each depth-free estimate by its own covariance, while its
    difference from the 3D-3D estimate, which shares the points, varies almost along one direction
    (the translation along the optical axis), so ``q`` is nearly a scaled chi2(1). Under the per-point
    model alone the normalised statistic's 90 / 99 / 99.9 % quantiles are 21 / 45 / 73 (chi2(6):
    10.6 / 16.8 / 22.5), as on the clean shared fr1_rpy pairs (17 / 43; docs/derivation.md).
    """

    def __init__(self, window: int = 300) -> None:
        self._values: deque[float] = deque(maxlen=window)
        self._ascending: list[float] = []  # the same values, sorted: the medians without sorting each time

    def normalise(self, statistic: float) -> float:
        """The statistic divided by the run's scale (the median taken with this pair included);
        :meth:`add` makes the pair part of the run's scale."""
        if not np.isfinite(statistic):
            return float("inf")
        values = self._ascending.copy()
        bisect.insort(values, float(statistic))
        scale = _median(values) / CHI2_6_MEDIAN
        return statistic / scale if scale > 0 else 0.0

    def add(self, statistic: float) -> None:
        """Count a kept pair's statistic in the run's scale."""
        if np.isfinite(statistic):
            if len(self._values) == self._values.maxlen:  # the oldest value leaves the window
                del self._ascending[bisect.bisect_left(self._ascending, self._values[0])]
            self._values.append(float(statistic))
            bisect.insort(self._ascending, float(statistic))

    @property
    def scale(self) -> float:
        """Current scale (1 before any pair)."""
        return _median(self._ascending) / CHI2_6_MEDIAN if self._ascending else 1.0


def _median(ascending: list[float]) -> float:
    """The median of sorted values as ``np.median`` computes it: the middle value, or the mean
    ``(a + b) / 2`` of the middle two."""
    m = len(ascending) // 2
    return ascending[m] if len(ascending) % 2 else (ascending[m - 1] + ascending[m]) / 2
