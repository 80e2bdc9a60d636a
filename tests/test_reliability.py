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
from covo_gtsam.errors import CovoError, DegenerateGeometryError, InputError
from covo_gtsam.estimator import estimate_relative_pose
from covo_gtsam.io import load_relative_poses, load_tum_trajectory
from covo_gtsam.odometry import VisualOdometry
from conftest import copy_sample

N_FRAMES = 8


@pytest.fixture
def small_seq(sample_dir, tmp_path) -> Path:
    """A copy of the first N_FRAMES frames of the sample sequence, safe to corrupt."""
    return copy_sample(tmp_path / "rgbd_dataset_freiburg1_small", N_FRAMES)


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


def test_cli_listed_file_missing_makes_its_frame_lost(small_seq, tmp_path):
    rgb, _, t = frame_files(small_seq, 3)
    rgb.unlink()
    proc = run_cli(["run", str(small_seq), "--out", str(tmp_path / "o"), "--no-plots"])
    assert proc.returncode == 0 and "Traceback" not in proc.stderr
    m = json.loads((tmp_path / "o" / "metrics.json").read_text())
    assert m["lost_frames"] == 1 and m["lost"][0]["timestamp"] == pytest.approx(t)
    assert rgb.name in m["lost"][0]["reason"]


def test_cli_no_frame_has_both_images(small_seq, tmp_path):
    shutil.rmtree(small_seq / "depth")
    assert_clean_error(run_cli(["run", str(small_seq), "--out", str(tmp_path / "o")]), "no frame has both")


@pytest.mark.parametrize("content,needle", [("{not json", "not a valid JSON"), ('{"pixel_sigmaa": 2}', "unknown"),
                                            (None, "cannot read"), ('{"weighting": "fancy"}', "unknown weighting"),
                                            ('{"robust": "tukey"}', "unknown robust"),
                                            ('{"motion_model": "fast"}', "unknown motion_model"),
                                            ('{"pixel_sigma": -1}', "pixel_sigma must be a positive"),
                                            ('{"frame_sigma_trans_m": "x"}', "frame_sigma_trans_m must be"),
                                            ('{"restart_after": 0}', "restart_after must be"),
                                            ('{"frontend": 5}', "frontend must be a table"),
                                            ('{"frontend": "abc"}', "frontend must be a table"),
                                            ('{"keyframes": "false"}', "keyframes must be true or false"),
                                            ('{"pixel_sigma": true}', "pixel_sigma must be a positive"),
                                            ('{"frontend": {"scale_factor": 1e300}}', "frontend.scale_factor"),
                                            ('{"frontend": {"n_levels": 100000}}', "frontend.n_levels"),
                                            ('{"frontend": {"patch_size": 100000}}', "frontend.patch_size"),
                                            ('{"frontend": {"n_levels": 40, "scale_factor": 2}}', "pyramid"),
                                            ('{"frontend": {"patch_size": 300}}', "frontend.patch_size 300")])
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
    from covo_gtsam.datasets.images import load_depth
    from covo_gtsam.datasets.tum import TumSequence
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


# -- configuration values: every field type- and range-checked -----------------------------------

def _bad_values(default) -> list:
    """Values of the wrong type (or out of range) for a field with this default."""
    if isinstance(default, bool):
        return ["false", "true", 0, 1, None]
    if isinstance(default, int):
        return [True, 2.5, "3", None, -1]
    if isinstance(default, float):
        return [True, "1.0", None, float("nan"), -1.0]
    if isinstance(default, str):
        return [5, "no-such-choice", None, ["rigid3d"]]
    return [True, "x", -1, 2.5]  # robust/max_hamming (None by default)


def _config_cases():
    import dataclasses

    from covo_gtsam.frontend import FrontendConfig
    from covo_gtsam.odometry import OdometryConfig

    for cls, prefix in ((OdometryConfig, ""), (FrontendConfig, "frontend.")):
        for f in dataclasses.fields(cls):
            if f.name == "frontend":
                continue
            default = getattr(cls(), f.name)
            for bad in _bad_values(default):
                if f.name == "robust" and bad is None:
                    continue  # None is a valid kernel choice
                yield pytest.param(prefix, f.name, bad, id=f"{prefix}{f.name}={bad!r}")


