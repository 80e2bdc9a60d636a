"""File I/O at the edges: TUM trajectories, relative-pose files with covariances, JSON.

Trajectory files use the TUM format ``t tx ty tz qx qy qz qw`` (evo reads them as they are).
Relative-pose files hold one line per frame pair::

    t_ref t_cur tx ty tz qx qy qz qw c00 c01 ... c55

where the pose is T_ref,cur (maps points of the current frame into the reference frame) and the
36 values are its 6x6 covariance, row-major, in GTSAM's Pose3 tangent ``[rx ry rz tx ty tz]``
with the right perturbation ``T_true = T_est * Exp(xi)``.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import IO

import numpy as np

from .errors import DatasetError
from .geometry import pose_from_tum, pose_to_tum

RELATIVE_HEADER = (
    "# covo-gtsam relative poses\n"
    "# t_ref t_cur tx ty tz qx qy qz qw c00 c01 ... c55\n"
    "# pose: T_ref,cur maps points of the current camera frame into the reference camera frame\n"
    "# covariance: 6x6 row-major, GTSAM Pose3 tangent [rx ry rz tx ty tz] (rad, m),\n"
    "#   right perturbation T_true = T_est * Exp(xi)\n"
)
TRAJECTORY_HEADER = "# timestamp tx ty tz qx qy qz qw (T_world,cam; world = first camera frame)\n"


def _load_rows(path: str | os.PathLike, min_cols: int) -> np.ndarray:
    p = Path(path)
    try:
        lines = p.read_text().splitlines()
    except OSError as exc:
        raise DatasetError(f"{p}: cannot read ({exc.strerror or exc})") from exc
    rows = []
    for no, line in enumerate(lines, 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.replace(",", " ").split()
        try:
            vals = [float(x) for x in parts]
        except ValueError:
            raise DatasetError(f"{p}:{no}: not a line of numbers: {s[:60]!r}") from None
        if len(vals) < min_cols:
            raise DatasetError(f"{p}:{no}: expected {min_cols} values, got {len(vals)}")
        rows.append(vals[:min_cols])
    return np.array(rows, dtype=float).reshape(-1, min_cols)


def format_tum_line(t: float, T: np.ndarray) -> str:
    """One TUM trajectory line of a timestamp (s) and a 4x4 pose."""
    row = pose_to_tum(T)
    return f"{t:.6f} " + " ".join(f"{v:.9f}" for v in row) + "\n"


def write_tum_trajectory(path: str | os.PathLike, stamps: np.ndarray, poses: np.ndarray) -> None:
    """Write stamps (N,) and 4x4 poses (N, 4, 4) in TUM format."""
    with TrajectoryWriter(path) as w:
        for t, T in zip(stamps, poses):
            w.write(float(t), T)


def load_tum_trajectory(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Stamps (N,) and poses (N, 4, 4) of a TUM trajectory file (also ``groundtruth.txt``)."""
    rows = _load_rows(path, 8)
    return rows[:, 0], pose_from_tum(rows[:, 1:8]).reshape(-1, 4, 4)


def format_relative_line(t_ref: float, t_cur: float, T: np.ndarray, cov: np.ndarray) -> str:
    """One relative-pose line (see the module docstring)."""
    row = pose_to_tum(T)
    return (
        f"{t_ref:.6f} {t_cur:.6f} "
        + " ".join(f"{v:.9f}" for v in row)
        + " "
        + " ".join(f"{v:.9e}" for v in np.asarray(cov, dtype=float).reshape(36))
        + "\n"
    )


def write_relative_header(fileobj: IO[str]) -> None:
    fileobj.write(RELATIVE_HEADER)


def load_relative_poses(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``t_ref`` (N,), ``t_cur`` (N,), T_ref,cur (N, 4, 4) and covariances (N, 6, 6) of a relative file."""
    rows = _load_rows(path, 45)
    return rows[:, 0], rows[:, 1], pose_from_tum(rows[:, 2:9]).reshape(-1, 4, 4), rows[:, 9:45].reshape(-1, 6, 6)


class _LineWriter:
    """Opens ``path``, writes a header, appends one flushed line per :meth:`write`."""

    header = ""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        try:
            self._f = open(self.path, "w")
        except OSError as exc:
            raise DatasetError(f"{self.path}: cannot write ({exc.strerror or exc})") from exc
        self._f.write(self.header)
        self._f.flush()

    def _write(self, line: str) -> None:
        self._f.write(line)
        self._f.flush()

    def close(self) -> None:
        self._f.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class TrajectoryWriter(_LineWriter):
    """TUM trajectory file written line by line: ``write(t, T_world_cam)``."""

    header = TRAJECTORY_HEADER

    def write(self, t: float, T: np.ndarray) -> None:
        self._write(format_tum_line(t, T))


class RelativePoseWriter(_LineWriter):
    """Relative-pose file written line by line: ``write(t_ref, t_cur, T_ref_cur, cov)``."""

    header = RELATIVE_HEADER

    def write(self, t_ref: float, t_cur: float, T: np.ndarray, cov: np.ndarray) -> None:
        self._write(format_relative_line(t_ref, t_cur, T, cov))


def _plain(obj):
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _plain(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def write_json(path: str | os.PathLike, obj) -> None:
    """Write ``obj`` as indented JSON atomically (temporary file + rename); numpy values become plain."""
    p = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=".json", dir=p.parent)
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(_plain(obj), f, indent=2)
            f.write("\n")
        os.replace(tmp, p)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
