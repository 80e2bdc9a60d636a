"""Front-end settings: :class:`FrontendConfig` (ORB values of the thesis's Table A.2, matching,
outlier rejection, depth range), the image-size check of ORB's pyramid and patch
(:meth:`FrontendConfig.check_image_size`) and the ORB detector of a configuration (:func:`make_orb`).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2

from ..errors import ConfigError
from ..validation import check_choice, check_int, check_real, is_int, is_real

OUTLIER_REJECTIONS = ("rigid3d", "homography", "none")
#: chi-square(3) 99 % quantile: default gate of the Mahalanobis inlier test.
CHI2_3DOF_99 = 11.345
#: Default RANSAC hypotheses / iterations: ``FrontendConfig.ransac_iterations`` and the default of
#: :func:`~covo_gtsam.frontend.ransac.ransac_rigid3d` and
#: :func:`~covo_gtsam.frontend.ransac.ransac_homography`.
RANSAC_ITERATIONS = 200
#: Upper limits of the front-end settings (memory: ORB reserves ``n_features`` keypoints, the
#: rigid RANSAC draws all its samples at once; a patch must fit in the image, see
#: :meth:`FrontendConfig.check_image_size`).
MAX_FEATURES = 1_000_000
MAX_LEVELS = 64
MAX_PATCH_SIZE = 1024
MAX_RANSAC_ITERATIONS = 1_000_000


@dataclass(frozen=True)
class FrontendConfig:
    """Front-end settings; ORB values follow the thesis's Table A.2.

    Attributes:
        n_features, scale_factor, n_levels, fast_threshold, patch_size, wta_k: ORB parameters
            (``edgeThreshold`` = ``patch_size``; Harris score).
        keep_ratio: fraction of the cross-checked matches kept, best Hamming distances first.
        outlier_rejection: ``"rigid3d"``, ``"homography"`` or ``"none"``.
        ransac_px: homography RANSAC reprojection threshold (pixels).
        ransac_iterations: RANSAC hypotheses (rigid3d) / maximum iterations (homography).
        ransac_chi2: gate of the rigid3d inlier test, ``r^T (Q_ref + R Q_cur R^T)^-1 r``
            (chi-square with 3 dof; default its 99 % quantile).
        seed: seed of the rigid3d RANSAC; each call uses a fresh ``np.random.default_rng(seed)``.
        min_depth, max_depth: valid depth range (metres).
        min_pairs: fewest point pairs a frame pair needs (checked by the caller, e.g. odometry).
        max_hamming: optional absolute cut on the Hamming distance, applied after ``keep_ratio``.

    Every value is type- and range-checked (:class:`ConfigError` naming the field): integers
    must be integers, numbers real numbers (not booleans); ``1 < scale_factor <= 2``,
    ``0 <= fast_threshold <= 255``, ``2 <= patch_size``, and upper limits (:data:`MAX_FEATURES`,
    :data:`MAX_LEVELS`, :data:`MAX_PATCH_SIZE`, :data:`MAX_RANSAC_ITERATIONS`) that keep OpenCV
    and the RANSAC within memory. Whether the pyramid and patch fit a given image size is checked
    by :meth:`check_image_size`.
    """

    n_features: int = 1000
    scale_factor: float = 1.2
    n_levels: int = 8
    fast_threshold: int = 20
    patch_size: int = 31
    wta_k: int = 2
    keep_ratio: float = 0.75
    outlier_rejection: str = "rigid3d"
    ransac_px: float = 10.0
    ransac_iterations: int = RANSAC_ITERATIONS
    ransac_chi2: float = CHI2_3DOF_99
    seed: int = 0
    min_depth: float = 0.5
    max_depth: float = 5.0
    min_pairs: int = 30
    max_hamming: int | None = None

    def __post_init__(self) -> None:
        for name, lo, hi in (("n_features", 1, MAX_FEATURES), ("n_levels", 1, MAX_LEVELS),
                             ("fast_threshold", 0, 255), ("patch_size", 2, MAX_PATCH_SIZE),
                             ("ransac_iterations", 1, MAX_RANSAC_ITERATIONS), ("min_pairs", 3, None),
                             ("seed", 0, None)):
            check_int(f"frontend.{name}", getattr(self, name), lo, hi)
        if not (is_int(self.wta_k) and self.wta_k in (2, 3, 4)):
            raise ConfigError(f"frontend.wta_k must be 2, 3 or 4, got {self.wta_k!r}")
        # OpenCV's ORB: scaleFactor < 1 fails, 1 finds nothing; above 2 levels skip pixels (aliasing).
        if not (is_real(self.scale_factor) and 1.0 < self.scale_factor <= 2.0):
            raise ConfigError(f"frontend.scale_factor must be a number > 1 and <= 2, got {self.scale_factor!r}")
        if not (is_real(self.keep_ratio) and 0.0 < self.keep_ratio <= 1.0):
            raise ConfigError(f"frontend.keep_ratio must be a number in (0, 1], got {self.keep_ratio!r}")
        check_choice("frontend.outlier_rejection", self.outlier_rejection, OUTLIER_REJECTIONS)
        for name in ("ransac_px", "ransac_chi2"):
            check_real(f"frontend.{name}", getattr(self, name), "positive")
        check_real("frontend.min_depth", self.min_depth, "non-negative")
        check_real("frontend.max_depth", self.max_depth, "positive", finite=False)
        if not self.min_depth < self.max_depth:
            raise ConfigError(
                f"frontend depth range needs 0 <= min_depth < max_depth, got [{self.min_depth!r}, {self.max_depth!r}]")
        if self.max_hamming is not None:
            check_int("frontend.max_hamming", self.max_hamming, 0)

    def check_image_size(self, width: int, height: int) -> None:
        """Raise :class:`ConfigError` when ORB with these settings cannot work on ``width`` x
        ``height`` images: the smallest pyramid level, ``1 / scale_factor ** (n_levels - 1)`` of
        the image, must keep at least one pixel (OpenCV fails otherwise), and keypoints, which
        ORB keeps ``patch_size`` pixels (its edge threshold) from the border, need
        ``2 * patch_size < min(width, height)``."""
        short = min(int(width), int(height))
        shrink = float(self.scale_factor) ** (int(self.n_levels) - 1)
        if shrink > short:
            raise ConfigError(
                f"frontend.n_levels {self.n_levels} with frontend.scale_factor {self.scale_factor:g} shrinks the "
                f"smallest ORB pyramid level of {width}x{height} images below one pixel "
                f"(scale_factor ** (n_levels - 1) = {shrink:.4g} must be <= {short})")
        if 2 * self.patch_size >= short:
            raise ConfigError(
                f"frontend.patch_size {self.patch_size} leaves no room for keypoints in {width}x{height} images "
                f"(ORB keeps them patch_size pixels from the border; needs 2 * patch_size < {short})")


def make_orb(cfg: FrontendConfig | None = None) -> cv2.ORB:
    """``cv2.ORB`` with the configuration's parameters (Harris score, ``edgeThreshold = patch_size``)."""
    cfg = cfg or FrontendConfig()
    return cv2.ORB_create(
        nfeatures=int(cfg.n_features),
        scaleFactor=float(cfg.scale_factor),
        nlevels=int(cfg.n_levels),
        edgeThreshold=int(cfg.patch_size),
        firstLevel=0,
        WTA_K=int(cfg.wta_k),
        scoreType=cv2.ORB_HARRIS_SCORE,
        patchSize=int(cfg.patch_size),
        fastThreshold=int(cfg.fast_threshold),
    )
