"""``covo evaluate``: ``covo run`` on many sequences (TUM folders or ROS bags), one results folder each,
and a summary table.

Each sequence runs as one task of :func:`covo_gtsam.parallel.map_tasks` (serially, on a local
process pool, or on a Dask cluster) into ``OUT/<name>/``, exactly as ``covo run`` would; the
summary rows come from each run's metrics:

==================  ===========================================================================
column              meaning
==================  ===========================================================================
sequence            the sequence's name (its results folder)
frames, lost        frames processed, frames without a pose
flagged             pairs the integrity check flagged (metrics.json's flagged_pairs)
weak_consensus      pairs kept with fewer than half of their matches agreeing in 3-D (weak_consensus_pairs)
rpe1_m, rpe30_m     translational RPE RMSE (m) over 1 and 30 frames (empty without ground truth)
ate_m               ATE RMSE (m) after alignment
anees_t, anees_r    ANEES of translation and rotation (3 = consistent)
above_9.35_t/_r     share of frame pairs whose NEES exceeds chi2(3) 97.5 % = 9.35
chain_anees_t/_r    the same over chains of 30 linked pairs (composed as between factors; metrics.json's chains)
chain_anees_r_axes_turned_back
                    their rotation ANEES against the reference turned back by reference_axes
twist_change_delay_ms
                    the delay of the images against the reference (twist_change_response's delay_ms)
worst_60_t/_r       the highest ANEES of the run's blocks of 60 pairs (metrics.json's nees_breakdown; empty
                    for fewer pairs): where an ANEES near 3 hides a stretch the covariance does not cover
frames_per_s        speed of that run (the only column that depends on where it ran)
==================  ===========================================================================

Written: ``summary.csv``, ``summary.md`` and ``plots/summary.png`` (with matplotlib).
"""

from __future__ import annotations

import csv
import math
import os
import warnings
from pathlib import Path

from .errors import ConfigError, CovoError, CovoWarning, DatasetError

__all__ = ["COLUMNS", "evaluate_sequences", "run_one", "summary_row"]

COLUMNS = ("sequence", "frames", "lost", "flagged", "weak_consensus", "rpe1_m", "rpe30_m", "ate_m", "anees_t", "anees_r",
           "above_9.35_t", "above_9.35_r", "chain_anees_t", "chain_anees_r", "chain_anees_r_axes_turned_back",
           "twist_change_delay_ms", "worst_60_t", "worst_60_r", "frames_per_s")


def _get(m: dict, *keys):
    for k in keys:
        if not isinstance(m, dict) or m.get(k) is None:
            return None
        m = m[k]
    return m


def summary_row(name: str, metrics: dict) -> dict:
    """The summary row of one run's ``metrics.json`` dict (None where a metric is missing): the
    :data:`COLUMNS`, then ``relative_poses`` as :func:`run_one` gives it and ``error`` (the message
    of a run that failed, else None; not columns)."""
    return {
        "sequence": name,
        "frames": metrics.get("frames"),
        "lost": metrics.get("lost_frames"),
        "flagged": metrics.get("flagged_pairs"),
        "weak_consensus": metrics.get("weak_consensus_pairs"),
        "rpe1_m": _get(metrics, "rpe_1", "trans_rmse"),
        "rpe30_m": _get(metrics, "rpe_30", "trans_rmse"),
        "ate_m": _get(metrics, "ate", "rmse"),
        "anees_t": metrics.get("anees_translation"),
        "anees_r": metrics.get("anees_rotation"),
        "above_9.35_t": metrics.get("share_nees_translation_above_chi2_975"),
        "above_9.35_r": metrics.get("share_nees_rotation_above_chi2_975"),
        "chain_anees_t": _get(metrics, "chains", "anees_translation"),
        "chain_anees_r": _get(metrics, "chains", "anees_rotation"),
        "chain_anees_r_axes_turned_back": _get(metrics, "reference_axes", "chains_anees_rotation"),
        "twist_change_delay_ms": _get(metrics, "twist_change_response", "delay_ms"),
        "worst_60_t": _get(metrics, "nees_breakdown", "windows", "anees_translation", "highest"),
        "worst_60_r": _get(metrics, "nees_breakdown", "windows", "anees_rotation", "highest"),
        "frames_per_s": metrics.get("frames_per_second"),
        "relative_poses": metrics.get("relative_poses"),
        "error": metrics.get("error"),
    }


