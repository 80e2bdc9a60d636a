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
  ground truth exists; ``version``: the package's version;
* ``groundtruth_at_frames.txt`` -- with ground truth: TUM format, the reference's poses interpolated
  at the frames' colour stamps (in the reference's own world frame), which ``metrics.json``'s
  accuracy and consistency are measured against; evo reproduces them from it;
* ``config.toml`` -- the configuration of the run (:func:`covo_gtsam.config.save_config`):
  ``covo run SEQ --config OUT/config.toml`` repeats it;
* ``plots/`` -- PNG figures (unless disabled).

The sequence returns decoded frames: a :class:`~covo_gtsam.datasets.tum.TumSequence` (image
files, decoded by :meth:`~covo_gtsam.datasets.tum.TumSequence.loader` at the run's camera size and
``config.depth_scale``) or any object with the same attributes and a ``loader(n)`` method returning
a thread-safe function ``i -> (grey, depth in metres)`` (e.g.
:class:`~covo_gtsam.datasets.rosbag.RosbagSequence`, which streams the bag).

The text files are flushed line by line, so an interrupted run leaves valid files for the frames
processed so far. Decoding and feature extraction of the next frames run on worker processes
(threads where a fork is not safe; :mod:`covo_gtsam.prefetch`) while the current frame pair is
solved on the main thread. These workers are the run's parallelism: during the run OpenCV and
numpy's BLAS are kept to one thread each (:func:`kernel_threads`).
"""

from __future__ import annotations

import ctypes
import os
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import numpy as np

from . import __version__
from .camera import Camera
from .config import OdometryConfig, save_config
from .datasets import frame_count
from .datasets.tum import TumSequence
from .errors import ConfigError, CovoError, DatasetError, InputError
from .frontend import FrameData
from .g2o import G2oWriter
from .gyro import Gyroscope
from .interrupt import check as check_interrupt
from .io import FolderLock, RelativePoseWriter, TrajectoryWriter, write_json, write_tum_trajectory
from .odometry import EMPTY_DEPTH, OdometryStep, VisualOdometry
from .prefetch import Prefetcher
from .steps import StepHistory
from .validation import check_int

if TYPE_CHECKING:
    from .evaluation import RunEvaluation


#: Files a run writes into its results folder (besides the figures of ``plots/``).
RUN_FILES = ("trajectory.txt", "relative.txt", "graph.g2o", "metrics.json", "config.toml", "groundtruth_at_frames.txt")


@dataclass
class RunResult:
    """What :func:`run_sequence` produced (also written to disk)."""

    out_dir: Path
    #: the ``metrics.json`` dictionary (``evaluation.to_dict()``)
    metrics: dict
    steps: list[OdometryStep] = field(repr=False)
    #: the statistics and the errors behind them (:class:`~covo_gtsam.evaluation.RunEvaluation`)
    evaluation: RunEvaluation | None = field(default=None, repr=False)
    #: figures written; None when plots were asked for but matplotlib is not installed
    plot_files: list[Path] | None = field(default_factory=list)


#: Files that make a folder a sequence's own: a TUM sequence, a ROS 2 bag.
SEQUENCE_FILES = {"rgb.txt": "a TUM sequence's rgb.txt", "metadata.yaml": "a ROS 2 bag's metadata.yaml"}


def check_not_a_sequence(out_dir: str | os.PathLike) -> None:
    """DatasetError when the folder ``out_dir`` holds a sequence (:data:`SEQUENCE_FILES`): results are
    never written into a dataset."""
    for name, what in SEQUENCE_FILES.items():
        if (Path(out_dir) / name).is_file():
            raise DatasetError(f"{out_dir}: is a sequence's folder (it holds {what}); write the results into "
                               "another one (--out)")


def check_output_dir(out_dir: str | os.PathLike) -> Path:
    """Create ``out_dir`` if needed and check it is writable.

    Raises:
        ConfigError: the path is empty (it would write into the current folder).
        DatasetError: it exists and is not a folder, it is a sequence's folder (:func:`check_not_a_sequence`),
            or it cannot be created or written.
    """
    if not os.fspath(out_dir).strip():
        raise ConfigError("the output folder is an empty path (that would write into the current folder); "
                          "give a folder name")
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise DatasetError(f"{out_dir}: exists and is not a folder; cannot write results into it")
    check_not_a_sequence(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        probe = out_dir / ".covo_write_test"
        probe.write_text("")
        probe.unlink()
    except OSError as exc:
        raise DatasetError(f"{out_dir}: output folder is not writable ({exc.strerror or exc})") from exc
    return out_dir


def prepare_outputs(out: Path, files: Sequence[str], figures: tuple[str, Sequence[str]] | None = None,
                    write_figures: bool = True) -> None:
    """Before the first result is written: check that each of ``files`` (names in ``out``) and, with
    ``write_figures``, the figure folder ``figures = (folder, names)`` can be written, then remove
    earlier results of those names, so that the folder never mixes two runs.

    Raises:
        DatasetError: a results file is a folder, the figure folder is a file or not writable.
    """
    out = Path(out)
    for name in files:
        target = out / name
        if target.is_dir():
            raise DatasetError(f"{target}: is a folder; cannot write {name} there")
    folder = None if figures is None else out / figures[0]
    if folder is not None and write_figures:
        if folder.exists() or folder.is_symlink():
            if not folder.is_dir():
                raise DatasetError(f"{folder}: exists and is not a folder; cannot write the figures into it "
                                   "(remove it, or run with --no-plots)")
            check_output_dir(folder)
        for name in figures[1]:
            if (folder / name).is_dir():
                raise DatasetError(f"{folder / name}: is a folder; cannot write {name} there")
    stale = [out / name for name in files]
    if folder is not None and folder.is_dir():
        stale += [folder / name for name in figures[1] if not (folder / name).is_dir()]
    for path in stale:
        try:
            path.unlink(missing_ok=True)
        except OSError as exc:
            raise DatasetError(f"{path}: cannot remove the result of an earlier run ({exc.strerror or exc})") from exc


@contextmanager
def kernel_threads(n: int = 1):
    """Keep OpenCV and numpy's BLAS library to ``n`` threads each inside the block (restored after),
    and glibc's ``malloc`` from handing freed memory back to the system (:func:`_keep_freed_memory`).

    The run already keeps the cores busy (the frame pair on the main thread,
    :data:`~covo_gtsam.prefetch.PREFETCH` frames prepared on workers). A multi-threaded BLAS (OpenBLAS) would split the small matrix
    products of the RANSAC and the solves over every core, and its threads spin while they wait
    for work: on two cores that cost a quarter of the run's CPU time and a fifth of its wall time,
    for the same results. BLAS is limited through ``threadpoolctl`` when it is installed.
    """
    import cv2

    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - threadpoolctl is a dependency
        threadpool_limits = None
    before = cv2.getNumThreads()
    cv2.setNumThreads(n)
    _keep_freed_memory(True)
    try:
        if threadpool_limits is None:
            yield
        else:
            with threadpool_limits(limits=n, user_api="blas"):
                yield
    finally:
        cv2.setNumThreads(before)
        _keep_freed_memory(False)


#: glibc ``mallopt`` parameters and the values :func:`_keep_freed_memory` sets (bytes): blocks up to
#: 64 MiB come from the heap (not a fresh ``mmap`` each), whose top is kept up to 256 MiB and grown
#: 16 MiB at a time. glibc's defaults (restored after): 128 KiB, 128 KiB, 0.
_MALLOPT = {-3: (64 << 20, 128 << 10), -1: (256 << 20, 128 << 10), -2: (16 << 20, 0)}  # MMAP_THRESHOLD, TRIM_THRESHOLD, TOP_PAD
_malloc_lock = threading.Lock()
_malloc = {"blocks": 0, "kept": False}  # open kernel_threads blocks (nested, or on several threads); set?


def _glibc_mallopt():
    """glibc's ``mallopt`` through ctypes, or None on any other C library or platform."""
    try:
        if not (os.confstr("CS_GNU_LIBC_VERSION") or "").startswith("glibc"):
            return None
        mallopt = ctypes.CDLL(None).mallopt
    except (AttributeError, ValueError, OSError, TypeError):  # no confstr (Windows), not glibc (musl, macOS)
        return None
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return mallopt


