#!/usr/bin/env python
"""Fuse covo's visual odometry with sparse absolute position fixes in an iSAM2 pose graph.

    python examples/pose_graph_isam2.py SEQ_DIR [--out DIR] [--max-frames N]
        [--fix-every N] [--fix-sigma M] [--seed S] [--repeat K] [--config FILE] [--no-plots]

The results go to ``--out DIR``; without it, to a new temporary folder (its name is printed).

What it does:

1. Runs :class:`covo_gtsam.odometry.VisualOdometry` over the TUM sequence (through
   :func:`covo_gtsam.pipeline.run_sequence`, which also writes ``OUT/vo/``) with the default
   :class:`~covo_gtsam.config.OdometryConfig` or the settings of ``--config``.
2. Builds the same pose graph several times, incrementally with ``gtsam.ISAM2`` (one update per
   frame, new poses initialised from the current estimate of their reference frame composed with
   the odometry):

   * a tight prior on the first pose (identity: the world frame is the first camera frame);
   * one ``BetweenFactorPose3`` per tracked frame pair (:func:`covo_gtsam.graph.between_factors`);
   * every ``--fix-every`` frames an absolute position fix ``p_i = t(gt_0^-1 gt_i) + n``,
     ``n ~ N(0, fix_sigma^2 I)`` (seeded), as ``gtsam.PoseTranslationPrior3D`` -- GPS-like, the
     error is ``t(x_i) - p_i`` in the world frame, Jacobian ``[0, R]``.

   The variants differ only in the noise of the odometry factors:

   ``covo``
       each factor gets the covariance covo estimated for that frame pair;
   ``unit``
       one constant covariance ``diag(1e-2^2)``: 0.01 rad and 0.01 m per step, the kind of
       hand-tuned constant an odometry without covariances is usually given;
   ``median``
       a fairer constant: per block (rotation, translation) the isotropic covariance whose trace
       equals the median trace of covo's covariances over the run, i.e. the same overall
       confidence as covo, without the per-frame variation or the correlations. Comparing
       ``covo`` with ``median`` isolates the value of *per-frame* covariances from the value of
       the overall level, which ``unit`` mixes.
   ``covo_scaled_oracle`` (diagnostic, only with ground truth)
       covo's covariances times the odometry's own relative-pose ANEES / 3 measured against the
       ground truth of this run: covo's per-frame shape with the overall level calibrated by an
       oracle. Not a fair competitor; it tells whether a worse ``covo`` result comes from the
       level (over-confidence) or from the per-frame shape.

3. Reports the ATE RMSE (metres, SE(3)-aligned, :func:`covo_gtsam.metrics.ate`) of each fused
   trajectory and of the odometry alone, the average NEES of the fused positions against their
   iSAM2 marginal covariances (3 dof; about 3 when the marginals are consistent), and plots the
   fused trajectories with marginal 3-sigma ellipses into ``OUT``.

A single draw of 7 fixes is a noisy experiment: ``--repeat K`` fuses again with the fixes of seeds
``S+1 .. S+K-1`` (the odometry runs once) and reports the mean/median/min/max ATE of every variant
and how often ``covo`` wins.

The last printed line is a JSON object (also written to ``OUT/pose_graph.json``) with
``ate_rmse_covo``, ``ate_rmse_unit``, ``ate_rmse_median``, ``ate_rmse_vo_only``, ``frames``,
``fixes`` and more.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import gtsam
import numpy as np

from covo_gtsam.config import OdometryConfig, load_config
from covo_gtsam.datasets.tum import TumSequence
from covo_gtsam.errors import CovoError
from covo_gtsam.geometry import invert_pose
from covo_gtsam.graph import between_factors, step_keys, unit_between_factors
from covo_gtsam.metrics import ate
from covo_gtsam.pipeline import run_sequence
from covo_gtsam.plots import ellipse_xy, plane_axes, save_figure

#: Constant odometry covariance of the ``unit`` variant: 0.01 rad and 0.01 m standard deviations.
UNIT_SIGMA = 1e-2
#: Standard deviation (rad, m) of the prior that anchors the first pose at the identity.
PRIOR_SIGMA = 1e-6


def position_fix_factor(key: int, position: np.ndarray, sigma: float) -> gtsam.NonlinearFactor:
    """Absolute position factor on a ``Pose3``: error ``t(x) - position`` (world frame), sd ``sigma``."""
    noise = gtsam.noiseModel.Isotropic.Sigma(3, sigma)
    position = np.asarray(position, dtype=float)
    if hasattr(gtsam, "PoseTranslationPrior3D"):
        # the Pose3 constructor (only its translation is used) exists in every GTSAM 4.2+ wrapper
        return gtsam.PoseTranslationPrior3D(key, gtsam.Pose3(gtsam.Rot3(), position), noise)

    def error(this, values, H):  # pragma: no cover - only for GTSAM builds without the prior
        pose = values.atPose3(key)
        if H is not None:
            J = np.zeros((3, 6))
            J[:, 3:] = pose.rotation().matrix()
            H[0] = J
        return pose.translation() - position

    return gtsam.CustomFactor(noise, gtsam.KeyVector([key]), error)


def median_block_covariance(covs: np.ndarray) -> np.ndarray:
    """Block-isotropic 6x6 covariance whose rotation / translation traces are the median ones of ``covs``."""
    covs = np.asarray(covs)
    var_r = np.median(np.trace(covs[:, :3, :3], axis1=1, axis2=2)) / 3.0
    var_t = np.median(np.trace(covs[:, 3:, 3:], axis1=1, axis2=2)) / 3.0
    return np.diag([var_r] * 3 + [var_t] * 3)


def fuse_isam2(factors, keys: dict[int, int], fixes: dict[int, np.ndarray], fix_sigma: float):
    """Incremental iSAM2 over the frames in order; returns (poses {i: Pose3}, marginals {i: 6x6}, isam)."""
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(1e-3)
    params.relinearizeSkip = 1
    isam = gtsam.ISAM2(params)
    by_cur = {int(f.keys()[1]): f for f in factors}
    key_to_index = {k: i for i, k in keys.items()}
    prior_noise = gtsam.noiseModel.Isotropic.Sigma(6, PRIOR_SIGMA)
    first = True
    for i in sorted(keys):
        k = keys[i]
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        f = by_cur.get(k)
        if f is None:
            if not first:
                raise CovoError(f"frame {i} has a pose but no odometry factor")  # a second "first" frame
            graph.add(gtsam.PriorFactorPose3(k, gtsam.Pose3(), prior_noise))
            values.insert(k, gtsam.Pose3())
            first = False
        else:
            ref_key = int(f.keys()[0])
            values.insert(k, isam.calculateEstimatePose3(ref_key).compose(f.measured()))
            graph.add(f)
        if i in fixes:
            graph.add(position_fix_factor(k, fixes[i], fix_sigma))
        isam.update(graph, values)
    for _ in range(3):  # a few more relinearisation passes over the whole graph
        isam.update()
    est = isam.calculateEstimate()
    poses = {key_to_index[k]: est.atPose3(k) for k in keys.values()}
    marginals = {key_to_index[k]: np.asarray(isam.marginalCovariance(k)) for k in keys.values()}
    return poses, marginals, isam


def batch_check(isam: gtsam.ISAM2, poses: dict[int, gtsam.Pose3], keys: dict[int, int]) -> float:
    """Largest position difference (m) between iSAM2's estimate and a batch Levenberg-Marquardt solve."""
    graph = isam.getFactorsUnsafe()
    initial = gtsam.Values()
    for i, k in keys.items():
        initial.insert(k, poses[i])
    batch = gtsam.LevenbergMarquardtOptimizer(graph, initial).optimize()
    return float(max(np.linalg.norm(batch.atPose3(k).translation() - poses[i].translation()) for i, k in keys.items()))