@pytest.mark.parametrize("prefix,name,bad", list(_config_cases()))
def test_every_config_field_rejects_wrong_types(prefix, name, bad):
    from covo_gtsam.errors import ConfigError
    from covo_gtsam.odometry import OdometryConfig

    data = {"frontend": {name: bad}} if prefix else {name: bad}
    with pytest.raises(ConfigError) as info:
        OdometryConfig.from_dict(data)
    assert name in str(info.value)


def test_config_accepts_its_own_dict_and_numpy_scalars():
    from covo_gtsam.odometry import OdometryConfig

    cfg = OdometryConfig()
    assert OdometryConfig.from_dict(cfg.to_dict()) == cfg
    assert OdometryConfig.from_dict({"frontend": None}) == cfg
    OdometryConfig.from_dict({"pixel_sigma": np.float32(1.5), "restart_after": np.int64(3), "keyframes": np.bool_(True),
                              "frontend": {"n_features": np.int32(500), "scale_factor": 2}})


def test_orb_pyramid_and_patch_must_fit_the_camera():
    from covo_gtsam.errors import ConfigError
    from covo_gtsam.frontend import FrontendConfig
    from covo_gtsam.odometry import OdometryConfig

    with pytest.raises(ConfigError, match="frontend.n_levels 40 .*pyramid"):
        VisualOdometry(Camera.preset("fr1"), OdometryConfig(frontend=FrontendConfig(n_levels=40, scale_factor=2.0)))
    with pytest.raises(ConfigError, match="frontend.patch_size 240"):
        VisualOdometry(Camera.preset("fr1"), OdometryConfig(frontend=FrontendConfig(patch_size=240)))
    VisualOdometry(Camera.preset("fr1"), OdometryConfig(frontend=FrontendConfig(n_levels=9, scale_factor=2.0)))


# -- analyze-noise and simulate arguments ---------------------------------------------------------

def assert_argument_error(proc: subprocess.CompletedProcess, *needles: str) -> None:
    """argparse's usage lines, then one error line; exit 2, no traceback."""
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    last = proc.stderr.strip().splitlines()[-1]
    assert "error:" in last
    for n in needles:
        assert n in last, last


def test_cli_analyze_noise_too_few_frames(small_seq, tmp_path):
    assert_argument_error(run_cli(["analyze-noise", str(small_seq), "--out", str(tmp_path / "o"), "--max-frames", "1"]),
                          "--max-frames", "2")
    rgb = (small_seq / "rgb.txt").read_text().splitlines()
    (small_seq / "rgb.txt").write_text(rgb[0] + "\n")  # a one-frame sequence
    assert_clean_error(run_cli(["analyze-noise", str(small_seq), "--out", str(tmp_path / "o"), "--no-plots",
                                "--quiet"]), small_seq.name, "at least 2 frames")


def test_cli_analyze_noise_without_any_analysable_pair(small_seq, tmp_path):
    # ground truth exists but covers none of the frames: no pair can be analysed
    (small_seq / "groundtruth.txt").write_text("1.0 0 0 0 0 0 0 1\n1.01 0 0 0 0 0 0 1\n")
    proc = run_cli(["analyze-noise", str(small_seq), "--out", str(tmp_path / "o"), "--no-plots", "--quiet"])
    assert_clean_error(proc, "no frame pair could be analysed")
    assert not (tmp_path / "o" / "noise.json").exists()


def test_analysis_skips_unreadable_frames_but_not_bugs(small_seq, monkeypatch):
    from covo_gtsam import analysis
    from covo_gtsam.datasets.tum import TumSequence

    corrupt(small_seq, 3, "truncated")
    summary = analysis.analyze_sequence(TumSequence(small_seq))
    assert summary["frame_pairs"] == N_FRAMES - 3  # the pairs 2-3 and 3-4 are gone

    def broken(*a, **k):
        raise RuntimeError("a bug, not a bad frame")

    monkeypatch.setattr(analysis, "prepare_frame", broken)
    with pytest.raises(RuntimeError, match="a bug"):
        analysis.analyze_sequence(TumSequence(small_seq))


