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