def _keep_freed_memory(on: bool) -> bool:
    """Tell glibc's ``malloc`` to keep freed memory for reuse (``on``, the first open block) or
    restore its defaults (the last block closed); returns whether the settings are in effect
    (always False without glibc: nothing happens there).

    The odometry allocates and frees arrays of hundreds of kilobytes to megabytes per frame
    (matching, RANSAC, decoding). By default glibc maps each block above 128 KiB afresh and trims
    the heap as soon as its free top exceeds the threshold, so the same memory is faulted in again
    and again: on the shared 240 frames that was about 100 000 page faults per run, and the RANSAC
    took about twice as long as on memory it had used before. The peak memory is unchanged (freed
    memory is reused, not added to). Process-wide while on; glibc's adaptive threshold stays off
    after the restore."""
    with _malloc_lock:
        _malloc["blocks"] = _malloc["blocks"] + 1 if on else max(_malloc["blocks"] - 1, 0)
        first, last = on and _malloc["blocks"] == 1, not on and _malloc["blocks"] == 0
        mallopt = _glibc_mallopt() if first or (last and _malloc["kept"]) else None
        if mallopt is not None:
            done = [mallopt(param, values[0] if on else values[1]) == 1 for param, values in _MALLOPT.items()]
            if on and not all(done):  # a C library that refuses one: all back to the defaults
                for param, values in _MALLOPT.items():
                    mallopt(param, values[1])
            _malloc["kept"] = on and all(done)
        return _malloc["kept"]

