"""Streaming RGB-D visual odometry: one entry point, :meth:`VisualOdometry.register_frame`.

Data flow per frame: colour + depth -> ORB features and per-keypoint 3D points with covariances
(:mod:`covo_gtsam.frontend`) -> matched point pairs with the previous tracked frame -> relative
pose ``T_ref,cur`` and its covariance (:mod:`covo_gtsam.estimator`) -> absolute pose
``T_world,cur`` (world = the first tracked camera frame) with a first-order composed covariance.
"""

from __future__ import annotations

import dataclasses
import threading
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np

from .calibration import ERROR_TERMS, frame_covariance, sensor_covariance, timing_covariance
from .camera import Camera
from .covariance import compose_covariance
from .errors import ConfigError, CovoError, EstimationError, InputError
from .estimator import ROBUST_KERNELS, RelativePoseResult, estimate_relative_pose
from .transfer import WEIGHTINGS
from .clock import FrameClock, restamp
from .integrity import IntegrityScale, depth_free_check
from .datasets.images import to_grey
from .frontend import FrameData, FrontendConfig, PointPairs, associate_frames, make_orb, prepare_frame
from .geometry import image_velocities
from .noise import KinectAxialNoise, PixelNoise, PointNoiseModel, depth_lookup_variance
from .frame_errors import (depth_scale_basis, depth_time_basis, depth_time_shift, rolling_shutter_basis,
                           transfer_gains)
from .rolling_shutter import compensate_points, frame_twists, row_time_offsets
from .validation import (MAX_PIXEL_SIGMA, MAX_SCALE, MIN_PIXEL_SIGMA, check_bool, check_choice, check_int,
                         check_real)


#: Step statuses that carry a pose (``OdometryStep.tracked``).
POSED_STATUSES = ("first", "tracked", "restart")
#: Choices of ``OdometryConfig.motion_model``.
MOTION_MODELS = ("constant_velocity", "none")
#: Longest time (s) between a frame and its reference frame that is still matched: a longer gap is
#: not one recording (e.g. a corrupt timestamp), and the frame term would grow without bound.
MAX_GAP_S = 3600.0


#: Real-valued settings of :class:`OdometryConfig`: kind and range (None: unbounded on that side).
_REAL_LIMITS = {
    "pixel_sigma": ("positive", MIN_PIXEL_SIGMA, MAX_PIXEL_SIGMA),
    "depth_sigma_scale": ("positive", 1e-3, 1e3),
    "scale": ("positive", None, MAX_SCALE),
    "depth_scale": ("positive", None, 1e9),
    "keyframe_ratio": ("positive", None, 1.0),
    "max_rotation_deg": ("positive", None, 180.0),
    "max_translation_m": ("positive", None, 1e3),
    "correlation_factor": ("positive", None, MAX_SCALE),
    "frame_sigma_rot_deg": ("non-negative", None, 180.0),
    "frame_sigma_trans_m": ("non-negative", None, 1e3),
    "frame_interval_s": ("positive", 1e-4, 1e3),
    "timing_sigma_s": ("non-negative", None, 1.0),
    "depth_scale_sigma": ("non-negative", None, 1.0),
    "depth_time_factor": ("non-negative", None, 100.0),
    "rolling_shutter_factor": ("non-negative", None, 100.0),
    "stamp_jitter_s": ("non-negative", None, 1.0),
    "integrity_threshold": ("positive", None, None),
    "rolling_shutter_s": ("non-negative", None, 1.0),
    "depth_offset_factor": ("non-negative", None, 100.0),
}


