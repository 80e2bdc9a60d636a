"""Realistic simulation study: writes docs/realistic_simulation.md.

    python studies/realistic_simulation.py [--seeds 5] [--frames 300]

The whole odometry on synthetic sequences (`covo_gtsam.sequence_simulation`) whose error sources
are known: stamp jitter, a common stamp delay (latency), a rolling shutter, colour-depth offsets,
a per-frame depth-scale error and bad frames (a depth image 100 ms away from its colour image).
Reported, over several seeds: what the run recovers of the injected parameters without ground
truth (frame clock), what a maximum-likelihood fit against the truth recovers
(`covo_gtsam.calibration.fit_sensor_terms`), the integrity check's detection and false-alarm
rates, and the ANEES of the default settings.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from covo_gtsam.calibration import ERROR_TERMS, TwistChanges, latency_basis  # noqa: E402
from covo_gtsam.metrics import block_shares, nees, se3_log  # noqa: E402
from covo_gtsam.sequence_simulation import SequenceSimulationConfig, simulate_sequence  # noqa: E402

#: the odometry's defaults told the simulated sensor's readout
DEFAULTS = SequenceSimulationConfig().odometry_defaults()
#: the odometry told the simulated sensor's true noise, no frame-level term, and (the simulated depths do
#: not drift, except where a section injects a drift) no depth-drift correction
TRUTH = DEFAULTS.replace(noise={"pixel_sigma": 1.0, "depth_sigma_scale": 1.0}, sensor={
    "correlation_factor": 1.0, "frame_sigma_rot_deg": 0.0, "frame_sigma_trans_m": 0.0, "depth_drift_pairs": 0,
    **{name: 0.0 for name in ERROR_TERMS.values()}})
SIM = SequenceSimulationConfig(period_s=1 / 29.7, stamp_jitter_s=0.002, stamp_latency_s=0.01, depth_scale_sigma=0.0005,
                               bad_frame_rate=0.05)


#: the rigid3d gate (chi2(3)) of the fits that show what the default gate's (its 99 % quantile) selection
#: adds: 1.4e-6 of chi2(3) lies beyond it
WIDE_GATE = 30.0

#: faster turns (rad/s, the angular speed's bound) the fitted terms are checked on
FASTER = (4.0, 6.0)
#: slower turns (rad/s) the fitted terms and the defaults are checked on
SLOWER = (0.25, 0.5)


#: the stamp delay alone: no jitter, rolling shutter, colour-depth offset, depth-scale error or bad frame
DELAY_ONLY = dict(stamp_jitter_s=0.0, readout_s=0.0, depth_offset_s=(0.0, 0.0), depth_scale_sigma=0.0,
                  bad_frame_rate=0.0, period_s=1 / 30)


def delay_parts(seed: int, frames: int, speed: float) -> dict:
    """One delay-only run (stamps ``SIM.stamp_latency_s`` late, nothing else but pixel and depth
    noise): the rotation NEES of each consecutive pair's estimation error (against the motion
    between the captures) under the per-point covariance, and of the part the delay makes
    (``stamp_errors``) under ``L^2 B + C_points`` for the true delay ``L`` and three bases ``B``:
    the run's own (recent changes of the estimated twists, minus their noise), the same from the
    true twists (same lag: the changes up to the pair before), and the true change centred half an
    interval before the pair (between the twists of the pair before and of this pair); with the
    ratio of the delay part's mean square to the run's basis's."""
    cfg = dataclasses.replace(SIM, frames=frames, seed=seed, max_angular_speed=speed, **DELAY_ONLY)
    q = simulate_sequence(cfg, TRUTH.replace(sensor={"rolling_shutter_s": 0.0}))
    L, dt = cfg.stamp_latency_s, cfg.period_s
    twists = se3_log(q.capture_truth) / dt  # each pair's mean twist, true
    history, lagged, centred = TwistChanges(TRUTH.sensor.twist_history), [], []
    for n, i in enumerate(q.frames[:, 0]):
        follows = n > 0 and q.frames[n - 1, 1] == i
        lagged.append(history.basis())
        centred.append(latency_basis(q.capture_truth[n], twists[n - 1], twists[n]) if follows else np.zeros((6, 6)))
        if follows:
            history.add(q.capture_truth[n], twists[n - 1], twists[n], np.zeros((6, 6)), np.zeros((6, 6)))
        else:
            history.clear()
    m = q.kept_consecutive
    m[:TRUTH.sensor.twist_history + 2] = False  # the history's window filled
    est = q.errors[m] - q.stamp_errors[m]  # first order: the estimate's own error
    C = q.covariances[m][:, :3, :3]
    d = q.stamp_errors[m, :3]
    out = {"est": nees(est[:, :3], C).mean(),
           "ratio": np.mean(np.sum(d**2, 1)) / np.mean(np.trace(L**2 * q.bases["latency"][m][:, :3, :3], axis1=1,
                                                                    axis2=2))}
    for name, B in (("own", q.bases["latency"][m]), ("true_lagged", np.array(lagged)[m]),
                    ("true_centred", np.array(centred)[m])):
        out[name] = nees(d, L**2 * B[:, :3, :3] + C).mean()
    return out


