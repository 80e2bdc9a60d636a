"""TUM RGB-D benchmark reader (folder with rgb.txt, depth.txt, rgb/, depth/, groundtruth.txt).

Colour and depth are associated by nearest timestamp, at most ``max_dt`` (0.02 s) apart,
one-to-one, smallest difference first (the benchmark's ``associate.py``). Ground truth
(T_world,cam of the colour camera, ~100 Hz) is interpolated at the colour timestamps: linear in
translation, slerp in rotation. Frames are decoded on request (:meth:`TumSequence.load`,
:meth:`~TumSequence.loader`, :meth:`~TumSequence.images`): the grey image and the depth in metres,
raw 16-bit values divided by the sequence's ``depth_scale`` (:data:`DEPTH_SCALE`, 5000 per metre,
unless given).
"""

from __future__ import annotations

import os
import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ConfigError, CovoWarning, DatasetError, InputError
from ..geometry import make_pose, matrix_to_quat, quat_to_matrix
from ..io import data_lines, file_problem, load_tum_trajectory
from ..validation import check_real
from .images import load_depth, load_grey

#: Largest ground-truth position coordinate (m) used: beyond it (far beyond any geodetic coordinate)
#: relative poses of two frames lose all precision or overflow, so such frames count as without
#: ground truth.
MAX_GT_COORDINATE = 1e9
#: Raw units per metre of the TUM depth images (16-bit PNG, value / 5000 = metres).
DEPTH_SCALE = 5000.0

__all__ = ["DEPTH_SCALE", "Frame", "TumSequence", "associate", "interpolate_poses", "read_file_list",
           "camera_name_from_path"]


@dataclass(frozen=True)
class Frame:
    """One associated frame: colour timestamp (s) and absolute image paths (not decoded; see
    :meth:`TumSequence.load`)."""

    timestamp: float
    rgb_path: str
    depth_path: str


def read_file_list(path: str | os.PathLike) -> tuple[np.ndarray, list[str]]:
    """Timestamps (N,) in s and file names of a TUM ``rgb.txt`` / ``depth.txt`` (``timestamp filename`` lines).

    ``#`` comment lines and blank lines are skipped, and so is a line that repeats an earlier one
    exactly (the same timestamp and file: an extraction that wrote it twice). A malformed line, a
    timestamp that an earlier line already has with another file (two images at one instant:
    association by time could not tell them apart), or a file that an earlier line already has with
    another timestamp (one image at two instants: a frame pair without motion under a wrong stamp)
    raises :class:`DatasetError` naming the file and the line numbers.
    """
    p = Path(path)
    stamps, names = [], []
    first_line: dict[float, int] = {}
    name_at: dict[float, str] = {}
    listed_at: dict[str, tuple[int, str]] = {}  # image path (normalised) -> (line, timestamp as written)
    for no, s in data_lines(p):
        parts = s.split()
        try:
            if len(parts) != 2:
                raise ValueError
            t = float(parts[0])
            if not np.isfinite(t):
                raise ValueError
        except ValueError:
            raise DatasetError(f"{p}:{no}: expected 'timestamp filename', got {s[:80]!r}") from None
        image = os.path.normpath(parts[1])
        if t in first_line:
            if os.path.normpath(name_at[t]) == image:  # the same line again
                continue
            raise DatasetError(f"{p}:{no}: timestamp {parts[0]} repeats the one of line {first_line[t]} (two "
                               "images at one instant; each image needs its own timestamp)")
        if image in listed_at:
            line, stamp = listed_at[image]
            raise DatasetError(f"{p}:{no}: image {parts[1]} is listed at line {line} already, with timestamp {stamp} "
                               f"(here {parts[0]}): one image at two instants; each timestamp needs its own image")
        listed_at[image] = (no, parts[0])
        first_line[t], name_at[t] = no, parts[1]
        stamps.append(t)
        names.append(parts[1])
    return np.array(stamps, dtype=float), names


