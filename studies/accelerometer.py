"""Can the Kinect's accelerometer stand in for a gyroscope? (quoted in docs/derivation.md)

    python studies/accelerometer.py [--data ../shared/data]

Every TUM RGB-D sequence has ``accelerometer.txt``, the Kinect's own accelerometer (specific force,
m/s^2, in its axes). The latency and rolling-shutter terms need each pair's change of the angular
velocity, which the run's own twists give too noisily (docs/derivation.md, "Latency"); an
accelerometer sees the angular velocity only through the turning of gravity, ``du/dt = -w x u``
(``u`` the unit specific force, as if the camera did not accelerate), so it gives the angular
velocity's components across gravity. Over fr1_rpy's ground-truth span:

1. The accelerometer's axes against the camera's and the world's up direction, fitted by least
   squares on ``u`` (averaged over one frame interval) against the reference's rotation (several
   starts), and the angle left between them.
2. Per camera axis: the angular velocity across gravity from ``u``'s turning against the
   reference's, its correlation and RMS error, over one frame interval and averaged over three;
   the same for the change of the angular velocity from one frame interval to the next (what the
   terms need), against the reference's change.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation, Slerp

ROOT = Path(__file__).resolve().parent.parent
PERIOD = 1 / 30  # s, the frame interval


def window_means(t: np.ndarray, x: np.ndarray, at: np.ndarray, width: float) -> np.ndarray:
    """Mean of the samples ``x`` (n, d) at times ``t`` within ``width`` / 2 of each of ``at``."""
    c = np.vstack([np.zeros(x.shape[1]), np.cumsum(x, axis=0)])
    lo, hi = np.searchsorted(t, at - width / 2), np.searchsorted(t, at + width / 2)
    return (c[hi] - c[lo]) / np.maximum(hi - lo, 1)[:, None]


def up(x: np.ndarray) -> np.ndarray:
    return np.array([np.cos(x[0]) * np.cos(x[1]), np.cos(x[0]) * np.sin(x[1]), np.sin(x[0])])


def fit_axes(u: np.ndarray, R_wc: Rotation) -> tuple[Rotation, np.ndarray]:
    """The rotation ``A`` of the accelerometer's axes into the camera's and the world's up
    direction ``e`` with ``A u ~ R_wc^T e``, least squares from 30 random starts."""

    def residual(x):
        return (Rotation.from_rotvec(x[:3]).apply(u) - R_wc.inv().apply(np.tile(up(x[3:]), (len(u), 1)))).ravel()

    rng = np.random.default_rng(0)
    best = min((least_squares(residual, np.r_[Rotation.random(random_state=k).as_rotvec(),
                                               rng.uniform(-1.5, 1.5), rng.uniform(-3, 3)]) for k in range(30)),
               key=lambda r: r.cost)
    return Rotation.from_rotvec(best.x[:3]), up(best.x[3:])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    folder = parser.parse_args().data / "tum" / "rgbd_dataset_freiburg1_rpy_head240"
    acc, gt = np.loadtxt(folder / "accelerometer.txt"), np.loadtxt(folder / "groundtruth.txt")
    t = np.arange(max(acc[0, 0], gt[0, 0]) + 0.2, min(acc[-1, 0], gt[-1, 0]) - 0.2, PERIOD)
    R_wc = Slerp(gt[:, 0], Rotation.from_quat(gt[:, 4:8]))(t)
    print(f"fr1_rpy: {len(acc)} accelerometer samples over {acc[-1, 0] - acc[0, 0]:.1f} s; "
          f"{len(t)} frame intervals with the reference")
    for average in (1, 3):
        f = window_means(acc[:, 0], acc[:, 1:], t, average * PERIOD)
        u = f / np.linalg.norm(f, axis=1, keepdims=True)
        A, e = fit_axes(u, R_wc)
        gap = np.degrees(np.arccos(np.clip(np.sum(A.apply(u) * R_wc.inv().apply(np.tile(e, (len(t), 1))), 1), -1, 1)))
        u = A.apply(u)
        w_ref = (R_wc[:-1].inv() * R_wc[1:]).as_rotvec() / PERIOD  # camera axes, rad/s
        mid = u[1:] + u[:-1]
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        w_acc = -np.cross(mid, np.diff(u, axis=0) / PERIOD)
        w_ref = w_ref - np.sum(w_ref * mid, axis=1, keepdims=True) * mid  # the components across gravity
        print(f"\naveraged over {average} frame interval(s): gravity's direction within {np.median(gap):.1f} deg "
              f"(median; 90 %: {np.percentile(gap, 90):.1f} deg) of the reference's")
        for label, a, b in (("angular velocity (rad/s)", w_acc, w_ref),
                            ("its change per interval (rad/s)", np.diff(w_acc, axis=0), np.diff(w_ref, axis=0))):
            corr = [np.corrcoef(a[:, i], b[:, i])[0, 1] for i in range(3)]
            err, size = np.sqrt(np.mean((a - b) ** 2, axis=0)), np.sqrt(np.mean(b**2, axis=0))
            print(f"  {label}, camera x / y / z: correlation {' / '.join(f'{c:.2f}' for c in corr)}; "
                  f"RMS error {' / '.join(f'{v:.2f}' for v in err)} against RMS {' / '.join(f'{v:.2f}' for v in size)}")


if __name__ == "__main__":
    main()