#: the colour-depth offsets of the error-source and offset sections (s, uniform)
OFFSETS = (0.0, 0.015)
#: one error source at a time (the readout, which the odometry compensates, always on)
SOURCES = {"readout alone": {}, "+ stamp jitter": {"stamp_jitter_s": 0.002}, "+ stamp delay": {"stamp_latency_s": 0.01},
           "+ colour-depth offsets": {"depth_offset_s": OFFSETS}, "+ depth scale": {"depth_scale_sigma": 0.0005}}


def source_rows(seeds: range, frames: int) -> list[str]:
    """Per error source alone: the terms fitted at the base speed (``SIM.max_angular_speed``) and
    checked on the same sensor turning faster (:data:`FASTER`), ANEES t / r of consecutive pairs."""
    rows = []
    for label, source in SOURCES.items():
        per_speed: dict[float, list] = {}
        for seed in seeds:
            base = dataclasses.replace(SIM, frames=frames, seed=seed, **{**DELAY_ONLY, "readout_s": SIM.readout_s,
                                                                         "stamp_latency_s": 0.0, **source})
            q = simulate_sequence(base, TRUTH)
            fit = q.fit_terms()
            for speed in (SIM.max_angular_speed, *FASTER):
                if speed != SIM.max_angular_speed:
                    q = simulate_sequence(dataclasses.replace(base, max_angular_speed=speed), TRUTH)
                m = q.kept_consecutive
                covs = q.kept_covariances(fit)
                per_speed.setdefault(speed, []).append((nees(q.errors[m, 3:], covs[:, 3:, 3:]).mean(),
                                                        nees(q.errors[m, :3], covs[:, :3, :3]).mean()))
        rows.append(f"| {label} | " + " | ".join(
            f"{np.mean([v[0] for v in vals]):.2f} / {np.mean([v[1] for v in vals]):.2f}" for vals in per_speed.values())
            + " |")
    return rows


def offset_rows(seeds: range, frames: int) -> list[str]:
    """The colour-depth offsets alone (no readout or delay), per angular speed: the coherent colour-depth
    factor (the offsets' own effect; 1 here, where the stamped offsets are the true ones) and the
    independent one (an error of each offset; 0 here) fitted in sample (uncompensated), and the
    ANEES t / r with the depths moved to the colour image's time by the stamped offsets, which are
    the true ones here (``depth_time_compensation``, the terms zero): what is left of the offsets'
    effect once compensated with the pairs' twists."""
    rows = []
    for speed in (SIM.max_angular_speed, *FASTER):
        coherent, factor, compensated = [], [], []
        for seed in seeds:
            cfg = dataclasses.replace(SIM, frames=frames, seed=seed, max_angular_speed=speed,
                                      **{**DELAY_ONLY, "stamp_latency_s": 0.0, "depth_offset_s": OFFSETS})
            truth = TRUTH.replace(sensor={"rolling_shutter_s": 0.0})
            fit = simulate_sequence(cfg, truth).fit_terms()
            coherent.append(fit.sigmas["depth_time_coherent"])
            factor.append(fit.sigmas["depth_time"])
            q = simulate_sequence(cfg, truth.replace(sensor={"depth_time_compensation": True}))
            m = q.kept_consecutive
            compensated.append((nees(q.errors[m, 3:], q.covariances[m][:, 3:, 3:]).mean(),
                                nees(q.errors[m, :3], q.covariances[m][:, :3, :3]).mean()))
        rows.append(f"| {speed:g} | {mean_sd(coherent)} | {mean_sd(factor)} | {mean_sd([c[0] for c in compensated])} / "
                    f"{mean_sd([c[1] for c in compensated])} |")
    return rows


#: the sensor of the fit above with the stamps not delayed, less one source at a time, and the odometry's
#: settings changed (the coherent colour-depth factor's excess over 1: which source or stage it comes with)
#: (every source with the stamps not delayed is the main fit's own, not run again)
FACTOR_SOURCES = {"no readout": ({"readout_s": 0.0}, {}),
                  "no stamp jitter": ({"stamp_jitter_s": 0.0}, {}),
                  "no depth-scale error": ({"depth_scale_sigma": 0.0}, {}),
                  "colour-depth offsets and readout only": ({"stamp_jitter_s": 0.0, "depth_scale_sigma": 0.0}, {}),
                  "every source, a noiseless 1 kHz gyroscope": ({"gyro_rate_hz": 1000.0}, {}),
                  f"every source, the rigid3d gate at chi2 {WIDE_GATE:g}": (
                      {}, {"frontend": {"ransac_chi2": WIDE_GATE}}),
                  "every source, no outlier rejection": ({}, {"frontend": {"outlier_rejection": "none"}})}


