"""Time and CPU per frame, whole-process frames/s and peak memory of `covo run` on a TUM sequence.

    python benchmarks/bench_pipeline.py SEQ_DIR [--max-frames N]

1. Stages timed one after another on the main thread (no overlap), calling the same functions the
   pipeline calls, OpenCV and BLAS single-threaded as in `covo run` (wall ms per frame; the
   matching is guided by the previous pair's motion, as the odometry's prediction guides it).
2. ``register_frame`` alone on frames prepared beforehand, one thread (wall and CPU ms per frame).
3. CPU of a whole run in this process (:func:`covo_gtsam.pipeline.run_sequence`, progress bar and
   output files included, no figures), with the frames prepared on worker processes (as `covo
   run`; their CPU counted from ``RUSAGE_CHILDREN``), on worker threads (``time.thread_time``
   inside each frame's preparation), and on the main thread when needed (same work, no overlap,
   so it varies less with what else the machine runs): CPU per frame of the frame pairs and
   output, of the frames' preparation, and the rest (hand-offs, start of the workers).
4. Where that CPU goes: the same run under ``cProfile`` with a CPU clock per thread
   (``time.thread_time``), main thread and workers merged, summed by stage (each stage the
   inclusive time of the functions named in :data:`STAGES`; "other" is the rest: Python glue,
   thread hand-offs, step bookkeeping), frames prepared on worker threads. Profiling slows Python
   code down, so the shares matter, not the absolute figures.
5. Whole process: `covo run --no-plots --quiet` as a child process (start-up, decoding and the
   worker processes included): wall frames/s, CPU (user + sys) per frame, and peak RSS for 60
   frames and for the whole sequence to show that memory stays flat.
6. "Decoded in advance": the odometry as `covo run` runs it (features of the next frames prepared
   on worker processes) on images decoded beforehand.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as `covo run`: no BLAS threads, so runs fork their workers

import contextlib
import cProfile
import io
import pstats
import resource
import subprocess
import sys
import tempfile
import threading
import time
from collections import defaultdict

import gtsam
import numpy as np

from covo_gtsam import pipeline
from covo_gtsam.datasets.images import load_depth, load_grey
from covo_gtsam.datasets.tum import TumSequence
from covo_gtsam.estimator import estimate_relative_pose
from covo_gtsam.frontend import (
    GUIDED_CELL_PX,
    associate_frames,
    detect,
    guided_cross_check,
    keep_best,
    make_orb,
    match,
    predicted_pixels,
    prepare_frame,
    ransac_rigid3d,
)
from covo_gtsam.io import format_relative_line, format_tum_line
from covo_gtsam.odometry import OdometryConfig, VisualOdometry
from covo_gtsam.pipeline import kernel_threads, run_sequence
from covo_gtsam.prefetch import Prefetcher
from covo_gtsam.rolling_shutter import compensate_points, frame_twists

from _common import sequence_from_command_line

#: Profile stages: (module file, function) pairs whose inclusive CPU time makes up the stage.
#: None of them calls another of a different stage, except ``prepare_frame``, which calls
#: ``detect`` (subtracted, see :func:`stage_profile`).
STAGES = {
    "decode colour + depth (PNG)": [("images.py", "load_grey"), ("images.py", "load_depth")],
    "ORB": [("matching.py", "detect")],
    "3D points + covariances": [("points.py", "prepare_frame")],
    "matching (guided; all pairs without a prediction)": [("matching.py", "match"),
                                                          ("matching.py", "guided_cross_check"),
                                                          ("pairs.py", "predicted_pixels")],
    "RANSAC": [("ransac.py", "ransac_rigid3d")],
    "solve + marginals (1 per pair)": [("odometry.py", "_solve")],
    "time compensation of points, offsets' lookup variance": [("odometry.py", "_to_frame_time"),
                                                              ("rolling_shutter.py", "frame_twists"),
                                                              ("odometry.py", "_with_motion_noise")],
    "covariance terms + composition": [("odometry.py", "_error_bases"), ("odometry.py", "sensor_covariance"),
                                       ("covariance.py", "compose_covariance"), ("clock.py", "restamp")],
    "integrity check": [("integrity.py", "depth_free_check"), ("integrity.py", "normalise")],
    "frame clock + motion prediction": [("clock.py", "offset"), ("odometry.py", "predict")],
    "output files": [("io.py", "write"), ("g2o.py", "vertex"), ("g2o.py", "edge")],
    "progress bar": [("std.py", "update"), ("std.py", "set_postfix")],
    "metrics (end of run)": [("evaluation.py", "evaluate_run")],
}


def compensated_solve(pairs, dt: float, height: int, readout: float):
    """The odometry's solve: points moved to their image's timestamp with the twist of the RANSAC's
    pose, then solved once (with its marginal covariance)."""
    initial = gtsam.Pose3(pairs.T_init)
    twist_ref, twist_cur = frame_twists(initial, dt)
    X_ref = compensate_points(pairs.X_ref, pairs.uv_ref[:, 1], twist_ref, height, readout)
    X_cur = compensate_points(pairs.X_cur, pairs.uv_cur[:, 1], twist_cur, height, readout)
    return estimate_relative_pose(X_ref, X_cur, pairs.Q_ref, pairs.Q_cur, initial=initial)


def guided_match(prev, frame, prior, camera, fe):
    """The odometry's matching with a motion prediction ``prior`` (4x4 T_ref,cur)."""
    ia, ib, dist = guided_cross_check(prev.valid_features, predicted_pixels(prev, prior, camera), frame.valid_features,
                                      frame.uv_undistorted[frame.valid_index], GUIDED_CELL_PX, fe.wta_k > 2)
    keep = keep_best(dist, fe.keep_ratio, fe.max_hamming)
    return ia[keep], ib[keep], dist[keep]


