"""The results folder: checked before the first frame, never mixing two runs, one writer at a time;
valid files after an interruption, the same bytes for the same input, figures kept in step."""

from __future__ import annotations

import fcntl
import json
import os
import re

import numpy as np
import pytest

from covo_gtsam import cli
from covo_gtsam.cli import main
from covo_gtsam.io import load_relative_poses, load_tum_trajectory
from covo_gtsam.odometry import VisualOdometry


def error_line(capsys) -> str:
    """The single non-empty stderr line of a failed command."""
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(lines) == 1, lines
    assert lines[0].startswith("covo: ") and "Traceback" not in lines[0]
    return lines[0]


@pytest.mark.slow
def test_interrupted_rerun_leaves_no_results_of_the_earlier_run(small_sample, tmp_path, monkeypatch, capsys):
    seq, out = small_sample(5), tmp_path / "out"
    assert main(["run", str(seq), "--out", str(out), "--quiet"]) == 0
    assert (out / "metrics.json").is_file() and (out / "plots" / "trajectory.png").is_file()
    # the second run is interrupted at its third frame
    original = VisualOdometry.register_frame
    calls = []

    def interrupt(self, *args, **kw):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return original(self, *args, **kw)

    monkeypatch.setattr(VisualOdometry, "register_frame", interrupt)
    assert main(["run", str(seq), "--out", str(out), "--quiet"]) == 130
    capsys.readouterr()
    # what is left describes the interrupted run alone: its first two frames, no metrics, no figures
    stamps, _ = load_tum_trajectory(out / "trajectory.txt")
    assert len(stamps) == 2
    assert len(load_relative_poses(out / "relative.txt")[0]) == 1
    assert not (out / "metrics.json").exists()
    assert not any((out / "plots").glob("*.png"))


@pytest.mark.slow
def test_rerun_without_plots_removes_the_earlier_figures(small_sample, tmp_path, capsys):
    seq, out = small_sample(4), tmp_path / "out"
    assert main(["run", str(seq), "--out", str(out), "--quiet"]) == 0
    assert (out / "plots" / "nees.png").is_file()
    assert main(["run", str(seq), "--out", str(out), "--quiet", "--no-plots"]) == 0
    assert not any((out / "plots").glob("*.png"))
    assert json.loads((out / "metrics.json").read_text())["frames"] == 4


@pytest.mark.parametrize("command", [["run"], ["analyze-noise"], ["calibrate"]])
def test_empty_output_path_is_refused(small_sample, tmp_path, monkeypatch, capsys, command):
    seq = small_sample(2)
    work = tmp_path / "cwd"
    work.mkdir()
    monkeypatch.chdir(work)
    assert main([*command, str(seq), "--out", ""]) == 2
    assert "empty path" in error_line(capsys)
    assert os.listdir(work) == []


def test_simulate_refuses_an_empty_output_path(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["simulate", "--runs", "1", "--out", ""]) == 2
    assert "empty path" in error_line(capsys)
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("blocker", ["plots_file", "metrics_dir", "figure_dir", "trajectory_dir"])
def test_unwritable_result_is_reported_before_the_first_frame(small_sample, tmp_path, capsys, blocker):
    seq, out = small_sample(3), tmp_path / "out"
    out.mkdir()
    if blocker == "plots_file":
        (out / "plots").write_text("not a folder")
        needle = "plots"
    elif blocker == "metrics_dir":
        (out / "metrics.json").mkdir()
        needle = "metrics.json"
    elif blocker == "figure_dir":
        (out / "plots" / "nees.png").mkdir(parents=True)
        needle = "nees.png"
    else:
        (out / "trajectory.txt").mkdir()
        needle = "trajectory.txt"
    assert main(["run", str(seq), "--out", str(out), "--quiet"]) == 2
    assert needle in error_line(capsys)
    assert not (out / "relative.txt").exists()  # nothing was written


def test_plots_file_is_fine_without_plots(small_sample, tmp_path, capsys):
    seq, out = small_sample(3), tmp_path / "out"
    out.mkdir()
    (out / "plots").write_text("a file of the user's")
    assert main(["run", str(seq), "--out", str(out), "--quiet", "--no-plots"]) == 0
    assert (out / "plots").read_text() == "a file of the user's"


