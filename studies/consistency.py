"""Consistency study: writes docs/consistency.md with its tables and plots.

    python studies/consistency.py [--runs 300] [--data ../shared/data]

Simulation (thesis 5.2): ANEES and predicted vs Monte Carlo sigmas over pixel noise and depth
ranges for each covariance variant. Real data: ANEES and share of NEES above the chi2(3) 97.5 %
quantile on the shared TUM sequences for each variant, next to the thesis's Table 5.2.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from covo_gtsam.datasets.tum import TumSequence  # noqa: E402
from covo_gtsam.evaluation import ground_truth_lookup, relative_ground_truth  # noqa: E402
from covo_gtsam.odometry import OdometryConfig  # noqa: E402
from covo_gtsam.pipeline import run_sequence  # noqa: E402
from covo_gtsam.simulation import SimulationConfig, run_simulation  # noqa: E402

SIM_VARIANTS = {
    "consistent (default)": dict(weighting="consistent", scale=1.0),
    "thesis, phi = 1": dict(weighting="thesis", scale=1.0),
    "thesis, phi = 16": dict(weighting="thesis", scale=16.0),
}
REAL_VARIANTS = {
    "default (consistent, 2 px, frame term, rolling-shutter compensation)": OdometryConfig(),
    "default without rolling-shutter compensation": OdometryConfig(rolling_shutter_s=0.0),
    "consistent, 2 px, no frame term": OdometryConfig(frame_sigma_rot_deg=0.0, frame_sigma_trans_m=0.0),
    "consistent, 2 px, no frame term, variance factor": OdometryConfig(
        frame_sigma_rot_deg=0.0, frame_sigma_trans_m=0.0, variance_factor=True),
    "consistent, 2 px, no frame term, Huber": OdometryConfig(frame_sigma_rot_deg=0.0, frame_sigma_trans_m=0.0,
                                                             robust="huber"),
    "consistent, 2 px, no frame term, Cauchy": OdometryConfig(frame_sigma_rot_deg=0.0, frame_sigma_trans_m=0.0,
                                                              robust="cauchy"),
    "default + Huber": OdometryConfig(robust="huber"),
    "consistent, 8 px, no frame term": OdometryConfig(pixel_sigma=8.0, frame_sigma_rot_deg=0.0, frame_sigma_trans_m=0.0),
    "thesis, 8 px, phi = 1": OdometryConfig(pixel_sigma=8.0, weighting="thesis", frame_sigma_rot_deg=0.0,
                                           frame_sigma_trans_m=0.0, rolling_shutter_s=0.0),
    "thesis, 8 px, phi = 16": OdometryConfig(pixel_sigma=8.0, weighting="thesis", scale=16.0,
                                            frame_sigma_rot_deg=0.0, frame_sigma_trans_m=0.0, rolling_shutter_s=0.0),
}


def simulation_tables(runs: int, out_dir: Path) -> list[str]:
    lines = ["## Simulation (thesis 5.2)", "",
             f"{runs} Monte Carlo runs per cell, seed 0, 500 points, fr1 intrinsics, the thesis's motion, "
             "depth uniform in the given range. ANEES translation / rotation (consistent: about 3; the 95 % "
             f"acceptance region for {runs} runs is roughly 3 ± {1.96 * np.sqrt(6 / runs):.2f}).", ""]
    pxs = [0.5, 1, 2, 4, 8]
    lines += ["| variant | " + " | ".join(f"{p} px" for p in pxs) + " |", "|---" * (len(pxs) + 1) + "|"]
    keep = {}
    for name, v in SIM_VARIANTS.items():
        cells = []
        for px in pxs:
            r = run_simulation(SimulationConfig(runs=runs, seed=0, pixel_sigma=px, **v))
            cells.append(f"{r.anees_translation:.2f} / {r.anees_rotation:.2f}")
            keep[(name, px)] = r
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines += ["", "Thesis (its Figs 5.2.6/5.2.7, 8 px): 15.64 / 15.72 with phi = 1 and 2.70 / 2.69 with phi = 16.", ""]

    lines += ["### Depth ranges (8 px)", "", "| variant | 1-2 m | 1-3 m | 0.5-5 m | 2-5 m |", "|---|---|---|---|---|"]
    for name, v in SIM_VARIANTS.items():
        cells = []
        for rng_ in [(1.0, 2.0), (1.0, 3.0), (0.5, 5.0), (2.0, 5.0)]:
            r = run_simulation(SimulationConfig(runs=runs, seed=0, pixel_sigma=8.0, depth_range=rng_, **v))
            cells.append(f"{r.anees_translation:.2f} / {r.anees_rotation:.2f}")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")

    lines += ["", "### Predicted vs Monte Carlo standard deviations (consistent weighting, 8 px)", "",
              "| axis | predicted (mean) | Monte Carlo | ratio |", "|---|---|---|---|"]
    r = keep[("consistent (default)", 8)]
    s = r.summary()
    for ax in ("rx", "ry", "rz", "tx", "ty", "tz"):
        p, e = s["sigma_predicted_mean"][ax], s["sigma_empirical"][ax]
        unit = "deg" if ax[0] == "r" else "mm"
        f = np.rad2deg(1) if ax[0] == "r" else 1000.0
        lines.append(f"| {ax} | {p * f:.4f} {unit} | {e * f:.4f} {unit} | {e / p:.2f} |")
    lines += rotation_table(keep[("consistent (default)", 8)])
    from covo_gtsam.plots import plot_simulation

    for name in ("consistent (default)", "thesis, phi = 1"):
        sub = out_dir / ("sim_consistent" if name.startswith("consistent") else "sim_thesis")
        plot_simulation(keep[(name, 8)], sub)
    lines += ["", "![simulation NEES, consistent](consistency/sim_consistent/nees.png)",
              "![simulation NEES, thesis](consistency/sim_thesis/nees.png)",
              "![errors against bounds](consistency/sim_consistent/errors_bounds.png)", ""]
    return lines


def rotation_table(r) -> list[str]:
    """NEES of the same runs under the convention mistakes that can make a rotation covariance look wrong."""
    import gtsam

    from covo_gtsam.covariance import tq_jacobian
    from covo_gtsam.metrics import nees

    T = gtsam.Pose3(make_true_pose(r.config))
    G = tq_jacobian(T)
    Ad = T.AdjointMap()
    e, C = r.errors, r.covariances
    rows = {
        "right perturbation, GTSAM tangent (correct)": (nees(e[:, 3:], C[:, 3:, 3:]), nees(e[:, :3], C[:, :3, :3])),
        "(t, q_v) errors against Q_tq (correct, thesis parameters)": (
            nees(e @ G.T[:, :3], (G @ C @ G.T)[:, :3, :3]), nees(e @ G.T[:, 3:], (G @ C @ G.T)[:, 3:, 3:])),
        "rotation error in radians against the q_v block (half angle mixed up)": (
            nees(e @ G.T[:, :3], (G @ C @ G.T)[:, :3, :3]), nees(e[:, :3], (G @ C @ G.T)[:, 3:, 3:])),
        "left-perturbation error against the right covariance": (
            nees((e @ Ad.T)[:, 3:], C[:, 3:, 3:]), nees((e @ Ad.T)[:, :3], C[:, :3, :3])),
        "covariance times (1/2)^2 as printed in (4.20)": (
            nees(e[:, 3:], C[:, 3:, 3:] / 4), nees(e[:, :3], C[:, :3, :3] / 4)),
    }
    lines = ["### Convention mistakes and their effect (same runs, consistent weighting, 8 px)", "",
             "| how the NEES is formed | ANEES translation | ANEES rotation |", "|---|---|---|"]
    for k, (nt, nr) in rows.items():
        lines.append(f"| {k} | {nt.mean():.2f} | {nr.mean():.2f} |")
    return lines + [""]


def make_true_pose(cfg):
    from covo_gtsam.geometry import pose_from_tum

    return pose_from_tum(np.asarray(cfg.motion))


def real_tables(data: Path, out_dir: Path) -> list[str]:
    seqs = sorted(p for p in (data / "tum").iterdir() if (p / "rgb.txt").is_file()) if (data / "tum").is_dir() else []
    lines = ["## Real data (shared TUM frames)", "",
             "ANEES translation / rotation, then the share of NEES above the chi2(3) 97.5 % quantile (9.35), "
             "and the translational RPE over 30 frames where the sequence is long enough.", ""]
    if not seqs:
        return lines + [f"(no sequences under {data})", ""]
    lines += ["| variant | " + " | ".join(s.name for s in seqs) + " |", "|---" * (len(seqs) + 1) + "|"]
    from covo_gtsam.plots import _plt, nees_histogram
    from covo_gtsam.metrics import relative_pose_nees

    import tempfile

    tmp = Path(tempfile.mkdtemp(prefix="covo-study-"))
    for name, cfg in REAL_VARIANTS.items():
        cells = []
        for s in seqs:
            res = run_sequence(TumSequence(s), tmp / s.name, config=cfg, plots=False, progress=False)
            m = res.metrics
            cell = (f"{m['anees_translation']:.2f} / {m['anees_rotation']:.2f}; "
                    f"{100 * m['share_nees_translation_above_chi2_975']:.0f} % / "
                    f"{100 * m['share_nees_rotation_above_chi2_975']:.0f} %")
            if m.get("rpe_30"):
                cell += f"; RPE30 {m['rpe_30']['trans_rmse']:.4f} m"
            cells.append(cell)
            if name.startswith("default") or name.startswith("thesis, 8 px, phi = 16"):
                plt = _plt()
                T_est, T_true, covs = relative_ground_truth(res.steps, ground_truth_lookup(TumSequence(s)))
                nr, nt = relative_pose_nees(T_est, T_true, covs)
                fig, axes = plt.subplots(1, 2, figsize=(11, 4))
                nees_histogram(axes[0], nt, f"translation NEES, {s.name}")
                nees_histogram(axes[1], nr, f"rotation NEES, {s.name}")
                fig.suptitle(name)
                fig.tight_layout()
                tag = "default" if name.startswith("default") else "thesis16"
                fig.savefig(out_dir / f"real_{tag}_{s.name}.png", dpi=100)
                plt.close(fig)
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines += ["", "Thesis, Table 5.2 (phi = 16, 8 px, whole sequences): fr1 rpy 1.08 / 3.10, fr1 desk 2.88 / 4.99.", ""]
    for s in seqs:
        lines += [f"![NEES default {s.name}](consistency/real_default_{s.name}.png)"]
    return lines + [""]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=300)
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "consistency.md")
    args = ap.parse_args()
    fig_dir = args.out.parent / "consistency"
    fig_dir.mkdir(parents=True, exist_ok=True)
    head = (ROOT / "studies" / "consistency_intro.md").read_text()
    lines = [head, "", "*Generated by `python studies/consistency.py --runs "
             f"{args.runs}`; do not edit by hand.*", ""]
    lines += simulation_tables(args.runs, fig_dir)
    lines += real_tables(args.data, fig_dir)
    args.out.write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
