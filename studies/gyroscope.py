"""A gyroscope in the rolling-shutter compensation: writes docs/gyroscope.md.

    python studies/gyroscope.py [--data ../shared/data] [--seeds 2]

Without a gyroscope the compensation moves each frame's rows with the mean of the two pairs' twists
around the frame, which misses how the turn changes within those two intervals; with one
(`covo run --gyro`, `covo_gtsam.gyro`) it takes the measured angular velocity at the frame and
its change over the readout, and the latency term its measured change across each pair.

1. The realistic simulation driven by the whole fr1_rpy's recorded motion
   (`studies/recorded_motion.py`'s runs), without and with a simulated gyroscope (200 Hz, 0.005
   rad/s of white noise per sample): terms fitted on the first 240 frames, checked on the rest.
2. The shared fr1 frames with a stand-in gyroscope: the reference's own angular velocity (its
   motion smoothed over 20 ms, at 200 Hz). It shares the reference's errors, so the figures
   against that reference only indicate what a gyroscope would do: the accuracy by readout time
   and by the gyroscope's clock offset, and the sensor terms fitted on one half of fr1_rpy and
   checked on the other and on fr1_desk.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from multiprocessing import Pool
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from cross_validation import DESK, RPY, check, fit_row, per_point_pairs, subset  # noqa: E402
from recorded_motion import check as sim_check  # noqa: E402
from recorded_motion import halves, ms, part, simulate  # noqa: E402

from covo_gtsam.calibration import DEFAULT_TERMS, GYRO_TERMS, fit_sensor_terms  # noqa: E402
from covo_gtsam.config import OdometryConfig  # noqa: E402
from covo_gtsam.datasets.tum import TumSequence  # noqa: E402
from covo_gtsam.evaluation import ground_truth_lookup, pairs_with_truth, relative_ground_truth  # noqa: E402
from covo_gtsam.gyro import Gyroscope  # noqa: E402
from covo_gtsam.io import load_tum_trajectory  # noqa: E402
from covo_gtsam.metrics import relative_pose_tangent_errors  # noqa: E402
from covo_gtsam.pipeline import run_sequence  # noqa: E402
from covo_gtsam.sequence_simulation import RecordedMotion  # noqa: E402

ROOT = HERE.parent
#: the simulated gyroscope: sample rate (Hz) and white noise per sample (rad/s), a MEMS gyroscope's
GYRO = {"gyro_rate_hz": 200.0, "gyro_noise_rad_s": 0.005}
#: the readout the only error source besides the point noise
READOUT_ALONE = {"stamp_jitter_s": 0.0, "stamp_latency_s": 0.0, "depth_offset_s": (0.0, 0.0),
                 "depth_scale_sigma": 0.0, "bad_frame_rate": 0.0}
SOURCES = {"every source": {}, "the readout alone": READOUT_ALONE}
#: a gyroscope with a MEMS part's uncalibrated bias (0.5 deg/s) and its clock 3 ms off the frames'
IMPERFECT = {**GYRO, "gyro_bias_rad_s": 0.0087, "gyro_clock_offset_s": 0.003}
#: the stand-in gyroscope: the reference's motion smoothed over this (s), sampled at this rate (Hz)
REF_SMOOTH_S, REF_RATE_HZ = 0.02, 200.0
READOUTS = (0.020, 0.025, 0.030, 0.035, 0.040)
OFFSETS = (-0.010, -0.005, 0.005, 0.010)


def sim_run(job: tuple) -> tuple:
    """One simulated run: the terms fitted on its first 240 frames and checked on the rest."""
    data, seed, sources, with_gyro = job
    gyro = {False: {}, True: GYRO, "imperfect": IMPERFECT}[with_gyro]
    q = simulate(data, seed, 0.02, **SOURCES[sources], **gyro)
    head, rest = halves(q)
    fit = fit_sensor_terms(*part(q, head)[:2], bases=part(q, head)[2])
    rms = np.degrees(np.sqrt(np.mean(q.errors[rest][:, :3] ** 2, axis=0)))
    return (*sim_check(fit, q, head)[:2], *sim_check(fit, q, rest), *rms, 1e3 * fit.sigmas.get("latency", 0.0),
            fit.correlation_factor, fit.sigmas.get("gyro", 0.0) if with_gyro else np.nan)


GYRO_LABELS = {False: "no", True: "yes", "imperfect": "yes, biased 0.0087 rad/s and 3 ms late"}


def simulation_lines(data: Path, seeds: range) -> list[str]:
    jobs = [(data, seed, sources, g) for sources in SOURCES for g in (False, True) for seed in seeds]
    jobs += [(data, seed, "every source", "imperfect") for seed in seeds]
    with Pool(2) as pool:
        out = pool.map(sim_run, jobs)
    rows = {}
    for (_, _, sources, g), r in zip(jobs, out):
        rows.setdefault((sources, g), []).append(r)
    lines = ["## 1. Simulation: the whole fr1_rpy's recorded motion", "",
             "`studies/recorded_motion.py`'s runs (700 frames from the first colour frame, the motion smoothed over "
             "20 ms, the realistic sensor with a 25 ms readout and 10 ms stamp delay, 8000 scene points all around, "
             "the odometry told the true point noise): every term fitted on the pairs ending before frame 240 and "
             "checked on those from frame 240 on, without and with a gyroscope sampling the true angular velocity at "
             f"{GYRO['gyro_rate_hz']:.0f} Hz with {GYRO['gyro_noise_rad_s']} rad/s of white noise, stamped on the "
             f"frames' clock (mean ± s.d. over {len(seeds)} seeds); the last row's gyroscope also has a constant bias "
             "of 0.0087 rad/s (0.5 deg/s, an uncalibrated MEMS part's) on each axis and its stamps 3 ms late against "
             "the frames', neither known to the odometry.", "",
             "| error sources | gyroscope | frames 0-239 ANEES t / r | frames 240-699 (held out) ANEES t / r | "
             "held out NEES > 9.35 t / r (%) | held-out rotation error RMS x / y / z (deg) | latency fitted (ms; "
             "10 injected with every source) | kappa | gyroscope's error fitted (rad/s) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for (sources, g), rs in rows.items():
        r = np.array(rs)
        lines.append(f"| {sources} | {GYRO_LABELS[g]} | {ms(r[:, 0])} / {ms(r[:, 1])} | {ms(r[:, 2])} / "
                     f"{ms(r[:, 3])} | {ms(r[:, 4])} / {ms(r[:, 5])} | {r[:, 6].mean():.4f} / {r[:, 7].mean():.4f} / "
                     f"{r[:, 8].mean():.4f} | {ms(r[:, 9])} | {ms(r[:, 10])} | "
                     f"{'—' if np.isnan(r[0, 11]) else f'{r[:, 11].mean():.4f} ± {r[:, 11].std():.4f}'} |")
    return lines + [""]


def reference_gyro(seq_dir: Path, offset: float = 0.0) -> Gyroscope:
    """The stand-in gyroscope of a TUM sequence: its ground truth's angular velocity (:data:`REF_SMOOTH_S`,
    :data:`REF_RATE_HZ`), on the ground truth's clock plus ``offset`` (s)."""
    gt = seq_dir / "groundtruth.txt"
    motion = RecordedMotion.from_tum(gt, 0.0, REF_SMOOTH_S)
    first = float(load_tum_trajectory(gt)[0][0])
    t = np.arange(motion.span[0] + 0.01, motion.span[1] - 0.01, 1.0 / REF_RATE_HZ)
    return Gyroscope(t + first, motion.angular_velocity(t), time_offset_s=offset)