@pytest.mark.skipif(os.geteuid() == 0, reason="root can write into any folder")
def test_unwritable_plots_folder_is_reported_before_the_first_frame(small_sample, tmp_path, capsys):
    seq, out = small_sample(3), tmp_path / "out"
    (out / "plots").mkdir(parents=True)
    (out / "plots").chmod(0o500)
    try:
        assert main(["run", str(seq), "--out", str(out), "--quiet"]) == 2
        assert "plots" in error_line(capsys)
        assert not (out / "trajectory.txt").exists()
    finally:
        (out / "plots").chmod(0o700)


def _hold_lock(folder):
    """Lock ``folder`` as another process writing into it would (flock on the folder)."""
    fd = os.open(folder, os.O_RDONLY)
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    return fd


@pytest.mark.parametrize("command", ["run", "calibrate", "analyze-noise", "simulate"])
def test_second_writer_into_the_same_folder_is_refused(small_sample, tmp_path, capsys, command):
    seq, out = small_sample(2), tmp_path / "out"
    out.mkdir()
    (out / "relative.txt").write_text("# the other run's line\n")
    args = {"run": ["run", str(seq)], "calibrate": ["calibrate", str(seq)],
            "analyze-noise": ["analyze-noise", str(seq)], "simulate": ["simulate", "--runs", "2"]}[command]
    fd = _hold_lock(out)
    try:
        assert main([*args, "--out", str(out), "--quiet"]) == 2
        assert "another covo command" in error_line(capsys)
    finally:
        os.close(fd)
    assert (out / "relative.txt").read_text() == "# the other run's line\n"
    # once the other writer is done, the folder can be used again
    if command == "run":
        assert main([*args, "--out", str(out), "--quiet", "--no-plots"]) == 0


@pytest.mark.parametrize("command", ["run", "analyze-noise", "calibrate"])
def test_results_are_not_written_into_a_sequence_folder(small_sample, tmp_path, capsys, command):
    """An ``--out`` that is a sequence's folder (its own, however spelt, or another one) is refused
    before anything is written into it."""
    seq, other = small_sample(2), small_sample(2)
    before = {d: sorted(p.name for p in d.rglob("*")) for d in (seq, other)}
    for out in (seq, seq / "rgb" / "..", other):
        plots = [] if command == "calibrate" else ["--no-plots"]
        assert main([command, str(seq), "--out", str(out), "--quiet", *plots]) == 2
        err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
        assert err == [f"covo: error: {out}: is a sequence's folder (it holds a TUM sequence's rgb.txt); write the "
                       "results into another one (--out)"], err
    assert {d: sorted(p.name for p in d.rglob("*")) for d in (seq, other)} == before


def test_package_warnings_print_as_one_line_and_others_as_python_prints_them(monkeypatch, capsys):
    import warnings

    from covo_gtsam.errors import CovoWarning

    def command(args):
        warnings.warn("ours", CovoWarning, stacklevel=1)
        warnings.warn("a library's", UserWarning, stacklevel=1)
        return 0

    monkeypatch.setattr(cli, "cmd_run", command)
    with pytest.warns(UserWarning) as record:  # what the printer leaves to the handler before it
        assert main(["run", "x", "--out", "y"]) == 0
    assert [str(w.message) for w in record] == ["a library's"]
    assert capsys.readouterr().err == "covo: warning: ours\n"
    with warnings.catch_warnings():  # as under python -W error: the warning is one error line, exit code 2
        warnings.simplefilter("error", CovoWarning)
        assert main(["run", "x", "--out", "y"]) == 2
    assert capsys.readouterr().err == "covo: error: ours\n"


def test_run_leaves_the_folder_unlocked(small_sample, tmp_path, capsys):
    seq, out = small_sample(2), tmp_path / "out"
    assert main(["run", str(seq), "--out", str(out), "--quiet", "--no-plots"]) == 0
    os.close(_hold_lock(out))  # would raise BlockingIOError if the run had kept its lock


