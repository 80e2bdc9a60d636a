"""TUM RGB-D reader: association, ground-truth interpolation, real sequences, error cases."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from covo_gtsam.datasets.tum import Frame, TumSequence, associate, interpolate_poses, read_file_list
from covo_gtsam.errors import CovoError, DatasetError
from covo_gtsam.geometry import make_pose, quat_to_matrix
from covo_gtsam.io import load_tum_trajectory


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def benchmark_associate(first, second, max_difference):
    """The TUM benchmark's associate.py (offset 0), with '<=' and indices instead of stamps."""
    potential = sorted(
        (abs(a - b), a, b, i, j)
        for i, a in enumerate(first)
        for j, b in enumerate(second)
        if abs(a - b) <= max_difference
    )
    used_i, used_j, matches = set(), set(), []
    for _, a, _, i, j in potential:
        if i in used_i or j in used_j:
            continue
        used_i.add(i)
        used_j.add(j)
        matches.append((a, i, j))
    return [(i, j) for _, i, j in sorted(matches)]


# ---- association -------------------------------------------------------------------------------


def test_associate_hand_example():
    rgb = np.array([1.000, 1.033, 1.050, 1.100, 1.112, 1.300, 1.400])
    depth = np.array([1.001, 1.040, 1.062, 1.115, 1.321, 1.419])
    # r0-d0 0.001; r1-d1 0.007 beats r2-d1 0.010, so r2 (nearest: d1) takes d2 (0.012);
    # r4-d3 0.003 beats r3-d3 0.015 and r3 has no other candidate; r5-d4 0.021 is cut; r6-d5 0.019 kept.
    assert associate(rgb, depth) == [(0, 0), (1, 1), (2, 2), (4, 3), (6, 5)]
    # tighter cut
    assert associate(rgb, depth, max_dt=0.005) == [(0, 0), (4, 3)]


def test_associate_is_one_to_one_sorted_by_rgb_time_and_index_safe():
    rgb = np.array([1.112, 1.000, 1.400, 1.050, 1.300, 1.033, 1.100])
    depth = np.array([1.419, 1.062, 1.001, 1.321, 1.040, 1.115])
    pairs = associate(rgb, depth)
    assert [rgb[i] for i, _ in pairs] == sorted(rgb[i] for i, _ in pairs)
    assert [(rgb[i], depth[j]) for i, j in pairs] == [
        (1.000, 1.001), (1.033, 1.040), (1.050, 1.062), (1.112, 1.115), (1.400, 1.419)
    ]
    assert len({i for i, _ in pairs}) == len({j for _, j in pairs}) == len(pairs)


def test_associate_edge_cases():
    assert associate(np.array([]), np.array([1.0])) == []
    assert associate(np.array([1.0]), np.array([])) == []
    assert associate(np.array([1.0]), np.array([2.0])) == []
    assert associate([5.0, 5.0], [5.0]) == [(0, 0)]


@pytest.mark.parametrize("seed", range(5))
def test_associate_matches_benchmark_tool_on_random_stamps(seed):
    rng = np.random.default_rng(seed)
    rgb = np.round(np.cumsum(rng.uniform(0.01, 0.05, 60)), 6)
    depth = np.round(np.cumsum(rng.uniform(0.01, 0.05, 60)), 6)
    assert associate(rgb, depth, 0.02) == benchmark_associate(rgb.tolist(), depth.tolist(), 0.02)


# ---- ground-truth interpolation ----------------------------------------------------------------


def test_interpolation_at_gt_stamp_is_exact():
    rng = np.random.default_rng(3)
    q = rng.normal(size=(5, 4))
    P = make_pose(quat_to_matrix(q), rng.normal(size=(5, 3)))
    ts = 100.0 + 0.01 * np.arange(5)
    out, ok = interpolate_poses(ts, P, ts)
    assert ok.all()
    np.testing.assert_array_equal(out, P)


def test_interpolation_midpoint_and_quarter_slerp():
    R0 = rot_x(0.3)
    R1 = R0 @ rot_z(0.4)
    P = np.array([make_pose(R0, [0.0, 0.0, 0.0]), make_pose(R1, [1.0, 2.0, -4.0])])
    ts = np.array([10.0, 10.05])
    out, ok = interpolate_poses(ts, P, np.array([10.025, 10.0125]))
    assert ok.all()
    np.testing.assert_allclose(out[0], make_pose(R0 @ rot_z(0.2), [0.5, 1.0, -2.0]), atol=1e-12)
    np.testing.assert_allclose(out[1], make_pose(R0 @ rot_z(0.1), [0.25, 0.5, -1.0]), atol=1e-12)


