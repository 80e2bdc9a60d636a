"""File I/O at the edges: TUM trajectories, relative-pose files with covariances, JSON.

Trajectory files use the TUM format ``t tx ty tz qx qy qz qw`` (``%.6f`` stamps in s, ``%.9f``
values in m and unit quaternions ``(qx, qy, qz, qw)``); evo reads them as they are. Relative-pose
files hold one line per frame pair::

    t_ref t_cur tx ty tz qx qy qz qw c00 c01 ... c55

where the pose is T_ref,cur (maps points of the current frame into the reference frame) and the
36 values are its 6x6 covariance, row-major, in GTSAM's Pose3 tangent ``[rx ry rz tx ty tz]``
(rad, m) with the right (body) perturbation ``T_true = T_est * Exp(xi)``.
Both formats allow ``#`` comment lines and blank lines.
"""

from __future__ import annotations

import json
import math
import os
import stat
import tempfile
import warnings
from pathlib import Path
from typing import IO

import numpy as np

from .errors import ConfigError, CovoWarning, DatasetError, InputError
from .geometry import pose_from_tum, pose_to_tum

__all__ = [
    "FolderLock",
    "RELATIVE_HEADER",
    "TRAJECTORY_HEADER",
    "RelativePoseWriter",
    "TrajectoryWriter",
    "format_relative_line",
    "format_tum_line",
    "load_relative_poses",
    "load_tum_trajectory",
    "read_settings_file",
    "write_json",
    "write_relative_header",
    "write_tum_trajectory",
]

RELATIVE_HEADER = (
    "# covo-gtsam relative poses, one line per frame pair:\n"
    "# t_ref t_cur tx ty tz qx qy qz qw c00 c01 ... c55 quality\n"
    "# t_ref, t_cur: timestamps (s) of the reference and current frames\n"
    "# pose: T_ref,cur (m, unit quaternion qx qy qz qw) maps points of the current camera frame into the\n"
    "#   reference camera frame\n"
    "# c00 ... c55: 6x6 covariance, row-major, in GTSAM's Pose3 tangent order [rx ry rz tx ty tz] (rad, m),\n"
    "#   right (body) perturbation T_true = T_est * Exp(xi)\n"
    "# quality: the pair's integrity statistic over the run's scale so far (a pair at the run's running\n"
    "#   median reads 5.35, chi2(6)'s median; a pair over k frame intervals taken on the scale of one),\n"
    "#   larger for a pair\n"
    "#   whose depth-free estimates disagree with it (flagged above the configured threshold, 50 by default;\n"
    "#   its covariance then covers the disagreement); -1 when it could not be formed\n"
)
TRAJECTORY_HEADER = "# timestamp tx ty tz qx qy qz qw (pose T_world,cam: maps camera-frame points into the world frame)\n"

_TUM_COLS = 8
_REL_COLS = 2 + 7 + 36 + 1


def data_lines(path: Path):
    """``(line number, stripped line)`` of a text file, skipping blank and ``#`` comment lines.

    Raises :class:`DatasetError` naming the file when it cannot be read.
    """
    try:
        # as editors write them: a UTF-8 byte-order mark, CRLF or CR line ends; bytes that are not
        # UTF-8 (e.g. Latin-1 file names) are kept as the file system's surrogate escapes
        text = Path(path).read_text(encoding="utf-8-sig", errors="surrogateescape")
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: cannot read ({getattr(exc, 'strerror', None) or exc})") from exc
    if "\x00" in text:  # UTF-16 text (every other byte NUL for ASCII) or a binary file
        raise DatasetError(f"{path}: not a text file in UTF-8 (it holds NUL bytes: UTF-16, or not text)")
    lines = text.splitlines()
    for no, line in enumerate(lines, 1):
        s = line.strip()
        if s and not s.startswith("#"):
            yield no, s


def file_problem(path: str | os.PathLike) -> str | None:
    """Why ``path`` cannot be read as a file -- ``"does not exist"``, ``"is not a file"`` or
    ``"cannot be read (...)"`` (e.g. a folder on the way without permission) -- or None if it can."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return "does not exist"
    except OSError as exc:
        return f"cannot be read ({exc.strerror or exc})"
    if not stat.S_ISREG(st.st_mode):
        return "is not a file"
    if not os.access(path, os.R_OK):
        return "cannot be read (permission denied)"
    return None


def _load_rows(path: str | os.PathLike, ncols: int, what: str, optional: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Numeric rows (N, ncols) of a whitespace-separated file and their line numbers (N,); lines may
    lack the last ``optional`` columns (an older layout), which then read as NaN.

    '#' comment lines and blank lines are skipped; other malformed lines raise :class:`DatasetError`.
    """
    p = Path(path)
    rows, line_nos = [], []
    for no, s in data_lines(p):
        parts = s.replace(",", " ").split()
        if not ncols - optional <= len(parts) <= ncols:
            raise DatasetError(f"{p}:{no}: expected {ncols} values ({what}), got {len(parts)}")
        parts += ["nan"] * (ncols - len(parts))
        try:
            rows.append([float(x) for x in parts])
            line_nos.append(no)
        except ValueError:
            raise DatasetError(f"{p}:{no}: not a line of numbers: {s[:80]!r}") from None
    return np.array(rows, dtype=float).reshape(-1, ncols), np.array(line_nos, dtype=int)


