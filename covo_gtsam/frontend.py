"""Feature front end: ORB features, registered depth, matching and outlier rejection.

Per frame (:func:`prepare_frame`, computed once and reused for the next pair):

1. ORB keypoints and descriptors on the grey image (thesis Table A.2 parameters, :func:`make_orb`).
2. Depth registration: nearest-pixel depth at the *measured* keypoint (TUM depth is registered to
   the colour image); invalid when 0, outside ``[min_depth, max_depth]`` or off the image
   (:func:`lookup_depth`).
3. Back-projection of the *undistorted* keypoint (:meth:`Camera.undistort`, :meth:`Camera.backproject`)
   and its 3x3 covariance (:meth:`PointNoiseModel.point_covariances`, surface angle from
   :func:`covo_gtsam.noise.surface_angles` on the depth image at the measured pixel).

Per frame pair (:func:`associate_frames`):

4. Brute-force Hamming matching with cross-check among keypoints with valid depth (:func:`match`,
   ``np.bitwise_count`` (a 16-bit lookup table on numpy < 2) on XORed uint64 descriptor words;
   same matches as ``cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)``), then the best
   ``keep_ratio`` by distance.
5. Outlier rejection: ``"rigid3d"`` (default) RANSAC of a rigid transform over 3-point samples with
   a Mahalanobis inlier test using the point covariances (:func:`ransac_rigid3d`),
   ``"homography"`` (the thesis's C++ code: ``cv2.findHomography`` RANSAC at ``ransac_px``) or
   ``"none"``.

Direction: ``X_ref`` are points in the reference (earlier) frame k, ``X_cur`` in the current frame
k+1; the transform fitted by the rigid RANSAC is ``T_ref,cur`` with ``X_ref ≈ R X_cur + t``, the
convention of :func:`covo_gtsam.estimator.estimate_relative_pose`.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

import cv2
import numpy as np

from .camera import Camera
from .errors import ConfigError, InputError
from .factors import SYM6, sym3_mahalanobis, transfer_mahalanobis, weighted_rigid_fit
from .geometry import make_pose, rigid_fit
from .noise import PointNoiseModel, depth_lookup_variance, surface_angles
from .validation import check_choice, check_int, check_real, is_int, is_real

OUTLIER_REJECTIONS = ("rigid3d", "homography", "none")
#: chi-square(3) 99 % quantile: default gate of the Mahalanobis inlier test.
CHI2_3DOF_99 = 11.345
#: ORB descriptor length in bytes (256 bits = 4 uint64 words).
DESCRIPTOR_BYTES = 32
#: Entries of the Hamming distance matrix computed at a time (a block of rows; bounds scratch
#: memory to about 11 bytes per entry).
MATCH_BLOCK_ENTRIES = 1 << 20
#: Hypothesis x point elements scored at a time by the rigid RANSAC at most (bounds memory).
RANSAC_CHUNK = 400_000
#: Samples fitted and scored per batch by the rigid RANSAC before the early-termination check.
RANSAC_BATCH = 25
#: Probability that the rigid RANSAC has drawn at least one all-inlier sample when it stops early.
RANSAC_CONFIDENCE = 0.999
#: Default RANSAC hypotheses / iterations: ``FrontendConfig.ransac_iterations`` and the default of
#: :func:`ransac_rigid3d` and :func:`ransac_homography`.
RANSAC_ITERATIONS = 200
#: Upper limits of the front-end settings (memory: ORB reserves ``n_features`` keypoints, the
#: rigid RANSAC draws all its samples at once; a patch must fit in the image, see
#: :meth:`FrontendConfig.check_image_size`).
MAX_FEATURES = 1_000_000
MAX_LEVELS = 64
MAX_PATCH_SIZE = 1024
MAX_RANSAC_ITERATIONS = 1_000_000


# --------------------------------------------------------------------------------------------
# configuration
# --------------------------------------------------------------------------------------------
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


# --------------------------------------------------------------------------------------------
# images
# --------------------------------------------------------------------------------------------
def _check_file(path: str | os.PathLike, what: str) -> str:
    from .io import file_problem

    p = os.fspath(path)
    problem = file_problem(p)
    if problem is not None:
        raise InputError(f"{p}: {what} file {problem}")
    return p


def load_grey(path: str | os.PathLike) -> np.ndarray:
    """Grey uint8 image (H, W) of an image file (``cv2.IMREAD_GRAYSCALE``).

    Raises:
        InputError: the file is missing, unreadable or corrupt.
    """
    p = _check_file(path, "image")
    img = cv2.imread(p, cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise InputError(f"{p}: image is unreadable or corrupt")
    return img


def load_depth(
    path: str | os.PathLike, depth_scale: float = 5000.0, shape: tuple[int, int] | None = (480, 640)
) -> np.ndarray:
    """Depth image in metres (float32, 0 = no measurement) of a 16-bit PNG: ``value / depth_scale``.

    ``shape`` is the expected ``(height, width)``; None accepts any size.

    Raises:
        InputError: the file is missing, unreadable or corrupt, not a single-channel 16-bit
            image (e.g. an 8-bit PNG), or not of the expected size.
    """
    if not (depth_scale > 0 and math.isfinite(depth_scale)):
        raise InputError(f"depth_scale must be a positive number, got {depth_scale!r}")
    p = _check_file(path, "depth")
    raw = cv2.imread(p, cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise InputError(f"{p}: depth image is unreadable or corrupt")
    if raw.ndim != 2:
        raise InputError(f"{p}: depth image has {raw.shape[2]} channels, expected a single channel")
    if raw.dtype != np.uint16:
        bits = 8 * raw.dtype.itemsize
        raise InputError(
            f"{p}: depth image is {bits}-bit {raw.dtype}, expected 16-bit (uint16, value/{depth_scale:g} = metres)")
    if shape is not None and raw.shape != tuple(shape):
        raise InputError(
            f"{p}: depth image is {raw.shape[1]}x{raw.shape[0]}, expected {shape[1]}x{shape[0]}")
    return raw.astype(np.float32) * np.float32(1.0 / depth_scale)


def to_grey(image: np.ndarray, bgr: bool = True) -> np.ndarray:
    """Grey uint8 (H, W) of a grey (H, W) / (H, W, 1), colour (H, W, 3) or (H, W, 4) uint8 image.

    Colour channels are in OpenCV's BGR(A) order unless ``bgr`` is False (RGB(A)).
    """
    img = np.asarray(image)
    if img.dtype != np.uint8:
        raise InputError(f"image must be 8-bit (uint8), got {img.dtype}")
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim == 2:
        return np.ascontiguousarray(img)
    if img.ndim == 3 and img.shape[2] in (3, 4):
        code = {
            (3, True): cv2.COLOR_BGR2GRAY, (3, False): cv2.COLOR_RGB2GRAY,
            (4, True): cv2.COLOR_BGRA2GRAY, (4, False): cv2.COLOR_RGBA2GRAY,
        }[(img.shape[2], bool(bgr))]
        return cv2.cvtColor(np.ascontiguousarray(img), code)
    raise InputError(f"image must have shape (H, W), (H, W, 1), (H, W, 3) or (H, W, 4), got {img.shape}")


# --------------------------------------------------------------------------------------------
# features and matching
# --------------------------------------------------------------------------------------------
@dataclass
class Features:
    """ORB features of one image.

    Attributes:
        uv: (N, 2) float64 measured (distorted) pixel coordinates.
        descriptors: (N, 32) uint8 ORB descriptors.
        octave: (N,) int pyramid level of each keypoint (0 = full resolution; zeros if unknown).
        words: (N, 4) uint64 view of ``descriptors`` used by :func:`match` (set automatically).
    """

    uv: np.ndarray
    descriptors: np.ndarray
    octave: np.ndarray | None = None
    words: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        uv = np.ascontiguousarray(self.uv, dtype=float).reshape(-1, 2)
        d = np.ascontiguousarray(self.descriptors, dtype=np.uint8)
        if d.size == 0:
            d = np.zeros((0, DESCRIPTOR_BYTES), np.uint8)
        if d.ndim != 2 or d.shape[1] != DESCRIPTOR_BYTES or d.shape[0] != uv.shape[0]:
            raise InputError(
                f"features need descriptors (N, {DESCRIPTOR_BYTES}) for uv (N, 2); got {d.shape} and {uv.shape}")
        octave = np.zeros(uv.shape[0], np.int32) if self.octave is None else np.asarray(self.octave, np.int32).reshape(-1)
        if octave.shape[0] != uv.shape[0]:
            raise InputError(f"features need one octave per keypoint; got {octave.shape[0]} for {uv.shape[0]}")
        self.uv = uv
        self.descriptors = d
        self.octave = octave
        self.words = d.view(np.uint64)

    def __len__(self) -> int:
        return self.uv.shape[0]

    def subset(self, index: np.ndarray) -> "Features":
        """Features at ``index`` (integer indices or boolean mask)."""
        return Features(self.uv[index], self.descriptors[index], self.octave[index])


def detect(grey: np.ndarray, orb: cv2.Feature2D, mask: np.ndarray | None = None) -> Features:
    """ORB keypoints and descriptors of a grey uint8 image (optional uint8 detection ``mask``)."""
    grey = np.asarray(grey)
    if grey.ndim != 2 or grey.dtype != np.uint8:
        raise InputError(f"detect needs a grey uint8 image (H, W), got {grey.dtype} {grey.shape}")
    keypoints, descriptors = orb.detectAndCompute(grey, mask)
    if not keypoints or descriptors is None:
        return Features(np.zeros((0, 2)), np.zeros((0, DESCRIPTOR_BYTES), np.uint8))
    uv = cv2.KeyPoint_convert(keypoints).astype(float).reshape(-1, 2)
    octave = np.fromiter((k.octave for k in keypoints), np.int32, len(keypoints))
    return Features(uv, descriptors, octave)


def _as_words(f: Features | np.ndarray) -> np.ndarray:
    if isinstance(f, Features):
        return f.words
    w = np.asarray(f)
    if w.dtype == np.uint8 and w.ndim == 2 and w.shape[1] == DESCRIPTOR_BYTES:
        return np.ascontiguousarray(w).view(np.uint64)
    if w.dtype == np.uint64 and w.ndim == 2 and w.shape[1] == DESCRIPTOR_BYTES // 8:
        return w
    raise InputError(f"descriptors must be (N, 32) uint8 or (N, 4) uint64, got {w.dtype} {w.shape}")


_HAMMING2_MASK = np.uint64(0x5555555555555555)


def _bitcount(x: np.ndarray, out: np.ndarray) -> np.ndarray:
    """Number of set bits of each uint64 of ``x`` into ``out`` (uint8 or uint16):
    ``np.bitwise_count`` on numpy >= 2, else a 16-bit lookup table (about 13 times slower)."""
    if _POPCOUNT16 is None:
        return np.bitwise_count(x, out=out)
    v = np.ascontiguousarray(x).view(np.uint16).reshape(*x.shape, 4)
    np.add(np.take(_POPCOUNT16, v[..., 0]), np.take(_POPCOUNT16, v[..., 1]), out=out)
    np.add(out, np.take(_POPCOUNT16, v[..., 2]), out=out)
    return np.add(out, np.take(_POPCOUNT16, v[..., 3]), out=out)


def _popcount_table() -> np.ndarray:
    """Bits set in each 16-bit value (65536,) uint8."""
    t = np.zeros(1 << 16, np.uint8)
    for bit in range(16):
        t += (np.arange(1 << 16) >> bit & 1).astype(np.uint8)
    return t


#: Lookup table for numpy < 2 (no ``np.bitwise_count``); None when numpy has it.
_POPCOUNT16 = None if hasattr(np, "bitwise_count") else _popcount_table()


def _popcount_block(x: np.ndarray, out8: np.ndarray, hamming2: bool) -> np.ndarray:
    """Bit count of each uint64 in ``x`` into ``out8`` (uint8); 2-bit cells for ``hamming2``."""
    if hamming2:  # NORM_HAMMING2 (WTA_K 3, 4): count 2-bit cells that differ
        np.bitwise_or(x, x >> np.uint64(1), out=x)
        np.bitwise_and(x, _HAMMING2_MASK, out=x)
    return _bitcount(x, out8)


def hamming_distances(f_a: Features | np.ndarray, f_b: Features | np.ndarray, hamming2: bool = False) -> np.ndarray:
    """Full (Na, Nb) uint16 Hamming distance matrix (for small inputs and tests; :func:`match`
    computes the same values block by block without storing the matrix)."""
    a, b = _as_words(f_a), _as_words(f_b)
    d = np.zeros((a.shape[0], b.shape[0]), np.uint16)
    bT = np.ascontiguousarray(b.T)
    bs = min(_block_rows(b.shape[0]), max(a.shape[0], 1))
    scratch = _scratch(bs, b.shape[0])
    for s in range(0, a.shape[0], bs):
        _distance_block(a[s:s + bs], bT, hamming2, d[s:s + bs], scratch)
    return d


def _block_rows(nb: int) -> int:
    return max(1, MATCH_BLOCK_ENTRIES // max(nb, 1))


def _scratch(n: int, nb: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Work buffers of :func:`_distance_block` for up to n x nb entries."""
    return np.empty((n, nb), np.uint64), np.empty((n, nb), np.uint8), np.empty((n, nb), np.uint8)


