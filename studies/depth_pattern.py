"""Three checks of the per-point errors on the shared fr1 frames (quoted in docs/derivation.md).

    python studies/depth_pattern.py [--data ../shared/data]

1. A fixed depth-distortion pattern (a depth error that depends on the pixel, as reported for
   Kinect-type sensors): for each matched point of the consecutive pairs of fr1_rpy, the ray
   residual ``r = (X_cur - T_gt^-1 X_ref) . ray_cur`` with the ground-truth motion at the depth
   images' stamps. A pattern ``e(u, v) Z^p`` (p = 1: a depth multiplier; p = 2: a disparity
   offset) gives ``r ~ Zm^p (e(uv_cur) - e(uv_ref))`` (``Zm`` the mean of the two depths, so the
   regressors do not carry the depths' own noise), plus the ground truth's translation error per
   pair along the ray (fitted per pair and projected out). ``e`` on a polynomial or a bilinear grid
   basis is fitted on frames 0-119 and checked on frames 120-239 and on fr1_desk, and the other way
   round: the share of the weighted residual sum of squares it explains.
2. The per-point image noise at larger spans: the reprojection residual of each inlier pair of
   frames 1, 2 or 3 apart after the pair's own estimate (robust RMS per axis, px), by the span and
   by the ORB octave.
3. The per-point depth noise at larger image displacements: the same pairs' residuals along the
   reference ray after the pair's own estimate, in units of ``sigma_K = 1.425e-3 Z^2`` (Khoshelham
   and Elberink's Kinect depth noise as a yardstick; robust s.d.), by the point's displacement
   between the two images and by the larger of the two frames' stamped colour-depth offsets; and
   their mean square over the per-point model's variance along the ray (both frames' covariances,
   as the estimator weighs them).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from numpy.polynomial import legendre

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import gtsam  # noqa: E402

from covo_gtsam.datasets.tum import TumSequence, interpolate_poses  # noqa: E402
from covo_gtsam.estimator import estimate_relative_pose  # noqa: E402
from covo_gtsam.frontend import associate_frames  # noqa: E402
from covo_gtsam.odometry import VisualOdometry  # noqa: E402
from covo_gtsam.pipeline import kernel_threads  # noqa: E402

RPY, DESK = "rgbd_dataset_freiburg1_rpy_head240", "rgbd_dataset_freiburg1_desk_9frames"
BASES = ("poly2", "poly4", "grid5x4", "grid9x7")


def prepared(seq: TumSequence) -> tuple[VisualOdometry, list]:
    vo = VisualOdometry(seq.camera)
    offsets = np.asarray(seq.depth_timestamps) - np.asarray(seq.timestamps)
    return vo, [vo.prepare(*seq.load(i), float(offsets[i])) for i in range(len(seq))]


def ray_residuals(seq: TumSequence) -> np.ndarray:
    """Rows ``pair, r, Z_cur, Z_ref, u_cur, v_cur, u_ref, v_ref, ray (3)`` of the consecutive pairs."""
    raw = np.loadtxt(seq.path / "groundtruth.txt")
    poses = np.array([gtsam.Pose3(gtsam.Rot3.Quaternion(q[7], q[4], q[5], q[6]), q[1:4]).matrix() for q in raw])
    G, ok = interpolate_poses(raw[:, 0], poses, seq.depth_timestamps)
    vo, frames = prepared(seq)
    rows = []
    for i in range(1, len(frames)):
        if not (ok[i] and ok[i - 1]):
            continue
        p = associate_frames(frames[i - 1], frames[i], vo.config.frontend, camera=vo.camera)
        T = np.linalg.inv(G[i - 1]) @ G[i]  # T_ref,cur at the depth stamps
        ray = p.X_cur / np.linalg.norm(p.X_cur, axis=1, keepdims=True)
        r = np.sum((p.X_cur - (p.X_ref - T[:3, 3]) @ T[:3, :3]) * ray, axis=1)
        rows.append(np.column_stack([np.full(len(r), i), r, p.X_cur[:, 2], p.X_ref[:, 2], p.uv_cur, p.uv_ref, ray]))
    d = np.vstack(rows)
    return d[np.abs(d[:, 1]) < 0.1]  # gross mismatches out


def basis(uv: np.ndarray, kind: str, width: int, height: int) -> np.ndarray:
    """Pattern basis at pixels ``uv``: Legendre polynomials up to a total degree (no constant,
    which cancels in the difference) or bilinear hats on a grid."""
    u, v = 2 * uv[:, 0] / (width - 1) - 1, 2 * uv[:, 1] / (height - 1) - 1
    if kind.startswith("poly"):
        deg = int(kind[4:])
        return np.column_stack([legendre.legval(u, np.eye(a + 1)[a]) * legendre.legval(v, np.eye(b + 1)[b])
                                for a in range(deg + 1) for b in range(deg + 1 - a) if a + b])
    nx, ny = map(int, kind[4:].split("x"))
    gx, gy = (u + 1) / 2 * (nx - 1), (v + 1) / 2 * (ny - 1)
    return np.column_stack([np.clip(1 - abs(gx - a), 0, 1) * np.clip(1 - abs(gy - b), 0, 1)
                            for a in range(nx) for b in range(ny)])


def whitened(d: np.ndarray, M: np.ndarray) -> np.ndarray:
    """Columns of ``M`` weighted by the depth noise (1 / (Z_cur^4 + Z_ref^4)) with each pair's
    translation along the rays projected out."""
    w = np.sqrt(1.0 / (d[:, 2] ** 4 + d[:, 3] ** 4))[:, None]
    out = np.empty_like(M)
    for pair in np.unique(d[:, 0]):
        s = d[:, 0] == pair
        R, Ms = d[s, 8:11] * w[s], M[s] * w[s]
        out[s] = Ms - R @ np.linalg.lstsq(R, Ms, rcond=None)[0]
    return out


def explained(train: np.ndarray, tests: list[np.ndarray], kind: str, power: int, size: tuple[int, int]) -> list[float]:
    """Share (%) of the whitened residual sum of squares of each test set that the pattern fitted
    on ``train`` explains (points beyond 4 robust sigma left out)."""
    def design(d):
        zm = (0.5 * (d[:, 2] + d[:, 3]))[:, None] ** power
        return whitened(d, zm * (basis(d[:, 4:6], kind, *size) - basis(d[:, 6:8], kind, *size)))

    X, y = design(train), whitened(train, train[:, 1:2])[:, 0]
    keep = np.ones(len(y), bool)
    for _ in range(2):
        c = np.linalg.lstsq(X[keep], y[keep], rcond=None)[0]
        e = y - X @ c
        keep = np.abs(e) < 4 * 1.4826 * np.median(np.abs(e[keep]))
    out = []
    for d in tests:
        Xh, yh = design(d), whitened(d, d[:, 1:2])[:, 0]
        k = np.abs(yh) < 4 * 1.4826 * np.median(np.abs(yh))
        out.append(100 * (1 - np.sum((yh - Xh @ c)[k] ** 2) / np.sum(yh[k] ** 2)))
    return out


def span_pairs(seq: TumSequence) -> list:
    """Per pair of frames 1, 2 and 3 apart with enough inliers: ``(k, i, pairs, frames, X, R)``,
    ``X`` the current points moved into the reference frame by the pair's own estimate, ``R`` its
    rotation."""
    vo, frames = prepared(seq)
    out = []
    for k in (1, 2, 3):
        for i in range(k, len(frames)):
            p = associate_frames(frames[i - k], frames[i], vo.config.frontend, camera=vo.camera)
            if p.num_inliers < vo.config.frontend.min_pairs:
                continue
            M = estimate_relative_pose(p.X_ref, p.X_cur, p.Q_ref, p.Q_cur).pose.matrix()
            out.append((k, i, p, frames, p.X_cur @ M[:3, :3].T + M[:3, 3], M[:3, :3]))
    return out


def robust_sd(x: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(x - np.median(x))))


def pixel_residuals(seq: TumSequence, pairs: list) -> list[str]:
    cam = VisualOdometry(seq.camera).camera
    lines = ["| frames apart | points | robust RMS per axis (px) | octave 0 | octave 3 | octave 7 |",
             "|---|---|---|---|---|---|"]
    res, octave, span = [], [], []
    for k, i, p, frames, X, _ in pairs:
        uv = cam.undistort(p.uv_ref)
        res.append(np.hypot(cam.fx * X[:, 0] / X[:, 2] + cam.cx - uv[:, 0],
                            cam.fy * X[:, 1] / X[:, 2] + cam.cy - uv[:, 1]))
        octave.append(np.maximum(frames[i - k].features.octave[p.idx_ref], frames[i].features.octave[p.idx_cur]))
        span.append(np.full(len(X), k))
    res, octave, span = np.concatenate(res), np.concatenate(octave), np.concatenate(span)
    for k in (1, 2, 3):
        res_k, octave_k = res[span == k], octave[span == k]

        def rms(x):  # per axis, from the median of the 2-D norm (Rayleigh: median^2 = 1.386 sigma^2)
            return np.sqrt(np.median(x**2) / 1.386)

        by_octave = " | ".join(f"{rms(res_k[octave_k == o]):.2f}" for o in (0, 3, 7))
        lines.append(f"| {k} | {len(res_k)} | {rms(res_k):.2f} | {by_octave} |")
    return lines


def depth_residuals(seq: TumSequence, pairs: list) -> list[str]:
    """Robust s.d. of the residuals along the reference ray after each pair's own estimate, in
    units of sigma_K = 1.425e-3 Z^2 (Z the two depths' mean), by the point's image
    displacement and the pair's larger stamped colour-depth offset."""
    offset = np.abs(np.asarray(seq.depth_timestamps) - np.asarray(seq.timestamps))
    rows = []
    for k, i, p, _, X, R in pairs:
        ray = p.X_ref / np.linalg.norm(p.X_ref, axis=1, keepdims=True)
        z = 0.5 * (p.X_cur[:, 2] + p.X_ref[:, 2])
        r = np.sum((X - p.X_ref) * ray, axis=1)
        var = np.einsum("ni,nij,nj->n", ray, p.Q_ref + R @ p.Q_cur @ R.T, ray)  # the model's, along the ray
        rows.append(np.column_stack([r / (1.425e-3 * z**2), r**2 / var, np.linalg.norm(p.uv_cur - p.uv_ref, axis=1),
                                     np.full(len(X), 1e3 * max(offset[i], offset[i - k]))]))
    r, model, disp, off = np.vstack(rows).T
    bands = ((0, 5), (5, 12), (12, np.inf))
    lines = ["| image displacement (px) | points | robust s.d. (sigma_K) | offset below 5 ms | 5-12 ms | above 12 ms "
             "| mean square over the point model's variance |", "|---|---|---|---|---|---|---|"]
    for lo, hi in ((0, 30), (30, 50), (50, 80), (80, np.inf)):
        m = (disp >= lo) & (disp < hi)
        cells = [f"{robust_sd(r[m & (off >= a) & (off < b)]):.2f}" if np.sum(m & (off >= a) & (off < b)) >= 300
                 else "—" for a, b in bands]
        lines.append(f"| {lo}-{hi} | {int(m.sum())} | {robust_sd(r[m]):.2f} | " + " | ".join(cells)
                     + f" | {model[m].mean():.2f} |")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    args = parser.parse_args()
    rpy_seq, desk_seq = TumSequence(args.data / "tum" / RPY), TumSequence(args.data / "tum" / DESK)
    size = (rpy_seq.camera.width, rpy_seq.camera.height)
    with kernel_threads(1):
        rpy, desk = ray_residuals(rpy_seq), ray_residuals(desk_seq)
        a, b = rpy[rpy[:, 0] <= 119], rpy[rpy[:, 0] >= 121]
        print("Share of the ray residuals' weighted sum of squares a fixed depth pattern explains (%; A = frames "
              "0-119, B = frames 120-239 of fr1_rpy):\n")
        print("| pattern | fitted on A: A / B / fr1_desk | fitted on B: B / A / fr1_desk |")
        print("|---|---|---|")
        for kind in BASES:
            for power, name in ((1, "depth multiplier"), (2, "disparity offset")):
                fa = explained(a, [a, b, desk], kind, power, size)
                fb = explained(b, [b, a, desk], kind, power, size)
                print(f"| {kind}, {name} | " + " / ".join(f"{x:.1f}" for x in fa) + " | "
                      + " / ".join(f"{x:.1f}" for x in fb) + " |")
        print(f"\n({len(a)} / {len(b)} / {len(desk)} points)\n\nReprojection residuals after each pair's own estimate, "
              "fr1_rpy:\n")
        pairs = span_pairs(rpy_seq)
        print("\n".join(pixel_residuals(rpy_seq, pairs)))
        print("\nResiduals along the ray after each pair's own estimate (frames 1, 2 and 3 apart), fr1_rpy:\n")
        print("\n".join(depth_residuals(rpy_seq, pairs)))


if __name__ == "__main__":
    main()