def draw_fixes(gt_rel: dict, first: int, n: int, every: int, sigma: float, seed: int) -> dict[int, np.ndarray]:
    """Position fixes ``{frame: t(gt_0^-1 gt_i) + N(0, sigma^2 I)}`` at frames ``first + k * every`` (k >= 1).

    The noise is drawn for every slot, so a frame without tracking or ground truth (skipped) does
    not change the noise of the other fixes.
    """
    rng = np.random.default_rng(seed)
    fixes: dict[int, np.ndarray] = {}
    for i in range(first + every, n, every):
        noise = rng.normal(0.0, sigma, 3)
        if i in gt_rel:
            fixes[i] = gt_rel[i][:3, 3] + noise
    return fixes


def position_nees(poses, marginals, gt_rel, indices) -> np.ndarray:
    """NEES (3 dof) of the fused positions against the marginals' translation block in the world frame."""
    out = []
    for i in indices:
        R = poses[i].rotation().matrix()
        C = R @ marginals[i][3:, 3:] @ R.T  # right perturbation: t_true - t = R v to first order
        e = poses[i].translation() - gt_rel[i][:3, 3]
        out.append(float(e @ np.linalg.solve(C, e)))
    return np.array(out)


def plot_results(out: Path, variants: dict, gt_rel: dict, vo_poses: dict, fixes: dict,
                 indices: list[int]) -> list[Path]:
    try:
        import matplotlib
    except ImportError:  # pragma: no cover
        return []
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    G = np.array([gt_rel[i][:3, 3] for i in indices])
    spread = G.max(axis=0) - G.min(axis=0)
    a, b = sorted(np.argsort(spread)[-2:])  # the two axes the camera moved most along
    written = []
    fig, axes = plt.subplots(1, len(variants), figsize=(6 * len(variants), 5.6), squeeze=False)
    every = max(1, len(indices) // 25)
    for ax, (name, v) in zip(axes[0], variants.items()):
        P = np.array([v["poses"][i].translation() for i in indices])
        V = np.array([vo_poses[i].translation() for i in indices])
        ax.plot(G[:, a], G[:, b], "k--", lw=1.0, label="ground truth")
        ax.plot(V[:, a], V[:, b], "-", color="0.6", lw=0.8, label="odometry only")
        ax.plot(P[:, a], P[:, b], "b-", lw=1.2, label=f"fused ({name})")
        for n_, i in enumerate(indices):
            if n_ % every and i not in fixes:
                continue
            R = v["poses"][i].rotation().matrix()
            C = (R @ v["marginals"][i][3:, 3:] @ R.T)[np.ix_([a, b], [a, b])]
            ellipse_xy(ax, P[n_, [a, b]], C, color="tab:orange", lw=0.7)
        ax.plot([], [], color="tab:orange", lw=0.7, label="3$\\sigma$ (iSAM2 marginal)")
        F = np.array([fixes[i] for i in indices if i in fixes]).reshape(-1, 3)
        ax.plot(F[:, a], F[:, b], "r+", ms=9, mew=1.5, label="position fixes")
        plane_axes(ax, a, b, f"{name}: ATE {v['ate_rmse'] * 100:.2f} cm, position ANEES {v['anees_position']:.2f}", 7)
    written.append(save_figure(fig, out / "pose_graph_trajectories.png"))

    fig, axes = plt.subplots(len(variants), 1, figsize=(10, 2.6 * len(variants)), sharex=True, squeeze=False)
    for ax, (name, v) in zip(axes[:, 0], variants.items()):
        err = np.array([np.linalg.norm(v["poses"][i].translation() - gt_rel[i][:3, 3]) for i in indices])
        sig = np.array([np.sqrt(np.linalg.eigvalsh(v["marginals"][i][3:, 3:])[-1]) for i in indices])
        ax.plot(indices, err * 100, "b-", lw=1, label="|position error|")
        ax.plot(indices, 3 * sig * 100, "r-", lw=0.8, label="3 $\\sigma_{max}$ (marginal)")
        for i in fixes:
            ax.axvline(i, color="0.8", lw=0.6, zorder=0)
        ax.set_ylabel(f"{name} [cm]")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7, loc="upper left")
    axes[-1, 0].set_xlabel("frame (grey lines: position fixes)")
    written.append(save_figure(fig, out / "pose_graph_errors.png"))
    return written


