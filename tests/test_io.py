"""File formats: TUM trajectories (read by evo), relative poses with covariances, atomic JSON."""

from __future__ import annotations

import io
import json
import re

import gtsam
import numpy as np
import pytest

from covo_gtsam.errors import DatasetError, InputError
from covo_gtsam.geometry import invert_pose
from covo_gtsam.io import (
    RelativePoseWriter,
    TrajectoryWriter,
    format_relative_line,
    load_relative_poses,
    load_tum_trajectory,
    write_json,
    write_relative_header,
    write_tum_trajectory,
)


def random_covs(n, seed=0):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, 6, 6)) * np.array([1e-3] * 3 + [1e-2] * 3)[:, None]
    return A @ np.swapaxes(A, 1, 2) + 1e-9 * np.eye(6)


def test_tum_round_trip_and_format(tmp_path, random_trajectory):
    stamps, poses = random_trajectory()
    path = tmp_path / "traj.txt"
    write_tum_trajectory(path, stamps, poses)
    lines = path.read_text().splitlines()
    assert lines[0].startswith("#") and len(lines) == 21
    assert re.fullmatch(r"\d+\.\d{6}( -?\d+\.\d{9}){7}", lines[1])
    s2, p2 = load_tum_trajectory(path)
    np.testing.assert_allclose(s2, stamps, rtol=0, atol=1e-6)
    np.testing.assert_allclose(p2, poses, atol=1e-8)


def test_trajectory_writer_matches_bulk_writer(tmp_path, random_trajectory):
    stamps, poses = random_trajectory(5)
    write_tum_trajectory(tmp_path / "a.txt", stamps, poses)
    with TrajectoryWriter(tmp_path / "b.txt") as w:
        for t, T in zip(stamps, poses):
            w.write(t, T)
    assert (tmp_path / "a.txt").read_text() == (tmp_path / "b.txt").read_text()


def test_evo_reads_written_trajectory(tmp_path, random_trajectory):
    from evo.tools import file_interface

    stamps, poses = random_trajectory()
    write_tum_trajectory(tmp_path / "traj.txt", stamps, poses)
    traj = file_interface.read_tum_trajectory_file(str(tmp_path / "traj.txt"))
    np.testing.assert_allclose(traj.timestamps, stamps, atol=1e-6)
    np.testing.assert_allclose(np.array(traj.poses_se3), poses, atol=1e-8)


def test_relative_round_trip(tmp_path, random_trajectory):
    stamps, poses = random_trajectory()
    rel = invert_pose(poses[:-1]) @ poses[1:]
    covs = random_covs(len(rel))
    path = tmp_path / "rel.txt"
    with RelativePoseWriter(path) as w:
        for i in range(len(rel)):
            w.write(stamps[i], stamps[i + 1], rel[i], covs[i])
    text = path.read_text().splitlines()
    header = [line for line in text if line.startswith("#")]
    assert header and "T_ref,cur" in " ".join(header) and "[rx ry rz tx ty tz]" in " ".join(header)
    assert all(len(line.split()) == 46 for line in text if not line.startswith("#"))  # 45 + quality
    t_ref, t_cur, P, C = load_relative_poses(path)
    np.testing.assert_allclose(t_ref, stamps[:-1], atol=1e-6)
    np.testing.assert_allclose(t_cur, stamps[1:], atol=1e-6)
    np.testing.assert_allclose(P, rel, atol=1e-8)
    np.testing.assert_allclose(C, covs, rtol=1e-8, atol=1e-20)


def test_relative_header_and_line_functions():
    buf = io.StringIO()
    write_relative_header(buf)
    T = gtsam.Pose3.Expmap(np.array([0.1, -0.2, 0.3, 1.0, 2.0, 3.0])).matrix()
    buf.write(format_relative_line(1.5, 2.0, T, np.diag([1e-6, 2e-6, 3e-6, 1e-4, 2e-4, 3e-4])))
    lines = buf.getvalue().splitlines()
    assert all(line.startswith("#") for line in lines[:-1])
    vals = [float(v) for v in lines[-1].split()]
    assert vals[:2] == [1.5, 2.0] and vals[9] == 1e-6 and vals[9 + 35] == 3e-4
    with pytest.raises(InputError):
        format_relative_line(0.0, 1.0, T, np.eye(3))


def test_interrupted_writers_leave_valid_files(tmp_path, random_trajectory):
    stamps, poses = random_trajectory(6)
    covs = random_covs(5)
    with pytest.raises(RuntimeError):
        with TrajectoryWriter(tmp_path / "t.txt") as tw, RelativePoseWriter(tmp_path / "r.txt") as rw:
            for i in range(3):
                tw.write(stamps[i], poses[i])
                rw.write(stamps[i], stamps[i + 1], invert_pose(poses[i]) @ poses[i + 1], covs[i])
            raise RuntimeError("interrupted")
    assert len(load_tum_trajectory(tmp_path / "t.txt")[0]) == 3
    assert len(load_relative_poses(tmp_path / "r.txt")[0]) == 3
    # lines are flushed as they are written, before close
    w = TrajectoryWriter(tmp_path / "open.txt")
    w.write(stamps[0], poses[0])
    assert len(load_tum_trajectory(tmp_path / "open.txt")[0]) == 1
    w.close()


