"""Where a run's covariance holds and where it does not: the pairs' NEES by the camera's true
motion, over windows of the run, and in its tails (``metrics.json``'s ``nees_breakdown``).

An ANEES near 3 over a whole run can hide a model that is conservative on slow pairs and
overconfident on fast ones; these statistics show it. The motion is the ground truth's: the true
body twist of each pair is ``Log(T_true) / Δt`` (rad/s, m/s; ``Δt`` from the frames' stamps), and
a pair's angular acceleration is the change of that angular velocity from the pair before it
(when that pair ends where this one starts) over the interval, ``|ω_k − ω_{k−1}| / Δt_k``
(rad/s²; the two pairs' body frames are one frame apart, which a first-order magnitude ignores).
Frame to frame that is every pair but a segment's first; with keyframes only a pair whose reference
is the previous pair's current frame has one, and it compares twists over that pair's interval.
"""

from __future__ import annotations

import numpy as np

from .chi2 import anees_band
from .metrics import se3_log

#: bin edges of the true angular speed (rad/s)
SPEED_EDGES = (0.0, 0.5, 1.0, 1.5, 2.0, 3.0, np.inf)
#: bin edges of the true angular acceleration (rad/s^2)
ACCELERATION_EDGES = (0.0, 4.0, 8.0, 12.0, 20.0, np.inf)
#: pairs per window of the run (about two seconds of a 30 Hz camera)
WINDOW_PAIRS = 60
#: the share of the largest NEES values whose part of the total is reported
TOP_SHARE = 0.02


def true_motion(T_true: np.ndarray, ref_stamps: np.ndarray, cur_stamps: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """Angular speed (K,) in rad/s and angular acceleration (K,) in rad/s² of each pair
    ``T_true`` (K, 4, 4) (T_ref,cur) from ``ref_stamps`` to ``cur_stamps`` (s); the acceleration
    is NaN where the pair before does not end at this pair's reference frame."""
    ref_stamps = np.asarray(ref_stamps, dtype=float)
    cur_stamps = np.asarray(cur_stamps, dtype=float)
    dt = cur_stamps - ref_stamps
    omega = se3_log(np.asarray(T_true, dtype=float))[:, :3] / dt[:, None]
    accel = np.full(len(dt), np.nan)
    follows = np.zeros(len(dt), bool)
    follows[1:] = cur_stamps[:-1] == ref_stamps[1:]
    accel[follows] = np.linalg.norm(omega[1:] - omega[:-1], axis=1)[follows[1:]] / dt[follows]
    return np.linalg.norm(omega, axis=1), accel


def by_bins(values: np.ndarray, edges, nees_rot: np.ndarray, nees_tr: np.ndarray) -> list[dict]:
    """ANEES t / r and pair count per bin ``[lo, hi)`` of ``values`` (NaN values in no bin);
    ``None`` ANEES for an empty bin."""
    out = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        m = (values >= lo) & (values < hi)
        n = int(m.sum())
        out.append({"range": [float(lo), None if np.isinf(hi) else float(hi)], "pairs": n,
                    "anees_translation": float(nees_tr[m].mean()) if n else None,
                    "anees_rotation": float(nees_rot[m].mean()) if n else None})
    return out


def tail_statistics(nees: np.ndarray) -> dict:
    """Largest NEES, its 95th percentile and the share of the summed NEES that the largest
    :data:`TOP_SHARE` of the pairs (at least one) carry (for chi²(3) values 0.080)."""
    nees = np.sort(np.asarray(nees, dtype=float))[::-1]
    top = max(1, int(round(TOP_SHARE * len(nees))))
    return {"largest": float(nees[0]), "percentile_95": float(np.percentile(nees, 95)),
            "share_of_sum_in_top_2_percent": float(nees[:top].sum() / nees.sum()) if nees.sum() > 0 else 0.0}


def window_statistics(nees_rot: np.ndarray, nees_tr: np.ndarray, w: int = WINDOW_PAIRS) -> dict | None:
    """ANEES t / r of the run's consecutive blocks of ``w`` pairs (in run order; a last block of
    fewer pairs left out): the lowest, median and highest window, and the share of windows whose
    ANEES lies above the upper end of the two-sided 95 % band of a consistent covariance
    (:func:`~covo_gtsam.chi2.anees_band`, 3.65 for 60 pairs); None without a full window."""
    n = len(nees_tr) // w
    if n == 0:
        return None
    upper = anees_band(w)[1]
    out: dict = {"pairs_per_window": int(w), "windows": int(n), "anees_upper_95": upper}
    for name, values in (("translation", nees_tr), ("rotation", nees_rot)):
        anees = np.asarray(values[:n * w], dtype=float).reshape(n, w).mean(axis=1)
        out[f"anees_{name}"] = {"lowest": float(anees.min()), "median": float(np.median(anees)),
                                "highest": float(anees.max()), "share_above_upper_95": float(np.mean(anees > upper))}
    return out


def nees_breakdown(T_true: np.ndarray, ref_stamps: np.ndarray, cur_stamps: np.ndarray,
                   nees_rot: np.ndarray, nees_tr: np.ndarray) -> dict:
    """``metrics.json``'s ``nees_breakdown`` of the pairs (in run order): ANEES by true angular
    speed and acceleration, the tails of the NEES values, and the run's windows."""
    nees_rot = np.asarray(nees_rot, dtype=float)
    nees_tr = np.asarray(nees_tr, dtype=float)
    speed, accel = true_motion(T_true, ref_stamps, cur_stamps)
    return {
        "by_angular_speed_rad_s": by_bins(speed, SPEED_EDGES, nees_rot, nees_tr),
        "by_angular_acceleration_rad_s2": by_bins(accel, ACCELERATION_EDGES, nees_rot, nees_tr),
        "tails_translation": tail_statistics(nees_tr),
        "tails_rotation": tail_statistics(nees_rot),
        "windows": window_statistics(nees_rot, nees_tr),
    }
