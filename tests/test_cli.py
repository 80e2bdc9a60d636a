"""The command line (covo_gtsam.cli): one clear line and exit code 2 for bad input, argument checks, help.

The commands run in-process: ``cli.main(argv)`` returns the exit code, argparse's own exits
(``--help``, usage errors) are ``SystemExit``, and capsys holds what was printed. The last tests
start a real process, where that is what they test.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pytest

from covo_gtsam import cli
from covo_gtsam.cli import main

from conftest import REPO, SAMPLE_DIR, corrupt_frame, frame_files


class Result(NamedTuple):
    returncode: int
    stdout: str
    stderr: str


@pytest.fixture
def run_cli(capsys):
    """``run_cli(argv)`` -> Result of ``covo ARGV`` run in-process."""

    def run(args: list[str]) -> Result:
        capsys.readouterr()  # drop what earlier steps printed
        try:
            code = cli.main(args)
        except SystemExit as exc:  # argparse: --help, --version, usage errors
            code = exc.code
        out = capsys.readouterr()
        return Result(code, out.out, out.err)

    return run


def assert_clean_error(proc: Result, *needles: str) -> None:
    assert proc.returncode != 0
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, proc.stderr
    assert "Traceback" not in proc.stderr
    for n in needles:
        assert n in lines[0], lines[0]


def assert_argument_error(proc: Result, *needles: str) -> None:
    """argparse's usage lines, then one error line; exit 2, no traceback."""
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    last = proc.stderr.strip().splitlines()[-1]
    assert "error:" in last
    for n in needles:
        assert n in last, last


# -- covo run: unusable input ---------------------------------------------------------------------

def test_cli_missing_folder(run_cli, tmp_path):
    assert_clean_error(run_cli(["run", str(tmp_path / "nope"), "--out", str(tmp_path / "o")]), "nope", "does not exist")


def test_cli_folder_without_lists(run_cli, tmp_path):
    (tmp_path / "seq").mkdir()
    assert_clean_error(run_cli(["run", str(tmp_path / "seq"), "--out", str(tmp_path / "o")]), "rgb.txt", "missing")


def test_cli_folder_without_depth_list(run_cli, small_seq, tmp_path):
    (small_seq / "depth.txt").unlink()
    assert_clean_error(run_cli(["run", str(small_seq), "--out", str(tmp_path / "o")]), "depth.txt")


def test_cli_listed_file_missing_makes_its_frame_lost(run_cli, small_seq, tmp_path):
    rgb, _, t = frame_files(small_seq, 3)
    rgb.unlink()
    proc = run_cli(["run", str(small_seq), "--out", str(tmp_path / "o"), "--no-plots"])
    assert proc.returncode == 0 and "Traceback" not in proc.stderr
    m = json.loads((tmp_path / "o" / "metrics.json").read_text())
    assert m["lost_frames"] == 1 and m["lost"][0]["timestamp"] == pytest.approx(t)
    assert rgb.name in m["lost"][0]["reason"]


def test_cli_no_frame_has_both_images(run_cli, small_seq, tmp_path):
    shutil.rmtree(small_seq / "depth")
    assert_clean_error(run_cli(["run", str(small_seq), "--out", str(tmp_path / "o")]), "no frame has both")


@pytest.mark.parametrize("content,needle", [("{not json", "not a valid JSON"), ('{"pixel_sigmaa": 2}', "unknown"),
                                            ('{"noise": {"pixel_sigmaa": 2}}', "unknown configuration keys: noise."),
                                            (None, "cannot read"),
                                            ('{"estimator": {"weighting": "fancy"}}', "unknown estimator.weighting"),
                                            ('{"estimator": {"robust": "tukey"}}', "unknown estimator.robust"),
                                            ('{"tracking": {"motion_model": "fast"}}', "unknown tracking.motion_model"),
                                            ('{"noise": {"pixel_sigma": -1}}', "noise.pixel_sigma must be a positive"),
                                            ('{"sensor": {"frame_sigma_trans_m": "x"}}', "frame_sigma_trans_m must be"),
                                            ('{"tracking": {"restart_after": 0}}', "restart_after must be"),
                                            ('{"frontend": 5}', "frontend must be a table"),
                                            ('{"frontend": "abc"}', "frontend must be a table"),
                                            ('{"sensor": 5}', "sensor must be a table"),
                                            ('{"tracking": {"keyframes": "false"}}', "keyframes must be true or false"),
                                            ('{"noise": {"pixel_sigma": true}}', "pixel_sigma must be a positive"),
                                            ('{"pixel_sigma": true}', "noise.pixel_sigma must be a positive"),
                                            ('{"pixel_sigma": 1, "noise": {"pixel_sigma": 2}}', "given twice"),
                                            ('{"frontend": {"scale_factor": 1e300}}', "frontend.scale_factor"),
                                            ('{"frontend": {"n_levels": 100000}}', "frontend.n_levels"),
                                            ('{"frontend": {"patch_size": 100000}}', "frontend.patch_size"),
                                            ('{"frontend": {"n_levels": 40, "scale_factor": 2}}', "pyramid"),
                                            ('{"frontend": {"patch_size": 300}}', "frontend.patch_size 300")])