@dataclass(frozen=True)
class OdometryConfig:
    """Settings of :class:`VisualOdometry` (front end, noise model, estimator).

    ``pixel_sigma`` (pixels) is the conic-ray noise of the keypoints; ``depth_sigma_scale``
    multiplies the Kinect depth model's ``sigma_Z`` (4.5: the value with the most accurate
    frame-to-frame poses on the first half of the shared fr1_rpy frames; 1: the published model;
    see docs/consistency.md, finding 3). The per-point model treats
    the points' errors as independent; a real Kinect v1 also has errors shared by the points of a
    frame pair (depth-image distortion correlated over the image, colour/depth synchronisation),
    which the post-fit residuals cannot show. The reported covariance of a pair is therefore
    ``correlation_factor * C_points + frame_noise(dt)`` (:meth:`sensor_covariance`):
    ``C_points`` is the estimator's covariance from the per-point model, ``correlation_factor``
    (kappa) inflates it for errors correlated between the points, and ``frame_sigma_rot_deg`` /
    ``frame_sigma_trans_m`` are per-axis standard deviations of an error common to the whole
    pair, per frame interval ``frame_interval_s`` (the camera's nominal frame period). For a pair
    ``k`` intervals apart (after lost frames, or against a keyframe; :meth:`frame_intervals`) the
    rotation variance grows like a random walk, ``k`` times, and the translation variance ``k^2``
    times (the error persists over the intervals); see :mod:`covo_gtsam.calibration`.
    The three defaults are a maximum-likelihood fit for the sensor on the consecutive pairs of the
    first half of the shared fr1_rpy frames (:func:`covo_gtsam.calibration.fit_sensor_terms`),
    checked on data the fit has not seen; see docs/consistency.md. ``correlation_factor = 1`` and
    zero frame sigmas give the per-point model alone (right for the simulation).

    ``motion_model``: ``"constant_velocity"`` predicts ``T_ref,cur`` from the motion between the
    last two tracked frames (scaled by the time elapsed); the prediction is an extra RANSAC
    hypothesis and, without RANSAC, the initial guess. ``"none"``: no prediction.

    ``scale`` (the thesis's phi, hand-set there) multiplies each pair's point-transfer covariance
    inside the estimator, so ``C_points`` above includes it; keep it at 1 and let the calibrated
    ``correlation_factor`` do that job.

    ``robust`` (``"huber"``/``"cauchy"``) and ``variance_factor`` select the estimator's robust
    re-weighting and a-posteriori variance scaling (see :func:`estimate_relative_pose`).

    A relative pose rotating more than ``max_rotation_deg`` or moving more than
    ``max_translation_m`` from its reference frame is not accepted (the frame is lost): such a
    jump is far more likely a wrong match (e.g. a swapped or flipped image) than real motion.

    With ``keyframes`` frames are matched to a keyframe until the point pairs drop
    below ``keyframe_ratio`` times the count of the first frame matched to it (at least twice
    ``frontend.min_pairs``); then the last tracked frame becomes the keyframe. Each emitted
    relative pose and covariance is that of its own pair (keyframe, frame). Without (default,
    more accurate on the shared data), every frame is matched to the previous tracked one.

    ``rolling_shutter_s`` is the colour camera's readout time from the top row to the bottom row
    (seconds; 0 turns the compensation off). With it, each pair is solved once, the camera's
    velocity at both frames is taken from that solution (at the reference frame averaged with
    its own pair's velocity), the points are moved to their image's timestamp
    (:func:`covo_gtsam.rolling_shutter.compensate_points`) and the pair is solved again. 0.025 s
    suits the Kinect v1 (TUM freiburg1/2), chosen on the first half of the shared fr1_rpy frames.

    After ``restart_after`` consecutive lost frames the last tracked frame is usually out of
    view, so the next frame that cannot be matched to it starts a new segment instead of being
    lost (status ``"restart"``, see :class:`OdometryStep`).

    Every field is type- and range-checked, :class:`ConfigError` naming it: flags must be real
    booleans (the string ``"false"`` is not), numbers real numbers (not booleans),
    ``restart_after`` an integer, ``keyframe_ratio`` in (0, 1], and ``frontend`` a
    :class:`FrontendConfig` (a table of its settings in :meth:`from_dict`).
    """

    frontend: FrontendConfig = field(default_factory=FrontendConfig)
    pixel_sigma: float = 2.0
    depth_sigma_scale: float = 2.0
    pixel_sigma_by_level: bool = False
    use_surface_angle: bool = True
    weighting: str = "consistent"
    scale: float = 1.0
    depth_scale: float = 5000.0
    keyframes: bool = False
    keyframe_ratio: float = 0.5
    motion_model: str = "constant_velocity"
    robust: str | None = None
    variance_factor: bool = False
    max_rotation_deg: float = 30.0
    max_translation_m: float = 0.5
    correlation_factor: float = 1.32
    frame_sigma_rot_deg: float = 0.105
    frame_sigma_trans_m: float = 0.00101
    frame_interval_s: float = 1.0 / 30.0
    timing_sigma_s: float = 0.00067
    integrity_threshold: float = 50.0
    frame_clock: bool = True
    depth_time_compensation: bool = False
    depth_scale_sigma: float = 0.0
    depth_time_factor: float = 0.0
    rolling_shutter_factor: float = 1.3
    stamp_jitter_s: float = 0.002
    clock_window: int = 60
    restart_after: int = 5
    rolling_shutter_s: float = 0.025
    depth_lookup_noise: bool = True
    depth_offset_factor: float = 1.0

    def __post_init__(self) -> None:
        if not isinstance(self.frontend, FrontendConfig):
            raise ConfigError(f"frontend must be a FrontendConfig, got {self.frontend!r}")
        if isinstance(self.robust, str) and self.robust in ("", "none"):  # TOML has no null
            object.__setattr__(self, "robust", None)
        choices = {"weighting": WEIGHTINGS, "robust": ROBUST_KERNELS, "motion_model": MOTION_MODELS}
        for name, allowed in choices.items():
            check_choice(name, getattr(self, name), allowed)
        for name in ("pixel_sigma_by_level", "use_surface_angle", "keyframes", "variance_factor", "frame_clock",
                     "depth_time_compensation", "depth_lookup_noise"):
            check_bool(name, getattr(self, name))
        for name, (kind, lo, hi) in _REAL_LIMITS.items():
            check_real(name, getattr(self, name), kind, lo, hi)
        check_int("restart_after", self.restart_after, 1)
        check_int("clock_window", self.clock_window, 20)

    def gap_noise(self) -> np.ndarray:
        """6x6 covariance of the unknown motion across a tracking gap (tangent [omega, v]):
        per axis the largest accepted motion, ``max_rotation_deg`` and ``max_translation_m``."""
        r = np.deg2rad(self.max_rotation_deg) ** 2
        t = self.max_translation_m**2
        return np.diag([r, r, r, t, t, t])

    def frame_noise(self, dt: float | None = None) -> np.ndarray:
        """6x6 frame term (tangent [omega, v]) of a pair whose frames are ``dt`` seconds apart,
        ``k = frame_intervals(dt)`` (1 if None): per axis ``frame_sigma_rot_deg^2 k`` and
        ``frame_sigma_trans_m^2 k^2`` (:func:`covo_gtsam.calibration.frame_covariance`)."""
        return frame_covariance(np.deg2rad(self.frame_sigma_rot_deg), self.frame_sigma_trans_m, self.frame_intervals(dt))

    def sensor_covariance(self, point_covariance: np.ndarray, dt: float | None = None,
                          bases: Mapping[str, np.ndarray] | None = None) -> np.ndarray:
        """Reported 6x6 covariance of a pair whose frames are ``dt`` seconds apart, from the
        estimator's per-point covariance (tangent [omega, v]):
        ``correlation_factor * point_covariance + frame_noise(dt) + sum_j sigma_j^2 B_j`` over the
        pair's frame-level error bases ``bases`` (:data:`covo_gtsam.calibration.ERROR_TERMS`, each
        sigma a field of this configuration)."""
        return sensor_covariance(point_covariance, self.correlation_factor, np.deg2rad(self.frame_sigma_rot_deg),
                                 self.frame_sigma_trans_m, self.frame_intervals(dt), bases, self.term_sigmas())

    def term_sigmas(self) -> dict[str, float]:
        """Sigma of each frame-level error term (:data:`covo_gtsam.calibration.ERROR_TERMS`)."""
        return {name: getattr(self, fieldname) for name, fieldname in ERROR_TERMS.items()}

    def frame_intervals(self, dt: float | None) -> int:
        """Frame intervals between two frames ``dt`` seconds apart: ``round(dt / frame_interval_s)``,
        at least 1 (timestamp jitter of consecutive frames does not change it); 1 if ``dt`` is None."""
        if dt is not None and dt > MAX_GAP_S:
            raise InputError(f"frames {dt:g} s apart: more than {MAX_GAP_S:g} s is not one recording")
        return max(1, int(round(dt / self.frame_interval_s))) if dt is not None and np.isfinite(dt) else 1

    def noise_model(self) -> PointNoiseModel:
        return PointNoiseModel(pixel=PixelNoise(self.pixel_sigma, self.pixel_sigma),
                               depth=KinectAxialNoise(scale=self.depth_sigma_scale))

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "OdometryConfig":
        """Build from a plain mapping, e.g. a parsed TOML/JSON file; a ``frontend`` table sets the front end."""
        if not isinstance(d, Mapping):
            raise ConfigError(f"the configuration must be a table/object of settings, got {d!r}")
        d = dict(d)
        fe = d.pop("frontend", None)
        if isinstance(fe, FrontendConfig):
            fe = dataclasses.asdict(fe)
        elif fe is None:
            fe = {}
        elif not isinstance(fe, Mapping):
            raise ConfigError(f"frontend must be a table/object of front-end settings, got {fe!r}")
        names = {f.name for f in dataclasses.fields(cls)} - {"frontend"}
        fe_names = {f.name for f in dataclasses.fields(FrontendConfig)}
        unknown = sorted(map(str, set(d) - names)) + sorted(f"frontend.{k}" for k in set(fe) - fe_names)
        if unknown:
            raise ConfigError(f"unknown configuration keys: {', '.join(unknown)}")
        try:
            return cls(frontend=FrontendConfig(**fe), **d)
        except TypeError as exc:
            raise ConfigError(f"invalid configuration: {exc}") from exc

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass
class OdometryStep:
    """Outcome of one :meth:`VisualOdometry.register_frame` call.

    ``status`` is ``"first"`` (the first tracked frame, identity pose), ``"tracked"``, ``"lost"``
    or ``"restart"``: the first frame of a new segment after ``restart_after`` lost frames. The
    motion across the gap is unknown, so a restart has no relative pose; its ``pose`` is the last
    tracked pose and ``pose_covariance`` that of the last tracked pose plus
    :meth:`OdometryConfig.gap_noise`. For tracked frames ``relative`` is T_ref,cur (points of this frame into the
    reference frame, the previous tracked one) with ``covariance`` in GTSAM's tangent
    ``[rx ry rz tx ty tz]`` (right perturbation); ``pose`` is T_world,cur with
    ``pose_covariance`` composed to first order along the trajectory as if the pairs were
    independent (over chains of some 30 pairs this understates the translation drift on real
    data; docs/consistency.md, finding 7), and ``velocity`` the
    camera's mean body twist ``[ω, v]`` (rad/s, m/s) over the pair, ``Log(T_ref,cur) / dt``.
    ``quality`` is the pair's integrity statistic (:mod:`covo_gtsam.integrity`; about chi2(6)
    for a typical pair of the run, None when it could not be formed) and ``flagged`` tells that it
    exceeded ``integrity_threshold``: the covariance then also covers the disagreement of the
    pair's two depth-free estimates. A back end can gate on either.
    """

    timestamp: float
    status: str
    reason: str = ""
    ref_timestamp: float | None = None
    relative: gtsam.Pose3 | None = None
    covariance: np.ndarray | None = None
    pose: gtsam.Pose3 | None = None
    pose_covariance: np.ndarray | None = None
    num_matches: int = 0
    num_pairs: int = 0
    velocity: np.ndarray | None = None
    quality: float | None = None
    flagged: bool = False
    integrity_statistic: float | None = None
    clock_offset: float = 0.0
    clock_samples: int = 0
    error_bases: dict | None = field(default=None, repr=False)
    result: RelativePoseResult | None = field(default=None, repr=False)

    @property
    def tracked(self) -> bool:
        return self.status in POSED_STATUSES