@pytest.mark.parametrize("args,needle", [(["--seed", "-1"], "--seed"), (["--runs", "0"], "--runs"),
                                         (["--points", "2"], "--points"), (["--pixel-sigma", "0"], "--pixel-sigma"),
                                         (["--pixel-sigma", "1e-9"], "--pixel-sigma"), (["--max-depth", "inf"], "--max-depth"),
                                         (["--min-depth", "-1"], "--min-depth"), (["--scale", "inf"], "--scale"),
                                         (["--points", "100000000"], "--points"), (["--pixel-sigma", "1e300"], "--pixel-sigma"),
                                         (["--scale", "1e308"], "--scale")])
def test_cli_simulate_bad_arguments(tmp_path, args, needle):
    assert_argument_error(run_cli(["simulate", *args, "--out", str(tmp_path / "o"), "--no-plots"]), needle)


def test_cli_simulate_depth_range_reversed(tmp_path):
    proc = run_cli(["simulate", "--min-depth", "5", "--max-depth", "1", "--out", str(tmp_path / "o"), "--no-plots"])
    assert_clean_error(proc, "--min-depth", "--max-depth")
    assert proc.returncode == 2


@pytest.mark.parametrize("content,needle", [
    ('{"pixel_sigma": 1e300}', "pixel_sigma"), ('{"frame_sigma_trans_m": 1e200}', "frame_sigma_trans_m"),
    ('{"frame_interval_s": 1e-320}', "frame_interval_s"), ('{"max_translation_m": 1e200}', "max_translation_m"),
    ('{"rolling_shutter_s": 1e300}', "rolling_shutter_s"), ('{"scale": 1e308}', "scale")])
def test_cli_config_values_beyond_sane_limits(small_seq, tmp_path, content, needle):
    cfg = tmp_path / "c.json"
    cfg.write_text(content)
    assert_clean_error(run_cli(["run", str(small_seq), "--out", str(tmp_path / "o"), "--config", str(cfg)]), needle)


@pytest.mark.parametrize("suffix", [".json", ".toml", ".TOML"])
def test_cli_config_not_utf8_or_broken(small_seq, tmp_path, suffix):
    cfg = tmp_path / f"c{suffix}"
    cfg.write_bytes(b"\xff\xfe\x00bad")
    assert_clean_error(run_cli(["run", str(small_seq), "--out", str(tmp_path / "o"), "--config", str(cfg)]), "UTF-8")
    if suffix != ".json" and sys.version_info < (3, 11):
        return  # no TOML parser before Python 3.11 (a separate message says so)
    cfg.write_text("not = [valid")
    kind = "JSON" if suffix == ".json" else "TOML"
    assert_clean_error(run_cli(["run", str(small_seq), "--out", str(tmp_path / "o"), "--config", str(cfg)]),
                       f"not a valid {kind}")


# -- library API: arguments -----------------------------------------------------------------------

@pytest.mark.parametrize("max_frames", [-5, 0, 2.5, True, "3"])
def test_run_sequence_rejects_bad_max_frames(small_seq, tmp_path, max_frames):
    from covo_gtsam.datasets.tum import TumSequence
    from covo_gtsam.errors import ConfigError
    from covo_gtsam.pipeline import run_sequence

    with pytest.raises(ConfigError, match="max_frames"):
        run_sequence(TumSequence(small_seq), tmp_path / "o", max_frames=max_frames, plots=False, progress=False)
    assert not (tmp_path / "o").exists()


def test_camera_preset_names_are_accepted(small_seq):
    from covo_gtsam.datasets.tum import TumSequence
    from covo_gtsam.errors import ConfigError

    assert TumSequence(small_seq, camera="fr2").camera == Camera.preset("fr2")
    assert TumSequence(small_seq, camera="freiburg3").camera == Camera.preset("fr3")
    with pytest.raises(ConfigError, match="fr9"):
        TumSequence(small_seq, camera="fr9")
    assert VisualOdometry("fr1").camera == Camera.preset("fr1")
    with pytest.raises(ConfigError, match="camera must be a Camera or a preset name"):
        VisualOdometry(5)
    with pytest.raises(ConfigError, match="config must be an OdometryConfig"):
        VisualOdometry("fr1", {"keyframes": True})


