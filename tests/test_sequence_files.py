"""Sequence folders as editors and tools leave them: every listed frame accounted for, clear reasons."""

from __future__ import annotations

import json
import os

import cv2
import numpy as np
import pytest

from covo_gtsam.cli import main
from covo_gtsam.datasets.tum import TumSequence
from covo_gtsam.errors import CovoWarning, DatasetError


def one_error_line(capsys) -> str:
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("covo: error: "), lines
    return lines[0]


@pytest.mark.parametrize("style", ["bom", "crlf", "cr", "bom+crlf", "tabs"])
def test_lists_as_editors_write_them(small_sample, style):
    seq = small_sample(3)
    plain = TumSequence(seq)
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt"):
        text = (seq / name).read_text()
        if "crlf" in style:
            text = text.replace("\n", "\r\n")
        if style == "cr":
            text = text.replace("\n", "\r")
        if style == "tabs":
            text = text.replace(" ", "\t")
        data = text.encode("utf-8")
        if "bom" in style:
            data = b"\xef\xbb\xbf" + data
        (seq / name).write_bytes(data)
    edited = TumSequence(seq)
    assert edited.timestamps.tolist() == plain.timestamps.tolist()
    assert edited.rgb_paths == plain.rgb_paths and edited.gt_valid.all()


def test_depth_folder_that_is_a_file_is_not_reported_as_missing(small_sample, tmp_path, capsys):
    seq = small_sample(2)
    for png in (seq / "depth").iterdir():
        png.unlink()
    (seq / "depth").rmdir()
    (seq / "depth").write_text("not a folder")
    assert main(["run", str(seq), "--out", str(tmp_path / "out")]) == 2
    line = one_error_line(capsys)
    assert "cannot be read" in line and "does not exist" not in line


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads any folder")
def test_unreadable_depth_folder_is_not_reported_as_missing(small_sample):
    seq = small_sample(2)
    (seq / "depth").chmod(0)
    try:
        with pytest.raises(DatasetError, match="cannot be read") as info:
            TumSequence(seq)
        assert "does not exist" not in str(info.value)
    finally:
        (seq / "depth").chmod(0o755)


def test_lost_frame_of_a_wrong_size_colour_image_names_the_file(small_sample, tmp_path, capsys):
    seq = small_sample(3)
    rgb = TumSequence(seq).rgb_paths[1]
    cv2.imwrite(rgb, cv2.resize(cv2.imread(rgb), (320, 240)))
    assert main(["run", str(seq), "--out", str(tmp_path / "out"), "--quiet", "--no-plots"]) == 0
    lost = json.loads((tmp_path / "out" / "metrics.json").read_text())["lost"]
    assert len(lost) == 1 and os.path.basename(rgb) in lost[0]["reason"] and "320x240" in lost[0]["reason"]


def test_colour_frame_without_depth_is_accounted_for(small_sample, tmp_path, capsys):
    seq = small_sample(4)
    lines = (seq / "depth.txt").read_text().splitlines()
    (seq / "depth.txt").write_text("\n".join(lines[:1] + lines[2:]) + "\n")  # the second frame has no depth
    assert main(["run", str(seq), "--out", str(tmp_path / "out"), "--quiet", "--no-plots"]) == 0
    m = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert m["frames"] == 3
    rgb_second = (seq / "rgb.txt").read_text().splitlines()[1].split()
    assert [u["file"] for u in m["unassociated"]] == [rgb_second[1]]
    assert "no depth image" in m["unassociated"][0]["reason"]


@pytest.mark.parametrize("suffix, text", [(".json", '{"noise": {"pixel_sigma": 3.0}}'),
                                          (".toml", "[noise]\npixel_sigma = 3.0\n")])
def test_configuration_file_with_a_byte_order_mark(tmp_path, suffix, text):
    from covo_gtsam.config import load_config

    path = tmp_path / f"config{suffix}"
    path.write_bytes(b"\xef\xbb\xbf" + text.replace("\n", "\r\n").encode("utf-8"))
    assert load_config(str(path)).noise.pixel_sigma == 3.0


def rounded_stamps(path, digits: int) -> None:
    """Rewrite the stamps of a ``timestamp filename`` list rounded to ``digits`` decimals, as a tool
    that writes too few digits leaves them."""
    lines = path.read_text().splitlines()
    path.write_text("\n".join(ln if ln.startswith("#") else f"{round(float(ln.split()[0]), digits):.{digits}f} "
                              f"{ln.split()[1]}" for ln in lines) + "\n")


@pytest.mark.parametrize("names, digits", [(("rgb.txt", "depth.txt"), 1), (("rgb.txt", "depth.txt"), 0),
                                           (("depth.txt",), 1)])
def test_stamps_written_with_too_few_digits_are_an_error(small_sample, tmp_path, capsys, names, digits):
    """Frames 33 ms apart whose stamps were rounded share them: the run stops with the first repeat's
    file and line instead of pairing frames with other frames' depth images."""
    seq = small_sample(5)
    for name in names:
        rounded_stamps(seq / name, digits)
    out = tmp_path / "out"
    assert main(["run", str(seq), "--out", str(out), "--quiet", "--no-plots"]) == 2
    line = one_error_line(capsys)
    assert f"{seq / names[0]}:" in line and "repeats the one of line" in line
    assert not (out / "trajectory.txt").exists()


