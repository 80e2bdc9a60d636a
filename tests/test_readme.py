"""The README's Python examples run as written."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import gtsam
import numpy as np

README = Path(__file__).resolve().parent.parent / "README.md"


def python_blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)


def test_readme_has_the_two_api_examples():
    blocks = python_blocks()
    assert len(blocks) == 2
    assert "estimate_relative_pose" in blocks[0] and "register_frame" in blocks[1]


def test_readme_estimator_example_runs():
    ns: dict = {}
    exec(compile(python_blocks()[0], "README.md", "exec"), ns)
    result, graph = ns["result"], ns["graph"]
    assert isinstance(result.pose, gtsam.Pose3) and result.covariance.shape == (6, 6)
    assert result.covariance_tq.shape == (6, 6) and graph.size() == 1
    np.testing.assert_allclose(np.linalg.inv(graph.at(0).noiseModel().information()), result.covariance, rtol=1e-9)


def test_readme_odometry_example_runs(sample_dir, capsys):
    from covo_gtsam.datasets.tum import TumSequence

    seq = TumSequence(sample_dir)
    frames = [(cv2.imread(seq.rgb_paths[i]), cv2.imread(seq.depth_paths[i], cv2.IMREAD_UNCHANGED), seq.timestamps[i])
              for i in range(3)]
    ns: dict = {"frames": frames}
    exec(compile(python_blocks()[1], "README.md", "exec"), ns)
    history = ns["history"]
    assert [s.status for s in history] == ["first", "tracked", "tracked"] and ns["poses"].shape == (3, 4, 4)
    assert "lost" not in capsys.readouterr().out
    graph, initial = ns["graph"], ns["initial"]
    assert graph.size() == 2 and initial.size() == 3  # a factor per relative pose, an initial pose per frame
    for i, step in enumerate(list(history)[1:]):
        factor = graph.at(i)
        assert factor.measured().equals(step.relative, 1e-12)
        np.testing.assert_allclose(np.linalg.inv(factor.noiseModel().information()), step.covariance, rtol=1e-8)


def test_public_api_is_importable_from_the_package():
    import covo_gtsam
    from covo_gtsam import Camera, VisualOdometry, estimate_relative_pose
    from covo_gtsam.estimator import estimate_relative_pose as direct

    assert estimate_relative_pose is direct
    assert VisualOdometry(Camera.preset("fr1")).camera.fx == 517.3
    for name in covo_gtsam.__all__:
        assert getattr(covo_gtsam, name) is not None
    import pytest

    with pytest.raises(AttributeError):
        covo_gtsam.no_such_name  # noqa: B018
    assert set(covo_gtsam.__all__) <= set(dir(covo_gtsam))


def test_public_api_covers_the_run_and_its_evaluation():
    import covo_gtsam
    from covo_gtsam import RunEvaluation, RunResult, evaluate_run, run_sequence
    from covo_gtsam.evaluation import RunEvaluation as direct

    assert RunEvaluation is direct and {"ate", "rpe", "relative_pose_nees"} <= set(covo_gtsam.__all__)
    assert evaluate_run.__module__ == "covo_gtsam.evaluation" and run_sequence.__module__ == "covo_gtsam.pipeline"
    assert RunResult.__dataclass_fields__["evaluation"]


def test_importing_the_package_loads_no_heavy_module():
    import subprocess
    import sys

    code = ("import sys, covo_gtsam; heavy = ('numpy', 'gtsam', 'cv2', 'matplotlib', 'scipy'); "
            "print(sorted(m for m in heavy if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_quick_start_test_command_is_the_one_ci_runs():
    """.ci/run installs and runs the tests exactly as the README's quick start says: the whole
    suite, slow tests included."""
    quick_start = re.search(r"## Quick start\n.*?```bash\n(.*?)```", README.read_text(), flags=re.S).group(1)
    command = quick_start.strip().splitlines()[-1]  # the second command
    ci = (README.parent / ".ci" / "run").read_text().splitlines()
    install, pytest_line = command.split(" && ")[-2:]
    assert install in ci and pytest_line in ci
    assert "--run-slow" in pytest_line.split()


def test_readme_command_synopsis_lists_every_option():
    """The README's command-line synopsis names every option of every command's parser."""
    import argparse

    from covo_gtsam.cli import build_parser

    text = README.read_text()
    block = text[text.index("## Command line"):]
    block = block[block.index("```text\n") + 8:block.index("```", block.index("```text\n") + 8)]
    synopsis = {m.group(1): m.group(2) for m in re.finditer(r"^covo ([a-z-]+)(.*?)(?=^covo |\Z)", block, re.S | re.M)}
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    assert set(synopsis) == set(sub.choices)
    for name, parser in sub.choices.items():
        options = {o for a in parser._actions for o in a.option_strings if o.startswith("--") and o != "--help"}
        missing = sorted(o for o in options if not re.search(rf"{re.escape(o)}(?![\w-])", synopsis[name]))
        assert not missing, f"covo {name}: {missing}"
