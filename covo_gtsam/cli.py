"""Command line: ``covo run``, ``covo evaluate``, ``covo simulate``, ``covo analyze-noise``, ``covo calibrate``.

Every failure the package knows about ends with exit code 2 and one line on stderr naming the
file and the problem; no traceback. ``covo run`` that tracks no frame at all ends with exit code 3
(its results are written); Ctrl-C ends any command with 130.
"""

from __future__ import annotations

import argparse
import math
import sys
import warnings
from pathlib import Path

from .errors import ConfigError, CovoError

EPILOG = """\
conventions:
  T_ref,cur maps points of the current camera frame into the reference frame.
  Covariances are 6x6 in GTSAM's Pose3 tangent [rx ry rz tx ty tz] (rad, m),
  right perturbation T_true = T_est * Exp(xi).  Quaternions are qx qy qz qw.
"""


def _int_in(minimum: int, maximum: int | None = None):
    """argparse type: an integer in ``[minimum, maximum]`` (no upper limit if None)."""
    expected = f"an integer >= {minimum}" if maximum is None else f"an integer from {minimum} to {maximum}"

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}") from None
        if value < minimum or (maximum is not None and value > maximum):
            raise argparse.ArgumentTypeError(f"expected {expected}, got {value}")
        return value

    return parse


def _float_in(minimum: float | None = None, maximum: float | None = None):
    """argparse type: a positive finite number, optionally in ``[minimum, maximum]``."""
    expected = "a positive number" + (f" >= {minimum:g}" if minimum is not None else "") + (
        f" <= {maximum:g}" if maximum is not None else "")

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}") from None
        if not (value > 0 and math.isfinite(value) and (minimum is None or value >= minimum)
                and (maximum is None or value <= maximum)):
            raise argparse.ArgumentTypeError(f"expected {expected}, got {value:g}")
        return value

    return parse


def _setting(cls, name: str):
    """argparse type of the declared setting ``name`` of the settings class ``cls``: its range as
    declared (:mod:`covo_gtsam.validation`)."""
    import dataclasses

    meta = next(f for f in dataclasses.fields(cls) if f.name == name).metadata
    if meta["kind"] == "int":
        return _int_in(meta["minimum"], meta["maximum"])
    return _float_in(meta["minimum"], meta["maximum"])


def load_config_file(path: str):
    """Deprecated: :func:`covo_gtsam.config.load_config` (removed from the command line module in
    the next release)."""
    from .config import load_config

    warnings.warn("covo_gtsam.cli.load_config_file is deprecated; use covo_gtsam.config.load_config",
                  DeprecationWarning, stacklevel=2)
    return load_config(path)


#: Exit code of ``covo run`` when no frame could be tracked (the results folder is still written).
EXIT_NOTHING_TRACKED = 3


def cmd_run(args: argparse.Namespace) -> int:
    from .pipeline import check_output_dir, run_sequence

    config = _load_config(args)
    if args.weighting:
        config = config.replace(estimator={"weighting": args.weighting})
    if args.scale is not None:
        config = config.replace(estimator={"scale": args.scale})
    seq = _sequence(args)
    _check_config_fits(args, config, seq)
    if args.bag_out:
        from .ros_io import require_rosbags

        require_rosbags()
    check_output_dir(args.out)
    result = run_sequence(
        seq, args.out, config=config, max_frames=args.max_frames, plots=not args.no_plots, progress=not args.quiet,
        bag_out=args.bag_out,
    )
    m = result.metrics
    fps = m["frames_per_second"]
    line = f"{m['frames']} frames, {m['lost_frames']} lost" + (f", {fps:.1f} frames/s" if fps is not None else "")
    if m.get("unassociated"):
        line += f", {len(m['unassociated'])} colour frames without depth (not run)"
    if m.get("rpe_30"):
        line += f", RPE30 {m['rpe_30']['trans_rmse']:.4f} m"
    if m.get("anees_translation") is not None and m.get("anees_rotation") is not None:
        line += f", ANEES t {m['anees_translation']:.2f} r {m['anees_rotation']:.2f}"
    print(line)
    if getattr(seq, "groundtruth", None) is None:
        print(f"{seq.name}: no ground truth; accuracy and consistency metrics skipped")
    if result.plot_files is None:
        _plots_missing()
    print(f"results in {result.out_dir}")
    if m["tracked_frames"] == 0:
        first = m["lost"][0]["reason"] if m["lost"] else "no frame"
        print(f"covo: error: no frame could be tracked: all {m['frames']} frames are lost (first reason: {first}); "
              f"see metrics.json", file=sys.stderr)
        return EXIT_NOTHING_TRACKED
    return 0


