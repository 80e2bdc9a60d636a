"""Per-point uncertainty: conic-ray pixel noise plus the Kinect depth-noise model.

Each 3D point measured by an RGB-D camera is ``X = F_bp(u, v, Z)`` (4.3). Its covariance in the
camera frame (metres squared) is the first-order propagation (4.6), with the Jacobian the right
way round::

    Q_xyz = J_bp Q_uvz J_bp^T,    Q_uvz = diag(sigma_u^2, sigma_v^2, sigma_Z(Z, theta)^2)

where ``J_bp = d(X, Y, Z)/d(u, v, Z)`` (4.5). ``theta`` is the angle (radians) between the
surface normal and the viewing ray; 0 when unknown.

The models are small dataclasses so that another sensor's model can be plugged in: anything with
``sigma(z, theta)`` works as a depth model and anything with ``sigma(theta)`` (pixels) as a
lateral model.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from .camera import Camera
from .errors import InputError
from .geometry import cross

_HALF_PI = np.pi / 2.0
#: Angles are clipped below 90 deg so the hyperbolic terms stay finite (radians).
MAX_THETA = np.deg2rad(89.0)


class DepthModel(Protocol):
    def sigma(self, z: np.ndarray, theta: np.ndarray | float = 0.0) -> np.ndarray:
        """Axial standard deviation (metres) at depth ``z`` (metres) and surface angle ``theta``."""


@dataclass(frozen=True)
class PixelNoise:
    """Conic-ray pixel noise: isotropic Gaussian on the image plane, standard deviations in pixels."""

    sigma_u: float = 8.0
    sigma_v: float = 8.0


@dataclass(frozen=True)
class KinectAxialNoise:
    """Kinect v1 axial (depth) noise of Nguyen, Izadi and Lovell (2012), thesis (4.7)/(4.8).

    ``sigma_Z = a + b (Z - z0)^2`` metres, plus ``c / sqrt(Z) * theta^2 / (pi/2 - theta)^2``
    for ``theta > theta_max`` (60 deg). Below 10 deg the 10-60 deg fit is used unchanged.

    ``scale`` multiplies the whole ``sigma_Z`` (1: the published model). On the shared TUM
    frames the depth errors that matter for the pose are larger than the model says, and partly
    systematic, so :class:`~covo_gtsam.config.NoiseConfig` scales it (``depth_sigma_scale``).

    The model is defined for measured depths ``Z > 0`` only: zero, negative or non-finite depths
    are no measurement (a depth camera reports 0; the front end drops such keypoints) and raise
    :class:`~covo_gtsam.errors.InputError`.
    """

    a: float = 0.0012
    b: float = 0.0019
    z0: float = 0.4
    c: float = 0.0001
    theta_max: float = np.deg2rad(60.0)
    scale: float = 1.0

    def sigma(self, z: np.ndarray, theta: np.ndarray | float = 0.0) -> np.ndarray:
        z = np.asarray(z, dtype=float)
        bad = ~(np.isfinite(z) & (z > 0))
        if np.any(bad):
            raise InputError(
                f"depth must be positive and finite (metres), got {int(np.count_nonzero(bad))} invalid "
                f"value(s), e.g. {float(z[bad].flat[0])!r}; invalid depths are no measurement and have no noise")
        theta = np.minimum(np.broadcast_to(np.asarray(theta, dtype=float), z.shape), MAX_THETA)
        s = self.a + self.b * (z - self.z0) ** 2
        steep = theta > self.theta_max
        if not np.any(steep):
            return self.scale * np.asarray(s)
        th = np.where(steep, theta, 0.0)  # the extra term only where it applies
        extra = self.c / np.sqrt(z) * th**2 / (_HALF_PI - th) ** 2
        return self.scale * np.where(steep, s + extra, s)


@dataclass(frozen=True)
class KinectLateralNoise:
    """Kinect v1 lateral noise (4.9): ``sigma_L = a + b * theta / (pi/2 - theta)`` pixels."""

    a: float = 0.8
    b: float = 0.035

    def sigma(self, theta: np.ndarray | float = 0.0) -> np.ndarray:
        theta = np.minimum(np.asarray(theta, dtype=float), MAX_THETA)
        return self.a + self.b * theta / (_HALF_PI - theta)


@dataclass(frozen=True)
class PointNoiseModel:
    """Everything needed to turn pixel + depth measurements into 3x3 point covariances.

    ``lateral`` (optional) adds the depth image's lateral noise to the pixel variance, for a
    registration error between colour and depth; the thesis leaves it out (``None``).
    """

    pixel: PixelNoise = PixelNoise()
    depth: DepthModel = KinectAxialNoise()
    lateral: KinectLateralNoise | None = None

    def uvz_covariances(
        self, z: np.ndarray, theta: np.ndarray | float = 0.0, pixel_scale: np.ndarray | float = 1.0,
        lookup_variance: np.ndarray | float = 0.0,
    ) -> np.ndarray:
        """Diagonal ``Q_uvz`` (N, 3, 3) of (4.10): pixel variances (px^2) and depth variance (m^2).

        ``pixel_scale`` multiplies the pixel standard deviations per point, e.g. the ORB pyramid
        scale ``scale_factor ** octave`` of each keypoint (a keypoint found on level L is
        localised to about ``scale_factor ** L`` full-resolution pixels). ``lookup_variance`` (m^2,
        per point) is added to the depth variance: the depth the image holds around the keypoint
        (:func:`depth_lookup_variance`).
        """
        z = np.asarray(z, dtype=float)
        n = z.shape[0]
        s2 = np.broadcast_to(np.asarray(pixel_scale, dtype=float) ** 2, (n,))
        var_u = self.pixel.sigma_u**2 * s2
        var_v = self.pixel.sigma_v**2 * s2
        if self.lateral is not None:
            lat = np.broadcast_to(self.lateral.sigma(theta), (n,)) ** 2
            var_u = var_u + lat
            var_v = var_v + lat
        Q = np.zeros((n, 3, 3))
        Q[:, 0, 0] = var_u
        Q[:, 1, 1] = var_v
        Q[:, 2, 2] = self.depth.sigma(z, theta) ** 2 + lookup_variance
        return Q

    def point_covariances(
        self, camera: Camera, uv: np.ndarray, z: np.ndarray, theta: np.ndarray | float = 0.0,
        pixel_scale: np.ndarray | float = 1.0, lookup_variance: np.ndarray | float = 0.0,
    ) -> np.ndarray:
        """Camera-frame covariances ``Q_xyz`` (N, 3, 3) in m^2 of points at undistorted ``uv``, depth ``z``.

        ``pixel_scale``: per-point factor on the pixel standard deviations (see :meth:`uvz_covariances`).
        """
        J = camera.backprojection_jacobian(uv, z)
        return propagate(J, self.uvz_covariances(z, theta, pixel_scale, lookup_variance))


def propagate(J: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """First-order propagation ``J Q J^T`` for stacks (N, m, n) and (N, n, n): ``(J Q) J^T`` as two
    stacked matrix products (what ``np.einsum(..., optimize=True)`` computes, without its path search)."""
    J = np.asarray(J, dtype=float)
    return (J @ np.asarray(Q, dtype=float)) @ np.swapaxes(J, -1, -2)


def blur_covariances(X: np.ndarray, uv_velocity: np.ndarray, exposure_s: float, fx: float, fy: float) -> np.ndarray:
    """Covariances (N, 3, 3; m^2) that motion blur adds to points ``X`` (N, 3; camera frame, m): over
    an exposure of ``exposure_s`` s a keypoint is smeared along its image velocity ``uv_velocity``
    (N, 2; px/s) over ``L = exposure_s |u'|`` px, and where along the smear the detector places it is
    taken as uniform: variance ``L^2 / 12`` along ``u'``. Carried to the point at its depth by
    ``dX/d(u, v) = diag(Z/fx, Z/fy)`` (the depth is read, not smeared)."""
    X = np.asarray(X, dtype=float)
    d = exposure_s * np.asarray(uv_velocity, dtype=float) * X[:, 2:3] / np.array([fx, fy])  # m, along x and y
    Q = np.zeros((len(X), 3, 3))
    Q[:, :2, :2] = d[:, :, None] * d[:, None, :] / 12.0
    return Q


def surface_angles(
    depth: np.ndarray, uv: np.ndarray, camera: Camera, step: int = 3, max_jump: float = 0.05
) -> np.ndarray:
    """Angle (radians) between the local surface normal and the viewing ray at pixels ``uv``.

    The normal is the cross product of the back-projected central differences of the depth image
    (metres, 0 = invalid) ``step`` pixels around each pixel. Where a neighbour is invalid, off the
    image, or differs by more than ``max_jump`` metres times the depth (a depth edge), the angle
    is 0, the thesis's default.
    """
    uv = np.asarray(uv, dtype=float)
    n = uv.shape[0]
    theta = np.zeros(n)
    if n == 0:
        return theta
    h, w = depth.shape
    ui = np.rint(uv[:, 0]).astype(int)
    vi = np.rint(uv[:, 1]).astype(int)
    ok = (ui >= step) & (ui < w - step) & (vi >= step) & (vi < h - step)
    ui_c, vi_c = np.where(ok, ui, step), np.where(ok, vi, step)

    # the pixel and its four neighbours (centre, right, left, down, up), back-projected: (5, N, 3)
    u = ui_c + np.array([0, step, -step, 0, 0])[:, None]
    v = vi_c + np.array([0, 0, 0, step, -step])[:, None]
    z = depth[v, u].astype(float)
    p = np.empty((5, n, 3))
    p[:, :, 0] = (u - camera.cx) * z / camera.fx
    p[:, :, 1] = (v - camera.cy) * z / camera.fy
    p[:, :, 2] = z
    pc, pr, pl, pd, pu = p
    zc, zs = z[0], z.T
    ok &= np.all(zs > 0, axis=1)
    ok &= np.all(np.abs(zs[:, 1:] - zc[:, None]) < max_jump * np.maximum(zc[:, None], 1e-9), axis=1)
    normal = cross(pr - pl, pd - pu)
    norm = np.linalg.norm(normal, axis=1) * np.linalg.norm(pc, axis=1)
    ok &= norm > 0
    cosang = np.abs(np.einsum("ij,ij->i", normal, pc)) / np.where(ok, norm, 1.0)
    theta[ok] = np.arccos(np.clip(cosang[ok], 0.0, 1.0))
    return theta


#: Gauss-Hermite quadrature of a standard normal with 5 nodes: the nonzero nodes and the weight of
#: each sign (the centre node, weight 8/15, adds nothing to a variance about the centre)
GAUSS_HERMITE_5 = ((1.3556261799742659, 0.2220759220056126), (2.8569700138728056, 0.011257411327720693))


def depth_lookup_variance(depth: np.ndarray, uv: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Variance (m^2, N) of the depth read at keypoints ``uv`` (N, 2; pixels of the depth image
    ``depth``, metres, 0 = none) whose true position is off by independent Gaussian errors with
    standard deviations along the directions ``offsets`` (K, 2) or (K, N, 2) pixels.

    Per direction ``o_k`` a 5-node Gauss-Hermite quadrature of the squared change of the
    (nearest-pixel) depth: ``sum_j w_j [dZ(a_j o_k)^2 + dZ(-a_j o_k)^2]`` (:data:`GAUSS_HERMITE_5`),
    summed over the directions. It is ``|o . grad Z|^2`` summed on a smooth surface and grows
    with the chance that the lookup lands across a depth edge up to 2.9 sigma away. A node off the
    image or without depth is no information: the other sign's value stands in for it.

    On a real depth image the changes also hold the image's own noise between neighbouring pixels,
    so the variance measures the local spread of the depth: shape and noise (docs/derivation.md)."""
    uv = np.asarray(uv, dtype=float)
    n = uv.shape[0]
    offsets = np.asarray(offsets, dtype=float)
    if offsets.ndim == 2:
        offsets = np.broadcast_to(offsets[:, None, :], (offsets.shape[0], n, 2))
    out = np.zeros(n)
    if n == 0 or offsets.shape[0] == 0:
        return out
    h, w = depth.shape
    ui = np.clip(np.floor(uv[:, 0] + 0.5).astype(np.intp), 0, w - 1)
    vi = np.clip(np.floor(uv[:, 1] + 0.5).astype(np.intp), 0, h - 1)
    zc = depth[vi, ui].astype(float)
    nodes = np.array([(a, -a) for a, _ in GAUSS_HERMITE_5])  # (J, 2): each node with both signs
    # every sigma point at once: (K, J, 2, N, 2)
    points = uv + nodes[None, :, :, None, None] * offsets[:, None, None, :, :]
    z2, ok = nearest_depth(depth, points)
    squared = np.where(ok, (z2 - zc) ** 2, 0.0)
    total = squared[:, :, 0] + squared[:, :, 1]
    count = ok.sum(axis=2)
    for k in range(offsets.shape[0]):
        for j, (_, weight) in enumerate(GAUSS_HERMITE_5):
            out += 2.0 * weight * np.where(count[k, j] > 0, total[k, j] / np.maximum(count[k, j], 1), 0.0)
    return out


def nearest_depth(depth: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Depth (...) at the nearest pixel to ``uv`` (..., 2) in a depth image (H, W; metres, 0 = none)
    and whether it is a measurement there: the pixel is on the image and its depth finite and
    positive (``z`` means nothing elsewhere)."""
    h, w = depth.shape
    with np.errstate(invalid="ignore"):
        u = np.floor(uv[..., 0] + 0.5)
        v = np.floor(uv[..., 1] + 0.5)
        on = np.isfinite(u) & np.isfinite(v) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    z = depth[np.where(on, v, 0).astype(np.intp), np.where(on, u, 0).astype(np.intp)].astype(float)
    with np.errstate(invalid="ignore"):
        ok = on & np.isfinite(z) & (z > 0)
    return z, ok