def test_interpolation_takes_shortest_arc_and_unsorted_input():
    R0, R1 = rot_z(3.0), rot_z(-3.0)  # 0.283 rad apart across +-pi
    P = np.array([make_pose(R1, [1.0, 0, 0]), make_pose(R0, [0.0, 0, 0])])
    out, ok = interpolate_poses(np.array([1.02, 1.0]), P, np.array([1.01]))
    assert ok[0]
    np.testing.assert_allclose(out[0], make_pose(rot_z(np.pi), [0.5, 0, 0]), atol=1e-12)


def test_interpolation_invalid_outside_range_and_across_gaps():
    P = np.array([make_pose(rot_z(a), [a, 0, 0]) for a in (0.0, 0.1, 0.2, 0.3)])
    ts = np.array([0.0, 0.05, 0.30, 0.35])  # 0.25 s hole between samples 1 and 2
    query = np.array([-0.01, 0.0, 0.02, 0.05, 0.1, 0.3, 0.32, 0.35, 0.4, np.nan])
    out, ok = interpolate_poses(ts, P, query)
    assert ok.tolist() == [False, True, True, True, False, True, True, True, False, False]
    assert np.isfinite(out).all()
    np.testing.assert_array_equal(out[~ok], np.tile(np.eye(4), (int((~ok).sum()), 1, 1)))
    _, ok_wide = interpolate_poses(ts, P, query, max_gap=0.3)
    assert ok_wide[4]


def test_interpolation_degenerate_inputs():
    out, ok = interpolate_poses(np.array([]), np.zeros((0, 4, 4)), np.array([1.0, 2.0]))
    assert out.shape == (2, 4, 4) and not ok.any()
    P = make_pose(rot_z(0.5), [1, 2, 3])[None]
    out, ok = interpolate_poses(np.array([1.0]), P, np.array([1.0, 1.5]))
    assert ok.tolist() == [True, False]
    np.testing.assert_array_equal(out[0], P[0])


# ---- real sequences ----------------------------------------------------------------------------


@pytest.mark.realdata
def test_desk_9frames(fr1_desk_dir):
    seq = TumSequence(fr1_desk_dir)
    assert len(seq) == 9
    assert seq.camera_name == "fr1" and seq.name == fr1_desk_dir.name
    assert seq.groundtruth is not None and seq.groundtruth.shape == (9, 4, 4) and seq.gt_valid.all()
    assert np.all(np.diff(seq.timestamps) > 0)
    f = seq[0]
    assert isinstance(f, Frame) and f.timestamp == seq.timestamps[0]
    for p in seq.rgb_paths + seq.depth_paths:
        assert Path(p).is_absolute() and Path(p).is_file()
    assert Path(f.rgb_path).parent.name == "rgb" and Path(f.depth_path).parent.name == "depth"
    # interpolated poses lie close to the nearest raw ground-truth sample (<= 5 ms away, slow motion)
    gt_t, gt_P = load_tum_trajectory(fr1_desk_dir / "groundtruth.txt")
    k = np.abs(gt_t[None, :] - seq.timestamps[:, None]).argmin(axis=1)
    assert np.max(np.linalg.norm(seq.groundtruth[:, :3, 3] - gt_P[k, :3, 3], axis=1)) < 0.01
    np.testing.assert_allclose(seq.groundtruth[:, :3, :3] @ np.swapaxes(seq.groundtruth[:, :3, :3], 1, 2),
                               np.tile(np.eye(3), (9, 1, 1)), atol=1e-12)
    assert seq.camera.fx == pytest.approx(517.3)


@pytest.mark.realdata
def test_rpy_head240(fr1_rpy_dir):
    seq = TumSequence(fr1_rpy_dir)
    assert 235 <= len(seq) <= 240
    assert seq.gt_valid.sum() >= len(seq) - 2
    rgb_t, _ = read_file_list(fr1_rpy_dir / "rgb.txt")
    dep_t, _ = read_file_list(fr1_rpy_dir / "depth.txt")
    assert associate(rgb_t, dep_t) == benchmark_associate(rgb_t.tolist(), dep_t.tolist(), 0.02)