def test_every_frame_lost_is_loud_with_exit_code_3(small_sample, tmp_path, capsys):
    import cv2

    seq, out = small_sample(3), tmp_path / "out"
    for png in (seq / "depth").glob("*.png"):
        cv2.imwrite(str(png), np.zeros((480, 640), np.uint16))
    assert main(["run", str(seq), "--out", str(out), "--quiet"]) == cli.EXIT_NOTHING_TRACKED == 3
    captured = capsys.readouterr()
    assert "no frame could be tracked" in captured.err and "all 3 frames are lost" in captured.err
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["tracked_frames"] == 0 and len(metrics["lost"]) == 3
    first_depth = re.escape(str(sorted((seq / "depth").glob("*.png"))[0]))
    assert re.fullmatch(rf"only 0 features with valid depth \(of [1-9]\d* detected; need \d+\); the depth image "
                        rf"{first_depth} has no depth within \[0\.5, 5\] m \(all zero or out of range\)",
                        metrics["lost"][0]["reason"]), metrics["lost"][0]


def test_no_relative_pose_at_all_is_loud_with_exit_code_3(small_sample, tmp_path, capsys):
    import cv2

    seq, out = small_sample(4), tmp_path / "out"
    for png in sorted((seq / "depth").glob("*.png"))[1:]:  # only the first frame has depth
        cv2.imwrite(str(png), np.zeros((480, 640), np.uint16))
    assert main(["run", str(seq), "--out", str(out), "--quiet", "--no-plots"]) == cli.EXIT_NOTHING_TRACKED
    captured = capsys.readouterr()
    assert "no relative pose could be estimated" in captured.err
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["tracked_frames"] == 1 and len(metrics["lost"]) == 3
    # the reason says which stage ran short: features were found, none had depth
    pattern = (r"only 0 point pairs \(need \d+; [1-9]\d* features detected, 0 with valid depth, 0 matched\); "
               r"the depth image {} has no depth within")
    depths = sorted((seq / "depth").glob("*.png"))[1:]
    assert all(re.search(pattern.format(re.escape(str(png))), lost["reason"])
               for lost, png in zip(metrics["lost"], depths, strict=True)), metrics["lost"]
    assert not [line for line in (out / "relative.txt").read_text().splitlines() if not line.startswith("#")]


@pytest.mark.parametrize("exc", [KeyboardInterrupt(), "import"])
def test_ctrl_c_during_start_up_is_one_line(monkeypatch, capsys, exc):
    def interrupted():
        if exc == "import":
            try:
                raise KeyboardInterrupt
            except KeyboardInterrupt as inner:
                raise ImportError("initialization failed") from inner
        raise exc

    monkeypatch.setattr(cli, "build_parser", interrupted)
    assert main(["run", "x", "--out", "y"]) == 130
    assert "interrupted" in error_line(capsys)


def test_unrelated_import_error_is_not_hidden(monkeypatch):
    def broken():
        raise ImportError("no module named something")

    monkeypatch.setattr(cli, "build_parser", broken)
    with pytest.raises(ImportError):
        main(["run", "x", "--out", "y"])


# -- interrupted runs, determinism, figures --------------------------------------------------------

def test_interrupted_run_leaves_valid_files(small_seq, tmp_path, monkeypatch):
    from covo_gtsam import odometry
    from covo_gtsam.datasets.tum import TumSequence
    from covo_gtsam.pipeline import run_sequence

    original = odometry.VisualOdometry.register_frame
    calls = {"n": 0}

    def interrupting(self, *a, **k):
        calls["n"] += 1
        if calls["n"] == 5:
            raise KeyboardInterrupt
        return original(self, *a, **k)

    monkeypatch.setattr(odometry.VisualOdometry, "register_frame", interrupting)
    with pytest.raises(KeyboardInterrupt):
        run_sequence(TumSequence(small_seq), tmp_path / "o", plots=False, progress=False)
    stamps, poses = load_tum_trajectory(tmp_path / "o" / "trajectory.txt")
    t_ref, _, rel, covs = load_relative_poses(tmp_path / "o" / "relative.txt")
    assert len(stamps) == 4 and len(rel) == 3
    assert np.all(np.isfinite(poses)) and np.all(np.isfinite(covs))