def _open_sequence(path: str, camera: str | None, topics: dict):
    from .camera_file import resolve_camera
    from .datasets.rosbag import RosbagSequence, is_bag
    from .datasets.tum import TumSequence

    cam, scale = resolve_camera(camera)
    if is_bag(path):
        return RosbagSequence(path, camera=cam, **topics), scale
    return TumSequence(path, camera=cam), scale


def run_one(path: str, out_dir: str, camera: str | None = None, config: dict | None = None,
            max_frames: int | None = None, plots: bool = False, topics: dict | None = None,
            bag_out: str | None = None) -> dict:
    """``covo run`` of one sequence into ``out_dir``; returns its ``metrics.json`` dict with
    ``relative_poses`` added (the frames that got a relative pose: the lines of ``relative.txt``).
    Plain arguments only (it runs on other processes and machines)."""
    from .config import OdometryConfig
    from .pipeline import run_sequence

    with warnings.catch_warnings():  # what opening a TUM folder warns about was shown when it was checked
        warnings.simplefilter("ignore", CovoWarning)
        seq, scale = _open_sequence(path, camera, topics or {})
    cfg = OdometryConfig.from_dict(config) if config else OdometryConfig()
    if scale is not None:
        cfg = cfg.replace(sensor={"depth_scale": scale})
    result = run_sequence(seq, out_dir, config=cfg, max_frames=max_frames, plots=plots, progress=False,
                          bag_out=bag_out)
    return {**result.metrics, "relative_poses": sum(s.has_relative_pose for s in result.steps)}


def _run_or_error(*args) -> dict:
    """:func:`run_one`, or ``{"error": message}`` when the run fails with a :class:`CovoError` (a bag
    that cannot be read): the study goes on with the other sequences and reports it."""
    try:
        return run_one(*args)
    except CovoError as exc:
        return {"error": str(exc)}


def _names(paths: list[str]) -> list[str]:
    """Results-folder names: the sequence names, made unique with ``_2``, ``_3``, ..."""
    seen: dict[str, int] = {}
    out = []
    for p in paths:
        base = Path(os.path.abspath(p)).name
        base = base[:-4] if base.lower().endswith(".bag") else base
        seen[base] = seen.get(base, 0) + 1
        out.append(base if seen[base] == 1 else f"{base}_{seen[base]}")
    return out


def _check_inputs(paths: list[str], camera: str | None, topics: dict | None) -> None:
    """Every TUM folder opened (its lists, ground truth and camera) before the first run: one that
    cannot be used stops the study before hours of runs are spent on the others. A bag is checked
    when its run opens it (opening reads the whole bag)."""
    from .datasets.rosbag import is_bag

    for p in paths:
        if not (is_bag(p) or (Path(p) / "rgb.txt").is_file()):
            raise DatasetError(f"{p}: neither a TUM sequence folder (rgb.txt) nor a ROS bag (.bag file or "
                               "folder with metadata.yaml)")
    for p in paths:
        if is_bag(p):
            continue
        seq, _ = _open_sequence(p, camera, topics or {})
        _ = seq.camera  # a TUM folder's camera comes from its name: an error when it cannot


def _fmt(v, digits: int = 4) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return ""
    if isinstance(v, float):
        return f"{v:.{digits}g}" if abs(v) < 1e-3 and v != 0 else f"{v:.{digits}f}"
    return str(v)


#: the study's own files in its folder (besides each sequence's results folder and plots/summary.png)
SUMMARY_FILES = ("summary.csv", "summary.md")


def _summary_sequences(out: Path) -> list[str]:
    """The sequences (results-folder names) an earlier study's ``summary.csv`` in ``out`` lists; none
    without a readable one."""
    try:
        with open(out / "summary.csv", newline="") as f:
            return [row["sequence"] for row in csv.DictReader(f) if row.get("sequence")]
    except (OSError, csv.Error, KeyError, UnicodeDecodeError):
        return []


