"""Feature front end, one module per stage::

    images -> features -> matches -> 3-D points with covariances -> RANSAC -> point pairs

1. Images: decoded by the dataset readers (:mod:`covo_gtsam.datasets`), which hand the front end a
   grey uint8 image and a depth image in metres registered to it; not part of this package.
2. Features (:mod:`~covo_gtsam.frontend.matching`, :func:`detect`): ORB keypoints and descriptors
   on the grey image, with the parameters of :class:`FrontendConfig` (thesis Table A.2,
   :mod:`~covo_gtsam.frontend.settings`, :func:`make_orb`).
3. Matches (:mod:`~covo_gtsam.frontend.matching`, :func:`match`): brute-force Hamming matching with
   cross-check among keypoints with valid depth (``np.bitwise_count`` (a 16-bit lookup table on
   numpy < 2) on XORed uint64 descriptor words; same matches as
   ``cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)``), then the best ``keep_ratio`` by distance.
   Given a predicted motion (the odometry's constant-velocity prediction) and the camera, only
   keypoints near their predicted pixel are compared (:func:`guided_cross_check`), with a
   fall-back to all pairs when the prediction was wrong (:func:`associate_frames`).
4. 3-D points with covariances (:mod:`~covo_gtsam.frontend.points`, :func:`prepare_frame`):
   nearest-pixel depth at the *measured* keypoint (:func:`lookup_depth`), back-projection of the
   *undistorted* keypoint and its 3x3 covariance from the point noise model.
5. RANSAC (:mod:`~covo_gtsam.frontend.ransac`): ``"rigid3d"`` (default) RANSAC of a rigid transform
   over 3-point samples with a Mahalanobis inlier test using the point covariances
   (:func:`ransac_rigid3d`), ``"homography"`` (the thesis's C++ code: ``cv2.findHomography``
   RANSAC at ``ransac_px``, :func:`ransac_homography`) or ``"none"``.
6. Point pairs (:mod:`~covo_gtsam.frontend.pairs`, :func:`associate_frames`): the inlier pairs of
   3-D points, their covariances and pixels (:class:`PointPairs`).

Per frame, :func:`prepare_frame` runs stages 2 and 4 once (:class:`FrameData`, reused for the next
pair); per frame pair, :func:`associate_frames` runs stages 3, 5 and 6.

Direction: ``X_ref`` are points in the reference (earlier) frame k, ``X_cur`` in the current frame
k+1; the transform fitted by the rigid RANSAC is ``T_ref,cur`` with ``X_ref ≈ R X_cur + t``, the
convention of :func:`covo_gtsam.estimator.estimate_relative_pose`.

The front end imports no GTSAM (the transfer maths of the RANSAC is :mod:`covo_gtsam.transfer`).
"""

from .matching import (
    DESCRIPTOR_BYTES,
    GUIDED_CELL_PX,
    MATCH_BLOCK_ENTRIES,
    Features,
    cross_check_matches,
    detect,
    guided_cross_check,
    hamming_distances,
    keep_best,
    match,
)
from .pairs import GUIDED_MIN_SHARE, PointPairs, associate_frames, predicted_pixels
from .points import FrameData, lookup_depth, prepare_frame
from .ransac import (
    RANSAC_BATCH,
    RANSAC_CHUNK,
    RANSAC_CONFIDENCE,
    RansacResult,
    ransac_homography,
    ransac_rigid3d,
    required_samples,
    sample_triples,
)
from .settings import (
    CHI2_3DOF_99,
    MAX_FEATURES,
    MAX_LEVELS,
    MAX_PATCH_SIZE,
    MAX_RANSAC_ITERATIONS,
    OUTLIER_REJECTIONS,
    RANSAC_ITERATIONS,
    FrontendConfig,
    make_orb,
)

__all__ = [
    # settings
    "FrontendConfig", "make_orb", "OUTLIER_REJECTIONS", "CHI2_3DOF_99", "RANSAC_ITERATIONS", "MAX_FEATURES",
    "MAX_LEVELS", "MAX_PATCH_SIZE", "MAX_RANSAC_ITERATIONS",
    # features and matches
    "Features", "detect", "hamming_distances", "cross_check_matches", "keep_best", "match", "guided_cross_check",
    "DESCRIPTOR_BYTES", "MATCH_BLOCK_ENTRIES", "GUIDED_CELL_PX",
    # 3-D points
    "FrameData", "prepare_frame", "lookup_depth",
    # RANSAC
    "RansacResult", "ransac_rigid3d", "ransac_homography", "required_samples", "sample_triples", "RANSAC_CHUNK",
    "RANSAC_BATCH", "RANSAC_CONFIDENCE",
    # point pairs
    "PointPairs", "associate_frames", "predicted_pixels", "GUIDED_MIN_SHARE",
]