def test_cli_bad_config(run_cli, small_seq, tmp_path, content, needle):
    cfg = tmp_path / "cfg.json"
    if content is not None:
        cfg.write_text(content)
    assert_clean_error(run_cli(["run", str(small_seq), "--out", str(tmp_path / "o"), "--config", str(cfg)]),
                       "cfg.json", needle)


@pytest.mark.parametrize("content,needle", [
    ('{"pixel_sigma": 1e300}', "pixel_sigma"), ('{"frame_sigma_trans_m": 1e200}', "frame_sigma_trans_m"),
    ('{"frame_interval_s": 1e-320}', "frame_interval_s"), ('{"max_translation_m": 1e200}', "max_translation_m"),
    ('{"rolling_shutter_s": 1e300}', "rolling_shutter_s"), ('{"scale": 1e308}', "scale")])
def test_cli_config_values_beyond_sane_limits(run_cli, small_seq, tmp_path, content, needle):
    cfg = tmp_path / "c.json"
    cfg.write_text(content)
    assert_clean_error(run_cli(["run", str(small_seq), "--out", str(tmp_path / "o"), "--config", str(cfg)]), needle)


@pytest.mark.parametrize("suffix", [".json", ".toml", ".TOML"])
def test_cli_config_not_utf8_or_broken(run_cli, small_seq, tmp_path, suffix):
    cfg = tmp_path / f"c{suffix}"
    cfg.write_bytes(b"\xff\xfe\x00bad")
    assert_clean_error(run_cli(["run", str(small_seq), "--out", str(tmp_path / "o"), "--config", str(cfg)]), "UTF-8")
    if suffix != ".json" and sys.version_info < (3, 11):
        return  # no TOML parser before Python 3.11 (a separate message says so)
    cfg.write_text("not = [valid")
    kind = "JSON" if suffix == ".json" else "TOML"
    assert_clean_error(run_cli(["run", str(small_seq), "--out", str(tmp_path / "o"), "--config", str(cfg)]),
                       f"not a valid {kind}")


def test_cli_output_not_writable(run_cli, small_seq, tmp_path):
    blocker = tmp_path / "file.txt"
    blocker.write_text("x")
    assert_clean_error(run_cli(["run", str(small_seq), "--out", str(blocker / "sub")]), "file.txt", "not writable")


def test_progress_line_shows_lost_count(run_cli, small_seq, tmp_path):
    corrupt_frame(small_seq, 3, "truncated")
    proc = run_cli(["run", str(small_seq), "--out", str(tmp_path / "o"), "--no-plots"])
    assert proc.returncode == 0
    assert "lost=1" in proc.stderr and "Traceback" not in proc.stderr


# -- analyze-noise and simulate arguments ---------------------------------------------------------

def test_cli_analyze_noise_too_few_frames(run_cli, small_seq, tmp_path):
    assert_argument_error(run_cli(["analyze-noise", str(small_seq), "--out", str(tmp_path / "o"), "--max-frames", "1"]),
                          "--max-frames", "2")
    rgb = (small_seq / "rgb.txt").read_text().splitlines()
    (small_seq / "rgb.txt").write_text(rgb[0] + "\n")  # a one-frame sequence
    assert_clean_error(run_cli(["analyze-noise", str(small_seq), "--out", str(tmp_path / "o"), "--no-plots",
                                "--quiet"]), small_seq.name, "at least 2 frames")