def write_summary(out: Path, rows: list[dict]) -> None:
    """``summary.csv`` (full precision) and ``summary.md`` (rounded) of the rows."""
    with open(out / "summary.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: "" if r[k] is None else (repr(r[k]) if isinstance(r[k], float) else r[k]) for k in COLUMNS})
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for r in rows:
        lines.append("| " + " | ".join(_fmt(r[k], 1 if k == "frames_per_s" else 4) for k in COLUMNS) + " |")
    (out / "summary.md").write_text("\n".join(lines) + "\n")


def plot_summary(out: Path, rows: list[dict]) -> Path | None:
    """``plots/summary.png``: RPE over 1 frame and ANEES per sequence; None without matplotlib."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    names = [r["sequence"] for r in rows]
    x = range(len(rows))
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(max(6, 1.2 * len(rows) + 4), 3.5))
    a1.bar(x, [r["rpe1_m"] or 0 for r in rows])
    a1.set_ylabel("RPE 1 frame, translation RMSE (m)")
    w = 0.4
    a2.bar([i - w / 2 for i in x], [r["anees_t"] or 0 for r in rows], w, label="translation")
    a2.bar([i + w / 2 for i in x], [r["anees_r"] or 0 for r in rows], w, label="rotation")
    a2.axhline(3.0, color="k", lw=0.8, ls="--", label="consistent (3)")
    a2.set_ylabel("ANEES")
    a2.legend(fontsize=8)
    for a in (a1, a2):
        a.set_xticks(list(x))
        a.set_xticklabels(names, rotation=20, ha="right", fontsize=7)
    fig.tight_layout()
    (out / "plots").mkdir(exist_ok=True)
    path = out / "plots" / "summary.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def evaluate_sequences(paths: list[str], out_dir: str | os.PathLike, camera: str | None = None,
                       config: dict | None = None, max_frames: int | None = None, workers: int | None = None,
                       scheduler: str | None = None, timeout: float | None = None, plots: bool = True,
                       topics: dict | None = None, progress: bool = False) -> list[dict]:
    """Run every sequence (see the module docstring) and write the summary; returns the rows
    (:func:`summary_row`).

    A run that fails (a bag that cannot be read; TUM folders are opened before the first run) gets
    a row with its ``error`` and empty metrics, and the others go on.

    Raises:
        DatasetError: a path is neither a TUM folder nor a bag, or a TUM folder cannot be used.
        ConfigError: the scheduler cannot be reached.
    """
    from .parallel import CONNECT_TIMEOUT, map_tasks
    from .pipeline import check_not_a_sequence, check_output_dir, prepare_outputs

    paths = [os.path.abspath(os.fspath(p)) for p in paths]
    if not paths:
        raise ConfigError("evaluate needs at least one sequence")
    _check_inputs(paths, camera, topics)
    out = check_output_dir(Path(out_dir))
    names = _names(paths)
    for n in names:  # before anything is written: no sequence's results go into a dataset
        check_not_a_sequence(out / n)
    earlier = _summary_sequences(out)
    # an earlier study's summary and figure go first (also with plots off: never a stale figure)
    prepare_outputs(out, SUMMARY_FILES, ("plots", ("summary.png",)), write_figures=plots)
    left = [n for n in earlier if n not in names and (out / n).is_dir()]
    if left:
        warnings.warn(f"{out}: the results folders of an earlier study's sequences stay ({', '.join(left)}); "
                      "the summary lists this study's only", CovoWarning, stacklevel=2)
    args = [(p, str(out / n), camera, config, max_frames, plots, topics) for p, n in zip(paths, names)]
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(args), desc="evaluate", unit="sequence")
    try:
        metrics = map_tasks(_run_or_error, args, workers=workers, scheduler=scheduler,
                            timeout=timeout or CONNECT_TIMEOUT,
                            progress=(lambda k: bar.update(k - bar.n)) if bar is not None else None)
    finally:
        if bar is not None:
            bar.close()
    rows = [summary_row(n, m) for n, m in zip(names, metrics)]
    write_summary(out, rows)
    if plots and plot_summary(out, rows) is None:
        import sys

        from .plots import PLOTS_MISSING

        print(PLOTS_MISSING, file=sys.stderr)
    return rows