def factor_source_rows(seeds: range, frames: int) -> list[str]:
    """The two colour-depth factors and kappa fitted against the truth (stamps not delayed, no bad
    frame, the odometry told the true noise) with the error sources and odometry settings of
    :data:`FACTOR_SOURCES`; with the gyroscope, the rows are moved with the true angular velocity at
    each frame."""
    rows = []
    for label, (change, settings) in FACTOR_SOURCES.items():
        fits = []
        for seed in seeds:
            cfg = dataclasses.replace(SIM, frames=frames, seed=seed, bad_frame_rate=0.0, stamp_latency_s=0.0, **change)
            truth = TRUTH if cfg.readout_s > 0 else TRUTH.replace(sensor={"rolling_shutter_s": 0.0})
            fits.append(simulate_sequence(cfg, truth.replace(**settings)).fit_terms())
        rows.append(factor_row(label, [f.sigmas["depth_time_coherent"] for f in fits],
                               [f.sigmas["depth_time"] for f in fits], [f.correlation_factor for f in fits]))
    return rows


def factor_row(label: str, coherent, independent, kappa) -> str:
    """A row of the table of :func:`factor_source_rows`: each figure's mean ± s.d. over the seeds."""
    return f"| {label} | {mean_sd(coherent)} | {mean_sd(independent)} | {mean_sd(kappa)} |"


#: the depth clock's period, relative to the colour clock's, in the depth-clock section
DEPTH_CLOCK = 1.005


def depth_clock_rows(seeds: range, frames: int) -> list[str]:
    """Depth images on their own clock (``DEPTH_CLOCK`` times the colour period), each colour frame
    taking the depth image with the nearest stamp; no other error source but the stamps' jitter
    (which makes the association switch near half a period), pixel and depth noise; the odometry
    told the true noise, the integrity check off. ANEES t / r of the pairs whose depth images are a
    whole period apart (the jump) and of the others, with the jump term off and on, and the size of
    the jump's part of the error along the term's basis."""
    period = 1 / 30
    rows = []
    for speed in (1.0, 2.0):
        rec: dict[str, list] = {}
        for seed in seeds:
            cfg = SequenceSimulationConfig(frames=frames, seed=seed, period_s=period,
                                           depth_period_s=DEPTH_CLOCK * period, max_angular_speed=speed,
                                           stamp_jitter_s=0.002, readout_s=0.0, depth_offset_s=(0.0, 0.0),
                                           depth_scale_sigma=0.0, bad_frame_rate=0.0)
            for factor in (0.0, 1.0):
                r = simulate_sequence(cfg, TRUTH.replace(sensor={"rolling_shutter_s": 0.0, "integrity_threshold": 1e12,
                                                                 "depth_jump_factor": factor}))
                jump = np.abs(np.diff(r.depth_offsets[r.frames], axis=1)[:, 0]) > period / 2
                nt, _ = r.nees(good_only=False)
                for part, m in (("jump", jump), ("other", ~jump)):
                    if m.any():
                        rec.setdefault(f"{part}{factor:g}_t", []).append(nt[m].mean())
                if factor:
                    rec.setdefault("n", []).append(int(jump.sum()))
                    # the error along the basis b = sqrt(B's eigenvalue) x its eigenvector, in units of b
                    w, V = np.linalg.eigh(r.bases["depth_jump"][jump])
                    b = V[:, :, -1] * np.sqrt(np.maximum(w[:, -1:], 0.0))
                    s = np.abs(np.sum(b[:, 3:] * r.errors[jump, 3:], axis=1) / np.sum(b[:, 3:] ** 2, axis=1))
                    rec.setdefault("size", []).extend(s)
        if not rec.get("size"):  # runs too short for the offset to reach half a period
            rows.append(f"| {speed:g} | 0 | — | — | {mean_sd(rec['other1_t'])} | — |")
            continue
        rows.append(f"| {speed:g} | {sum(rec['n'])} | {mean_sd(rec['jump0_t'])} | {mean_sd(rec['jump1_t'])} | "
                    f"{mean_sd(rec['other1_t'])} | {np.median(rec['size']):.2f} ({np.percentile(rec['size'], 10):.2f}"
                    f"-{np.percentile(rec['size'], 90):.2f}) |")
    return rows


#: the depths' drift in its section: amplitude (fraction) and period (s) of the sine, chain length
DRIFT, DRIFT_PERIOD_S, DRIFT_CHAIN = 0.01, 3.0, 30