@pytest.mark.realdata
def test_shared_sequences_load_every_listed_line(shared_data_dir):
    """The shared TUM sequences have no repeated stamps: every line of rgb.txt, depth.txt and
    groundtruth.txt is read as it is written, and no image serves two frames."""
    folders = sorted(p for p in (shared_data_dir / "tum").iterdir() if (p / "rgb.txt").is_file())
    assert folders
    for folder in folders:
        seq = TumSequence(folder)
        for name in ("rgb.txt", "depth.txt"):
            rows = [ln.split() for ln in (folder / name).read_text().splitlines() if ln[:1].isdigit()]
            stamps, names = read_file_list(folder / name)
            assert stamps.tolist() == [float(r[0]) for r in rows] and names == [r[1] for r in rows]
        assert len(set(seq.rgb_paths)) == len(set(seq.depth_paths)) == len(seq)
        assert len(seq) + len(seq.unassociated) == len(read_file_list(folder / "rgb.txt")[0])
        raw = np.loadtxt(folder / "groundtruth.txt")
        np.testing.assert_array_equal(seq.gt_samples[0], raw[:, 0])
        np.testing.assert_allclose(seq.gt_samples[1][:, :3, 3], raw[:, 1:4])


# ---- errors ------------------------------------------------------------------------------------