def _invalid_poses(rows: np.ndarray, col: int) -> np.ndarray:
    """Mask (N,) of the rows whose TUM columns ``tx ty tz qx qy qz qw`` (from ``col``) hold a
    non-finite value or a zero quaternion."""
    tum = rows[:, col : col + 7]
    return ~np.isfinite(tum).all(axis=1) | ~(np.linalg.norm(tum[:, 3:7], axis=1) > 1e-12)


def _poses_from_rows(p: str | os.PathLike, rows: np.ndarray, line_nos: np.ndarray, col: int) -> np.ndarray:
    """4x4 poses from TUM columns ``tx ty tz qx qy qz qw`` starting at ``col``; checks the quaternions."""
    bad = np.flatnonzero(_invalid_poses(rows, col))
    if bad.size:
        raise DatasetError(f"{p}:{line_nos[bad[0]]}: non-finite pose value or zero quaternion")
    return pose_from_tum(rows[:, col : col + 7]).reshape(-1, 4, 4)


def _check_pose(T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4):
        raise InputError(f"a pose must be a 4x4 matrix, got shape {T.shape}")
    return T


def format_tum_line(t: float, T: np.ndarray) -> str:
    """One TUM trajectory line (with newline) of a timestamp (s) and a 4x4 pose."""
    row = pose_to_tum(_check_pose(T))
    return f"{float(t):.6f} " + " ".join(f"{v:.9f}" for v in row) + "\n"


def write_tum_trajectory(path: str | os.PathLike, stamps: np.ndarray, poses: np.ndarray) -> None:
    """Write stamps (N,) in s and 4x4 poses (N, 4, 4) as a TUM trajectory file (one '#' header line)."""
    stamps = np.asarray(stamps, dtype=float).reshape(-1)
    poses = np.asarray(poses, dtype=float).reshape(-1, 4, 4)
    if stamps.shape[0] != poses.shape[0]:
        raise InputError(f"{stamps.shape[0]} stamps but {poses.shape[0]} poses")
    rows = pose_to_tum(poses)
    lines = [f"{t:.6f} " + " ".join(f"{v:.9f}" for v in r) + "\n" for t, r in zip(stamps.tolist(), rows.tolist())]
    with TrajectoryWriter(path) as w:
        w._write("".join(lines))