def accuracy(seq: TumSequence, readout: float, gyro: Gyroscope | None) -> tuple:
    """RPE over one frame (mm / deg, RMS) on the pairs ending in frames 1-119 and 120-239, and RPE30 (m)."""
    cfg = OdometryConfig().replace(sensor={"rolling_shutter_s": readout})
    with tempfile.TemporaryDirectory() as tmp:
        run = run_sequence(seq, tmp, config=cfg, plots=False, progress=False, gyro=gyro)
    lookup = ground_truth_lookup(seq)
    pairs = [s for s in pairs_with_truth(run.steps, lookup)
             if round((s.timestamp - s.ref_timestamp) / cfg.sensor.frame_interval_s) == 1]
    err = relative_pose_tangent_errors(*relative_ground_truth(pairs, lookup)[:2])
    index = {t: i for i, t in enumerate(seq.timestamps)}
    end = np.array([index[s.timestamp] for s in pairs])
    out = []
    for m in (end <= 119, end >= 120):
        out += [1e3 * np.sqrt(np.mean(np.sum(err[m, 3:] ** 2, axis=1))),
                np.degrees(np.sqrt(np.mean(np.sum(err[m, :3] ** 2, axis=1))))]
    return (*out, run.metrics["rpe_30"]["trans_rmse"])