def test_groundtruth_dropouts_are_left_out_with_a_warning(small_sample, tmp_path, capsys):
    """A motion-capture dropout (a ground-truth line with NaN, or a zero quaternion) is left out of
    the reference with one ``covo: warning:`` line naming the file and its lines: the run goes on and
    is evaluated against the samples left. A trajectory file read as such still refuses the line."""
    from covo_gtsam.io import load_tum_trajectory

    seq = small_sample(5)
    plain = TumSequence(seq)
    gt = seq / "groundtruth.txt"
    lines = gt.read_text().splitlines()
    first = next(i for i, ln in enumerate(lines) if not ln.startswith("#"))
    for k, value in ((first + 3, "nan"), (first + 6, None)):
        v = lines[k].split()
        lines[k] = " ".join(v[:2] + [value] + v[3:]) if value else " ".join(v[:4] + ["0", "0", "0", "0"])
    gt.write_text("\n".join(lines) + "\n")
    left_out = rf"groundtruth\.txt: 2 line\(s\) .* left out \(line {first + 4}, {first + 7}\)"
    with pytest.warns(CovoWarning, match=left_out):
        dropped = TumSequence(seq)
    assert len(dropped.gt_samples[0]) == len(plain.gt_samples[0]) - 2
    assert np.isin(dropped.gt_samples[0], plain.gt_samples[0]).all()
    assert np.all(np.isfinite(dropped.groundtruth)) and dropped.gt_valid.sum() == plain.gt_valid.sum()
    with pytest.raises(DatasetError, match=rf"groundtruth\.txt:{first + 4}: non-finite pose value"):
        load_tum_trajectory(gt)
    capsys.readouterr()
    assert main(["run", str(seq), "--out", str(tmp_path / "o"), "--quiet", "--no-plots"]) == 0
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and err[0].startswith(f"covo: warning: {gt}: 2 line(s)"), err
    assert json.loads((tmp_path / "o" / "metrics.json").read_text())["ate"] is not None


def test_groundtruth_samples_beyond_the_limit_are_left_out_before_interpolation(small_sample):
    """A sample 2e9 m away, weighted by interpolation, would come out below the 1e9 m limit and
    enter the metrics: it is left out before, with a warning naming it, like a non-finite one."""
    seq = small_sample(5)
    plain = TumSequence(seq)
    gt = seq / "groundtruth.txt"
    lines = gt.read_text().splitlines()
    k = next(i for i, ln in enumerate(lines) if not ln.startswith("#")) + 4
    v = lines[k].split()
    lines[k] = " ".join([v[0], "2e9"] + v[2:])
    gt.write_text("\n".join(lines) + "\n")
    with pytest.warns(CovoWarning, match=rf"1 sample\(s\) more than 1e\+09 m from the origin left out \(stamp {v[0]}"):
        far = TumSequence(seq)
    assert len(far.gt_samples[0]) == len(plain.gt_samples[0]) - 1
    assert np.abs(far.groundtruth[far.gt_valid][:, :3, 3]).max() < 10
    assert far.gt_valid.sum() == plain.gt_valid.sum()


def test_a_non_finite_stamp_in_a_trajectory_file_is_an_error(tmp_path):
    from covo_gtsam.io import load_tum_trajectory

    path = tmp_path / "trajectory.txt"
    path.write_text("1.0 0 0 0 0 0 0 1\nnan 0 0 0 0 0 0 1\n")
    with pytest.raises(DatasetError, match=r"trajectory\.txt:2: non-finite timestamp"):
        load_tum_trajectory(path)


def test_groundtruth_with_repeated_lines(small_sample, tmp_path, capsys):
    """Every ground-truth line written twice: the run and the reference's own noise are those of the
    plain file; a repeat with a pose 1 m away stops the run naming the file and line."""
    from covo_gtsam.reference_noise import reference_jitter

    seq = small_sample(5)
    assert main(["run", str(seq), "--out", str(tmp_path / "plain"), "--quiet", "--no-plots"]) == 0
    plain = TumSequence(seq)
    gt = seq / "groundtruth.txt"
    text = gt.read_text()
    gt.write_text("".join(ln if ln.startswith("#") else ln + ln for ln in text.splitlines(keepends=True)))
    doubled = TumSequence(seq)
    for a, b in zip(doubled.gt_samples, plain.gt_samples):
        np.testing.assert_array_equal(a, b)
    jitter = reference_jitter(*doubled.gt_samples)
    assert jitter is not None
    np.testing.assert_equal(jitter, reference_jitter(*plain.gt_samples))
    assert main(["run", str(seq), "--out", str(tmp_path / "doubled"), "--quiet", "--no-plots"]) == 0
    metrics = [json.loads((tmp_path / d / "metrics.json").read_text()) for d in ("plain", "doubled")]
    for key in ("ate", "reference_jitter"):
        assert metrics[1][key] == metrics[0][key] and metrics[0][key] is not None
    lines = text.splitlines()
    no = next(i for i, ln in enumerate(lines) if not ln.startswith("#")) + 1
    v = lines[no - 1].split()
    lines.insert(no, " ".join([v[0], f"{float(v[1]) + 1.0:.4f}"] + v[2:]))
    gt.write_text("\n".join(lines) + "\n")
    assert main(["run", str(seq), "--out", str(tmp_path / "conflict"), "--quiet", "--no-plots"]) == 2
    line = one_error_line(capsys)
    assert f"{gt}:{no + 1}:" in line and f"line {no} with a different pose" in line
