"""Shared fixtures and the test selection.

Tests marked ``slow`` (more than about 2 s each) are skipped unless ``--run-slow`` is given; CI
(``.ci/run``) gives it, so a plain ``python -m pytest -q`` runs the fast subset.

Real-data tests use the TUM sequences in ``../shared/data`` (or ``$COVO_DATA_DIR``) through the
fixtures ``shared_data_dir``, ``fr1_rpy_dir`` and ``fr1_desk_dir``, and carry the ``realdata`` marker
(collection fails when one of the two is there without the other). They skip with a reason when the
data is absent, except under CI (``CI`` set), where missing data is an error: CI always has it.
"""

from __future__ import annotations

import os
from pathlib import Path

# as `covo run` does: OpenBLAS without threads of its own, so that runs fork their frame workers here too
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import gtsam  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
SAMPLE_DIR = REPO / "data" / "rgbd_dataset_freiburg1_rpy_head40"


#: Fixtures that give a folder of ``../shared/data``: a test using one needs the ``realdata`` marker.
REAL_DATA_FIXTURES = frozenset({"shared_data_dir", "fr1_rpy_dir", "fr1_desk_dir"})


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--run-slow", action="store_true", default=False,
                     help="also run the tests marked slow (more than about 2 s each); CI does")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    unmarked, stray = [], []
    for item in items:
        # a test module's own fixture of the same name overrides ours (test_frontend's falls back
        # to the sample in data/), so it does not count
        module = getattr(item, "module", None)
        requested = REAL_DATA_FIXTURES & set(getattr(item, "fixturenames", ()))
        uses_data = any(not hasattr(module, name) for name in requested)
        marked = item.get_closest_marker("realdata") is not None
        if uses_data and not marked:
            unmarked.append(item.nodeid)
        elif marked and not uses_data:
            stray.append(item.nodeid)
    if unmarked or stray:
        problems = ([f"not marked: {', '.join(unmarked)}"] if unmarked else []) + (
            [f"marked without a real-data fixture: {', '.join(stray)}"] if stray else [])
        names = ", ".join(sorted(REAL_DATA_FIXTURES))
        raise pytest.UsageError(f"the realdata marker and the real-data fixtures ({names}) go together; "
                                + "; ".join(problems))
    if config.getoption("--run-slow"):
        return
    skip_slow = pytest.mark.skip(reason="slow (more than about 2 s): run with --run-slow, as CI does")
    for item in items:
        if item.get_closest_marker("slow") is not None:
            item.add_marker(skip_slow)


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


#: Frames in the ``small_seq`` copy of the sample sequence.
SMALL_SEQ_FRAMES = 8


@pytest.fixture
def small_seq(tmp_path) -> Path:
    """A copy of the first SMALL_SEQ_FRAMES frames of the sample sequence, safe to corrupt."""
    return copy_sample(tmp_path / "rgbd_dataset_freiburg1_small", SMALL_SEQ_FRAMES)


def frame_files(seq: Path, i: int) -> tuple[Path, Path, float]:
    """Colour image, depth image and timestamp of frame ``i`` of the TUM folder ``seq``."""
    from covo_gtsam.datasets.tum import TumSequence

    s = TumSequence(seq)
    return Path(s.rgb_paths[i]), Path(s.depth_paths[i]), float(s.timestamps[i])


def corrupt_frame(seq: Path, i: int, kind: str) -> float:
    """Damage frame ``i`` of ``seq`` in place (``kind``: truncated, random, small, depth8, zero_depth,
    uniform, jump); returns its timestamp."""
    import cv2

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
    else:
        raise ValueError(f"unknown kind of damage {kind!r}")
    return t