def test_same_input_gives_identical_outputs(small_seq, tmp_path):
    for name in ("a", "b"):
        assert main(["run", str(small_seq), "--out", str(tmp_path / name), "--quiet", "--no-plots"]) == 0
    for f in ("trajectory.txt", "relative.txt"):
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes()


def test_missing_matplotlib_is_reported_not_silent(small_seq, tmp_path, monkeypatch, capsys):
    from covo_gtsam import plots

    monkeypatch.setattr(plots, "_plt", lambda: None)
    assert main(["run", str(small_seq), "--out", str(tmp_path / "o"), "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "plots skipped" in err and "covo-gtsam[plots]" in err
    assert not (tmp_path / "o" / "plots").exists()


@pytest.mark.slow
def test_rerun_without_ground_truth_removes_stale_plots(small_seq, tmp_path):
    pytest.importorskip("matplotlib")
    out = tmp_path / "o"
    assert main(["run", str(small_seq), "--out", str(out), "--quiet"]) == 0
    assert (out / "plots" / "nees.png").exists() and (out / "plots" / "rpe.png").exists()
    (small_seq / "groundtruth.txt").unlink()
    assert main(["run", str(small_seq), "--out", str(out), "--quiet"]) == 0
    assert (out / "plots" / "trajectory.png").exists()
    assert not (out / "plots" / "nees.png").exists() and not (out / "plots" / "rpe.png").exists()


@pytest.mark.parametrize("kind", ["missing", "empty", "folder"])
def test_a_run_without_usable_ground_truth_says_why(small_sample, tmp_path, capsys, kind):
    seq = small_sample(3)
    gt = seq / "groundtruth.txt"
    gt.unlink()
    if kind == "empty":
        gt.write_text("# timestamp tx ty tz qx qy qz qw\n")
    elif kind == "folder":
        gt.mkdir()
    assert main(["run", str(seq), "--out", str(tmp_path / "o"), "--quiet", "--no-plots"]) == 0
    out = capsys.readouterr().out
    want = {"missing": "no ground truth", "empty": "groundtruth.txt has no samples",
            "folder": "groundtruth.txt is not a file"}[kind]
    assert f"{want}; accuracy and consistency metrics skipped" in out


def test_relative_txt_carries_each_pairs_settled_covariance_and_pose(small_seq, tmp_path):
    """A pair is written once the next frame has settled its latency term
    (``sensor.latency_look_ahead``) and moved its pose (``sensor.rolling_shutter_look_ahead``):
    relative.txt holds the covariances and relative poses the run's steps end with, which differ
    from those the look-ahead off gives for the pairs it revised, and the last pair is written too."""
    from covo_gtsam.config import OdometryConfig
    from covo_gtsam.datasets.tum import TumSequence
    from covo_gtsam.pipeline import run_sequence

    covs, poses = {}, {}
    for on in (True, False):
        cfg = OdometryConfig().replace(sensor={"latency_look_ahead": on, "rolling_shutter_look_ahead": on})
        result = run_sequence(TumSequence(small_seq), tmp_path / str(on), config=cfg, plots=False, progress=False)
        pairs = [s for s in result.steps if s.has_relative_pose]
        _, _, T, written = load_relative_poses(tmp_path / str(on) / "relative.txt")
        assert len(written) == len(pairs) == len(result.steps) - 1
        np.testing.assert_allclose(written, [s.covariance for s in pairs], rtol=1e-6, atol=1e-15)
        np.testing.assert_allclose(T, [s.relative.matrix() for s in pairs], atol=1e-6)
        covs[on], poses[on] = written, T
    assert np.sum(np.any(~np.isclose(covs[True], covs[False], rtol=1e-3), axis=(1, 2))) >= len(covs[True]) // 2
    moved = np.linalg.norm(poses[True][:, :3, 3] - poses[False][:, :3, 3], axis=1)
    assert np.sum(moved > 1e-5) >= len(moved) // 2
