"""Side-by-side run of covo and the RGB-D odometry peers that install from PyPI, same frames, same process.

    python benchmarks/peers.py SEQ_DIR [--max-frames N]

Peers (optional; skipped with a message when not installed): Open3D
``compute_rgbd_odometry`` (hybrid photometric + geometric, frame to frame) and OpenCV's
``cv2.Odometry`` (RGB-D). Prints time per frame pair (median, decoding excluded) and translational /
rotational RPE over 1 and 30 frames against the ground truth, with ratios to covo. Only pairs of
frames that both have ground truth (``seq.gt_valid``: inside the motion-capture span, no gap) and
no frame without it between them are scored.
"""

from __future__ import annotations

import time

import cv2
import numpy as np

from covo_gtsam.metrics import relative_pose_errors, rpe_statistics
from covo_gtsam.odometry import VisualOdometry

from _common import sequence_from_command_line


def valid_rpe(gt: np.ndarray, valid: np.ndarray, poses: np.ndarray, delta: int) -> dict | None:
    """RPE over ``delta`` frames pooled over the runs of consecutive frames with valid ground truth
    (a frame without it, e.g. before the motion capture starts, has an identity placeholder and
    must not be scored); None when no run is longer than ``delta``."""
    valid = np.asarray(valid, bool)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], valid.astype(int), [0]])))
    tr, rot = [], []
    for a, b in zip(edges[::2], edges[1::2]):
        if b - a > delta:
            t, r = relative_pose_errors(gt[a:b], poses[a:b], delta)
            tr.append(t)
            rot.append(r)
    return rpe_statistics(np.concatenate(tr), np.concatenate(rot), delta) if tr else None


def run_covo(seq, frames):
    vo = VisualOdometry(seq.camera)
    times, poses = [], [np.eye(4)]
    last = np.eye(4)
    for k, (grey, _colour, depth) in enumerate(frames):
        t = time.perf_counter()
        step = vo.register_frame(grey, depth, seq.timestamps[k])
        times.append(time.perf_counter() - t)
        if k and step.has_pose:
            last = step.pose.matrix()
        if k:
            poses.append(last)
    return np.array(times[1:]), np.array(poses)


def run_open3d(seq, frames):
    import open3d as o3d

    cam = seq.camera
    intr = o3d.camera.PinholeCameraIntrinsic(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy)
    option = o3d.pipelines.odometry.OdometryOption()
    jac = o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm()

    def rgbd(colour, depth):
        return o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(np.ascontiguousarray(colour[:, :, ::-1])), o3d.geometry.Image(depth),
            depth_scale=1.0, depth_trunc=5.0, convert_rgb_to_intensity=True)

    prev = rgbd(frames[0][1], frames[0][2])
    poses, times = [np.eye(4)], []
    for _, colour, depth in frames[1:]:
        cur = rgbd(colour, depth)
        t = time.perf_counter()
        ok, T, _ = o3d.pipelines.odometry.compute_rgbd_odometry(cur, prev, intr, np.eye(4), jac, option)
        times.append(time.perf_counter() - t)
        # source = current, target = previous: T maps points of the current frame into the previous one
        poses.append(poses[-1] @ (T if ok else np.eye(4)))
        prev = cur
    return np.array(times), np.array(poses)


def run_opencv(seq, frames):
    cam = seq.camera
    settings = cv2.OdometrySettings()
    settings.setCameraMatrix(cam.K.astype(np.float32))
    odo = cv2.Odometry(cv2.OdometryType_RGB_DEPTH, settings, cv2.OdometryAlgoType_COMMON)
    poses, times = [np.eye(4)], []
    for k in range(1, len(frames)):
        (g0, _, d0), (g1, _, d1) = frames[k - 1], frames[k]
        t = time.perf_counter()
        ok, Rt = odo.compute(d1, g1, d0, g0)
        times.append(time.perf_counter() - t)
        # "Rt * src = dst" with src = current, dst = previous: Rt = T_prev,cur (checked against ground truth)
        poses.append(poses[-1] @ (Rt if ok else np.eye(4)))
    return np.array(times), np.array(poses)


def main() -> None:
    seq, n = sequence_from_command_line(__doc__)
    frames = []
    for i in range(n):
        colour = cv2.imread(seq.rgb_paths[i])
        grey, depth = seq.load(i)
        frames.append((grey, colour, depth))
    if seq.groundtruth is None or not seq.gt_valid[:n].any():
        raise SystemExit(f"{seq.path}: no ground truth for the first {n} frames; nothing to score")
    gt, valid = seq.groundtruth[:n], seq.gt_valid[:n]
    rows = {}
    for name, fn in (("covo", run_covo), ("open3d", run_open3d), ("opencv", run_opencv)):
        try:
            times, poses = fn(seq, frames)
        except ImportError as exc:
            print(f"{name}: not installed ({exc}); skipped")
            continue
        rows[name] = (np.median(times) * 1000, valid_rpe(gt, valid, poses, 1), valid_rpe(gt, valid, poses, 30))
    base = rows["covo"]
    print(f"{n} frames of {seq.name}")
    print(f"{'method':<8} {'ms/pair':>8} {'RPE1 m':>8} {'RPE1 deg':>9} {'RPE30 m':>8} {'RPE30 deg':>9} "
          f"{'time/covo':>9} {'RPE30/covo':>10}")
    nan = float("nan")
    for name, (ms, r1, r30) in rows.items():
        r1t, r1r = (r1["trans_rmse"], r1["rot_rmse_deg"]) if r1 else (nan, nan)
        r30t, r30r = (r30["trans_rmse"], r30["rot_rmse_deg"]) if r30 else (nan, nan)
        ratio = r30t / base[2]["trans_rmse"] if r30 and base[2] else nan
        print(f"{name:<8} {ms:8.2f} {r1t:8.4f} {r1r:9.3f} {r30t:8.4f} {r30r:9.3f} "
              f"{ms / base[0]:9.2f} {ratio:10.2f}")


if __name__ == "__main__":
    main()