def test_cli_analyze_noise_without_any_analysable_pair(run_cli, small_seq, tmp_path):
    # ground truth exists but covers none of the frames: no pair can be analysed
    (small_seq / "groundtruth.txt").write_text("1.0 0 0 0 0 0 0 1\n1.01 0 0 0 0 0 0 1\n")
    proc = run_cli(["analyze-noise", str(small_seq), "--out", str(tmp_path / "o"), "--no-plots", "--quiet"])
    assert_clean_error(proc, "no frame pair could be analysed")
    assert not (tmp_path / "o" / "noise.json").exists()


@pytest.mark.parametrize("args,needle", [(["--seed", "-1"], "--seed"), (["--runs", "0"], "--runs"),
                                         (["--points", "2"], "--points"), (["--pixel-sigma", "0"], "--pixel-sigma"),
                                         (["--pixel-sigma", "1e-9"], "--pixel-sigma"),
                                         (["--max-depth", "inf"], "--max-depth"),
                                         (["--min-depth", "-1"], "--min-depth"), (["--scale", "inf"], "--scale"),
                                         (["--points", "100000000"], "--points"),
                                         (["--pixel-sigma", "1e300"], "--pixel-sigma"),
                                         (["--scale", "1e308"], "--scale")])
def test_cli_simulate_bad_arguments(run_cli, tmp_path, args, needle):
    assert_argument_error(run_cli(["simulate", *args, "--out", str(tmp_path / "o"), "--no-plots"]), needle)


def test_cli_simulate_depth_range_reversed(run_cli, tmp_path):
    proc = run_cli(["simulate", "--min-depth", "5", "--max-depth", "1", "--out", str(tmp_path / "o"), "--no-plots"])
    assert_clean_error(proc, "--min-depth", "--max-depth")
    assert proc.returncode == 2


# -- help and version ----------------------------------------------------------------------------

def test_run_notes_when_the_default_sensor_terms_belong_to_another_camera(run_cli, tmp_path):
    """The default sensor terms were fitted on the freiburg1 Kinect: a run with another camera and no
    ``--config`` says so (one line on stdout, the run as usual); the fr1 camera, or a configuration
    file, does not get the note."""
    note = "note: the covariance's sensor terms are the defaults, fitted on the freiburg1 Kinect"
    base = ["run", str(SAMPLE_DIR), "--max-frames", "4", "--no-plots", "--quiet"]
    other = run_cli([*base, "--out", str(tmp_path / "fr3"), "--camera", "fr3"])
    parts = json.loads((tmp_path / "fr3" / "metrics.json").read_text())["covariance_parts"]
    assert other.returncode == 0 and note in other.stdout
    rotation, translation = (100 * (1 - parts[block]["points"] - parts[block]["depth_drift"])
                             for block in ("rotation", "translation"))
    assert (f"(this camera: fr3; they are {rotation:.0f} % of this run's rotation variance and {translation:.0f} % "
            f"of its translation variance, the constant frame term {100 * parts['rotation']['frame_term']:.0f} % "
            "of the rotation)") in other.stdout
    same = run_cli([*base, "--out", str(tmp_path / "fr1")])  # the sample's folder names freiburg1
    assert same.returncode == 0 and note not in same.stdout
    (tmp_path / "c.toml").write_text("[sensor]\nlatency_sigma_s = 0.005\n")
    told = run_cli([*base, "--out", str(tmp_path / "cfg"), "--camera", "fr3", "--config", str(tmp_path / "c.toml")])
    assert told.returncode == 0 and note not in told.stdout


def test_the_freiburg1_kinect_is_known_by_its_intrinsics_or_its_bags_name():
    """A TUM bag's camera info carries the ROS default intrinsics (525 px), not the freiburg1
    calibration: its name tells the sensor, unless ``--camera`` told another camera."""
    from dataclasses import replace
    from types import SimpleNamespace

    from covo_gtsam.camera import PRESETS, Camera

    ros_default = Camera(525.0, 525.0, 319.5, 239.5, name="openni_rgb_optical_frame")
    bag = SimpleNamespace(camera=ros_default, path=Path("rgbd_dataset_freiburg1_desk.bag"))
    assert cli._is_fr1(bag, told=False) and not cli._is_fr1(bag, told=True)
    renamed = SimpleNamespace(camera=replace(PRESETS["fr1"], name="kinect"), path=Path("x"))
    assert cli._is_fr1(renamed, told=True)  # the preset's intrinsics under another name
    fr3 = SimpleNamespace(camera=PRESETS["fr3"], path=Path("rgbd_dataset_freiburg3_teddy"))
    assert not cli._is_fr1(fr3, told=False)


