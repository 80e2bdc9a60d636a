"""Extreme but finite input values never give NaN or inf in any output, nor a traceback."""

from __future__ import annotations

import json
import math
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from covo_gtsam import odometry
from covo_gtsam.cli import main
from covo_gtsam.errors import CovoWarning, InputError
from covo_gtsam.io import load_relative_poses, load_tum_trajectory
from covo_gtsam.odometry import OdometryConfig, VisualOdometry

#: metrics of covo run that are None exactly when not_computed names them
GT_METRICS = {"rpe_1": "rpe_1", "rpe_30": "rpe_30", "ate": "ate", "anees_translation": "anees"}


def strict_json(path: Path):
    """JSON without NaN/Infinity tokens (Python's json accepts them by default)."""
    def refuse(token):
        raise AssertionError(f"{path}: non-finite JSON token {token}")

    return json.loads(path.read_text(), parse_constant=refuse)


def all_numbers(obj):
    if isinstance(obj, dict):
        for v in obj.values():
            yield from all_numbers(v)
    elif isinstance(obj, list):
        for v in obj:
            yield from all_numbers(v)
    elif isinstance(obj, (int, float)) and not isinstance(obj, bool):
        yield obj


def check_outputs(out: Path) -> dict | None:
    """Every output of a run is finite and parses; returns metrics.json (None if not written)."""
    for name in ("trajectory.txt", "relative.txt"):
        for line in (out / name).read_text().splitlines():
            if not line.startswith("#"):
                values = [float(v) for v in line.split()]
                assert all(math.isfinite(v) for v in values), (name, line[:200])
    stamps, poses = load_tum_trajectory(out / "trajectory.txt")
    assert np.all(np.isfinite(poses))
    t_ref, t_cur, rel, covs = load_relative_poses(out / "relative.txt")
    assert np.all(np.isfinite(rel)) and np.all(np.isfinite(covs))
    for c in covs:
        assert np.allclose(c, c.T, rtol=1e-6, atol=0) and np.linalg.eigvalsh(0.5 * (c + c.T))[0] > 0
    if not (out / "metrics.json").exists():
        return None
    m = strict_json(out / "metrics.json")
    assert all(math.isfinite(v) for v in all_numbers(m))
    if "not_computed" in m:
        for key, reason_key in GT_METRICS.items():
            assert (m[key] is None) == (reason_key in m["not_computed"]), (key, m[key], m["not_computed"])
    return m


def set_stamp(seq: Path, index: int, stamp: str) -> None:
    """Give frame ``index`` of rgb.txt and depth.txt the timestamp text ``stamp``."""
    for name in ("rgb.txt", "depth.txt"):
        lines = (seq / name).read_text().splitlines()
        data = [i for i, ln in enumerate(lines) if ln.strip() and not ln.startswith("#")]
        parts = lines[data[index]].split()
        lines[data[index]] = f"{stamp} {parts[1]}"
        (seq / name).write_text("\n".join(lines) + "\n")


# ---- 1. a timestamp far beyond the others ------------------------------------------------------

@pytest.mark.parametrize("stamp", ["1e300", "1e308"])
def test_huge_last_timestamp_is_a_lost_frame(small_sample, tmp_path, capsys, stamp):
    seq, out = small_sample(4), tmp_path / "out"
    set_stamp(seq, 3, stamp)
    assert main(["run", str(seq), "--out", str(out), "--quiet", "--no-plots"]) == 0
    m = check_outputs(out)
    assert m["tracked_frames"] == 3 and m["lost_frames"] == 1
    assert m["lost"][0]["timestamp"] == float(stamp)
    assert "s after its reference frame" in m["lost"][0]["reason"]
    assert len(load_relative_poses(out / "relative.txt")[0]) == 2


def test_register_frame_after_a_huge_gap_is_lost(sample_dir):
    from covo_gtsam.datasets.tum import TumSequence

    seq = TumSequence(sample_dir)
    vo = VisualOdometry("fr1")
    images = [seq.load(i) for i in range(2)]
    assert vo.register_frame(*images[0], seq.timestamps[0]).status == "first"
    step = vo.register_frame(*images[1], 1e300)
    assert step.status == "lost" and step.covariance is None and "reference frame" in step.reason
    # the frames that follow at the new time are not matched across the gap either; after
    # restart_after of them a new segment starts, with a finite pose covariance
    steps = [vo.register_frame(*images[k % 2], 1e300) for k in range(vo.config.tracking.restart_after)]
    assert steps[-1].status == "restart" and np.all(np.isfinite(steps[-1].pose_covariance))


def test_frame_intervals_refuses_a_gap_no_recording_has():
    MAX_GAP_S = odometry.MAX_GAP_S
    cfg = OdometryConfig()
    assert cfg.frame_intervals(MAX_GAP_S) == round(MAX_GAP_S / cfg.sensor.frame_interval_s)
    assert np.all(np.isfinite(cfg.frame_noise(MAX_GAP_S)))
    for dt in (1e300, 1e308, math.inf):
        with pytest.raises(InputError, match="not one recording"):
            cfg.frame_intervals(dt)


