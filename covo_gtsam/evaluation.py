"""Metrics of an odometry run against the sequence's ground truth.

:func:`evaluate_run` returns one :class:`RunEvaluation`: the statistics written to ``metrics.json``
(:meth:`RunEvaluation.to_dict`) together with the per-pair errors they summarise, which the
figures (:func:`covo_gtsam.plots.plot_run`) draw, so the two cannot disagree.
"""

from __future__ import annotations

import contextlib
import copy
import math
from dataclasses import dataclass, field
from functools import cache, partial
from typing import Sequence

import numpy as np

from .chi2 import CHI2_3_975, anees_band
from .covariance import compose_chains
from .datasets.tum import MAX_GT_COORDINATE, usable_poses
from .errors import InputError
from .geometry import invert_pose
from .integrity import below_majority
from .metrics import anees, ate_errors, ate_statistics, relative_pose_errors, relative_pose_nees, rpe_statistics
from .nees_breakdown import nees_breakdown
from .odometry import OdometryStep
from .reference_noise import (
    axes_rotation,
    axes_transform,
    pair_jitter_covariances,
    reference_jitter,
    twist_change_response,
)

#: Longest median interval (s) between ground-truth samples whose jitter :func:`reference_statistics`
#: measures (a 100 Hz motion-capture reference: 0.01 s).
MAX_JITTER_INTERVAL_S = 0.015
#: RPE intervals (frames) reported by ``covo run``.
RPE_DELTAS = (1, 30)
#: Pairs per chain of ``metrics.json``'s ``chains`` (about a second of a 30 Hz camera).
CHAIN_PAIRS = 30


def consistency_metrics(T_est: np.ndarray, T_true: np.ndarray, covs: np.ndarray) -> dict:
    """ANEES of rotation and translation (3 dof each) and the share of NEES above chi2(3) 97.5 %."""
    return consistency_statistics(*relative_pose_nees(T_est, T_true, covs))


def consistency_statistics(nees_rot: np.ndarray, nees_tr: np.ndarray, band: bool = True) -> dict:
    """The :func:`consistency_metrics` dictionary of rotational and translational NEES values (N,);
    with ``band`` also ``anees_band_95``, the two-sided 95 % band of the ANEES of N independent
    pairs of a consistent covariance (:func:`~covo_gtsam.chi2.anees_band`: how far from 3 an ANEES
    of that many pairs strays by chance; not for overlapping chains, whose NEES are not independent)."""
    upper = CHI2_3_975
    out = {
        "anees_translation": float(np.mean(nees_tr)),
        "anees_rotation": float(np.mean(nees_rot)),
        "share_nees_translation_above_chi2_975": float(np.mean(nees_tr > upper)),
        "share_nees_rotation_above_chi2_975": float(np.mean(nees_rot > upper)),
        "chi2_3_975": float(upper),
        "nees_pairs": int(len(nees_tr)),
    }
    if band:
        out["anees_band_95"] = list(anees_band(len(nees_tr)))
    return out


def pairs_with_truth(steps: Sequence[OdometryStep], stamp_to_gt: dict[float, np.ndarray]) -> list[OdometryStep]:
    """The tracked pairs (in run order) with ground truth at both frames."""
    return [s for s in steps if s.status == "tracked" and s.ref_timestamp in stamp_to_gt and s.timestamp in stamp_to_gt]


def relative_ground_truth(steps: Sequence[OdometryStep], stamp_to_gt: dict[float, np.ndarray]):
    """Estimated and true T_ref,cur (K, 4, 4) and covariances (K, 6, 6) of the tracked pairs with ground truth."""
    pairs = pairs_with_truth(steps, stamp_to_gt)
    est = [s.relative.matrix() for s in pairs]
    true = [invert_pose(stamp_to_gt[s.ref_timestamp]) @ stamp_to_gt[s.timestamp] for s in pairs]
    covs = [s.covariance for s in pairs]
    return np.array(est).reshape(-1, 4, 4), np.array(true).reshape(-1, 4, 4), np.array(covs).reshape(-1, 6, 6)