def drift_rows(seeds: range, frames: int) -> list[str]:
    """A depth scale that drifts (a sine of ``DRIFT`` amplitude, ``DRIFT_PERIOD_S`` period) and none;
    pixel and depth noise only, the odometry told the true noise and no term; the drift correction
    off (window 0) and on (10 pairs). ANEES t of the pairs, translation RMS and ANEES t of the chains of
    ``DRIFT_CHAIN`` consecutive pairs (stamps at the captures: no jitter or delay)."""
    import gtsam

    from covo_gtsam.covariance import compose_chains
    from covo_gtsam.metrics import relative_pose_tangent_errors

    rows = []
    for amplitude in (0.0, DRIFT):
        rec: dict[str, list] = {}
        for seed in seeds:
            cfg = SequenceSimulationConfig(frames=frames, seed=seed, depth_drift=amplitude,
                                           depth_drift_period_s=DRIFT_PERIOD_S, **DELAY_ONLY)  # no stamp delay
            for window in (0, 10):
                odometry = TRUTH.replace(sensor={"rolling_shutter_s": 0.0, "depth_drift_pairs": window})
                r = simulate_sequence(cfg, odometry)
                nt, _ = r.nees()
                T_est = r.capture_truth @ np.array([gtsam.Pose3.Expmap(-e).matrix() for e in r.errors])
                est, C = compose_chains(T_est, r.covariances, DRIFT_CHAIN)
                true, _ = compose_chains(r.capture_truth, r.covariances, DRIFT_CHAIN)
                e = relative_pose_tangent_errors(est, true)[:, 3:]
                rec.setdefault(f"pair{window}", []).append(nt.mean())
                rec.setdefault(f"rms{window}", []).append(1e3 * np.sqrt(np.mean(np.sum(e**2, axis=1))))
                rec.setdefault(f"chain{window}", []).append(nees(e, C[:, 3:, 3:]).mean())
        rows.append(f"| {100 * amplitude:g} | " + " | ".join(
            f"{mean_sd(rec[f'pair{w}'])}, {mean_sd(rec[f'rms{w}'])}, {mean_sd(rec[f'chain{w}'])}" for w in (0, 10))
            + " |")
    return rows


def drift_cost_rows(seeds: range, frames: int) -> list[str]:
    """What the correction costs where nothing drifts, on the section above's sensor (every error
    source but bad frames and the stamp delay): the consecutive pairs' translation RMS and the
    depth-scale term fitted against the truth, the correction off and on."""
    rec: dict[str, list] = {}
    for seed in seeds:
        cfg = dataclasses.replace(SIM, frames=frames, seed=seed, bad_frame_rate=0.0, stamp_latency_s=0.0)
        for window in (0, 10):
            q = simulate_sequence(cfg, TRUTH.replace(sensor={"depth_drift_pairs": window}))
            m = q.kept_consecutive
            fit = q.fit_terms()
            rec.setdefault(f"rms{window}", []).append(1e3 * np.sqrt(np.mean(np.sum(q.errors[m, 3:] ** 2, axis=1))))
            rec.setdefault(f"scale{window}", []).append(100 * fit.sigmas["depth_scale"])
    return [f"| {window} | {mean_sd(rec[f'rms{window}'])} | {mean_sd(rec[f'scale{window}'])} |" for window in (0, 10)]


def default_parts(q) -> dict:
    """The default settings' ANEES t / r of a run's consecutive pairs without a bad frame, the frame term's
    mean share of their rotation variance (trace), and their rotation ANEES without the frame term."""
    m = q.consecutive & ~q.bad
    e, C = q.errors[m], q.covariances[m]
    frame = DEFAULTS.sensor.frame_noise()  # consecutive pairs: one frame interval
    return {"def_t": nees(e[:, 3:], C[:, 3:, 3:]).mean(), "def_r": nees(e[:, :3], C[:, :3, :3]).mean(),
            "def_share": float(np.mean(block_shares(frame, C)[:, 0])),
            "def_r_noframe": nees(e[:, :3], (C - frame)[:, :3, :3]).mean()}


