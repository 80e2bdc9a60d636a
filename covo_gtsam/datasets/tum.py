"""TUM RGB-D benchmark reader (folder with rgb.txt, depth.txt, rgb/, depth/, groundtruth.txt).

Colour and depth are associated by nearest timestamp, at most ``max_dt`` (0.02 s) apart,
one-to-one, smallest difference first (the benchmark's ``associate.py``). Ground truth
(T_world,cam of the colour camera at ~100 Hz) is interpolated at the colour timestamps:
linear in translation, slerp in rotation. Images are not decoded here.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..errors import DatasetError
from ..geometry import make_pose, matrix_to_quat, quat_to_matrix
from ..io import load_tum_trajectory


@dataclass(frozen=True)
class Frame:
    timestamp: float
    rgb_path: str
    depth_path: str


def read_file_list(path: Path) -> tuple[np.ndarray, list[str]]:
    """Timestamps and file names of a TUM ``rgb.txt`` / ``depth.txt``."""
    try:
        lines = path.read_text().splitlines()
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    stamps, names = [], []
    for no, line in enumerate(lines, 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.split()
        try:
            if len(parts) < 2:
                raise ValueError
            stamps.append(float(parts[0]))
        except ValueError:
            raise DatasetError(f"{path}:{no}: expected 'timestamp filename', got {s[:60]!r}") from None
        names.append(parts[1])
    return np.array(stamps, dtype=float), names


def associate(rgb_stamps: np.ndarray, depth_stamps: np.ndarray, max_dt: float = 0.02) -> list[tuple[int, int]]:
    """One-to-one pairs ``(i_rgb, i_depth)`` with ``|dt| <= max_dt``, smallest difference first, by rgb time."""
    a = np.asarray(rgb_stamps, dtype=float)
    b = np.asarray(depth_stamps, dtype=float)
    if a.size == 0 or b.size == 0:
        return []
    order_b = np.argsort(b)
    bs = b[order_b]
    cand = []
    # candidates: the depth stamps within max_dt of each rgb stamp
    lo = np.searchsorted(bs, a - max_dt, side="left")
    hi = np.searchsorted(bs, a + max_dt, side="right")
    for i in np.flatnonzero(hi > lo):
        for j in range(lo[i], hi[i]):
            cand.append((abs(a[i] - bs[j]), i, int(order_b[j])))
    cand.sort()
    used_a, used_b, pairs = set(), set(), []
    for _, i, j in cand:
        if i in used_a or j in used_b:
            continue
        used_a.add(i)
        used_b.add(j)
        pairs.append((int(i), j))
    pairs.sort()
    return pairs


def interpolate_poses(
    gt_stamps: np.ndarray, gt_poses: np.ndarray, query: np.ndarray, max_gap: float = 0.1
) -> tuple[np.ndarray, np.ndarray]:
    """Poses (K, 4, 4) at ``query`` stamps (linear + slerp) and a validity mask (K,).

    Invalid (identity, mask False) outside the ground-truth span or where the bracketing samples
    are more than ``max_gap`` seconds apart.
    """
    ts = np.asarray(gt_stamps, dtype=float)
    order = np.argsort(ts)
    ts, P = ts[order], np.asarray(gt_poses)[order]
    q = np.asarray(query, dtype=float)
    out = np.tile(np.eye(4), (q.shape[0], 1, 1))
    if ts.size == 0:
        return out, np.zeros(q.shape[0], bool)
    j = np.clip(np.searchsorted(ts, q, side="right"), 1, max(ts.size - 1, 1))
    i = j - 1
    exact = np.isclose(q, ts[np.minimum(i, ts.size - 1)], atol=1e-9, rtol=0)
    valid = (q >= ts[0]) & (q <= ts[-1]) & ((ts[j] - ts[i] <= max_gap) | exact) if ts.size > 1 else exact
    if ts.size == 1:
        out[exact] = P[0]
        return out, valid
    dt = np.where(ts[j] > ts[i], ts[j] - ts[i], 1.0)
    s = np.clip((q - ts[i]) / dt, 0.0, 1.0)
    t = (1 - s)[:, None] * P[i, :3, 3] + s[:, None] * P[j, :3, 3]
    q0 = matrix_to_quat(P[i, :3, :3])
    q1 = matrix_to_quat(P[j, :3, :3])
    dot = np.sum(q0 * q1, axis=1)
    q1 = np.where(dot[:, None] < 0, -q1, q1)
    dot = np.abs(dot)
    omega = np.arccos(np.clip(dot, -1.0, 1.0))
    so = np.sin(omega)
    lin = so < 1e-9
    w0 = np.where(lin, 1 - s, np.sin((1 - s) * omega) / np.where(lin, 1.0, so))
    w1 = np.where(lin, s, np.sin(s * omega) / np.where(lin, 1.0, so))
    qs = w0[:, None] * q0 + w1[:, None] * q1
    poses = make_pose(quat_to_matrix(qs), t)
    out[valid] = poses[valid]
    return out, valid


def camera_name_from_path(path: Path) -> str | None:
    """``"fr1"``/``"fr2"``/``"fr3"`` from a folder name containing ``freiburgN``, else None."""
    m = re.search(r"freiburg([123])", path.name)
    return f"fr{m.group(1)}" if m else None


class TumSequence:
    """A TUM RGB-D sequence folder; frames are associated colour/depth file pairs.

    Attributes: ``path``, ``name``, ``camera_name``, ``camera`` (preset or the given camera),
    ``timestamps`` (colour stamps, s), ``rgb_paths``, ``depth_paths``, ``groundtruth``
    (T_world,cam (K, 4, 4) at the frame stamps, or None) and ``gt_valid`` (K,).
    """

    def __init__(self, path: str | os.PathLike, camera: Camera | None = None, max_dt: float = 0.02) -> None:
        self.path = Path(path)
        if not self.path.is_dir():
            raise DatasetError(f"{self.path}: sequence folder does not exist")
        self.name = self.path.name
        for f in ("rgb.txt", "depth.txt"):
            if not (self.path / f).is_file():
                raise DatasetError(f"{self.path / f}: missing (a TUM sequence folder has rgb.txt and depth.txt)")
        rgb_t, rgb_n = read_file_list(self.path / "rgb.txt")
        dep_t, dep_n = read_file_list(self.path / "depth.txt")
        pairs = associate(rgb_t, dep_t, max_dt)
        if not pairs:
            raise DatasetError(f"{self.path}: no colour frame has a depth frame within {max_dt} s")
        self.timestamps = np.array([rgb_t[i] for i, _ in pairs])
        self.rgb_paths = [str(self.path / rgb_n[i]) for i, _ in pairs]
        self.depth_paths = [str(self.path / dep_n[j]) for _, j in pairs]
        for listing, paths in (("rgb.txt", self.rgb_paths), ("depth.txt", self.depth_paths)):
            missing = next((p for p in paths if not os.path.isfile(p)), None)
            if missing is not None:
                raise DatasetError(f"{self.path / listing} lists {missing}, which does not exist")
        self.camera_name = camera_name_from_path(self.path)
        if camera is not None:
            self.camera = camera
        elif self.camera_name is not None:
            self.camera = Camera.preset(self.camera_name)
        else:
            raise DatasetError(
                f"{self.path}: cannot tell the camera from the folder name (no 'freiburg1/2/3'); pass --camera"
            )
        self.groundtruth: np.ndarray | None = None
        self.gt_valid = np.zeros(len(self.timestamps), bool)
        gt_file = self.path / "groundtruth.txt"
        if gt_file.is_file():
            stamps, poses = load_tum_trajectory(gt_file)
            if stamps.size:
                self.groundtruth, self.gt_valid = interpolate_poses(stamps, poses, self.timestamps)

    def __len__(self) -> int:
        return len(self.timestamps)

    def __getitem__(self, i: int) -> Frame:
        return Frame(float(self.timestamps[i]), self.rgb_paths[i], self.depth_paths[i])