def make_sequence(root: Path, n: int = 4, name: str = "rgbd_dataset_freiburg2_tiny", gt: bool = True) -> Path:
    """A tiny TUM-like folder with empty image files (the reader does not decode images)."""
    seq = root / name
    (seq / "rgb").mkdir(parents=True)
    (seq / "depth").mkdir()
    rgb_lines, depth_lines, gt_lines = ["# colour images", "# timestamp filename"], ["# depth"], ["# ground truth"]
    for i in range(n):
        tr, td = 1000.0 + 0.033 * i, 1000.004 + 0.033 * i
        (seq / "rgb" / f"{tr:.6f}.png").write_bytes(b"")
        (seq / "depth" / f"{td:.6f}.png").write_bytes(b"")
        rgb_lines.append(f"{tr:.6f} rgb/{tr:.6f}.png")
        depth_lines.append(f"{td:.6f} depth/{td:.6f}.png")
    for k in range(int(0.033 * n * 100) + 3):
        gt_lines.append(f"{999.99 + 0.01 * k:.4f} {0.01 * k} 0 0 0 0 0 1")
    (seq / "rgb.txt").write_text("\n".join(rgb_lines) + "\n\n")
    (seq / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    if gt:
        (seq / "groundtruth.txt").write_text("\n".join(gt_lines) + "\n")
    return seq


def test_tiny_sequence_reads(tmp_path):
    seq = TumSequence(make_sequence(tmp_path))
    assert len(seq) == 4 and seq.camera_name == "fr2" and seq.gt_valid.all()
    np.testing.assert_allclose(seq.groundtruth[:, 0, 3], seq.timestamps - 999.99, atol=1e-9)
    assert [f.timestamp for f in seq] == seq.timestamps.tolist()
    with pytest.raises(IndexError):
        seq[4]


def test_no_groundtruth_and_unknown_camera(tmp_path):
    seq = TumSequence(make_sequence(tmp_path, name="my_recording", gt=False))
    assert seq.groundtruth is None and not seq.gt_valid.any() and len(seq.gt_valid) == 4
    assert seq.camera_name is None
    with pytest.raises(DatasetError, match="camera"):
        seq.camera  # noqa: B018 (the property raises)
    sentinel = object()
    assert TumSequence(seq.path, camera=sentinel).camera is sentinel


def test_a_folder_name_naming_two_cameras_is_no_guess(tmp_path):
    from covo_gtsam.datasets.tum import camera_name_from_path

    assert camera_name_from_path("rgbd_dataset_freiburg3_from_freiburg1") is None
    assert camera_name_from_path("freiburg3_freiburg3_copy") == "fr3"
    seq = TumSequence(make_sequence(tmp_path, name="rgbd_freiburg3_from_freiburg1", gt=False))
    with pytest.raises(DatasetError, match="it names freiburg1 and freiburg3.*--camera"):
        seq.camera  # noqa: B018 (the property raises)


def test_missing_folder(tmp_path):
    with pytest.raises(DatasetError, match="nope.*does not exist"):
        TumSequence(tmp_path / "nope")


def test_missing_rgb_txt(tmp_path):
    seq = make_sequence(tmp_path)
    (seq / "rgb.txt").unlink()
    with pytest.raises(DatasetError, match=r"rgb\.txt"):
        TumSequence(seq)


def test_missing_depth_txt(tmp_path):
    seq = make_sequence(tmp_path)
    (seq / "depth.txt").unlink()
    with pytest.raises(DatasetError, match=r"depth\.txt"):
        TumSequence(seq)


def test_listed_file_missing_is_kept_and_reported(tmp_path):
    """A missing image stays in the sequence (its frame is lost when read); none present is an error."""
    seq = make_sequence(tmp_path)
    victim = sorted((seq / "rgb").iterdir())[2]
    victim.unlink()
    s = TumSequence(seq)
    assert str(victim) in s.rgb_paths and s.missing_files == [str(victim)]
    assert s.frames(2, 4).missing_files == [str(victim)] and s.frames(3).missing_files == []
    for f in (seq / "depth").iterdir():  # colour images left, but no frame is usable
        f.unlink()
    with pytest.raises(DatasetError, match="no frame has both") as info:
        TumSequence(seq)
    assert isinstance(info.value, CovoError)


@pytest.mark.parametrize("name", ["rgb.txt", "depth.txt"])
def test_an_empty_image_list_says_so(tmp_path, name):
    seq = make_sequence(tmp_path)
    (seq / name).write_text("# timestamp filename\n")
    with pytest.raises(DatasetError, match=rf"{name.replace('.', '[.]')}: lists no image$"):
        TumSequence(seq)


def test_malformed_line_names_file_and_line(tmp_path):
    seq = make_sequence(tmp_path)
    lines = (seq / "rgb.txt").read_text().splitlines()
    lines.insert(3, "1000.5xx rgb/a.png")  # line 4
    (seq / "rgb.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=r"rgb\.txt:4"):
        TumSequence(seq)


def test_malformed_groundtruth_line(tmp_path):
    seq = make_sequence(tmp_path)
    with open(seq / "groundtruth.txt", "a") as f:
        f.write("1001.0 0 0 0 0 0 1\n")  # 7 values
    n = len((seq / "groundtruth.txt").read_text().splitlines())
    with pytest.raises(DatasetError, match=rf"groundtruth\.txt:{n}"):
        TumSequence(seq)


@pytest.mark.parametrize("name", ["rgb.txt", "depth.txt"])
def test_repeated_image_stamp_names_file_and_line(tmp_path, name):
    """Two images at one instant cannot be told apart by time: an error, not a frame with the wrong depth."""
    seq = make_sequence(tmp_path)
    lines = (seq / name).read_text().splitlines()
    first = next(no for no, ln in enumerate(lines, 1) if ln[:1].isdigit()) + 1  # the second image's line
    stamp = lines[first - 1].split()[0]
    lines[first] = f"{stamp} {lines[first].split()[1]}"  # the third image takes the second's stamp
    (seq / name).write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=rf"{name.replace('.', '[.]')}:{first + 1}: timestamp {stamp} "
                                           rf"repeats the one of line {first}\b"):
        TumSequence(seq)
    lines[first] = f"{float(stamp):.9f} {lines[first].split()[1]}"  # the same instant written otherwise
    (seq / name).write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=rf"{name.replace('.', '[.]')}:{first + 1}:"):
        read_file_list(seq / name)


@pytest.mark.parametrize("name", ["rgb.txt", "depth.txt"])
def test_a_line_written_twice_in_an_image_list_is_read_once(tmp_path, name):
    seq = make_sequence(tmp_path)
    plain = read_file_list(seq / name)
    lines = (seq / name).read_text().splitlines()
    k = next(no for no, ln in enumerate(lines) if ln[:1].isdigit()) + 1
    (seq / name).write_text("\n".join(lines[:k + 1] + [lines[k]] + lines[k + 1:]) + "\n")
    twice = read_file_list(seq / name)
    np.testing.assert_array_equal(twice[0], plain[0])
    assert twice[1] == plain[1]


