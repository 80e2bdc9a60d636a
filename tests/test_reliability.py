"""Bad input: clear errors on the command line, lost frames inside a sequence, package exceptions."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from covo_gtsam.camera import Camera
from covo_gtsam.cli import main
from covo_gtsam.errors import CovoError, DegenerateGeometryError
from covo_gtsam.estimator import estimate_relative_pose
from covo_gtsam.io import load_relative_poses, load_tum_trajectory
from covo_gtsam.odometry import VisualOdometry

N_FRAMES = 8


@pytest.fixture
def small_seq(sample_dir, tmp_path) -> Path:
    """A copy of the first N_FRAMES frames of the sample sequence, safe to corrupt."""
    dst = tmp_path / "rgbd_dataset_freiburg1_small"
    dst.mkdir()
    (dst / "rgb").mkdir()
    (dst / "depth").mkdir()
    rgb = [line for line in (sample_dir / "rgb.txt").read_text().splitlines() if not line.startswith("#")][:N_FRAMES]
    last = float(rgb[-1].split()[0])
    depth = [line for line in (sample_dir / "depth.txt").read_text().splitlines()
             if not line.startswith("#") and float(line.split()[0]) <= last + 0.02]
    for line in rgb + depth:
        name = line.split()[1]
        shutil.copy(sample_dir / name, dst / name)
    (dst / "rgb.txt").write_text("\n".join(rgb) + "\n")
    (dst / "depth.txt").write_text("\n".join(depth) + "\n")
    shutil.copy(sample_dir / "groundtruth.txt", dst / "groundtruth.txt")
    return dst


def frame_files(seq: Path, i: int) -> tuple[Path, Path, float]:
    from covo_gtsam.datasets.tum import TumSequence

    s = TumSequence(seq)
    return Path(s.rgb_paths[i]), Path(s.depth_paths[i]), float(s.timestamps[i])


def run_cli(args: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "covo_gtsam.cli", *args], capture_output=True, text=True,
                          timeout=120, env={**os.environ, "PYTHONWARNINGS": "ignore"})


def assert_clean_error(proc: subprocess.CompletedProcess, *needles: str) -> None:
    assert proc.returncode != 0
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, proc.stderr
    assert "Traceback" not in proc.stderr
    for n in needles:
        assert n in lines[0], lines[0]


# -- command line ------------------------------------------------------------------------------

def test_cli_missing_folder(tmp_path):
    assert_clean_error(run_cli(["run", str(tmp_path / "nope"), "--out", str(tmp_path / "o")]), "nope", "does not exist")


def test_cli_folder_without_lists(tmp_path):
    (tmp_path / "seq").mkdir()
    assert_clean_error(run_cli(["run", str(tmp_path / "seq"), "--out", str(tmp_path / "o")]), "rgb.txt", "missing")


def test_cli_folder_without_depth_list(small_seq, tmp_path):
    (small_seq / "depth.txt").unlink()
    assert_clean_error(run_cli(["run", str(small_seq), "--out", str(tmp_path / "o")]), "depth.txt")


def test_cli_listed_file_missing(small_seq, tmp_path):
    rgb, _, _ = frame_files(small_seq, 3)
    rgb.unlink()
    assert_clean_error(run_cli(["run", str(small_seq), "--out", str(tmp_path / "o")]), rgb.name, "does not exist")


@pytest.mark.parametrize("content,needle", [("{not json", "not a valid JSON"), ('{"pixel_sigmaa": 2}', "unknown"),
                                            (None, "cannot read"), ('{"weighting": "fancy"}', "unknown weighting"),
                                            ('{"robust": "tukey"}', "unknown robust"),
                                            ('{"motion_model": "fast"}', "unknown motion_model"),
                                            ('{"pixel_sigma": -1}', "pixel_sigma must be a positive"),
                                            ('{"frame_sigma_trans_m": "x"}', "frame_sigma_trans_m must be"),
                                            ('{"restart_after": 0}', "restart_after must be")])
def test_cli_bad_config(small_seq, tmp_path, content, needle):
    cfg = tmp_path / "cfg.json"
    if content is not None:
        cfg.write_text(content)
    assert_clean_error(run_cli(["run", str(small_seq), "--out", str(tmp_path / "o"), "--config", str(cfg)]),
                       "cfg.json", needle)


def test_cli_output_not_writable(small_seq, tmp_path):
    blocker = tmp_path / "file.txt"
    blocker.write_text("x")
    assert_clean_error(run_cli(["run", str(small_seq), "--out", str(blocker / "sub")]), "file.txt", "not writable")


def test_cli_help_explains_conventions():
    for args in (["--help"], ["run", "--help"], ["simulate", "--help"], ["analyze-noise", "--help"]):
        proc = run_cli(args)
        assert proc.returncode == 0
        assert "T_ref,cur" in proc.stdout and "right perturbation" in proc.stdout


# -- inside a sequence: the frame is lost, the run goes on ---------------------------------------

def run_and_load(seq: Path, out: Path, progress: bool = False) -> tuple[dict, tuple]:
    args = ["run", str(seq), "--out", str(out), "--no-plots"] + ([] if progress else ["--quiet"])
    assert main(args) == 0
    m = json.loads((out / "metrics.json").read_text())
    return m, load_relative_poses(out / "relative.txt")


def corrupt(seq: Path, i: int, kind: str) -> float:
    rgb, depth, t = frame_files(seq, i)
    if kind == "truncated":
        data = rgb.read_bytes()
        rgb.write_bytes(data[: len(data) // 2])
    elif kind == "random":
        rgb.write_bytes(np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8).tobytes())
    elif kind == "small":
        cv2.imwrite(str(rgb), cv2.resize(cv2.imread(str(rgb)), (320, 240)))
    elif kind == "depth8":
        cv2.imwrite(str(depth), (cv2.imread(str(depth), cv2.IMREAD_UNCHANGED) // 256).astype(np.uint8))
    elif kind == "zero_depth":
        cv2.imwrite(str(depth), np.zeros((480, 640), np.uint16))
    elif kind == "uniform":
        cv2.imwrite(str(rgb), np.full((480, 640, 3), 128, np.uint8))
    elif kind == "jump":
        img = cv2.imread(str(rgb))
        cv2.imwrite(str(rgb), np.ascontiguousarray(np.roll(img[::-1, ::-1], 200, axis=1)))
    return t


@pytest.mark.parametrize("kind", ["truncated", "random", "small", "depth8", "zero_depth", "uniform", "jump"])
def test_bad_frame_is_lost_and_run_continues(small_seq, tmp_path, kind):
    t_bad = corrupt(small_seq, 3, kind)
    _, _, t_prev = frame_files(small_seq, 2)
    m, (t_ref, t_cur, rel, covs) = run_and_load(small_seq, tmp_path / "o")
    assert m["lost_frames"] == 1, m["lost"]
    assert m["restarts"] == []
    assert m["lost"][0]["timestamp"] == pytest.approx(t_bad) and m["lost"][0]["reason"]
    assert m["tracked_frames"] == N_FRAMES - 1
    # the frame after the lost one is matched to the last good one
    k = int(np.argmin(np.abs(t_cur - frame_files(small_seq, 4)[2])))
    assert t_ref[k] == pytest.approx(t_prev, abs=1e-6)
    assert np.all(np.isfinite(rel)) and np.all(np.isfinite(covs))
    stamps, _ = load_tum_trajectory(tmp_path / "o" / "trajectory.txt")
    assert len(stamps) == N_FRAMES - 1


def test_progress_line_shows_lost_count(small_seq, tmp_path):
    corrupt(small_seq, 3, "truncated")
    proc = run_cli(["run", str(small_seq), "--out", str(tmp_path / "o"), "--no-plots"])
    assert proc.returncode == 0
    assert "lost=1" in proc.stderr and "Traceback" not in proc.stderr


def test_run_restarts_after_a_run_of_lost_frames(sample_dir):
    """Frames 3..4 are blank, then the view jumps (flipped images, which cannot be matched to the
    last good frame): after restart_after lost frames the next frame starts a new segment and
    the frames after it are tracked again instead of being lost for good."""
    from covo_gtsam.datasets.tum import TumSequence
    from covo_gtsam.frontend import load_depth
    from covo_gtsam.graph import between_factors
    from covo_gtsam.odometry import OdometryConfig

    seq = TumSequence(sample_dir)
    cfg = OdometryConfig(restart_after=3)
    vo = VisualOdometry(seq.camera, cfg)
    statuses = []
    for i in range(10):
        img = cv2.imread(seq.rgb_paths[i])
        if i in (3, 4):
            img = np.full_like(img, 128)
        elif i >= 5:
            img = np.ascontiguousarray(np.roll(img[::-1, ::-1], 200, axis=1))
        statuses.append(vo.register_frame(img, load_depth(seq.depth_paths[i]), seq.timestamps[i]).status)
    # 3, 4 blank and 5 (flipped) lost; 6 cannot be matched to frame 2 either and restarts
    assert statuses == ["first", "tracked", "tracked", "lost", "lost", "lost", "restart",
                        "tracked", "tracked", "tracked"], statuses
    last, restart = vo.steps[2], vo.steps[6]
    assert restart.relative is None and "3 lost frames" in restart.reason
    assert np.allclose(restart.pose.matrix(), last.pose.matrix())
    assert np.allclose(restart.pose_covariance, last.pose_covariance + cfg.gap_noise())
    assert vo.steps[7].ref_timestamp == pytest.approx(restart.timestamp)
    factors, initial = between_factors(vo.steps)
    assert len(factors) == 2 + 3 and initial.size() == 7  # no factor across the gap


# -- library API -----------------------------------------------------------------------------

def test_register_frame_with_zero_depth_is_lost():
    vo = VisualOdometry(Camera.preset("fr1"))
    img = (np.random.default_rng(0).random((480, 640)) * 255).astype(np.uint8)
    step = vo.register_frame(img, np.zeros((480, 640), np.uint16), 1.0)
    assert step.status == "lost" and "depth" in step.reason


def test_register_frame_with_wrong_shapes_is_lost():
    vo = VisualOdometry(Camera.preset("fr1"))
    step = vo.register_frame(np.zeros((240, 320), np.uint8), np.zeros((240, 320), np.uint16), 1.0)
    assert step.status == "lost" and "size" in step.reason


def test_gtsam_exceptions_never_leak_for_coincident_points():
    X = np.tile([0.0, 0.0, 2.0], (5, 1))
    Q = np.tile(np.eye(3) * 1e-4, (5, 1, 1))
    with pytest.raises(CovoError) as info:
        estimate_relative_pose(X, X, Q, Q)
    assert isinstance(info.value, DegenerateGeometryError)


# -- outputs: interrupted runs, determinism ---------------------------------------------------

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


def test_rerun_without_ground_truth_removes_stale_plots(small_seq, tmp_path):
    pytest.importorskip("matplotlib")
    out = tmp_path / "o"
    assert main(["run", str(small_seq), "--out", str(out), "--quiet"]) == 0
    assert (out / "plots" / "nees.png").exists() and (out / "plots" / "rpe.png").exists()
    (small_seq / "groundtruth.txt").unlink()
    assert main(["run", str(small_seq), "--out", str(out), "--quiet"]) == 0
    assert (out / "plots" / "trajectory.png").exists()
    assert not (out / "plots" / "nees.png").exists() and not (out / "plots" / "rpe.png").exists()