def accuracy_lines(data: Path) -> tuple[list[str], float]:
    seq_dir = data / "tum" / RPY
    seq, gyro = TumSequence(seq_dir), reference_gyro(seq_dir)
    lines = ["## 2. The shared fr1 frames with the reference's angular velocity as a gyroscope", "",
             f"The stand-in gyroscope is fr1_rpy's reference motion smoothed over {1e3 * REF_SMOOTH_S:.0f} ms, its "
             f"angular velocity at {REF_RATE_HZ:.0f} Hz on the reference's clock. It shares the reference's errors, "
             "so every figure here is "
             "measured against the source of the angular velocity it used: an indication, not a check, of what a "
             "gyroscope does on the real Kinect.", "",
             "### Accuracy by readout time", "",
             "`covo run` with default settings but the readout, over the 240 shared frames: RPE over one frame "
             "(translation mm / rotation deg, RMS) of the pairs ending in frames 1-119 (A) and 120-239 (B), and "
             "RPE30.", "",
             "| readout (ms) | gyroscope | A (mm / deg) | B (mm / deg) | RPE30 (m) |", "|---|---|---|---|---|"]
    best, best_a = None, np.inf
    for readout in READOUTS:
        for g in (None, gyro):
            r = accuracy(seq, readout, g)
            if g is not None and r[0] < best_a:
                best, best_a = readout, r[0]
            lines.append(f"| {1e3 * readout:.0f} | {'yes' if g else 'no'} | {r[0]:.3f} / {r[1]:.4f} | "
                         f"{r[2]:.3f} / {r[3]:.4f} | {r[4]:.4f} |")
    lines += ["", f"With the gyroscope, half A's translation chooses a readout of {1e3 * best:.0f} ms.", "",
              "### The gyroscope's clock", "",
              f"At {1e3 * best:.0f} ms of readout, the stand-in gyroscope's stamps moved by an offset (a gyroscope "
              "on a clock of its own, or the reference's delay against the frames' stamps):", "",
              "| offset (ms) | A (mm / deg) | B (mm / deg) | RPE30 (m) |", "|---|---|---|---|"]
    for offset in (*OFFSETS[:2], 0.0, *OFFSETS[2:]):
        r = accuracy(seq, best, reference_gyro(seq_dir, offset))
        lines.append(f"| {1e3 * offset:+.0f} | {r[0]:.3f} / {r[1]:.4f} | {r[2]:.3f} / {r[3]:.4f} | {r[4]:.4f} |")
    return lines + [""], best


def calibration_lines(data: Path, readout: float) -> list[str]:
    lines = ["### The sensor terms refitted with the gyroscope", "",
             "The default terms fitted by maximum likelihood on one half of fr1_rpy (as `covo calibrate` fits, the "
             "reference's own jitter held as a known term; with the gyroscope its `gyro` term in place of the "
             "rolling-shutter term, whose bases are zero wherever the gyroscope covers a pair) and checked on the "
             "other half and on fr1_desk (its own stand-in gyroscope): without the gyroscope at the default readout, "
             "and with it at "
             f"{1e3 * readout:.0f} ms. Columns as in cross_validation.md.", "",
             "| gyroscope | fitted on | terms | checked on | ANEES t / r | NEES > 9.35 t / r | largest NEES t / r | "
             "30-pair chains ANEES t / r | log-likelihood per pair |", "|---|---|---|---|---|---|---|---|---|"]
    for label, rpy_gyro, desk_gyro, sensor, terms in (
            ("no", None, None, {}, DEFAULT_TERMS),
            ("yes", reference_gyro(data / "tum" / RPY), reference_gyro(data / "tum" / DESK),
             {"rolling_shutter_s": readout}, GYRO_TERMS)):
        rpy = per_point_pairs(data, RPY, gyro=rpy_gyro, **sensor)
        desk = per_point_pairs(data, DESK, gyro=desk_gyro, **sensor)
        halves_ = {"A": rpy["end"] <= 119, "B": rpy["end"] >= 120}
        for name, m in halves_.items():
            train = subset(rpy, m & rpy["fit_ok"])
            fit = fit_sensor_terms(train["err"], train["cov"], False,
                                   bases={n: train["bases"][n] for n in terms}, fixed=train["fixed"])
            other = "B" if name == "A" else "A"
            for target, p in ((f"{other} (held out)", subset(rpy, halves_[other])), ("fr1_desk (held out)", desk)):
                lines.append(f"| {label} | {name} | {fit_row(fit)} | {target} | {check(fit, p)} |")
    return lines + [""]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    ap.add_argument("--seeds", type=int, default=2)
    args = ap.parse_args()
    lines = ["# A gyroscope in the rolling-shutter compensation", "",
             "*Generated by `python studies/gyroscope.py`; do not edit by hand.* What the figures mean: "
             "docs/derivation.md, \"A gyroscope\".", ""]
    lines += simulation_lines(args.data, range(args.seeds))
    acc, readout = accuracy_lines(args.data)
    lines += acc + calibration_lines(args.data, readout)
    (ROOT / "docs" / "gyroscope.md").write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
