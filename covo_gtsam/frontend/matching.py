"""Features and matches: ORB keypoints and descriptors of a grey image (:func:`detect`) and
brute-force Hamming matching with cross-check (:func:`match`).

Distances are ``np.bitwise_count`` (a 16-bit lookup table on numpy < 2) on XORed uint64 descriptor
words, computed block by block (:func:`cross_check_matches`); the matches are those of
``cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)``, of which the best ``keep_ratio`` by distance
are kept (:func:`keep_best`). Given where each keypoint is expected in the other image (a
predicted motion), :func:`guided_cross_check` compares only keypoints near their predicted pixel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from ..errors import InputError
from ..validation import is_real

#: ORB descriptor length in bytes (256 bits = 4 uint64 words).
DESCRIPTOR_BYTES = 32
#: Entries of the Hamming distance matrix computed at a time (a block of rows; bounds scratch
#: memory to about 11 bytes per entry).
MATCH_BLOCK_ENTRIES = 1 << 20
#: Cell size (pixels) of guided matching (:func:`guided_cross_check`): a keypoint is compared with
#: those in its predicted cell and the 8 around it, so at least with those within this distance.
GUIDED_CELL_PX = 32.0


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


def guided_cross_check(
    f_a: Features | np.ndarray, uv_pred: np.ndarray, f_b: Features | np.ndarray, uv_b: np.ndarray,
    cell: float = GUIDED_CELL_PX, hamming2: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`cross_check_matches` among the pairs that a predicted motion allows: ``(idx_a, idx_b, dist)``.

    ``uv_pred`` (Na, 2) are the pixels where the keypoints of ``f_a`` are expected in the image of
    ``f_b``, whose keypoints are at ``uv_b`` (Nb, 2). The plane is cut into square cells of
    ``cell`` pixels; keypoint i of ``f_a`` and keypoint j of ``f_b`` are compared when the cell of
    ``uv_pred[i]`` and the cell of ``uv_b[j]`` touch (same cell or one of its 8 neighbours), so each
    keypoint meets at least those within ``cell`` pixels of its prediction. The mutual-best test is
    that of :func:`cross_check_matches` (ties to the lowest index) over the compared pairs; a
    keypoint with a non-finite prediction is compared with none.
    """
    a, b = _as_words(f_a), _as_words(f_b)
    na, nb = a.shape[0], b.shape[0]
    uv_pred = np.asarray(uv_pred, dtype=float).reshape(-1, 2)
    uv_b = np.asarray(uv_b, dtype=float).reshape(-1, 2)
    if uv_pred.shape[0] != na or uv_b.shape[0] != nb:
        raise InputError(f"guided matching needs one pixel per keypoint; got {uv_pred.shape[0]} for {na} and "
                         f"{uv_b.shape[0]} for {nb}")
    if not (is_real(cell) and cell > 0 and math.isfinite(cell)):
        raise InputError(f"the cell size must be a positive number of pixels, got {cell!r}")
    if not np.all(np.isfinite(uv_b)):
        raise InputError("guided matching needs finite pixels of the keypoints it matches against")
    empty = (np.zeros(0, np.intp), np.zeros(0, np.intp), np.zeros(0, np.uint16))
    if na == 0 or nb == 0:
        return empty
    # cells of f_b's keypoints, and f_b sorted by cell (row-major: a row of cells is contiguous)
    gx0, gy0 = np.floor(uv_b.min(axis=0) / cell) - 1
    bx = (np.floor(uv_b[:, 0] / cell) - gx0).astype(np.intp)
    by = (np.floor(uv_b[:, 1] / cell) - gy0).astype(np.intp)
    nx, ny = int(bx.max()) + 2, int(by.max()) + 2
    order = np.argsort(by * nx + bx, kind="stable").astype(np.int32)
    start = np.zeros(nx * ny + 1, np.intp)
    np.cumsum(np.bincount(by * nx + bx, minlength=nx * ny), out=start[1:])
    # each keypoint of f_a: its cell's three rows of three cells among f_b's
    with np.errstate(invalid="ignore"):
        px = np.floor(uv_pred[:, 0] / cell) - gx0
        py = np.floor(uv_pred[:, 1] / cell) - gy0
        near = (px >= 0) & (px < nx) & (py >= 0) & (py < ny)  # else no cell of f_b's touches it
    ia = np.flatnonzero(near).astype(np.int32)
    if ia.shape[0] == 0:
        return empty
    px, py = px[ia].astype(np.intp), py[ia].astype(np.intp)
    x0, x1 = np.maximum(px - 1, 0), np.minimum(px + 1, nx - 1)
    rows = np.clip(py[:, None] + np.arange(-1, 2), 0, ny - 1)
    lo = start[rows * nx + x0[:, None]]
    hi = start[rows * nx + x1[:, None] + 1]
    hi[:, 0] = np.where(py > 0, hi[:, 0], lo[:, 0])  # the clipped rows would repeat a row
    hi[:, 2] = np.where(py < ny - 1, hi[:, 2], lo[:, 2])
    counts = (hi - lo).ravel()
    total = int(counts.sum())
    if total == 0:
        return empty
    # the compared pairs, grouped by i (ascending), j in cell order
    first = np.cumsum(counts) - counts
    ii = np.repeat(np.repeat(ia, 3), counts)
    jj = np.take(order, np.arange(total, dtype=np.int32) + np.repeat((lo.ravel() - first).astype(np.int32), counts))
    x = np.take(a, ii, axis=0)
    x ^= np.take(b, jj, axis=0)
    if hamming2:
        np.bitwise_or(x, x >> np.uint64(1), out=x)
        np.bitwise_and(x, _HAMMING2_MASK, out=x)
    c = _bitcount(x, np.empty(x.shape, np.uint8))
    # keys (distance << shift) | index: the smallest key is the best distance, ties to the lowest index
    shift, key_type = (20, np.int32) if max(na, nb) <= 1 << 20 else (32, np.int64)  # distance <= 256
    d = np.add(c[:, 0], c[:, 1]).astype(key_type)
    d += c[:, 2]
    d += c[:, 3]
    d <<= shift
    low = (1 << shift) - 1
    # forward: the best (distance, j) per i; backward: the best (distance, i) per j
    per_i = counts.reshape(-1, 3).sum(axis=1)
    has = per_i > 0
    best_j = np.minimum.reduceat(d | jj, (np.cumsum(per_i) - per_i)[has])
    best_i = np.full(nb, np.iinfo(key_type).max, key_type)
    np.minimum.at(best_i, jj, d | ii)
    i_has = ia[has]
    j_best = (best_j & low).astype(np.intp)
    mutual = (best_i[j_best] & low) == i_has
    return i_has[mutual].astype(np.intp), j_best[mutual], (best_j[mutual] >> shift).astype(np.uint16)


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
