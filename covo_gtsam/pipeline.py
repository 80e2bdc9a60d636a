"""Run the odometry over a recorded sequence and write a results folder.

Outputs in ``out_dir``:

* ``trajectory.txt`` -- TUM format ``t tx ty tz qx qy qz qw``, T_world,cam with world = first
  tracked camera frame (evo reads it as is);
* ``relative.txt`` -- one line per estimated frame pair, ``t_ref t_cur tx ty tz qx qy qz qw``
  and the 36 covariance values row-major (T_ref,cur; GTSAM tangent ``[rx ry rz tx ty tz]``,
  right perturbation);
* ``graph.g2o`` -- the pose graph in g2o's format (:mod:`covo_gtsam.g2o`): a vertex per tracked
  frame, an edge with its information matrix per frame pair;
* ``odometry.bag`` / ``odometry/`` -- with ``bag_out="ros1"`` / ``"ros2"``, the odometry as ROS
  messages (:mod:`covo_gtsam.ros_io`);
* ``metrics.json`` -- frames, lost frames, frames/s, and accuracy/consistency metrics when
  ground truth exists;
* ``plots/`` -- PNG figures (unless disabled).

The sequence is a :class:`~covo_gtsam.datasets.tum.TumSequence` (image files, decoded by path) or
any object with the same attributes and a ``loader(n)`` method returning a thread-safe function
``i -> (grey, depth in metres)`` (e.g. :class:`~covo_gtsam.datasets.rosbag.RosbagSequence`, which
streams the bag).

The text files are flushed line by line, so an interrupted run leaves valid files for the frames
processed so far. Decoding and feature extraction of the next frame run on a worker thread
(OpenCV releases the GIL) while the current frame pair is solved on the main thread (GTSAM's
Python callbacks stay there).
"""

from __future__ import annotations

import os
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .camera import Camera
from .datasets.tum import TumSequence
from .errors import CovoError, DatasetError
from .frontend import FrameData, load_depth, load_grey
from .g2o import G2oWriter
from .io import RelativePoseWriter, TrajectoryWriter, write_json
from .odometry import OdometryConfig, OdometryStep, VisualOdometry
from .validation import check_int


#: Frames decoded and prepared ahead on worker threads.
PREFETCH = 2


@dataclass
class RunResult:
    """What :func:`run_sequence` produced (also written to disk)."""

    out_dir: Path
    metrics: dict
    steps: list[OdometryStep] = field(repr=False)
    gt_poses: np.ndarray | None = field(default=None, repr=False)
    #: figures written; None when plots were asked for but matplotlib is not installed
    plot_files: list[Path] | None = field(default_factory=list)


def check_output_dir(out_dir: Path) -> Path:
    """Create ``out_dir`` if needed and check it is writable; DatasetError otherwise."""
    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        probe = out_dir / ".covo_write_test"
        probe.write_text("")
        probe.unlink()
    except OSError as exc:
        raise DatasetError(f"{out_dir}: output folder is not writable ({exc.strerror or exc})") from exc
    return out_dir


def _frame_loader(seq, n: int, depth_scale: float):
    """``i -> (grey, depth)`` for the frames of ``seq``: the sequence's own ``loader`` if it has one
    (a bag), else the image files of a TUM folder."""
    if hasattr(seq, "loader"):
        return seq.loader(n)

    def load(i: int):
        return load_grey(seq.rgb_paths[i]), load_depth(seq.depth_paths[i], depth_scale)

    return load


def _load_frame(vo: VisualOdometry, load, i: int) -> FrameData | CovoError:
    """Decode and prepare one frame; errors are returned (the frame is then reported lost)."""
    try:
        item = load(i)
        if isinstance(item, CovoError):
            return item
        grey, depth = item
        return vo.prepare(grey, depth)
    except CovoError as exc:
        return exc