def associate(rgb_stamps: np.ndarray, depth_stamps: np.ndarray, max_dt: float = 0.02) -> list[tuple[int, int]]:
    """One-to-one index pairs ``(i_rgb, i_depth)`` with ``|t_rgb - t_depth| <= max_dt`` (s).

    Greedy like the benchmark's ``associate.py``: candidate pairs are taken by increasing time
    difference (ties: earlier rgb, then earlier depth stamp), skipping those whose rgb or depth
    index is already used. The result is sorted by rgb time.
    """
    a = np.asarray(rgb_stamps, dtype=float).reshape(-1)
    b = np.asarray(depth_stamps, dtype=float).reshape(-1)
    if a.size == 0 or b.size == 0:
        return []
    order_b = np.argsort(b, kind="stable")
    bs = b[order_b]
    # candidates: every depth stamp within max_dt of each rgb stamp (a small window per rgb stamp)
    lo = np.searchsorted(bs, a - max_dt, side="left")
    hi = np.searchsorted(bs, a + max_dt, side="right")
    counts = np.maximum(hi - lo, 0)
    total = int(counts.sum())
    if total == 0:
        return []
    ia = np.repeat(np.arange(a.size), counts)
    starts = np.repeat(lo, counts)
    offsets = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
    jb = order_b[starts + offsets]
    dt = np.abs(a[ia] - b[jb])
    keep = dt <= max_dt  # the window bounds were computed with rounded sums
    ia, jb, dt = ia[keep], jb[keep], dt[keep]
    order = np.lexsort((b[jb], a[ia], dt))
    used_a = np.zeros(a.size, bool)
    used_b = np.zeros(b.size, bool)
    chosen = []
    for i, j in zip(ia[order].tolist(), jb[order].tolist()):  # greedy pass: inherently sequential
        if used_a[i] or used_b[j]:
            continue
        used_a[i] = used_b[j] = True
        chosen.append((i, j))
    chosen.sort(key=lambda p: (a[p[0]], p[0]))
    return chosen


