"""The ``covo`` command line's arguments: sub-commands, their options and ranges (read from the
declared settings), help texts. :mod:`covo_gtsam.cli` runs the commands."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable, Mapping

EPILOG = """\
conventions:
  T_ref,cur maps points of the current camera frame into the reference frame.
  Covariances (relative.txt, the Python API) are 6x6 in GTSAM's Pose3 tangent
  [rx ry rz tx ty tz] (rad, m), right perturbation T_true = T_est * Exp(xi).
  graph.g2o holds their inverse in g2o's order [x y z rx ry rz]; ROS bags
  (--bag-out) hold ROS's [x y z rot_x rot_y rot_z] about the parent's axes.
  Quaternions are qx qy qz qw.

exit codes:
  0 done; 2 unusable input (one line on stderr); 130 interrupted (Ctrl-C);
  3 covo run tracked no frame, or of two or more frames estimated no relative
  pose (its results are written); covo evaluate, when that happened to one of
  its sequences (the summary is written). A standard output closed early
  (piped into head) loses the rest of what is printed, nothing else.
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


def _number_in(minimum: float, maximum: float):
    """argparse type: a finite number in ``[minimum, maximum]`` (zero and negative ones included)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number in [{minimum:g}, {maximum:g}], got {text!r}") from None
        if not (math.isfinite(value) and minimum <= value <= maximum):
            raise argparse.ArgumentTypeError(f"expected a number in [{minimum:g}, {maximum:g}], got {value:g}")
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


def _parallel_arguments(parser: argparse.ArgumentParser, what: str) -> None:
    parser.add_argument("--workers", type=_int_in(1, 256), metavar="N",
                        help=f"local worker processes for the {what}; 1 runs them in this process (default: one "
                        "per core, at most one per task)")
    parser.add_argument("--scheduler", metavar="ADDR",
                        help=f"run the {what} on the Dask distributed scheduler at ADDR, e.g. tcp://127.0.0.1:8786 "
                        "(needs dask[distributed] here and on the workers)")
    parser.add_argument("--connect-timeout", type=_float_in(maximum=600), default=10.0, metavar="S",
                        help="seconds to wait for the scheduler (default 10)")


def _sequence_arguments(parser: argparse.ArgumentParser, help: str, bags: bool = False) -> None:
    """The sequence and ``--camera`` (and with ``bags`` the topic options), common to the commands
    that read a sequence."""
    if bags:
        parser.add_argument("sequence", metavar="SEQ", help=help)
    else:
        parser.add_argument("sequence", metavar="SEQ_DIR", help=help)
    _camera_argument(parser, bags)
    if bags:
        _topic_arguments(parser)


def _camera_argument(parser: argparse.ArgumentParser, bags: bool = True) -> None:
    default = "the bag's camera info, or guessed" if bags else "guessed"
    parser.add_argument("--camera", metavar="NAME|FILE",
                        help="camera preset fr1, fr2 or fr3, or a camera file: ROS camera_calibration YAML, OpenCV "
                        "calibration YAML (cv::FileStorage), or "
                        f"TOML/JSON with fx fy cx cy width height depth_scale [k1 k2 p1 p2 k3] (default: {default} "
                        "from the folder name, e.g. 'freiburg1' -> fr1)")


def _topic_arguments(parser: argparse.ArgumentParser) -> None:
    from .datasets.rosbag import DEFAULT_TOPICS

    parser.add_argument("--rgb-topic", default=DEFAULT_TOPICS["rgb_topic"], metavar="TOPIC",
                        help="ROS bags: colour image topic, rgb8/bgr8/mono8 (default %(default)s)")
    parser.add_argument("--depth-topic", default=DEFAULT_TOPICS["depth_topic"], metavar="TOPIC",
                        help="ROS bags: depth image topic, 32FC1 metres or 16UC1 millimetres (default %(default)s)")
    parser.add_argument("--camera-info-topic", default=DEFAULT_TOPICS["camera_info_topic"], metavar="TOPIC",
                        help="ROS bags: sensor_msgs/CameraInfo topic (default %(default)s)")


def _gyro_arguments(parser: argparse.ArgumentParser) -> None:
    from .datasets.rosbag import DEFAULT_GYRO_TOPIC

    parser.add_argument("--gyro", metavar="FILE|BAG",
                        help="the camera's gyroscope: a text file of 't wx wy wz' lines (s on the frames' clock, "
                        "rad/s) or a ROS bag's sensor_msgs/Imu topic (--gyro-topic), whose angular velocity at each "
                        "frame (and its change over the readout) moves the colour rows in place of the pairs' twists "
                        "(its error: sensor.gyro_sigma_rad_s; frame to frame only, not in keyframe mode); "
                        "metrics.json's gyro says how many pairs it covered")
    parser.add_argument("--gyro-topic", default=DEFAULT_GYRO_TOPIC, metavar="TOPIC",
                        help=f"with --gyro BAG: its sensor_msgs/Imu topic (default {DEFAULT_GYRO_TOPIC})")
    parser.add_argument("--gyro-rotation", type=float, nargs=4, metavar=("QX", "QY", "QZ", "QW"),
                        help="with --gyro: the gyroscope's axes in the camera's optical frame (x right, y down, "
                        "z forward), R_cam_gyro as a unit quaternion (default: the same axes)")
    parser.add_argument("--gyro-time-offset", type=_number_in(-1.0, 1.0), default=0.0, metavar="S",
                        help="with --gyro: added to its stamps to put them on the frames' clock (default 0)")


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
    """A sub-command with the shared epilog and formatter; ``args.command_parser`` is it (for errors
    about its own arguments)."""
    command = sub.add_parser(name, help=help, description=description, epilog=EPILOG, formatter_class=_HelpFormatter)
    command.set_defaults(command_parser=command)
    return command


def build_parser(handlers: Mapping[str, Callable[[argparse.Namespace], int]]) -> argparse.ArgumentParser:
    """The ``covo`` argument parser; ``handlers`` maps each sub-command to the function that runs it
    (``args.func``)."""
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
    run.add_argument("--config", metavar="FILE", help="TOML or JSON settings, one table per stage (every setting: "
                     "docs/configuration.md; a run's OUT/config.toml repeats it)")
    run.add_argument("--weighting", choices=weightings, help="residual weighting (default: consistent)")
    run.add_argument("--scale", type=_setting(EstimatorConfig, "scale"), metavar="PHI",
                     help="the thesis's covariance scale phi: multiplies each pair's point-transfer "
                     "covariance inside the estimator; the calibrated sensor terms are applied after (default 1)")
    _gyro_arguments(run)
    run.add_argument("--bag-out", choices=["ros1", "ros2"],
                     help="also write the odometry as a ROS bag: OUT/odometry.bag (ros1) or OUT/odometry/ (ros2) "
                     "with /covo/odometry (nav_msgs/Odometry) and /covo/relative (PoseWithCovarianceStamped)")
    _output_arguments(run)
    run.set_defaults(func=handlers["run"])

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
    sim.add_argument("--bias-draws", type=_setting(SimulationConfig, "bias_draws"), default=0, metavar="N",
                     help="correct each estimate for its bias by a parametric bootstrap of N re-estimates "
                     "(default 0: none; 16 removes the bias at 8 px, docs/consistency.md finding 12)")
    _parallel_arguments(sim, "Monte Carlo runs, same seed same numbers,")
    _output_arguments(sim, "DIR")
    sim.set_defaults(func=handlers["simulate"])

    ev = _command(
        sub, "evaluate",
        help="run covo on many sequences (TUM folders or ROS bags) and summarise, locally or on Dask",
        description="Run `covo run` on each sequence into DIR/<name>/ and write DIR/summary.csv, DIR/summary.md "
        "(frames, lost, RPE 1 and 30 frames, ATE, ANEES, share of NEES above 9.35, ANEES of the 30-pair chains, "
        "the highest ANEES of the blocks of 60 pairs, frames/s per sequence; every NEES adds the ground truth's own "
        "jitter when its samples allow measuring it) and "
        "DIR/plots/summary.png. The runs go to a local process pool (default one per sequence, at most one per "
        "core) or to a Dask distributed cluster; the numbers do not depend on where they ran.",
    )
    ev.add_argument("sequences", nargs="+", metavar="SEQ", help="TUM RGB-D folders, ROS 1 .bag files or ROS 2 bags")
    _camera_argument(ev)
    _topic_arguments(ev)
    ev.add_argument("--max-frames", type=_int_in(1), metavar="N", help="only the first N frames of each (default: all)")
    ev.add_argument("--config", metavar="FILE",
                    help="TOML or JSON settings for every run (every setting: docs/configuration.md)")
    _parallel_arguments(ev, "sequences")
    _output_arguments(ev, "DIR")
    ev.set_defaults(func=handlers["evaluate"])
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
    noise.set_defaults(func=handlers["analyze-noise"])

    cal = _command(
        sub, "calibrate",
        help="fit the sensor terms of the covariance on a sequence with ground truth",
        description="Fit the sensor terms of the reported covariance (correlation_factor, frame_sigma_rot_deg, "
        "frame_sigma_trans_m and the frame-level terms timing_sigma_s, rolling_shutter_factor, latency_sigma_s, "
        "depth_scale_sigma, depth_time_factor, depth_time_coherent_factor; see covo_gtsam.calibration) by maximum "
        "likelihood on the consecutive "
        "frame pairs of a sequence with ground truth, for a sensor other than the Kinect v1 the defaults belong to; "
        "then span_factor (pairs over more than one frame interval) on the pairs of runs over every 2nd and 3rd "
        "frame, the other terms held (it keeps the configured value with fewer than 10 such pairs, about 50 "
        "frames). Runs the odometry with the per-point model alone into OUT/per_point_run, writes "
        "OUT/calibration.json and prints the configuration lines. Needs SciPy.",
    )
    _sequence_arguments(cal, "TUM RGB-D sequence folder with groundtruth.txt")
    cal.add_argument("--max-frames", type=_int_in(11), metavar="N",
                     help="only the first N frames (at least 11, and about 30 with the frame clock on, which "
                          "places the stamps from the 20th frame on; default: all)")
    cal.add_argument("--config", metavar="FILE",
                     help="TOML or JSON settings for the run; its sensor terms are ignored, except span_factor "
                          "when too few pairs fit it (see README)")
    cal.add_argument("--jitter-in-terms", action="store_true",
                     help="let the fitted terms take in the ground truth's own rotation jitter too (default: that "
                     "jitter, measured from all its samples as reference_jitter in metrics.json, is held as a known "
                     "term, so the terms describe the camera alone and covo's NEES adds the reference's jitter back "
                     "when it checks against one; terms fitted with this flag have the jitter twice in such a check)")
    _gyro_arguments(cal)
    _output_arguments(cal, plots=False)
    cal.set_defaults(func=handlers["calibrate"])
    return parser