def load_tum_trajectory(path: str | os.PathLike, skip_invalid: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Stamps (N,) in s and poses (N, 4, 4) of a TUM trajectory file (also ``groundtruth.txt``), in
    the file's order, one pose per stamp.

    A line repeating an earlier line's stamp and pose is dropped; one repeating the stamp with a
    different pose raises :class:`DatasetError` naming the file and both lines, as do malformed lines.
    A line with a non-finite stamp or pose value or a zero quaternion raises too, or with
    ``skip_invalid`` (a motion-capture dropout in a ground truth) is left out with a warning naming
    the file and the lines.
    """
    rows, line_nos = _load_rows(path, _TUM_COLS, "timestamp tx ty tz qx qy qz qw")
    bad_stamps = ~np.isfinite(rows[:, 0])
    if skip_invalid:
        bad = _invalid_poses(rows, 1) | bad_stamps
        if bad.any():
            shown = ", ".join(str(n) for n in line_nos[bad][:5]) + (", ..." if bad.sum() > 5 else "")
            warnings.warn(f"{path}: {int(bad.sum())} line(s) with a non-finite value or a zero quaternion left "
                          f"out (line {shown})", CovoWarning, stacklevel=2)
            rows, line_nos = rows[~bad], line_nos[~bad]
    elif bad_stamps.any():
        raise DatasetError(f"{path}:{line_nos[np.flatnonzero(bad_stamps)[0]]}: non-finite timestamp")
    stamps, poses = rows[:, 0].copy(), _poses_from_rows(path, rows, line_nos, 1)  # checks the poses left
    keep = _first_of_each_stamp(path, stamps, poses, line_nos)
    return stamps[keep], poses[keep]


def _first_of_each_stamp(p: str | os.PathLike, stamps: np.ndarray, poses: np.ndarray, line_nos: np.ndarray
                         ) -> np.ndarray:
    """Mask (N,) of the lines to keep: the first line of each stamp (s). A later line with the same
    stamp and pose (4x4, exactly equal) is a repeat; one with another pose raises :class:`DatasetError`."""
    order = np.argsort(stamps, kind="stable")  # stable: lines of one stamp stay in file order
    s = stamps[order]
    repeat = np.flatnonzero(s[1:] == s[:-1]) + 1  # positions (sorted) equal to the one before
    keep = np.ones(stamps.shape[0], bool)
    if repeat.size == 0:
        return keep
    starts = np.r_[True, s[1:] != s[:-1]]
    first = order[np.maximum.accumulate(np.where(starts, np.arange(s.shape[0]), 0))[repeat]]
    later = order[repeat]
    conflict = (poses[later] != poses[first]).any(axis=(1, 2))
    if conflict.any():
        k = np.flatnonzero(conflict)[np.argmin(line_nos[later[conflict]])]
        raise DatasetError(f"{p}:{line_nos[later[k]]}: timestamp {float(stamps[later[k]])!r} repeats the one of "
                           f"line {line_nos[first[k]]} with a different pose (a trajectory has one pose per instant)")
    keep[later] = False
    return keep


def format_relative_line(t_ref: float, t_cur: float, T: np.ndarray, cov: np.ndarray, quality: float | None = None
                         ) -> str:
    """One relative-pose line (with newline): stamps (s), T_ref,cur (4x4), its 6x6 covariance and the
    pair's integrity statistic ``quality`` (-1 when None or not finite).

    Stamps ``%.6f``, pose values ``%.9f``, covariance entries ``%.9e`` (they are often < 1e-6).
    """
    quality = -1.0 if quality is None or not np.isfinite(quality) else float(quality)
    row = pose_to_tum(_check_pose(T))
    cov = np.asarray(cov, dtype=float)
    if cov.shape != (6, 6):
        raise InputError(f"a relative-pose covariance must be 6x6, got shape {cov.shape}")
    return (
        f"{float(t_ref):.6f} {float(t_cur):.6f} "
        + " ".join(f"{v:.9f}" for v in row)
        + " "
        + " ".join(f"{v:.9e}" for v in cov.reshape(36))
        + f" {quality:.4g}\n"
    )


def write_relative_header(fileobj: IO[str]) -> None:
    """Write the '#' header lines describing the relative-pose format to an open text file."""
    fileobj.write(RELATIVE_HEADER)


def load_relative_poses(path: str | os.PathLike, with_quality: bool = False):
    """``t_ref`` (N,), ``t_cur`` (N,) in s, T_ref,cur (N, 4, 4) and covariances (N, 6, 6) of a relative
    file; with ``with_quality`` also the quality column (N,; -1 where not formed, NaN in files
    written before it existed)."""
    rows, line_nos = _load_rows(path, _REL_COLS, "t_ref t_cur tx ty tz qx qy qz qw c00 ... c55 quality", optional=1)
    poses = _poses_from_rows(path, rows, line_nos, 2)
    out = rows[:, 0].copy(), rows[:, 1].copy(), poses, rows[:, 9:45].reshape(-1, 6, 6).copy()
    return (*out, rows[:, 45].copy()) if with_quality else out


class _LineWriter:
    """Opens ``path`` for writing, writes a header, appends one flushed line per ``write`` call."""

    header = ""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        try:
            self._f = open(self.path, "w")
        except OSError as exc:
            raise DatasetError(f"{self.path}: cannot write ({exc.strerror or exc})") from exc
        self._write(self.header)

    def _write(self, text: str) -> None:
        self._f.write(text)
        self._f.flush()

    @property
    def closed(self) -> bool:
        return self._f.closed

    def close(self) -> None:
        self._f.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class TrajectoryWriter(_LineWriter):
    """TUM trajectory file written line by line: ``write(t, T_world_cam)``; usable as a context manager."""

    header = TRAJECTORY_HEADER

    def write(self, t: float, T: np.ndarray) -> None:
        self._write(format_tum_line(t, T))


class RelativePoseWriter(_LineWriter):
    """Relative-pose file written line by line: ``write(t_ref, t_cur, T_ref_cur, cov, quality)``; a
    context manager."""

    header = RELATIVE_HEADER

    def write(self, t_ref: float, t_cur: float, T: np.ndarray, cov: np.ndarray, quality: float | None = None) -> None:
        self._write(format_relative_line(t_ref, t_cur, T, cov, quality))


def _plain(obj):
    """Plain-Python copy of ``obj`` for JSON: numpy scalars/arrays, tuples, paths; NaN/inf become None."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, set, frozenset)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _plain(obj.tolist())
    if isinstance(obj, np.generic):
        return _plain(obj.item())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    return obj


def write_json(path: str | os.PathLike, obj) -> None:
    """Write ``obj`` as indented JSON atomically (temporary file in the same folder, then ``os.replace``).

    numpy scalars and arrays become plain Python numbers and lists; NaN and inf become ``null``.
    """
    p = Path(path)
    text = json.dumps(_plain(obj), indent=2, allow_nan=False) + "\n"
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent)
    except OSError as exc:
        raise DatasetError(f"{p}: cannot write ({exc.strerror or exc})") from exc
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)
        os.replace(tmp, p)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


