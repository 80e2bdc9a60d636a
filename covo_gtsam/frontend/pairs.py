"""Point pairs of a frame pair (:func:`associate_frames`): matches among the keypoints with valid
depth, then outlier rejection by ``FrontendConfig.outlier_rejection``. Given a predicted motion
(the odometry's constant-velocity prediction) and the camera, only keypoints near their predicted
pixel are compared (:func:`~covo_gtsam.frontend.matching.guided_cross_check`), with a fall-back to
all pairs when the prediction was wrong.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..camera import Camera
from .matching import GUIDED_CELL_PX, guided_cross_check, keep_best, match
from .points import FrameData
from .ransac import ransac_homography, ransac_rigid3d
from .settings import FrontendConfig

#: Guided matches are kept when at least this share of them are inliers (and ``2 * min_pairs``);
#: else the frames are matched again over all pairs (:func:`associate_frames`).
GUIDED_MIN_SHARE = 0.5


@dataclass
class PointPairs:
    """Matched 3D point pairs of a reference frame k and a current frame k+1 (inliers only).

    Attributes:
        X_ref, X_cur: (N, 3) camera-frame points (metres) in frames k and k+1.
        Q_ref, Q_cur: (N, 3, 3) their covariances (m^2).
        uv_ref, uv_cur: (N, 2) measured (distorted) pixels.
        idx_ref, idx_cur: (N,) indices into the frames' :attr:`FrameData.features`.
        distances: (N,) Hamming distances of the matches.
        num_matches: matches after cross-check, ``keep_ratio`` and ``max_hamming``, before
            outlier rejection.
        num_inliers: pairs kept by outlier rejection (= N).
        method: the outlier rejection used.
        T_init: 4x4 ``T_ref,cur`` of the rigid3d RANSAC refit (the prior, if any, for other
            methods); a good ``initial`` for :func:`covo_gtsam.estimator.estimate_relative_pose`.
        match_ref, match_cur: (num_matches,) indices into the frames' features of every match,
            before outlier rejection.
    """

    X_ref: np.ndarray
    X_cur: np.ndarray
    Q_ref: np.ndarray
    Q_cur: np.ndarray
    uv_ref: np.ndarray
    uv_cur: np.ndarray
    idx_ref: np.ndarray
    idx_cur: np.ndarray
    num_matches: int
    num_inliers: int
    distances: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint16))
    method: str = "none"
    T_init: np.ndarray | None = None
    match_ref: np.ndarray = field(default_factory=lambda: np.zeros(0, np.intp))
    match_cur: np.ndarray = field(default_factory=lambda: np.zeros(0, np.intp))

    def __len__(self) -> int:
        return int(self.X_ref.shape[0])


def predicted_pixels(ref: FrameData, prior: np.ndarray, camera: Camera) -> np.ndarray:
    """Undistorted pixels (valid keypoints of ``ref``, 2) where ``ref``'s points appear in the current
    image under the predicted ``prior`` (4x4 ``T_ref,cur``); NaN for points not in front of the camera."""
    T = np.asarray(prior, dtype=float)
    X = (ref.points[ref.valid_index] - T[:3, 3]) @ T[:3, :3]  # R^T (X_ref - t)
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.stack([camera.fx * X[:, 0] / X[:, 2] + camera.cx, camera.fy * X[:, 1] / X[:, 2] + camera.cy], axis=1)
    uv[~(X[:, 2] > 1e-6)] = np.nan
    return uv


def associate_frames(
    ref: FrameData, cur: FrameData, cfg: FrontendConfig | None = None, prior: np.ndarray | None = None,
    camera: Camera | None = None,
) -> PointPairs:
    """Point pairs of a reference frame k and the current frame k+1.

    Only keypoints with valid depth are matched (cross-checked Hamming, best ``keep_ratio``,
    optional ``max_hamming``); outliers are then rejected by ``cfg.outlier_rejection``.
    ``prior`` (4x4 predicted ``T_ref,cur``, optional) is an extra rigid-RANSAC hypothesis and,
    with the other outlier rejections, the initial guess ``T_init`` of the pose.

    With ``prior`` and the ``camera`` of the frames (and an outlier rejection other than
    ``"none"``), the matching is guided: a reference keypoint is compared only with the current
    keypoints near where ``prior`` puts it (:func:`predicted_pixels`,
    :func:`~covo_gtsam.frontend.matching.guided_cross_check`, cells of
    :data:`~covo_gtsam.frontend.matching.GUIDED_CELL_PX`). When the prediction was wrong (fewer
    than ``2 * min_pairs`` inliers, or fewer than :data:`GUIDED_MIN_SHARE` of the matches), the
    frames are matched again over all pairs and the result with more inliers is kept.
    """
    cfg = cfg or FrontendConfig()
    hamming2 = cfg.wta_k > 2
    if prior is not None and camera is not None and cfg.outlier_rejection != "none":
        ia, ib, dist = guided_cross_check(ref.valid_features, predicted_pixels(ref, prior, camera),
                                          cur.valid_features, cur.uv_undistorted[cur.valid_index],
                                          GUIDED_CELL_PX, hamming2)
        keep = keep_best(dist, cfg.keep_ratio, cfg.max_hamming)
        guided = _matched_pairs(ref, cur, cfg, prior, ia[keep], ib[keep], dist[keep])
        if guided.num_inliers >= max(2 * cfg.min_pairs, GUIDED_MIN_SHARE * guided.num_matches):
            return guided
    else:
        guided = None
    ia, ib, dist = match(ref.valid_features, cur.valid_features, cfg.keep_ratio, cfg.max_hamming, hamming2=hamming2)
    pairs = _matched_pairs(ref, cur, cfg, prior, ia, ib, dist)
    return guided if guided is not None and guided.num_inliers > pairs.num_inliers else pairs


def _matched_pairs(ref: FrameData, cur: FrameData, cfg: FrontendConfig, prior: np.ndarray | None, ia: np.ndarray,
                   ib: np.ndarray, dist: np.ndarray) -> PointPairs:
    """:func:`associate_frames` after matching: the matches ``(ia, ib, dist)`` (indices into the
    frames' valid features) through the outlier rejection."""
    idx_ref = ref.valid_index[ia]
    idx_cur = cur.valid_index[ib]
    num_matches = int(idx_ref.shape[0])
    X_ref, X_cur = ref.points[idx_ref], cur.points[idx_cur]
    Q_ref, Q_cur = ref.covariances[idx_ref], cur.covariances[idx_cur]
    T_init = prior
    if cfg.outlier_rejection == "rigid3d":
        res = ransac_rigid3d(X_ref, X_cur, Q_ref, Q_cur, cfg.ransac_iterations, cfg.ransac_chi2, cfg.seed,
                             prior=prior)
        keep = res.inliers
        T_init = res.T if res.num_inliers >= 3 else None
    elif cfg.outlier_rejection == "homography":
        # Undistorted pixels: a homography only models undistorted image motion.
        keep = ransac_homography(ref.uv_undistorted[idx_ref], cur.uv_undistorted[idx_cur], cfg.ransac_px,
                                 cfg.ransac_iterations)
    else:
        keep = np.ones(num_matches, bool)
    return PointPairs(
        X_ref=X_ref[keep], X_cur=X_cur[keep], Q_ref=Q_ref[keep], Q_cur=Q_cur[keep],
        uv_ref=ref.features.uv[idx_ref[keep]], uv_cur=cur.features.uv[idx_cur[keep]],
        idx_ref=idx_ref[keep], idx_cur=idx_cur[keep], num_matches=num_matches,
        num_inliers=int(np.count_nonzero(keep)), distances=dist[keep], method=cfg.outlier_rejection,
        T_init=T_init, match_ref=idx_ref, match_cur=idx_cur,
    )