def _load_config(args: argparse.Namespace):
    """The odometry configuration of ``--config``, or the default one; a ``--camera`` file's
    ``depth_scale`` replaces the configuration's. A deprecation of the file's form is one
    ``covo: warning:`` line on stderr (unless Python's warnings options say otherwise)."""
    from .config import OdometryConfig, load_config

    config = OdometryConfig()
    if args.config:
        with warnings.catch_warnings(record=True) as caught:
            if not sys.warnoptions:
                warnings.simplefilter("default", DeprecationWarning)
            config = load_config(args.config)
        for w in caught:
            print(f"covo: warning: {w.message}", file=sys.stderr)
    _, depth_scale = _camera(args)
    return config if depth_scale is None else config.replace(sensor={"depth_scale": depth_scale})


def _camera(args: argparse.Namespace):
    """``(camera or None, depth scale or None)`` of ``--camera`` (a preset name or a camera file)."""
    from .camera_file import resolve_camera

    if not hasattr(args, "_camera_resolved"):
        args._camera_resolved = resolve_camera(getattr(args, "camera", None))
    return args._camera_resolved


def _sequence(args: argparse.Namespace):
    """The sequence of ``SEQ`` (a TUM folder, or for ``covo run`` a ROS bag) with the ``--camera``, if given."""
    from .datasets.rosbag import RosbagSequence, is_bag
    from .datasets.tum import TumSequence

    camera, _ = _camera(args)
    if is_bag(args.sequence):
        if not hasattr(args, "rgb_topic"):
            raise ConfigError(f"{args.sequence}: {args.command} reads TUM folders; ROS bags work with covo run "
                              "and covo evaluate")
        return RosbagSequence(args.sequence, camera=camera, rgb_topic=args.rgb_topic, depth_topic=args.depth_topic,
                              camera_info_topic=args.camera_info_topic)
    return TumSequence(args.sequence, camera=camera)


def _check_config_fits(args: argparse.Namespace, config, seq) -> None:
    """The front end of a ``--config`` file must fit the images; the error names the file."""
    if args.config:
        try:
            config.frontend.check_image_size(seq.camera.width, seq.camera.height)
        except ConfigError as exc:
            raise ConfigError(f"{args.config}: {exc}") from exc


def cmd_simulate(args: argparse.Namespace) -> int:
    from .io import write_json
    from .pipeline import check_output_dir
    from .plots import SIMULATION_PLOTS
    from .simulation import SimulationConfig, run_simulation

    if not args.min_depth < args.max_depth:
        raise ConfigError(f"--min-depth ({args.min_depth:g} m) must be smaller than --max-depth ({args.max_depth:g} m)")
    out = check_output_dir(args.out)
    with _lock_outputs(out, ["metrics.json"], ("plots", SIMULATION_PLOTS), not args.no_plots):
        cfg = SimulationConfig(
            runs=args.runs, seed=args.seed, weighting=args.weighting, scale=args.scale,
            pixel_sigma=args.pixel_sigma, num_points=args.points,
            depth_range=(args.min_depth, args.max_depth),
        )
        if args.workers or args.scheduler:
            from .simulation import run_simulation_parallel

            result = run_simulation_parallel(cfg, workers=args.workers, scheduler=args.scheduler,
                                             timeout=args.connect_timeout)
        else:
            result = run_simulation(cfg, progress=not args.quiet)
        summary = result.summary()
        write_json(out / "metrics.json", summary)
        if not args.no_plots:
            from .plots import plot_simulation

            if plot_simulation(result, out / "plots") is None:
                _plots_missing()
        print(
            f"{cfg.runs} runs, {cfg.weighting} weighting, scale {cfg.scale:g}, {cfg.pixel_sigma:g} px: "
            f"ANEES translation {summary['anees_translation']:.2f}, rotation {summary['anees_rotation']:.2f} "
            f"(consistent: about 3)"
        )
        print(f"results in {out}")
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    from .study import evaluate_sequences

    config = _load_config(args).to_dict() if args.config else None
    topics = {"rgb_topic": args.rgb_topic, "depth_topic": args.depth_topic,
              "camera_info_topic": args.camera_info_topic}
    if args.camera:
        _camera(args)  # a bad --camera fails here, before any run
    rows = evaluate_sequences(args.sequences, args.out, camera=args.camera, config=config,
                              max_frames=args.max_frames, workers=args.workers, scheduler=args.scheduler,
                              timeout=args.connect_timeout, plots=not args.no_plots, topics=topics,
                              progress=not args.quiet)
    for r in rows:
        line = f"{r['sequence']}: {r['frames']} frames, {r['lost']} lost"
        if r["rpe1_m"] is not None:
            line += f", RPE1 {r['rpe1_m']:.4f} m"
        if r["anees_t"] is not None:
            line += f", ANEES t {r['anees_t']:.2f} r {r['anees_r']:.2f}"
        print(line)
    print(f"results in {args.out} (summary.csv, summary.md)")
    return 0