def run(args: argparse.Namespace) -> dict:
    t0 = time.perf_counter()
    seq = TumSequence(args.seq)
    if seq.groundtruth is None:
        raise CovoError(f"{args.seq}: the sequence has no ground truth (groundtruth.txt); fixes need it")
    out = Path(args.out)
    config = load_config(args.config) if args.config else OdometryConfig()
    res = run_sequence(seq, out / "vo", config=config, max_frames=args.max_frames, plots=False, progress=False)
    steps = res.steps
    n = len(steps)
    keys = step_keys(steps)
    if len(keys) < 2:
        raise CovoError(f"only {len(keys)} frame(s) tracked; nothing to fuse")
    gt_all = np.asarray(seq.groundtruth)[:n]
    gt_ok = np.asarray(seq.gt_valid, dtype=bool)[:n]
    first = min(keys)
    if not gt_ok[first]:
        raise CovoError(f"the first tracked frame ({first}) has no ground truth; cannot express fixes in its frame")
    gt0_inv = invert_pose(gt_all[first])
    gt_rel = {i: gt0_inv @ gt_all[i] for i in keys if gt_ok[i]}
    indices = sorted(gt_rel)  # tracked frames with ground truth: the frames evaluated

    covo_factors, _ = between_factors(steps)
    tracked_covs = np.array([s.covariance for s in steps if s.has_relative_pose])
    median_cov = median_block_covariance(tracked_covs)
    unit_factors, _ = unit_between_factors(steps, sigma=UNIT_SIGMA)
    median_factors, _ = unit_between_factors(steps, covariance=median_cov)
    factor_sets = {"covo": covo_factors, "unit": unit_factors, "median": median_factors}
    # Diagnostic only (uses ground truth, so not a fair competitor): covo's covariances scaled by
    # the odometry's own relative-pose ANEES / 3, i.e. with the overall level calibrated on this run.
    m = res.metrics
    oracle_scale = None
    if "anees_translation" in m and "anees_rotation" in m:
        oracle_scale = float((m["anees_translation"] + m["anees_rotation"]) / 6.0)
        factor_sets["covo_scaled_oracle"] = between_factors(steps, noise=lambda st: oracle_scale * st.covariance)[0]

    G = np.array([gt_rel[i] for i in indices])
    vo_poses = {i: steps[i].pose for i in keys}
    ate_vo = ate(G, np.array([vo_poses[i].matrix() for i in indices]))["rmse"]

    def fuse_all(seed: int, full: bool):
        fixes = draw_fixes(gt_rel, first, n, args.fix_every, args.fix_sigma, seed)
        variants: dict[str, dict] = {}
        for name, factors in factor_sets.items():
            poses, marginals, isam = fuse_isam2(factors, keys, fixes, args.fix_sigma)
            nees = position_nees(poses, marginals, gt_rel, indices)
            variants[name] = {
                "poses": poses,
                "marginals": marginals,
                "ate_rmse": float(ate(G, np.array([poses[i].matrix() for i in indices]))["rmse"]),
                "anees_position": float(np.mean(nees)),
                "isam2_vs_batch_m": batch_check(isam, poses, keys) if full else 0.0,
            }
        return fixes, variants

    fixes, variants = fuse_all(args.seed, True)
    repeats = {name: [v["ate_rmse"]] for name, v in variants.items()}
    for seed in range(args.seed + 1, args.seed + args.repeat):
        _, vs = fuse_all(seed, False)
        for name, v in vs.items():
            repeats[name].append(v["ate_rmse"])
    written = [] if args.no_plots else plot_results(out, variants, gt_rel, vo_poses, fixes, indices)

    sig_r = np.sqrt(np.median(np.trace(tracked_covs[:, :3, :3], axis1=1, axis2=2)) / 3)
    sig_t = np.sqrt(np.median(np.trace(tracked_covs[:, 3:, 3:], axis1=1, axis2=2)) / 3)
    summary = {
        "sequence": str(seq.name) if hasattr(seq, "name") else str(args.seq),
        "frames": n,
        "tracked_frames": len(keys),
        "evaluated_frames": len(indices),
        "fixes": len(fixes),
        "fix_every": args.fix_every,
        "fix_sigma_m": args.fix_sigma,
        "seed": args.seed,
        "ate_rmse_covo": variants["covo"]["ate_rmse"],
        "ate_rmse_unit": variants["unit"]["ate_rmse"],
        "ate_rmse_median": variants["median"]["ate_rmse"],
        "ate_rmse_vo_only": float(ate_vo),
        "anees_position_covo": variants["covo"]["anees_position"],
        "anees_position_unit": variants["unit"]["anees_position"],
        "anees_position_median": variants["median"]["anees_position"],
        "unit_sigma": UNIT_SIGMA,
        "median_sigma_rot_rad": float(sig_r),
        "median_sigma_trans_m": float(sig_t),
        "ate_rmse_covo_scaled_oracle": variants.get("covo_scaled_oracle", {}).get("ate_rmse"),
        "oracle_scale": oracle_scale,
        "isam2_vs_batch_max_m": max(v["isam2_vs_batch_m"] for v in variants.values()),
        "repeat": args.repeat,
        "repeat_ate_rmse": {
            name: {"mean": float(np.mean(v)), "median": float(np.median(v)), "min": float(np.min(v)),
                   "max": float(np.max(v))} for name, v in repeats.items()},
        "repeat_share_covo_best": float(np.mean(
            [repeats["covo"][r] < min(repeats["unit"][r], repeats["median"][r]) for r in range(args.repeat)])),
        "repeat_share_covo_below_median": float(np.mean(
            [repeats["covo"][r] < repeats["median"][r] for r in range(args.repeat)])),
        "repeat_share_covo_below_unit": float(np.mean(
            [repeats["covo"][r] < repeats["unit"][r] for r in range(args.repeat)])),
        "repeat_share_below_unit": {
            name: float(np.mean([v[r] < repeats["unit"][r] for r in range(args.repeat)]))
            for name, v in repeats.items() if name != "unit"},
        "vo_metrics": {k: res.metrics[k] for k in ("anees_translation", "anees_rotation") if k in res.metrics},
        "vo_config": config.to_dict(),
        "plots": [str(p) for p in written],
        "elapsed_s": time.perf_counter() - t0,
    }
    out.mkdir(parents=True, exist_ok=True)
    (out / "pose_graph.json").write_text(json.dumps(summary, indent=2, default=str) + "\n")
    return summary


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("seq", metavar="SEQ_DIR", help="TUM RGB-D sequence folder with groundtruth.txt")
    p.add_argument("--out", metavar="DIR",
                   help="output folder (default: a new temporary folder, printed at the end)")
    p.add_argument("--config", metavar="FILE", help="odometry settings, TOML or JSON (as for 'covo run --config')")
    p.add_argument("--max-frames", type=int, default=None, metavar="N", help="use only the first N frames")
    p.add_argument("--fix-every", type=int, default=30, metavar="N", help="a position fix every N frames (default 30)")
    p.add_argument("--fix-sigma", type=float, default=0.05, metavar="M",
                   help="standard deviation of the fixes' noise per axis, metres (default 0.05)")
    p.add_argument("--seed", type=int, default=0, metavar="S", help="seed of the fixes' noise (default 0)")
    p.add_argument("--repeat", type=int, default=1, metavar="K",
                   help="also fuse with the fixes of seeds S+1 .. S+K-1 (odometry run once) and report ATE statistics")
    p.add_argument("--no-plots", action="store_true", help="do not write the figures")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.fix_every < 1 or not args.fix_sigma > 0 or args.repeat < 1 or (
            args.max_frames is not None and args.max_frames < 2):
        print("error: --fix-every >= 1, --fix-sigma > 0, --repeat >= 1 and --max-frames >= 2 are required",
              file=sys.stderr)
        return 2
    if args.out is None:
        args.out = tempfile.mkdtemp(prefix="covo-pose-graph-")
    try:
        summary = run(args)
    except CovoError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"{summary['frames']} frames ({summary['tracked_frames']} tracked), {summary['fixes']} position fixes "
          f"(every {args.fix_every} frames, sigma {args.fix_sigma:g} m)")
    print(f"ATE RMSE [m]: odometry only {summary['ate_rmse_vo_only']:.4f} | fused with covo covariances "
          f"{summary['ate_rmse_covo']:.4f} | unit diag({UNIT_SIGMA:g}^2) {summary['ate_rmse_unit']:.4f} | "
          f"median-trace constant {summary['ate_rmse_median']:.4f}")
    print(f"fused position ANEES (3 = consistent): covo {summary['anees_position_covo']:.2f} | "
          f"unit {summary['anees_position_unit']:.2f} | median {summary['anees_position_median']:.2f}")
    if args.repeat > 1:
        r = summary["repeat_ate_rmse"]
        print(f"over {args.repeat} fix seeds, mean ATE RMSE [m]: covo {r['covo']['mean']:.4f} | unit "
              f"{r['unit']['mean']:.4f} | median {r['median']['mean']:.4f}; covo best in "
              f"{summary['repeat_share_covo_best'] * 100:.0f} %, below unit in "
              f"{summary['repeat_share_covo_below_unit'] * 100:.0f} % of the seeds")
    print(f"results in {args.out}")
    print(json.dumps(summary, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