def _distance_block(a: np.ndarray, bT: np.ndarray, hamming2: bool, out: np.ndarray | None = None,
                    scratch: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Hamming distances (n, Nb) uint16 between words ``a`` (n, 4) and transposed words ``bT`` (4, Nb).

    Words 0-2 (at most 192 differing bits) are summed in uint8 with fast same-type adds; the
    last word is counted straight into the uint16 output and the uint8 sum added once (max 256).
    """
    n, nb = a.shape[0], bT.shape[1]
    out = np.empty((n, nb), np.uint16) if out is None else out
    tmp, acc, c8 = _scratch(n, nb) if scratch is None else (x[:n] for x in scratch)
    last = a.shape[1] - 1
    for w in range(last + 1):
        np.bitwise_xor(a[:, w, None], bT[w], out=tmp)
        if w == 0:
            _popcount_block(tmp, acc, hamming2)
        elif w < last:
            np.add(acc, _popcount_block(tmp, c8, hamming2), out=acc)
        else:
            if hamming2:
                out[...] = _popcount_block(tmp, c8, True)
            else:
                _bitcount(tmp, out)
            np.add(out, acc, out=out)
    return out


def cross_check_matches(
    f_a: Features | np.ndarray, f_b: Features | np.ndarray, hamming2: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mutual nearest neighbours by Hamming distance: ``(idx_a, idx_b, dist)``, sorted by ``idx_a``.

    ``b = argmin_j d(a, j)`` and ``a = argmin_i d(i, b)``, ties to the lowest index (as OpenCV).
    Distances are computed in row blocks of about :data:`MATCH_BLOCK_ENTRIES` entries (one block
    for ~1000 x 1000); only the (Na,) row and (Nb,) column bests are kept across blocks.
    """
    a, b = _as_words(f_a), _as_words(f_b)
    na, nb = a.shape[0], b.shape[0]
    empty = (np.zeros(0, np.intp), np.zeros(0, np.intp), np.zeros(0, np.uint16))
    if na == 0 or nb == 0:
        return empty
    bT = np.ascontiguousarray(b.T)
    bs = min(_block_rows(nb), na)
    out, scratch = np.empty((bs, nb), np.uint16), _scratch(bs, nb)
    fwd = np.empty(na, np.intp)
    fwd_d = np.empty(na, np.uint16)
    col_d = np.full(nb, np.iinfo(np.uint16).max, np.uint16)
    bwd = np.zeros(nb, np.intp)
    cols = np.arange(nb)
    for s in range(0, na, bs):
        n = min(bs, na - s)
        d = _distance_block(a[s:s + n], bT, hamming2, out[:n], scratch)
        j = np.argmin(d, axis=1)
        fwd[s:s + n] = j
        fwd_d[s:s + n] = np.take_along_axis(d, j[:, None], axis=1)[:, 0]
        i = np.argmin(d, axis=0)
        di = d[i, cols]
        better = di < col_d  # strict: an earlier block keeps ties (lowest index wins)
        col_d[better] = di[better]
        bwd[better] = i[better] + s
    idx_a = np.flatnonzero(bwd[fwd] == np.arange(na))
    return idx_a, fwd[idx_a], fwd_d[idx_a]


def keep_best(dist: np.ndarray, keep_ratio: float, max_hamming: int | None = None) -> np.ndarray:
    """Indices of the best ``ceil(keep_ratio * N)`` distances, ascending (stable), then those
    ``<= max_hamming`` if given."""
    dist = np.asarray(dist)
    order = np.argsort(dist, kind="stable")
    n_keep = min(dist.shape[0], int(math.ceil(keep_ratio * dist.shape[0] - 1e-9)))
    order = order[:n_keep]
    if max_hamming is not None:
        order = order[dist[order] <= max_hamming]
    return order


def match(
    f_a: Features | np.ndarray,
    f_b: Features | np.ndarray,
    keep_ratio: float = 1.0,
    max_hamming: int | None = None,
    hamming2: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cross-checked brute-force Hamming matches, best ``keep_ratio`` kept.

    Args:
        f_a, f_b: :class:`Features` (or (N, 32) uint8 / (N, 4) uint64 descriptor arrays).
        keep_ratio: fraction in (0, 1] of the cross-checked matches kept, smallest distance first.
        max_hamming: optional absolute distance cut applied after ``keep_ratio``.
        hamming2: 2-bit-cell distance (``cv2.NORM_HAMMING2``) for ORB with WTA_K 3 or 4.

    Returns:
        ``(idx_a, idx_b, dist)``: indices into ``f_a`` and ``f_b`` and the uint16 Hamming
        distances, sorted by ascending distance (ties by ``idx_a``). With ``keep_ratio = 1`` the
        pairs are those of ``cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(a, b)``.
    """
    if not (0.0 < keep_ratio <= 1.0):
        raise InputError(f"keep_ratio must be in (0, 1], got {keep_ratio!r}")
    idx_a, idx_b, dist = cross_check_matches(f_a, f_b, hamming2)
    keep = keep_best(dist, keep_ratio, max_hamming)
    return idx_a[keep], idx_b[keep], dist[keep]


# --------------------------------------------------------------------------------------------
# depth and 3D points
# --------------------------------------------------------------------------------------------
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
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    h, w = depth_m.shape
    with np.errstate(invalid="ignore"):
        ui = np.floor(uv[:, 0] + 0.5)
        vi = np.floor(uv[:, 1] + 0.5)
        on = np.isfinite(ui) & np.isfinite(vi) & (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h)
    ui = np.where(on, ui, 0).astype(np.intp)
    vi = np.where(on, vi, 0).astype(np.intp)
    z = depth_m[vi, ui].astype(float)
    with np.errstate(invalid="ignore"):
        valid = on & np.isfinite(z) & (z > 0) & (z >= min_depth) & (z <= max_depth)
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
        grey: (H, W) uint8 image (see :func:`to_grey`).
        depth_m: (H, W) depth in metres registered to the colour image, 0 = invalid.
        camera: intrinsics and distortion of the colour camera.
        orb: detector from :func:`make_orb`.
        noise_model: per-point noise model (thesis defaults if None).
        cfg: front-end configuration (defaults if None); its depth range is applied.
        use_surface_angle: compute the surface angle from the depth image for the depth noise;
            otherwise theta = 0.
        pixel_sigma_by_level: scale each keypoint's pixel noise by ``cfg.scale_factor ** octave``
            (its ORB pyramid level); otherwise every keypoint has the model's pixel noise.
        depth_lookup_noise: add to each depth variance what the depth image changes within the
            keypoint's pixel noise (:func:`covo_gtsam.noise.depth_lookup_variance`, sigma points
            one pixel sigma along each image axis): large beside depth edges.
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


# --------------------------------------------------------------------------------------------
# outlier rejection
# --------------------------------------------------------------------------------------------
def _score_hypotheses(
    R: np.ndarray, t: np.ndarray, X_ref: np.ndarray, X_cur: np.ndarray, Qa6: np.ndarray, Qb9: np.ndarray
) -> np.ndarray:
    """Mahalanobis distances (H, N) of all points under H hypotheses ``(R, t)``.

    ``R Q_cur R^T`` for all hypotheses and points is one matrix product with
    ``kron(R, R)``: ``vec(R Q R^T) = (R ⊗ R) vec(Q)``; only its 6 unique entries are formed.
    """
    H, n = R.shape[0], X_ref.shape[0]
    K = np.einsum("hik,hjl->hijkl", R, R).reshape(H, 9, 9)
    rows = [3 * i + j for i, j in SYM6]
    M = (K[:, rows, :].transpose(1, 0, 2).reshape(6 * H, 9) @ Qb9.T).reshape(6, H, n)  # entries of R Q_cur R^T
    S6 = tuple(M[k] + Qa6[k] for k in range(6))
    P = (R.reshape(3 * H, 3) @ X_cur.T).reshape(H, 3, n)  # R X_cur
    r = tuple(X_ref[:, k] - P[:, k] - t[:, k, None] for k in range(3))
    return sym3_mahalanobis(S6, r)


@dataclass
class RansacResult:
    """Outcome of :func:`ransac_rigid3d`: ``X_ref ≈ R X_cur + t``, the inlier mask (N,) and the
    number of hypotheses scored."""

    R: np.ndarray
    t: np.ndarray
    inliers: np.ndarray
    hypotheses: int

    @property
    def T(self) -> np.ndarray:
        """4x4 ``T_ref,cur``."""
        return make_pose(self.R, self.t)

    @property
    def num_inliers(self) -> int:
        return int(np.count_nonzero(self.inliers))


def required_samples(inlier_ratio: float, confidence: float = RANSAC_CONFIDENCE, sample_size: int = 3) -> float:
    """Samples needed to draw an all-inlier sample with probability ``confidence``:
    ``log(1 - confidence) / log(1 - w^s)`` (inf when it cannot be reached)."""
    good = float(inlier_ratio) ** sample_size
    if confidence >= 1.0 or good <= 0.0:
        return math.inf
    if good >= 1.0:
        return 1.0
    return math.log(1.0 - confidence) / math.log(1.0 - good)


def sample_triples(rng: np.random.Generator, n: int, count: int) -> np.ndarray:
    """``count`` uniformly drawn triples (count, 3) of distinct indices in ``[0, n)``, n >= 3."""
    i0 = rng.integers(0, n, count)
    i1 = rng.integers(0, n - 1, count)
    i1 += i1 >= i0
    lo, hi = np.minimum(i0, i1), np.maximum(i0, i1)
    i2 = rng.integers(0, n - 2, count)
    i2 += i2 >= lo
    i2 += i2 >= hi
    return np.stack([i0, i1, i2], axis=1)


def _rigid_consistent(
    samples: np.ndarray, X_ref: np.ndarray, X_cur: np.ndarray, Q_ref: np.ndarray, Q_cur: np.ndarray, chi2: float
) -> np.ndarray:
    """Mask of triples whose three pairwise distances agree in both frames (a rigid motion keeps
    them): ``(|a_i - a_j| - |b_i - b_j|)^2 < chi2 * var`` with the first-order variance of the
    difference from the point covariances. Removes most outlier samples before scoring."""
    ok = np.ones(samples.shape[0], bool)
    for p, q in ((0, 1), (0, 2), (1, 2)):
        i, j = samples[:, p], samples[:, q]
        da, db = X_ref[i] - X_ref[j], X_cur[i] - X_cur[j]
        la, lb = np.linalg.norm(da, axis=1), np.linalg.norm(db, axis=1)
        ua, ub = da / np.maximum(la, 1e-12)[:, None], db / np.maximum(lb, 1e-12)[:, None]
        var = (np.einsum("ni,nij,nj->n", ua, Q_ref[i] + Q_ref[j], ua)
               + np.einsum("ni,nij,nj->n", ub, Q_cur[i] + Q_cur[j], ub))
        ok &= (la - lb) ** 2 < chi2 * var
    return ok


def ransac_rigid3d(
    X_ref: np.ndarray,
    X_cur: np.ndarray,
    Q_ref: np.ndarray,
    Q_cur: np.ndarray,
    iterations: int = RANSAC_ITERATIONS,
    chi2: float = CHI2_3DOF_99,
    seed: int | np.random.Generator = 0,
    refits: int = 10,
    confidence: float = RANSAC_CONFIDENCE,
    prior: np.ndarray | None = None,
) -> RansacResult:
    """RANSAC of a rigid transform ``X_ref ≈ R X_cur + t`` over 3-point samples.

    All ``iterations`` samples are drawn at once (3 distinct pairs each, from
    ``np.random.default_rng(seed)``, so a given seed always gives the same result). Samples whose
    pairwise distances differ between the frames beyond their noise are dropped
    (:func:`_rigid_consistent`); the rest are fitted with the batched :func:`rigid_fit` and
    scored on every pair, :data:`RANSAC_BATCH` samples at a time, with
    ``r^T (Q_ref + R Q_cur R^T)^-1 r < chi2``, ``r = X_ref - (R X_cur + t)``. The hypothesis with
    the most inliers (ties: smallest summed Mahalanobis distance of its inliers) is then refitted
    on its inliers (weights ``1 / trace(Q_ref + Q_cur)``) and the inliers recomputed, up to
    ``refits`` times until the inlier set stops changing (``refits=1``: refit once).

    Scoring stops early once ``required_samples(best inlier ratio, confidence)`` samples have been
    drawn (standard adaptive RANSAC; ``confidence=1`` scores all ``iterations``). The samples and
    their order are fixed by the seed, so the result is deterministic either way.

    Why iterate: with 8 px pixel noise the gate is wide laterally, so a minimal-sample
    hypothesis ~1 deg off still collects a few depth-inconsistent pairs that bias a single
    refit; on freiburg1_rpy frames 0->1, iterating made the estimated pose independent of the
    seed (0.97 cm / 0.37 deg from ground truth for each of 20 seeds; refitting once: up to
    1.7 cm / 0.52 deg).

    ``prior`` (4x4 ``T_ref,cur``, e.g. a constant-velocity prediction) is scored as one more
    hypothesis before the samples; when it is good, its inlier ratio ends the sampling early.

    Fewer than 3 pairs, or no consistent sample (and no prior with 3 inliers): identity and no inliers.
    """
    X_ref = np.asarray(X_ref, dtype=float)
    X_cur = np.asarray(X_cur, dtype=float)
    Q_ref = np.asarray(Q_ref, dtype=float)
    Q_cur = np.asarray(Q_cur, dtype=float)
    n = X_ref.shape[0]
    if not (X_cur.shape == X_ref.shape == (n, 3) and Q_ref.shape == Q_cur.shape == (n, 3, 3)):
        raise InputError(
            "ransac_rigid3d needs X (N, 3) and Q (N, 3, 3); "
            f"got {X_ref.shape}, {X_cur.shape}, {Q_ref.shape}, {Q_cur.shape}")
    if n < 3:
        return RansacResult(np.eye(3), np.zeros(3), np.zeros(n, bool), 0)
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    drawn = sample_triples(rng, n, int(iterations))
    consistent = _rigid_consistent(drawn, X_ref, X_cur, Q_ref, Q_cur, chi2)

    Qa6 = np.stack([Q_ref[:, i, j] for i, j in SYM6])  # (6, N)
    Qb9 = Q_cur.reshape(n, 9)
    R_all, t_all, count_all, cost_all = [], [], [], []
    best_count = 0

    def score(R_h: np.ndarray, t_h: np.ndarray) -> None:
        nonlocal best_count
        d2 = _score_hypotheses(R_h, t_h, X_ref, X_cur, Qa6, Qb9)
        inl = d2 < chi2
        R_all.append(R_h)
        t_all.append(t_h)
        count_all.append(inl.sum(axis=1))
        cost_all.append(np.where(inl, d2, 0.0).sum(axis=1))
        best_count = max(best_count, int(count_all[-1].max()))

    if prior is not None:
        prior = np.asarray(prior, dtype=float)
        if prior.shape != (4, 4) or not np.all(np.isfinite(prior)):
            raise InputError(f"the RANSAC prior must be a finite 4x4 pose, got shape {prior.shape}")
        score(prior[None, :3, :3], prior[None, :3, 3])
        if best_count < 3:
            best_count = 0
    chunk = max(1, min(RANSAC_BATCH, RANSAC_CHUNK // n))
    for s in range(0, drawn.shape[0], chunk):
        samples = drawn[s:s + chunk][consistent[s:s + chunk]]
        if samples.shape[0]:
            score(*rigid_fit(X_ref[samples], X_cur[samples]))
        if s + chunk >= required_samples(best_count / n, confidence):
            break
    if not R_all or best_count < 3:  # no 3 pairs agree with any rigid motion
        return RansacResult(np.eye(3), np.zeros(3), np.zeros(n, bool), 0)
    R_h, t_h = np.concatenate(R_all), np.concatenate(t_all)
    counts, costs = np.concatenate(count_all), np.concatenate(cost_all)
    H = R_h.shape[0]
    best = int(np.lexsort((costs, -counts))[0])
    R, t = R_h[best], t_h[best]
    inliers = transfer_mahalanobis(R, t, X_ref, X_cur, Q_ref, Q_cur) < chi2
    for _ in range(int(refits)):
        if np.count_nonzero(inliers) < 3:
            break
        R2, t2 = weighted_rigid_fit(X_ref[inliers], X_cur[inliers], Q_ref[inliers], Q_cur[inliers])
        if not (np.all(np.isfinite(R2)) and np.all(np.isfinite(t2))):
            break
        inliers2 = transfer_mahalanobis(R2, t2, X_ref, X_cur, Q_ref, Q_cur) < chi2
        R, t = R2, t2
        if np.array_equal(inliers2, inliers):
            break
        inliers = inliers2
    return RansacResult(R, t, inliers, H)


def ransac_homography(uv_ref: np.ndarray, uv_cur: np.ndarray, threshold_px: float = 10.0,
                      iterations: int = RANSAC_ITERATIONS) -> np.ndarray:
    """Inlier mask (N,) of ``cv2.findHomography(uv_cur, uv_ref, RANSAC, threshold_px)``.

    (The thesis's C++ outlier rejection.) Fewer than 4 pairs or no homography found: no inliers.
    """
    uv_ref = np.asarray(uv_ref, dtype=np.float64).reshape(-1, 2)
    uv_cur = np.asarray(uv_cur, dtype=np.float64).reshape(-1, 2)
    n = uv_ref.shape[0]
    if n < 4:
        return np.zeros(n, bool)
    Hm, mask = cv2.findHomography(uv_cur, uv_ref, cv2.RANSAC, float(threshold_px), maxIters=int(iterations))
    if Hm is None or mask is None:
        return np.zeros(n, bool)
    return mask.reshape(-1).astype(bool)


# --------------------------------------------------------------------------------------------
# frame pairs
# --------------------------------------------------------------------------------------------
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

    def __len__(self) -> int:
        return int(self.X_ref.shape[0])


def associate_frames(
    ref: FrameData, cur: FrameData, cfg: FrontendConfig | None = None, prior: np.ndarray | None = None
) -> PointPairs:
    """Point pairs of a reference frame k and the current frame k+1.

    Only keypoints with valid depth are matched (cross-checked Hamming, best ``keep_ratio``,
    optional ``max_hamming``); outliers are then rejected by ``cfg.outlier_rejection``.
    ``prior`` (4x4 predicted ``T_ref,cur``, optional) is an extra rigid-RANSAC hypothesis and,
    with the other outlier rejections, the initial guess ``T_init`` of the pose.
    """
    cfg = cfg or FrontendConfig()
    ia, ib, dist = match(ref.valid_features, cur.valid_features, cfg.keep_ratio, cfg.max_hamming,
                         hamming2=cfg.wta_k > 2)
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
        T_init=T_init,
    )
