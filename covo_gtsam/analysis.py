"""Noise analysis against ground truth (thesis 5.3.1): pixel errors of matched inliers and depth residuals.

For each frame pair (k, k+1) the front end's inlier pairs (pseudo-inliers included) are checked with
the ground-truth relative pose ``T_k,k1``: the point of frame k+1 is moved into frame k and
projected (with distortion) into image k; the image-plane error is the measured keypoint of frame k
minus that projection (pixels). The depth residual is the measured depth in frame k minus the
depth of the moved point, divided by the model's ``sqrt(sigma_Z(z_k)^2 + sigma_Z(z_k1)^2)`` — a
standard normal if the depth model is right.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .datasets import frame_count
from .datasets.tum import TumSequence
from .errors import DatasetError, InputError
from .frontend import FrontendConfig, associate_frames, make_orb, prepare_frame
from .geometry import invert_pose
from .noise import KinectAxialNoise, PixelNoise, PointNoiseModel
from .validation import MAX_PIXEL_SIGMA, MIN_PIXEL_SIGMA, check_int, check_real


def robust_sigma(x: np.ndarray) -> float:
    """1.4826 x median absolute deviation about the median."""
    x = np.asarray(x, dtype=float)
    return float(1.4826 * np.median(np.abs(x - np.median(x)))) if x.size else float("nan")


def analyze_sequence(seq: TumSequence, cfg: FrontendConfig | None = None, pixel_sigma: float = 2.0,
                     max_frames: int | None = None, progress: bool = False) -> dict:
    """Per-pair and overall statistics of pixel errors and normalised depth residuals.

    Frames are paired with the next one; a pair needs both frames readable, both with ground
    truth and matched points in front of the camera.

    Raises:
        ConfigError: ``max_frames`` is not an integer >= 2 (or None), ``pixel_sigma`` is not a
            positive number, or ``cfg`` does not fit the camera's image size.
        DatasetError: no ground truth, fewer than 2 frames, or no frame pair could be analysed.
    """
    if max_frames is not None:
        check_int("max_frames", max_frames, 2)
    check_real("pixel_sigma", pixel_sigma, "positive", MIN_PIXEL_SIGMA, MAX_PIXEL_SIGMA)
    if seq.groundtruth is None:
        raise DatasetError(f"{seq.path}: the noise analysis needs groundtruth.txt")
    cfg = cfg or FrontendConfig()
    cam = seq.camera
    cfg.check_image_size(cam.width, cam.height)
    orb = make_orb(cfg)
    depth_model = KinectAxialNoise()
    model = PointNoiseModel(pixel=PixelNoise(pixel_sigma, pixel_sigma), depth=depth_model)
    n = frame_count(seq, max_frames)
    if n < 2:
        raise DatasetError(f"{seq.path}: the noise analysis needs at least 2 frames (frame pairs), got {n}")
    frames = range(n)
    if progress:
        from tqdm import tqdm

        frames = tqdm(frames, desc="analyze", unit="frame")
    prev = None
    per_pair, all_du, all_dv, all_dz = [], [], [], []
    for i in frames:
        try:
            cur = prepare_frame(*seq.load(i), cam, orb, model, cfg)
        except InputError:  # missing, unreadable, corrupt or wrong-sized image: the pair chain restarts
            prev = None
            continue
        if prev is not None and seq.gt_valid[i] and seq.gt_valid[prev[0]]:
            j, ref = prev
            pairs = associate_frames(ref, cur, cfg)
            if len(pairs):
                T = invert_pose(seq.groundtruth[j]) @ seq.groundtruth[i]
                Xm = pairs.X_cur @ T[:3, :3].T + T[:3, 3]
                ok = Xm[:, 2] > 0
                if not ok.any():
                    prev = (i, cur)
                    continue
                proj = cam.distort(cam.project(Xm[ok]))
                d = pairs.uv_ref[ok] - proj
                dz = (pairs.X_ref[ok, 2] - Xm[ok, 2]) / np.hypot(
                    depth_model.sigma(pairs.X_ref[ok, 2]), depth_model.sigma(pairs.X_cur[ok, 2]))
                all_du.append(d[:, 0])
                all_dv.append(d[:, 1])
                all_dz.append(dz)
                err = np.hypot(d[:, 0], d[:, 1])
                per_pair.append({
                    "t_ref": float(seq.timestamps[j]), "t_cur": float(seq.timestamps[i]),
                    "pairs": int(ok.sum()), "std_u": float(np.std(d[:, 0])), "std_v": float(np.std(d[:, 1])),
                    "robust_sigma_u": robust_sigma(d[:, 0]), "robust_sigma_v": robust_sigma(d[:, 1]),
                    "share_above_10px": float(np.mean(err > 10.0)),
                    "depth_residual_std": float(np.std(dz)), "depth_residual_robust_sigma": robust_sigma(dz),
                })
        prev = (i, cur)
    if not per_pair:
        raise DatasetError(
            f"{seq.path}: no frame pair could be analysed among the first {n} frames (a pair needs two "
            "consecutive readable frames with ground truth and matched points)")
    du = np.concatenate(all_du) if all_du else np.zeros(0)
    dv = np.concatenate(all_dv) if all_dv else np.zeros(0)
    dz = np.concatenate(all_dz) if all_dz else np.zeros(0)
    err = np.hypot(du, dv)
    return {
        "sequence": seq.name,
        "frame_pairs": len(per_pair),
        "points": int(du.size),
        "pixel_error": {
            "std_u": float(np.std(du)), "std_v": float(np.std(dv)),
            "robust_sigma_u": robust_sigma(du), "robust_sigma_v": robust_sigma(dv),
            "median_norm": float(np.median(err)) if err.size else None,
            "p90_norm": float(np.percentile(err, 90)) if err.size else None,
            "share_above_10px": float(np.mean(err > 10)) if err.size else None,
        },
        "depth_residual_normalised": {
            "std": float(np.std(dz)), "robust_sigma": robust_sigma(dz),
            "share_abs_above_3": float(np.mean(np.abs(dz) > 3)) if dz.size else None,
        },
        "per_pair": per_pair,
        "_samples": {"du": du, "dv": dv, "dz": dz},
    }


def plot_noise(summary: dict, out_dir: Path) -> list[Path] | None:
    """Figures of 5.3.1-5.3.3: error histogram, per-pair sigma over time, box plots; depth residuals.
    Returns the files written, or None when matplotlib is not installed."""
    from .plots import _plt, boxplot, save_figure

    plt = _plt()
    if plt is None:
        return None
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    s = summary["_samples"]
    pp = summary["per_pair"]
    written = []
    fig, axes = plt.subplots(2, 2, figsize=(12, 8))
    lim = 20
    axes[0, 0].hist(np.clip(s["du"], -lim, lim), bins=80, alpha=0.6, label="u")
    axes[0, 0].hist(np.clip(s["dv"], -lim, lim), bins=80, alpha=0.6, label="v")
    axes[0, 0].set_xlabel(f"image-plane error [px] (clipped at ±{lim})")
    axes[0, 0].set_title("pixel errors of matched inliers against ground truth")
    axes[0, 0].legend()
    t = np.array([p["t_cur"] for p in pp]) - (pp[0]["t_cur"] if pp else 0)
    axes[0, 1].plot(t, [p["std_u"] for p in pp], ".-", ms=3, label="std u")
    axes[0, 1].plot(t, [p["std_v"] for p in pp], ".-", ms=3, label="std v")
    axes[0, 1].plot(t, [p["robust_sigma_u"] for p in pp], "-", lw=0.8, label="robust sigma u")
    axes[0, 1].set_xlabel("time [s]")
    axes[0, 1].set_ylabel("[px]")
    axes[0, 1].set_title("per frame pair")
    axes[0, 1].legend(fontsize=8)
    boxplot(axes[1, 0], [[p["std_u"] for p in pp], [p["std_v"] for p in pp]], ["std u", "std v"])
    axes[1, 0].set_ylabel("[px]")
    axes[1, 0].set_title("per-pair standard deviations")
    x = np.linspace(-5, 5, 200)
    axes[1, 1].hist(np.clip(s["dz"], -8, 8), bins=80, density=True, alpha=0.6, label="normalised depth residual")
    axes[1, 1].plot(x, np.exp(-x**2 / 2) / np.sqrt(2 * np.pi), "k-", label="N(0, 1)")
    axes[1, 1].set_title("depth residuals / model sigma (4.7)")
    axes[1, 1].legend(fontsize=8)
    for ax in axes.ravel():
        ax.grid(True, alpha=0.3)
    written.append(save_figure(fig, out_dir / "noise.png"))
    return written