def _sim_pairs(n: int = 60, pixel_sigma: float = 2.0):
    from covo_gtsam.noise import PixelNoise, PointNoiseModel
    from covo_gtsam.simulation import SimulationConfig, make_scene, noisy_measurements

    rng = np.random.default_rng(1)
    scene = make_scene(SimulationConfig(num_points=n), rng)
    model = PointNoiseModel(pixel=PixelNoise(pixel_sigma, pixel_sigma))
    X0, Q0 = noisy_measurements(scene.X0, scene.camera, model, rng)
    X1, Q1 = noisy_measurements(scene.X1, scene.camera, model, rng)
    return scene, X0, X1, Q0, Q1


def test_estimate_accepts_a_4x4_initial_pose():
    import gtsam

    from covo_gtsam.errors import InputError

    scene, X0, X1, Q0, Q1 = _sim_pairs()
    a = estimate_relative_pose(X0, X1, Q0, Q1, initial=gtsam.Pose3(scene.T01))
    b = estimate_relative_pose(X0, X1, Q0, Q1, initial=scene.T01)
    np.testing.assert_allclose(b.matrix, a.matrix, atol=1e-9)
    np.testing.assert_allclose(b.covariance, a.covariance, rtol=1e-6)
    c = estimate_relative_pose(X0, X1, Q0, Q1, initial=np.eye(4))
    np.testing.assert_allclose(c.matrix, a.matrix, atol=1e-6)
    for bad, needle in ((np.eye(3), "4x4"), (2 * np.eye(4), "rigid"), ("x", "4x4"), (np.full((4, 4), np.nan), "NaN")):
        with pytest.raises(InputError, match=needle) as info:
            estimate_relative_pose(X0, X1, Q0, Q1, initial=bad)
        assert "initial" in str(info.value)


def test_string_scale_is_a_clear_error():
    from covo_gtsam.errors import ConfigError
    from covo_gtsam.odometry import OdometryConfig
    from covo_gtsam.simulation import SimulationConfig

    for cls in (OdometryConfig, SimulationConfig):
        with pytest.raises(ConfigError, match="scale must be a positive number.*, got '2'"):
            cls(scale="2")
        with pytest.raises(ConfigError, match="scale"):
            cls(scale=True)
    X = np.random.default_rng(0).uniform(-1, 1, (10, 3)) + [0, 0, 3]
    Q = np.tile(np.eye(3) * 1e-4, (10, 1, 1))
    for bad in ("2", True, float("nan")):
        with pytest.raises(InputError, match="scale must be a positive finite number"):
            estimate_relative_pose(X, X, Q, Q, scale=bad)


def test_register_frame_rejects_bad_timestamps(sample_dir):
    from covo_gtsam.datasets.tum import TumSequence
    from covo_gtsam.errors import InputError

    seq = TumSequence(sample_dir)
    vo = VisualOdometry(seq.camera)
    frame = vo.prepare(*seq.load(0))
    assert vo.register_frame(frame, timestamp=10.0).status == "first"
    for bad, needle in ((float("nan"), "finite"), (float("inf"), "finite"), (9.5, "earlier"), ("11", "number"),
                        (None, "number")):
        with pytest.raises(InputError, match=needle):
            vo.register_frame(frame, timestamp=bad)
    with pytest.raises(InputError, match="earlier"):
        vo.mark_lost(9.0, "unreadable")
    assert len(vo.steps) == 1  # rejected frames are not recorded
    # a repeated stamp is accepted (no velocity over a zero interval)
    step = vo.register_frame(frame, timestamp=10.0)
    assert step.tracked and step.velocity is None and np.all(np.isfinite(step.covariance))


# -- error messages -------------------------------------------------------------------------------

def test_huge_inputs_are_input_errors_not_numpy_errors():
    _, X0, X1, Q0, Q1 = _sim_pairs()
    for args in ((X0 * 1e160, X1 * 1e160, Q0, Q1), (X0, X1, Q0 * 1e200, Q1)):
        with pytest.raises(InputError, match="in magnitude"):
            estimate_relative_pose(*args)