#: Descriptors of the folder locks this process holds; a forked child closes its copies at once.
_HELD_LOCKS: set[int] = set()


def _close_locks_in_child() -> None:
    for fd in _HELD_LOCKS:
        try:
            os.close(fd)
        except OSError:
            pass
    _HELD_LOCKS.clear()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_close_locks_in_child)


class FolderLock:
    """Exclusive lock on a folder for the time one command writes into it (``with FolderLock(path):``).

    An advisory ``flock`` on the folder itself: it leaves no file behind and is released when the
    process ends, however it ends (a forked child, such as a frame worker, does not keep it). A
    second writer gets :class:`DatasetError` at once instead of interleaving its lines with the
    first one's. Without ``fcntl`` (Windows) there is no lock.
    """

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self._fd: int | None = None

    def acquire(self) -> "FolderLock":
        if self._fd is not None:  # already held
            return self
        try:
            import fcntl
        except ImportError:  # pragma: no cover - not on POSIX
            return self
        try:
            fd = os.open(self.path, os.O_RDONLY)
        except OSError as exc:
            raise DatasetError(f"{self.path}: cannot open the output folder ({exc.strerror or exc})") from exc
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            raise DatasetError(f"{self.path}: another covo command is writing into this output folder; "
                               "wait for it or choose another --out") from None
        self._fd = fd
        _HELD_LOCKS.add(fd)
        return self

    def release(self) -> None:
        if self._fd is not None:
            _HELD_LOCKS.discard(self._fd)
            os.close(self._fd)  # closing the descriptor releases the flock
            self._fd = None

    def __enter__(self) -> "FolderLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


#: settings-file suffixes and the format each names
SETTINGS_FORMATS = {".toml": "TOML", ".json": "JSON", ".yaml": "YAML", ".yml": "YAML"}


def read_settings_file(path: str | os.PathLike, what: str, formats: tuple[str, ...] = ("TOML", "JSON")) -> dict:
    """The table of settings in a TOML, JSON (or, if in ``formats``, YAML) file, chosen by its suffix
    (anything else reads as JSON when JSON is allowed); ``what`` names the file in messages
    ("configuration file", "camera file"). A UTF-8 byte-order mark is dropped.

    Raises :class:`ConfigError` naming the file: unreadable, not UTF-8, not valid, not a table, or
    TOML on Python 3.10 / YAML without PyYAML.
    """
    p = Path(path)
    kind = SETTINGS_FORMATS.get(p.suffix.lower(), "JSON")
    if kind not in formats:
        raise ConfigError(f"{p}: a {what} is {' or '.join(formats)} (by its suffix)")
    try:
        text = p.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read {what} ({exc.strerror or exc})") from exc
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{p}: not a text file in UTF-8 ({exc.reason} at byte {exc.start})") from exc
    try:
        if kind == "YAML":
            try:
                import yaml
            except ImportError:
                raise ConfigError(f'{p}: YAML files need PyYAML: pip install "covo-gtsam[ros]" '
                                  "(or pip install pyyaml)") from None
            data = yaml.safe_load(text)
        elif kind == "TOML":
            try:
                import tomllib
            except ImportError:  # Python 3.10
                raise ConfigError(f"{p}: TOML needs Python >= 3.11; use a .json file") from None
            data = tomllib.loads(text)
        else:
            data = json.loads(text)
    except ConfigError:
        raise
    except Exception as exc:  # the parsers' own error classes
        raise ConfigError(f"{p}: not a valid {kind} file ({str(exc).splitlines()[0]})") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"{p}: the {what} must be a table/object of settings")
    return data