def _frame_loader(seq, n: int, depth_scale: float, camera: Camera):
    """``i -> (grey, depth)`` for the frames of ``seq``: a TUM folder's image files decoded at
    ``camera``'s size (an image of another size is an :class:`InputError` naming its file) with
    ``depth_scale``, else the sequence's own ``loader(n)`` (a bag)."""
    if isinstance(seq, TumSequence):
        return seq.loader(camera, depth_scale)
    return seq.loader(n)


def _load_frame(vo: VisualOdometry, load, i: int, depth_offset: float = 0.0) -> FrameData | CovoError:
    """Decode and prepare one frame; errors are returned (the frame is then reported lost)."""
    try:
        item = load(i)
        if isinstance(item, CovoError):
            return item
        grey, depth = item
        return vo.prepare(grey, depth, depth_offset)
    except CovoError as exc:
        return exc


def run_sequence(
    seq: TumSequence | str | os.PathLike,
    out_dir: str | os.PathLike,
    config: OdometryConfig | None = None,
    camera: Camera | str | None = None,
    max_frames: int | None = None,
    plots: bool = True,
    progress: bool = True,
    keep_error_bases: bool = False,
    bag_out: str | None = None,
    gyro: Gyroscope | None = None,
) -> RunResult:
    """Run :class:`VisualOdometry` over ``seq`` and write the results folder.

    ``seq`` is a decoded sequence (:class:`TumSequence`, :class:`~covo_gtsam.datasets.rosbag.RosbagSequence`)
    or the path of a TUM folder or a ROS bag (read with the default topics), as ``covo run`` takes it.
    ``camera`` (a :class:`Camera` or preset name) overrides ``seq.camera``; ``max_frames`` (an
    integer >= 1, or None for all) limits the frames processed; ``bag_out`` (``"ros1"``,
    ``"ros2"`` or None) also writes the odometry as a ROS bag; ``gyro`` is the camera's gyroscope
    (:class:`~covo_gtsam.gyro.Gyroscope`), whose angular velocities the rolling-shutter
    compensation takes.

    The folder is checked before the first frame (the files of :data:`RUN_FILES` and, with
    ``plots``, the figures of ``plots/`` must be writable) and the results of an earlier run of
    those names are removed, so the folder describes one run (so is an earlier bag, but only one
    covo wrote: a user's file of that name stays); ``config.toml`` (``config``, which
    ``--config`` reads back) is written first. An interrupted run leaves its text files (valid up
    to the last line) and no ``metrics.json``.
    The folder is locked while the run writes into it.

    Raises:
        ConfigError: an invalid ``max_frames``, ``camera`` or ``config``, an empty ``out_dir``, or a
            ``seq`` that is neither a sequence nor a path.
        DatasetError: ``seq``'s path is no readable sequence, the output folder cannot be written, or
            another run is writing into it.
    """
    if max_frames is not None:
        check_int("max_frames", max_frames, 1)
    if isinstance(seq, (str, os.PathLike)):
        from .datasets.rosbag import RosbagSequence, is_bag

        seq = RosbagSequence(seq) if is_bag(seq) else TumSequence(seq)
    elif not hasattr(seq, "camera") or not hasattr(seq, "timestamps"):
        raise ConfigError(f"run_sequence needs a sequence (e.g. TumSequence) or its path, got {type(seq).__name__}")
    config = config or OdometryConfig()
    vo = VisualOdometry(seq.camera if camera is None else camera, config, gyro=gyro)
    out = check_output_dir(out_dir)
    n = frame_count(seq, max_frames)
    with FolderLock(out):
        from .plots import RUN_PLOTS

        from .ros_io import check_bag_stamps, clear_bag_output, remove_earlier_bags

        inputs = (getattr(seq, "path", None),)
        if bag_out is not None:  # checked before anything is removed; the bag writer removes covo's own
            check_bag_stamps(seq.timestamps[:n], bag_out, f"{getattr(seq, 'path', seq.name)}: a frame stamp")
            clear_bag_output(out, bag_out, inputs=inputs, remove=False)
        prepare_outputs(out, RUN_FILES, ("plots", RUN_PLOTS), write_figures=plots)
        remove_earlier_bags(out, bag_out, inputs)  # of the other format, or of any without --bag-out
        save_config(config, out / "config.toml", header=f"covo-gtsam {__version__}: the configuration of this run")
        with kernel_threads(1):
            return _run(vo, StepHistory(keep_error_bases, config.sensor), seq, out, config, n, plots, progress, bag_out)


