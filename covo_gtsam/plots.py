"""Figures for runs and simulations (matplotlib, imported lazily; the ``plots`` extra)."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from .chi2 import anees_band, chi2_pdf, chi2_quantile
from .geometry import invert_pose


def _plt():
    try:
        import matplotlib
    except ImportError:  # pragma: no cover - depends on the install
        return None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def nees_histogram(ax, nees: np.ndarray, title: str, dof: int = 3, chains: np.ndarray | None = None,
                   chain_label: str = "chains") -> None:
    """Histogram of NEES values with the chi2(dof) density and its 2.5 %/97.5 % quantiles; with
    ``chains`` (NEES of composed chains) their histogram as an outline on the same bins."""
    nees = np.asarray(nees)
    chains = np.empty(0) if chains is None else np.asarray(chains)
    upper = max(chi2_quantile(0.995, dof) * 1.5, *(float(np.percentile(v, 95)) for v in (nees, chains) if v.size))
    bins = np.linspace(0, upper, 40)
    ax.hist(np.clip(nees, 0, upper), bins=bins, density=True, alpha=0.6, label=f"NEES (mean {np.mean(nees):.2f})")
    if chains.size:
        ax.hist(np.clip(chains, 0, upper), bins=bins, density=True, histtype="step", lw=1.5, color="tab:purple",
                label=f"{chain_label} (mean {np.mean(chains):.2f})")
    x = np.linspace(1e-3, upper, 300)
    ax.plot(x, chi2_pdf(x, dof), "k-", lw=1.5, label=f"$\\chi^2({dof})$ density")
    for p in (0.025, 0.975):
        ax.axvline(chi2_quantile(p, dof), color="r", ls="--", lw=1)
    ax.set_title(title)
    ax.set_xlabel("NEES (values above the range are put in the last bin)")
    ax.set_ylabel("density")
    ax.legend(fontsize=8)


PLOTS_MISSING = 'plots skipped: matplotlib is not installed (pip install "covo-gtsam[plots]")'


def boxplot(ax, data: Sequence, labels: Sequence[str]) -> None:
    """Box plot with tick labels (``tick_labels`` on matplotlib >= 3.9, ``labels`` before)."""
    import matplotlib

    major, minor = (int(x) for x in matplotlib.__version__.split(".")[:2])
    key = "tick_labels" if (major, minor) >= (3, 9) else "labels"
    ax.boxplot(data, **{key: list(labels)})


def save_figure(fig, path: Path) -> Path:
    """Lay out, write (PNG, 110 dpi) and close a figure; return its path."""
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    _plt().close(fig)
    return path


def plane_axes(ax, a: int, b: int, title: str, legend_size: int = 8) -> None:
    """Label a top view on world axes ``a``, ``b`` (0..2 = x, y, z in metres), equal scale, grid, legend."""
    ax.set_xlabel(f"{'xyz'[a]} [m] (first tracked camera frame)")
    ax.set_ylabel(f"{'xyz'[b]} [m]")
    ax.set_title(title)
    ax.axis("equal")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=legend_size)


def ellipse_xy(ax, center: np.ndarray, cov2: np.ndarray, nsigma: float = 3.0, **kw) -> None:
    """Draw the ``nsigma`` ellipse of a 2x2 covariance around ``center`` on a matplotlib axis."""
    vals, vecs = np.linalg.eigh(0.5 * (cov2 + cov2.T))
    vals = np.maximum(vals, 0.0)
    a = np.linspace(0, 2 * np.pi, 60)
    pts = (vecs @ (nsigma * np.sqrt(vals)[:, None] * np.stack([np.cos(a), np.sin(a)]))).T + center
    ax.plot(pts[:, 0], pts[:, 1], **kw)


RUN_PLOTS = ("trajectory.png", "nees.png", "nees_motion.png", "rpe.png", "covariance.png")
SIMULATION_PLOTS = ("nees.png", "errors_bounds.png")


def anees_bars(ax, bins: list[dict], title: str, unit: str, dof: int = 3) -> None:
    """ANEES t / r per bin of ``nees_breakdown`` (bins without pairs left out), each bin's 95 %
    band of a consistent covariance over its pair count (:func:`~covo_gtsam.chi2.anees_band`)."""
    bins = [b for b in bins if b["pairs"]]
    x = np.arange(len(bins))
    for key, colour, shift in (("anees_translation", "tab:blue", -0.2), ("anees_rotation", "tab:orange", 0.2)):
        ax.bar(x + shift, [b[key] for b in bins], width=0.4, color=colour, label=key.split("_")[1])
    for i, b in enumerate(bins):
        n = b["pairs"]
        lo, hi = anees_band(n, dof)
        ax.plot([i - 0.45, i + 0.45], [lo, lo], "k:", lw=0.8)
        ax.plot([i - 0.45, i + 0.45], [hi, hi], "k:", lw=0.8)
    ax.axhline(dof, color="k", lw=0.8)
    labels = [f"{b['range'][0]:g}-{b['range'][1]:g}" if b["range"][1] is not None else f">{b['range'][0]:g}"
              for b in bins]
    ax.set_xticks(x, [f"{lab}\n({b['pairs']})" for lab, b in zip(labels, bins)], fontsize=8)
    ax.set_xlabel(f"{unit} (pairs)")
    ax.set_ylabel("ANEES (3 = consistent; dotted: 95 % band)")
    ax.set_title(title)
    ax.legend(fontsize=8)
    ax.grid(True, axis="y", alpha=0.3)


def twist_change_scatter(ax, points: np.ndarray, response: dict) -> None:
    """Each pair's rotation error along the change of the true angular velocity across it against
    that change's size (``points`` (n, 2): rad/s, rad), with the delay the fit gives
    (``metrics.json``'s ``twist_change_response``) as a line."""
    size, along = points[:, 0], np.rad2deg(points[:, 1])
    ax.plot(size, along, ".", ms=3, alpha=0.6, color="tab:blue", label="frame pairs")
    x = np.array([0.0, float(size.max()) if size.size else 1.0])
    delay, se = response["delay_ms"], response["delay_standard_error_ms"]
    ax.plot(x, np.rad2deg(1e-3 * delay * x), "r-", lw=1.2,
            label=f"delay {delay:.1f} $\\pm$ {se:.1f} ms $\\times$ change")
    ax.axhline(0.0, color="k", lw=0.6)
    ax.set_xlabel("change of the true angular velocity across the pair [rad/s]")
    ax.set_ylabel("rotation error along that change [deg]")
    ax.set_title("rotation error against the change of the turn")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)