def run_sequence(
    seq: TumSequence,
    out_dir: str | os.PathLike,
    config: OdometryConfig | None = None,
    camera: Camera | str | None = None,
    max_frames: int | None = None,
    plots: bool = True,
    progress: bool = True,
    bag_out: str | None = None,
) -> RunResult:
    """Run :class:`VisualOdometry` over ``seq`` and write the results folder.

    ``camera`` (a :class:`Camera` or preset name) overrides ``seq.camera``; ``max_frames`` (an
    integer >= 1, or None for all) limits the frames processed; ``bag_out`` (``"ros1"``,
    ``"ros2"`` or None) also writes the odometry as a ROS bag.

    Raises:
        ConfigError: an invalid ``max_frames``, ``camera`` or ``config``.
    """
    if max_frames is not None:
        check_int("max_frames", max_frames, 1)
    config = config or OdometryConfig()
    vo = VisualOdometry(seq.camera if camera is None else camera, config)
    out = check_output_dir(Path(out_dir))
    bag = None
    if bag_out is not None:
        from .ros_io import OdometryBagWriter

        bag = OdometryBagWriter(out, bag_out, camera_frame=getattr(seq, "camera_frame", "camera"))
    n = len(seq) if max_frames is None else min(len(seq), max_frames)
    start = time.perf_counter()

    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=n, desc=seq.name, unit="frame", dynamic_ncols=True)
    lost_count = 0
    index_of: dict[float, int] = {}
    with TrajectoryWriter(out / "trajectory.txt") as traj_w, RelativePoseWriter(out / "relative.txt") as rel_w, \
            G2oWriter(out / "graph.g2o") as g2o_w, ThreadPoolExecutor(max_workers=PREFETCH) as pool:
        load = _frame_loader(seq, n, config.depth_scale)

        def submit(i: int):
            return pool.submit(_load_frame, vo, load, i)

        pending = deque(submit(i) for i in range(min(PREFETCH, n)))
        try:
            for i in range(n):
                frame = pending.popleft().result()
                if i + PREFETCH < n:
                    pending.append(submit(i + PREFETCH))
                t = float(seq.timestamps[i])
                if isinstance(frame, CovoError):
                    step = vo.mark_lost(t, str(frame))
                else:
                    step = vo.register_frame(frame, timestamp=t)
                if step.tracked:
                    traj_w.write(t, step.pose.matrix())
                    g2o_w.vertex(i, step.pose.matrix())
                    index_of[t] = i
                    if step.status == "tracked":
                        rel_w.write(step.ref_timestamp, t, step.relative.matrix(), step.covariance)
                        g2o_w.edge(index_of[step.ref_timestamp], i, step.relative.matrix(), step.covariance)
                    if bag is not None:
                        bag.write(step)
                else:
                    lost_count += 1
                if bar is not None:
                    bar.set_postfix(lost=lost_count, pairs=step.num_pairs, refresh=False)
                    bar.update(1)
        finally:
            if bag is not None:
                bag.close()
    if bar is not None:
        bar.close()
    elapsed = time.perf_counter() - start

    from .evaluation import evaluate_run

    metrics = evaluate_run(vo.steps, seq, elapsed)
    write_json(out / "metrics.json", metrics)
    result = RunResult(out, metrics, vo.steps)
    if plots:
        from .plots import plot_run

        result.plot_files = plot_run(vo.steps, seq, metrics, out / "plots")
    return result


def calibrate_sequence(
    seq: TumSequence,
    out_dir: str | os.PathLike,
    config: OdometryConfig | None = None,
    max_frames: int | None = None,
    progress: bool = True,
):
    """Fit the sensor terms (:func:`covo_gtsam.calibration.fit_sensor_terms`) on a sequence with
    ground truth.

    Runs the odometry with the per-point model alone (``config`` with ``correlation_factor = 1``
    and zero frame sigmas, frame to frame) into ``out_dir`` and fits the consecutive pairs
    (one frame interval) that have ground truth. Returns ``(SensorTerms, RunResult)``.

    Raises:
        DatasetError: the sequence has no ground truth.
        InputError: fewer than 10 usable pairs.
    """
    import dataclasses

    from .calibration import fit_sensor_terms
    from .evaluation import ground_truth_lookup, relative_ground_truth
    from .metrics import relative_pose_tangent_errors

    if seq.groundtruth is None:
        raise DatasetError(f"{seq.path}: calibration needs ground truth (groundtruth.txt)")
    config = dataclasses.replace(config or OdometryConfig(), correlation_factor=1.0, frame_sigma_rot_deg=0.0,
                                 frame_sigma_trans_m=0.0, keyframes=False)
    result = run_sequence(seq, out_dir, config=config, max_frames=max_frames, plots=False, progress=progress)
    lookup = ground_truth_lookup(seq)
    consecutive = [s for s in result.steps if s.status == "tracked"
                   and config.frame_intervals(s.timestamp - s.ref_timestamp) == 1]
    T_est, T_true, covs = relative_ground_truth(consecutive, lookup)
    return fit_sensor_terms(relative_pose_tangent_errors(T_est, T_true), covs), result