def stage_times(seq: TumSequence, n: int) -> dict[str, np.ndarray]:
    cfg = OdometryConfig()
    orb = make_orb(cfg.frontend)
    noise = cfg.noise_model()
    fe = cfg.frontend
    t = defaultdict(list)
    prev = prior = None

    def clock(name, fn, *a, **k):
        s = time.perf_counter()
        out = fn(*a, **k)
        t[name].append((time.perf_counter() - s) * 1000)
        return out

    for i in range(n):
        grey = clock("decode colour", load_grey, seq.rgb_paths[i])
        depth = clock("decode depth", load_depth, seq.depth_paths[i])
        clock("ORB detect", detect, grey, orb)
        frame = clock("prepare frame (ORB + 3D points + covariances)", prepare_frame, grey, depth, seq.camera, orb,
                      noise, fe, use_surface_angle=cfg.noise.use_surface_angle,
                      pixel_sigma_by_level=cfg.noise.pixel_sigma_by_level,
                      depth_lookup_noise=cfg.noise.depth_lookup_noise)
        if prev is not None:
            if prior is None:
                ia, ib, _ = clock("matching (all pairs: no prediction yet)", match, prev.valid_features,
                                  frame.valid_features, fe.keep_ratio)
            else:
                ia, ib, _ = clock("matching (guided by the last pair's motion)", guided_match, prev, frame, prior,
                                  seq.camera, fe)
            ir, ic = prev.valid_index[ia], frame.valid_index[ib]
            clock("outlier rejection (3D RANSAC)", ransac_rigid3d, prev.points[ir], frame.points[ic],
                  prev.covariances[ir], frame.covariances[ic], fe.ransac_iterations, fe.ransac_chi2, fe.seed,
                  prior=prior)
            pairs = associate_frames(prev, frame, fe, prior, seq.camera)
            dt = seq.timestamps[i] - seq.timestamps[i - 1]
            res = clock("rolling-shutter compensation + solve + marginals", compensated_solve, pairs, dt,
                        seq.camera.height, cfg.sensor.rolling_shutter_s)
            prior = res.matrix
            clock("output lines", lambda res=res: (format_tum_line(0.0, res.matrix),
                                                    format_relative_line(0.0, 0.0, res.matrix, res.covariance)))
        prev = frame
    return {k: np.array(v) for k, v in t.items()}


def depth_offset(seq, i: int) -> float:
    """Frame ``i``'s depth stamp minus its colour stamp, as `covo run` hands it to ``prepare``."""
    stamps = getattr(seq, "depth_timestamps", None)
    return 0.0 if stamps is None else float(stamps[i] - seq.timestamps[i])


def pre_decoded_rate(seq, n: int) -> float:
    """Frames/s of the odometry on images decoded beforehand, preparing ahead as :mod:`covo_gtsam.pipeline` does."""
    images = [(*seq.load(i), depth_offset(seq, i)) for i in range(n)]
    vo = VisualOdometry(seq.camera)
    start = time.perf_counter()
    with kernel_threads(1), Prefetcher(lambda i: vo.prepare(*images[i]), n) as frames:
        for i in range(n):
            vo.register_frame(frames.get(i), None, seq.timestamps[i])
    return n / (time.perf_counter() - start)


