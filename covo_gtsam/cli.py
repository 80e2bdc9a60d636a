"""Command line: ``covo run``, ``covo evaluate``, ``covo simulate``, ``covo analyze-noise``, ``covo calibrate``.

Every failure the package knows about ends with exit code 2 and one line on stderr naming the
file and the problem; no traceback. ``covo run`` that tracks no frame at all, or of more than one
frame estimates no relative pose, ends with exit code 3 (its results are written), and so does
``covo evaluate`` when that happens to one of its sequences (its summary is written); Ctrl-C ends
any command with 130.
"""

from __future__ import annotations

import argparse
import gc
import math
import os
import sys
import warnings
from pathlib import Path

from .errors import ConfigError, CovoError, CovoWarning
from .interrupt import recorded_sigint

#: ``covo calibrate`` warns when it fits the terms on fewer consecutive pairs than this
FEW_CALIBRATION_PAIRS = 100


def one_line(message: str) -> str:
    """``message`` on one line: a library's multi-line text (e.g. a YAML parser's, with its caret
    line) joined by ``"; "``, runs of spaces squeezed."""
    parts = [" ".join(line.split()) for line in message.splitlines()]
    return "; ".join(p for p in parts if p and p != "^")


def load_config_file(path: str):
    """Deprecated: :func:`covo_gtsam.config.load_config` (removed from the command line module in
    the next release)."""
    from .config import load_config

    warnings.warn("covo_gtsam.cli.load_config_file is deprecated; use covo_gtsam.config.load_config",
                  DeprecationWarning, stacklevel=2)
    return load_config(path)


#: Exit code of ``covo run`` when no frame could be tracked, or no relative pose estimated (the
#: results folder is still written); of ``covo evaluate`` when that happened to a sequence.
EXIT_NOTHING_TRACKED = 3


def _no_relative_pose(frames: int, tracked_frames: int, relative_poses: int) -> bool:
    """A run that tracked frames but estimated no relative pose between any two of them (a run of
    one frame has no pair to estimate)."""
    return frames > 1 and tracked_frames > 0 and relative_poses == 0