def test_degeneracy_message_tells_collinear_from_ill_conditioned():
    _, X0, X1, Q0, Q1 = _sim_pairs(pixel_sigma=1e6)
    with pytest.raises(DegenerateGeometryError) as info:
        estimate_relative_pose(X0, X1, Q0, Q1)
    msg = str(info.value)
    assert "ill-conditioned" in msg and "collinear" not in msg and "\n" not in msg
    X = np.stack([np.linspace(-1, 1, 10), np.zeros(10), np.full(10, 2.0)], 1)
    Q = np.tile(np.eye(3) * 1e-4, (10, 1, 1))
    with pytest.raises(DegenerateGeometryError, match="collinear"):
        estimate_relative_pose(X + [0.05, 0.0, 0.0], X, Q, Q)


def test_covariance_error_is_one_line(monkeypatch):
    import gtsam

    from covo_gtsam import estimator
    from covo_gtsam.errors import CovarianceError

    def singular_marginals(information, pose, key=estimator.POSE_KEY):
        R = np.zeros((6, 6))
        R[:5, :5] = np.eye(5)
        graph = gtsam.GaussianFactorGraph()
        graph.add(gtsam.JacobianFactor(key, R, np.zeros(6), gtsam.noiseModel.Unit.Create(6)))
        values = gtsam.Values()
        values.insert(key, pose)
        return gtsam.Marginals(graph, values).marginalCovariance(key)  # GTSAM's multi-line error

    monkeypatch.setattr(estimator, "marginal_covariance", singular_marginals)
    _, X0, X1, Q0, Q1 = _sim_pairs()
    with pytest.raises(CovarianceError) as info:
        estimate_relative_pose(X0, X1, Q0, Q1)
    msg = str(info.value)
    assert "\n" not in msg and "GTSAM could not compute the marginal covariance" in msg
    assert "ndetermina" in msg and "https://" not in msg  # GTSAM 4.2 says "Indeterminant"


def test_cli_version_and_help(capsys):
    from covo_gtsam import __version__

    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0 and capsys.readouterr().out.strip() == f"covo {__version__}"
    with pytest.raises(SystemExit):
        main(["run", "--help"])
    out = capsys.readouterr().out
    assert "default: all" in out and "calibrated sensor terms" in out and "[rx ry rz tx ty tz]" in out


def test_frame_term_grows_with_the_frame_intervals_a_pair_spans(sample_dir):
    """Frames 0, 1 and then 3 (frame 2 skipped): the pair (1, 3) spans two intervals, so its frame
    term has twice the per-interval rotation variance and four times the translation variance;
    the reported covariance is kappa times the estimator's plus that term."""
    from covo_gtsam.calibration import ERROR_TERMS
    from covo_gtsam.datasets.tum import TumSequence
    from covo_gtsam.odometry import OdometryConfig

    seq = TumSequence(sample_dir)
    # the frame term alone: no frame-level terms, no restamping by the frame clock
    cfg = OdometryConfig(frame_clock=False, **{name: 0.0 for name in ERROR_TERMS.values()})
    vo = VisualOdometry(seq.camera, cfg)
    steps = [vo.register_frame(*seq.load(i), seq.timestamps[i]) for i in (0, 1, 3)]
    assert [s.status for s in steps] == ["first", "tracked", "tracked"]
    for step, k in ((steps[1], 1), (steps[2], 2)):
        assert cfg.frame_intervals(step.timestamp - step.ref_timestamp) == k
        r2, t2 = np.deg2rad(cfg.frame_sigma_rot_deg) ** 2, cfg.frame_sigma_trans_m**2
        frame = np.diag([r2 * k] * 3 + [t2 * k * k] * 3)
        np.testing.assert_allclose(cfg.frame_noise(step.timestamp - step.ref_timestamp), frame, rtol=1e-12)
        np.testing.assert_allclose(step.covariance, cfg.correlation_factor * step.result.covariance + frame,
                                   rtol=1e-12)
    assert cfg.frame_intervals(0.0) == 1 and cfg.frame_intervals(0.040) == 1 and cfg.frame_intervals(0.1) == 3