# ---- 2. huge finite ground truth ---------------------------------------------------------------

def huge_ground_truth(seq: Path, value: str = "1e308") -> None:
    lines = (seq / "groundtruth.txt").read_text().splitlines()
    (seq / "groundtruth.txt").write_text("\n".join(
        ln if ln.startswith("#") else " ".join([ln.split()[0], value, value, value, *ln.split()[4:]])
        for ln in lines) + "\n")


@pytest.mark.slow
def test_run_with_huge_ground_truth_gives_null_metrics_with_reasons(small_sample, tmp_path, capsys):
    seq, out = small_sample(4), tmp_path / "out"
    huge_ground_truth(seq)
    assert main(["run", str(seq), "--out", str(out), "--quiet"]) == 0
    m = check_outputs(out)
    assert m["tracked_frames"] == 4
    for key, reason_key in GT_METRICS.items():
        assert m[key] is None and "ground truth" in m["not_computed"][reason_key]
    assert (out / "plots" / "trajectory.png").is_file()


def test_calibrate_with_huge_ground_truth_is_one_line(small_sample, tmp_path, capsys):
    """Every sample beyond the limit: each is left out (one warning line), and calibrate stops before
    its run with one error line; with one sample of each frame pair's left, at the run's end."""
    seq, out = small_sample(11), tmp_path / "out"
    plain = (seq / "groundtruth.txt").read_text()
    huge_ground_truth(seq)
    assert main(["calibrate", str(seq), "--out", str(out), "--quiet"]) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 2 and err[0].startswith("covo: warning:") and "more than 1e+09 m" in err[0], err
    assert err[1] == f"covo: error: {seq / 'groundtruth.txt'}: has no usable sample; calibration needs ground truth"
    assert not (out / "per_point_run").exists()
    samples = [ln for ln in plain.splitlines() if not ln.startswith("#")]
    (seq / "groundtruth.txt").write_text("\n".join(samples[:1]) + "\n")  # one sample: no frame pair inside it
    assert main(["calibrate", str(seq), "--out", str(out), "--quiet"]) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and "usable ground truth" in err[0], err
    assert check_outputs(out / "per_point_run")["tracked_frames"] == 11  # the run's own outputs are kept


def test_analyze_noise_with_huge_ground_truth_prints_no_nan(small_sample, tmp_path, capsys):
    seq, out = small_sample(3), tmp_path / "out"
    huge_ground_truth(seq)
    code = main(["analyze-noise", str(seq), "--out", str(out), "--quiet", "--no-plots"])
    captured = capsys.readouterr()
    assert not re.search(r"\bnan\b", captured.out + captured.err, re.IGNORECASE)
    # every sample is left out (a warning line), so there is no ground truth to analyse against
    assert code == 2 and "more than 1e+09 m from the origin left out" in captured.err
    assert "the noise analysis needs groundtruth.txt" in captured.err


def test_ground_truth_beyond_the_coordinate_limit_counts_as_missing(small_sample):
    from covo_gtsam.datasets.tum import MAX_GT_COORDINATE, TumSequence

    seq = small_sample(3)
    assert TumSequence(seq).gt_valid.all()
    huge_ground_truth(seq, f"{10 * MAX_GT_COORDINATE:g}")
    with pytest.warns(CovoWarning, match="more than 1e\\+09 m from the origin left out"):
        assert not TumSequence(seq).gt_valid.any()


# ---- whatever the input: no NaN/inf in any output ----------------------------------------------

FUZZ_FRAMES = 4

STEPS = st.sampled_from([0.0, 1e-9, 1e-4, 0.0333, 0.034, 1.0, 600.0, 1e5, 1e300])
POSITIONS = st.one_of(st.floats(-5.0, 5.0), st.sampled_from([1e8, -1e12, 1e300, 1e308, -1e308]))
CONFIG = st.fixed_dictionaries({}, optional={
    "pixel_sigma": st.floats(0.01, 1e4),
    "depth_sigma_scale": st.floats(1e-3, 1e3),
    "scale": st.floats(1e-6, 1e6),
    "correlation_factor": st.floats(1e-6, 1e6),
    "frame_sigma_rot_deg": st.floats(0.0, 180.0),
    "frame_sigma_trans_m": st.floats(0.0, 1e3),
    "frame_interval_s": st.floats(1e-4, 1e3),
    "rolling_shutter_s": st.floats(0.0, 1.0),
    "max_rotation_deg": st.floats(1e-3, 180.0),
    "max_translation_m": st.floats(1e-3, 1e3),
    "depth_scale": st.sampled_from([1.0, 5000.0, 1e9]),
    "motion_model": st.sampled_from(["constant_velocity", "none"]),
    "robust": st.sampled_from(["none", "huber", "cauchy"]),
    "variance_factor": st.booleans(),
    "keyframes": st.booleans(),
    "restart_after": st.integers(1, 3),
})


