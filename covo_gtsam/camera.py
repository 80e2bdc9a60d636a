"""Pinhole camera with OpenCV's 5-parameter distortion, vectorised.

Pixel coordinates ``(u, v)`` are in pixels with the origin at the top-left pixel centre,
``u`` to the right and ``v`` down. Camera-frame points ``X = (X, Y, Z)`` are in metres with
``Z`` along the optical axis (OpenCV / TUM convention). Projection and back-projection work on
*undistorted* pixel coordinates; :meth:`Camera.undistort` maps measured (distorted) pixels to
them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .errors import ConfigError


#: Focal lengths a pinhole camera can have, in pixels (below: more than a radian per pixel; above:
#: a field of view below a milliradian, where float arithmetic of the projections breaks down).
MIN_FOCAL_PX, MAX_FOCAL_PX = 1.0, 1e6
#: :meth:`Camera.undistort`: a pixel whose 20 fixed-point steps leave it farther than this from its
#: measurement (px, distorted again) gets up to this many steps
UNDISTORT_TOLERANCE_PX, UNDISTORT_MAX_ITERATIONS = 0.01, 1000


@dataclass(frozen=True)
class Camera:
    """Intrinsics ``fx, fy, cx, cy`` (pixels) and distortion ``(k1, k2, p1, p2, k3)``."""

    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    width: int = 640
    height: int = 480
    name: str = "custom"
    _K: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not (self.fx > 0 and self.fy > 0):
            raise ConfigError(f"camera focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if not (MIN_FOCAL_PX <= self.fx <= MAX_FOCAL_PX and MIN_FOCAL_PX <= self.fy <= MAX_FOCAL_PX):
            raise ConfigError(f"camera focal lengths must be {MIN_FOCAL_PX:g} to {MAX_FOCAL_PX:g} px, got fx={self.fx}, "
                              f"fy={self.fy}")
        if len(self.dist) != 5:
            raise ConfigError(f"distortion needs 5 values (k1 k2 p1 p2 k3), got {len(self.dist)}")
        object.__setattr__(self, "dist", tuple(float(d) for d in self.dist))
        K = np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])
        object.__setattr__(self, "_K", K)

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix."""
        return self._K.copy()

    @property
    def has_distortion(self) -> bool:
        return any(d != 0.0 for d in self.dist)

    @classmethod
    def preset(cls, name: str) -> "Camera":
        """TUM RGB-D colour-camera presets: ``"fr1"``, ``"fr2"``, ``"fr3"``."""
        key = name.lower().replace("freiburg", "fr") if isinstance(name, str) else None
        if key not in PRESETS:
            raise ConfigError(f"unknown camera preset {name!r}; choose one of {sorted(PRESETS)}")
        return PRESETS[key]

    @classmethod
    def resolve(cls, camera: "Camera | str", what: str = "camera") -> "Camera":
        """The preset ``camera`` names (see :meth:`preset`) if it is a string, else ``camera``
        itself: a :class:`Camera` or an object with the same interface.

        Raises:
            ConfigError: an unknown preset name, or an object without the camera interface
                (``what`` names the argument).
        """
        if isinstance(camera, str):
            return cls.preset(camera)
        if isinstance(camera, cls) or all(hasattr(camera, a) for a in _CAMERA_INTERFACE):
            return camera
        raise ConfigError(
            f"{what} must be a Camera or a preset name ({', '.join(sorted(PRESETS))}), got {camera!r}")

    def project(self, X: np.ndarray) -> np.ndarray:
        """Undistorted pixels (N, 2) of camera-frame points (N, 3); Z must be > 0."""
        X = np.asarray(X, dtype=float)
        z = X[:, 2]
        return np.stack([self.fx * X[:, 0] / z + self.cx, self.fy * X[:, 1] / z + self.cy], axis=1)

    def backproject(self, uv: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Camera-frame points (N, 3) from undistorted pixels (N, 2) and depth Z (N,) in metres (4.3)."""
        uv = np.asarray(uv, dtype=float)
        z = np.asarray(z, dtype=float)
        return np.stack([(uv[:, 0] - self.cx) * z / self.fx, (uv[:, 1] - self.cy) * z / self.fy, z], axis=1)

    def backprojection_jacobian(self, uv: np.ndarray, z: np.ndarray) -> np.ndarray:
        """J_bp of (4.5): d(X, Y, Z)/d(u, v, Z), shape (N, 3, 3); rows X, Y, Z, columns u, v, Z."""
        uv = np.asarray(uv, dtype=float)
        z = np.asarray(z, dtype=float)
        J = np.zeros((uv.shape[0], 3, 3))
        J[:, 0, 0] = z / self.fx
        J[:, 0, 2] = (uv[:, 0] - self.cx) / self.fx
        J[:, 1, 1] = z / self.fy
        J[:, 1, 2] = (uv[:, 1] - self.cy) / self.fy
        J[:, 2, 2] = 1.0
        return J

    def distort(self, uv: np.ndarray) -> np.ndarray:
        """Measured (distorted) pixels (N, 2) of undistorted pixels (N, 2), OpenCV's model."""
        uv = np.asarray(uv, dtype=float)
        if not self.has_distortion:
            return uv.copy()
        k1, k2, p1, p2, k3 = self.dist
        x = (uv[:, 0] - self.cx) / self.fx
        y = (uv[:, 1] - self.cy) / self.fy
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return np.stack([self.fx * xd + self.cx, self.fy * yd + self.cy], axis=1)

    def undistort(self, uv: np.ndarray) -> np.ndarray:
        """Undistorted pixels (N, 2) of measured pixels (N, 2) (iterative inverse of :meth:`distort`:
        20 iterations, and up to :data:`UNDISTORT_MAX_ITERATIONS` for the pixels that are then still
        more than :data:`UNDISTORT_TOLERANCE_PX` from their measurement when distorted again, as
        under strong wide-angle distortion)."""
        uv = np.asarray(uv, dtype=float)
        if not self.has_distortion or uv.shape[0] == 0:
            return uv.copy()
        out = self._undistort_iterations(uv, 20, 1e-6)
        off = np.linalg.norm(self.distort(out) - uv, axis=1)
        slow = np.flatnonzero(np.isfinite(uv).all(axis=1) & ~(off <= UNDISTORT_TOLERANCE_PX))
        if slow.size:
            out[slow] = self._undistort_iterations(uv[slow], UNDISTORT_MAX_ITERATIONS, 1e-12)
        return out

    def _undistort_iterations(self, uv: np.ndarray, iterations: int, eps: float) -> np.ndarray:
        """OpenCV's fixed-point undistortion of pixels (N, 2): at most ``iterations`` steps, until a
        step's change is below ``eps`` (normalised image coordinates)."""
        import cv2

        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, iterations, eps)
        src, dist = uv.reshape(-1, 1, 2), np.asarray(self.dist, dtype=float)
        if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4.x: the iterative variant takes criteria
            pts = cv2.undistortPointsIter(src, self._K, dist, np.eye(3), self._K, criteria)
        else:  # OpenCV 5: undistortPoints takes criteria itself
            pts = cv2.undistortPoints(src, self._K, dist, R=None, P=self._K, criteria=criteria)
        return pts.reshape(-1, 2).astype(float)

    def in_image(self, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Boolean mask (N,) of pixels inside the image, ``margin`` pixels from the border."""
        uv = np.asarray(uv, dtype=float)
        return (
            (uv[:, 0] >= margin)
            & (uv[:, 0] <= self.width - 1 - margin)
            & (uv[:, 1] >= margin)
            & (uv[:, 1] <= self.height - 1 - margin)
        )


#: What :meth:`Camera.resolve` requires of a camera that is not a :class:`Camera`.
_CAMERA_INTERFACE = ("width", "height", "project", "backproject", "backprojection_jacobian", "undistort", "distort")

PRESETS: dict[str, Camera] = {
    # TUM RGB-D benchmark colour cameras (thesis Table A.1; freiburg3 images are undistorted).
    "fr1": Camera(517.3, 516.5, 318.6, 255.3, (0.2624, -0.9531, -0.0054, 0.0026, 1.1633), name="fr1"),
    "fr2": Camera(520.9, 521.0, 325.1, 249.7, (0.2312, -0.7849, -0.0033, -0.0001, 0.9172), name="fr2"),
    "fr3": Camera(535.4, 539.2, 320.1, 247.6, name="fr3"),
}