def _parallel_arguments(parser: argparse.ArgumentParser, what: str) -> None:
    parser.add_argument("--workers", type=_int_in(1, 256), metavar="N",
                        help=f"local worker processes for the {what} (1: in this process)")
    parser.add_argument("--scheduler", metavar="ADDR",
                        help=f"run the {what} on the Dask distributed scheduler at ADDR, e.g. tcp://127.0.0.1:8786 "
                        "(needs dask[distributed] here and on the workers)")
    parser.add_argument("--connect-timeout", type=_float_in(maximum=600), default=10.0, metavar="S",
                        help="seconds to wait for the scheduler (default 10)")


def cmd_analyze_noise(args: argparse.Namespace) -> int:
    from .analysis import analyze_sequence, plot_noise
    from .io import write_json
    from .pipeline import check_output_dir

    seq = _sequence(args)
    _, depth_scale = _camera(args)
    if depth_scale is not None and depth_scale != 5000:
        raise ConfigError(f"{args.camera}: analyze-noise reads TUM depth images (depth_scale 5000), got {depth_scale:g}")
    out = check_output_dir(args.out)
    with _lock_outputs(out, ["noise.json"], ("plots", ("noise.png",)), not args.no_plots):
        summary = analyze_sequence(seq, pixel_sigma=args.pixel_sigma, max_frames=args.max_frames,
                                   progress=not args.quiet)
        if not args.no_plots:
            if plot_noise(summary, out / "plots") is None:
                _plots_missing()
        summary.pop("_samples")
        write_json(out / "noise.json", summary)
        pe, dz = summary["pixel_error"], summary["depth_residual_normalised"]
        print(f"{summary['frame_pairs']} frame pairs, {summary['points']} inlier points: pixel error std "
              f"u {pe['std_u']:.2f} v {pe['std_v']:.2f} px "
              f"(robust {pe['robust_sigma_u']:.2f} / {pe['robust_sigma_v']:.2f}), "
              f"{100 * pe['share_above_10px']:.1f} % above 10 px; normalised depth residual std {dz['std']:.2f} "
              f"(robust {dz['robust_sigma']:.2f}, 1 = model right)")
        print(f"results in {out}")
    return 0


