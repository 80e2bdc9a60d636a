"""3-D points with covariances of one frame (:func:`prepare_frame`, computed once and reused for
the next pair).

* Depth registration: nearest-pixel depth at the *measured* keypoint (TUM depth is registered to
  the colour image); invalid when 0, outside ``[min_depth, max_depth]`` or off the image
  (:func:`lookup_depth`).
* Back-projection of the *undistorted* keypoint (:meth:`Camera.undistort`, :meth:`Camera.backproject`)
  and its 3x3 covariance (:meth:`PointNoiseModel.point_covariances`, surface angle from
  :func:`covo_gtsam.noise.surface_angles` on the depth image at the measured pixel).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from ..camera import Camera
from ..errors import InputError
from ..noise import PointNoiseModel, depth_lookup_variance, nearest_depth, surface_angles
from .matching import Features, detect
from .settings import FrontendConfig


def lookup_depth(
    depth_m: np.ndarray, uv: np.ndarray, min_depth: float = 0.5, max_depth: float = 5.0
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest-pixel depth at measured pixels ``uv`` (N, 2) in a depth image (H, W) in metres.

    Returns ``(z, valid)``: depth (N,) float64 (0 where invalid) and the mask (N,) of keypoints
    whose pixel is on the image and whose depth is finite, non-zero and in
    ``[min_depth, max_depth]``.
    """
    depth_m = np.asarray(depth_m)
    if depth_m.ndim != 2:
        raise InputError(f"depth image must be 2-D (H, W), got shape {depth_m.shape}")
    z, measured = nearest_depth(depth_m, np.asarray(uv, dtype=float).reshape(-1, 2))
    with np.errstate(invalid="ignore"):
        valid = measured & (z >= min_depth) & (z <= max_depth)
    return np.where(valid, z, 0.0), valid


@dataclass
class FrameData:
    """One frame's front-end data, computed once by :func:`prepare_frame` and reused per pair.

    Per keypoint i of :attr:`features` (N of them): ``valid[i]`` tells whether it has usable
    depth; ``points[i]`` (camera frame, metres), ``covariances[i]`` (m^2), ``depths[i]``,
    ``uv_undistorted[i]`` and ``theta[i]`` (surface angle, rad) are NaN (0 for depth/theta)
    where not valid. ``depth_offset`` is the depth image's capture time minus the colour image's
    (seconds; 0 for a synchronised camera). ``valid_index`` lists the valid keypoints and ``valid_features`` is the
    matching subset, both precomputed.
    """

    features: Features
    depth: np.ndarray = field(repr=False)
    points: np.ndarray = field(repr=False)
    covariances: np.ndarray = field(repr=False)
    valid: np.ndarray = field(repr=False)
    depths: np.ndarray = field(repr=False)
    uv_undistorted: np.ndarray = field(repr=False)
    theta: np.ndarray = field(repr=False)
    depth_offset: float = 0.0
    valid_index: np.ndarray = field(init=False, repr=False)
    valid_features: Features = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.valid_index = np.flatnonzero(self.valid)
        self.valid_features = self.features.subset(self.valid_index)

    @property
    def num_features(self) -> int:
        return len(self.features)

    @property
    def num_valid(self) -> int:
        """Number of keypoints with valid depth (those taking part in matching)."""
        return int(self.valid_index.shape[0])


def prepare_frame(
    grey: np.ndarray,
    depth_m: np.ndarray,
    camera: Camera,
    orb: cv2.Feature2D,
    noise_model: PointNoiseModel | None = None,
    cfg: FrontendConfig | None = None,
    use_surface_angle: bool = True,
    pixel_sigma_by_level: bool = False,
    depth_lookup_noise: bool = False,
) -> FrameData:
    """Features, registered depth, 3D points and their covariances of one frame.

    Args:
        grey: (H, W) uint8 image (see :func:`covo_gtsam.datasets.images.to_grey`).
        depth_m: (H, W) depth in metres registered to the colour image, 0 = invalid.
        camera: intrinsics and distortion of the colour camera.
        orb: detector from :func:`make_orb`.
        noise_model: per-point noise model (thesis defaults if None).
        cfg: front-end configuration (defaults if None); its depth range is applied.
        use_surface_angle: compute the surface angle from the depth image for the depth noise;
            otherwise theta = 0.
        pixel_sigma_by_level: scale each keypoint's pixel noise by ``cfg.scale_factor ** octave``
            (its ORB pyramid level); otherwise every keypoint has the model's pixel noise.
        depth_lookup_noise: add to each depth variance how much the depth image changes within the
            keypoint's pixel noise along each image axis (:func:`covo_gtsam.noise.depth_lookup_variance`):
            large beside depth edges.
    """
    cfg = cfg or FrontendConfig()
    noise_model = noise_model or PointNoiseModel()
    grey = np.asarray(grey)
    depth_m = np.asarray(depth_m)
    if grey.ndim != 2 or grey.dtype != np.uint8:
        raise InputError(f"grey image must be (H, W) uint8, got {grey.dtype} {grey.shape}; see to_grey()")
    if depth_m.shape != grey.shape:
        raise InputError(f"depth image shape {depth_m.shape} does not match the grey image {grey.shape}")
    if not np.issubdtype(depth_m.dtype, np.floating):
        raise InputError(f"depth image must be float metres, got {depth_m.dtype}; divide raw values by the depth scale")
    feats = detect(grey, orb)
    n = len(feats)
    z, valid = lookup_depth(depth_m, feats.uv, cfg.min_depth, cfg.max_depth)
    vi = np.flatnonzero(valid)
    uv_v = feats.uv[vi]
    z_v = z[vi]
    uv_u = camera.undistort(uv_v)
    theta_v = surface_angles(depth_m, uv_v, camera) if use_surface_angle else np.zeros(vi.shape[0])

    points = np.full((n, 3), np.nan)
    covs = np.full((n, 3, 3), np.nan)
    uv_und = np.full((n, 2), np.nan)
    theta = np.zeros(n)
    if vi.shape[0]:
        points[vi] = camera.backproject(uv_u, z_v)
        scale = cfg.scale_factor ** feats.octave[vi] if pixel_sigma_by_level else 1.0
        lookup = 0.0
        if depth_lookup_noise:
            s = np.broadcast_to(np.asarray(scale, dtype=float), z_v.shape)
            zero = np.zeros_like(s)
            lookup = depth_lookup_variance(depth_m, uv_v, np.stack([np.stack([noise_model.pixel.sigma_u * s, zero], 1),
                                                                     np.stack([zero, noise_model.pixel.sigma_v * s], 1)]))
        covs[vi] = noise_model.point_covariances(camera, uv_u, z_v, theta_v, scale, lookup)
        uv_und[vi] = uv_u
        theta[vi] = theta_v
    return FrameData(
        features=feats, depth=depth_m, points=points, covariances=covs, valid=valid,
        depths=z, uv_undistorted=uv_und, theta=theta,
    )