def _seconds(value, what: str = "timestamp") -> float:
    """``value`` as float seconds; InputError naming ``what`` for anything but a real number."""
    if isinstance(value, (str, bytes, bool, np.bool_)):
        raise InputError(f"{what} must be a number (seconds), got {value!r}")
    try:
        return float(value)
    except (TypeError, ValueError):
        raise InputError(f"{what} must be a number (seconds), got {value!r}") from None


def check_depth_offset(offset) -> float:
    """``offset`` (depth minus colour time, s) as float; InputError unless finite and at most 1 s."""
    d = _seconds(offset, "depth time offset")
    if not (np.isfinite(d) and abs(d) <= 1.0):
        raise InputError(f"the depth image is {d!r} s from its colour image; at most 1 s is usable")
    return d


class VisualOdometry:
    """Keyframe-based (or frame-to-frame) RGB-D odometry with per-step covariance.

    >>> vo = VisualOdometry(Camera.preset("fr1"))
    >>> step = vo.register_frame(colour, depth_raw, timestamp)   # doctest: +SKIP
    """

    def __init__(self, camera: Camera | str, config: OdometryConfig | None = None) -> None:
        """``camera``: a :class:`Camera` or a preset name (``"fr1"``). Raises :class:`ConfigError`
        for anything else, a ``config`` that is not an :class:`OdometryConfig`, or front-end
        settings that do not fit the camera's image size (:meth:`FrontendConfig.check_image_size`)."""
        self.camera = Camera.resolve(camera)
        if config is not None and not isinstance(config, OdometryConfig):
            raise ConfigError(f"config must be an OdometryConfig (see OdometryConfig.from_dict), got {config!r}")
        self.config = config or OdometryConfig()
        self.config.frontend.check_image_size(self.camera.width, self.camera.height)
        self._orb_local = threading.local()  # one ORB detector per thread (see prepare)
        self._noise = self.config.noise_model()
        self._ref: FrameData | None = None  # the reference (key)frame
        self._ref_step: OdometryStep | None = None
        self._last: tuple[FrameData, OdometryStep] | None = None  # the last tracked frame
        self._keyframe_min_pairs = 0
        self._velocity: tuple[gtsam.Pose3, float] | None = None  # (T_prev,last, dt) of the last two tracked frames
        self._lost_run = 0  # consecutive lost frames since the last tracked one
        self._integrity = IntegrityScale()
        self._clock = FrameClock(self.config.frame_interval_s, self.config.clock_window)
        self._clock_offset: float | None = None  # offset of the frame being registered from the frame clock
        self.steps: list[OdometryStep] = []
        #: keep each step's ``error_bases`` in :attr:`steps` (what :func:`covo_gtsam.pipeline.calibrate_sequence` fits)
        self.keep_error_bases = False

    # -- front end -------------------------------------------------------------------------
    def prepare(self, image: np.ndarray, depth: np.ndarray, depth_offset: float = 0.0) -> FrameData:
        """Features, 3D points and covariances of one frame (thread-safe; no GTSAM calls).

        ``image``: grey (H, W) or BGR (H, W, 3) uint8. ``depth``: metres (float) or raw
        integer values divided by ``config.depth_scale``. ``depth_offset``: the depth image's
        timestamp minus the colour image's (seconds, at most 1 s apart; 0 for a synchronised camera).
        """
        depth_offset = check_depth_offset(depth_offset)
        depth = np.asarray(depth)
        image = np.asarray(image)
        if depth.shape[:2] != image.shape[:2] or depth.ndim != 2:
            raise InputError(f"depth image shape {depth.shape} does not match the colour image {image.shape[:2]}")
        if image.shape[:2] != (self.camera.height, self.camera.width):
            raise InputError(
                f"image size {image.shape[1]}x{image.shape[0]} differs from the camera's "
                f"{self.camera.width}x{self.camera.height}")
        if np.issubdtype(depth.dtype, np.integer):
            depth = depth.astype(np.float32) / self.config.depth_scale
        orb = getattr(self._orb_local, "orb", None)
        if orb is None:
            orb = self._orb_local.orb = make_orb(self.config.frontend)
        frame = prepare_frame(
            to_grey(image), depth, self.camera, orb, self._noise, self.config.frontend,
            use_surface_angle=self.config.use_surface_angle,
            pixel_sigma_by_level=self.config.pixel_sigma_by_level,
            depth_lookup_noise=self.config.depth_lookup_noise,
        )
        frame.depth_offset = depth_offset
        return frame

    # -- the entry point ---------------------------------------------------------------------
    def register_frame(self, image: np.ndarray | FrameData, depth: np.ndarray | None = None, timestamp: float = 0.0,
                       depth_timestamp: float | None = None) -> OdometryStep:
        """Add a frame; return its relative pose to the reference frame, or a lost status.

        The reference is the current keyframe (``config.keyframes``) or the previous tracked
        frame; ``step.ref_timestamp`` names it.

        ``image`` may also be a :class:`FrameData` from :meth:`prepare` (then ``depth`` is
        ignored), which lets a caller compute features on another thread. A frame that cannot be
        tracked is reported lost and the next frame is matched to the last tracked one.

        ``timestamp`` (seconds) must be finite and not earlier than that of the previous frame
        (registered or marked lost); an equal one is accepted (some datasets repeat stamps): such
        a pair has no velocity, so no motion prediction or rolling-shutter compensation.
        ``depth_timestamp`` (seconds, optional) is the depth image's stamp when the camera does
        not synchronise its streams; a :class:`FrameData` carries its own ``depth_offset``.

        Raises:
            InputError: the timestamp is not a finite number or goes back in time (the frame is
                not recorded).
        """
        timestamp = self._new_stamp(timestamp)
        try:
            if isinstance(image, FrameData):
                frame = image
            else:
                offset = 0.0 if depth_timestamp is None else _seconds(depth_timestamp, "depth timestamp") - timestamp
                frame = self.prepare(image, depth, offset)
        except CovoError as exc:
            return self._record(OdometryStep(timestamp, "lost", reason=str(exc)))
        if self._ref is None:
            return self._start(frame, timestamp)
        if timestamp - self._ref_step.timestamp > MAX_GAP_S:
            step = OdometryStep(timestamp, "lost", ref_timestamp=self._ref_step.timestamp, reason=(
                f"{timestamp - self._ref_step.timestamp:.3g} s after its reference frame (more than {MAX_GAP_S:g} s)"))
            return self._restart(frame, step) if self._lost_run >= self.config.restart_after else self._record(step)
        step = self._track(self._ref, self._ref_step, frame, timestamp)
        last = self._last
        if self.config.keyframes and last is not None and last[1] is not self._ref_step and (
            not step.tracked or step.num_pairs < self._keyframe_min_pairs
        ):
            # Too little overlap with the keyframe: the last tracked frame becomes the keyframe.
            self._set_keyframe(*last)
            retry = self._track(self._ref, self._ref_step, frame, timestamp)
            if retry.tracked or not step.tracked:
                step = retry
        if not step.tracked and self._lost_run >= self.config.restart_after:
            return self._restart(frame, step)
        if step.tracked:
            if step.integrity_statistic is not None:
                self._integrity.add(step.integrity_statistic)
            if last is not None and step.timestamp > last[1].timestamp:
                self._velocity = (last[1].pose.between(step.pose), step.timestamp - last[1].timestamp)
            self._last = (frame, step)
            if not self.config.keyframes:
                self._set_keyframe(frame, step)
        return self._record(step)

    def _set_keyframe(self, frame: FrameData, step: OdometryStep) -> None:
        self._ref, self._ref_step = frame, step
        self._keyframe_min_pairs = 0  # set from the first pair matched to this keyframe

    def predict(self, ref_step: OdometryStep, timestamp: float) -> gtsam.Pose3 | None:
        """Constant-velocity prediction of ``T_ref,cur`` for a frame at ``timestamp`` (None without one).

        The motion ``T_prev,last`` between the last two tracked frames, taken over their time
        difference ``dt``, is extrapolated as ``Exp(s Log(T_prev,last))`` with
        ``s = (timestamp - t_last) / dt`` (at most 5) and composed with ``T_ref,last``.
        """
        if self.config.motion_model != "constant_velocity" or self._velocity is None:
            return None  # a velocity exists only once two frames were tracked, so _last is set
        last_step = self._last[1]
        motion, dt = self._velocity
        s = min((timestamp - last_step.timestamp) / dt, 5.0)
        if not s > 0:
            return None
        ahead = gtsam.Pose3.Expmap(s * gtsam.Pose3.Logmap(motion))
        return ref_step.pose.between(last_step.pose).compose(ahead)

    def _track(self, ref: FrameData, ref_step: OdometryStep, frame: FrameData, timestamp: float) -> OdometryStep:
        """Relative pose of ``frame`` to ``ref`` (a lost step if it cannot be estimated)."""
        guess = self.predict(ref_step, timestamp)
        pairs = associate_frames(ref, frame, self.config.frontend, None if guess is None else guess.matrix())
        step = OdometryStep(timestamp, "lost", ref_timestamp=ref_step.timestamp,
                            num_matches=pairs.num_matches, num_pairs=pairs.num_inliers)
        min_pairs = self.config.frontend.min_pairs
        if pairs.num_inliers < min_pairs:
            step.reason = f"only {pairs.num_inliers} point pairs (need {min_pairs})"
            return step
        # time between the two captures: the stamps' difference corrected by the frame clock
        dt, r_ref, r_cur = self._capture_interval(ref_step, timestamp)
        try:
            X_ref, X_cur = pairs.X_ref, pairs.X_cur
            res = self._solve(X_ref, X_cur, pairs, None if pairs.T_init is None else gtsam.Pose3(pairs.T_init))
            if dt > 0 and (self.config.rolling_shutter_s > 0 or self.config.depth_time_compensation):
                twist_ref, twist_cur = frame_twists(res.pose, dt, ref_step.velocity)
                if self.config.depth_offset_factor > 0 and (ref.depth_offset or frame.depth_offset):
                    pairs = self._with_offset_noise(pairs, ref, frame, twist_ref, twist_cur)
                X_ref = self._to_frame_time(ref, pairs.X_ref, pairs.uv_ref, twist_ref)
                X_cur = self._to_frame_time(frame, pairs.X_cur, pairs.uv_cur, twist_cur)
                res = self._solve(X_ref, X_cur, pairs, res.pose)
        except (EstimationError, InputError) as exc:  # InputError: e.g. points moved beyond range by compensation
            step.reason = str(exc)
            return step
        angle = float(np.rad2deg(np.linalg.norm(gtsam.Rot3.Logmap(res.pose.rotation()))))
        dist = float(np.linalg.norm(res.pose.translation()))
        if angle > self.config.max_rotation_deg or dist > self.config.max_translation_m:
            step.reason = (f"implausible motion ({angle:.1f} deg, {dist:.2f} m to the reference frame; limits "
                           f"{self.config.max_rotation_deg:g} deg, {self.config.max_translation_m:g} m)")
            return step
        twists = frame_twists(res.pose, dt, ref_step.velocity) if dt > 0 else None
        step.velocity = None if twists is None else twists[1]
        step.error_bases = self._error_bases(res.pose, X_ref, X_cur, pairs, ref, frame, ref_step, twists)
        try:
            step.covariance = self.config.sensor_covariance(res.covariance, dt, step.error_bases)
        except InputError as exc:  # e.g. a gap of more frame intervals than any camera has
            step.reason = str(exc)
            return step
        step.status = "tracked"
        try:
            check = depth_free_check(res.pose.matrix(), X_ref, X_cur, pairs.Q_ref, pairs.Q_cur,
                                     self.camera.fx, self.camera.fy, self.config.pixel_sigma)
        except np.linalg.LinAlgError:
            check = None  # too few well-spread points for a depth-free estimate: no quality value
        if check is not None and np.isfinite(check.statistic) and np.all(np.isfinite(check.inflation())):
            # the run's scale learns from this pair only if the pair is kept (register_frame)
            step.integrity_statistic = check.statistic
            step.quality = self._integrity.normalise(check.statistic)
            step.flagged = not step.quality <= self.config.integrity_threshold
            if step.flagged:  # honest: the covariance covers the disagreement of the two depth-free estimates
                step.covariance = check.inflate(step.covariance, step.quality)
        step.relative = res.pose
        if twists is not None and (r_ref or r_cur):
            # the pose between the two stamps, as a back end fed with the stamps reads it; the
            # reference frame moves with the twist its own pair moved it with, so consecutive
            # restamps cancel along the trajectory
            shift_ref = r_ref * (step.velocity if ref_step.velocity is None else ref_step.velocity)
            step.relative, Ad = restamp(res.pose, shift_ref, r_cur * step.velocity)
            step.covariance = Ad @ step.covariance @ Ad.T
            step.error_bases = {k: Ad @ B @ Ad.T for k, B in step.error_bases.items()}
        step.result = res
        step.pose = ref_step.pose.compose(step.relative)
        step.pose_covariance = compose_covariance(ref_step.pose, ref_step.pose_covariance, step.relative,
                                                  step.covariance)
        if self._keyframe_min_pairs == 0:
            self._keyframe_min_pairs = max(2 * min_pairs, int(self.config.keyframe_ratio * pairs.num_inliers))
        return step

    def _with_offset_noise(self, pairs: PointPairs, ref: FrameData, frame: FrameData, twist_ref: np.ndarray,
                           twist_cur: np.ndarray) -> PointPairs:
        """``pairs`` with each point's covariance grown by the depth its image changes over the
        frame's colour-depth offset (``depth_offset_factor`` times the stamped one): the depth image
        saw the scene shifted by the point's image velocity times the offset, so the depth read at
        the colour keypoint may belong to a neighbouring surface (:func:`~covo_gtsam.noise.depth_lookup_variance`,
        sigma points at plus and minus that shift; added along the viewing ray)."""
        Q = []
        for fd, X, uv, Q_f, twist in ((ref, pairs.X_ref, pairs.uv_ref, pairs.Q_ref, twist_ref),
                                      (frame, pairs.X_cur, pairs.uv_cur, pairs.Q_cur, twist_cur)):
            if not fd.depth_offset:
                Q.append(Q_f)
                continue
            shift = image_velocities(X, twist, self.camera.fx, self.camera.fy) * (
                self.config.depth_offset_factor * fd.depth_offset)
            ray = X / X[:, 2:3]
            Q.append(Q_f + depth_lookup_variance(fd.depth, uv, shift[None])[:, None, None]
                     * ray[:, :, None] * ray[:, None, :])
        return dataclasses.replace(pairs, Q_ref=Q[0], Q_cur=Q[1])

    def _capture_interval(self, ref_step: OdometryStep, timestamp: float) -> tuple[float, float, float]:
        """``(dt, r_ref, r_cur)``: the time between the two frames' captures (s) and the clock offsets
        (s) used to move the pose to the stamps. The stamps' difference corrected by the frame clock;
        the stamps' difference with no offsets when the clock has not placed both frames or would
        change the interval by more than half (e.g. a repeated stamp). An interval shorter than a
        quarter of ``frame_interval_s`` counts as 0: no velocity is taken from it."""
        stamp_dt = timestamp - ref_step.timestamp
        r_ref, r_cur = ref_step.clock_offset, (self._clock_offset or 0.0)
        dt = stamp_dt - r_cur + r_ref
        if not (ref_step.clock_samples and self._clock_offset is not None and stamp_dt > 0
                and 0.5 * stamp_dt <= dt <= 2.0 * stamp_dt):
            dt, r_ref, r_cur = stamp_dt, 0.0, 0.0
        if dt < 0.25 * self.config.frame_interval_s:
            dt = 0.0
        return dt, r_ref, r_cur

    def _error_bases(self, T: gtsam.Pose3, X_ref: np.ndarray, X_cur: np.ndarray, pairs, ref: FrameData,
                     frame: FrameData, ref_step: OdometryStep, twists: tuple[np.ndarray, np.ndarray] | None) -> dict:
        """The pair's basis of each frame-level error term (:mod:`covo_gtsam.frame_errors`); ``twists``
        are the camera's twists at the two frames (:func:`~covo_gtsam.rolling_shutter.frame_twists`),
        None without motion."""
        M = T.matrix()
        G_ref, G_cur = transfer_gains(M[:3, :3], M[:3, 3], X_ref, X_cur, pairs.Q_ref, pairs.Q_cur)
        b_ref, b_cur = depth_scale_basis(G_ref, X_ref), depth_scale_basis(G_cur, X_cur)
        bases = {"depth_scale": np.outer(b_ref, b_ref) + np.outer(b_cur, b_cur)}
        if twists is None:
            return bases  # no motion: no timing terms
        twist_ref, velocity = twists
        bases["timing"] = timing_covariance(np.stack([twist_ref, velocity]))
        # a frame's stamp keeps its full jitter until the frame clock places it, and then the
        # uncertainty of the clock's phase, fitted to n stamps: 1/n of the jitter's variance
        n_cur = self._clock.samples if self._clock_offset is not None else 0
        weights = np.array([1.0 / max(ref_step.clock_samples, 1), 1.0 / max(n_cur, 1)])
        bases["stamp_jitter"] = timing_covariance(np.stack([twist_ref, velocity]) * np.sqrt(weights)[:, None])
        h_ref = ref.depth_offset * depth_time_basis(G_ref, X_ref, twist_ref)
        h_cur = frame.depth_offset * depth_time_basis(G_cur, X_cur, velocity)
        bases["depth_time"] = np.outer(h_ref, h_ref) + np.outer(h_cur, h_cur)
        if self.config.rolling_shutter_s > 0:
            # the twist at the current frame may differ from the pair's mean by half its change
            # since the previous pair; without a previous pair, by half of itself (both frames)
            rows_cur = row_time_offsets(pairs.uv_cur[:, 1], self.camera.height, self.config.rolling_shutter_s)
            B = rolling_shutter_basis(G_cur, X_cur, rows_cur)
            if ref_step.velocity is not None:
                u = B @ (0.5 * (velocity - np.asarray(ref_step.velocity)))
            else:
                rows_ref = row_time_offsets(pairs.uv_ref[:, 1], self.camera.height, self.config.rolling_shutter_s)
                u = (B + rolling_shutter_basis(G_ref, X_ref, rows_ref)) @ (0.5 * velocity)
            bases["rolling_shutter"] = np.outer(u, u)
        return bases

    def _to_frame_time(self, fd: FrameData, X: np.ndarray, uv: np.ndarray, twist: np.ndarray) -> np.ndarray:
        """A frame's points moved to its colour image's timestamp: the depths along their rays to
        the bearings' time (:func:`covo_gtsam.frame_errors.depth_time_shift`), then each row to the
        timestamp (:func:`covo_gtsam.rolling_shutter.compensate_points`)."""
        if self.config.depth_time_compensation and fd.depth_offset:
            X = depth_time_shift(X, twist, fd.depth_offset)
        if self.config.rolling_shutter_s > 0:
            X = compensate_points(X, uv[:, 1], twist, self.camera.height, self.config.rolling_shutter_s)
        return X

    def _solve(self, X_ref: np.ndarray, X_cur: np.ndarray, pairs, initial: gtsam.Pose3 | None) -> RelativePoseResult:
        return estimate_relative_pose(
            X_ref, X_cur, pairs.Q_ref, pairs.Q_cur, weighting=self.config.weighting, scale=self.config.scale,
            robust=self.config.robust, variance_factor=self.config.variance_factor, initial=initial)

    def _start(self, frame: FrameData, timestamp: float) -> OdometryStep:
        if frame.num_valid < self.config.frontend.min_pairs:
            return self._record(OdometryStep(
                timestamp, "lost", reason=f"only {frame.num_valid} features with valid depth"))
        step = OdometryStep(timestamp, "first", pose=gtsam.Pose3(), pose_covariance=np.zeros((6, 6)))
        self._set_keyframe(frame, step)
        self._last = (frame, step)
        return self._record(step)

    def _restart(self, frame: FrameData, lost: OdometryStep) -> OdometryStep:
        """Start a new segment at ``frame`` (it could not be matched after a run of lost frames)."""
        if frame.num_valid < self.config.frontend.min_pairs:
            return self._record(lost)
        last = self._last[1]
        step = OdometryStep(
            lost.timestamp, "restart",
            reason=f"new segment after {self._lost_run} lost frames ({lost.reason})",
            pose=last.pose, pose_covariance=last.pose_covariance + self.config.gap_noise())
        self._set_keyframe(frame, step)
        self._last = (frame, step)
        self._velocity = None
        return self._record(step)

    def mark_lost(self, timestamp: float, reason: str) -> OdometryStep:
        """Report a frame that could not be used at all (e.g. an unreadable file); ``timestamp``
        is checked as in :meth:`register_frame`."""
        return self._record(OdometryStep(self._new_stamp(timestamp), "lost", reason=reason))

    def _new_stamp(self, timestamp) -> float:
        """A frame's checked stamp (:meth:`_check_timestamp`), with the frame clock advanced to it."""
        t = self._check_timestamp(timestamp)
        self._clock_offset = self._clock.offset(t) if self.config.frame_clock else None
        return t

    def _check_timestamp(self, timestamp) -> float:
        """``timestamp`` as float; InputError unless finite and >= the previous frame's."""
        t = _seconds(timestamp)
        if not np.isfinite(t):
            raise InputError(f"timestamp must be finite, got {t!r}")
        if self.steps and t < self.steps[-1].timestamp:
            raise InputError(
                f"timestamp {t!r} is earlier than the previous frame's {self.steps[-1].timestamp!r}; "
                "frames must be registered in time order")
        return t

    def _record(self, step: OdometryStep) -> OdometryStep:
        step.clock_offset = self._clock_offset or 0.0
        step.clock_samples = self._clock.samples if self._clock_offset is not None else 0
        self._lost_run = 0 if step.tracked else self._lost_run + 1
        # The history keeps poses only, so memory stays small on long runs.
        self.steps.append(dataclasses.replace(step, result=None,
                                              error_bases=step.error_bases if self.keep_error_bases else None))
        return step

    def self_calibration(self) -> dict:
        """What the run learnt about its sensor without ground truth: the frame clock's period (s),
        the scatter of the stamps around it (s.d. of the clock offsets, s) and the integrity
        statistic's scale (median over the run's pairs / median of chi2(6))."""
        offsets = [s.clock_offset for s in self.steps if s.clock_samples]
        return {"frame_period_s": self._clock.period_s,
                "stamp_jitter_s": float(np.std(offsets)) if len(offsets) > 2 else None,
                "integrity_scale": self._integrity.scale}

    # -- results -------------------------------------------------------------------------------
    @property
    def tracked_steps(self) -> list[OdometryStep]:
        return [s for s in self.steps if s.tracked]

    @property
    def lost_steps(self) -> list[OdometryStep]:
        return [s for s in self.steps if not s.tracked]

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """Timestamps (K,) and poses T_world,cur (K, 4, 4) of the tracked frames."""
        tracked = self.tracked_steps
        stamps = np.array([s.timestamp for s in tracked])
        poses = np.array([s.pose.matrix() for s in tracked]).reshape(-1, 4, 4)
        return stamps, poses