def cmd_calibrate(args: argparse.Namespace) -> int:
    import importlib.util

    from .io import write_json
    from .pipeline import calibrate_sequence, check_output_dir

    if importlib.util.find_spec("scipy") is None:
        raise CovoError('calibrate needs SciPy: pip install "covo-gtsam[calibrate]" (or pip install scipy)')
    config = _load_config(args)
    seq = _sequence(args)
    _check_config_fits(args, config, seq)
    out = check_output_dir(args.out)
    with _lock_outputs(out, ["calibration.json"]):
        fit, result = calibrate_sequence(seq, out / "per_point_run", config=config, max_frames=args.max_frames,
                                         progress=not args.quiet)
        summary = {"sequence": seq.name, "pairs": fit.pairs, **fit.config_values(),
                   "log_likelihood_per_pair": fit.log_likelihood,
                   "per_point_model_anees": [result.metrics.get("anees_translation"),
                                             result.metrics.get("anees_rotation")]}
        write_json(out / "calibration.json", summary)
        anees_t, anees_r = summary["per_point_model_anees"]
        anees = (f"ANEES t {anees_t:.2f} r {anees_r:.2f} (3 = consistent)"
                 if anees_t is not None and anees_r is not None else "no ANEES (see per_point_run/metrics.json)")
        print(f"{fit.pairs} consecutive pairs with ground truth; the per-point model alone gives {anees}")
        print("maximum-likelihood sensor terms (configuration lines):")
        print("[sensor]")
        for name, value in fit.config_values().items():
            print(f"{name} = {value:.3g}")
        print(f"results in {out}")
    return 0


def _lock_outputs(out: Path, files: list[str], figures: tuple | None = None, write_figures: bool = True):
    """Lock ``out`` for this command (a :class:`FolderLock`, held; use it in a ``with`` block), check
    what it will write and remove earlier results of those names."""
    from .io import FolderLock
    from .pipeline import prepare_outputs

    lock = FolderLock(out).acquire()
    try:
        prepare_outputs(out, files, figures, write_figures)
    except BaseException:
        lock.release()
        raise
    return lock


def _plots_missing() -> None:
    from .plots import PLOTS_MISSING

    print(PLOTS_MISSING, file=sys.stderr)


def _sequence_arguments(parser: argparse.ArgumentParser, help: str, bags: bool = False) -> None:
    """The sequence and ``--camera`` (and with ``bags`` the topic options), common to the commands
    that read a sequence."""
    if bags:
        parser.add_argument("sequence", metavar="SEQ", help=help)
    else:
        parser.add_argument("sequence", metavar="SEQ_DIR", help=help)
    _camera_argument(parser)
    if bags:
        _topic_arguments(parser)


def _camera_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--camera", metavar="NAME|FILE",
                        help="camera preset fr1, fr2 or fr3, or a camera file: ROS camera_calibration YAML, or "
                        "TOML/JSON with fx fy cx cy width height depth_scale [k1 k2 p1 p2 k3] (default: the bag's "
                        "camera info, or guessed from the folder name, e.g. 'freiburg1' -> fr1)")


def _topic_arguments(parser: argparse.ArgumentParser) -> None:
    from .datasets.rosbag import DEFAULT_TOPICS

    parser.add_argument("--rgb-topic", default=DEFAULT_TOPICS["rgb_topic"], metavar="TOPIC",
                        help="ROS bags: colour image topic, rgb8/bgr8/mono8 (default %(default)s)")
    parser.add_argument("--depth-topic", default=DEFAULT_TOPICS["depth_topic"], metavar="TOPIC",
                        help="ROS bags: depth image topic, 32FC1 metres or 16UC1 millimetres (default %(default)s)")
    parser.add_argument("--camera-info-topic", default=DEFAULT_TOPICS["camera_info_topic"], metavar="TOPIC",
                        help="ROS bags: sensor_msgs/CameraInfo topic (default %(default)s)")


def _output_arguments(parser: argparse.ArgumentParser, metavar: str = "OUT", plots: bool = True) -> None:
    """``--out`` (required), ``--no-plots`` (if the command plots) and ``--quiet``, common to every command."""
    parser.add_argument("--out", required=True, metavar=metavar, help="results folder (created if missing)")
    if plots:
        parser.add_argument("--no-plots", action="store_true", help="do not write plots/")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


class _HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Keeps the conventions epilog as written; wraps descriptions and help to the terminal width."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        if text.startswith("conventions:"):
            return super()._fill_text(text, width, indent)
        return argparse.HelpFormatter._fill_text(self, text, width, indent)


def _command(sub, name: str, help: str, description: str) -> argparse.ArgumentParser:
    """A sub-command with the shared epilog and formatter."""
    return sub.add_parser(name, help=help, description=description, epilog=EPILOG, formatter_class=_HelpFormatter)