def write_frame_ground_truth(path: Path, seq, n: int) -> bool:
    """Write the ground truth at the first ``n`` frames' colour stamps (TUM format; the frames
    without one left out), the poses ``metrics.json`` measures against; False (nothing written)
    when the sequence has none."""
    gt = getattr(seq, "groundtruth", None)
    if gt is None:
        return False
    ok = np.asarray(seq.gt_valid[:n], bool)
    if not ok.any():
        return False
    write_tum_trajectory(path, np.asarray(seq.timestamps[:n])[ok], np.asarray(gt[:n])[ok])
    return True


def _naming_the_depth_file(step, seq, i: int):
    """``step``, its reason naming frame ``i``'s depth image file where the frame was lost for an empty
    depth image (a TUM folder's; a bag's images have no file)."""
    paths = getattr(seq, "depth_paths", None)
    if paths is not None and step.reason and EMPTY_DEPTH in step.reason:
        step.reason = step.reason.replace(EMPTY_DEPTH, EMPTY_DEPTH.replace("image", f"image {paths[i]}", 1), 1)
    return step


def _run(vo: VisualOdometry, history: StepHistory, seq: TumSequence, out: Path, config: OdometryConfig,
         n: int, plots: bool, progress: bool, bag_out: str | None) -> RunResult:
    """The frame loop over the first ``n`` frames and the results of :func:`run_sequence`, in a
    checked and locked folder; the steps go to ``history``."""
    start = time.perf_counter()
    load = _frame_loader(seq, n, config.sensor.depth_scale, vo.camera)
    stamps = getattr(seq, "depth_timestamps", None)

    def prepare(i: int) -> FrameData | CovoError:
        offset = 0.0 if stamps is None else float(stamps[i] - seq.timestamps[i])
        return _load_frame(vo, load, i, offset)

    # the workers start before the progress bar's thread and before any output file is open (a
    # forked worker inherits neither); a streamed bag is read on threads of this process
    bar = None
    lost_count = 0
    index_of: dict[float, int] = {}
    with Prefetcher(prepare, n, mode="auto" if isinstance(seq, TumSequence) else "thread") as frames:
        bag = None
        if bag_out is not None:
            from .ros_io import OdometryBagWriter

            exact = getattr(seq, "timestamps_ns", None)  # a bag's own stamps, kept exactly in its messages
            bag = OdometryBagWriter(out, bag_out, camera_frame=getattr(seq, "camera_frame", "camera"),
                                    stamps_ns=None if exact is None else dict(zip(seq.timestamps.tolist(),
                                                                                 exact.tolist())))
        if progress:
            from tqdm import tqdm

            class Bar(tqdm):
                monitor_interval = 0  # no monitor thread: a later run in this process can fork its workers too

            bar = Bar(total=n, desc=seq.name, unit="frame", dynamic_ncols=True)
        with TrajectoryWriter(out / "trajectory.txt") as traj_w, RelativePoseWriter(out / "relative.txt") as rel_w, \
                G2oWriter(out / "graph.g2o") as g2o_w:

            def write(i: int, step) -> None:
                """A posed step into the outputs, once settled (the next frame may revise its pose and covariance)."""
                t = step.timestamp
                traj_w.write(t, step.pose.matrix())
                g2o_w.vertex(i, step.pose.matrix())
                index_of[t] = i
                if step.has_relative_pose:
                    rel_w.write(step.ref_timestamp, t, step.relative.matrix(), step.covariance, step.quality)
                    g2o_w.edge(index_of[step.ref_timestamp], i, step.relative.matrix(), step.covariance)
                if bag is not None:
                    bag.write(step)

            pending = None  # (frame index, step): the last posed step, written when the next frame settles it
            try:
                for i in range(n):
                    check_interrupt()  # a Ctrl-C that a finalizer swallowed
                    frame = frames.get(i)
                    t = float(seq.timestamps[i])
                    if isinstance(frame, CovoError):
                        step = vo.mark_lost(t, str(frame))
                    else:
                        step = vo.register_frame(frame, timestamp=t)
                    history.add(_naming_the_depth_file(step, seq, i))
                    if pending is not None:
                        settled, pending = pending, None
                        write(*settled)
                    if step.has_pose:
                        pending = (i, step)
                    else:
                        lost_count += 1
                    if bar is not None:
                        bar.set_postfix(lost=lost_count, pairs=step.num_pairs, refresh=False)
                        bar.update(1)
            finally:
                try:
                    if pending is not None:  # the last posed step (also of an interrupted run), as it stands
                        write(*pending)
                finally:
                    if bag is not None:
                        bag.close()
    if bar is not None:
        bar.close()
    elapsed = time.perf_counter() - start

    from .evaluation import evaluate_run, part_shares

    evaluation = evaluate_run(history.steps, seq, elapsed)
    evaluation.self_calibration = vo.self_calibration()
    names, index, shares = part_shares(history.variance_parts)
    evaluation.part_shares = names, np.array([history[i].timestamp for i in index]), shares
    cam = vo.camera
    evaluation.camera = {"name": cam.name, "fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy,
                         "distortion": list(cam.dist), "width": cam.width, "height": cam.height,
                         "depth_scale": config.sensor.depth_scale}
    evaluation.version = __version__
    evaluation.gyro = vo.gyro_summary()
    metrics = evaluation.to_dict()
    write_json(out / "metrics.json", metrics)
    write_frame_ground_truth(out / "groundtruth_at_frames.txt", seq, n)
    result = RunResult(out, metrics, history.steps, evaluation)
    if plots:
        from .plots import plot_run

        try:
            result.plot_files = plot_run(history.steps, evaluation, out / "plots")
        except OSError as exc:
            raise DatasetError(f"{out / 'plots'}: cannot write the figures ({exc.strerror or exc}); "
                               "the other results are complete") from exc
    return result