def interpolate_poses(
    gt_stamps: np.ndarray, gt_poses: np.ndarray, query_stamps: np.ndarray, max_gap: float = 0.1
) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth poses (K, 4, 4) at ``query_stamps`` (K,) and a validity mask (K,).

    Between the bracketing samples the translation is interpolated linearly and the rotation by
    slerp; a query equal to a ground-truth stamp returns that pose exactly. Queries outside the
    ground-truth span, or whose bracketing samples are more than ``max_gap`` seconds apart, are
    invalid: mask False and an identity pose (no NaN).
    """
    ts = np.asarray(gt_stamps, dtype=float).reshape(-1)
    P = np.asarray(gt_poses, dtype=float).reshape(-1, 4, 4)
    if ts.shape[0] != P.shape[0]:
        raise ValueError(f"{ts.shape[0]} ground-truth stamps but {P.shape[0]} poses")
    order = np.argsort(ts, kind="stable")
    ts, P = ts[order], P[order]
    q = np.asarray(query_stamps, dtype=float).reshape(-1)
    out = np.tile(np.eye(4), (q.shape[0], 1, 1))
    valid = np.zeros(q.shape[0], bool)
    m = ts.shape[0]
    if m == 0 or q.shape[0] == 0:
        return out, valid

    j = np.searchsorted(ts, q, side="right")  # first sample strictly after q
    i = np.clip(j - 1, 0, m - 1)
    exact = (j >= 1) & (ts[i] == q)
    jj = np.minimum(j, m - 1)
    interp = ~exact & (q > ts[0]) & (q < ts[-1]) & (ts[jj] - ts[i] <= max_gap)

    out[exact] = P[i[exact]]
    valid[exact] = True
    if np.any(interp):
        i0, i1, qi = i[interp], jj[interp], q[interp]
        s = (qi - ts[i0]) / (ts[i1] - ts[i0])
        t = (1.0 - s)[:, None] * P[i0, :3, 3] + s[:, None] * P[i1, :3, 3]
        q0 = matrix_to_quat(P[i0, :3, :3])
        q1 = matrix_to_quat(P[i1, :3, :3])
        dot = np.sum(q0 * q1, axis=1)
        q1 = np.where(dot[:, None] < 0, -q1, q1)  # shortest arc
        omega = np.arccos(np.clip(np.abs(dot), -1.0, 1.0))
        so = np.sin(omega)
        small = so < 1e-9
        so_safe = np.where(small, 1.0, so)
        w0 = np.where(small, 1.0 - s, np.sin((1.0 - s) * omega) / so_safe)
        w1 = np.where(small, s, np.sin(s * omega) / so_safe)
        out[interp] = make_pose(quat_to_matrix(w0[:, None] * q0 + w1[:, None] * q1), t)
        valid[interp] = True
    return out, valid


def camera_name_from_path(path: str | os.PathLike) -> str | None:
    """``"fr1"``/``"fr2"``/``"fr3"`` from a folder name containing ``freiburg1/2/3``, else None
    (also when it names two of them, e.g. ``freiburg3_from_freiburg1``: no guess)."""
    names = {f"fr{n}" for n in re.findall(r"freiburg([123])", Path(path).name, flags=re.IGNORECASE)}
    return names.pop() if len(names) == 1 else None


class TumSequence:
    """A TUM RGB-D sequence folder; frames are associated colour/depth file pairs.

    Attributes: ``path`` (absolute), ``name`` (folder name), ``camera_name`` (``"fr1"``/``"fr2"``/
    ``"fr3"`` from the folder name, or None), ``timestamps`` (colour stamps of the frames, s, (K,)),
    ``depth_timestamps`` (the stamps of their depth images, s, (K,)),
    ``rgb_paths`` / ``depth_paths`` (absolute paths), ``groundtruth`` (T_world,cam (K, 4, 4) at the
    frame stamps, or None without ``groundtruth.txt``), ``gt_valid`` (K,) bool (the frame's stamp is
    inside the ground truth's span, between samples at most ``max_gap`` apart, and its position is
    within :data:`MAX_GT_COORDINATE` m) and
    ``unassociated`` (``(timestamp, file name)`` of the colour frames of ``rgb.txt`` without a
    depth image within ``max_dt``; they are no frames of the sequence) and
    ``missing_files`` (listed image files that do not exist or cannot be read; their frames are
    reported lost when read).
    ``camera`` is the given camera (a :class:`~covo_gtsam.camera.Camera`, or a preset name such as
    ``"fr1"``, which must be known: :class:`ConfigError` otherwise), else the preset named by
    ``camera_name`` (reading it raises :class:`DatasetError` when neither is known).
    ``depth_scale`` is the depth images' raw units per metre (:data:`DEPTH_SCALE` unless given; a
    positive number, :class:`ConfigError` otherwise).

    Frames are decoded by :meth:`load` (one frame), :meth:`loader` (a thread-safe function of the
    frame index) and :meth:`images` (frames in order).

    Raises :class:`DatasetError` when the folder, ``rgb.txt`` or ``depth.txt`` is missing, a line
    is malformed, a timestamp or an image repeats within ``rgb.txt`` or ``depth.txt`` (exactly
    repeated lines are read once), a timestamp repeats within ``groundtruth.txt`` with a different
    pose (exactly repeated ground-truth samples are dropped), no frame can be associated, or no
    associated frame has both of its images.
    """

    def __init__(self, path: str | os.PathLike, camera=None, max_dt: float = 0.02, max_gap: float = 0.1,
                 depth_scale: float = DEPTH_SCALE) -> None:
        check_real("depth_scale", depth_scale, "positive")
        self.depth_scale = float(depth_scale)
        self.path = Path(os.path.abspath(os.fspath(path)))
        if self.path.exists() and not self.path.is_dir():
            raise DatasetError(f"{self.path}: is a file, neither a TUM sequence folder nor a ROS bag")
        if not self.path.is_dir():
            raise DatasetError(f"{self.path}: sequence folder does not exist")
        self.name = self.path.name
        for f in ("rgb.txt", "depth.txt"):
            problem = file_problem(self.path / f)
            if problem is not None:
                what = "missing" if problem == "does not exist" else problem
                raise DatasetError(f"{self.path / f}: {what} (a TUM sequence folder has rgb.txt and depth.txt)")
        rgb_t, rgb_n = read_file_list(self.path / "rgb.txt")
        dep_t, dep_n = read_file_list(self.path / "depth.txt")
        for name, stamps in (("rgb.txt", rgb_t), ("depth.txt", dep_t)):
            if not len(stamps):
                raise DatasetError(f"{self.path / name}: lists no image")
        pairs = associate(rgb_t, dep_t, max_dt)
        if not pairs:
            raise DatasetError(
                f"{self.path}: no frame could be associated: no colour stamp of rgb.txt ({len(rgb_t)} lines) has a "
                f"depth stamp of depth.txt ({len(dep_t)} lines) within {max_dt} s"
            )
        used = {i for i, _ in pairs}
        #: colour frames of rgb.txt without a depth image within max_dt: (timestamp, file name)
        self.unassociated = sorted((float(rgb_t[i]), rgb_n[i]) for i in range(len(rgb_t)) if i not in used)
        self.max_dt = max_dt
        self.timestamps = np.array([rgb_t[i] for i, _ in pairs], dtype=float)
        self.depth_timestamps = np.array([dep_t[j] for _, j in pairs], dtype=float)
        self.rgb_paths = [str(self.path / rgb_n[i]) for i, _ in pairs]
        self.depth_paths = [str(self.path / dep_n[j]) for _, j in pairs]
        # A listed file that is missing makes its frame lost when it is read (the run goes on);
        # when no frame has both of its images the folder itself is wrong.
        problems = {p: file_problem(p) for pair in zip(self.rgb_paths, self.depth_paths) for p in pair}
        self.missing_files = [p for p, problem in problems.items() if problem is not None]
        missing = set(self.missing_files)
        if all(rp in missing or dp in missing for rp, dp in zip(self.rgb_paths, self.depth_paths)):
            first = self.missing_files[0]
            raise DatasetError(f"{self.path}: no frame has both its colour and its depth image "
                               f"(e.g. {first} {problems[first]})")
        self.camera_name = camera_name_from_path(self.path)
        if isinstance(camera, str):  # a preset name
            from ..camera import Camera

            camera = Camera.preset(camera)
        self._camera = camera

        self.groundtruth: np.ndarray | None = None
        self.gt_valid = np.zeros(len(self.timestamps), bool)
        #: the ground truth's own samples ``(stamps (M,) s, T_world,cam (M, 4, 4))``, one per stamp, or None
        self.gt_samples: tuple[np.ndarray, np.ndarray] | None = None
        gt_file = self.path / "groundtruth.txt"
        if gt_file.is_file():
            stamps, poses = load_tum_trajectory(gt_file, skip_invalid=True)
            far = ~usable_poses(poses)
            if far.any():  # before interpolating: a weight would bring such a sample below the limit
                warnings.warn(f"{gt_file}: {int(far.sum())} sample(s) more than {MAX_GT_COORDINATE:g} m from the "
                              f"origin left out (stamp {', '.join(f'{t:.4f}' for t in stamps[far][:3])}"
                              f"{', ...' if far.sum() > 3 else ''})", CovoWarning, stacklevel=2)
                stamps, poses = stamps[~far], poses[~far]
            if stamps.size:
                self.gt_samples = (stamps, poses)
                self.groundtruth, self.gt_valid = interpolate_poses(stamps, poses, self.timestamps, max_gap)
                self.gt_valid &= usable_poses(self.groundtruth)

    @property
    def camera(self):
        """The camera given to the constructor, else the ``camera_name`` preset."""
        if self._camera is None:
            if self.camera_name is None:
                named = sorted(set(re.findall(r"freiburg[123]", self.path.name, flags=re.IGNORECASE)))
                why = f"it names {' and '.join(named)}" if named else "no 'freiburg1/2/3'"
                raise DatasetError(
                    f"{self.path}: cannot tell the camera from the folder name ({why}); "
                    "pass a camera (CLI: --camera)"
                )
            from ..camera import Camera

            self._camera = Camera.preset(self.camera_name)
        return self._camera

    def __len__(self) -> int:
        return len(self.timestamps)

    def __getitem__(self, i: int) -> Frame:
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"frame index {i} out of range for {n} frames")
        return Frame(float(self.timestamps[i]), self.rgb_paths[i], self.depth_paths[i])

    def __iter__(self):
        return (self[i] for i in range(len(self)))

    def load(self, i: int, camera=None, depth_scale: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Frame ``i`` decoded: ``(grey uint8 (H, W), depth float32 metres (H, W))``, 0 = no depth.

        Depth is the raw 16-bit value / ``depth_scale`` (the sequence's :attr:`depth_scale` if
        None); both images must have the size of ``camera`` (the sequence's :attr:`camera` if None).

        Raises:
            InputError: an image file is missing, unreadable or corrupt, the depth image is not a
                single-channel 16-bit image, or an image is not of the camera's size (the message
                names the file).
        """
        camera = self.camera if camera is None else camera
        depth_scale = self.depth_scale if depth_scale is None else depth_scale
        grey = load_grey(self.rgb_paths[i], shape=(camera.height, camera.width))
        return grey, load_depth(self.depth_paths[i], depth_scale, shape=(camera.height, camera.width))

    def loader(self, camera=None, depth_scale: float | None = None):
        """A thread-safe function ``i -> load(i, camera, depth_scale)`` (frames are files, decoded
        independently in any order)."""

        def load(i: int):
            return self.load(i, camera, depth_scale)

        return load

    def images(self, n: int | None = None):
        """``(grey, depth in metres)`` of frames ``0 .. n-1`` (all if None) in order (:meth:`load`);
        a frame that cannot be decoded yields its :class:`InputError` in its place, as
        :meth:`~covo_gtsam.datasets.rosbag.RosbagSequence.images` does."""
        n = len(self) if n is None else min(int(n), len(self))
        for i in range(n):
            try:
                yield self.load(i)
            except InputError as exc:
                yield exc

    def frames(self, start: int, stop: int | None = None) -> "TumSequence":
        """The same sequence restricted to frames ``start`` to ``stop - 1`` (a copy; ``stop`` None:
        to the end). Raises :class:`ConfigError` unless ``0 <= start < stop <= len(self)``."""
        import copy

        stop = len(self) if stop is None else stop
        if not (isinstance(start, int) and isinstance(stop, int) and 0 <= start < stop <= len(self)):
            raise ConfigError(f"frames need 0 <= start < stop <= {len(self)}, got {start!r}, {stop!r}")
        part = copy.copy(self)
        part.timestamps = self.timestamps[start:stop]
        part.depth_timestamps = self.depth_timestamps[start:stop]
        part.rgb_paths, part.depth_paths = self.rgb_paths[start:stop], self.depth_paths[start:stop]
        listed = set(part.rgb_paths) | set(part.depth_paths)
        part.missing_files = [f for f in self.missing_files if f in listed]
        lo, hi = part.timestamps[0], part.timestamps[-1]
        part.unassociated = [u for u in self.unassociated
                             if (start == 0 or u[0] >= lo) and (stop == len(self) or u[0] <= hi)]
        part.gt_valid = self.gt_valid[start:stop]
        part.groundtruth = None if self.groundtruth is None else self.groundtruth[start:stop]
        return part

    def __repr__(self) -> str:
        gt = "no ground truth" if self.groundtruth is None else f"{int(self.gt_valid.sum())} with ground truth"
        return f"TumSequence({self.name!r}, {len(self)} frames, {gt})"


def usable_poses(P: np.ndarray) -> np.ndarray:
    """Which ground-truth poses (K, 4, 4) are usable (K,): finite, positions within
    :data:`MAX_GT_COORDINATE` m."""
    P = np.asarray(P, dtype=float)
    with np.errstate(invalid="ignore"):
        return np.isfinite(P).all(axis=(1, 2)) & (np.abs(P[:, :3, 3]).max(axis=1) <= MAX_GT_COORDINATE)
