"""Front-end settings: :class:`FrontendConfig` (ORB values of the thesis's Table A.2, matching,
outlier rejection, depth range), the image-size check of ORB's pyramid and patch
(:meth:`FrontendConfig.check_image_size`) and the ORB detector of a configuration (:func:`make_orb`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import cv2

from ..chi2 import CHI2_3_99
from ..choices import OutlierRejection
from ..errors import ConfigError
from ..validation import check_settings, choice, integer, number

OUTLIER_REJECTIONS = ("rigid3d", "homography", "none")
#: chi-square(3) 99 % quantile: default gate of the Mahalanobis inlier test.
CHI2_3DOF_99 = CHI2_3_99  # the rigid RANSAC's default gate (covo_gtsam.chi2)
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
    """Front-end settings (ORB values follow the thesis's Table A.2); each field declares its
    default, unit, range and meaning, and is checked on construction (:class:`ConfigError` naming
    it as ``frontend.<name>``). The upper limits keep OpenCV and the RANSAC within memory; whether
    the pyramid and patch fit a given image size is checked by :meth:`check_image_size`."""

    section: ClassVar[str] = "frontend"

    n_features: int = integer(1000, "ORB keypoints per image at most", 1, MAX_FEATURES, "keypoints")
    # OpenCV's ORB: scaleFactor < 1 fails, 1 finds nothing; above 2 levels skip pixels (aliasing).
    scale_factor: float = number(1.2, "ORB pyramid scale between levels", "ratio", above=1.0, maximum=2.0)
    n_levels: int = integer(8, "ORB pyramid levels", 1, MAX_LEVELS, "levels")
    fast_threshold: int = integer(20, "FAST corner threshold of ORB", 0, 255, "grey levels")
    patch_size: int = integer(31, "ORB patch size; also its edge threshold (keypoints this far from the border)",
                              2, MAX_PATCH_SIZE, "px")
    wta_k: int = integer(2, "points compared per ORB descriptor element (OpenCV's WTA_K)", values=(2, 3, 4))
    keep_ratio: float = number(0.75, "fraction of the cross-checked matches kept, best Hamming distances first",
                               "fraction", maximum=1.0)
    outlier_rejection: OutlierRejection = choice(OutlierRejection.RIGID3D, "outlier rejection of the matched pairs",
                                                 OutlierRejection)
    ransac_px: float = number(10.0, "homography RANSAC reprojection threshold", "px")
    ransac_iterations: int = integer(RANSAC_ITERATIONS, "RANSAC hypotheses (rigid3d) / maximum iterations (homography)",
                                     1, MAX_RANSAC_ITERATIONS, "hypotheses")
    ransac_chi2: float = number(CHI2_3DOF_99, "gate of the rigid3d inlier test r^T (Q_ref + R Q_cur R^T)^-1 r "
                                "(chi-square, 3 dof; default its 99 % quantile)", "chi²(3)")
    seed: int = integer(0, "seed of the rigid3d RANSAC (a fresh np.random.default_rng(seed) per pair)", 0)
    min_depth: float = number(0.5, "nearest valid depth", "m", "non-negative")
    max_depth: float = number(5.0, "farthest valid depth", "m", finite=False)
    min_pairs: int = integer(30, "fewest point pairs a frame pair needs (checked by the caller: the odometry "
                             "loses the frame)", 3, unit="pairs")
    max_hamming: int | None = integer(None, "absolute cut on the Hamming distance, after keep_ratio (unset: none)",
                                      0, unit="bits", optional=True)

    def __post_init__(self) -> None:
        check_settings(self, self.section)
        if not self.min_depth < self.max_depth:
            raise ConfigError(
                f"frontend depth range needs 0 <= min_depth < max_depth, got [{self.min_depth!r}, {self.max_depth!r}]")

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
