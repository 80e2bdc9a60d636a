"""Cross-validation of the covariance's sensor terms: writes docs/cross_validation.md.

    python studies/cross_validation.py [--data ../shared/data]

The odometry runs once per sequence with the per-point model alone (frame to frame, everything
else default). The sensor terms (kappa, the frame term and frame-level terms; the stamp-jitter
prior held at its default, the ground truth's own rotation jitter, measured from its samples, held
as a known term) are fitted by maximum likelihood
(`covo_gtsam.calibration.fit_sensor_terms`) on the consecutive pairs of one half of the shared
fr1_rpy frames and checked on the other half and on fr1_desk, both ways round. Reported per
check: ANEES translation / rotation, share of NEES above 9.35, largest NEES, 30-pair chains. Every
NEES against the ground truth adds its jitter, as `metrics.json`'s does (at a chain's two ends).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from covo_gtsam.calibration import (  # noqa: E402
    DEFAULT_TERMS,
    ERROR_TERMS,
    PRIOR_TERMS,
    fit_sensor_terms,
    sensor_covariance,
)
from covo_gtsam.camera import Camera  # noqa: E402
from covo_gtsam.config import OdometryConfig  # noqa: E402
from covo_gtsam.covariance import compose_chains, compose_covariance  # noqa: E402
from covo_gtsam.datasets.tum import TumSequence  # noqa: E402
from covo_gtsam.evaluation import (  # noqa: E402
    ground_truth_lookup,
    pairs_with_truth,
    reference_covariances,
    reference_statistics,
    relative_ground_truth,
)
from covo_gtsam.metrics import nees, relative_pose_tangent_errors, se3_log  # noqa: E402
from covo_gtsam.nees_breakdown import ACCELERATION_EDGES, by_bins, true_motion  # noqa: E402
from covo_gtsam.pipeline import calibration_pairs, prior_covariances, run_sequence, stacked_bases  # noqa: E402
from covo_gtsam.reference_noise import axes_rotation, axes_transform, twist_change_response  # noqa: E402

RPY, DESK = "rgbd_dataset_freiburg1_rpy_head240", "rgbd_dataset_freiburg1_desk_9frames"
#: the per-point model alone (sensor settings): no sensor terms
POINTS_ONLY = dict(correlation_factor=1.0, frame_sigma_rot_deg=0.0, frame_sigma_trans_m=0.0,
                   **{name: 0.0 for name in ERROR_TERMS.values()})
LATENCY_TERMS = ("timing", "rolling_shutter", "latency")
#: covariance models compared: whether kappa is fitted, and the frame-level terms each fits
MODELS = {"kappa + frame term": (True, ()), "+ timing": (True, ("timing",)),
          "+ timing, rolling shutter": (True, ("timing", "rolling_shutter")),
          "+ timing, rolling shutter, latency": (True, LATENCY_TERMS),
          "+ latency, kappa 1": (False, LATENCY_TERMS),
          "+ latency, depth scale, depth time (both forms); kappa 1 (default)": (False, DEFAULT_TERMS)}
CHAIN = 30
#: the pairs the per-pair tables report: sequence, then (label, first and last frame a pair ends at)
SEGMENTS = ((RPY, (("fr1_rpy, frames 1-119", 1, 119), ("fr1_rpy, frames 120-239", 120, 239))),
            (DESK, (("fr1_desk", 1, 10**9),)))


def per_point_pairs(data: Path, name: str, gyro=None, **sensor) -> dict:
    """Errors (N, 6), per-point covariances (N, 6, 6), frame-level error bases (name -> (N, 6, 6)),
    end frame index (N,) and true/estimated poses of the consecutive pairs with ground truth,
    per-point model alone (and the ``sensor`` settings given; ``gyro`` a
    :class:`~covo_gtsam.gyro.Gyroscope`, whose own part the per-point covariances then hold). ``fixed``
    holds the known terms: the prior terms' and the ground truth's own jitter (``ref``, as
    ``metrics.json``'s NEES adds it); ``jitter`` is that jitter's function of the stamps (for the chains' ends)."""
    seq = TumSequence(data / "tum" / name)
    cfg = OdometryConfig().replace(sensor={**POINTS_ONLY, **sensor})
    with tempfile.TemporaryDirectory() as tmp:
        run = run_sequence(seq, tmp, config=cfg, plots=False, progress=False, keep_error_bases=True, gyro=gyro)
    lookup = ground_truth_lookup(seq)
    pairs = calibration_pairs(run.steps, lookup, cfg, require_clock=False)
    fit_ok = {id(s) for s in calibration_pairs(run.steps, lookup, cfg)}  # the pairs covo calibrate fits
    T_est, T_true, covs = relative_ground_truth(pairs, lookup)
    index = {t: i for i, t in enumerate(seq.timestamps)}
    priors = {k: getattr(OdometryConfig().sensor, ERROR_TERMS[k]) for k in PRIOR_TERMS}
    jitter = reference_covariances(seq.gt_samples)
    t_ref, t_cur = np.array([s.ref_timestamp for s in pairs]), np.array([s.timestamp for s in pairs])
    ref = jitter(t_ref, t_cur)
    return {"err": relative_pose_tangent_errors(T_est, T_true), "cov": covs, "bases": stacked_bases(pairs),
            "fixed": prior_covariances(pairs, priors) + ref, "ref": ref, "jitter": jitter,
            "fit_ok": np.array([id(s) in fit_ok for s in pairs], bool), "t_ref": t_ref, "t_cur": t_cur,
            "end": np.array([index[s.timestamp] for s in pairs]), "T_est": T_est, "T_true": T_true}


def against_reference(seq: TumSequence, steps: list, lookup: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`covo_gtsam.evaluation.relative_ground_truth` of ``steps``, the covariances with the
    ground truth's own jitter added, as ``metrics.json``'s NEES adds it."""
    pairs = pairs_with_truth(steps, lookup)
    T_est, T_true, covs = relative_ground_truth(pairs, lookup)
    ref = reference_covariances(seq.gt_samples)([s.ref_timestamp for s in pairs], [s.timestamp for s in pairs])
    return T_est, T_true, covs + ref


def subset(p: dict, mask: np.ndarray) -> dict:
    return {k: (v if callable(v) else {n: b[mask] for n, b in v.items()} if isinstance(v, dict) else v[mask])
            for k, v in p.items()}


def model_covs(fit, p: dict) -> np.ndarray:
    return fit.covariances(p["cov"], p["bases"]) + p["fixed"]


def anees_cells(err: np.ndarray, covs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """NEES of the translation and the rotation blocks (tangent ``[omega, v]``)."""
    return nees(err[:, 3:], covs[:, 3:, 3:]), nees(err[:, :3], covs[:, :3, :3])


def chain_anees(p: dict, covs: np.ndarray, w: int = CHAIN) -> tuple[float, float]:
    """ANEES t / r of windows of ``w`` consecutive pairs (covariances composed as independent,
    :func:`covo_gtsam.covariance.compose_chains`; the ground truth's jitter, in ``covs`` per pair,
    taken out and added at the chains' ends)."""
    breaks = np.flatnonzero(np.diff(p["end"]) != 1) + 1  # runs of pairs ending in consecutive frames
    nt, nr = [], []
    for run in np.split(np.arange(len(p["end"])), breaks):
        T, C = compose_chains(p["T_est"][run], covs[run] - p["ref"][run], w)
        if not len(T):
            continue
        C = C + p["jitter"](p["t_ref"][run][:len(T)], p["t_cur"][run][w - 1:])
        true, _ = compose_chains(p["T_true"][run], covs[run], w)
        t, r = anees_cells(relative_pose_tangent_errors(T, true), C)
        nt.append(t)
        nr.append(r)
    if not nt:
        return float("nan"), float("nan")
    return float(np.concatenate(nt).mean()), float(np.concatenate(nr).mean())


def check(fit, p: dict) -> str:
    from covo_gtsam.calibration import log_likelihood

    covs = model_covs(fit, p)
    nt, nr = anees_cells(p["err"], covs)
    ct, cr = chain_anees(p, covs)
    chain = "—" if np.isnan(ct) else f"{ct:.2f} / {cr:.2f}"
    return (f"{nt.mean():.2f} / {nr.mean():.2f} | "
            f"{100 * np.mean(nt > 9.35):.0f} % / {100 * np.mean(nr > 9.35):.0f} % | "
            f"{nt.max():.1f} / {nr.max():.1f} | {chain} | {log_likelihood(p['err'], covs):.2f}")


UNITS = {"timing": (1e3, "ms"), "latency": (1e3, "ms"), "depth_scale": (1e2, "%"), "depth_time": (1.0, ""),
         "depth_time_coherent": (1.0, ""), "rolling_shutter": (1.0, ""), "gyro": (1.0, " rad/s")}


def fit_row(fit) -> str:
    terms = "".join(f", {k} {UNITS[k][0] * v:.3g}{UNITS[k][1]}" for k, v in fit.sigmas.items())
    return (f"kappa {fit.correlation_factor:.2f}, {fit.frame_sigma_rot_deg:.3f} deg, "
            f"{1e3 * fit.frame_sigma_trans_m:.2f} mm{terms}; ll {fit.log_likelihood:.2f}")


def tables(data: Path) -> list[str]:
    lines = []
    delay = None
    for label, overrides in (("default (frame clock on)", {}), ("frame clock off", {"frame_clock": False})):
        rpy, desk = per_point_pairs(data, RPY, **overrides), per_point_pairs(data, DESK, **overrides)
        delay = delay or delay_table(data, rpy, desk)
        halves = {"A: pairs ending in frames 1-119": rpy["end"] <= 119,
                  "B: pairs ending in frames 120-239": rpy["end"] >= 120}
        lines += [f"### {label}", "",
                  "| fitted on | model | terms | checked on | ANEES t / r | NEES > 9.35 t / r | largest NEES t / r | "
                  f"{CHAIN}-pair chains ANEES t / r | log-likelihood per pair |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for fit_name, m in halves.items():
            train = subset(rpy, m & rpy["fit_ok"])
            for model, (fit_kappa, names) in MODELS.items():
                fit = fit_sensor_terms(train["err"], train["cov"], fit_kappa,
                                       bases={n: train["bases"][n] for n in names}, fixed=train["fixed"])
                for other, mo in halves.items():
                    if other != fit_name:
                        lines.append(f"| {fit_name[:1]} | {model} | {fit_row(fit)} | {other[:1]} (held out) | "
                                     f"{check(fit, subset(rpy, mo))} |")
                row = f"| {fit_name[:1]} | {model} | {fit_row(fit)} |"
                lines.append(f"{row} fr1_desk (held out) | {check(fit, desk)} |")
                lines.append(f"{row} {fit_name[:1]} (in sample) | {check(fit, train)} |")
        lines.append("")
    return lines + delay


#: common shifts of the stamps against the ground truth tried (s)
SHIFTS = np.arange(-30.0, 30.1, 2.5) * 1e-3


def shifted_truth(seq: TumSequence, end: np.ndarray, shift: float) -> tuple[np.ndarray, np.ndarray]:
    """True T_ref,cur (K, 4, 4) of the consecutive pairs ending at frames ``end``, with the ground
    truth interpolated at the colour stamps plus ``shift`` (s), and where it exists (K,)."""
    from covo_gtsam.datasets.tum import interpolate_poses
    from covo_gtsam.io import load_tum_trajectory

    stamps, poses = load_tum_trajectory(seq.path / "groundtruth.txt")
    ts = np.asarray(seq.timestamps)
    P0, ok0 = interpolate_poses(stamps, poses, ts[end - 1] + shift)
    P1, ok1 = interpolate_poses(stamps, poses, ts[end] + shift)
    return np.linalg.inv(P0) @ P1, ok0 & ok1


def delay_table(data: Path, rpy: dict, desk: dict) -> list[str]:
    """Rotation RMS of the consecutive pairs against the ground truth taken at the stamps shifted
    by a common delay: the evidence for the latency term (poses of the runs above)."""
    lines = ["## The stamps' delay against the ground truth", "",
             "Rotation RMS of the frame-to-frame poses against the ground truth interpolated at the colour "
             "stamps plus a common shift (positive: the ground truth later); the shift with the smallest RMS "
             "on a 2.5 ms grid from -30 to 30 ms.", "",
             "| pairs | rotation RMS at the stamps (deg) | best shift (ms) | rotation RMS there (deg) | "
             "translation RMS at the stamps / there (mm) |", "|---|---|---|---|---|"]
    for label, name, p, mask in (("fr1_rpy, frames 1-119", RPY, rpy, rpy["end"] <= 119),
                                 ("fr1_rpy, frames 120-239", RPY, rpy, rpy["end"] >= 120),
                                 ("fr1_desk", DESK, desk, np.ones(len(desk["end"]), bool))):
        seq = TumSequence(data / "tum" / name)
        rms, rms_t = [], []
        for shift in SHIFTS:
            true, ok = shifted_truth(seq, p["end"][mask], shift)
            xi = relative_pose_tangent_errors(p["T_est"][mask], true)[ok]
            rms.append(np.rad2deg(np.sqrt(np.mean(np.sum(xi[:, :3] ** 2, axis=1)))))
            rms_t.append(1e3 * np.sqrt(np.mean(np.sum(xi[:, 3:] ** 2, axis=1))))
        best, zero = int(np.argmin(rms)), len(SHIFTS) // 2
        lines.append(f"| {label} | {rms[zero]:.3f} | {1e3 * SHIFTS[best]:+.1f} | {rms[best]:.3f} | "
                     f"{rms_t[zero]:.2f} / {rms_t[best]:.2f} |")
    return lines + [""]


def moved_table(data: Path) -> list[str]:
    """The default run's consecutive pairs moved by a common delay along their frames' twists (as
    the frame clock moves them to the stamps, :func:`covo_gtsam.clock.restamp`): rotation and
    translation RMS against the ground truth at the stamps, per delay."""
    from covo_gtsam.clock import restamp

    delays = (-0.010, -0.0075, 0.0, 0.0075, 0.010)
    lines = ["Moving the poses instead: each consecutive pair of the default run moved by a common delay `L` along "
             "its two frames' twists (`Exp(L xi_ref)^-1 T Exp(L xi_cur)`, the twists the frame clock moves them with; "
             "positive: the image was taken before its stamp), against the ground truth at the stamps. Rotation RMS "
             "(deg) / translation RMS (mm). All pairs, the one ending at frame 108 that the integrity check flags "
             "included (the delay table above leaves it out).", "",
             "| pairs | " + " | ".join(f"L = {1e3 * L:+.1f} ms" for L in delays) + " |",
             "|---" * (len(delays) + 1) + "|"]
    for name, ranges in SEGMENTS:
        seq = TumSequence(data / "tum" / name)
        index = {t: i for i, t in enumerate(seq.timestamps)}
        steps = {index[s.timestamp]: s for s in every_nth(seq, OdometryConfig(), 1)}
        pairs = [(k, s) for k, s in sorted(steps.items())
                 if index.get(s.ref_timestamp) == k - 1 and s.stamp_twist is not None]
        ends = np.array([k for k, _ in pairs])
        for label, lo, hi in ranges:
            m = (ends >= lo) & (ends <= hi)
            true, ok = shifted_truth(seq, ends[m], 0.0)
            cells = []
            for L in delays:
                moved = []
                for k, s in (pair for pair, keep in zip(pairs, m) if keep):
                    ref = steps.get(k - 1)  # as the odometry: the reference's own twist, else this pair's
                    twist_ref = s.velocity if ref is None or ref.stamp_twist is None else ref.stamp_twist
                    moved.append(restamp(s.relative, L * twist_ref, L * s.stamp_twist)[0].matrix())
                e = relative_pose_tangent_errors(np.array(moved), true)[ok]
                cells.append(f"{np.degrees(np.sqrt(np.mean(np.sum(e[:, :3] ** 2, 1)))):.3f} / "
                             f"{1e3 * np.sqrt(np.mean(np.sum(e[:, 3:] ** 2, 1))):.2f}")
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return lines + [""]


def fit_half(p: dict, mask: np.ndarray) -> tuple:
    """The default model fitted on the pairs of ``mask`` (those ``covo calibrate`` fits) and
    ``"ANEES t / r | log-likelihood"`` on the other pairs."""
    from covo_gtsam.calibration import log_likelihood

    train = subset(p, mask & p["fit_ok"])
    fit = fit_sensor_terms(train["err"], train["cov"], False,
                           bases={n: train["bases"][n] for n in DEFAULT_TERMS}, fixed=train["fixed"])
    held = subset(p, ~mask)
    covs = model_covs(fit, held)
    nt, nr = anees_cells(held["err"], covs)
    return fit, f"{nt.mean():.2f} / {nr.mean():.2f} | {log_likelihood(held['err'], covs):.2f}"


def window_table(data: Path) -> list[str]:
    """The default model fitted with the latency and rolling-shutter terms' twist history over 3, 10
    (the default) and 30 pairs: fit on one half of fr1_rpy, check on the other."""
    lines = ["## The twist history's length", "",
             "The latency and rolling-shutter terms take the size of the twist's change over a pair from the "
             "changes of the pairs before it (`sensor.twist_history` of them). The default model fitted on one half "
             "of fr1_rpy and checked on the other, per history length.", "",
             "| history (pairs) | fitted on | latency (ms) | rolling shutter | log-likelihood in sample | "
             "checked on | ANEES t / r | log-likelihood held out |", "|---|---|---|---|---|---|---|---|"]

    for window in (3, 10, 30):
        rpy = per_point_pairs(data, RPY, twist_history=window)
        halves = {"A": rpy["end"] <= 119, "B": rpy["end"] >= 120}
        for name, m in halves.items():
            fit, held = fit_half(rpy, m)
            lines.append(f"| {window} | {name} | {1e3 * fit.sigmas['latency']:.2f} | "
                         f"{fit.sigmas['rolling_shutter']:.2f} | {fit.log_likelihood:.2f} | "
                         f"{'B' if name == 'A' else 'A'} | {held} |")
    return lines + [""]


#: runs already made by :func:`every_nth`: (sequence folder, first stamp, frames, configuration, n) -> steps
_RUNS: dict = {}


def every_nth(seq: TumSequence, cfg: OdometryConfig, n: int) -> list:
    """The tracked steps of runs over every ``n``-th frame of ``seq``, one run per phase (each run
    made once: the tables share the default model's)."""
    from covo_gtsam.odometry import VisualOdometry

    key = (str(seq.path), float(seq.timestamps[0]), len(seq.timestamps), cfg, n)  # a part of a sequence too
    if key in _RUNS:
        return _RUNS[key]
    steps = _RUNS[key] = []
    for start in range(n):
        vo = VisualOdometry(seq.camera_name, cfg)
        for i in range(start, len(seq.timestamps), n):
            step = vo.register_frame(*seq.load(i), seq.timestamps[i], depth_timestamp=seq.depth_timestamps[i])
            if step.status == "tracked":
                steps.append(step)
    return steps


def stride_table(data: Path) -> list[str]:
    """The default model on fr1_rpy taken every 2nd and 3rd frame (all phases): pairs over two and
    three frame intervals, the motion of a faster turn or of a camera that drops frames."""
    seq = TumSequence(data / "tum" / RPY)
    lookup = ground_truth_lookup(seq)
    lines = ["## Larger motion between frames (every 2nd and 3rd frame)", "",
             "The default model (fitted on frames 0-119: the span term on that half's pairs over 2 and 3 "
             "intervals, the rest on its consecutive pairs) on fr1_rpy taken every n-th frame, "
             "each phase a run of its own: each pair spans n frame intervals, as in a turn n times as fast (the "
             "readout's and the clock's share do not grow) or a camera that drops frames.", "",
             "| every n-th frame | pairs | ANEES t / r | NEES > 9.35 t / r | largest NEES t / r |",
             "|---|---|---|---|---|"]
    for n in (1, 2, 3):
        T_est, T_true, covs = against_reference(seq, every_nth(seq, OdometryConfig(), n), lookup)
        nt, nr = anees_cells(relative_pose_tangent_errors(T_est, T_true), covs)
        lines.append(f"| {n} | {len(nt)} | {nt.mean():.2f} / {nr.mean():.2f} | {100 * np.mean(nt > 9.35):.0f} % / "
                     f"{100 * np.mean(nr > 9.35):.0f} % | {nt.max():.1f} / {nr.max():.1f} |")
    return lines + [""]


def span_table(data: Path) -> list[str]:
    """The span term fitted with the rest of the default model on one half of fr1_rpy
    (:func:`covo_gtsam.pipeline.calibrate_sequence`: the consecutive pairs, then the pairs of runs
    over every 2nd and 3rd frame) and checked on the other half (every 2nd and 3rd frame, frame to
    frame, keyframe mode) and on fr1_desk's keyframe pairs, with and without the span term."""
    from covo_gtsam.pipeline import calibrate_sequence

    seq = TumSequence(data / "tum" / RPY)
    desk = TumSequence(data / "tum" / DESK)
    sd = np.deg2rad(reference_statistics(seq.gt_samples)["rotation_deg"])
    halves = {"A": (0, 120), "B": (120, len(seq))}

    def anees(part: TumSequence, steps: list, span_bins: bool = False) -> str:
        lookup = ground_truth_lookup(part)
        pairs = pairs_with_truth([s for s in steps if s.has_relative_pose], lookup)
        T_est, T_true, covs = against_reference(part, pairs, lookup)
        nt, nr = anees_cells(relative_pose_tangent_errors(T_est, T_true), covs)
        if not span_bins:
            return f"{nt.mean():.2f} / {nr.mean():.2f}"
        k = np.array([OdometryConfig().frame_intervals(s.timestamp - s.ref_timestamp) for s in pairs])
        cells = [f"{nt[(k >= lo) & (k <= hi)].mean():.2f}" if np.any((k >= lo) & (k <= hi)) else "—"
                 for lo, hi in ((1, 1), (2, 3), (4, 6), (7, 10**6))]
        return f"{nt.mean():.2f} / {nr.mean():.2f} ({' / '.join(cells)})"

    def keyframe_run(part: TumSequence, cfg: OdometryConfig) -> list:
        return every_nth(part, cfg.replace(tracking={"keyframes": True}), 1)

    lines = ["## Pairs over more than one interval: the span term", "",
             "The default model fitted on one half of fr1_rpy as `covo calibrate` fits it (the consecutive pairs; "
             "then the span term on the pairs of runs over every 2nd and 3rd frame, the other terms held) and "
             "checked on the other half: every 2nd and 3rd frame (all phases), frame to frame, and keyframe mode; "
             "then fr1_desk in keyframe mode (its 8 pairs all against its first frame, 1-8 intervals, "
             "a camera moving about three times as far per interval). ANEES t / r; keyframe mode also the "
             "translation ANEES of pairs over 1 / 2-3 / 4-6 / 7 or more intervals. With the fitted span "
             "factor and, for comparison, with it set to 0.", "",
             "| fitted on | span factor (pairs) | span term | checked on | every 2nd | every 3rd | frame to frame | "
             "keyframe mode | fr1_desk, keyframe mode |", "|---|---|---|---|---|---|---|---|---|"]
    for name, (lo, hi) in halves.items():
        other = "B" if name == "A" else "A"
        with tempfile.TemporaryDirectory() as tmp:
            fit, _ = calibrate_sequence(seq.frames(lo, hi), tmp, reference_sd=sd, progress=False)
        check = seq.frames(*halves[other])
        for label, span in (("fitted", fit.sigmas["span"]), ("0", 0.0)):
            cfg = OdometryConfig().replace(sensor={**fit.config_values(), "span_factor": span})
            strided = [anees(check, every_nth(check, cfg, n)) for n in (2, 3)]
            cells = " | ".join(strided + [anees(check, every_nth(check, cfg, 1)),
                                          anees(check, keyframe_run(check, cfg), True),
                                          anees(desk, keyframe_run(desk, cfg), True)])
            lines.append(f"| {name} | {fit.sigmas['span']:.3f} ({fit.span_pairs}) | {label} | {other} | {cells} |")
    return lines + [""]


def motion_table(data: Path) -> list[str]:
    """The default model's ANEES on fr1_rpy (every n-th frame, as :func:`stride_table`) by the pair's
    angular speed times its larger colour-depth offset, and by its angular speed alone."""
    seq = TumSequence(data / "tum" / RPY)
    lookup = ground_truth_lookup(seq)
    offset = dict(zip(seq.timestamps, np.asarray(seq.depth_timestamps) - np.asarray(seq.timestamps)))
    cells: dict = {}
    for n in (1, 2, 3):
        steps = pairs_with_truth(every_nth(seq, OdometryConfig(), n), lookup)
        T_est, T_true, covs = against_reference(seq, steps, lookup)
        nt, nr = anees_cells(relative_pose_tangent_errors(T_est, T_true), covs)
        w = (np.linalg.norm(se3_log(T_est)[:, :3], axis=1)
             / np.array([s.timestamp - s.ref_timestamp for s in steps]))
        d = np.array([max(offset[s.ref_timestamp], offset[s.timestamp]) for s in steps])
        for label, x, edges in (("angular speed x colour-depth offset (rad)", w * d, (0.0, 0.005, 0.01, np.inf)),
                                ("angular speed (rad/s)", w, (0.0, 0.5, 1.5, np.inf))):
            for lo, hi in zip(edges[:-1], edges[1:]):
                m = (x >= lo) & (x < hi)
                key = (label, f"{lo:g}-{hi:g}" if np.isfinite(hi) else f"above {lo:g}")
                cells.setdefault(key, []).append(
                    f"{nt[m].mean():.2f} / {nr[m].mean():.2f} ({m.sum()})" if m.any() else "—")
    lines = ["## By the motion: angular speed and colour-depth offset", "",
             "The default model's ANEES t / r (pairs) on fr1_rpy taken every n-th frame (as above), by the pair's "
             "estimated angular speed (its rotation over its interval) times the larger of its two frames' stamped "
             "colour-depth offsets, and by the angular speed alone.", "",
             "| binned by | bin | every frame | every 2nd | every 3rd |", "|---|---|---|---|---|"]
    lines += [f"| {label} | {b} | {' | '.join(v)} |" for (label, b), v in cells.items()]
    return lines + [""]


def default_motion(data: Path) -> tuple:
    """The default model on the consecutive pairs of fr1_rpy with ground truth: the sequence, the
    pairs, their NEES t and r (against the reference with its jitter) and their true angular speed
    and acceleration (:func:`covo_gtsam.nees_breakdown.true_motion`)."""
    seq = TumSequence(data / "tum" / RPY)
    lookup = ground_truth_lookup(seq)
    steps = pairs_with_truth(every_nth(seq, OdometryConfig(), 1), lookup)
    T_est, T_true, covs = against_reference(seq, steps, lookup)
    nt, nr = anees_cells(relative_pose_tangent_errors(T_est, T_true), covs)
    speed, accel = true_motion(T_true, [s.ref_timestamp for s in steps], [s.timestamp for s in steps])
    return seq, steps, nt, nr, speed, accel


def acceleration_table(data: Path) -> list[str]:
    """The default model's ANEES on consecutive pairs of fr1_rpy by the true angular acceleration
    (:func:`covo_gtsam.nees_breakdown.true_motion`, as ``metrics.json``'s ``nees_breakdown``)."""
    seq, steps, nt, nr, _, accel = default_motion(data)
    index = {t: i for i, t in enumerate(seq.timestamps)}
    end = np.array([index[s.timestamp] for s in steps])
    halves = (("frames 1-119", end <= 119), ("frames 120-239", end >= 120), ("all", end >= 0))
    cols = [by_bins(np.where(m, accel, np.nan), ACCELERATION_EDGES, nr, nt) for _, m in halves]
    lines = ["## By the true angular acceleration", "",
             "The default model's ANEES t / r (pairs) on the consecutive pairs of fr1_rpy, by the change of the true "
             "angular velocity from the pair before over the interval (rad/s^2; metrics.json's nees_breakdown). A "
             "consistent model gives about 3 in every bin.", "",
             "| angular acceleration (rad/s^2) | " + " | ".join(label for label, _ in halves) + " |",
             "|---" * (len(halves) + 1) + "|"]
    for i, b in enumerate(cols[0]):
        lo, hi = b["range"]
        cells = [f"{c[i]['anees_translation']:.2f} / {c[i]['anees_rotation']:.2f} ({c[i]['pairs']})"
                 if c[i]["pairs"] else "—" for c in cols]
        lines.append(f"| {lo:g}-{hi:g} | " if hi is not None else f"| above {lo:g} | ")
        lines[-1] += " | ".join(cells) + " |"
    return lines + [""]


def whole_sequence_table(data: Path) -> list[str]:
    """The motion of all of fr1_rpy, from its ground-truth file (which covers the whole sequence,
    not only the shared 240 frames): per block of 60 pairs at the frames' period, the mean true
    angular speed, the pairs above 2 rad/s, and the ANEES the shared frames' ANEES by angular
    acceleration (:func:`acceleration_table`'s bins, all pairs but the run's start) would give with
    that block's accelerations: where the shared frames do not cover the motion, and what to expect."""
    from covo_gtsam.datasets.tum import interpolate_poses
    from covo_gtsam.geometry import invert_pose
    from covo_gtsam.io import load_tum_trajectory

    seq, _, nt, nr, shared_speed, accel = default_motion(data)
    # the pairs before the twist history holds its changes are a run's start, which the rest of the
    # sequence does not have: they do not enter the bins
    start = OdometryConfig().sensor.twist_history + 1
    mid_run = np.where(np.arange(len(accel)) >= start, accel, np.nan)
    shared = by_bins(mid_run, ACCELERATION_EDGES, nr, nt)
    # by_bins of the indicators NEES > 9.35: its "anees_*" are each bin's share of NEES above chi2(3)'s 97.5 % quantile
    above = by_bins(mid_run, ACCELERATION_EDGES, (nr > 9.35).astype(float), (nt > 9.35).astype(float))
    t, P = load_tum_trajectory(seq.path / "groundtruth.txt")
    period = float(np.median(np.diff(seq.timestamps)))
    stamps = seq.timestamps[0] + period * np.arange(int((t[-1] - seq.timestamps[0]) / period))
    G, ok = interpolate_poses(t, P, stamps, 0.1)
    T = invert_pose(G[:-1]) @ G[1:]
    speed, acc = true_motion(T, stamps[:-1], stamps[1:])
    both = ok[:-1] & ok[1:]  # a pair with the ground truth at both frames (no gap in the reference)
    speed[~both] = np.nan
    acc[~(both & np.r_[False, both[:-1]])] = np.nan
    lines = ["## The rest of fr1_rpy, by its ground truth", "",
             f"fr1_rpy's ground-truth file covers the whole sequence ({t[-1] - t[0]:.1f} s; the shared frames are its "
             f"first {seq.timestamps[-1] - seq.timestamps[0]:.1f} s). Its pairs at the frames' period "
             f"({1e3 * period:.1f} ms), in blocks of 60: the mean true angular speed, the pairs above 2 rad/s, and "
             "the ANEES t / r that the shared frames' ANEES by angular acceleration (table above, all pairs but "
             f"the run's first {start}, before its twist history is full: the rest of the sequence has no such "
             "start) gives for the block's accelerations. Not a measurement of those frames: where the shared "
             f"frames do not cover the motion (the shared frames have {int(np.sum(shared_speed > 2))} pairs above "
             "2 rad/s), what the model's known dependence on the acceleration alone would make, and so the share "
             "of NEES above 9.35 "
             f"t / r (on the shared frames {100 * np.mean(nt > 9.35):.1f} / {100 * np.mean(nr > 9.35):.1f} %; 2.5 % "
             "when consistent).", "",
             "| pairs | mean angular speed (rad/s) | pairs above 2 rad/s | ANEES t / r expected from the "
             "acceleration | NEES above 9.35 t / r expected (%) |", "|---|---|---|---|---|"]

    def row(label: str, a: np.ndarray, w: np.ndarray) -> str:
        """The table's row of a stretch of pairs with true accelerations ``a`` and speeds ``w``: the
        shared bins' ANEES and shares above 9.35, weighted by the stretch's pairs per bin."""
        n = [b["pairs"] for b in by_bins(a, ACCELERATION_EDGES, np.zeros(len(a)), np.zeros(len(a)))]
        et, er, st, sr = (sum(k * b[key] for k, b in zip(n, bins) if k) / max(sum(n), 1)
                          for bins in (shared, above) for key in ("anees_translation", "anees_rotation"))
        return (f"| {label} | {np.nanmean(w):.2f} | {int(np.sum(w > 2))} | {et:.2f} / {er:.2f} | "
                f"{100 * st:.1f} / {100 * sr:.1f} |")

    for start in range(0, len(T) - 30, 60):
        a, w = acc[start:start + 60], speed[start:start + 60]
        lines.append(row(f"{start}-{start + len(w) - 1}", a, w))
    lines.append(row("240 on (the frames not shared)", acc[240:], speed[240:]))
    return lines + [""]


def speed_term_table(data: Path) -> list[str]:
    """The default terms; the same with one more, a rotation error per axis growing with the pair's
    estimated angular speed, ``sigma^2 |omega|^2 I`` (a timing error of the whole frame, the same about
    every axis); that term instead of the frame term; and neither. Fitted on one half of fr1_rpy and
    checked on the other and on fr1_desk."""
    from covo_gtsam.calibration import log_likelihood

    def with_speed(p: dict) -> dict:
        w2 = np.sum((se3_log(p["T_est"])[:, :3] * 30.0) ** 2, axis=1)  # (rad/s)^2, 30 Hz pairs
        B = np.zeros((len(w2), 6, 6))
        B[:, [0, 1, 2], [0, 1, 2]] = w2[:, None]
        return {**p, "bases": {**p["bases"], "speed": B}}

    rpy, desk = with_speed(per_point_pairs(data, RPY)), with_speed(per_point_pairs(data, DESK))
    A = rpy["end"] <= 119
    models = {"default": (DEFAULT_TERMS, True), "default + speed": ((*DEFAULT_TERMS, "speed"), True),
              "speed instead of the frame term": ((*DEFAULT_TERMS, "speed"), False),
              "default without the frame term": (DEFAULT_TERMS, False)}
    held_out: dict[str, list] = {label: [] for label in models}  # (speed, rotation NEES) of the checks on fr1_rpy
    lines = ["## A rotation term growing with the angular speed", "",
             "The default terms; the same with one more, a rotation error of sigma times the pair's estimated "
             "angular speed about each axis (a whole frame's timing error, alike about every axis); that term in "
             "place of the frame term (a rotation error per frame interval, constant); and neither. Fitted on the "
             "consecutive pairs of one half of fr1_rpy. Log-likelihood per pair and ANEES t / r on each check.", "",
             "| fitted on | terms | frame term (deg) | speed term (ms) | latency (ms) | checked on | ANEES t / r | "
             "log-likelihood |", "|---|---|---|---|---|---|---|---|"]
    for name, mask in (("A", A), ("B", ~A)):
        train = subset(rpy, mask & rpy["fit_ok"])
        for label, (terms, frame) in models.items():
            fit = fit_sensor_terms(train["err"], train["cov"], False, bases={n: train["bases"][n] for n in terms},
                                   fixed=train["fixed"], frame_rotation=frame)
            speed = f"{1e3 * fit.sigmas['speed']:.2f}" if "speed" in terms else "—"
            for check, held in (("A" if name == "B" else "B", subset(rpy, ~mask)), ("fr1_desk", desk)):
                covs = fit.covariances(held["cov"], {n: held["bases"][n] for n in terms}) + held["fixed"]
                nt, nr = anees_cells(held["err"], covs)
                if check != "fr1_desk":
                    held_out[label].append((true_motion(held["T_true"], held["t_ref"], held["t_cur"])[0], nr))
                lines.append(f"| {name} | {label} | {fit.frame_sigma_rot_deg:.3f} | {speed} | "
                             f"{1e3 * fit.sigmas['latency']:.2f} | {check} | {nt.mean():.2f} / {nr.mean():.2f} | "
                             f"{log_likelihood(held['err'], covs):.2f} |")
    edges = (0.0, 0.5, 0.8, 1.2, 1.6, np.inf)
    lines += ["", "Where the rotation error goes with the speed: the rotation ANEES of fr1_rpy's pairs by their true "
              "angular speed (rad/s), each half under the fit on the other (pairs per bin in brackets).", "",
              "| terms | " + " | ".join(f"{lo:g}-{hi:g}" if np.isfinite(hi) else f"{lo:g}+"
                                      for lo, hi in zip(edges[:-1], edges[1:])) + " |",
              "|---|" + "---|" * (len(edges) - 1)]
    for label in ("default", "speed instead of the frame term", "default without the frame term"):
        speed, nr = (np.concatenate(v) for v in zip(*held_out[label]))
        cells = [f"{nr[m].mean():.2f} ({m.sum()})" for m in ((speed >= lo) & (speed < hi)
                                                            for lo, hi in zip(edges[:-1], edges[1:]))]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return lines + [""] + twist_change_lines(rpy) + frame_term_lines(rpy) + jerk_lines(data, rpy)


def second_change_basis(p: dict, T: np.ndarray, history: int | None) -> np.ndarray:
    """Per pair (N, 6, 6), rotation block: the outer product of the second difference of the pairs'
    mean angular velocities from poses ``T`` (N, 4, 4), ``d = w_(k+1) - 2 w_k + w_(k-1)`` (rad/s),
    centred on the pair (one frame late, as the latency term's look-ahead): the pair's own
    (``history`` None; the reference's, exact but for its jitter) or the mean over the ``history``
    pairs before it, less the run's own noise (the per-point model's ``N_(k+1) + 4 N_k + N_(k-1)``),
    clipped to positive semidefinite (the run's own, as the latency term's history)."""
    n, dt = len(T), p["t_cur"] - p["t_ref"]
    follows = np.r_[False, p["end"][1:] == p["end"][:-1] + 1]
    w = se3_log(T)[:, :3] / dt[:, None]
    noise = p["cov"][:, :3, :3] / dt[:, None, None] ** 2
    out, recent = np.zeros((n, 6, 6)), []
    for k in range(n):
        inner = 1 <= k < n - 1 and follows[k] and follows[k + 1]
        if inner:
            d = w[k + 1] - 2 * w[k] + w[k - 1]
            own = np.outer(d, d)
        if history is None:
            out[k, :3, :3] = own if inner else 0.0
            continue
        if recent:
            ev, V = np.linalg.eigh(np.mean(recent, axis=0))
            out[k, :3, :3] = (V * np.clip(ev, 0.0, None)) @ V.T
        if inner:
            recent = (recent + [own - noise[k + 1] - 4 * noise[k] - noise[k - 1]])[-history:]
        elif not follows[k]:
            recent = []
    return out


def jerk_lines(data: Path, rpy: dict) -> list[str]:
    """The default terms with one more, ``sigma^2 d d^T`` on the second difference ``d`` of the pairs'
    angular velocities (:func:`second_change_basis`), from the reference (raw, or smoothed over 20 and
    35 ms: :class:`~covo_gtsam.sequence_simulation.RecordedMotion`) or from the run's own twists;
    fitted on one half of fr1_rpy and checked on the other."""
    from covo_gtsam.calibration import log_likelihood
    from covo_gtsam.sequence_simulation import RecordedMotion

    stamps, poses = TumSequence(data / "tum" / RPY).gt_samples
    sources: dict[str, np.ndarray | None] = {"none (the default terms)": None,
                                             "the reference's, the pair's own": second_change_basis(
                                                 rpy, rpy["T_true"], None)}
    for smooth in (0.02, 0.035):
        motion = RecordedMotion(stamps, poses, smooth_s=smooth)
        at = {t: motion.pose(t - stamps[0]).matrix() for t in np.unique(np.r_[rpy["t_ref"], rpy["t_cur"]])}
        T = np.array([np.linalg.inv(at[a]) @ at[b] for a, b in zip(rpy["t_ref"], rpy["t_cur"])])
        sources[f"the reference smoothed over {1e3 * smooth:.0f} ms, the pair's own"] = second_change_basis(
            rpy, T, None)
    sources["the run's own, the pair's"] = second_change_basis(rpy, rpy["T_est"], None)
    sources["the run's own, the 10 pairs before, less their noise"] = second_change_basis(rpy, rpy["T_est"], 10)
    lines = ["## The frame term and the change of the angular acceleration", "",
             "The default terms with one more, `sigma^2 d d^T` (rotation block) on the second difference `d` of "
             "the pairs' mean angular velocities centred on the pair (the change of the angular acceleration over "
             "a frame interval, times dt^2), fitted on one half of fr1_rpy and checked on the other. The "
             "realistic simulation driven by fr1_rpy's recorded motion finds the compensated readout's error "
             "growing with it (docs/recorded_motion.md). From the reference, `d` carries the reference's jitter, "
             "which is in the pairs' errors too; smoothed over 20 ms (the motion up to about 8 Hz kept) or 35 ms "
             "(about 4.5 Hz) less of it.", "",
             "| d from | fitted on | frame term (deg) | sigma (ms) | checked on | ANEES t / r | log-likelihood "
             "held out |", "|---|---|---|---|---|---|---|"]
    halves = {"A": rpy["end"] <= 119, "B": rpy["end"] >= 120}
    for label, J in sources.items():
        p = rpy if J is None else {**rpy, "bases": {**rpy["bases"], "jerk": J}}
        terms = list(DEFAULT_TERMS) + ([] if J is None else ["jerk"])
        for name, m in halves.items():
            train = subset(p, m & p["fit_ok"])
            fit = fit_sensor_terms(train["err"], train["cov"], False, bases={t: train["bases"][t] for t in terms},
                                   fixed=train["fixed"])
            held = subset(p, ~m)
            covs = fit.covariances(held["cov"], {t: held["bases"][t] for t in terms}) + held["fixed"]
            nt, nr = anees_cells(held["err"], covs)
            lines.append(f"| {label} | {name} | {fit.frame_sigma_rot_deg:.3f} | "
                         f"{1e3 * fit.sigmas.get('jerk', 0.0):.2f} | {'B' if name == 'A' else 'A'} | "
                         f"{nt.mean():.2f} / {nr.mean():.2f} | {log_likelihood(held['err'], covs):.3f} |")
    return lines + [""]


def frame_term_lines(p: dict) -> list[str]:
    """The rotation frame term fitted by maximum likelihood (every other term at its default) on groups of
    fr1_rpy's consecutive pairs: blocks of 60 pairs, and thirds by the pair's angular acceleration, true
    or as the run can estimate it (from the pair's own twist and the one before, or across the pair from
    the twists before and after it, one frame later)."""
    s = OdometryConfig().sensor
    k = np.flatnonzero(p["fit_ok"] & (np.r_[-1, p["end"][:-1]] == p["end"] - 1))
    k = k[(k >= 1) & (k < len(p["end"]) - 1)]
    # the prior terms are in p["fixed"] already
    sigmas = {name: sigma for name, sigma in s.term_sigmas().items() if name not in PRIOR_TERMS}
    others = sensor_covariance(np.zeros_like(p["cov"]), 0.0, 0.0, s.frame_sigma_trans_m, 1, p["bases"],
                               sigmas) + p["fixed"]
    dt = p["t_cur"] - p["t_ref"]
    accel = {"true": true_motion(p["T_true"], p["t_ref"], p["t_cur"])[1],
             "estimated from the pair's own twist and the one before": true_motion(p["T_est"], p["t_ref"],
                                                                                  p["t_cur"])[1]}
    w_est = se3_log(p["T_est"])[:, :3] / dt[:, None]
    across = np.full(len(dt), np.nan)  # where the pair after follows this one too
    after = k[p["end"][k + 1] == p["end"][k] + 1]
    across[after] = np.linalg.norm(w_est[after + 1] - w_est[after - 1], axis=1) / (dt[after - 1] + dt[after + 1])
    accel["estimated across the pair, from the twists before and after it"] = across

    def frame_deg(m: np.ndarray) -> str:
        fit = fit_sensor_terms(p["err"][m], s.correlation_factor * p["cov"][m], False, fixed=others[m])
        return f"{fit.frame_sigma_rot_deg:.3f}"

    lines = ["## Where the frame term's need lies", "",
             "The rotation frame term (deg per axis and frame interval; the default "
             f"{s.frame_sigma_rot_deg:.3f}, fitted on frames 0-119) fitted by maximum likelihood on groups of "
             "fr1_rpy's consecutive pairs, every other term at its default (the translation's frame term fitted "
             "along): blocks of up to 60 pairs with the RMS of their true angular acceleration, and thirds of the "
             "pairs by their angular acceleration, true (from the reference, whose jitter is in the pairs' "
             "errors too) or as the run can estimate it. A frame term that followed the run's motion would grow "
             "with the blocks' acceleration or with the run's own estimates of it.", "",
             "| pairs | true angular acceleration, RMS (rad/s^2) | frame term (deg) |", "|---|---|---|"]
    for a in range(0, len(k), 60):
        m = k[a:a + 60]
        lines.append(f"| frames {p['end'][m[0]]}-{p['end'][m[-1]]} | {np.sqrt(np.mean(accel['true'][m] ** 2)):.1f} | "
                     f"{frame_deg(m)} |")
    lines += ["", "| thirds by the angular acceleration | lowest | middle | highest |", "|---|---|---|---|"]
    for label, a in accel.items():
        known = k[np.isfinite(a[k])]
        edges = np.quantile(a[known], [0.0, 1 / 3, 2 / 3, 1.0])
        third = np.clip(np.searchsorted(edges, a[known], side="right") - 1, 0, 2)
        thirds = [known[third == i] for i in range(3)]
        lines.append(f"| {label} | " + " | ".join(f"{frame_deg(m)} ({edges[i]:.1f}-{edges[i + 1]:.1f} rad/s^2)"
                                                  for i, m in enumerate(thirds)) + " |")
    return lines + [""]


def twist_change_lines(p: dict) -> list[str]:
    """The consecutive pairs' rotation error against the change of the pair's rotation from the
    pair before, ``w_k - w_(k-1)`` (``w`` the rotation vector of a pair), true and estimated: the
    least-squares factor ``c`` of ``error = c (w_k - w_(k-1))`` over the three axes and the share
    of the error's variance it explains."""
    w_true, w_est = se3_log(p["T_true"])[:, :3], se3_log(p["T_est"])[:, :3]
    lines = ["## The rotation error against the change of the pair's rotation", "",
             "The rotation error of a pair (the truth minus the estimate) against the change of the pair's rotation "
             "from the pair before, true or estimated by the run: the factor `c` of `error = c (w_k - w_(k-1))` "
             "fitted over the three axes and the share of the error's variance it explains; the RMS per axis of "
             "the true change and of the estimated change's own error.", "",
             "| pairs | c, true change | explained | c, estimated change | explained | true change RMS (deg) | "
             "its estimate's error RMS (deg) |", "|---|---|---|---|---|---|---|"]
    for label, lo, hi in (("frames 1-119", 1, 119), ("frames 120-239", 120, 239)):
        k = np.flatnonzero((p["end"] >= lo) & (p["end"] <= hi) & (np.r_[-1, p["end"][:-1]] == p["end"] - 1))
        y = p["err"][k, :3].ravel()
        cells = []
        for w in (w_true, w_est):
            x = (w[k] - w[k - 1]).ravel()
            c = x @ y / (x @ x)
            cells.append(f"{c:+.2f} | {1 - np.sum((y - c * x) ** 2) / np.sum(y**2):.2f}")
        true, est = w_true[k] - w_true[k - 1], w_est[k] - w_est[k - 1]
        lines.append(f"| {label} | {' | '.join(cells)} | {np.rad2deg(np.sqrt(np.mean(true**2))):.3f} | "
                     f"{np.rad2deg(np.sqrt(np.mean((est - true) ** 2))):.3f} |")
    return lines + [""]


def closure_table(data: Path) -> list[str]:
    """Closures of overlapping pairs on fr1_rpy: the pairs (k-1, k) and (k, k+1) of a frame-to-frame run
    against the pair (k-1, k+1) of a run over every other frame, ``d = Log(T_skip^-1 T_a T_b)``; the
    NEES of ``d`` under the chain's and the skip pair's covariances taken as independent, per model,
    beside the same model's ANEES against the ground truth (consecutive pairs)."""
    import gtsam

    seq = TumSequence(data / "tum" / RPY)
    lookup = ground_truth_lookup(seq)
    lines = ["## Closures of overlapping pairs (no ground truth)", "",
             "Each frame k of fr1_rpy closes a loop: the frame-to-frame pairs (k-1, k) and (k, k+1) against "
             "the pair (k-1, k+1) of a run over every other frame. The closure's NEES takes the chain's and "
             "the skip pair's covariances as independent (they share the keypoints of frames k-1 and k+1, so "
             "the closures are if anything smaller than that). What a closure cannot show: any error that "
             "moves a frame's pose as a whole cancels in it: timing, a delay, the ground truth's own error, "
             "and the part of frame k's point noise that moves where frame k appears to be.",
             "", "| model | closures | closure ANEES t / r (median) | consecutive pairs against the ground truth: "
             "ANEES t / r |", "|---|---|---|---|"]
    for label, sensor in (("per-point model alone", POINTS_ONLY), ("default", {})):
        cfg = OdometryConfig().replace(sensor=sensor)
        consecutive = {s.timestamp: s for s in every_nth(seq, cfg, 1)}  # by the frame each pair ends in
        d, S = [], []
        for skip in every_nth(seq, cfg, 2):
            b = consecutive.get(skip.timestamp)
            a = None if b is None else consecutive.get(b.ref_timestamp)
            if a is None or a.ref_timestamp != skip.ref_timestamp:
                continue  # a frame lost in either run: no closure over these frames
            chain = compose_covariance(a.relative, a.covariance, b.relative, b.covariance)
            d.append(gtsam.Pose3.Logmap(skip.relative.between(a.relative.compose(b.relative))))
            S.append(chain + skip.covariance)
        nt, nr = anees_cells(np.array(d), np.array(S))
        T_est, T_true, covs = against_reference(seq, list(consecutive.values()), lookup)
        gt, gr = anees_cells(relative_pose_tangent_errors(T_est, T_true), covs)
        lines.append(f"| {label} | {len(d)} | {nt.mean():.2f} / {nr.mean():.2f} ({np.median(nt):.2f} / "
                     f"{np.median(nr):.2f}) | {gt.mean():.2f} / {gr.mean():.2f} |")
    return lines + [""]


def reference_table(data: Path) -> list[str]:
    """The ground truth's own noise, and the default model fitted with it as a known term: what
    the frame term is once the reference's jitter is taken out of it."""

    lines = ["## The ground truth's own noise", "",
             "The freiburg1 reference jitters from sample to sample (`covo_gtsam.reference_noise`, from the "
             "ground-truth file alone; `reference_jitter` in `metrics.json`). Per sample, about the camera's "
             "x / y / z axes; then the default model fitted on one half of fr1_rpy with that jitter as a known "
             "term of each pair's covariance (interpolated at the frame stamps; the default, as everywhere in this "
             "document) and, for comparison, with the jitter left to the frame term, checked on the other half "
             "(the known term added back).", "",
             "| sequence | rotation jitter per sample (deg) | share of the pairs' rotation error variance x / y / z |",
             "|---|---|---|"]
    parts = {}
    for name in (RPY, DESK):
        seq = TumSequence(data / "tum" / name)
        p = per_point_pairs(data, name)
        sd, ref = np.deg2rad(reference_statistics(seq.gt_samples)["rotation_deg"]), p["ref"]
        parts[name] = (p, ref)
        share = np.diagonal(ref, axis1=1, axis2=2)[:, :3].mean(axis=0) / np.mean(p["err"][:, :3] ** 2, axis=0)
        lines.append(f"| {name} | {' / '.join(f'{v:.3f}' for v in np.rad2deg(sd))} | "
                     f"{' / '.join(f'{100 * v:.0f} %' for v in share)} |")
    lines += ["", "| fitted on | reference jitter | frame term (deg) | latency (ms) | log-likelihood in sample | "
              "checked on | ANEES t / r | log-likelihood held out |", "|---|---|---|---|---|---|---|---|"]
    rpy, ref = parts[RPY]
    halves = {"A": rpy["end"] <= 119, "B": rpy["end"] >= 120}
    for name, m in halves.items():
        for label, extra in (("in the frame term", 0.0 * ref), ("a known term", ref)):
            fit, held = fit_half({**rpy, "fixed": rpy["fixed"] - ref + extra}, m)
            lines.append(f"| {name} | {label} | {fit.frame_sigma_rot_deg:.3f} | {1e3 * fit.sigmas['latency']:.2f} | "
                         f"{fit.log_likelihood:.2f} | {'B' if name == 'A' else 'A'} | {held} |")
    return lines + [""]


def frame_noise_table(data: Path) -> list[str]:
    """Errors of single frames: the share of consecutive pairs' rotation errors that one frame's
    error makes (it enters the pair ending there and, with the opposite sign, the next one), per
    axis, for covo, OpenCV's dense RGB-D odometry and what the two share; against the reference's
    jitter at the frames, and the frame-to-frame roughness of the ground truth and of covo's
    trajectory at the frame stamps."""
    import cv2

    from covo_gtsam.geometry import invert_pose
    from covo_gtsam.reference_noise import reference_jitter

    lines = ["## Errors of single frames", "",
             "An error of one frame's pose (the reference's, the camera's) enters the pair ending at that frame and, "
             "with the opposite sign, the next pair: consecutive pairs' errors then anticorrelate, and "
             "-E[e_k e_k+1] is that error's variance per frame. Per axis x / y / z, in degrees as s.d. per frame "
             "(0 where the pairs' errors correlate positively): covo's consecutive pairs (default model, poses at "
             "the stamps), OpenCV's dense RGB-D odometry on the same pairs (as in 'What an independent estimator "
             "shares'), and what the two have in common (-E[covo e_k x OpenCV e_k+1], symmetrised); the reference's "
             "sample jitter as metrics.json measures it, interpolated at the frames; and the roughness at the frame "
             "stamps (`reference_jitter` with two neighbours on either side, applied to the ground truth at the "
             "frames and to covo's trajectory, both at about 30 Hz, which leaves the same unfollowed motion in both).",
             ""]
    if not hasattr(cv2, "Odometry"):
        return lines + [f"Not computed: OpenCV {cv2.__version__} has no `cv2.Odometry` (OpenCV 5's RGB-D odometry).",
                        ""]
    lines += ["| pairs | n | per frame: covo | OpenCV | common | reference jitter at the frames | roughness at the "
              "frames: ground truth | covo's trajectory |", "|---|---|---|---|---|---|---|---|"]
    seq = TumSequence(data / "tum" / RPY)
    lookup = ground_truth_lookup(seq)
    index = {t: i for i, t in enumerate(seq.timestamps)}
    steps = every_nth(seq, OdometryConfig(), 1)
    ours = {index[s.timestamp]: s.relative.matrix() for s in steps
            if s.status == "tracked" and index.get(s.ref_timestamp) == index[s.timestamp] - 1}
    theirs = opencv_pairs(seq, lookup)
    ends = np.array(sorted(set(ours) & set(theirs)))
    true = np.array([invert_pose(lookup[seq.timestamps[k - 1]]) @ lookup[seq.timestamps[k]] for k in ends])
    x = np.rad2deg(relative_pose_tangent_errors(np.array([ours[k] for k in ends]), true)[:, :3])
    y = np.rad2deg(relative_pose_tangent_errors(np.array([theirs[k] for k in ends]), true)[:, :3])
    ref = reference_covariances(seq.gt_samples)(seq.timestamps[ends - 1], seq.timestamps[ends])
    posed = {index[s.timestamp]: s.pose.matrix() for s in steps if s.has_pose}
    frames = np.array(sorted(k for k in posed if seq.timestamps[k] in lookup))
    first = lookup[seq.timestamps[frames[0]]] @ invert_pose(posed[frames[0]])  # covo's world in the reference's

    def sd(v: np.ndarray) -> str:
        return " / ".join(f"{np.sqrt(max(c, 0.0)):.3f}" for c in v)

    for label, lo, hi in (("frames 1-119", 1, 119), ("frames 120-239", 120, 239), ("all", 1, 239)):
        m = (ends >= lo) & (ends <= hi)
        k = np.flatnonzero(m)
        k = k[:-1][np.diff(ends[k]) == 1]  # pairs followed by the next pair
        lag = {n: -np.mean(a[k] * b[k + 1], axis=0) for n, (a, b) in {"covo": (x, x), "cv": (y, y)}.items()}
        common = -0.5 * (np.mean(x[k] * y[k + 1], axis=0) + np.mean(y[k] * x[k + 1], axis=0))
        white = np.rad2deg(np.sqrt(np.diagonal(ref[m], axis1=1, axis2=2)[:, :3].mean(axis=0) / 2))
        f = frames[(frames >= lo - 1) & (frames <= hi)]
        t = seq.timestamps[f]
        rough = [np.rad2deg(reference_jitter(t, P, 2)["rotation_rad"]) for P in
                 (np.array([lookup[seq.timestamps[j]] for j in f]), np.array([first @ posed[j] for j in f]))]
        lines.append(f"| {label} | {len(k)} | {sd(lag['covo'])} | {sd(lag['cv'])} | {sd(common)} | "
                     f"{' / '.join(f'{v:.3f}' for v in white)} | {' / '.join(f'{v:.3f}' for v in rough[0])} | "
                     f"{' / '.join(f'{v:.3f}' for v in rough[1])} |")
    return lines + [""]


def persistence_table(data: Path) -> list[str]:
    """How much larger the errors of chains of consecutive pairs are than independent pairs' errors
    would make them: mean squared chain error over the mean of the sum of its pairs' squared errors,
    per half of fr1_rpy. 1 for independent pairs; above 1 where errors persist from pair to pair."""
    p = per_point_pairs(data, RPY)
    lengths = (2, 5, 10, 30)
    lines = ["## Errors that persist from pair to pair", "",
             "Chains of consecutive pairs of fr1_rpy (frame to frame): the mean squared error of the composed "
             "chain over the mean of the sum of its pairs' squared errors, translation / rotation (1 for independent "
             "pairs, above 1 where a pair's error persists into the next ones, below 1 where the next pairs undo "
             "it). With independent between factors a chain's ANEES is about its pairs' ANEES times this ratio.", "",
             "| pairs | " + " | ".join(f"chains of {w}" for w in lengths) + " |", "|---" * (len(lengths) + 1) + "|"]
    for label, lo, hi in (("frames 1-119", 1, 119), ("frames 120-239", 120, 239), ("all", 1, 239)):
        m = (p["end"] >= lo) & (p["end"] <= hi)
        ratios = [persistence(p["T_est"][m], p["T_true"][m], p["end"][m], w) for w in lengths]
        cells = [f"{t:.2f} / {r:.2f}" for t, r in ratios]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return lines + [""]


#: windows of the depth-drift correction compared (pairs; 0: off) and the chain lengths (frames)
DRIFT_WINDOWS, DRIFT_LENGTHS = (0, 5, 10, 20, 30), (10, 30, 60, 120, 200)


def drift_table(data: Path) -> list[str]:
    """The depth's drift: the default model on fr1_rpy with the correction's window of 0 (off), 5,
    10 (the default), 20 and 30 pairs, per half (pair and 30-pair chain ANEES, the chains'
    translation RMS) and over all frames (translation RMS of chains of 10-200 pairs, ATE)."""
    seq = TumSequence(data / "tum" / RPY)
    lines = ["## The depth's drift", "",
             "Each pair's translation moved by the mean, over the last pairs, of the depth-free estimates' "
             "disagreement with the 3D-3D estimate along the pair's depth-scale response "
             "(`sensor.depth_drift_pairs`; 0: off; docs/derivation.md, \"The depth's drift\"). The default "
             "model (its terms fitted on frames 0-119 with the window of 10) on the consecutive pairs of fr1_rpy: "
             "ANEES t / r of the pairs and of chains of 30 (against the reference with its jitter) and the "
             "chains' translation RMS per half; over all pairs, the translation RMS of chains of 10 to 200 pairs "
             "and the ATE after alignment (`metrics.json`).", "",
             "| window (pairs) | frames 1-119: pairs / chains of 30 / chain RMS (mm) | frames 120-239: pairs / "
             "chains of 30 / chain RMS (mm) | chains of " + " / ".join(map(str, DRIFT_LENGTHS)) + ": RMS (mm) | "
             "ATE (m) |", "|---|---|---|---|---|"]
    for m in DRIFT_WINDOWS:
        cfg = OdometryConfig().replace(sensor={"depth_drift_pairs": m})
        with tempfile.TemporaryDirectory() as tmp:
            run = run_sequence(seq, tmp, config=cfg, plots=False, progress=False)
        p, covs = reported_pairs(seq, run.steps)
        T_est, T_true = p["T_est"], p["T_true"]
        cells = []
        for lo, hi in ((1, 119), (120, 239)):
            half = (p["end"] >= lo) & (p["end"] <= hi)
            h, h_covs = subset(p, half), covs[half]
            nt, nr = anees_cells(relative_pose_tangent_errors(h["T_est"], h["T_true"]), h_covs)
            ct, cr = chain_anees(h, h_covs)
            cells.append(f"{nt.mean():.2f} / {nr.mean():.2f}, {ct:.2f} / {cr:.2f}, "
                         f"{1e3 * chain_translation_rms(h['T_est'], h['T_true'], CHAIN):.1f}")
        lengths = " / ".join(f"{1e3 * chain_translation_rms(T_est, T_true, w):.1f}" for w in DRIFT_LENGTHS)
        lines.append(f"| {m} | {cells[0]} | {cells[1]} | {lengths} | {run.metrics['ate']['rmse']:.4f} |")
    return lines + [""]


def reported_pairs(seq: TumSequence, steps: list) -> tuple[dict, np.ndarray]:
    """The tracked pairs of ``steps`` with ground truth as :func:`chain_anees` takes them (poses,
    the reference's jitter per pair and its function of the stamps, end frames) and their reported
    covariances with that jitter added, as ``metrics.json``'s NEES adds it."""
    lookup = ground_truth_lookup(seq)
    jitter = reference_covariances(seq.gt_samples)
    index = {t: i for i, t in enumerate(seq.timestamps)}
    steps = pairs_with_truth(steps, lookup)
    T_est, T_true, covs = relative_ground_truth(steps, lookup)
    t_ref, t_cur = np.array([s.ref_timestamp for s in steps]), np.array([s.timestamp for s in steps])
    ref = jitter(t_ref, t_cur)
    return ({"T_est": T_est, "T_true": T_true, "ref": ref, "jitter": jitter, "t_ref": t_ref, "t_cur": t_cur,
             "end": np.array([index[t] for t in t_cur])}, covs + ref)


def opencv_reported(seq: TumSequence, p: dict) -> tuple[dict, np.ndarray]:
    """OpenCV's dense odometry (:func:`opencv_pairs`) on those pairs of ``p`` (:func:`reported_pairs`)
    it solved: ``p`` on them with OpenCV's poses as ``T_est``, and as its covariance its own errors'
    mean square per axis (rotation and translation blocks, one for all its pairs of ``seq``)."""
    theirs = opencv_pairs(seq, ground_truth_lookup(seq))
    o = subset(p, np.isin(p["end"], list(theirs)))
    o["T_est"] = np.array([theirs[k] for k in o["end"]])
    e = relative_pose_tangent_errors(o["T_est"], o["T_true"])
    covs = np.zeros((len(e), 6, 6))
    covs[:, :3, :3] = np.diag(np.mean(e[:, :3] ** 2, axis=0))
    covs[:, 3:, 3:] = np.diag(np.mean(e[:, 3:] ** 2, axis=0))
    return o, covs


#: the principal point's row of the fr1 colour camera (px): its calibration's, and 10 px either side
PRINCIPAL_ROWS = (245.3, 255.3, 265.3)


def axes_table(data: Path) -> list[str]:
    """The fixed rotation between the reference's axes and the camera's
    (:func:`covo_gtsam.reference_noise.axes_rotation`) fitted per half of fr1_rpy and on all its
    pairs (covo's and OpenCV's), with the 30-pair chains' rotation ANEES per half against the
    reference turned back by the fit on all pairs; then, against the reference as it is and turned
    back: every 2nd and 3rd frame, keyframe mode (fr1_rpy and fr1_desk), the sensor terms fitted on
    one half; and the fit with the camera's principal point moved up and down by 10 px."""
    seq = TumSequence(data / "tum" / RPY)
    halves = {"frames 1-119": (1, 119), "frames 120-239": (120, 239), "all": (1, 239)}

    def fits(p: dict, covs: np.ndarray) -> dict:
        return {label: axes_rotation(p["T_est"][m], p["T_true"][m], covs[m])
                for label, (lo, hi) in halves.items() for m in [(p["end"] >= lo) & (p["end"] <= hi)]}

    def turned_back(p: dict, d: np.ndarray) -> dict:
        D = axes_transform(d)
        return {**p, "T_true": np.linalg.inv(D) @ p["T_true"] @ D}

    def chains_r(p: dict, covs: np.ndarray, lo: int, hi: int) -> str:
        m = (p["end"] >= lo) & (p["end"] <= hi)
        return f"{chain_anees(subset(p, m), covs[m])[1]:.2f}"

    def angles(f: dict) -> str:
        return " / ".join(f"{a:+.2f} ± {s:.2f}" for a, s in
                          zip(np.rad2deg(f["rotation_rad"]), np.rad2deg(f["standard_error_rad"])))

    p, covs = reported_pairs(seq, every_nth(seq, OdometryConfig(), 1))
    fit = fits(p, covs)
    lines = ["## A fixed rotation between the reference's axes and the camera's", "",
             "A reference whose axes are the camera's turned by a fixed rotation `d` (a hand-eye calibration's "
             "error, or the camera's principal point) reports each pair as `D T D^-1`, a rotation error of "
             "about `d x w` for a turn `w`: small per pair, but it grows with a chain's net turn, which "
             "independent pairs' covariances do not. `d` fitted by generalized least squares on the "
             "consecutive pairs of fr1_rpy (default model, reported covariances with the reference's "
             "jitter; `covo_gtsam.reference_noise.axes_rotation`, `reference_axes` in `metrics.json`), about "
             "the camera's x / y / z axes with its standard errors (pairs taken as independent, scaled up by the "
             "fit's reduced chi-square where it exceeds 1), and the same for "
             "OpenCV's dense RGB-D odometry on the same pairs (table \"What an independent estimator shares\"; "
             "its covariance its own errors' mean square per axis); a component "
             "is observed only by turns about the other two axes, so each half of fr1_rpy, turning mostly about "
             "one axis, leaves that axis's component to the other half (and a fit on one half cannot be carried to "
             "the other). Then the rotation ANEES of the chains of "
             f"{CHAIN} pairs of each half, against the reference as it is and turned back by the fit on all pairs "
             "(in sample).", "",
             "| pairs | d (deg) x / y / z | RMS true turn per pair x / y / z (deg) | chains of 30, rotation ANEES: "
             "as it is / turned back |", "|---|---|---|---|"]
    turns = np.rad2deg(se3_log(p["T_true"])[:, :3])
    for label, (lo, hi) in halves.items():
        m = (p["end"] >= lo) & (p["end"] <= hi)
        rms = " / ".join(f"{v:.2f}" for v in np.sqrt(np.mean(turns[m] ** 2, axis=0)))
        cells = [chains_r(p, covs, lo, hi), chains_r(turned_back(p, fit["all"]["rotation_rad"]), covs, lo, hi)]
        lines.append(f"| {label} ({fit[label]['pairs']}) | {angles(fit[label])} | {rms} | {' / '.join(cells)} |")
    # an estimator of its own on the same pairs, its covariance its errors' mean square per axis
    for label, f in fits(*opencv_reported(seq, p)).items():
        lines.append(f"| OpenCV's dense odometry, {label} ({f['pairs']}) | {angles(f)} | — | — |")
    lines += ["", "Pairs over more intervals turn more: fr1_rpy taken every n-th frame (each phase a run of its own), "
              "rotation ANEES per half and over all pairs against the reference as it is / turned back by the fit "
              "on all consecutive pairs.", "",
              "| every n-th frame | frames 1-119 | frames 120-239 | all |", "|---|---|---|---|"]
    for n in (1, 2, 3):
        q, q_covs = reported_pairs(seq, every_nth(seq, OdometryConfig(), n))
        nr = [anees_cells(relative_pose_tangent_errors(q["T_est"], T), q_covs)[1]
              for T in (q["T_true"], turned_back(q, fit["all"]["rotation_rad"])["T_true"])]
        masks = (q["end"] <= 119, q["end"] >= 120, q["end"] >= 0)
        cells = [" / ".join(f"{v[m].mean():.2f}" for v in nr) for m in masks]
        lines.append(f"| {n} | " + " | ".join(cells) + " |")
    lines += ["", "Keyframe mode (`tracking.keyframes`: each frame against its keyframe, pairs over 1 to 15 intervals, "
              "which overlap, so the standard errors understate): the fit on the mode's own pairs, and the rotation "
              "ANEES of its pairs against the reference as it is / turned back by the fit on fr1_rpy's consecutive "
              "pairs (the first table's last row).", "",
              "| sequence | pairs | d (deg) x / y / z | rotation ANEES: as it is / turned back |", "|---|---|---|---|"]
    for name in (RPY, DESK):
        kseq = TumSequence(data / "tum" / name)
        q, q_covs = reported_pairs(kseq, every_nth(kseq, OdometryConfig().replace(tracking={"keyframes": True}), 1))
        nr = [anees_cells(relative_pose_tangent_errors(q["T_est"], T), q_covs)[1].mean()
              for T in (q["T_true"], turned_back(q, fit["all"]["rotation_rad"])["T_true"])]
        k_fit = axes_rotation(q["T_est"], q["T_true"], q_covs)
        lines.append(f"| {name} | {k_fit['pairs']} | {angles(k_fit)} | {nr[0]:.2f} / {nr[1]:.2f} |")
    lines += ["", "The default model fitted on one half (as in the first tables) against the reference as it is and "
              "turned back by the fit on all pairs, checked on the other half against the same reference: how much "
              "of the sensor terms the reference's axes took.", "",
              "| fitted on | reference | frame term (deg) | latency (ms) | checked on | ANEES t / r | "
              "log-likelihood held out |", "|---|---|---|---|---|---|---|"]
    pp = per_point_pairs(data, RPY)
    references = (("as it is", pp["T_true"]), ("turned back", turned_back(pp, fit["all"]["rotation_rad"])["T_true"]))
    for name, m in (("A", pp["end"] <= 119), ("B", pp["end"] >= 120)):
        for label, T_true in references:
            f, held = fit_half({**pp, "err": relative_pose_tangent_errors(pp["T_est"], T_true)}, m)
            lines.append(f"| {name} | {label} | {f.frame_sigma_rot_deg:.3f} | {1e3 * f.sigmas['latency']:.2f} | "
                         f"{'B' if name == 'A' else 'A'} | {held} |")
    lines += ["", "The same with the fr1 camera's principal point (row `cy`, px; 255.3 is its calibration's) moved "
              "by 10 px either way: the fit on all pairs, RPE30 of the run, and the chains' rotation ANEES per "
              "half as the reference is.", "",
              "| cy (px) | d (deg) x / y / z | RPE30 (m) | chains of 30, rotation ANEES: frames 1-119 / 120-239 |",
              "|---|---|---|---|"]
    for cy in PRINCIPAL_ROWS:
        cam = dataclasses.replace(Camera.preset("fr1"), cy=cy)
        with tempfile.TemporaryDirectory() as tmp:
            run = run_sequence(seq, tmp, camera=cam, plots=False, progress=False)
        q, q_covs = reported_pairs(seq, run.steps)
        lines.append(f"| {cy:.1f} | {angles(fits(q, q_covs)['all'])} | {run.metrics['rpe_30']['trans_rmse']:.4f} | "
                     f"{chains_r(q, q_covs, 1, 119)} / {chains_r(q, q_covs, 120, 239)} |")
    return lines + [""]


def _linked(p: dict) -> np.ndarray:
    """Indices of the pairs of ``p`` (:func:`reported_pairs`) with a pair ending at their first frame
    and one starting at their last, and one more before (for the previous change)."""
    end = p["end"]
    return np.array([i for i in range(2, len(end) - 1)
                     if end[i - 2] == end[i] - 2 and end[i - 1] == end[i] - 1 and end[i + 1] == end[i] + 1])


def twist_change_table(data: Path) -> list[str]:
    """The delay of the images against the reference that the pairs' rotation errors show
    (:func:`covo_gtsam.reference_noise.twist_change_response`), covo's and OpenCV's, per half of
    fr1_rpy and on fr1_desk; then covo's rotation RMS with a multiple of a change of the angular
    velocity taken off, the multiple fitted on the other half: the true change across the pair,
    and the changes a run can estimate from its own twists (the previous one, this pair's own, the
    one across the pair, known one frame later)."""
    lines = ["## The rotation errors against the change of the angular velocity", "",
             "The consecutive pairs' rotation errors fitted (generalized least squares, "
             "`covo_gtsam.reference_noise.twist_change_response`, `twist_change_response` in `metrics.json`) as "
             "`a (w_k - w_k-1) + c (w_k+1 - w_k) + s r_k`, `w` the pairs' true mean angular velocities, `r` their "
             "true turns. Images taken `L` before their stamps give a delay `a + c = L`, with `c` about "
             "`(dt - L) / (dt + L)` of `a`; turns estimated `1 - s` times their size give `s` alone. The split "
             "between `a` and `c` rests on the difference of the changes before and after the pair, which the "
             "reference's jitter dominates (a test: with fr1's jitter and accelerations a 10 ms delay, 6.6 / 3.5 "
             "ms, reads as about 14 / -4 ms); the delay `a + c` holds. covo's reported pairs with their "
             "covariances and the reference's jitter; OpenCV's dense RGB-D odometry (between the captures, not "
             "moved to the stamps) with its own errors' mean square per axis as its covariance. In ms (`s` in %), "
             "with standard errors, and covo's fit's reduced chi-square.", "",
             "| pairs | covo: delay a + c (ms) | covo: a / c (ms), s (%) | reduced chi-square | OpenCV: delay (ms) "
             "| OpenCV: a / c (ms), s (%) |", "|---|---|---|---|---|---|"]

    def delay(f: dict) -> str:
        return f"{1e3 * f['delay_s']:+.1f} ± {1e3 * f['delay_standard_error_s']:.1f}"

    def fmt(f: dict) -> str:
        se = f["standard_error"]
        return (f"{1e3 * f['backward_s']:+.1f} ± {1e3 * se[0]:.1f} / {1e3 * f['forward_s']:+.1f} ± {1e3 * se[1]:.1f}, "
                f"{1e2 * f['rotation_scale']:+.1f} ± {1e2 * se[2]:.1f}")

    def fit(q: dict, q_covs: np.ndarray, lo: int, hi: int) -> dict:
        m = (q["end"] >= lo) & (q["end"] <= hi)
        return twist_change_response(q["T_est"][m], q["T_true"][m], q_covs[m], q["t_ref"][m], q["t_cur"][m])

    rpy = None
    for name, ranges in SEGMENTS:
        seq = TumSequence(data / "tum" / name)
        p, covs = reported_pairs(seq, every_nth(seq, OdometryConfig(), 1))
        o, o_covs = opencv_reported(seq, p)
        for label, lo, hi in (ranges if name == DESK else (*ranges, ("fr1_rpy, all", 1, 239))):
            ours, other = fit(p, covs, lo, hi), fit(o, o_covs, lo, hi)
            lines.append(f"| {label} ({ours['pairs']}) | {delay(ours)} | {fmt(ours)} | {ours['reduced_chi2']:.2f} | "
                         f"{delay(other)} | {fmt(other)} |")
        if name == RPY:
            rpy = p
    p = rpy
    k = _linked(p)
    dt = (p["t_cur"] - p["t_ref"])[:, None]
    w_true, w_est = se3_log(p["T_true"])[:, :3] / dt, se3_log(p["T_est"])[:, :3] / dt
    e = relative_pose_tangent_errors(p["T_est"], p["T_true"])[k, :3]
    R = p["T_true"][k, :3, :3]  # the earlier pairs' velocities into the pair's current frame, as the fit takes them
    changes = {"the true change across the pair, (w_k+1 - w_k-1) / 2 (not known to a run)":
                   0.5 * (w_true[k + 1] - np.einsum("nji,nj->ni", R, w_true[k - 1])),
               "the previous change, w_k-1 - w_k-2 (estimated; known when the pair is solved)":
                   w_est[k - 1] - w_est[k - 2],
               "this pair's own change, w_k - w_k-1 (estimated; carries the pair's own error)": w_est[k] - w_est[k - 1],
               "the central change, (w_k+1 - w_k-1) / 2 (estimated; known one frame later)":
                   0.5 * (w_est[k + 1] - w_est[k - 1])}
    halves = {"A": p["end"][k] <= 119, "B": p["end"][k] >= 120}

    def rms(x: np.ndarray) -> str:
        return f"{np.degrees(np.sqrt(np.mean(np.sum(x**2, axis=1)))):.3f}"

    lines += ["", "covo's rotation RMS per pair (deg) on fr1_rpy's consecutive pairs with a pair before and after, "
              "as it is and with `g` times a change of the angular velocity taken off, `g` (ms) the least-squares "
              "fit on the other half (held out). Only a change a run knows could correct it or size its "
              "covariance; the true change, measured from the reference, shares the reference's jitter with the "
              "errors.", "",
              "| change taken off | A: g fitted on B, RMS | B: g fitted on A, RMS |", "|---|---|---|",
              f"| none | {rms(e[halves['A']])} | {rms(e[halves['B']])} |"]
    for label, x in changes.items():
        cells = []
        for on, off in (("A", "B"), ("B", "A")):
            g = np.sum(e[halves[off]] * x[halves[off]]) / np.sum(x[halves[off]] ** 2)
            cells.append(f"{1e3 * g:+.1f} ms, {rms(e[halves[on]] - g * x[halves[on]])}")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return lines + [""]


def _after_a_pair(p: dict) -> np.ndarray:
    """Indices of the pairs of ``p`` whose first frame ends the pair before them."""
    return np.flatnonzero(np.r_[False, np.diff(p["end"]) == 1])


def own_change_basis(p: dict, T_key: str = "T_est", noise: float = 1.0) -> np.ndarray:
    """Latency bases (N, 6, 6) of fr1_rpy's consecutive pairs ``p`` from each pair's own change of the
    angular velocity, ``b b^T - noise N`` clipped to positive semidefinite
    (:func:`covo_gtsam.calibration.known_change_basis`): ``b`` from the pair's and the pair before's
    mean twists ``Log(T) / dt`` (``T_key``: the estimates, or ``"T_true"``, the reference's), ``N``
    their per-point covariances over ``dt^2``; zero without a pair before."""
    from covo_gtsam.calibration import known_change_basis

    dt = p["t_cur"] - p["t_ref"]
    w = se3_log(p[T_key]) / dt[:, None]
    out = np.zeros((len(dt), 6, 6))
    for k in _after_a_pair(p):
        out[k] = known_change_basis(p[T_key][k], w[k - 1], w[k], noise * p["cov"][k - 1] / dt[k - 1] ** 2,
                                    noise * p["cov"][k] / dt[k] ** 2)
    return out


def own_change_table(data: Path) -> list[str]:
    """The latency term's basis from the change across the pair, known one frame later (the
    default), from the recent pairs' changes (``latency_look_ahead`` off), and from the pair's own
    change of the angular velocity: refitted on one half of fr1_rpy, checked on the other (both
    ways), with the held-out pairs' rotation ANEES by the true angular acceleration; and from the
    true change (the reference's, not known to a run), what a run that knew the change could reach."""
    from covo_gtsam.calibration import log_likelihood

    rpy = per_point_pairs(data, RPY)
    rpy["accel"] = true_motion(rpy["T_true"], rpy["t_ref"], rpy["t_cur"])[1]
    recent = per_point_pairs(data, RPY, latency_look_ahead=False)
    assert np.array_equal(recent["end"], rpy["end"])  # the look-ahead moves no pose: the same pairs
    recent = recent["bases"]["latency"]
    variants = {"the change across the pair, (w_k+1 - w_k-1) / 2, one frame later (default)": rpy["bases"]["latency"],
                "the recent pairs' changes (latency_look_ahead false)": recent,
                "the pair's own change, w_k - w_k-1 (estimated)": own_change_basis(rpy),
                "the pair's own change, three times its per-point noise taken off": own_change_basis(rpy, noise=3.0),
                "half the recent changes' and half the own change's": 0.5 * (recent + own_change_basis(rpy)),
                "the true change from the pair before (not known to a run)": own_change_basis(rpy, "T_true", 0.0)}
    halves = {"A": rpy["end"] <= 119, "B": rpy["end"] >= 120}
    edges = ACCELERATION_EDGES
    bins = [f"{lo:g}-{hi:g}" if np.isfinite(hi) else f"above {lo:g}" for lo, hi in zip(edges[:-1], edges[1:])]
    lines = ["## The latency term's basis: the change across the pair, the recent changes, the pair's own", "",
             "A burst of acceleration is not announced by the pairs before it. The latency term's basis is taken "
             "from the change of the angular velocity across the pair, the next pair's twist minus the one "
             "before's over two (known when the next frame is registered; all six axes, the per-point noise of "
             "both twists taken off; the default), from the mean of the recent pairs' changes (rotation block; "
             "`sensor.latency_look_ahead` false, and every pair without a trusted pair before and after it), or "
             "from each pair's own change (its twist's and the pair before's, the per-point noise of both taken "
             "off), the default terms refitted on one half of fr1_rpy's consecutive pairs and checked on the "
             "other, both ways: held-out log-likelihood per pair, ANEES t / r, share of rotation NEES above "
             "9.35, and the held-out rotation ANEES by the true angular acceleration (rad/s^2; both halves' "
             "held-out pairs). "
             "The last row takes the change from the reference: it shares the reference's jitter with the "
             "errors, so it bounds what a perfectly known change could give rather than measuring it.", "",
             "| latency basis | latency fitted A / B (ms) | held out: B / A log-likelihood | ANEES t / r B; A | "
             "rotation NEES > 9.35 | " + " | ".join(bins) + " |", "|---" * (5 + len(bins)) + "|"]
    for label, basis in variants.items():
        p = {**rpy, "bases": {**rpy["bases"], "latency": basis}}
        fitted, ll, cells, nr_all, acc_all = [], [], [], [], []
        for on, off in (("A", "B"), ("B", "A")):
            train = subset(p, halves[on] & p["fit_ok"])
            fit = fit_sensor_terms(train["err"], train["cov"], False,
                                   bases={n: train["bases"][n] for n in DEFAULT_TERMS}, fixed=train["fixed"])
            check_ = subset(p, halves[off])
            covs = model_covs(fit, check_)
            nt, nr = anees_cells(check_["err"], covs)
            fitted.append(f"{1e3 * fit.sigmas['latency']:.2f}")
            ll.append(f"{log_likelihood(check_['err'], covs):.2f}")
            cells.append(f"{nt.mean():.2f} / {nr.mean():.2f}")
            nr_all.append(nr)
            acc_all.append(check_["accel"])
        nr, acc = np.concatenate(nr_all), np.concatenate(acc_all)
        by = by_bins(acc, edges, nr, nr)
        lines.append(f"| {label} | {' / '.join(fitted)} | {' / '.join(ll)} | {'; '.join(cells)} | "
                     f"{100 * np.mean(nr > 9.35):.1f} % | "
                     + " | ".join(f"{b['anees_rotation']:.2f} ({b['pairs']})" for b in by) + " |")
    from covo_gtsam.calibration import twist_change

    k = _after_a_pair(rpy)
    dt = (rpy["t_cur"] - rpy["t_ref"])[:, None]
    changes = []
    for key in ("T_est", "T_true"):
        w = se3_log(rpy[key]) / dt
        changes.append(np.array([twist_change(rpy[key][i], w[i - 1], w[i])[:3] for i in k]))
    est, true = changes
    corr = [np.corrcoef(est[:, i], true[:, i])[0, 1] for i in range(3)]

    def axes(v) -> str:
        return " / ".join(f"{x:.2f}" for x in v)

    lines += ["", f"The estimated own change against the reference's ({len(k)} pairs, about x / y / z): correlation "
              f"{axes(corr)}; the reference's change {axes(np.sqrt(np.mean(true**2, axis=0)))} rad/s RMS, the "
              f"estimate's error {axes(np.sqrt(np.mean((est - true)**2, axis=0)))} rad/s RMS."]
    return lines + [""]


def chain_translation_rms(T_est: np.ndarray, T_true: np.ndarray, w: int) -> float:
    """Translation RMS (m) of the chains of ``w`` consecutive pairs against the truth's."""
    est, _ = compose_chains(T_est, np.zeros((len(T_est), 6, 6)), w)
    true, _ = compose_chains(T_true, np.zeros((len(T_true), 6, 6)), w)
    return float(np.sqrt(np.mean(np.sum(relative_pose_tangent_errors(est, true)[:, 3:] ** 2, axis=1))))


def opencv_pairs(seq: TumSequence, lookup: dict) -> dict:
    """OpenCV's dense RGB-D odometry (``cv2.Odometry`` of OpenCV 5, photometric and depth terms,
    default settings) over the consecutive frames of ``seq``, on images undistorted with the
    sequence's camera (the depth by its nearest pixel): end frame index -> T_ref,cur (4, 4) of the
    pairs it solved. ``Rt * src = dst`` with the current frame as source: ``Rt`` is T_ref,cur."""
    import cv2

    key = (str(seq.path), len(seq.timestamps))
    if key in _OPENCV:
        return _OPENCV[key]
    cam = seq.camera
    K, dist = cam.K, np.asarray(cam.dist, dtype=float)
    maps = cv2.initUndistortRectifyMap(K, dist, None, K, (cam.width, cam.height), cv2.CV_32FC1)
    settings = cv2.OdometrySettings()
    settings.setCameraMatrix(K.astype(np.float32))
    odo = cv2.Odometry(cv2.OdometryType_RGB_DEPTH, settings, cv2.OdometryAlgoType_COMMON)

    def load(k: int) -> tuple[np.ndarray, np.ndarray]:
        grey, depth = seq.load(k)
        return (cv2.remap(grey, *maps, cv2.INTER_LINEAR),
                cv2.remap(depth.astype(np.float32), *maps, cv2.INTER_NEAREST))

    out, prev = {}, load(0)
    for k in range(1, len(seq.timestamps)):
        cur = load(k)
        if seq.timestamps[k] in lookup and seq.timestamps[k - 1] in lookup:
            ok, Rt = odo.compute(cur[1], cur[0], prev[1], prev[0])
            if ok and np.all(np.isfinite(Rt)):
                out[k] = np.asarray(Rt, dtype=float)
        prev = cur
    _OPENCV[key] = out
    return out


_OPENCV: dict = {}  # opencv_pairs' runs, made once for the two tables that read them


def independent_table(data: Path) -> list[str]:
    """covo's pair errors against those of an estimator with nothing of covo's own (OpenCV's dense
    RGB-D odometry): per axis correlation, the part of covo's error variance the two have in common
    (also with the ground truth at the stamps shifted by covo's best common delay), and how the
    errors and their difference persist along chains. Needs OpenCV 5 (``cv2.Odometry``)."""
    import cv2

    lines = ["## What an independent estimator shares", ""]
    if not hasattr(cv2, "Odometry"):
        return lines + [f"Not computed: OpenCV {cv2.__version__} has no `cv2.Odometry` (OpenCV 5's RGB-D odometry).",
                        ""]
    lines += [
        "covo's consecutive pairs (default model; its poses between the captures, before the frame clock moves them "
        "to the stamps) and OpenCV's dense RGB-D odometry (`cv2.Odometry`, default settings: photometric and depth "
        "terms over the pixels of strong image gradient, depths to 4 m; no keypoints, no per-point model; on the "
        "undistorted images) on the same pairs, both against the ground truth at the stamps. What the two have in "
        "common is their input: the images and their stamps, the camera's intrinsics, the depth's scale and "
        "registration, the scene, and the reference they are checked against. Common: sum over the axes of "
        "E[covo error x OpenCV error] over the sum of E[covo error^2]; if the errors are c + a (covo) and c + b "
        "(OpenCV) with a, b, c independent, this is c's share of covo's error variance (it can leave [0, 1] where "
        "they are not; fr1_desk has 8 pairs). Then the same with the ground truth at the stamps shifted by the "
        "common delay that minimises covo's rotation RMS (as in the delay table above). Chains of 30: mean squared "
        "translation error of the composed chain over the mean sum of its pairs' squared errors, covo / OpenCV / "
        "the difference of the two pair errors (summed as vectors). Frames 1-119 include the pair ending at frame "
        "108 that the integrity check flags, which the table 'Errors that persist from pair to pair' leaves out.",
        "",
        "| pairs | n | RMS rotation covo / OpenCV (deg) | RMS translation covo / OpenCV (mm) "
        "| correlation rotation x / y / z | correlation translation x / y / z | common rotation / translation "
        "| best shift (ms): RMS rotation covo / OpenCV, common rotation / translation "
        "| chains of 30, translation: covo / OpenCV / difference |", "|---|---|---|---|---|---|---|---|---|"]
    for name, ranges in SEGMENTS:
        seq = TumSequence(data / "tum" / name)
        lookup = ground_truth_lookup(seq)
        index = {t: i for i, t in enumerate(seq.timestamps)}
        ours = {index[s.timestamp]: s.result.pose.matrix() for s in every_nth(seq, OdometryConfig(), 1)
                if index.get(s.ref_timestamp) == index[s.timestamp] - 1}
        theirs = opencv_pairs(seq, lookup)
        ends = np.array(sorted(set(ours) & set(theirs)))
        est = {"covo": np.array([ours[k] for k in ends]), "OpenCV": np.array([theirs[k] for k in ends])}
        for label, lo, hi in ranges:
            m = (ends >= lo) & (ends <= hi)
            rot_rms = []
            for shift in SHIFTS:
                true, ok = shifted_truth(seq, ends[m], shift)
                e = relative_pose_tangent_errors(est["covo"][m], true)[ok]
                rot_rms.append(np.sqrt(np.mean(np.sum(e[:, :3] ** 2, 1))))
            cells = []
            for at_stamps, shift in ((True, 0.0), (False, SHIFTS[int(np.argmin(rot_rms))])):
                true, ok = shifted_truth(seq, ends[m], shift)
                err = {k: relative_pose_tangent_errors(T[m], true)[ok] for k, T in est.items()}
                x, y = err["covo"], err["OpenCV"]
                common = [np.sum(x[:, b] * y[:, b]) / np.sum(x[:, b] ** 2) for b in (slice(0, 3), slice(3, 6))]
                rms = {k: (np.degrees(np.sqrt(np.mean(np.sum(e[:, :3] ** 2, 1)))),
                           1e3 * np.sqrt(np.mean(np.sum(e[:, 3:] ** 2, 1)))) for k, e in err.items()}
                if at_stamps:
                    corr = [np.corrcoef(x[:, j], y[:, j])[0, 1] for j in range(6)]
                    cells += [f"{int(ok.sum())}", f"{rms['covo'][0]:.3f} / {rms['OpenCV'][0]:.3f}",
                              f"{rms['covo'][1]:.2f} / {rms['OpenCV'][1]:.2f}",
                              " / ".join(f"{c:.2f}" for c in corr[:3]), " / ".join(f"{c:.2f}" for c in corr[3:]),
                              f"{common[0]:.2f} / {common[1]:.2f}"]
                    run = ends[m][ok]
                    chains = [persistence(est[k][m][ok], true[ok], run, CHAIN)[0] for k in est]
                    chains.append(persistence_of_sums(x[:, 3:] - y[:, 3:], run, CHAIN))
                else:
                    cells.append(f"{1e3 * shift:+.1f}: {rms['covo'][0]:.3f} / {rms['OpenCV'][0]:.3f}, "
                                 f"{common[0]:.2f} / {common[1]:.2f}")
            cells.append("—" if np.isnan(chains[0]) else " / ".join(f"{c:.2f}" for c in chains))
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return lines + [""]


def _windows(ends: np.ndarray, w: int) -> np.ndarray:
    """Start indices of the windows of ``w`` pairs whose end frames are consecutive."""
    if len(ends) < w:
        return np.zeros(0, int)
    return np.flatnonzero(ends[w - 1:] - ends[:len(ends) - w + 1] == w - 1)


def persistence(est: np.ndarray, true: np.ndarray, ends: np.ndarray, w: int) -> np.ndarray:
    """Translation and rotation (2,): mean squared error of the chains of ``w`` consecutive pairs
    (end frames ``ends``, windows across a gap left out) over the mean sum of their pairs' squared
    errors; NaN without such a chain."""
    starts = _windows(ends, w)
    if not len(starts):
        return np.full(2, np.nan)
    zero = np.zeros((len(est), 6, 6))
    chain = relative_pose_tangent_errors(compose_chains(est, zero, w)[0], compose_chains(true, zero, w)[0])[starts]
    e = relative_pose_tangent_errors(est, true)
    sq = np.stack([np.sum(e[:, 3:] ** 2, axis=1), np.sum(e[:, :3] ** 2, axis=1)], axis=1)
    chain_sq = np.stack([np.sum(chain[:, 3:] ** 2, axis=1), np.sum(chain[:, :3] ** 2, axis=1)], axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):  # no error at all: NaN
        return chain_sq.mean(axis=0) / np.array([sq[s:s + w].sum(axis=0) for s in starts]).mean(axis=0)


def persistence_of_sums(e: np.ndarray, ends: np.ndarray, w: int) -> float:
    """The same ratio for error vectors ``e`` (K, 3) summed over the windows (a chain's error to
    first order)."""
    starts = _windows(ends, w)
    if not len(starts):
        return float("nan")
    sums = np.array([e[s:s + w].sum(axis=0) for s in starts])
    return float(np.mean(np.sum(sums**2, axis=1)) / np.mean([np.sum(e[s:s + w] ** 2) for s in starts]))

def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "cross_validation.md")
    args = ap.parse_args()
    lines = ["# Cross-validation of the sensor terms", "", __doc__.split("\n\n", 2)[2].strip(), "",
             "*Generated by `python studies/cross_validation.py`; do not edit by hand.*", ""]
    lines += (tables(args.data) + moved_table(args.data) + window_table(args.data) + stride_table(args.data)
              + span_table(args.data) + motion_table(args.data) + acceleration_table(args.data)
              + whole_sequence_table(args.data)
              + speed_term_table(args.data)
              + closure_table(args.data) + persistence_table(args.data) + drift_table(args.data)
              + reference_table(args.data) + frame_noise_table(args.data) + axes_table(args.data)
              + twist_change_table(args.data) + own_change_table(args.data) + independent_table(args.data))
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