def calibrate_sequence(
    seq: TumSequence,
    out_dir: str | os.PathLike,
    config: OdometryConfig | None = None,
    max_frames: int | None = None,
    progress: bool = True,
    terms=None,
    fit_correlation_factor: bool = False,
    reference_sd: np.ndarray | None = None,
    fit_span: bool = True,
    gyro: Gyroscope | None = None,
):
    """Fit the sensor terms (:func:`covo_gtsam.calibration.fit_sensor_terms`) on a sequence with
    ground truth.

    Runs the odometry with the per-point model alone (``config`` with ``correlation_factor = 1``
    and every other term zero, frame to frame, the poses moved by the rolling-shutter look-ahead)
    into ``out_dir`` and fits the consecutive pairs
    (one frame interval) that have ground truth, with the frame-level terms named in ``terms``
    (:data:`~covo_gtsam.calibration.DEFAULT_TERMS` if None, :data:`~covo_gtsam.calibration.GYRO_TERMS`
    with ``gyro``, the rolling-shutter term then held); ``correlation_factor`` stays 1 (the
    per-point model as it is) unless ``fit_correlation_factor``. Pairs the integrity check flagged are
    left out (their data is suspect), and so are the pairs of the first frames, which the frame
    clock has not placed yet; the prior terms (:data:`~covo_gtsam.calibration.PRIOR_TERMS`) are
    held at ``config``'s values. With ``reference_sd`` (rad, per axis: the ground truth's own rotation
    jitter per sample, :func:`~covo_gtsam.reference_noise.reference_jitter`) that jitter is held as a
    known term too (:func:`~covo_gtsam.reference_noise.pair_jitter_covariances`), so the fitted terms
    describe the camera without its reference. With ``fit_span``, the ``span`` term (zero for
    consecutive pairs) is then fitted on the pairs of runs over every 2nd and 3rd frame
    (:func:`strided_runs`) with the other terms held (:func:`~covo_gtsam.calibration.fit_span_factor`);
    with fewer than :data:`~covo_gtsam.calibration.MIN_SPAN_PAIRS` such pairs (:func:`calibration_pairs`
    with ``longer``, and a recent translation to scale the term with) it keeps ``config``'s value (``SensorTerms.span_pairs`` says how many it
    had). ``gyro`` (:class:`~covo_gtsam.gyro.Gyroscope`) is given to every run, as ``covo run --gyro``
    does. Returns ``(SensorTerms, RunResult)``.

    Raises:
        DatasetError: the sequence has no ground truth.
        InputError: fewer than 10 usable pairs.
    """
    from .calibration import (
        DEFAULT_TERMS,
        ERROR_TERMS,
        GYRO_TERMS,
        MIN_SPAN_PAIRS,
        PRIOR_TERMS,
        fit_sensor_terms,
        fit_span_factor,
        span_fit_pairs,
    )
    from .evaluation import ground_truth_lookup, reference_covariances, relative_ground_truth
    from .metrics import relative_pose_tangent_errors

    if seq.groundtruth is None:
        gt = Path(seq.path) / "groundtruth.txt"
        raise DatasetError(f"{gt}: has no usable sample; calibration needs ground truth" if gt.is_file()
                           else f"{seq.path}: calibration needs ground truth (groundtruth.txt)")
    config = config or OdometryConfig()
    span_prior = config.sensor.span_factor
    held = PRIOR_TERMS + (("rolling_shutter",) if gyro is not None else ())
    priors = {k: getattr(config.sensor, ERROR_TERMS[k]) for k in held}
    if terms is None:
        terms = DEFAULT_TERMS if gyro is None else GYRO_TERMS
    no_terms = {name: 0.0 for name in ERROR_TERMS.values()}
    # the poses moved by the rolling-shutter look-ahead: its factor is that of moved poses (a pose never
    # moved takes the term's model once more, VisualOdometry._shutter_unmoved)
    config = config.replace(sensor={"correlation_factor": 1.0, "frame_sigma_rot_deg": 0.0, "frame_sigma_trans_m": 0.0,
                                    "rolling_shutter_look_ahead": True, **no_terms}, tracking={"keyframes": False})
    result = run_sequence(seq, out_dir, config=config, max_frames=max_frames, plots=False, progress=progress,
                          keep_error_bases=True, gyro=gyro)
    lookup = ground_truth_lookup(seq)
    consecutive = calibration_pairs(result.steps, lookup, config)
    T_est, T_true, covs = relative_ground_truth(consecutive, lookup)
    if len(T_est) < 10:
        with_truth = calibration_pairs(result.steps, lookup, config, require_clock=False)
        tracked = calibration_pairs(result.steps, None, config, require_clock=False)
        clock = (" and both frames placed by the frame clock, which places the stamps from the 20th frame on"
                 if config.sensor.frame_clock else "")
        raise InputError(f"{seq.path}: the fit needs at least 10 consecutive tracked frame pairs with usable ground "
                         f"truth at both frames{clock}; got {len(T_est)} ({len(tracked)} consecutive pairs tracked, "
                         f"{len(with_truth)} of them with ground truth)")
    def known(steps) -> np.ndarray | None:
        """The terms the fits hold (N, 6, 6): the priors', and the reference's jitter if given."""
        fixed = prior_covariances(steps, priors)
        if reference_sd is not None:
            jitter = reference_covariances(seq.gt_samples, reference_sd)([s.ref_timestamp for s in steps],
                                                                          [s.timestamp for s in steps])
            fixed = jitter if fixed is None else fixed + jitter
        return fixed

    fit = fit_sensor_terms(relative_pose_tangent_errors(T_est, T_true), covs, fit_correlation_factor,
                           bases=stacked_bases(consecutive, terms),
                           fixed=known(consecutive))
    if not fit_span:
        return fit, result
    longer = [s for run in strided_runs(seq, config, max_frames, progress=progress, gyro=gyro)
              for s in calibration_pairs(run, lookup, config, longer=True)]
    span, used = span_prior, 0
    if longer:
        T_est, T_true, point_covs = relative_ground_truth(longer, lookup)
        bases = stacked_bases(longer, tuple(fit.sigmas) + ("span",))
        k = np.array([config.frame_intervals(s.timestamp - s.ref_timestamp) for s in longer])
        held = fit.covariances(point_covs, {n: B for n, B in bases.items() if n != "span"}, k)
        fixed = known(longer)
        held = held if fixed is None else held + fixed
        used = int(span_fit_pairs(bases["span"]).sum())
        if used >= MIN_SPAN_PAIRS:  # else too few such pairs: the configured value stays
            span = fit_span_factor(relative_pose_tangent_errors(T_est, T_true), held, bases["span"])
    return replace(fit, sigmas={**fit.sigmas, "span": span}, span_pairs=used), result