@pytest.fixture(scope="module")
def fuzz_base(tmp_path_factory):
    from conftest import copy_sample

    base = copy_sample(tmp_path_factory.mktemp("fuzz") / "rgbd_dataset_freiburg1_fuzz", FUZZ_FRAMES)
    names = {
        "rgb": [ln.split()[1] for ln in (base / "rgb.txt").read_text().splitlines()],
        "depth": [ln.split()[1] for ln in (base / "depth.txt").read_text().splitlines()][:FUZZ_FRAMES],
    }
    shutil.copytree(base / "depth", base.parent / "depth_as_recorded")
    return base, names


@pytest.mark.slow
@settings(max_examples=15, deadline=None, derandomize=True, phases=[Phase.explicit, Phase.generate],
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(start=st.sampled_from([0.0, 1305031229.5, -50.0, 1e300]), steps=st.lists(STEPS, min_size=3, max_size=3),
       gt=st.one_of(st.none(), st.lists(st.tuples(POSITIONS, st.floats(-1, 1), st.floats(0.1, 1)),
                                         min_size=FUZZ_FRAMES, max_size=FUZZ_FRAMES)),
       depth=st.sampled_from(["as recorded", "zero", "max", "noise", "times 0.01"]), config=CONFIG,
       plots=st.booleans())
def test_run_never_writes_nan_or_inf(fuzz_base, tmp_path, capsys, start, steps, gt, depth, config, plots):
    base, names = fuzz_base
    stamps = [start]
    for s in steps:
        stamps.append(stamps[-1] + s)
    (base / "rgb.txt").write_text("".join(f"{t!r} {n}\n" for t, n in zip(stamps, names["rgb"])))
    (base / "depth.txt").write_text("".join(f"{t!r} {n}\n" for t, n in zip(stamps, names["depth"])))
    if gt is None:
        (base / "groundtruth.txt").unlink(missing_ok=True)
    else:
        (base / "groundtruth.txt").write_text("".join(
            f"{t!r} {p!r} {0.1 * p!r} 0.5 {qx!r} 0.2 0.1 {qw!r}\n" for t, (p, qx, qw) in zip(stamps, gt)))
    shutil.rmtree(base / "depth")  # restore, then change the second frame's depth
    shutil.copytree(base.parent / "depth_as_recorded", base / "depth")
    if depth != "as recorded":
        path = base / names["depth"][1]
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        img = {"zero": np.zeros_like(img), "max": np.full_like(img, 65535),
               "noise": np.random.default_rng(0).integers(0, 65536, img.shape).astype(np.uint16),
               "times 0.01": (img * 0.01).astype(np.uint16)}[depth]
        cv2.imwrite(str(path), img)
    cfg = tmp_path / "config.json"
    cfg.write_text(json.dumps(config))
    out = tmp_path / "out"
    code = main(["run", str(base), "--out", str(out), "--quiet", "--config", str(cfg)]
                + ([] if plots else ["--no-plots"]))
    captured = capsys.readouterr()
    if len(set(stamps)) < len(stamps):  # two images at one instant: refused, one line
        assert code == 2 and "repeats the one of line" in captured.err and captured.err.count("covo: error") == 1
        return
    assert code in (0, 3), captured.err
    m = check_outputs(out)
    assert m is not None and 1 <= m["frames"] <= FUZZ_FRAMES
    summary = captured.out.splitlines()[0]
    assert not re.search(r"\b(nan|inf)\b", summary, re.IGNORECASE), summary


def test_a_covariance_without_information_loses_the_pair(sample_dir, tmp_path, monkeypatch):
    from covo_gtsam.config import OdometryConfig
    from covo_gtsam.odometry import _positive_definite
    from covo_gtsam.pipeline import run_sequence

    assert _positive_definite(np.diag([1e-6] * 3 + [1e-4] * 3))
    for bad in (np.full((6, 6), np.nan), np.zeros((6, 6)), np.diag([1.0] * 5 + [-1e-9]), np.eye(6) * 1e-320):
        assert not _positive_definite(bad)
    monkeypatch.setattr(OdometryConfig, "sensor_covariance", lambda self, C, dt, bases: np.eye(6) * 1e-320)
    run = run_sequence(str(sample_dir), tmp_path / "o", max_frames=3, plots=False, progress=False)
    lost = [s for s in run.steps if s.status == "lost"]
    assert len(lost) == 2 and all("positive definite" in s.reason for s in lost)
    assert "nan" not in (tmp_path / "o" / "graph.g2o").read_text().lower()


@pytest.mark.parametrize("setting", [("sensor", "correlation_factor"), ("estimator", "scale"),
                                     ("sensor", "depth_scale")])
def test_covariance_and_depth_scales_near_zero_are_rejected(setting):
    from covo_gtsam.config import OdometryConfig
    from covo_gtsam.errors import ConfigError

    section, name = setting
    with pytest.raises(ConfigError, match=name):
        OdometryConfig().replace(**{section: {name: 1e-310}})