def chain_statistics(nees_rot: np.ndarray, nees_tr: np.ndarray, length: int = CHAIN_PAIRS) -> dict:
    """``metrics.json``'s ``chains``: :func:`consistency_statistics` of the chains' NEES values
    (:func:`chain_nees`; ``nees_pairs``: the chains) and ``pairs_per_chain`` (``length``)."""
    return {"pairs_per_chain": int(length), **consistency_statistics(nees_rot, nees_tr, band=False)}


@dataclass(frozen=True, eq=False)
class LinkedChains:
    """Chains of linked tracked pairs, composed (:func:`linked_chains`): the relative poses ``T``
    (M, 4, 4) and covariances ``C`` (M, 6, 6) from each chain's first frame to its last, and the
    stamps ``first`` and ``last`` (M,) of those frames."""

    T: np.ndarray
    C: np.ndarray
    first: np.ndarray
    last: np.ndarray

    def nees(self, stamp_to_gt: dict[float, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """NEES of the rotation and of the translation (M,) of each chain against the ground truth
        ``stamp_to_gt`` (a pose T_world,cam at each stamp) between its two ends."""
        starts = np.array([stamp_to_gt[t] for t in self.first])
        ends = np.array([stamp_to_gt[t] for t in self.last])
        return relative_pose_nees(self.T, invert_pose(starts) @ ends, self.C)


def linked_chains(steps: Sequence[OdometryStep], stamp_to_gt: dict[float, np.ndarray],
                  length: int = CHAIN_PAIRS, jitter=None) -> LinkedChains:
    """Every chain of ``length`` linked tracked pairs with ground truth at their frames, the
    covariance composed as independent between factors compose it
    (:func:`~covo_gtsam.covariance.compose_chains`). A pair links to the pair that ends at its
    reference frame: frame to frame the previous one (across lost frames too), with keyframes the
    keyframe's own. A chain stops at a restart and at a frame without ground truth.
    ``jitter(ref_stamps, cur_stamps)``, if given, is what the reference's own noise adds to the
    error between two frames (N, 6, 6), added at the chains' ends. :class:`InputError` when no
    chain is that long."""
    pairs = pairs_with_truth(steps, stamp_to_gt)
    ending = {s.timestamp: i for i, s in enumerate(pairs)}
    chains = []
    for i in range(len(pairs)):
        chain = [i]
        while len(chain) < length and pairs[chain[-1]].ref_timestamp in ending:
            chain.append(ending[pairs[chain[-1]].ref_timestamp])
        if len(chain) == length:
            chains.append(chain[::-1])
    if not chains:
        raise InputError(f"no chain of {length} linked tracked pairs with ground truth")
    T_chain, C_chain = compose_chains(np.array([s.relative.matrix() for s in pairs]),
                                      np.array([s.covariance for s in pairs]), np.array(chains))
    first = np.array([pairs[c[0]].ref_timestamp for c in chains])
    last = np.array([pairs[c[-1]].timestamp for c in chains])
    if jitter is not None:
        C_chain = C_chain + jitter(first, last)
    return LinkedChains(T_chain, C_chain, first, last)


def chain_nees(steps: Sequence[OdometryStep], stamp_to_gt: dict[float, np.ndarray],
               length: int = CHAIN_PAIRS, jitter=None) -> tuple[np.ndarray, np.ndarray]:
    """NEES of the rotation and of the translation (M,) of every chain of :func:`linked_chains`
    against the ground truth between the chain's ends."""
    return linked_chains(steps, stamp_to_gt, length, jitter).nees(stamp_to_gt)


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
    """The colour frames of ``rgb.txt`` up to the last processed frame (those before the first
    included) that have no depth image (:attr:`TumSequence.unassociated`), each with the reason: no
    frame of the list is dropped without a word."""
    listed = getattr(seq, "unassociated", None) or []
    if not steps or not listed:
        return []
    n = len(steps)
    last = steps[-1].timestamp if n < len(seq) else float("inf")
    max_dt = getattr(seq, "max_dt", 0.02)
    return [{"timestamp": t, "file": name, "reason": f"no depth image in depth.txt within {max_dt:g} s"}
            for t, name in listed if t <= last]


@dataclass
class RunEvaluation:
    """What :func:`evaluate_run` measured of an odometry run: the statistics of ``metrics.json``
    (:meth:`to_dict`) and the arrays behind them, for figures and further analysis.

    Without ground truth only the frame counts, lost frames, timing and flagged pairs are filled
    in (``has_ground_truth`` False; :meth:`to_dict` writes the other statistics null). With it, a
    statistic that cannot be computed is None and ``not_computed[name]`` says why
    (``"rpe_<delta>"``, ``"ate"``, ``"anees"``, ``"chains"``, ``"nees_breakdown"``,
    ``"reference_jitter"``, ``"reference_axes"``, ``"twist_change_response"``); its array, if it
    has one, is then empty, or holds the values that made it fail (not finite).
    """

    sequence: str
    frames: int
    #: ``{"timestamp", "reason"}`` of each lost frame, and of each restart
    lost: list[dict]
    restarts: list[dict]
    #: colour frames without a depth image inside the processed span (:func:`_unassociated`)
    unassociated: list[dict]
    elapsed_s: float
    #: mean number of point pairs of the tracked frame pairs
    mean_pairs: float
    #: ``{"timestamp", "ref_timestamp", "quality"}`` of each pair the integrity check flagged
    flagged: list[dict]
    #: tracked pairs whose matches agreed on one motion in 3-D below a majority, kept because their
    #: colour images agreed about as little (a fast motion, blur; :data:`~covo_gtsam.integrity.MIN_CONSENSUS`)
    weak_consensus_pairs: int = 0
    has_ground_truth: bool = False
    #: trajectory segments (a restart starts a new one) with ground truth
    segments: int = 0
    #: RPE statistics (:func:`~covo_gtsam.metrics.rpe_statistics`) per interval in frames
    rpe: dict[int, dict | None] = field(default_factory=dict)
    #: ATE statistics (:func:`~covo_gtsam.metrics.ate_statistics`), segments aligned one by one
    ate: dict | None = None
    #: :func:`consistency_statistics` of the tracked pairs' relative poses
    consistency: dict | None = None
    #: :func:`chain_statistics` of chains of :data:`CHAIN_PAIRS` pairs
    chains: dict | None = None
    #: the pairs' NEES by true motion, in windows and in the tails
    #: (:func:`~covo_gtsam.nees_breakdown.nees_breakdown`)
    breakdown: dict | None = None
    #: the ground truth's own noise (:func:`reference_statistics`)
    reference: dict | None = None
    #: the fixed rotation between the reference's axes and the estimates' (:func:`reference_axes`)
    axes: dict | None = None
    #: how the pairs' rotation errors follow the change of the angular velocity (:func:`twist_change_statistics`)
    twist_change: dict | None = None
    #: per pair of that fit: the change of the true angular velocity across it (rad/s) and the
    #: rotation error along it (rad), (n, 2)
    twist_change_points: np.ndarray = field(default_factory=lambda: np.empty((0, 2)), repr=False)
    #: whether the NEES values take the ground truth's own jitter into account (its samples were at hand)
    nees_with_reference_jitter: bool = False
    #: :func:`consistency_statistics` of the pairs under the reported covariances alone, without the
    #: reference's jitter (None when the NEES takes none)
    without_reference_jitter: dict | None = None
    not_computed: dict[str, str] = field(default_factory=dict)
    #: what the run learnt about its sensor (:meth:`VisualOdometry.self_calibration`), set by
    #: :func:`~covo_gtsam.pipeline.run_sequence`
    self_calibration: dict | None = None
    #: what each pair's reported covariance is made of (:func:`part_shares`): the parts' names, the
    #: pairs' stamps (s) and shares (M, len(names), 2); ``metrics.json``'s ``covariance_parts`` is
    #: their mean (:func:`mean_shares`), the figure draws them; set by
    #: :func:`~covo_gtsam.pipeline.run_sequence`
    part_shares: tuple[list[str], np.ndarray, np.ndarray] | None = field(default=None, repr=False)
    #: the camera the run used (intrinsics, distortion, image size, depth scale), set by the pipeline
    camera: dict | None = None
    #: the covo-gtsam version that made the run, set by the pipeline
    version: str | None = None
    #: the gyroscope the run was given (:meth:`~covo_gtsam.odometry.VisualOdometry.gyro_summary`), set by the pipeline
    gyro: dict | None = None
    #: translational (m) and rotational (rad) RPE of each frame pair, per interval in frames
    rpe_errors: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict, repr=False)
    #: position error (m) of each aligned frame, segments pooled
    ate_errors: np.ndarray = field(default_factory=lambda: np.empty(0), repr=False)
    #: NEES of the rotation and of the translation (3 dof each) of each tracked pair
    nees_rotation: np.ndarray = field(default_factory=lambda: np.empty(0), repr=False)
    nees_translation: np.ndarray = field(default_factory=lambda: np.empty(0), repr=False)
    #: the same of each chain of :data:`CHAIN_PAIRS` pairs (:func:`chain_nees`)
    chain_nees_rotation: np.ndarray = field(default_factory=lambda: np.empty(0), repr=False)
    chain_nees_translation: np.ndarray = field(default_factory=lambda: np.empty(0), repr=False)
    #: frame timestamp -> ground-truth pose T_world,cam (:func:`ground_truth_lookup`)
    ground_truth: dict[float, np.ndarray] = field(default_factory=dict, repr=False)

    @property
    def lost_frames(self) -> int:
        return len(self.lost)

    @property
    def tracked_frames(self) -> int:
        return self.frames - len(self.lost)

    @property
    def frames_per_second(self) -> float | None:
        return float(self.frames / self.elapsed_s) if self.elapsed_s > 0 else None

    def to_dict(self) -> dict:
        """The ``metrics.json`` dictionary (a copy): the counts and timing, then ``not_computed``,
        ``segments``, ``rpe_<delta>``, ``ate``, the :data:`CONSISTENCY_KEYS`, ``chains``,
        ``nees_breakdown``, ``reference_jitter``, ``reference_axes``, ``twist_change_response``,
        ``nees_with_reference_jitter`` and ``without_reference_jitter`` (without ground truth null,
        each with that reason under ``not_computed``), then ``self_calibration``, ``covariance_parts``,
        ``camera`` and ``version`` when they are set (docs/metrics.md)."""
        out: dict = {
            "sequence": self.sequence,
            "frames": self.frames,
            "tracked_frames": self.tracked_frames,
            "lost_frames": self.lost_frames,
            "lost": self.lost,
            "restarts": self.restarts,
            "unassociated": self.unassociated,
            "elapsed_s": self.elapsed_s,
            "frames_per_second": self.frames_per_second,
            "mean_pairs": self.mean_pairs,
            "flagged_pairs": len(self.flagged),
            "flagged": self.flagged,
            "weak_consensus_pairs": self.weak_consensus_pairs,
        }
        # without ground truth the same keys, null, each with the reason
        rpe = self.rpe if self.has_ground_truth else dict.fromkeys(RPE_DELTAS)
        out["not_computed"] = self.not_computed if self.has_ground_truth else dict.fromkeys(
            (*(f"rpe_{delta}" for delta in rpe), "ate", "anees", "chains", "nees_breakdown", "reference_jitter",
             "reference_axes", "twist_change_response"), "the sequence has no ground truth")
        out["segments"] = self.segments
        out.update({f"rpe_{delta}": stats for delta, stats in rpe.items()})
        out["ate"] = self.ate
        out.update(self.consistency or dict.fromkeys(CONSISTENCY_KEYS))
        out["chains"] = self.chains
        out["nees_breakdown"] = self.breakdown
        out["reference_jitter"] = self.reference
        out["reference_axes"] = self.axes
        out["twist_change_response"] = self.twist_change
        out["nees_with_reference_jitter"] = self.nees_with_reference_jitter
        out["without_reference_jitter"] = self.without_reference_jitter
        if self.self_calibration is not None:
            out["self_calibration"] = self.self_calibration
        if self.part_shares is not None and self.part_shares[2].size:
            out["covariance_parts"] = mean_shares(self.part_shares[0], self.part_shares[2])
        if self.camera is not None:
            out["camera"] = self.camera
        if self.version is not None:
            out["version"] = self.version
        if self.gyro is not None:
            out["gyro"] = self.gyro
        return copy.deepcopy(out)


def evaluate_run(steps: Sequence[OdometryStep], seq, elapsed_s: float,
                 rpe_deltas: Sequence[int] = RPE_DELTAS) -> RunEvaluation:
    """Frames, lost frames, speed and, with ground truth, RPE (over each of ``rpe_deltas``
    frames), ATE and ANEES of an odometry run; see :class:`RunEvaluation`.

    The statistics are never NaN or inf: one that cannot be computed (too few frames with ground
    truth, values beyond double precision) is None, with the reason in ``not_computed``."""
    lost = [s for s in steps if not s.tracked]
    tracked_pairs = [s for s in steps if s.status == "tracked"]
    ev = RunEvaluation(
        sequence=getattr(seq, "name", ""),
        frames=len(steps),
        lost=[{"timestamp": s.timestamp, "reason": s.reason} for s in lost],
        restarts=[{"timestamp": s.timestamp, "reason": s.reason} for s in steps if s.status == "restart"],
        unassociated=_unassociated(steps, seq),
        elapsed_s=float(elapsed_s),
        mean_pairs=float(np.mean([s.num_pairs for s in tracked_pairs] or [0])),
        flagged=[{"timestamp": s.timestamp, "ref_timestamp": s.ref_timestamp, "quality": s.quality}
                 for s in tracked_pairs if s.flagged],
        weak_consensus_pairs=sum(below_majority(s.num_pairs, s.num_matches) for s in tracked_pairs),
    )
    if getattr(seq, "groundtruth", None) is None:
        return ev
    ev.has_ground_truth = True
    gt = ev.ground_truth = ground_truth_lookup(seq)
    segments = tracked_segments(steps, gt)
    ev.segments = len(segments)
    no_gt = ("no tracked frame has usable ground truth (inside its time span, positions within "
             f"{MAX_GT_COORDINATE:g} m)") if not segments else None
    for delta in rpe_deltas:
        tr, rot = ev.rpe_errors[delta] = segment_rpe_errors(segments, delta)
        ev.rpe[delta] = _computed(
            ev.not_computed, f"rpe_{delta}", partial(rpe_statistics, tr, rot, delta), no_gt or (
                None if tr.size else f"no two tracked frames {delta} apart with ground truth inside one segment"))

    # each segment is aligned on its own (segments are not connected); errors pooled
    ate_parts = [G_P for G_P in segments if len(G_P[0]) >= 3]

    def ate():
        ev.ate_errors = np.concatenate([ate_errors(G, P)[0] for G, P in ate_parts])
        return ate_statistics(ev.ate_errors)

    ev.ate = _computed(ev.not_computed, "ate", ate,
                       no_gt or (None if ate_parts else "no segment has 3 tracked frames with ground truth"))
    samples = getattr(seq, "gt_samples", None)
    ev.reference = _computed(
        ev.not_computed, "reference_jitter", partial(reference_statistics, samples),
        "no frame was processed" if not steps else None if samples is not None else
        "the ground truth's own samples are not at hand (only its poses at the frames, as from a bag's tf chain "
        "without exactly one moving link)")
    # what the reference's own jitter adds to each error measured against it (pair or chain ends)
    jitter = None if ev.reference is None else reference_covariances(samples, np.deg2rad(ev.reference["rotation_deg"]))
    ev.nees_with_reference_jitter = jitter is not None
    pairs = pairs_with_truth(steps, gt)
    T_est, T_true, covs = relative_ground_truth(pairs, gt)
    ref_stamps, cur_stamps = np.array([s.ref_timestamp for s in pairs]), np.array([s.timestamp for s in pairs])
    reported = covs
    if jitter is not None and len(pairs):
        covs = covs + jitter(ref_stamps, cur_stamps)

    def consistency():
        ev.nees_rotation, ev.nees_translation = relative_pose_nees(T_est, T_true, covs)
        return consistency_statistics(ev.nees_rotation, ev.nees_translation)

    no_pairs = None if len(T_est) else "no tracked frame pair has ground truth at both frames"
    ev.consistency = _computed(ev.not_computed, "anees", consistency, no_pairs)
    if jitter is not None:  # the same against the reported covariances alone, for comparison
        ev.without_reference_jitter = _computed(
            ev.not_computed, "without_reference_jitter",
            lambda: consistency_statistics(*relative_pose_nees(T_est, T_true, reported)), no_pairs)

    composed = cache(partial(linked_chains, steps, gt, jitter=jitter))  # once, for the chains and reference_axes

    def chains():
        ev.chain_nees_rotation, ev.chain_nees_translation = composed().nees(gt)
        return chain_statistics(ev.chain_nees_rotation, ev.chain_nees_translation)

    ev.chains = _computed(ev.not_computed, "chains", chains, no_pairs)

    def breakdown():
        if ev.consistency is None:
            raise InputError("the pairs' NEES could not be computed")
        return nees_breakdown(T_true, ref_stamps, cur_stamps, ev.nees_rotation, ev.nees_translation)

    ev.breakdown = _computed(ev.not_computed, "nees_breakdown", breakdown, no_pairs)
    ev.axes = _computed(ev.not_computed, "reference_axes",
                        partial(reference_axes, steps, gt, T_est, T_true, covs, jitter, composed), no_pairs)

    def response():  # the statistics, and the points of the figure's panel
        fit = twist_change_response(T_est, T_true, covs, ref_stamps, cur_stamps)
        size = np.linalg.norm(fit["changes"], axis=1)
        along = np.einsum("ni,ni->n", fit["errors"], fit["changes"]) / np.where(size > 0, size, 1.0)
        ev.twist_change_points = np.stack([size, along], axis=1)
        return twist_change_statistics(fit)

    ev.twist_change = _computed(ev.not_computed, "twist_change_response", response, no_pairs)
    return ev


def twist_change_statistics(fit: dict) -> dict:
    """``metrics.json``'s ``twist_change_response`` of a
    :func:`~covo_gtsam.reference_noise.twist_change_response` fit (the pairs with their covariances
    and the reference's jitter): the delay of the images against the reference that the pairs'
    rotation errors show (``delay_ms``, the sum of the responses to the change of the true angular
    velocity from the pair before, ``backward_ms``, and to the pair after, ``forward_ms``), and the
    share of each turn the estimates miss (``rotation_scale``), with standard errors and the fit's
    reduced chi-square. A check of the timing between the images and the reference, not a
    correction."""
    se = fit["standard_error"]
    return {"delay_ms": 1e3 * fit["delay_s"], "delay_standard_error_ms": 1e3 * fit["delay_standard_error_s"],
            "backward_ms": 1e3 * fit["backward_s"], "forward_ms": 1e3 * fit["forward_s"],
            "standard_error_ms": (1e3 * se[:2]).tolist(), "rotation_scale": fit["rotation_scale"],
            "rotation_scale_standard_error": float(se[2]), "reduced_chi2": fit["reduced_chi2"], "pairs": fit["pairs"]}


#: largest standard error (deg) of :func:`reference_axes`'s rotation with which the chains are
#: turned back by it
AXES_OBSERVED_DEG = 2.0


def reference_axes(steps: Sequence[OdometryStep], gt: dict[float, np.ndarray], T_est: np.ndarray,
                   T_true: np.ndarray, covs: np.ndarray, jitter=None, chains=None) -> dict:
    """``metrics.json``'s ``reference_axes``: the fixed rotation by which the reference's axes are
    turned against the estimates' (:func:`~covo_gtsam.reference_noise.axes_rotation` of the pairs
    ``T_est``, ``T_true`` with ``covs``, the reference's jitter in them), a rotation vector about the
    camera's x / y / z axes in degrees with its standard errors and the fit's reduced chi-square
    (the standard errors are scaled up by it where it exceeds 1), and the rotation ANEES of the
    chains (:func:`chain_nees`) against the reference turned back by it (fitted on the same pairs;
    None without a chain, or where a standard error exceeds :data:`AXES_OBSERVED_DEG`: the
    rotation is not observed about every axis). ``chains``, if given, returns the run's
    :func:`linked_chains` with the same ``jitter`` (e.g. composed once for the run's chains too). A
    check of the reference (a hand-eye rotation, a principal point), not a correction: the reported
    covariances do not carry it."""
    fit = axes_rotation(T_est, T_true, covs)
    turned = None
    if np.all(np.rad2deg(fit["standard_error_rad"]) <= AXES_OBSERVED_DEG):
        D = axes_transform(fit["rotation_rad"])
        with contextlib.suppress(InputError):
            linked = linked_chains(steps, gt, jitter=jitter) if chains is None else chains()
            turned = anees(linked.nees({t: G @ D for t, G in gt.items()})[0])
    return {"rotation_vector_deg": np.rad2deg(fit["rotation_rad"]).tolist(),
            "standard_error_deg": np.rad2deg(fit["standard_error_rad"]).tolist(),
            "reduced_chi2": fit["reduced_chi2"], "pairs": fit["pairs"], "chains_anees_rotation": turned}


def part_shares(variance_parts: Sequence[tuple[tuple[str, ...], np.ndarray] | None]
                ) -> tuple[list[str], np.ndarray, np.ndarray]:
    """The parts' names (the sensor terms in order of appearance, then ``points``), the indices
    (M,) of the entries of ``variance_parts`` (a :class:`~covo_gtsam.steps.StepHistory`'s) that
    hold a pair, and each pair's share (M, len(names), 2) of its rotation and translation variance
    that each part is: a part a pair lacks is 0, ``points`` the rest (see :func:`covariance_parts`)."""
    index = [i for i, v in enumerate(variance_parts) if v is not None]
    names = list(dict.fromkeys(name for i in index for name in variance_parts[i][0]))
    shares = np.zeros((len(index), len(names) + 1, 2))
    for row, i in enumerate(index):
        terms, traces = variance_parts[i]
        shares[row, [names.index(name) for name in terms]] = traces[:-1] / traces[-1]
    shares[:, -1] = 1.0 - shares[:, :-1].sum(axis=1)
    return [*names, "points"], np.array(index, dtype=int), shares


def covariance_parts(variance_parts: Sequence[tuple[tuple[str, ...], np.ndarray] | None]) -> dict | None:
    """``metrics.json``'s ``covariance_parts``: over the pairs a
    :class:`~covo_gtsam.steps.StepHistory` recorded (``variance_parts``: with a relative pose, not
    flagged), the mean share of the reported ``rotation`` and ``translation`` variance (the trace of
    each 3x3 block) that each part is: each sensor term (``frame_term``, the frame-level terms by
    name, with what the odometry added to them), ``depth_drift`` and ``points``, the rest, the
    per-point model's (times kappa). Each block's shares sum to 1. With the ``pairs`` counted; None
    without a pair."""
    names, index, shares = part_shares(variance_parts)
    return mean_shares(names, shares) if index.size else None


def mean_shares(names: Sequence[str], shares: np.ndarray) -> dict:
    """The mean over the pairs of :func:`part_shares`' ``shares`` (M, len(names), 2), by block and
    part, with the ``pairs`` counted: ``metrics.json``'s ``covariance_parts``."""
    mean = shares.mean(axis=0)
    return {"rotation": dict(zip(names, map(float, mean[:, 0]))),
            "translation": dict(zip(names, map(float, mean[:, 1]))), "pairs": len(shares)}


def reference_statistics(samples: tuple[np.ndarray, np.ndarray]) -> dict:
    """``metrics.json``'s ``reference_jitter``: the s.d. per axis of the ground truth's own noise per
    sample (:func:`~covo_gtsam.reference_noise.reference_jitter`) over all its samples: rotation about
    the camera's axes in degrees, translation along them in mm. :class:`InputError` for samples more
    than :data:`MAX_JITTER_INTERVAL_S` apart (median), where the quadratic through the neighbours
    no longer follows a hand-held motion and would report the motion as jitter (on fr1's reference
    taken every 2nd / 3rd sample, 0.11 / 0.16 deg about x against 0.069 at 100 Hz)."""
    stamps, poses = samples
    usable = usable_poses(poses) & np.isfinite(stamps)
    dt = float(np.median(np.diff(np.sort(stamps[usable])))) if usable.sum() > 1 else 0.0
    if dt > MAX_JITTER_INTERVAL_S:
        raise InputError(f"ground-truth samples {1e3 * dt:.0f} ms apart: too far apart to tell their jitter from the "
                         f"motion (at most {1e3 * MAX_JITTER_INTERVAL_S:g} ms)")
    with np.errstate(all="ignore"):  # beyond double precision: not finite, refused below
        out = reference_jitter(stamps[usable], poses[usable])
    if out is None:
        raise InputError("too few evenly spaced ground-truth samples")
    rot, trans = np.rad2deg(out["rotation_rad"]), 1e3 * out["translation_m"]
    if not (np.all(np.isfinite(rot)) and np.all(np.isfinite(trans))):
        raise InputError("not finite (ground truth too large for double precision)")
    return {"rotation_deg": rot.tolist(), "translation_mm": trans.tolist(), "samples": out["samples"]}


def reference_covariances(samples: tuple[np.ndarray, np.ndarray], rotation_sd: np.ndarray | None = None):
    """``jitter(ref_stamps, cur_stamps)``: what the ground truth's own rotation jitter adds (N, 6, 6)
    to the error of each pair of frames at those stamps (N,) measured against it
    (:func:`~covo_gtsam.reference_noise.pair_jitter_covariances`), from its samples ``(stamps,
    poses)`` (stamps that are not numbers left out) and its s.d. per sample and axis (rad; if not
    given, :func:`reference_statistics`'s, :class:`InputError` when the samples do not allow it)."""
    if rotation_sd is None:
        rotation_sd = np.deg2rad(reference_statistics(samples)["rotation_deg"])
    stamps = np.asarray(samples[0], dtype=float)
    return partial(pair_jitter_covariances, stamps[np.isfinite(stamps)], rotation_sd)


#: Keys of :func:`consistency_metrics` (None when it cannot be computed).
CONSISTENCY_KEYS = ("anees_translation", "anees_rotation", "share_nees_translation_above_chi2_975",
                    "share_nees_rotation_above_chi2_975", "chi2_3_975", "nees_pairs", "anees_band_95")


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
            if _finite(value):
                return value
            reason = "not finite (ground truth or estimates too large for double precision)"
    reasons[name] = reason
    return None


def _finite(value) -> bool:
    """Every number in ``value`` (nested dicts and lists; None allowed) is finite."""
    if isinstance(value, dict):
        return all(_finite(v) for v in value.values())
    if isinstance(value, (list, tuple)):
        return all(_finite(v) for v in value)
    return not isinstance(value, (int, float)) or math.isfinite(value)
