"""Metrics of an odometry run against the sequence's ground truth (a dict ready for JSON)."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from .geometry import invert_pose
from .metrics import ate_errors, ate_statistics, chi2_quantile, relative_pose_errors, relative_pose_nees, rpe_statistics
from .odometry import OdometryStep

#: RPE intervals (frames) reported by ``covo run``.
RPE_DELTAS = (1, 30)


def consistency_metrics(T_est: np.ndarray, T_true: np.ndarray, covs: np.ndarray) -> dict:
    """ANEES of rotation and translation (3 dof each) and the share of NEES above chi2(3) 97.5 %."""
    nees_rot, nees_tr = relative_pose_nees(T_est, T_true, covs)
    upper = chi2_quantile(0.975, 3)
    return {
        "anees_translation": float(np.mean(nees_tr)),
        "anees_rotation": float(np.mean(nees_rot)),
        "share_nees_translation_above_chi2_975": float(np.mean(nees_tr > upper)),
        "share_nees_rotation_above_chi2_975": float(np.mean(nees_rot > upper)),
        "chi2_3_975": float(upper),
        "nees_pairs": int(len(nees_tr)),
    }


def relative_ground_truth(steps: Sequence[OdometryStep], stamp_to_gt: dict[float, np.ndarray]):
    """Estimated and true T_ref,cur (K, 4, 4) and covariances (K, 6, 6) of the tracked pairs with ground truth."""
    est, true, covs = [], [], []
    for s in steps:
        if s.status != "tracked":
            continue
        g_ref, g_cur = stamp_to_gt.get(s.ref_timestamp), stamp_to_gt.get(s.timestamp)
        if g_ref is None or g_cur is None:
            continue
        est.append(s.relative.matrix())
        true.append(invert_pose(g_ref) @ g_cur)
        covs.append(s.covariance)
    return np.array(est).reshape(-1, 4, 4), np.array(true).reshape(-1, 4, 4), np.array(covs).reshape(-1, 6, 6)


def tracked_segments(steps: Sequence[OdometryStep], stamp_to_gt: dict[float, np.ndarray]):
    """Ground-truth and estimated poses T_world,cam (K_s, 4, 4) of the tracked frames with ground
    truth, one pair of arrays per segment. A restart begins a new segment: the motion across its
    gap is unknown, so no trajectory error may span it."""
    segments: list[list[OdometryStep]] = [[]]
    for s in steps:
        if s.status == "restart":
            segments.append([])
        if s.tracked and s.timestamp in stamp_to_gt:
            segments[-1].append(s)
    return [(np.array([stamp_to_gt[s.timestamp] for s in seg]), np.array([s.pose.matrix() for s in seg]))
            for seg in segments if seg]


def segment_rpe_errors(segments, delta: int) -> tuple[np.ndarray, np.ndarray]:
    """Translational (m) and rotational (rad) RPE over ``delta`` frames, pooled over the pairs
    ``(i, i + delta)`` inside each segment of :func:`tracked_segments`."""
    parts = [relative_pose_errors(G, P, delta) for G, P in segments if len(G) > delta]
    if not parts:
        return np.empty(0), np.empty(0)
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


def ground_truth_lookup(seq) -> dict[float, np.ndarray]:
    """Map frame timestamp -> ground-truth pose T_world,cam for frames with valid ground truth."""
    if getattr(seq, "groundtruth", None) is None:
        return {}
    return {float(t): g for t, g, ok in zip(seq.timestamps, seq.groundtruth, seq.gt_valid) if ok}


def evaluate_run(steps: Sequence[OdometryStep], seq, elapsed_s: float) -> dict:
    """Frames, lost frames, speed and, with ground truth, RPE/ATE/ANEES of an odometry run."""
    lost = [s for s in steps if not s.tracked]
    metrics: dict = {
        "sequence": getattr(seq, "name", ""),
        "frames": len(steps),
        "tracked_frames": len(steps) - len(lost),
        "lost_frames": len(lost),
        "lost": [{"timestamp": s.timestamp, "reason": s.reason} for s in lost],
        "restarts": [{"timestamp": s.timestamp, "reason": s.reason} for s in steps if s.status == "restart"],
        "elapsed_s": float(elapsed_s),
        "frames_per_second": float(len(steps) / elapsed_s) if elapsed_s > 0 else None,
        "mean_pairs": float(np.mean([s.num_pairs for s in steps if s.status == "tracked"] or [0])),
        "flagged_pairs": sum(1 for s in steps if s.status == "tracked" and s.flagged),
        "flagged": [{"timestamp": s.timestamp, "ref_timestamp": s.ref_timestamp, "quality": s.quality}
                    for s in steps if s.status == "tracked" and s.flagged],
    }
    gt = ground_truth_lookup(seq)
    if not gt:
        return metrics
    segments = tracked_segments(steps, gt)
    metrics["segments"] = len(segments)
    for delta in RPE_DELTAS:
        tr, rot = segment_rpe_errors(segments, delta)
        # None says there is no pair of tracked frames delta apart inside one segment
        metrics[f"rpe_{delta}"] = rpe_statistics(tr, rot, delta) if tr.size else None
    # each segment is aligned on its own (segments are not connected); errors pooled
    ate_parts = [ate_errors(G, P)[0] for G, P in segments if len(G) >= 3]
    metrics["ate"] = ate_statistics(np.concatenate(ate_parts)) if ate_parts else None
    T_est, T_true, covs = relative_ground_truth(steps, gt)
    if len(T_est):
        metrics.update(consistency_metrics(T_est, T_true, covs))
    return metrics