def mean_sd(values) -> str:
    v = np.asarray(values, dtype=float)
    return f"{v.mean():.4g} ± {v.std(ddof=1):.2g}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "realistic_simulation.md")
    args = ap.parse_args()
    rec: dict[str, list] = {k: [] for k in ("period", "jitter", "clock_err", "det", "fa", "n_bad", "anees_t", "anees_r",
                                            "share_t", "share_r", "pairs_det", "bad_lost", "good_lost")}
    # (the fits' figures are added as they come)
    for seed in range(args.seeds):
        cfg = dataclasses.replace(SIM, frames=args.frames, seed=seed)
        # the default settings: what a user gets (clock, integrity check, anees)
        r = simulate_sequence(cfg, DEFAULTS)
        late = slice(60, None)
        truth = r.true_stamp_offsets[late] - r.true_stamp_offsets[late].mean()
        rec["period"].append(1e3 * r.clock_period_s)
        rec["jitter"].append(1e3 * np.std(r.clock_offsets[late]))
        rec["clock_err"].append(1e3 * np.std(r.clock_offsets[late] - truth))
        rec["det"].append(100 * r.detection_rate)
        rec["fa"].append(100 * r.false_alarm_rate)
        rec["n_bad"].append(int(r.bad_frames.sum()))
        rec["pairs_det"].append(100 * np.mean(r.flagged[r.bad]))
        rec["bad_lost"].append(int(np.isin(r.lost_frames, np.flatnonzero(r.bad_frames)).sum()))
        rec["good_lost"].append(100 * r.false_loss_rate)
        nt, nr = r.nees()
        rec["anees_t"].append(nt.mean())
        rec["anees_r"].append(nr.mean())
        rec["share_t"].append(100 * np.mean(nt > 9.35))
        rec["share_r"].append(100 * np.mean(nr > 9.35))
        # the defaults by turning speed, with the frame term's share of the rotation variance
        for speed in (*SLOWER, cfg.max_angular_speed):
            q = r if speed == cfg.max_angular_speed else simulate_sequence(
                dataclasses.replace(cfg, max_angular_speed=speed), DEFAULTS)
            for key, value in default_parts(q).items():
                rec.setdefault(f"{key}{speed:g}", []).append(value)
        # the fit against the truth, with the per-point model told the true noise
        # (and once more without the stamp delay: what the delay's imperfect model leaks into the others)
        fits = {}
        # (and once with the poses not moved by the next twist: the rolling-shutter term's model of the
        # compensation's error with the pair's own twist)
        # (and once with the outlier rejection's gate far out: what its selection adds to the fit)
        for suffix, latency, ahead, gate in (("", cfg.stamp_latency_s, True, None), ("0", 0.0, True, None),
                                             ("_own", cfg.stamp_latency_s, False, None),
                                             ("_gate", cfg.stamp_latency_s, True, WIDE_GATE)):
            frontend = {} if gate is None else {"ransac_chi2": gate}
            q = simulate_sequence(dataclasses.replace(cfg, bad_frame_rate=0.0, stamp_latency_s=latency),
                                  TRUTH.replace(sensor={"rolling_shutter_look_ahead": ahead}, frontend=frontend))
            fit = q.fit_terms()
            rec.setdefault("scale" + suffix, []).append(100 * fit.sigmas["depth_scale"])
            rec.setdefault("dtime" + suffix, []).append(fit.sigmas["depth_time"])
            rec.setdefault("dcoh" + suffix, []).append(fit.sigmas["depth_time_coherent"])
            rec.setdefault("rs" + suffix, []).append(fit.sigmas["rolling_shutter"])
            rec.setdefault("timing" + suffix, []).append(1e3 * fit.sigmas["timing"])
            rec.setdefault("latency" + suffix, []).append(1e3 * fit.sigmas["latency"])
            rec.setdefault("kappa" + suffix, []).append(fit.correlation_factor)
            fits[suffix] = fit
        fit_delayed = fits[""]
        # the terms fitted at this motion (stamps delayed), checked on the same sensor turning faster
        for speed in (*SLOWER, *FASTER):
            q = simulate_sequence(dataclasses.replace(cfg, bad_frame_rate=0.0, max_angular_speed=speed), TRUTH)
            m = q.kept_consecutive
            covs = q.kept_covariances(fit_delayed)
            nt, nr = nees(q.errors[m, 3:], covs[:, 3:, 3:]), nees(q.errors[m, :3], covs[:, :3, :3])
            rec.setdefault(f"fast_t{speed:g}", []).append(nt.mean())
            rec.setdefault(f"fast_r{speed:g}", []).append(nr.mean())
            rec.setdefault(f"fast_s{speed:g}", []).append(100 * np.mean(nt > 9.35))
        print(f"seed {seed} done", flush=True)
    lag_seeds = range(min(args.seeds, 3))
    by_source = source_rows(lag_seeds, args.frames)
    lag = {speed: [delay_parts(seed, args.frames, speed) for seed in lag_seeds] for speed in (2.0, *FASTER)}
    depth_clock = depth_clock_rows(lag_seeds, args.frames)
    offsets = offset_rows(lag_seeds, args.frames)
    factor_sources = factor_source_rows(range(args.seeds), args.frames)
    drift = drift_rows(lag_seeds, args.frames)
    drift_cost = drift_cost_rows(lag_seeds, args.frames)
    c = SIM
    lines = ["# Realistic simulation", "", __doc__.split("\n\n", 2)[2].strip(), "",
             f"*Generated by `python studies/realistic_simulation.py --seeds {args.seeds} --frames {args.frames}`; "
             "do not edit by hand.*", "",
             f"Injected: frame period {1e3 * c.period_s:.3f} ms (the odometry assumes 33.333 ms), stamp jitter "
             f"{1e3 * c.stamp_jitter_s:g} ms, all stamps {1e3 * c.stamp_latency_s:g} ms late, rolling-shutter readout "
             f"{1e3 * c.readout_s:g} ms, colour-depth offsets "
             f"uniform {1e3 * c.depth_offset_s[0]:g}-{1e3 * c.depth_offset_s[1]:g} ms, depth-scale error "
             f"{100 * c.depth_scale_sigma:g} % per frame, bad frames at {100 * c.bad_frame_rate:g} % "
             f"({1e3 * c.bad_frame_offset_s:g} ms off), pixel noise {c.pixel_sigma:g} px, the Kinect depth model; "
             f"angular speed up to {c.max_angular_speed:g} rad/s. Mean ± standard deviation over "
             f"{args.seeds} seeds of {args.frames} frames.", "",
             "## Recovered without ground truth (default settings)", "",
             "| quantity | injected | recovered |", "|---|---|---|",
             f"| frame period (ms) | {1e3 * c.period_s:.3f} | {mean_sd(rec['period'])} |",
             f"| stamp scatter around the clock (ms) | {1e3 * c.stamp_jitter_s:g} | {mean_sd(rec['jitter'])} |",
             f"| error of each frame's clock offset (ms) | 0 | {mean_sd(rec['clock_err'])} |", "",
             "## Recovered by the maximum-likelihood fit against the truth", "",
             "The per-point model told the true pixel and depth noise; kappa, the frame term and every "
             "frame-level term fitted on the consecutive pairs.", "",
             f"The last column: the stamps delayed, the outlier rejection's gate at chi2 {WIDE_GATE:g} in place of "
             f"its 99 % quantile ({DEFAULTS.frontend.ransac_chi2:g}; docs/derivation.md, \"The colour-depth factors "
             "and the outlier rejection\").", "",
             "| term | injected / expected | fitted | fitted, stamps not delayed (latency 0 injected) | fitted, gate "
             f"at chi2 {WIDE_GATE:g} |",
             "|---|---|---|---|---|",
             f"| depth scale (%) | {100 * c.depth_scale_sigma:g} | {mean_sd(rec['scale'])} | "
             f"{mean_sd(rec['scale0'])} | {mean_sd(rec['scale_gate'])} |",
             "| colour-depth offsets' own effect (coherent factor) | 1 (the stamped offsets are the true ones, "
             f"uncompensated) | {mean_sd(rec['dcoh'])} | {mean_sd(rec['dcoh0'])} | {mean_sd(rec['dcoh_gate'])} |",
             "| error of each frame's colour-depth offset (independent factor) | 0 (the stamped offsets are the true "
             f"ones) | {mean_sd(rec['dtime'])} | {mean_sd(rec['dtime0'])} | {mean_sd(rec['dtime_gate'])} |",
             f"| rolling-shutter residual factor | below 1 (the poses moved by the next twist, the default, take "
             f"most of the compensation's error out) | {mean_sd(rec['rs'])} | {mean_sd(rec['rs0'])} | "
             f"{mean_sd(rec['rs_gate'])} |",
             f"| rolling-shutter residual factor, poses not moved (`rolling_shutter_look_ahead` false) | about 1 "
             f"(the model's size) | {mean_sd(rec['rs_own'])} | — | — |",
             f"| timing (ms) | the clock's residual, {mean_sd(rec['clock_err'])} | {mean_sd(rec['timing'])} | "
             f"{mean_sd(rec['timing0'])} | {mean_sd(rec['timing_gate'])} |",
             f"| latency (ms) | {1e3 * c.stamp_latency_s:g} (one delay for all stamps) | {mean_sd(rec['latency'])} | "
             f"{mean_sd(rec['latency0'])} | {mean_sd(rec['latency_gate'])} |",
             f"| kappa | 1 | {mean_sd(rec['kappa'])} | {mean_sd(rec['kappa0'])} | {mean_sd(rec['kappa_gate'])} |",
             f"| kappa, poses not moved | 1 | {mean_sd(rec['kappa_own'])} | — | — |", "",
             "## The fitted terms on a slower and a faster turn", "",
             f"The terms fitted above (stamps delayed, angular speed up to {c.max_angular_speed:g} rad/s), checked on "
             "the same sensor and seeds turning slower and faster (pairs of consecutive frames; a check of the "
             "terms' growth with the motion, whose truth is known here: a term that does not follow the motion "
             "leaves the slower turns conservative and the faster ones overconfident).", "",
             "| angular speed up to (rad/s) | ANEES t / r | NEES > 9.35 t (%) |", "|---|---|---|",
             *[f"| {speed:g} | {mean_sd(rec[f'fast_t{speed:g}'])} / {mean_sd(rec[f'fast_r{speed:g}'])} | "
               f"{mean_sd(rec[f'fast_s{speed:g}'])} |" for speed in (*SLOWER, *FASTER)], "",
             "### By error source", "",
             f"Each error source alone (on top of the {1e3 * c.readout_s:g} ms readout, which the odometry "
             "compensates; no bad frame, frame period 33.333 ms), the odometry told the true noise: every term fitted "
             f"at up to {c.max_angular_speed:g} rad/s and checked on the same sensor and seeds turning faster. ANEES "
             f"t / r of the consecutive pairs, mean over {len(lag_seeds)} seeds.", "",
             f"| error source | up to {c.max_angular_speed:g} rad/s (in sample) | "
             + " | ".join(f"up to {speed:g} rad/s" for speed in FASTER) + " |", "|---" * (2 + len(FASTER)) + "|",
             *by_source, "",
             "### The latency term's basis at faster turns", "",
             f"The stamp delay alone ({1e3 * c.stamp_latency_s:g} ms; no jitter, readout, colour-depth offset, "
             "depth-scale error or bad frame), the odometry told the true noise. Each consecutive pair's error splits "
             "into the estimate's own (against the motion between the two captures) and the part the delay makes "
             "(`SequenceSimulationResult.stamp_errors`); rotation NEES of each, the delay's part under "
             "`L^2 B + C_points` with the true delay `L` and three bases `B`. Mean ± s.d. over "
             f"{len(lag_seeds)} seeds, pairs after the first {TRUTH.sensor.twist_history + 2}.", "",
             "| angular speed up to (rad/s) | delay part's mean square / the run's basis's | estimate's own, "
             f"under C_points | delay part, the run's basis (estimated twists, last {TRUTH.sensor.twist_history} "
             "changes up to the pair before) | same from the true twists | true change centred half an interval "
             "before the pair |",
             "|---|---|---|---|---|---|",
             *[f"| {speed:g} | {mean_sd([r['ratio'] for r in rows])} | {mean_sd([r['est'] for r in rows])} | "
               f"{mean_sd([r['own'] for r in rows])} | {mean_sd([r['true_lagged'] for r in rows])} | "
               f"{mean_sd([r['true_centred'] for r in rows])} |" for speed, rows in lag.items()], "",
             "The basis has the right size at every speed and the estimate keeps up. Its direction is the "
             "question: the simulated motion's turn axis wanders within a few frames, so the direction of the "
             "recent changes does not carry over to the next pair, and the run spreads over all axes the share "
             "of the basis its own twist changes call for (docs/derivation.md, \"The direction of the change\"). "
             "With the recent direction alone the delay's part had NEES 3.2, 5.1 and 6.6 at 2, 4 and 6 rad/s "
             "(and the same from the true twists); the true change centred half an interval before the pair, a "
             "rank-one basis in the right direction half an interval early, still grows with the speed. What "
             "remains at the faster turns with every error source on (table above) is mostly the translation's, "
             "which the delay barely moves.", "",
             "### Colour-depth offsets at faster turns", "",
             "The colour-depth offsets alone (uniform "
             f"{1e3 * OFFSETS[0]:g}-{1e3 * OFFSETS[1]:g} ms; no readout, jitter, delay, "
             "depth-scale error or bad frame), the odometry told the true noise: the two colour-depth factors "
             "fitted in sample at each speed with the offsets uncompensated (the coherent one, the offsets' own "
             "effect, expected 1 at any speed; the independent one, an error of each offset, expected 0), and the "
             "ANEES t / r of the pairs with each point moved along its ray "
             "by the stamped offset, which is the true one here (`sensor.depth_time_compensation`; the terms zero). "
             f"Mean ± s.d. over {len(lag_seeds)} seeds. docs/derivation.md (\"Colour-depth offsets at fast turns\") "
             "has what this rests on.", "",
             "| angular speed up to (rad/s) | coherent factor, uncompensated | independent factor, uncompensated | "
             "ANEES t / r, compensated |",
             "|---|---|---|---|", *offsets, "",
             "### The colour-depth factors by error source", "",
             "The fit of the table \"Recovered by the maximum-likelihood fit against the truth\" with the stamps not "
             "delayed (its fourth column; the first row here), less one error source at a time, with a noiseless "
             f"gyroscope, with the outlier rejection's gate at chi2 {WIDE_GATE:g} and with the outlier rejection off: "
             "where the coherent factor's excess over 1 comes from. With the gyroscope the rows are moved with the "
             "true angular velocity at each frame (and its change over the readout) instead of the pairs' twists. "
             "docs/derivation.md (\"The colour-depth factors and the outlier rejection\") has what the rows show. "
             "Mean ± s.d. over "
             f"{args.seeds} seeds of {args.frames} frames.", "",
             "| error sources | coherent factor (1 expected) | independent factor (0 expected) | kappa (1 expected) |",
             "|---|---|---|---|", factor_row("every source", rec["dcoh0"], rec["dtime0"], rec["kappa0"]),
             *factor_sources, "",
             "## Depth images on their own clock", "",
             f"Depth images captured on a clock {100 * (DEPTH_CLOCK - 1):g} % slower than the colour images' "
             "(33.333 ms), stamped with 2 ms of jitter like them, each colour frame taking the depth image with the "
             "nearest stamp: the colour-depth offset drifts through half a period, where the nearest depth image "
             "switches to its neighbour and back as the stamps scatter, so some pairs' depth images are read a whole "
             "period apart. No other error source but pixel and depth noise; the odometry told the true noise, the "
             "integrity check off (the covariance is the terms' own). Translation ANEES of the pairs with such a "
             "jump, without and with the `depth_jump` term (`sensor.depth_jump_factor` 0 and 1), and of the other "
             f"pairs; mean ± s.d. over {len(lag_seeds)} seeds. Last column: the jump pairs' translation error along "
             "the term's basis `b`, in units of `b` (1: the basis has the error's size), median (10th-90th "
             "percentile).", "",
             "| angular speed up to (rad/s) | jump pairs | their ANEES t, term off | term on | other pairs | "
             "error along b / b |", "|---|---|---|---|---|---|",
             *depth_clock, "",
             "## A drifting depth scale", "",
             f"Each frame's depths scaled by `1 + {DRIFT:g} sin(2 pi t / {DRIFT_PERIOD_S:g} s + phase)` (a drift "
             "that carries the depth error over tens of frames) and by nothing; no other error source but pixel and "
             "depth noise, the stamps at the captures; the odometry told the true noise, no frame-level term. The "
             "depth-drift correction off (`sensor.depth_drift_pairs` 0) and on (10 pairs, the default): ANEES t of "
             f"the pairs, translation RMS (mm) and ANEES t of the chains of {DRIFT_CHAIN} pairs; mean ± s.d. over "
             f"{len(lag_seeds)} seeds.", "",
             "| drift amplitude (%) | correction off: pairs, chain RMS, chains | on (10 pairs) |", "|---|---|---|",
             *drift, "",
             f"Where nothing drifts, on the sensor of the fits above (every error source but the bad frames and the "
             f"stamp delay; depth-scale error {100 * SIM.depth_scale_sigma:g} % per frame, white), the correction "
             "moves the pairs by the noise of the depth-free estimates' mean: the consecutive pairs' translation RMS "
             "(mm) and the depth-scale term fitted against the truth, the correction off and on.", "",
             "| window (pairs) | translation RMS (mm) | depth scale fitted (%) |", "|---|---|---|",
             *drift_cost, "",
             "## Integrity check (default threshold)", "",
             "Per run: the bad frames; those caught (%: lost, since most of their matches disagree with one motion, "
             "or flagged in every pair they are in); of them lost; the pairs left with a bad frame that are flagged "
             "(%); the false alarms: pairs without a bad frame flagged (%), and frames that are not bad lost (%).", "",
             "| bad frames per run | caught (%) | lost | pairs with a bad frame flagged (%) | other pairs flagged (%) "
             "| other frames lost (%) |", "|---|---|---|---|---|---|",
             f"| {mean_sd(rec['n_bad'])} | {mean_sd(rec['det'])} | {mean_sd(rec['bad_lost'])} | "
             f"{mean_sd(rec['pairs_det'])} | {mean_sd(rec['fa'])} | {mean_sd(rec['good_lost'])} |", "",
             "## Consistency of the default settings (pairs without a bad frame)", "",
             "The defaults carry the sensor terms fitted for the Kinect v1 of the shared TUM frames, not the "
             "simulated sensor's (told its readout, a property of the sensor as its intrinsics are), so this row "
             "shows how they transfer to another sensor, not a fit.", "",
             "| ANEES t / r | NEES > 9.35 t / r (%) |", "|---|---|",
             f"| {mean_sd(rec['anees_t'])} / {mean_sd(rec['anees_r'])} | "
             f"{mean_sd(rec['share_t'])} / {mean_sd(rec['share_r'])} |", "",
             "The same by turning speed, consecutive pairs: the defaults' ANEES t / r, the share of the rotation "
             f"variance that is the frame term ({DEFAULTS.sensor.frame_sigma_rot_deg:g} deg per axis and frame "
             "interval, the one sensor term that does not follow the motion; docs/derivation.md, \"What the frame "
             "term stands for\"), and the rotation ANEES without it. The rest of the rotation's excess is the "
             f"per-point model's {DEFAULTS.noise.pixel_sigma:g} px against the simulated {c.pixel_sigma:g} px.", "",
             "| angular speed up to (rad/s) | ANEES t / r | frame term's share of the rotation variance | "
             "ANEES r without the frame term |", "|---|---|---|---|",
             *[f"| {speed:g} | {mean_sd(rec[f'def_t{speed:g}'])} / {mean_sd(rec[f'def_r{speed:g}'])} | "
               f"{mean_sd(rec[f'def_share{speed:g}'])} | {mean_sd(rec[f'def_r_noframe{speed:g}'])} |"
               for speed in (*SLOWER, c.max_angular_speed)], ""]
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