#: frame strides whose pairs (two and three intervals long) fit the span term
SPAN_STRIDES = (2, 3)


def strided_runs(seq, config: OdometryConfig, max_frames: int | None = None, strides: Sequence[int] = SPAN_STRIDES,
                 progress: bool = False, gyro: Gyroscope | None = None) -> list[list[OdometryStep]]:
    """The steps of each run of ``config`` over every ``s``-th frame of ``seq`` for each ``s`` in
    ``strides``, each phase a run of its own (pairs ``s`` frame intervals long, as from a camera that
    drops frames), all from one pass over the first ``max_frames`` frames; error bases kept."""
    n = frame_count(seq, max_frames)
    runs = {(s, p): VisualOdometry(seq.camera, config, gyro=gyro) for s in strides for p in range(s)}
    histories = {key: StepHistory(keep_error_bases=True) for key in runs}  # slim: no estimator results
    any_vo = next(iter(runs.values()))
    load = _frame_loader(seq, n, config.sensor.depth_scale, any_vo.camera)
    stamps = getattr(seq, "depth_timestamps", None)
    frames = range(n)
    if progress:
        from tqdm import tqdm

        frames = tqdm(frames, desc=f"{seq.name}, every {' and '.join(map(str, strides))}", unit="frame",
                      dynamic_ncols=True)
    for i in frames:
        t = float(seq.timestamps[i])
        offset = 0.0 if stamps is None else float(stamps[i] - t)
        frame = _load_frame(any_vo, load, i, offset)  # the runs share the configuration: one decoding
        for s in strides:
            vo = runs[(s, i % s)]
            histories[(s, i % s)].add(vo.mark_lost(t, str(frame)) if isinstance(frame, CovoError)
                                      else vo.register_frame(frame, timestamp=t))
    return [h.steps for h in histories.values()]


