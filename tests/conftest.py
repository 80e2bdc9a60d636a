"""Shared fixtures. Real-data tests use the TUM sequences in ``../shared/data`` (or ``$COVO_DATA_DIR``).

They skip with a reason when the data is absent, except under CI (``CI`` set), where missing data is
an error: CI always has it.
"""

from __future__ import annotations

import os
from pathlib import Path

import gtsam
import numpy as np
import pytest

REPO = Path(__file__).resolve().parent.parent
SAMPLE_DIR = REPO / "data" / "rgbd_dataset_freiburg1_rpy_head40"


def _data_root() -> Path:
    return Path(os.environ.get("COVO_DATA_DIR", REPO.parent / "shared" / "data"))


def _sequence(name: str) -> Path:
    path = _data_root() / "tum" / name
    if not (path / "rgb.txt").is_file():
        msg = f"TUM sequence {name} not found under {_data_root()} (set COVO_DATA_DIR)"
        if os.environ.get("CI"):
            pytest.fail(msg + "; CI must have the shared data")
        pytest.skip(msg)
    return path


@pytest.fixture
def shared_data_dir() -> Path:
    root = _data_root()
    if not root.is_dir():
        if os.environ.get("CI"):
            pytest.fail(f"shared data folder {root} not found; CI must have it")
        pytest.skip(f"shared data folder {root} not found (set COVO_DATA_DIR)")
    return root


@pytest.fixture
def fr1_rpy_dir() -> Path:
    return _sequence("rgbd_dataset_freiburg1_rpy_head240")


@pytest.fixture
def fr1_desk_dir() -> Path:
    return _sequence("rgbd_dataset_freiburg1_desk_9frames")


@pytest.fixture
def sample_dir() -> Path:
    return SAMPLE_DIR


@pytest.fixture
def random_trajectory():
    """``make(n, seed, step_sigma, t0)`` -> stamps (n,) s and poses (n, 4, 4): a seeded random walk
    on SE(3) with steps ``Exp(N(0, step_sigma^2))`` (tangent ``[omega, v]``), frames 0.033 s apart."""

    def make(n: int = 20, seed: int = 0, step_sigma=0.3, t0: float = 1305031229.528748):
        rng = np.random.default_rng(seed)
        poses = [gtsam.Pose3.Expmap(rng.normal(size=6)).matrix()]
        for _ in range(n - 1):
            poses.append(poses[-1] @ gtsam.Pose3.Expmap(rng.normal(scale=step_sigma, size=6)).matrix())
        return t0 + 0.033 * np.arange(n), np.array(poses)

    return make


def copy_sample(dst: Path, frames: int) -> Path:
    """A copy of the first ``frames`` frames of the sample sequence in ``dst`` (safe to modify):
    rgb.txt, depth.txt, the images they list and groundtruth.txt."""
    import shutil

    (dst / "rgb").mkdir(parents=True)
    (dst / "depth").mkdir()
    rgb = [ln for ln in (SAMPLE_DIR / "rgb.txt").read_text().splitlines() if not ln.startswith("#")][:frames]
    last = float(rgb[-1].split()[0])
    depth = [ln for ln in (SAMPLE_DIR / "depth.txt").read_text().splitlines()
             if not ln.startswith("#") and float(ln.split()[0]) <= last + 0.02]
    for line in rgb + depth:
        name = line.split()[1]
        shutil.copy(SAMPLE_DIR / name, dst / name)
    (dst / "rgb.txt").write_text("\n".join(rgb) + "\n")
    (dst / "depth.txt").write_text("\n".join(depth) + "\n")
    shutil.copy(SAMPLE_DIR / "groundtruth.txt", dst / "groundtruth.txt")
    return dst


@pytest.fixture
def small_sample(tmp_path):
    """``make(frames=5)`` -> a modifiable copy of the first frames of the sample sequence (a
    'freiburg1' folder name, so the camera preset is found)."""
    count = [0]

    def make(frames: int = 5) -> Path:
        count[0] += 1
        return copy_sample(tmp_path / f"rgbd_dataset_freiburg1_copy{count[0]}", frames)

    return make
