"""Per-stage time per frame, whole-process frames/s and peak memory of `covo run` on a TUM sequence.

    python benchmarks/bench_pipeline.py SEQ_DIR [--max-frames N]

Stages are timed one after another on the main thread (no overlap), calling the same functions
the pipeline calls. The "decoded in advance" figure runs the odometry as `covo run` does (features
of the next frames prepared on worker threads) on images decoded beforehand. The whole-process figure runs `covo run --no-plots --quiet` as a child process
(start-up, decoding and the prefetch threads included). Peak RSS of the child is given for 60 frames
and for the whole sequence to show that memory stays flat.
"""

from __future__ import annotations

import resource
import subprocess
import sys
import tempfile
import time
from collections import defaultdict, deque
from concurrent.futures import ThreadPoolExecutor

import gtsam
import numpy as np

from _common import sequence_from_command_line
from covo_gtsam.datasets.tum import TumSequence
from covo_gtsam.estimator import estimate_relative_pose
from covo_gtsam.frontend import (
    associate_frames,
    detect,
    load_depth,
    load_grey,
    make_orb,
    match,
    prepare_frame,
    ransac_rigid3d,
)
from covo_gtsam.io import format_relative_line, format_tum_line
from covo_gtsam.odometry import OdometryConfig, VisualOdometry
from covo_gtsam.pipeline import PREFETCH
from covo_gtsam.rolling_shutter import compensate_points, frame_twists


def compensated_solve(pairs, res, dt: float, height: int, readout: float):
    """The odometry's second solve: points moved to their image's timestamp with the pair's twist."""
    twist_ref, twist_cur = frame_twists(res.pose, dt)
    X_ref = compensate_points(pairs.X_ref, pairs.uv_ref[:, 1], twist_ref, height, readout)
    X_cur = compensate_points(pairs.X_cur, pairs.uv_cur[:, 1], twist_cur, height, readout)
    return estimate_relative_pose(X_ref, X_cur, pairs.Q_ref, pairs.Q_cur, initial=res.pose)


def stage_times(seq: TumSequence, n: int) -> dict[str, np.ndarray]:
    cfg = OdometryConfig()
    orb = make_orb(cfg.frontend)
    noise = cfg.noise_model()
    fe = cfg.frontend
    t = defaultdict(list)
    prev = None

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
                      noise, fe)
        if prev is not None:
            ia, ib, _ = clock("matching", match, prev.valid_features, frame.valid_features, fe.keep_ratio)
            ir, ic = prev.valid_index[ia], frame.valid_index[ib]
            clock("outlier rejection (3D RANSAC)", ransac_rigid3d, prev.points[ir], frame.points[ic],
                  prev.covariances[ir], frame.covariances[ic], fe.ransac_iterations, fe.ransac_chi2, fe.seed)
            pairs = associate_frames(prev, frame, fe)
            res = clock("solve + marginals", estimate_relative_pose, pairs.X_ref, pairs.X_cur, pairs.Q_ref,
                        pairs.Q_cur, initial=None if pairs.T_init is None else gtsam.Pose3(pairs.T_init))
            if cfg.rolling_shutter_s > 0:
                dt = seq.timestamps[i] - seq.timestamps[i - 1]
                res = clock("rolling shutter: compensate + solve again", compensated_solve, pairs, res, dt,
                            seq.camera.height, cfg.rolling_shutter_s)
            clock("output lines", lambda: (format_tum_line(0.0, res.matrix),
                                            format_relative_line(0.0, 0.0, res.matrix, res.covariance)))
        prev = frame
    return {k: np.array(v) for k, v in t.items()}


def pre_decoded_rate(seq, n: int) -> float:
    """Frames/s of the odometry on images decoded beforehand, preparing ahead as :mod:`covo_gtsam.pipeline` does."""
    images = [(load_grey(seq.rgb_paths[i]), load_depth(seq.depth_paths[i])) for i in range(n)]
    vo = VisualOdometry(seq.camera)
    start = time.perf_counter()
    with ThreadPoolExecutor(max_workers=PREFETCH) as pool:
        pending = deque(pool.submit(vo.prepare, *images[i]) for i in range(min(PREFETCH, n)))
        for i in range(n):
            frame = pending.popleft().result()
            if i + PREFETCH < n:
                pending.append(pool.submit(vo.prepare, *images[i + PREFETCH]))
            vo.register_frame(frame, None, seq.timestamps[i])
    return n / (time.perf_counter() - start)


def whole_process(seq_dir: str, n: int | None) -> tuple[float, float]:
    with tempfile.TemporaryDirectory() as out:
        cmd = [sys.executable, "-m", "covo_gtsam.cli", "run", seq_dir, "--out", out, "--no-plots", "--quiet"]
        if n:
            cmd += ["--max-frames", str(n)]
        before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
        s = time.perf_counter()
        subprocess.run(cmd, check=True, capture_output=True)
        wall = time.perf_counter() - s
        rss = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return wall, max(rss, before) / 1024.0


def main() -> None:
    seq, n = sequence_from_command_line(__doc__)
    times = stage_times(seq, n)
    print(f"per-stage time per frame on {seq.name} ({n} frames), ms")
    print(f"{'stage':<48} {'median':>7} {'p10':>7} {'p90':>7}")
    for name, v in times.items():
        print(f"{name:<48} {np.median(v):7.2f} {np.percentile(v, 10):7.2f} {np.percentile(v, 90):7.2f}")
    print("(prepare frame includes ORB detect and depth lookup; stages run sequentially here, while `covo run`"
          " decodes and prepares the next frames on worker threads)")
    # ru_maxrss of the children is a running maximum: the short run goes first
    small = min(60, n)
    _, rss60 = whole_process(str(seq.path), small)
    wall, rss = whole_process(str(seq.path), n)
    print(f"\nwhole process `covo run --no-plots`: {n} frames in {wall:.2f} s = {n / wall:.1f} frames/s "
          f"(start-up and decoding included)")
    print(f"peak RSS: {rss60:.0f} MB for {small} frames, {rss:.0f} MB for {n} frames")
    # after the child processes: they would otherwise be forked from a process holding the decoded images
    rates = [pre_decoded_rate(seq, n) for _ in range(3)]
    print(f"\ndecoded in advance (ORB, 3D points, matching, RANSAC, solve, covariance): "
          f"{np.median(rates):.1f} frames/s (median of 3 runs: {', '.join(f'{r:.1f}' for r in rates)})")


if __name__ == "__main__":
    main()