@pytest.mark.parametrize("name", ["rgb.txt", "depth.txt"])
def test_one_image_under_two_stamps_names_file_lines_and_image(tmp_path, name, capsys):
    """One image listed at two instants would give a pair without motion under a wrong stamp: an
    error naming the list, both lines and the image, however the path is spelt."""
    import re

    from covo_gtsam.cli import main

    seq = make_sequence(tmp_path)
    lines = (seq / name).read_text().splitlines()
    k = next(no for no, ln in enumerate(lines) if ln[:1].isdigit())  # the first image's line, 0-based
    image = lines[k].split()[1]
    lines[k + 2] = f"{lines[k + 2].split()[0]} ./{image}"  # the third stamp names the first image again
    (seq / name).write_text("\n".join(lines) + "\n")
    needle = f"{name}:{k + 3}: image ./{image} is listed at line {k + 1} already"
    with pytest.raises(DatasetError, match=re.escape(needle)):
        TumSequence(seq)
    assert main(["run", str(seq), "--out", str(tmp_path / "o"), "--quiet", "--no-plots"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and needle in err and str(seq / name) in err


def test_repeated_groundtruth_stamp(tmp_path):
    """A ground-truth stamp repeated with another pose is an error naming both lines; a line repeated
    exactly (also with the quaternion's sign flipped) is dropped, leaving the samples as they were."""
    seq = make_sequence(tmp_path)
    gt = seq / "groundtruth.txt"
    lines = gt.read_text().splitlines()
    plain = TumSequence(seq)
    doubled = []
    for ln in lines:
        doubled.append(ln)
        if not ln.startswith("#"):
            v = ln.split()
            doubled.append(" ".join(v[:4] + [repr(-float(x)) for x in v[4:]]) if len(doubled) % 4 else ln)
    gt.write_text("\n".join(doubled) + "\n")
    same = TumSequence(seq)
    np.testing.assert_array_equal(same.gt_samples[0], plain.gt_samples[0])
    np.testing.assert_array_equal(same.gt_samples[1], plain.gt_samples[1])
    np.testing.assert_array_equal(same.groundtruth, plain.groundtruth)
    v = lines[5].split()
    lines.insert(6, " ".join([v[0], str(float(v[1]) + 1.0)] + v[2:]))  # line 7: line 6's stamp, 1 m away
    gt.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=r"groundtruth\.txt:7: timestamp .* repeats the one of line 6 with a "
                                           r"different pose"):
        TumSequence(seq)


def test_no_frame_associated(tmp_path):
    seq = make_sequence(tmp_path)
    (seq / "depth.txt").write_text("# nothing close\n5000.0 depth/x.png\n")
    with pytest.raises(DatasetError, match="associated"):
        TumSequence(seq)


def test_frames_restricts_a_sequence(sample_dir):
    from covo_gtsam.errors import ConfigError

    seq = TumSequence(sample_dir)
    part = seq.frames(10, 20)
    assert len(part) == 10 and len(seq) == 40
    assert part.timestamps[0] == seq.timestamps[10] and part.rgb_paths[-1] == seq.rgb_paths[19]
    np.testing.assert_array_equal(part.groundtruth, seq.groundtruth[10:20])
    assert part.depth_paths == seq.depth_paths[10:20] and list(part.gt_valid) == list(seq.gt_valid[10:20])
    assert len(seq.frames(35)) == 5
    for bad in ((5, 5), (-1, 3), (0, 41), (2.0, 5)):
        with pytest.raises(ConfigError):
            seq.frames(*bad)


def test_file_lists_that_are_not_files_or_not_utf8_say_so(tmp_path):
    seq = make_sequence(tmp_path, name="rgbd_dataset_freiburg1_x")
    text = (seq / "rgb.txt").read_text()
    (seq / "rgb.txt").write_text(text, encoding="utf-16")  # as some Windows editors save it
    with pytest.raises(DatasetError, match=r"rgb.txt: not a text file in UTF-8 \(it holds NUL bytes: UTF-16"):
        TumSequence(seq)
    (seq / "rgb.txt").unlink()
    (seq / "rgb.txt").mkdir()
    with pytest.raises(DatasetError, match=r"rgb.txt: is not a file \(a TUM sequence folder"):
        TumSequence(seq)
    (seq / "rgb.txt").rmdir()
    with pytest.raises(DatasetError, match=r"rgb.txt: missing \(a TUM sequence folder"):
        TumSequence(seq)