def build_parser() -> argparse.ArgumentParser:
    from .choices import Weighting
    from .config import EstimatorConfig, NoiseConfig
    from .simulation import MAX_DEPTH, SimulationConfig

    weightings = [w.value for w in Weighting]

    parser = argparse.ArgumentParser(
        prog="covo",
        description="Error-aware RGB-D visual odometry on GTSAM: relative poses with covariances.",
        epilog=EPILOG,
        formatter_class=_HelpFormatter,
    )
    from . import __version__

    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    run = _command(
        sub, "run",
        help="run visual odometry on a TUM RGB-D sequence folder or a ROS bag",
        description="Run visual odometry on a TUM RGB-D sequence folder (rgb.txt, depth.txt, rgb/, depth/, "
        "optional groundtruth.txt) or a ROS bag (ROS 1 .bag file or ROS 2 bag folder; ground truth from /tf) "
        "and write trajectory.txt (TUM format), relative.txt (relative poses with 6x6 covariances), graph.g2o "
        "(pose graph), metrics.json, config.toml (the configuration used; --config OUT/config.toml repeats the run) "
        "and plots/ into OUT.",
    )
    _sequence_arguments(run, "TUM RGB-D sequence folder, ROS 1 .bag file or ROS 2 bag folder", bags=True)
    run.add_argument("--max-frames", type=_int_in(1), metavar="N",
                     help="process only the first N frames (default: all)")
    run.add_argument("--config", metavar="FILE", help="TOML or JSON settings (see README: configuration)")
    run.add_argument("--weighting", choices=weightings, help="residual weighting (default: consistent)")
    run.add_argument("--scale", type=_setting(EstimatorConfig, "scale"), metavar="PHI",
                     help="the thesis's covariance scale phi: multiplies each pair's point-transfer "
                     "covariance inside the estimator; the calibrated sensor terms are applied after (default 1)")
    run.add_argument("--bag-out", choices=["ros1", "ros2"],
                     help="also write the odometry as a ROS bag: OUT/odometry.bag (ros1) or OUT/odometry/ (ros2) "
                     "with /covo/odometry (nav_msgs/Odometry) and /covo/relative (PoseWithCovarianceStamped)")
    _output_arguments(run)
    run.set_defaults(func=cmd_run)

    sim = _command(
        sub, "simulate",
        help="Monte Carlo consistency study of the thesis's simulation (section 5.2)",
        description="Monte Carlo simulation of the thesis (5.2): 500 points seen by two fr1 cameras, motion "
        "[0.6 0.6 0.05 | -0.183 -0.183 0 0.966], pixel noise and Kinect depth noise. Writes metrics.json "
        "(ANEES, predicted vs empirical sigmas) and plots/ into OUT.",
    )
    sim.add_argument("--runs", type=_setting(SimulationConfig, "runs"), default=1000, metavar="N",
                     help="Monte Carlo runs (default 1000)")
    sim.add_argument("--seed", type=_setting(SimulationConfig, "seed"), default=0, metavar="S",
                     help="random seed, >= 0 (default 0)")
    sim.add_argument("--weighting", choices=weightings, default="consistent",
                     help="residual weighting (default: consistent)")
    sim.add_argument("--scale", type=_setting(SimulationConfig, "scale"), default=1.0, metavar="PHI",
                     help="covariance scale phi (thesis: 16; default 1)")
    sim.add_argument("--pixel-sigma", type=_setting(SimulationConfig, "pixel_sigma"), default=8.0, metavar="PX",
                     help="pixel noise standard deviation in pixels (default 8)")
    sim.add_argument("--points", type=_setting(SimulationConfig, "num_points"), default=500, metavar="N",
                     help="points per run (default 500)")
    sim.add_argument("--min-depth", type=_float_in(maximum=MAX_DEPTH), default=0.5, metavar="M",
                     help="nearest depth (default 0.5 m)")
    sim.add_argument("--max-depth", type=_float_in(maximum=MAX_DEPTH), default=5.0, metavar="M",
                     help=f"farthest depth (default 5 m, at most {MAX_DEPTH:g} m)")
    _parallel_arguments(sim, "Monte Carlo runs (same seed, same numbers)")
    _output_arguments(sim, "DIR")
    sim.set_defaults(func=cmd_simulate)

    ev = _command(
        sub, "evaluate",
        help="run covo on many sequences (TUM folders or ROS bags) and summarise, locally or on Dask",
        description="Run `covo run` on each sequence into DIR/<name>/ and write DIR/summary.csv, DIR/summary.md "
        "(frames, lost, RPE 1 and 30 frames, ATE, ANEES, share of NEES above 9.35, frames/s per sequence) and "
        "DIR/plots/summary.png. The runs go to a local process pool (default one per sequence, at most one per "
        "core) or to a Dask distributed cluster; the numbers do not depend on where they ran.",
    )
    ev.add_argument("sequences", nargs="+", metavar="SEQ", help="TUM RGB-D folders, ROS 1 .bag files or ROS 2 bags")
    _camera_argument(ev)
    _topic_arguments(ev)
    ev.add_argument("--max-frames", type=_int_in(1), metavar="N", help="only the first N frames of each (default: all)")
    ev.add_argument("--config", metavar="FILE", help="TOML or JSON settings for every run (see README: configuration)")
    _parallel_arguments(ev, "sequences")
    _output_arguments(ev, "DIR")
    ev.set_defaults(func=cmd_evaluate)
    noise = _command(
        sub, "analyze-noise",
        help="measure pixel and depth noise of matched inliers against ground truth (thesis 5.3.1)",
        description="Use the sequence's ground truth to measure the image-plane error of the matched inliers "
        "(pseudo-inliers included) per frame pair and over time, and the depth residuals against the depth "
        "model. Writes noise.json and plots/noise.png into OUT.",
    )
    _sequence_arguments(noise, "TUM RGB-D sequence folder with groundtruth.txt")
    noise.add_argument("--max-frames", type=_int_in(2), metavar="N",
                       help="only the first N frames (at least 2; default: all)")
    noise.add_argument("--pixel-sigma", type=_setting(NoiseConfig, "pixel_sigma"), default=2.0,
                       metavar="PX",
                       help="pixel noise used by the outlier gate (default 2)")
    _output_arguments(noise)
    noise.set_defaults(func=cmd_analyze_noise)

    cal = _command(
        sub, "calibrate",
        help="fit the sensor terms of the covariance on a sequence with ground truth",
        description="Fit the sensor terms of the reported covariance (correlation_factor, frame_sigma_rot_deg, "
        "frame_sigma_trans_m and the frame-level terms timing_sigma_s, rolling_shutter_factor; see covo_gtsam.calibration) by maximum likelihood on the consecutive frame pairs "
        "of a sequence with ground truth, for a sensor other than the Kinect v1 the defaults belong to. Runs "
        "the odometry with the per-point model alone into OUT/per_point_run, writes OUT/calibration.json and "
        "prints the configuration lines. Needs SciPy.",
    )
    _sequence_arguments(cal, "TUM RGB-D sequence folder with groundtruth.txt")
    cal.add_argument("--max-frames", type=_int_in(11), metavar="N",
                     help="only the first N frames (at least 11; default: all)")
    cal.add_argument("--config", metavar="FILE",
                     help="TOML or JSON settings for the run; its sensor terms are ignored (see README)")
    _output_arguments(cal, plots=False)
    cal.set_defaults(func=cmd_calibrate)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run one command; the exit code: 0 done, 2 unusable input (one line on stderr), 3 ``covo run``
    tracked no frame, 130 interrupted (Ctrl-C)."""
    try:
        parser = build_parser()  # imports GTSAM: Ctrl-C may arrive here
        args = parser.parse_args(argv)
        return args.func(args)
    except CovoError as exc:
        print(f"covo: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return _interrupted()
    except ImportError as exc:
        # Ctrl-C while an extension module initialises surfaces as an ImportError
        if isinstance(exc.__cause__ or exc.__context__, KeyboardInterrupt):
            return _interrupted()
        raise


def _interrupted() -> int:
    print("covo: interrupted; files written so far are valid (an interrupted run has no metrics.json)",
          file=sys.stderr)
    return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