def plot_run(steps: Sequence, evaluation, out_dir: Path) -> list[Path] | None:
    """Trajectory with 3-sigma ellipses, NEES histograms and RPE box plots of a run.

    ``evaluation`` is the run's :class:`~covo_gtsam.evaluation.RunEvaluation`: the figures show
    the errors behind its statistics (``metrics.json``), not a second computation of them.
    Returns the files written (figures that need ground truth are left out without it; older
    ones of the same names are removed), or None when matplotlib is not installed.
    """
    plt = _plt()
    if plt is None:
        return None

    out_dir = Path(out_dir)
    for name in RUN_PLOTS:  # a figure this run cannot make must not survive from an earlier one
        (out_dir / name).unlink(missing_ok=True)
    out_dir.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    gt = evaluation.ground_truth
    tracked = [s for s in steps if s.tracked]
    if not tracked:
        return written
    P = np.array([s.pose.matrix() for s in tracked])
    covs = np.array([s.pose_covariance for s in tracked])

    fig, axes = plt.subplots(1, 2, figsize=(12, 5.5))
    gt_first = next((gt[s.timestamp] for s in tracked if s.timestamp in gt), None)
    for ax, (i, j, names) in zip(axes, [(0, 2, "x / z"), (0, 1, "x / y")]):
        ax.plot(P[:, i, 3], P[:, j, 3], "b-", lw=1.2, label="covo")
        if gt_first is not None:
            G = np.array([invert_pose(gt_first) @ gt[s.timestamp] for s in tracked if s.timestamp in gt])
            ax.plot(G[:, i, 3], G[:, j, 3], "k--", lw=1.0, label="ground truth")
        every = max(1, len(tracked) // 15)
        for k in range(0, len(tracked), every):
            R = P[k, :3, :3]
            cov_w = R @ covs[k][3:, 3:] @ R.T  # translation block is body-frame; rotate to world
            ellipse_xy(ax, P[k, [i, j], 3], cov_w[np.ix_([i, j], [i, j])], color="tab:orange", lw=0.8)
        ax.plot([], [], color="tab:orange", lw=0.8, label="3$\\sigma$ (composed)")
        plane_axes(ax, i, j, f"trajectory, {names}")
    written.append(save_figure(fig, out_dir / "trajectory.png"))

    if evaluation.nees_translation.size:
        fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
        label = f"chains of {(evaluation.chains or {}).get('pairs_per_chain')} pairs, composed"
        nees_histogram(axes[0], evaluation.nees_translation, "translation NEES per frame pair",
                       chains=evaluation.chain_nees_translation, chain_label=label)
        nees_histogram(axes[1], evaluation.nees_rotation, "rotation NEES per frame pair",
                       chains=evaluation.chain_nees_rotation, chain_label=label)
        written.append(save_figure(fig, out_dir / "nees.png"))

    if evaluation.breakdown is not None:
        response = evaluation.twist_change
        fig, axes = plt.subplots(1, 3 if response else 2, figsize=(18 if response else 12, 4.2))
        bd = evaluation.breakdown
        anees_bars(axes[0], bd["by_angular_speed_rad_s"], "ANEES by the true angular speed", "rad/s")
        anees_bars(axes[1], bd["by_angular_acceleration_rad_s2"], "ANEES by the true angular acceleration",
                   "rad/s$^2$")
        if response:
            twist_change_scatter(axes[2], evaluation.twist_change_points, response)
        fig.suptitle(f"where the covariance holds, {evaluation.sequence}")
        written.append(save_figure(fig, out_dir / "nees_motion.png"))

    data_t, data_r, labels = [], [], []
    for delta, (tr, rot) in evaluation.rpe_errors.items():
        if tr.size:
            data_t.append(tr * 100)
            data_r.append(np.rad2deg(rot))
            labels.append(f"{delta} frame{'s' if delta > 1 else ''}")
    if data_t:
        fig, axes = plt.subplots(1, 2, figsize=(9, 4))
        boxplot(axes[0], data_t, labels)
        axes[0].set_ylabel("translational RPE [cm]")
        boxplot(axes[1], data_r, labels)
        axes[1].set_ylabel("rotational RPE [deg]")
        for ax in axes:
            ax.grid(True, alpha=0.3)
        fig.suptitle(f"relative pose error, {evaluation.sequence}")
        written.append(save_figure(fig, out_dir / "rpe.png"))

    if evaluation.part_shares is not None and evaluation.part_shares[1].size:
        fig, axes = plt.subplots(1, 2, figsize=(13, 4.2), sharex=True)
        covariance_parts_panels(axes, *evaluation.part_shares)
        fig.suptitle(f"what each pair's covariance is made of, {evaluation.sequence}")
        written.append(save_figure(fig, out_dir / "covariance.png"))
    return written


def plt_colour(i: int):
    """The ``i``-th of 20 distinct colours (matplotlib's tab20, the dark shades first)."""
    import matplotlib

    return matplotlib.colormaps["tab20"](2 * i % 20 + (2 * i // 20) % 2)


def covariance_parts_panels(axes, names: Sequence[str], stamps: np.ndarray, shares: np.ndarray) -> None:
    """Stacked shares of each pair's rotation and translation variance (one panel each) that each
    part of its covariance is (:func:`~covo_gtsam.evaluation.part_shares`), over the pairs' time;
    parts below 1 % everywhere are left out (the stack then stops short of 1 by them)."""
    t = stamps - stamps[0]
    shown = [k for k in range(len(names)) if shares[:, k].max() >= 0.01]
    for b, (ax, block) in enumerate(zip(axes, ("rotation", "translation"))):
        ax.stackplot(t, *(np.clip(shares[:, k, b], 0.0, 1.0) for k in shown), labels=[names[k] for k in shown],
                     colors=[plt_colour(i) for i in range(len(shown))], step="mid", alpha=0.85)
        ax.set_xlim(t[0], max(t[-1], t[0] + 1e-3))
        ax.set_ylim(0.0, 1.0)
        ax.set_xlabel("time of the pair's current frame [s]")
        ax.set_ylabel(f"share of the {block} variance")
        ax.set_title(block)
        ax.grid(True, alpha=0.3)
    axes[1].legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5))


def plot_simulation(result, out_dir: Path) -> list[Path] | None:
    """NEES histograms and per-axis errors against their 1/3-sigma bounds (thesis Figs 5.2.4-5.2.7);
    the files written, or None when matplotlib is not installed."""
    plt = _plt()
    if plt is None:
        return None
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    nees_histogram(axes[0], result.nees_translation, f"translation NEES (ANEES {result.anees_translation:.2f})")
    nees_histogram(axes[1], result.nees_rotation, f"rotation NEES (ANEES {result.anees_rotation:.2f})")
    fig.suptitle(f"simulation, {result.config.weighting} weighting, scale {result.config.scale:g}, "
                 f"{result.config.pixel_sigma:g} px, {len(result.errors)} runs")
    written.append(save_figure(fig, out_dir / "nees.png"))

    sig = np.sqrt(np.einsum("nii->ni", result.covariances))
    names = ["rx [deg]", "ry [deg]", "rz [deg]", "tx [cm]", "ty [cm]", "tz [cm]"]
    unit = np.array([np.rad2deg(1)] * 3 + [100.0] * 3)
    fig, axes = plt.subplots(2, 3, figsize=(13, 6.5), sharex=True)
    runs = np.arange(len(result.errors))
    for k, ax in enumerate(axes.ravel()):
        e, s = result.errors[:, k] * unit[k], sig[:, k] * unit[k]
        ax.plot(runs, e, ".", ms=2, color="tab:blue", label="error")
        ax.plot(runs, s, "-", color="tab:green", lw=0.6, label="$\\pm1\\sigma$")
        ax.plot(runs, -s, "-", color="tab:green", lw=0.6)
        ax.plot(runs, 3 * s, "-", color="tab:red", lw=0.6, label="$\\pm3\\sigma$")
        ax.plot(runs, -3 * s, "-", color="tab:red", lw=0.6)
        inside1 = np.mean(np.abs(e) <= s) * 100
        inside3 = np.mean(np.abs(e) <= 3 * s) * 100
        ax.set_title(f"{names[k]}: {inside1:.0f}% in 1$\\sigma$, {inside3:.1f}% in 3$\\sigma$", fontsize=9)
        ax.grid(True, alpha=0.3)
    axes[0, 0].legend(fontsize=7)
    for ax in axes[1]:
        ax.set_xlabel("run")
    fig.suptitle("errors of T_0,1 (GTSAM tangent, right perturbation) against predicted bounds")
    written.append(save_figure(fig, out_dir / "errors_bounds.png"))
    return written
