"""Smoke tests of the examples: run them as scripts on the 40-frame sample with small settings."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = "data/rgbd_dataset_freiburg1_rpy_head40"

pytestmark = pytest.mark.skipif(not (ROOT / SAMPLE).is_dir(), reason="sample sequence missing")


def run_example(*args: str, timeout: float = 120.0, env: dict | None = None) -> tuple[dict, str]:
    """Run an example script from the repository root; the timeout only guards against a hang
    (speed lives in benchmarks/)."""
    proc = subprocess.run([sys.executable, *args], cwd=ROOT, capture_output=True, text=True, timeout=timeout,
                          env=env)
    assert proc.returncode == 0, f"exit {proc.returncode}\nstdout:\n{proc.stdout}\nstderr:\n{proc.stderr}"
    lines = proc.stdout.strip().splitlines()
    assert lines, "no output"
    return json.loads(lines[-1]), proc.stdout


def finite_numbers(obj) -> list[float]:
    """All numbers in a JSON value (nested), as floats."""
    if isinstance(obj, bool):
        return []
    if isinstance(obj, (int, float)):
        return [float(obj)]
    if isinstance(obj, dict):
        return [x for v in obj.values() for x in finite_numbers(v)]
    if isinstance(obj, list):
        return [x for v in obj for x in finite_numbers(v)]
    return []


@pytest.mark.slow
def test_pose_graph_isam2(tmp_path):
    out = tmp_path / "pg"
    summary, stdout = run_example(
        "examples/pose_graph_isam2.py", SAMPLE, "--out", str(out), "--max-frames", "20", "--fix-every", "5",
        "--seed", "3", "--repeat", "2")
    for key in ("ate_rmse_covo", "ate_rmse_unit", "ate_rmse_median", "ate_rmse_vo_only"):
        assert math.isfinite(summary[key]) and 0 <= summary[key] < 1.0, (key, summary[key])
    assert summary["frames"] == 20
    assert summary["fixes"] == 3  # frames 5, 10, 15
    assert all(math.isfinite(x) for x in finite_numbers(summary))
    assert summary["isam2_vs_batch_max_m"] < 1e-3
    for name in ("pose_graph.json", "pose_graph_trajectories.png", "pose_graph_errors.png", "vo/trajectory.txt"):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    assert json.loads((out / "pose_graph.json").read_text())["ate_rmse_covo"] == summary["ate_rmse_covo"]
    assert "ATE RMSE" in stdout


def test_pose_graph_isam2_without_out_writes_into_a_temporary_folder(tmp_path):
    """Without --out the results go to a new folder in the temporary directory, never into the
    folder it is run from (here the repository root)."""
    before = sorted(p.name for p in ROOT.iterdir())
    summary, stdout = run_example(
        "examples/pose_graph_isam2.py", SAMPLE, "--max-frames", "8", "--fix-every", "3", "--no-plots",
        env={**os.environ, "TMPDIR": str(tmp_path)})
    out = Path(next(ln for ln in stdout.splitlines() if ln.startswith("results in ")).removeprefix("results in "))
    assert out.parent == tmp_path and out.name.startswith("covo-pose-graph-")
    assert json.loads((out / "pose_graph.json").read_text())["frames"] == summary["frames"] == 8
    assert (out / "vo" / "trajectory.txt").is_file()
    assert sorted(p.name for p in ROOT.iterdir()) == before


def test_pose_graph_isam2_rejects_bad_arguments(tmp_path):
    proc = subprocess.run([sys.executable, "examples/pose_graph_isam2.py", SAMPLE, "--out", str(tmp_path),
                           "--fix-every", "0"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "error" in proc.stderr


@pytest.mark.slow
def test_compare_covariances(tmp_path):
    summary, stdout = run_example(
        "examples/compare_covariances.py", "--runs", "30", "--seq", SAMPLE, "--out", str(tmp_path))
    sim = summary["simulation"]
    assert set(sim) >= {"consistent", "thesis"}
    for w in sim.values():
        # the independently propagated Q_tq maps back onto the Marginals covariance
        assert w["qtq_vs_marginals_rel_diff"] < 1e-5
        assert w["covariance_tq_vs_qtq_rel_diff"] < 1e-5
    assert sim["thesis"]["anees_translation"] > sim["consistent"]["anees_translation"]
    real = summary["real"]
    assert real["num_pairs"] >= 6
    for w in ("consistent", "thesis"):
        assert set(real[w]["sigma_marginals"]) == {"rx", "ry", "rz", "tx", "ty", "tz"}
        assert real[w]["reduced_chi2"] > 0
    assert all(math.isfinite(x) for x in finite_numbers(summary))
    assert (tmp_path / "compare_covariances.json").is_file()
    assert "half-angle" in stdout and "Marginals" in stdout