def test_cli_help_explains_conventions(run_cli):
    for args in (["--help"], ["run", "--help"], ["simulate", "--help"], ["analyze-noise", "--help"]):
        proc = run_cli(args)
        assert proc.returncode == 0
        assert "T_ref,cur" in proc.stdout and "right perturbation" in proc.stdout


def test_cli_version_and_help(capsys):
    from covo_gtsam import __version__

    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0 and capsys.readouterr().out.strip() == f"covo {__version__}"
    with pytest.raises(SystemExit):
        main(["run", "--help"])
    out = capsys.readouterr().out
    assert "default: all" in out and "calibrated sensor terms" in out and "[rx ry rz tx ty tz]" in out
    # an unknown option of a sub-command: that sub-command's usage, exit 2
    with pytest.raises(SystemExit) as info:
        main(["run", "seq", "--out", "o", "--bogus"])
    err = capsys.readouterr().err
    assert info.value.code == 2 and err.startswith("usage: covo run") and "unrecognized arguments: --bogus" in err


# -- a real process -------------------------------------------------------------------------------
# These tests start a process on purpose: what they test, the installed `covo` script and the
# interpreter's own SIGINT handling, does not exist inside pytest's process. Everything else above
# runs in-process, which is the same code without the start-up of a Python process per command.

#: Child processes ignore warnings, as the one-line stderr checks do not count a library's warnings.
QUIET_ENV = {**os.environ, "PYTHONWARNINGS": "ignore"}


def _stderr_lines(text: str) -> list[str]:
    return [ln for ln in text.splitlines() if ln.strip()]


def test_console_script_entry_point(tmp_path):
    """The installed ``covo`` script ([project.scripts] in pyproject.toml) reaches cli.main, and
    cli.main's return value becomes the process's exit code."""
    script = Path(sys.executable).with_name("covo")
    script = str(script) if script.is_file() else shutil.which("covo")
    if script is None:
        pytest.skip("no `covo` script: covo-gtsam is not installed in this environment (pip install .)")
    proc = subprocess.run([script, "run", str(tmp_path / "nope"), "--out", str(tmp_path / "o")],
                          capture_output=True, text=True, timeout=120, env=QUIET_ENV)
    assert proc.returncode == 2 and proc.stdout == ""
    lines = _stderr_lines(proc.stderr)
    assert len(lines) == 1 and "does not exist" in lines[0] and "Traceback" not in proc.stderr, proc.stderr


def _long_sequence(dst: Path, copies: int) -> Path:
    """The sample sequence listed ``copies`` times over, each copy one frame period after the last
    (images linked, not copied, through one folder link per copy, as an image is listed once; no
    ground truth): a run long enough to be interrupted."""
    dst.mkdir()
    for k in range(copies):
        (dst / f"rgb{k}").symlink_to(SAMPLE_DIR / "rgb")
        (dst / f"depth{k}").symlink_to(SAMPLE_DIR / "depth")
    for name in ("rgb.txt", "depth.txt"):
        text = (SAMPLE_DIR / name).read_text()
        rows = [ln.split() for ln in text.splitlines() if ln.strip() and not ln.startswith("#")]
        stamps = [float(r[0]) for r in rows]
        span = stamps[-1] - stamps[0] + 1 / 30
        lines = [f"{t + k * span:.6f} {r[1].replace('/', f'{k}/', 1)}" for k in range(copies)
                 for t, r in zip(stamps, rows)]
        (dst / name).write_text("\n".join(lines) + "\n")
    return dst


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
@pytest.mark.skipif(sys.platform == "win32", reason="needs POSIX signals")
def test_an_interrupt_swallowed_by_a_finalizer_is_not_lost():
    """A SIGINT whose KeyboardInterrupt is raised inside a ``__del__`` is printed as ignored and
    lost under Python's own handler; under ``recorded_sigint`` the frame loop's check still sees it."""
    from covo_gtsam.interrupt import check, recorded_sigint

    class Finalizer:
        def __del__(self):
            os.kill(os.getpid(), signal.SIGINT)
            for _ in range(10000):  # the handler runs in here, and Python ignores what it raises
                pass

    def swallow():
        Finalizer()  # collected at once

    swallow()  # Python's handler: nothing escapes, nothing is kept
    check()
    with recorded_sigint():
        swallow()
        with pytest.raises(KeyboardInterrupt):
            check()
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_the_frame_loop_stops_at_a_recorded_interrupt(small_sample, tmp_path, monkeypatch):
    """An interrupt recorded while the frames run (as a Ctrl-C that a finalizer swallowed leaves
    it) stops the run before its next frame, with no metrics."""
    from covo_gtsam import interrupt
    from covo_gtsam.odometry import VisualOdometry
    from covo_gtsam.pipeline import run_sequence

    calls = []
    register = VisualOdometry.register_frame

    def register_and_record(self, *args, **kwargs):
        calls.append(1)
        if len(calls) == 5:
            interrupt._ASKED.set()
        return register(self, *args, **kwargs)

    monkeypatch.setattr(VisualOdometry, "register_frame", register_and_record)
    try:
        with pytest.raises(KeyboardInterrupt):
            run_sequence(small_sample(12), tmp_path / "o", plots=False, progress=False)
    finally:
        interrupt._ASKED.clear()
    assert len(calls) == 5 and not (tmp_path / "o" / "metrics.json").exists()


