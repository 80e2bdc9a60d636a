"""Metrics of an odometry run against the sequence's ground truth (a dict ready for JSON)."""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from .chi2 import CHI2_3_975
from .datasets.tum import MAX_GT_COORDINATE
from .errors import InputError
from .geometry import invert_pose
from .metrics import ate_errors, ate_statistics, relative_pose_errors, relative_pose_nees, rpe_statistics
from .odometry import OdometryStep

#: RPE intervals (frames) reported by ``covo run``.
RPE_DELTAS = (1, 30)


def consistency_metrics(T_est: np.ndarray, T_true: np.ndarray, covs: np.ndarray) -> dict:
    """ANEES of rotation and translation (3 dof each) and the share of NEES above chi2(3) 97.5 %."""
    nees_rot, nees_tr = relative_pose_nees(T_est, T_true, covs)
    upper = CHI2_3_975
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


def _unassociated(steps: Sequence[OdometryStep], seq) -> list[dict]:
    """The colour frames of ``rgb.txt`` within the processed frames' time span that have no depth
    image (:attr:`TumSequence.unassociated`), each with the reason: no frame of the list is dropped
    without a word."""
    listed = getattr(seq, "unassociated", None) or []
    if not steps or not listed:
        return []
    n = len(steps)
    last = steps[-1].timestamp if n < len(seq) else float("inf")
    max_dt = getattr(seq, "max_dt", 0.02)
    return [{"timestamp": t, "file": name, "reason": f"no depth image in depth.txt within {max_dt:g} s"}
            for t, name in listed if t <= last]


def evaluate_run(steps: Sequence[OdometryStep], seq, elapsed_s: float) -> dict:
    """Frames, lost frames, speed and, with ground truth, RPE/ATE/ANEES of an odometry run.

    With ground truth, a metric that cannot be computed (too few frames with ground truth, values
    beyond double precision) is None and ``not_computed[name]`` gives the reason (``"anees"`` for
    the consistency keys); the values are never NaN or inf."""
    lost = [s for s in steps if not s.tracked]
    metrics: dict = {
        "sequence": getattr(seq, "name", ""),
        "frames": len(steps),
        "tracked_frames": len(steps) - len(lost),
        "lost_frames": len(lost),
        "lost": [{"timestamp": s.timestamp, "reason": s.reason} for s in lost],
        "restarts": [{"timestamp": s.timestamp, "reason": s.reason} for s in steps if s.status == "restart"],
        "unassociated": _unassociated(steps, seq),
        "elapsed_s": float(elapsed_s),
        "frames_per_second": float(len(steps) / elapsed_s) if elapsed_s > 0 else None,
        "mean_pairs": float(np.mean([s.num_pairs for s in steps if s.status == "tracked"] or [0])),
        "flagged_pairs": sum(1 for s in steps if s.status == "tracked" and s.flagged),
        "flagged": [{"timestamp": s.timestamp, "ref_timestamp": s.ref_timestamp, "quality": s.quality}
                    for s in steps if s.status == "tracked" and s.flagged],
    }
    if getattr(seq, "groundtruth", None) is None:
        return metrics
    # a metric that cannot be computed is None, and "not_computed" says why
    not_computed: dict[str, str] = {}
    metrics["not_computed"] = not_computed
    gt = ground_truth_lookup(seq)
    segments = tracked_segments(steps, gt)
    metrics["segments"] = len(segments)
    no_gt = ("no tracked frame has usable ground truth (inside its time span, positions within "
             f"{MAX_GT_COORDINATE:g} m)") if not segments else None
    for delta in RPE_DELTAS:
        tr, rot = segment_rpe_errors(segments, delta)
        metrics[f"rpe_{delta}"] = _computed(
            not_computed, f"rpe_{delta}", lambda: rpe_statistics(tr, rot, delta), no_gt or (
                None if tr.size else f"no two tracked frames {delta} apart with ground truth inside one segment"))
    # each segment is aligned on its own (segments are not connected); errors pooled
    ate_parts = [G_P for G_P in segments if len(G_P[0]) >= 3]
    metrics["ate"] = _computed(
        not_computed, "ate", lambda: ate_statistics(np.concatenate([ate_errors(G, P)[0] for G, P in ate_parts])),
        no_gt or (None if ate_parts else "no segment has 3 tracked frames with ground truth"))
    T_est, T_true, covs = relative_ground_truth(steps, gt)
    consistency = _computed(not_computed, "anees", lambda: consistency_metrics(T_est, T_true, covs),
                            None if len(T_est) else "no tracked frame pair has ground truth at both frames")
    metrics.update(consistency or dict.fromkeys(CONSISTENCY_KEYS))
    return metrics


#: Keys of :func:`consistency_metrics` (None when it cannot be computed).
CONSISTENCY_KEYS = ("anees_translation", "anees_rotation", "share_nees_translation_above_chi2_975",
                    "share_nees_rotation_above_chi2_975", "chi2_3_975", "nees_pairs")


def _computed(reasons: dict, name: str, compute, reason: str | None):
    """``compute()`` if ``reason`` is None and it succeeds with finite numbers; else None, with the
    reason recorded in ``reasons[name]``."""
    if reason is None:
        try:
            with np.errstate(all="ignore"):
                value = compute()
        except (InputError, ValueError, ArithmeticError, np.linalg.LinAlgError) as exc:
            reason = f"cannot be computed ({exc})"
        else:
            if all(math.isfinite(v) for v in value.values() if isinstance(v, (int, float))):
                return value
            reason = "not finite (ground truth or estimates too large for double precision)"
    reasons[name] = reason
    return None