def calibration_pairs(steps, lookup: dict | None, config: OdometryConfig, require_clock: bool = True,
                      longer: bool = False) -> list[OdometryStep]:
    """The steps a fit of the sensor terms uses: tracked consecutive pairs (one frame interval; with
    ``longer``, pairs over more than one, which the span term is fitted on) with a velocity and
    ground truth at both frames (``lookup``: stamp -> pose; None: ground truth not required), not
    flagged by the integrity check, with ``require_clock`` both frames placed by the frame clock
    (when it is on)."""
    clocked = {s.timestamp for s in steps if s.clock_samples or not config.sensor.frame_clock or not require_clock}
    return [s for s in steps if s.has_relative_pose and s.velocity is not None and not s.flagged
            and s.timestamp in clocked and s.ref_timestamp in clocked
            and (config.frame_intervals(s.timestamp - s.ref_timestamp) > 1) == longer
            and (lookup is None or (s.ref_timestamp in lookup and s.timestamp in lookup))]


def prior_covariances(steps, priors: dict[str, float]) -> np.ndarray | None:
    """``sum_j sigma_j^2 B_j`` (N, 6, 6) of the prior terms ``priors`` (name -> sigma) over ``steps``
    (None without priors): what a fit holds fixed."""
    if not priors:
        return None
    bases = stacked_bases(steps, priors)
    return sum(sigma**2 * bases[name] for name, sigma in priors.items())


def stacked_bases(steps, terms=None) -> dict[str, np.ndarray]:
    """The frame-level error bases (N, 6, 6) of ``steps`` for the terms named in ``terms`` (all of
    :data:`~covo_gtsam.calibration.ERROR_TERMS` if None; a term a step lacks counts as zero)."""
    from .calibration import ERROR_TERMS

    names = list(ERROR_TERMS) if terms is None else list(terms)
    return {k: np.array([s.error_bases.get(k, np.zeros((6, 6))) for s in steps]).reshape(-1, 6, 6) for k in names}