@pytest.mark.slow
@pytest.mark.skipif(sys.platform == "win32", reason="needs POSIX signals")
def test_ctrl_c_ends_a_real_run_with_exit_code_130(tmp_path):
    """SIGINT to a running ``covo run``, as Ctrl-C sends it: the interpreter's handler raises
    KeyboardInterrupt wherever the main thread is (OpenCV, GTSAM, a file write); the process ends
    with 130 and one line on stderr, and the files written so far are readable."""
    import re
    import selectors
    import time

    from covo_gtsam.io import load_tum_trajectory

    seq = _long_sequence(tmp_path / "rgbd_dataset_freiburg1_long", copies=10)
    out = tmp_path / "o"
    proc = subprocess.Popen([sys.executable, "-m", "covo_gtsam.cli", "run", str(seq), "--out", str(out), "--no-plots"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, cwd=REPO, env=QUIET_ENV)
    try:
        # wait for the progress bar to count a few frames: the run is past its start-up
        seen, deadline = b"", time.monotonic() + 120
        with selectors.DefaultSelector() as sel:
            sel.register(proc.stderr, selectors.EVENT_READ)
            while not re.search(rb" ([3-9]|\d\d+)/\d+ ", seen):
                assert time.monotonic() < deadline and proc.poll() is None, seen[-500:].decode(errors="replace")
                if sel.select(timeout=1.0):
                    seen += os.read(proc.stderr.fileno(), 4096)
        proc.send_signal(signal.SIGINT)
        _, rest = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    err = (seen + rest).decode(errors="replace")
    assert proc.returncode == 130, err[-500:]
    assert "Traceback" not in err and "KeyboardInterrupt" not in err
    messages = re.findall(r"covo: [^\r\n]*", err)  # what is not the progress bar
    assert len(messages) == 1 and messages[0].startswith("covo: interrupted"), err[-500:]
    assert not (out / "metrics.json").exists()  # an interrupted run has no metrics
    stamps, poses = load_tum_trajectory(out / "trajectory.txt")
    assert len(stamps) >= 3 and np.all(np.isfinite(poses))
    total = len((seq / "rgb.txt").read_text().splitlines())
    assert len(stamps) < total and "100%" not in err  # stopped early


def test_run_whose_stdout_is_closed_early_ends_as_it_would_have(small_sample, tmp_path):
    """``covo run ... | head -1``: the reader leaves before the last lines; the run is written, and
    the exit code and stderr are those of the run (no traceback, no BrokenPipeError at exit): 0, and
    for a sequence whose frames are all lost its error line and 3."""
    import cv2

    def run(seq, out):
        proc = subprocess.Popen([sys.executable, "-m", "covo_gtsam.cli", "run", str(seq), "--out", str(out),
                                 "--no-plots", "--quiet"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=REPO)
        proc.stdout.close()  # nobody reads what it prints
        err = proc.stderr.read().decode()
        return proc.wait(timeout=300), err

    rc, err = run(small_sample(3), tmp_path / "o")
    assert rc == 0 and "Traceback" not in err and "BrokenPipe" not in err, err
    assert (tmp_path / "o" / "metrics.json").is_file()
    blind = small_sample(3)
    for png in (blind / "depth").glob("*.png"):
        cv2.imwrite(str(png), np.zeros((480, 640), np.uint16))
    rc, err = run(blind, tmp_path / "b")
    assert rc == cli.EXIT_NOTHING_TRACKED == 3 and "no frame could be tracked" in err and "Traceback" not in err, err