def _gyroscope(args: argparse.Namespace):
    """``--gyro FILE`` and its settings as a :class:`~covo_gtsam.gyro.Gyroscope` (None without it)."""
    from .datasets.rosbag import DEFAULT_GYRO_TOPIC, is_bag, read_gyro

    told = ["gyro_rotation"] if args.gyro_rotation is not None else []
    told += ["gyro_time_offset"] if args.gyro_time_offset != 0.0 else []
    told += ["gyro_topic"] if args.gyro_topic != DEFAULT_GYRO_TOPIC else []
    if args.gyro is None:
        if told:
            raise ConfigError(f"--{told[0].replace('_', '-')} needs --gyro FILE|BAG")
        return None
    if is_bag(args.gyro):
        return read_gyro(args.gyro, args.gyro_topic, rotation=args.gyro_rotation, time_offset_s=args.gyro_time_offset)
    if args.gyro_topic != DEFAULT_GYRO_TOPIC:
        raise ConfigError(f"--gyro-topic reads a ROS bag; {args.gyro} is not one (a text file of 't wx wy wz' lines)")
    from .gyro import Gyroscope

    return Gyroscope.from_file(args.gyro, rotation=args.gyro_rotation, time_offset_s=args.gyro_time_offset)


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
    gyro = _gyroscope(args)
    check_output_dir(args.out)
    result = run_sequence(
        seq, args.out, config=config, max_frames=args.max_frames, plots=not args.no_plots, progress=not args.quiet,
        bag_out=args.bag_out, gyro=gyro,
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
    notes = []
    if m.get("anees_band_95"):  # how far from 3 so many pairs stray by chance
        notes.append(f"95 % band for {m['nees_pairs']} pairs {m['anees_band_95'][0]:.2f}-{m['anees_band_95'][1]:.2f}")
    if m.get("chains"):
        c = m["chains"]
        notes.append(f"chains of {c['pairs_per_chain']}: t {c['anees_translation']:.2f} r {c['anees_rotation']:.2f}")
    line += f" ({'; '.join(notes)})" if notes else ""
    print(line)
    if getattr(seq, "groundtruth", None) is None:
        gt = Path(getattr(seq, "path", "")) / "groundtruth.txt"
        why = ("groundtruth.txt is not a file" if gt.is_dir() else "groundtruth.txt has no samples"
               if gt.is_file() else "no ground truth")
        print(f"{seq.name}: {why}; accuracy and consistency metrics skipped")
    if not args.config and not _is_fr1(seq, told=bool(args.camera)):  # the default terms are a freiburg1 Kinect's
        parts = m.get("covariance_parts")
        constant = "" if parts is None else (
            f"; they are {100 * _sensor_share(parts['rotation']):.0f} % of this run's rotation variance and "
            f"{100 * _sensor_share(parts['translation']):.0f} % of its translation variance, the constant frame "
            f"term {100 * parts['rotation']['frame_term']:.0f} % of the rotation")
        print(f"note: the covariance's sensor terms are the defaults, fitted on the freiburg1 Kinect of TUM RGB-D "
              f"(this camera: {seq.camera.name}{constant}); check them on this camera with covo calibrate on a "
              "sequence with ground truth (README, \"Known limits of the covariance\")")
    late = (m.get("gyro") or {}).get("clock_offset_s")
    if late is not None and abs(late) > max(0.001, 3 * m["gyro"]["clock_offset_se_s"]):
        print(f"note: the gyroscope's stamps lie {1e3 * late:+.1f} ± {1e3 * m['gyro']['clock_offset_se_s']:.1f} ms "
              "behind the frames' clock by the pairs' own turns (its angular velocity is read that far off at each "
              f"frame); run again with --gyro-time-offset {args.gyro_time_offset - late:.4f}")
    if gyro is not None and not args.config:
        print(f"note: the sensor terms are the defaults, fitted without a gyroscope; {m['gyro']['pairs']} pairs were "
              f"compensated with it and take its error as sensor.gyro_sigma_rad_s "
              f"({config.sensor.gyro_sigma_rad_s:g} rad/s, a MEMS gyroscope's noise): fit the terms with covo calibrate "
              "--gyro on a sequence with ground truth before trusting the covariance")
    if result.plot_files is None:
        _plots_missing()
    print(f"results in {result.out_dir}")
    if m["tracked_frames"] == 0:
        first = m["lost"][0]["reason"] if m["lost"] else "no frame"
        print(f"covo: error: no frame could be tracked: all {m['frames']} frames are lost (first reason: {first}); "
              f"see metrics.json", file=sys.stderr)
        return EXIT_NOTHING_TRACKED
    if _no_relative_pose(m["frames"], m["tracked_frames"], sum(s.has_relative_pose for s in result.steps)):
        first = m["lost"][0]["reason"] if m["lost"] else "none was lost"
        print(f"covo: error: no relative pose could be estimated between any two of the {m['frames']} frames "
              f"(first lost frame: {first}); relative.txt is empty; see metrics.json", file=sys.stderr)
        return EXIT_NOTHING_TRACKED
    return 0


def _sensor_share(block: dict) -> float:
    """The sensor terms' share of a block of ``metrics.json``'s ``covariance_parts``: all but the
    per-point model's and the depth-drift correction's."""
    return 1.0 - block["points"] - block.get("depth_drift", 0.0)


def _is_fr1(seq, told: bool) -> bool:
    """Whether ``seq`` comes from the freiburg1 Kinect: its camera has the freiburg1 preset's
    intrinsics (whatever its name), or, unless ``--camera`` ``told`` another, its folder or bag is
    named for freiburg1 (a TUM bag's camera info carries other intrinsics)."""
    from dataclasses import replace

    from .camera import PRESETS
    from .datasets.tum import camera_name_from_path

    return (replace(seq.camera, name=PRESETS["fr1"].name) == PRESETS["fr1"]
            or (not told and camera_name_from_path(getattr(seq, "path", "")) == "fr1"))


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
            depth_range=(args.min_depth, args.max_depth), bias_draws=args.bias_draws,
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
        if r["error"]:
            print(f"{r['sequence']}: failed")
            continue
        line = f"{r['sequence']}: {r['frames']} frames, {r['lost']} lost"
        if r["rpe1_m"] is not None:
            line += f", RPE1 {r['rpe1_m']:.4f} m"
        if r["anees_t"] is not None:
            line += f", ANEES t {r['anees_t']:.2f} r {r['anees_r']:.2f}"
        print(line)
    print(f"results in {args.out} (summary.csv, summary.md)")
    failed = [r for r in rows if r["error"]]
    for r in failed:
        print(f"covo: error: {r['error']}", file=sys.stderr)
    if failed:
        return 2
    nothing = [r["sequence"] for r in rows if r["frames"] and r["lost"] == r["frames"]]
    no_pose = [r["sequence"] for r in rows
               if _no_relative_pose(r["frames"], r["frames"] - r["lost"], r["relative_poses"])]
    problems = []
    if nothing:
        problems.append(f"no frame could be tracked in {', '.join(nothing)}: all frames are lost")
    if no_pose:
        problems.append(f"no relative pose could be estimated between any two frames of {', '.join(no_pose)} "
                        "(relative.txt is empty)")
    if problems:
        print(f"covo: error: {'; '.join(problems)}; see their metrics.json", file=sys.stderr)
        return EXIT_NOTHING_TRACKED
    return 0


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

    from .calibration import MIN_SPAN_PAIRS
    from .io import write_json
    from .pipeline import calibrate_sequence, check_output_dir

    if importlib.util.find_spec("scipy") is None:
        raise CovoError('calibrate needs SciPy: pip install "covo-gtsam[calibrate]" (or pip install scipy)')
    config = _load_config(args)
    seq = _sequence(args)
    _check_config_fits(args, config, seq)
    out = check_output_dir(args.out)
    reference_sd, no_jitter = None, None
    if not args.jitter_in_terms:
        import numpy as np

        from .errors import InputError
        from .evaluation import reference_statistics

        try:
            if seq.gt_samples is None:
                raise InputError("no samples of its own")
            reference_sd = np.deg2rad(reference_statistics(seq.gt_samples)["rotation_deg"])
        except InputError as exc:
            no_jitter = (f"covo: warning: {seq.path}: the ground truth's own jitter cannot be measured ({exc}); the "
                         "fitted terms take it in")
    with _lock_outputs(out, ["calibration.json"]):
        fit, result = calibrate_sequence(seq, out / "per_point_run", config=config, max_frames=args.max_frames,
                                         progress=not args.quiet, reference_sd=reference_sd, gyro=_gyroscope(args))
        summary = {"sequence": seq.name, "pairs": fit.pairs, "span_pairs": fit.span_pairs, **fit.config_values(),
                   "log_likelihood_per_pair": fit.log_likelihood,
                   "per_point_model_anees": [result.metrics.get("anees_translation"),
                                             result.metrics.get("anees_rotation")],
                   "reference_jitter_held_deg": (None if reference_sd is None
                                                 else [math.degrees(float(x)) for x in reference_sd])}
        write_json(out / "calibration.json", summary)
        if no_jitter:
            print(no_jitter, file=sys.stderr)
        if fit.pairs < FEW_CALIBRATION_PAIRS:
            print(f"covo: warning: only {fit.pairs} consecutive pairs with ground truth: terms fitted on so few are "
                  f"uncertain (the defaults rest on 118)",
                  file=sys.stderr)
        anees_t, anees_r = summary["per_point_model_anees"]
        anees = (f"ANEES t {anees_t:.2f} r {anees_r:.2f} (3 = consistent)"
                 if anees_t is not None and anees_r is not None else "no ANEES (see per_point_run/metrics.json)")
        print(f"{fit.pairs} consecutive pairs with ground truth; the per-point model alone gives {anees}")
        print("maximum-likelihood sensor terms (configuration lines):")
        print("[sensor]")
        for name, value in fit.config_values().items():
            print(f"{name} = {value:.3g}")
        if fit.span_pairs < MIN_SPAN_PAIRS:
            print(f"(span_factor is the configured value: the runs over every 2nd and 3rd frame gave "
                  f"{fit.span_pairs} usable pairs to fit it on, fewer than {MIN_SPAN_PAIRS}: pairs with ground truth at both "
                  "frames, placed by the frame clock, not flagged, after a frame with a velocity)")
        else:
            print(f"(span_factor fitted on {fit.span_pairs} pairs over 2 and 3 frame intervals)")
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


def build_parser() -> argparse.ArgumentParser:
    """The ``covo`` argument parser (:func:`covo_gtsam.cli_parser.build_parser`) wired to the commands."""
    from .cli_parser import build_parser as parser_for

    return parser_for({"run": cmd_run, "simulate": cmd_simulate, "evaluate": cmd_evaluate,
                       "analyze-noise": cmd_analyze_noise, "calibrate": cmd_calibrate})


def main(argv: list[str] | None = None) -> int:
    """Run one command; the exit code: 0 done, 2 unusable input (one line on stderr), 3 ``covo run``
    tracked no frame or estimated no relative pose (``covo evaluate``: a sequence did), 130
    interrupted (Ctrl-C). A standard output closed early (``covo run ... | head -1``) loses the rest of
    what the command prints, nothing else (:class:`_ReaderMayLeave`)."""
    _one_blas_thread(sys.argv[1:] if argv is None else argv)
    stdout, sys.stdout = sys.stdout, _ReaderMayLeave(sys.stdout)
    try:
        parser = build_parser()  # imports GTSAM: Ctrl-C may arrive here
        args, unknown = parser.parse_known_args(argv)
        if unknown:  # the sub-command's usage, not the top level's
            args.command_parser.error(f"unrecognized arguments: {' '.join(unknown)}")
        with warnings.catch_warnings(), recorded_sigint():
            warnings.showwarning = _show_warning(warnings.showwarning)
            code = args.func(args)
        if argv is None:  # a program run (the console script, python -m) ends here
            gc.freeze()  # spares the interpreter's shutdown its collections over every object left
        return code
    except (CovoError, CovoWarning) as exc:  # a warning is raised where Python's options make warnings errors
        print(f"covo: error: {one_line(str(exc))}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return _interrupted()
    except ImportError as exc:
        # Ctrl-C while an extension module initialises surfaces as an ImportError
        if isinstance(exc.__cause__ or exc.__context__, KeyboardInterrupt):
            return _interrupted()
        raise
    finally:
        sys.stdout = stdout


class _ReaderMayLeave:
    """Standard output whose reader may leave before the end (a pipe into ``head``): from the first
    broken pipe on, what is printed goes to the null device, so the command runs to its end with its
    own exit code and stderr lines, and the interpreter's last flush finds nothing to fail on."""

    def __init__(self, inner) -> None:
        self._inner, self._gone = inner, False

    def _left(self) -> None:
        self._gone = True
        try:
            os.dup2(os.open(os.devnull, os.O_WRONLY), self._inner.fileno())
        except (OSError, ValueError, AttributeError):  # not a real file (a test's capture)
            pass

    def write(self, text: str) -> int:
        if not self._gone:
            try:
                return self._inner.write(text)
            except BrokenPipeError:
                self._left()
        return len(text)

    def flush(self) -> None:
        if not self._gone:
            try:
                self._inner.flush()
            except BrokenPipeError:
                self._left()

    def __getattr__(self, name):
        return getattr(self._inner, name)


def _show_warning(show):
    """``warnings.showwarning`` that prints the package's own warnings (:class:`~covo_gtsam.errors.CovoWarning`)
    as one ``covo: warning:`` line on stderr and leaves others to ``show``."""

    def showwarning(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, CovoWarning):
            print(f"covo: warning: {message}", file=sys.stderr)
        else:
            show(message, category, filename, lineno, file, line)

    return showwarning


def _one_blas_thread(argv: list[str]) -> None:
    """``covo run`` keeps numpy's BLAS to one thread while it runs (:func:`~covo_gtsam.pipeline.kernel_threads`):
    OpenBLAS is then started with one thread (``OPENBLAS_NUM_THREADS=1``, unless set), as long as numpy is
    not imported yet. Its other threads would spin on their cores for a while after starting, about 60 ms
    of CPU per run on two cores, and again after any BLAS call outside the run."""
    if argv[:1] == ["run"] and "numpy" not in sys.modules:
        os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def _interrupted() -> int:
    print("covo: interrupted; files written so far are valid (an interrupted run has no metrics.json)",
          file=sys.stderr)
    return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