def test_load_errors_name_file_and_line(tmp_path):
    p = tmp_path / "bad.txt"
    p.write_text("# header\n1.0 0 0 0 0 0 0 1\n2.0 0 0 zero 0 0 0 1\n")
    with pytest.raises(DatasetError, match=r"bad\.txt:3"):
        load_tum_trajectory(p)
    p.write_text("1.0 0 0 0 0 0 0 1\n\n2.0 0 0 0 0 0 0\n")
    with pytest.raises(DatasetError, match=r"bad\.txt:3"):
        load_tum_trajectory(p)
    p.write_text("1.0 0 0 0 0 0 0 0\n")
    with pytest.raises(DatasetError, match=r"bad\.txt:1.*quaternion"):
        load_tum_trajectory(p)
    with pytest.raises(DatasetError, match="missing.txt"):
        load_relative_poses(tmp_path / "missing.txt")
    p.write_text("# only a header\n")
    s, P = load_tum_trajectory(p)
    assert s.shape == (0,) and P.shape == (0, 4, 4)


def test_trajectory_has_one_pose_per_stamp(tmp_path):
    """Exact repeats of a stamp and pose are dropped (the file's order kept); the first line that
    repeats a stamp with another pose is named, with the line it repeats."""
    p = tmp_path / "t.txt"
    p.write_text("# t tx ty tz qx qy qz qw\n2.0 1 0 0 0 0 0 1\n1.0 0 0 0 0 0 0 1\n2.00 1 0 0 0 0 0 1\n"
                 "1.0 0 0 0 0 0 0 -1\n3.0 0 0 0 0 0 0 1\n")
    s, P = load_tum_trajectory(p)
    assert s.tolist() == [2.0, 1.0, 3.0] and P[:, 0, 3].tolist() == [1.0, 0.0, 0.0]
    with open(p, "a") as f:
        f.write("1.0 0 0 0.001 0 0 0 1\n2.0 1 0 0 0 0 0 1\n2.0 1 0 0 0 1 0 0\n")  # lines 7-9
    with pytest.raises(DatasetError, match=r"t\.txt:7: timestamp 1\.0 repeats the one of line 3 with a different"):
        load_tum_trajectory(p)


def test_write_json_plain_and_atomic(tmp_path):
    path = tmp_path / "m.json"
    path.write_text("old")
    obj = {
        "a": np.float64(1.5),
        "b": np.arange(3),
        "c": {"d": np.int32(7), "e": (np.bool_(True), np.float32(0.25))},
        "nan": float("nan"),
        "npnan": np.float64("nan"),
        "mat": np.eye(2),
        1: "key",
    }
    write_json(path, obj)
    assert json.loads(path.read_text()) == {
        "a": 1.5, "b": [0, 1, 2], "c": {"d": 7, "e": [True, 0.25]}, "nan": None, "npnan": None,
        "mat": [[1.0, 0.0], [0.0, 1.0]], "1": "key",
    }
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.json"]


def test_write_json_failure_keeps_old_file(tmp_path):
    path = tmp_path / "m.json"
    write_json(path, {"ok": 1})
    with pytest.raises(TypeError):
        write_json(path, {"bad": object()})
    assert json.loads(path.read_text()) == {"ok": 1}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.json"]


def test_relative_file_quality_column_round_trip_and_older_files(tmp_path):
    """The quality column is written (-1 where not formed, never NaN) and read back; files of the
    45-column layout still load, their quality NaN."""
    from covo_gtsam.io import RelativePoseWriter, load_relative_poses

    T, C = np.eye(4), np.eye(6) * 1e-6
    path = tmp_path / "relative.txt"
    with RelativePoseWriter(path) as w:
        w.write(0.0, 0.1, T, C, 4.25)
        w.write(0.1, 0.2, T, C, None)
        w.write(0.2, 0.3, T, C, float("nan"))
    assert "nan" not in path.read_text().lower()
    *_, q = load_relative_poses(path, with_quality=True)
    np.testing.assert_allclose(q, [4.25, -1.0, -1.0])
    old = tmp_path / "old.txt"
    old.write_text("".join(" ".join(line.split()[:45]) + "\n" for line in path.read_text().splitlines()
                           if not line.startswith("#")))
    t_ref, t_cur, poses, covs, q_old = load_relative_poses(old, with_quality=True)
    assert len(t_ref) == 3 and np.isnan(q_old).all()
    np.testing.assert_allclose(covs, [C] * 3)