def register_times(seq, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Wall and CPU ms of each ``register_frame`` (after the first) on frames prepared beforehand,
    one thread, OpenCV and BLAS single-threaded as in `covo run`."""
    vo = VisualOdometry(seq.camera)
    with kernel_threads(1):
        frames = [vo.prepare(*seq.load(i), depth_offset(seq, i)) for i in range(n)]
        wall, cpu = [], []
        for i in range(n):
            w, c = time.perf_counter(), time.thread_time()
            vo.register_frame(frames[i], None, seq.timestamps[i])
            wall.append(time.perf_counter() - w)
            cpu.append(time.thread_time() - c)
    return 1e3 * np.array(wall[1:]), 1e3 * np.array(cpu[1:])


@contextlib.contextmanager
def watched_workers(profile: bool):
    """Count the prefetch workers' CPU (``time.thread_time`` inside each frame load) and, with
    ``profile``, run a CPU-clock ``cProfile`` per worker thread. Yields ``(cpu_seconds, profiles)``."""
    original, local, lock = pipeline._load_frame, threading.local(), threading.Lock()
    cpu, profiles = [0.0], []

    def load_frame(*args):
        prof = getattr(local, "profile", None)
        if profile and prof is None:
            prof = local.profile = cProfile.Profile(time.thread_time)
            with lock:
                profiles.append(prof)
        start = time.thread_time()
        if prof is not None:
            prof.enable()
        try:
            return original(*args)
        finally:
            if prof is not None:
                prof.disable()
            with lock:
                cpu[0] += time.thread_time() - start

    pipeline._load_frame = load_frame
    try:
        yield cpu, profiles
    finally:
        pipeline._load_frame = original


@contextlib.contextmanager
def prefetch_mode(mode: str):
    """:func:`run_sequence` prepares its frames in ``mode`` (:class:`~covo_gtsam.prefetch.Prefetcher`:
    ``"process"``, ``"thread"`` or ``"serial"``, on the main thread when asked for)."""
    original = pipeline.Prefetcher

    class Forced(original):
        def __init__(self, prepare, n, **kwargs):
            super().__init__(prepare, n, **{**kwargs, "mode": mode})

    pipeline.Prefetcher = Forced
    try:
        yield
    finally:
        pipeline.Prefetcher = original


def in_process_run(seq, n: int, profile: bool = False, mode: str = "process") -> dict:
    """One `covo run` (no figures) in this process with the frames prepared in ``mode``
    (:func:`prefetch_mode`): wall, CPU of this process and its worker processes, of the main
    thread and of the frames' preparation (seconds; on the main thread with ``"serial"``), and
    with ``profile`` the merged ``pstats.Stats`` of all threads (not of worker processes)."""
    with tempfile.TemporaryDirectory() as out, watched_workers(profile) as (workers, profiles), \
            prefetch_mode(mode), contextlib.redirect_stderr(io.StringIO()):  # the progress bar runs, unseen
        main = cProfile.Profile(time.thread_time) if profile else None
        children = resource.getrusage(resource.RUSAGE_CHILDREN)
        wall, cpu, thread = time.perf_counter(), time.process_time(), time.thread_time()
        if main is not None:
            main.enable()
        run_sequence(seq, out, max_frames=n, plots=False, progress=True)
        if main is not None:
            main.disable()
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        forked = after.ru_utime + after.ru_stime - children.ru_utime - children.ru_stime
        result = {"wall": time.perf_counter() - wall, "process": time.process_time() - cpu + forked,
                  "main": time.thread_time() - thread, "workers": workers[0] + forked}
    if profile:
        stats = pstats.Stats(main)
        for p in profiles:
            stats.add(p)
        result["stats"] = stats
    return result


def stage_profile(stats: pstats.Stats) -> dict[str, float]:
    """CPU seconds per stage of :data:`STAGES` (inclusive times), "other" the rest of the
    profiled threads' CPU."""
    inclusive = defaultdict(float)
    for (path, _, name), (_, _, _, cumulative, _) in stats.stats.items():
        inclusive[(path.rsplit("/", 1)[-1], name)] += cumulative
    out = {stage: sum(inclusive[f] for f in functions) for stage, functions in STAGES.items()}
    out["3D points + covariances"] -= inclusive[("matching.py", "detect")]
    out["other (Python glue, hand-offs, bookkeeping)"] = stats.total_tt - sum(out.values())
    return out


def whole_process(seq_dir: str, n: int | None) -> tuple[float, float, float]:
    """Wall seconds, CPU seconds (user + sys) and peak RSS (MB) of `covo run --no-plots --quiet`."""
    with tempfile.TemporaryDirectory() as out:
        cmd = [sys.executable, "-m", "covo_gtsam.cli", "run", seq_dir, "--out", out, "--no-plots", "--quiet"]
        if n:
            cmd += ["--max-frames", str(n)]
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        s = time.perf_counter()
        subprocess.run(cmd, check=True, capture_output=True)
        wall = time.perf_counter() - s
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime
    return wall, cpu, max(after.ru_maxrss, before.ru_maxrss) / 1024.0


def main() -> None:
    seq, n = sequence_from_command_line(__doc__)
    with kernel_threads(1):
        times = stage_times(seq, n)
    print(f"per-stage time per frame on {seq.name} ({n} frames), ms")
    print(f"{'stage':<48} {'median':>7} {'p10':>7} {'p90':>7}")
    for name, v in times.items():
        print(f"{name:<48} {np.median(v):7.2f} {np.percentile(v, 10):7.2f} {np.percentile(v, 90):7.2f}")
    print("(prepare frame includes ORB detect and depth lookup; stages run sequentially here, while `covo run`"
          " decodes and prepares the next frames on worker processes)")

    # before the in-process runs, which hold many decoded frames (a forked child starts with the parent's
    # memory); ru_maxrss of the children is a running maximum: the short run goes first
    small = min(60, n)
    *_, rss60 = whole_process(str(seq.path), small)
    whole_wall, whole_cpu, rss = whole_process(str(seq.path), n)
    print(f"\nwhole process `covo run --no-plots`: {n} frames in {whole_wall:.2f} s = {n / whole_wall:.1f} "
          f"frames/s, CPU {whole_cpu:.2f} s = {1e3 * whole_cpu / n:.1f} ms per frame (start-up and decoding included)")
    print(f"peak RSS: {rss60:.0f} MB for {small} frames, {rss:.0f} MB for {n} frames")

    wall, cpu = register_times(seq, n)
    print(f"\nregister_frame on prepared frames, one thread: median {np.median(wall):.2f} ms wall, "
          f"{np.median(cpu):.2f} ms CPU (p10 {np.percentile(wall, 10):.2f}, p90 {np.percentile(wall, 90):.2f} ms wall)")

    ms = 1e3 / n
    print("\nCPU of a whole run in this process, ms per frame (median of 3 runs by CPU), frames prepared:")
    for mode, what in (("process", "on worker processes, as `covo run`"), ("thread", "on worker threads"),
                       ("serial", "on the main thread when needed (no overlap; steadier on a busy machine)")):
        runs = [in_process_run(seq, n, mode=mode) for _ in range(3)]
        r = sorted(runs, key=lambda x: x["process"])[1]  # the run with the median CPU
        pairs = r["main"] - (r["workers"] if mode == "serial" else 0.0)
        print(f"  {what}: {r['process'] * ms:.1f} = frame pairs and output {pairs * ms:.1f} + decoding and "
              f"preparing {r['workers'] * ms:.1f} + the rest {(r['process'] - pairs - r['workers']) * ms:.1f} "
              f"({n / r['wall']:.1f} frames/s wall)")
    prof = in_process_run(seq, n, profile=True, mode="thread")
    stages = stage_profile(prof["stats"])
    total = sum(stages.values())
    print(f"\nwhere the CPU goes (cProfile, CPU clock per thread, all threads; profiled: "
          f"{total * ms:.1f} ms per frame)")
    print(f"{'stage':<48} {'ms/frame':>8} {'share':>6}")
    for name, v in stages.items():
        print(f"{name:<48} {v * ms:8.2f} {100 * v / total:5.1f}%")

    rates = [pre_decoded_rate(seq, n) for _ in range(3)]
    print(f"\ndecoded in advance (ORB, 3D points, matching, RANSAC, solve, covariance): "
          f"{np.median(rates):.1f} frames/s (median of 3 runs: {', '.join(f'{r:.1f}' for r in rates)})")


if __name__ == "__main__":
    main()
