"""Streaming RGB-D visual odometry: one entry point, :meth:`VisualOdometry.register_frame`.

Per frame: colour + depth -> ORB features and 3D points with covariances (:mod:`covo_gtsam.frontend`)
-> point pairs with the reference frame -> ``T_ref,cur`` and its covariance (:mod:`covo_gtsam.estimator`
and the sensor terms) -> ``T_world,cur`` (world = the first posed camera frame), composed to first
order. Settings: :mod:`covo_gtsam.config`; what each frame gets: :mod:`covo_gtsam.steps`.
"""

from __future__ import annotations

import threading
import warnings
from dataclasses import dataclass, replace
from typing import NamedTuple

import gtsam
import numpy as np

from .calibration import TwistChanges, central_change_basis, known_change_basis, span_basis, stamp_error_basis
from .camera import Camera
from .choices import MotionModel
from .clock import FrameClock, check_depth_offset, check_stamp, restamp, seconds
from .config import MAX_GAP_S, OdometryConfig
from .covariance import compose_covariance
from .depth_drift import DepthDrift, drift_along
from .errors import ConfigError, CovoError, CovoWarning, EstimationError, InputError
from .estimator import RelativePoseResult, estimate_relative_pose
from .frame_errors import (depth_change_basis, depth_period_jump, depth_read_change, depth_scale_basis,
                           depth_time_response, depth_time_shift, rolling_shutter_basis, shared_frame_covariance,
                           transfer_gains)
from .datasets.images import to_grey
from .frontend import FrameData, PointPairs, associate_frames, make_orb, prepare_frame
from .geometry import image_velocities
from .gyro import ACCELERATION_SPAN_S, Gyroscope, clock_offset
from .integrity import (MIN_CONSENSUS, IntegrityScale, below_majority, depth_free_check, depth_free_consensus,
                        per_span, reprojection_consensus)
from .noise import blur_covariances, depth_lookup_variance
from .rolling_shutter import compensate_points, frame_twists, row_time_offsets
from .steps import POSED_STATUSES, DeprecatedStepAccess, OdometryStep, StepHistory, StepStatus

__all__ = ["VisualOdometry", "OdometryConfig", "OdometryStep", "StepStatus", "POSED_STATUSES", "MAX_GAP_S",
           "check_depth_offset"]

#: The odometry's ``reweight_tol`` of :func:`~covo_gtsam.estimator.estimate_relative_pose` (rad): the
#: consistent weighting is evaluated again only when the solution turned more than this from the
#: rotation it was evaluated at (the RANSAC's). On the 240 shared fr1_rpy frames a further pass at
#: 2e-3 rad (the estimator's default) moved the poses by at most 0.18 (median 0.005) of their
#: reported standard deviation and those by at most 1.1 %, for about a third of the solving time
#: (Levenberg-Marquardt iterations per pair 3.3 -> 2.1).
REWEIGHT_TOL_RAD = 1e-2
#: What a lost frame's reason says when no pixel of its depth image is in the depth range.
EMPTY_DEPTH = "the depth image has no depth"


@dataclass(frozen=True)
class _PosedFrame:
    """A frame with a pose and its step: the last posed frame, or the reference (key)frame."""

    frame: FrameData
    step: OdometryStep
    min_pairs: int = 0  # keyframe: fewest pairs before the last posed frame replaces it (0: not set yet)


class _TwistSpan(NamedTuple):
    """A frame's twist was taken over the motion ``motion`` (T_start,frame) from the frame stamped
    ``start``, ``intervals`` frame intervals long; ``noise``: the twist's estimation noise (6x6).
    A twist of the frame's own pair also keeps its response to the frame's points (``features``:
    their feature indices, ``gains``: (N, 6, 3), per second) for the next pair's, and ``cross``, its
    cross-covariance with the twist before it (6x6), which shares the reference frame's points."""

    start: float
    motion: gtsam.Pose3
    noise: np.ndarray
    intervals: int
    features: np.ndarray | None = None
    gains: np.ndarray | None = None
    cross: np.ndarray | None = None


class _Compensation(NamedTuple):
    """What a pair's two frames' rows were moved to their times with: the body twists (6,:
    ``[omega, v]``, rad/s and m/s, each frame's own axes) at the reference and the current frame,
    and the two frames' angular accelerations (3,: rad/s^2) where a gyroscope measured both frames'
    angular velocities (None: the twists are the pairs')."""

    twist_ref: np.ndarray
    twist_cur: np.ndarray
    accelerations: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def measured(self) -> bool:
        return self.accelerations is not None


class _FrameTerms(NamedTuple):
    """What a pair's terms that take the camera's twist at its current frame need besides it: the
    pair's motion ``T_ref,cur`` (4x4) and the twist at its reference frame (``timing``,
    ``stamp_jitter``), each frame's weight of the stamps' jitter, the reference frame's colour-depth
    effect ``h_ref`` (6,) and the current frame's response ``A_cur`` (6x6) to that twist
    (``depth_time``, ``depth_time_coherent``)."""

    motion: np.ndarray
    twist_ref: np.ndarray
    jitter_weights: tuple[float, float]
    h_ref: np.ndarray
    A_cur: np.ndarray


class _Provisional(NamedTuple):
    """A pair the next pair settles: its step, its reference frame's step (for the pose covariance),
    its motion between the captures, its frame intervals, the adjoint (6x6) its covariance was moved
    from the captures to the stamps with; for its latency term (``sensor.latency_look_ahead``) the
    twist of the pair before it with that twist's noise, and for its current frame's rolling-shutter
    compensation (``sensor.rolling_shutter_look_ahead``) the estimate's response (6x6) to an error
    of that compensation's twist and what the pair's rows were moved with (None where not settled);
    and what its stamp and colour-depth terms need besides the twist at its current frame."""

    step: OdometryStep
    ref_step: OdometryStep
    motion: gtsam.Pose3
    intervals: int
    restamp: np.ndarray
    twist_before: np.ndarray | None
    noise_before: np.ndarray | None
    shutter: tuple[np.ndarray, _Compensation] | None
    frame_terms: _FrameTerms | None = None


def _trusted_velocity(step: OdometryStep) -> np.ndarray | None:
    """The camera's twist at ``step``'s frame from its own pair (rad/s, m/s), for the next pair: its
    ``velocity``, or for a pair the integrity check flagged (whose twist is likely wrong, by metres
    per second after a bad depth image) the twist its frame was moved to its stamp with, its
    reference's (None without one: its stamp then took its own twist, which is not passed on)."""
    if not step.flagged:
        return step.velocity
    return None if step.stamp_twist is step.velocity else step.stamp_twist


def _between_captures(a: OdometryStep, b: OdometryStep) -> gtsam.Pose3:
    """``T_a,b`` between the two posed frames' captures: their poses (at their stamps) each moved
    back by what its pair moved it (``stamp_shift`` along ``stamp_twist``), as the pairs' own
    estimates between captures are taken."""

    def at_capture(step: OdometryStep) -> gtsam.Pose3:
        if step.stamp_shift is None:
            return step.pose
        return step.pose.compose(gtsam.Pose3.Expmap(-step.stamp_shift * np.asarray(step.stamp_twist, dtype=float)))

    return at_capture(a).between(at_capture(b))


def _repeats(ref: FrameData, frame: FrameData) -> bool:
    """True when ``frame``'s keypoints and descriptors are ``ref``'s exactly: the same colour image."""
    a, b = ref.features, frame.features
    return (len(a) > 0 and a.uv.shape == b.uv.shape and np.array_equal(a.uv, b.uv)
            and np.array_equal(a.descriptors, b.descriptors))


def _positive_definite(C: np.ndarray) -> bool:
    """True for a finite, symmetric positive-definite covariance whose inverse is finite too."""
    if not np.all(np.isfinite(C)):
        return False
    try:
        L = np.linalg.cholesky(0.5 * (C + C.T))
    except np.linalg.LinAlgError:
        return False
    L_inv = np.linalg.inv(L)
    with np.errstate(over="ignore", invalid="ignore"):
        return bool(np.all(np.isfinite(L_inv.T @ L_inv)))  # the information a back end is given


class VisualOdometry(DeprecatedStepAccess):
    """Keyframe-based (or frame-to-frame) RGB-D odometry with per-step covariance.

    >>> vo = VisualOdometry(Camera.preset("fr1"))
    >>> step = vo.register_frame(colour, depth_raw, timestamp)   # doctest: +SKIP
    """

    def __init__(self, camera: Camera | str, config: OdometryConfig | None = None,
                 gyro: Gyroscope | None = None) -> None:
        """``camera``: a :class:`Camera` or a preset name (``"fr1"``). Raises :class:`ConfigError`
        for anything else, a ``config`` that is not an :class:`OdometryConfig`, or front-end
        settings that do not fit the camera's image size (:meth:`FrontendConfig.check_image_size`).
        ``gyro``: the camera's gyroscope (:class:`~covo_gtsam.gyro.Gyroscope`, on the frames'
        clock), whose angular velocities the rolling-shutter compensation takes where its samples
        cover both frames of a pair."""
        self.camera = Camera.resolve(camera)
        if config is not None and not isinstance(config, OdometryConfig):
            raise ConfigError(f"config must be an OdometryConfig (see OdometryConfig.from_dict), got {config!r}")
        if gyro is not None and not isinstance(gyro, Gyroscope):
            raise ConfigError(f"gyro must be a covo_gtsam.gyro.Gyroscope, got {type(gyro).__name__}")
        if gyro is not None and (config or OdometryConfig()).tracking.keyframes:
            warnings.warn(CovoWarning("keyframe mode does not use the gyroscope (not checked with one): its pairs "
                                      "are compensated with the pairs' twists"), stacklevel=2)
        self.gyro = gyro
        self._gyro_pairs = 0  # pairs compensated with the gyroscope's angular velocities
        #: (capture of the reference, of the current frame, the pair's mean angular velocity) of the kept
        #: frame-to-frame pairs, for the gyroscope's clock offset (:func:`~covo_gtsam.gyro.clock_offset`)
        self._turns: list[tuple[float, float, np.ndarray]] = []
        self._turn: tuple | None = None  # the pair being registered's, until it is kept
        self.config = config or OdometryConfig()
        self.config.frontend.check_image_size(self.camera.width, self.camera.height)
        self._orb_local = threading.local()  # one ORB detector per thread (see prepare)
        self._noise = self.config.noise_model()
        self._keyframe: _PosedFrame | None = None  # the reference frame: the keyframe, or the last posed frame
        self._last: _PosedFrame | None = None  # the last posed frame
        self._velocity: tuple[gtsam.Pose3, float] | None = None  # (T_prev,last, dt) of the last two posed frames
        self._lost_run = 0  # consecutive lost frames since the last posed one
        self._last_stamp: float | None = None  # of the last registered frame
        self._integrity = IntegrityScale()
        self._twist_changes = TwistChanges(self.config.sensor.twist_history)
        #: stamp of a frame -> the span its twist was taken over (for the latency term's history)
        self._twist_noise: dict[float, _TwistSpan] = {}
        #: the last pair, while the next may still settle its latency term; the pair being registered
        self._provisional: _Provisional | None = None
        self._candidate: _Provisional | None = None
        #: stamp of the last posed frame and of the keyframe -> what their twists were taken over
        self._posed_twists: dict[float, _TwistSpan] = {}
        self._clock = FrameClock(self.config.sensor.frame_interval_s, self.config.sensor.clock_window)
        self._clock_offset: float | None = None  # offset of the frame being registered from the frame clock
        self._placed_offsets: list[float] = []  # clock offsets of the frames the clock placed
        self._depth_jumps = 0  # posed pairs whose depth images were read whole periods apart
        self._depth_clock = FrameClock(self.config.sensor.frame_interval_s, self.config.sensor.clock_window)
        self._depth_stamped = False  # a depth image stamped apart from its colour image was seen
        # the depth's drift, from the depth-free estimates of consecutive pairs (frame to frame only: against
        # a keyframe the twists are taken from the posed frames' poses, which the correction would move)
        self._drift = DepthDrift(0 if self.config.tracking.keyframes else self.config.sensor.depth_drift_pairs)
        self._drift_moves = np.zeros(2)  # sum of the squared corrections per frame interval (m^2), and how many
        self._history = StepHistory()  # behind the deprecated steps, tracked_steps, lost_steps, trajectory()

    # -- front end -------------------------------------------------------------------------
    def prepare(self, image: np.ndarray, depth: np.ndarray, depth_offset: float = 0.0) -> FrameData:
        """Features, 3D points and covariances of one frame (thread-safe; no GTSAM calls).

        ``image``: grey (H, W) or BGR (H, W, 3) uint8. ``depth``: metres (float) or raw
        integer values divided by ``config.sensor.depth_scale``. ``depth_offset``: the depth image's
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
            depth = depth.astype(np.float32) / self.config.sensor.depth_scale
        orb = getattr(self._orb_local, "orb", None)
        if orb is None:
            orb = self._orb_local.orb = make_orb(self.config.frontend)
        frame = prepare_frame(
            to_grey(image), depth, self.camera, orb, self._noise, self.config.frontend,
            use_surface_angle=self.config.noise.use_surface_angle,
            pixel_sigma_by_level=self.config.noise.pixel_sigma_by_level,
            depth_lookup_noise=self.config.noise.depth_lookup_noise,
        )
        frame.depth_offset = depth_offset
        return frame

    # -- the entry point ---------------------------------------------------------------------
    def register_frame(self, image: np.ndarray | FrameData, depth: np.ndarray | None = None, timestamp: float = 0.0,
                       depth_timestamp: float | None = None) -> OdometryStep:
        """Add a frame; return its step (:class:`~covo_gtsam.steps.OdometryStep`): the relative pose to
        the reference frame (the keyframe with ``tracking.keyframes``, else the previous posed frame;
        ``step.ref_timestamp``), or why it has none. After a lost frame the next is matched to the
        last posed frame; after ``tracking.restart_after`` lost frames in a row an unmatched frame
        starts a new segment. With ``sensor.latency_look_ahead`` and ``sensor.rolling_shutter_look_ahead``
        (the defaults) a pair is final one frame later: registering the next frame may replace the
        returned step's ``relative``, ``pose``, ``covariance``, ``pose_covariance`` and ``error_bases``
        by revised ones (``step.settled`` tells; the covariance as returned covers the pose as
        returned; :func:`~covo_gtsam.pipeline.run_sequence` writes each step once settled).

        ``image``: as in :meth:`prepare`, or its :class:`FrameData` (e.g. made on another thread;
        ``depth`` is then ignored). ``timestamp`` (s): finite and not earlier than the previous
        frame's (an equal one is accepted; such a pair has no velocity, so no motion prediction or
        rolling-shutter compensation). ``depth_timestamp`` (s, optional): the depth image's stamp
        when the camera does not synchronise its streams.

        Raises:
            InputError: the timestamp is not a finite number or goes back in time (not recorded).
        """
        t = self._place_stamp(timestamp)  # checked, and placed on the frame clock
        frame, step = self._frame_data(image, depth, t, depth_timestamp)  # step: lost if unusable
        if frame is not None:  # the depth stream's own clock, from the depth images' stamps
            self._depth_clock.offset(t + frame.depth_offset)
            self._depth_stamped |= frame.depth_offset != 0.0
        keyframe = self._keyframe
        if step is None and keyframe is None:
            step = self._first_step(frame, t)
        elif step is None:
            step, keyframe = self._match_to_reference(frame, t)  # solve, covariance, integrity, pose
            if not step.has_pose and self._lost_run >= self.config.tracking.restart_after:
                step = self._new_segment_step(frame, step)
        self._advance(frame, step, keyframe)
        return step

    def mark_lost(self, timestamp: float, reason: str) -> OdometryStep:
        """Report a frame that could not be used at all (e.g. an unreadable file); ``timestamp``
        is checked as in :meth:`register_frame`."""
        step = OdometryStep(self._place_stamp(timestamp), StepStatus.LOST, reason=reason)
        self._advance(None, step, self._keyframe)
        return step

    # -- the stages of register_frame, in order ---------------------------------------------------
    def _place_stamp(self, timestamp) -> float:
        """A frame's checked stamp (:func:`~covo_gtsam.clock.check_stamp`), with the frame clock advanced to it."""
        t = check_stamp(timestamp, self._last_stamp)
        self._clock_offset = self._clock.offset(t) if self.config.sensor.frame_clock else None
        return t

    def _frame_data(self, image, depth, t: float, depth_timestamp) -> tuple[FrameData | None, OdometryStep | None]:
        """``(frame, None)``: the frame's :class:`FrameData` (given, or made by :meth:`prepare`); or
        ``(None, lost step)`` when the images are unusable."""
        if isinstance(image, FrameData):
            return image, None
        try:
            offset = 0.0 if depth_timestamp is None else seconds(depth_timestamp, "depth timestamp") - t
            return self.prepare(image, depth, offset), None
        except CovoError as exc:
            return None, OdometryStep(t, StepStatus.LOST, reason=str(exc))

    def _first_step(self, frame: FrameData, t: float) -> OdometryStep:
        """The first posed frame, the world frame; lost without enough features with depth."""
        if frame.num_valid < self.config.frontend.min_pairs:
            return OdometryStep(t, StepStatus.LOST, reason=f"only {frame.num_valid} features with valid depth "
                                f"(of {frame.num_features} detected; need {self.config.frontend.min_pairs})"
                                f"{self._no_depth_note(frame)}")
        return OdometryStep(t, StepStatus.ORIGIN, pose=gtsam.Pose3(), pose_covariance=np.zeros((6, 6)))

    def _match_to_reference(self, frame: FrameData, t: float) -> tuple[OdometryStep, _PosedFrame]:
        """The frame matched to the keyframe; with ``tracking.keyframes``, when that is lost or has
        too few point pairs, the last posed frame becomes the keyframe and the frame is matched to
        it as well. Returns the step and the keyframe after it."""
        keyframe, last = self._keyframe, self._last
        if t - keyframe.step.timestamp > MAX_GAP_S:
            return OdometryStep(t, StepStatus.LOST, ref_timestamp=keyframe.step.timestamp, reason=(
                f"{t - keyframe.step.timestamp:.3g} s after its reference frame (more than {MAX_GAP_S:g} s)")), keyframe
        step = self._track(keyframe.frame, keyframe.step, frame, t)
        keyframe = self._count_pairs(keyframe, step)
        if self.config.tracking.keyframes and last.step is not keyframe.step and (
            not step.has_pose or step.num_pairs < keyframe.min_pairs
        ):
            # Too little overlap with the keyframe: the last posed frame becomes the keyframe.
            keyframe = _PosedFrame(last.frame, last.step)
            retry = self._track(keyframe.frame, keyframe.step, frame, t)
            keyframe = self._count_pairs(keyframe, retry)
            if retry.has_pose or not step.has_pose:
                step = retry
        return step, keyframe

    def _count_pairs(self, keyframe: _PosedFrame, step: OdometryStep) -> _PosedFrame:
        """``keyframe`` with its ``min_pairs`` set from ``step`` if it is the first posed frame matched to it."""
        if keyframe.min_pairs or not step.has_pose:
            return keyframe
        return replace(keyframe, min_pairs=max(2 * self.config.frontend.min_pairs,
                                               int(self.config.tracking.keyframe_ratio * step.num_pairs)))

    def _no_depth_note(self, frame: FrameData) -> str:
        """``"; the depth image has no depth within [min, max] m ..."`` when no pixel of ``frame``'s
        depth image is in the front end's depth range (the reason a frame without valid features is
        lost is then its depth image, not its colour image); else ``""``."""
        fe = self.config.frontend
        if frame.num_valid or np.any((frame.depth >= fe.min_depth) & (frame.depth <= fe.max_depth)):
            return ""
        return f"; {EMPTY_DEPTH} within [{fe.min_depth:g}, {fe.max_depth:g}] m (all zero or out of range)"

    def _new_segment_step(self, frame: FrameData, lost: OdometryStep) -> OdometryStep:
        """A new segment at ``frame`` (it could not be matched after a run of lost frames); ``lost``
        itself without enough features with depth."""
        if frame.num_valid < self.config.frontend.min_pairs:
            return lost
        last = self._last.step
        return OdometryStep(lost.timestamp, StepStatus.NEW_SEGMENT,
                            reason=f"new segment after {self._lost_run} lost frames ({lost.reason})",
                            pose=last.pose, pose_covariance=last.pose_covariance + self.config.gap_noise())

    def _advance(self, frame: FrameData | None, step: OdometryStep, keyframe: _PosedFrame | None) -> None:
        """Every change of the odometry's state by a registered frame (after the frame clock's)."""
        step.clock_offset = self._clock_offset or 0.0
        step.clock_samples = self._clock.samples if self._clock_offset is not None else 0
        if self._provisional is not None:  # the next frame came: its pair (if any) settled the last one's
            self._provisional.step.settled = True
        candidate, self._candidate = self._candidate, None
        self._provisional = candidate if candidate is not None and candidate.step is step else None
        if self._provisional is not None:
            step.settled = False
        if step.clock_samples:
            self._placed_offsets.append(step.clock_offset)
        self._keyframe = keyframe
        if step.status is StepStatus.RELATIVE_POSE:
            if step.integrity_statistic is not None:
                self._integrity.add(self._per_span(step))
            # counted for the pair kept (in keyframe mode it may have been tried against the old keyframe first)
            self._depth_jumps += step.depth_jump_s != 0.0
            self._gyro_pairs += "gyro" in (step.error_bases or {})
            turn, self._turn = self._turn, None
            if turn is not None and turn[0] == step.timestamp and not step.flagged and not self.config.tracking.keyframes:
                self._turns.append(turn[1:])
            last = self._last.step
            if step.timestamp > last.timestamp:
                self._velocity = (last.pose.between(step.pose), step.timestamp - last.timestamp)
            self._add_twist_change(last, step)
        elif step.status is StepStatus.NEW_SEGMENT:
            self._velocity = None
            self._twist_changes.clear()
            self._twist_noise = {}
            self._posed_twists = {}
            self._drift.clear()
        if step.has_pose:
            self._last = _PosedFrame(frame, step)
            if step.status is not StepStatus.RELATIVE_POSE or not self.config.tracking.keyframes:
                self._keyframe = self._last
            span = self._twist_noise.get(step.timestamp)
            kept = {t: v for t, v in self._posed_twists.items() if t == self._keyframe.step.timestamp}
            self._posed_twists = kept if span is None else {**kept, step.timestamp: span}
        self._lost_run = 0 if step.has_pose else self._lost_run + 1
        self._last_stamp = step.timestamp
        self._history.add(step)

    # -- one frame pair -------------------------------------------------------------------------
    def predict(self, ref_step: OdometryStep, timestamp: float) -> gtsam.Pose3 | None:
        """Constant-velocity prediction of ``T_ref,cur`` for a frame at ``timestamp`` (None without one).

        The motion ``T_prev,last`` between the last two tracked frames, taken over their time
        difference ``dt``, is extrapolated as ``Exp(s Log(T_prev,last))`` with
        ``s = (timestamp - t_last) / dt`` (at most 5) and composed with ``T_ref,last``.
        """
        if self.config.tracking.motion_model is not MotionModel.CONSTANT_VELOCITY or self._velocity is None:
            return None  # a velocity exists only once two frames were tracked, so _last is set
        last_step = self._last.step
        motion, dt = self._velocity
        s = min((timestamp - last_step.timestamp) / dt, 5.0)
        if not s > 0:
            return None
        ahead = gtsam.Pose3.Expmap(s * gtsam.Pose3.Logmap(motion))
        return ref_step.pose.between(last_step.pose).compose(ahead)

    def _track(self, ref: FrameData, ref_step: OdometryStep, frame: FrameData, timestamp: float) -> OdometryStep:
        """The pair (``ref``, ``frame``): matched point pairs, relative pose, covariance, integrity
        check, pose (a lost step with the reason when a stage fails)."""
        if _repeats(ref, frame):  # a real camera's noise never gives the same image twice
            return OdometryStep(timestamp, StepStatus.LOST, ref_timestamp=ref_step.timestamp, reason=(
                "its colour image repeats its reference frame's exactly (the same keypoints and descriptors): a "
                "frozen or duplicated frame, whose capture time is not its stamp"))
        guess = self.predict(ref_step, timestamp)
        pairs = associate_frames(ref, frame, self.config.frontend, None if guess is None else guess.matrix(),
                                 self.camera)
        step = OdometryStep(timestamp, StepStatus.LOST, ref_timestamp=ref_step.timestamp,
                            num_matches=pairs.num_matches, num_pairs=pairs.num_inliers,
                            depth_jump_s=self._depth_jump(ref, frame))
        min_pairs = self.config.frontend.min_pairs
        if pairs.num_inliers < min_pairs:
            step.reason = (f"only {pairs.num_inliers} point pairs (need {min_pairs}; {frame.num_features} features "
                           f"detected, {frame.num_valid} with valid depth, {pairs.num_matches} matched)"
                           f"{self._no_depth_note(frame)}")
            return step
        if below_majority(pairs.num_inliers, pairs.num_matches):
            agreed = self._bearings_consensus(ref, frame, pairs)
            if below_majority(pairs.num_inliers, agreed):
                step.reason = (f"no consensus: {pairs.num_inliers} of its {pairs.num_matches} matches agree on one "
                               f"motion in 3-D, {agreed} with one frame's depth left out (fewer than "
                               f"{MIN_CONSENSUS:.0%} of those: a depth image that does not belong to its colour "
                               "image)")
                return step
        # time between the two captures: the stamps' difference corrected by the frame clock
        dt, r_ref, r_cur = self._capture_interval(ref_step, timestamp)
        try:
            captures = (ref_step.timestamp - r_ref, timestamp - (r_cur or 0.0))
            res, X_ref, X_cur, pairs, compensation = self._solve_pair(ref, ref_step, frame, pairs, dt, timestamp,
                                                                      step.depth_jump_s, captures)
        except (EstimationError, InputError) as exc:  # InputError: e.g. points moved beyond range by compensation
            step.reason = str(exc)
            return step
        step.reason = self._implausible(res.pose)
        if step.reason:
            return step
        twists = self._frame_twists(res.pose, dt, ref_step, timestamp) if dt > 0 else None
        step.velocity = None if twists is None else twists[1]
        self._turn = None if twists is None or self.gyro is None else (timestamp, *captures, np.array(twists[1][:3]))
        M = res.pose.matrix()  # the estimate's response to each point of either frame
        gains = transfer_gains(M[:3, :3], M[:3, 3], X_ref, X_cur, pairs.Q_ref, pairs.Q_cur)
        if twists is not None:  # the span and noise of the frame's twist, for the latency term's history
            self._twist_noise[timestamp] = self._twist_span(res, ref_step, dt, timestamp, ref, pairs, gains)
        step.error_bases, b, shutter, frame_terms = self._error_bases(
            res.pose, X_ref, X_cur, pairs, ref, frame, ref_step, twists, dt, timestamp, r_cur, gains,
            step.depth_jump_s, compensation)
        step.added_covariance = {}
        try:
            step.covariance = self.config.sensor_covariance(res.covariance, dt, step.error_bases)
        except InputError as exc:  # e.g. a gap of more frame intervals than any camera has
            step.reason = str(exc)
            return step
        if not _positive_definite(step.covariance):  # no information a back end could use
            step.reason = "the pair's covariance is not finite and positive definite"
            return step
        step.status = StepStatus.RELATIVE_POSE
        check = self._integrity_check(step, res.pose, X_ref, X_cur, pairs)
        # the pose reported moves by the depth's drift; the twists stay the 3D-3D estimate's, as the
        # next pair's rolling-shutter compensation takes them (a moved twist would change by the
        # correction over one interval there, a spurious change of the camera's motion)
        res = self._corrected_for_drift(step, res, check, b, dt)
        self._settle(ref_step, step, compensation)
        if self._shutter_unmoved(step):
            # returned as estimated: its current frame's compensation may still miss half the twist's
            # change over the pair, the error the look-ahead takes out (the term's model at its own size)
            step.added_covariance = {**step.added_covariance, "rolling_shutter": step.error_bases["rolling_shutter"]}
            step.covariance = step.covariance + step.error_bases["rolling_shutter"]
        Ad = self._pose_between_stamps(step, res, ref_step, twists, r_ref, r_cur)
        self._candidate = self._provisional_pair(step, ref_step, Ad, shutter, compensation, frame_terms)
        return step

    def _bearings_consensus(self, ref: FrameData, frame: FrameData, pairs: PointPairs) -> int:
        """How many of all of the pair's matches agree on one motion with one frame's depth left out:
        :func:`~covo_gtsam.integrity.depth_free_consensus`, or the matches whose bearings the rigid
        RANSAC's motion (``pairs.T_init``; another outlier rejection's prediction, if any) explains that
        way (:func:`~covo_gtsam.integrity.reprojection_consensus`) where that is more (the
        perspective-n-point RANSACs found fewer or nothing)."""
        i, j = pairs.match_ref, pairs.match_cur
        points = (ref.points[i], frame.points[j], ref.covariances[i], frame.covariances[j], self.camera.fx,
                  self.camera.fy, self.config.noise.pixel_sigma)
        explained = 0 if pairs.T_init is None else reprojection_consensus(pairs.T_init, *points)
        return max(explained, depth_free_consensus(*points))

    def _corrected_for_drift(self, step: OdometryStep, res: RelativePoseResult, check, b: np.ndarray, dt: float
                             ) -> RelativePoseResult:
        """``res`` with its translation moved by the depth's drift (:mod:`covo_gtsam.depth_drift`)
        and ``step``'s covariance grown by that estimate's own: a kept pair's depth-free estimates
        (``check``) join the drift's window first, a flagged pair's do not, each weighted by the
        pair's covariance as it then stands (with the terms the next frame may still settle).
        Off in keyframe mode."""
        if not (self._drift.enabled and dt > 0):  # a pair without an interval gets none of the drift
            return res
        k = self.config.sensor.frame_intervals(dt)
        if check is not None and not step.flagged:
            delta = 0.5 * (check.delta_forward + check.delta_backward)
            self._drift.add(drift_along(delta, b, step.covariance), k)
        xi, C = self._drift.correction(k)
        if np.any(xi):  # the drift per interval, for the run's report
            self._drift_moves += (float(np.linalg.norm(xi)) / k) ** 2, 1
        step.covariance = step.covariance + C
        step.added_covariance = {**step.added_covariance, "depth_drift": C}
        return replace(res, pose=res.pose.compose(gtsam.Pose3.Expmap(xi)))

    def _since_last(self, T: gtsam.Pose3, ref_step: OdometryStep, timestamp: float
                    ) -> tuple[OdometryStep, gtsam.Pose3, float] | None:
        """Against an older keyframe: the last posed frame's step, the motion ``T_last,cur`` since it
        (``T`` is ``T_ref,cur``) and the capture interval (s); None against the last posed frame, or
        without an interval since it, or when the integrity check flagged the last frame's pair (its
        pose is likely off, so the motion since it would be too)."""
        last = self._last.step if self._last is not None else None
        if last is None or last is ref_step or last.timestamp <= ref_step.timestamp or last.flagged:
            return None
        dt_last = self._capture_interval(last, timestamp)[0]
        if not dt_last > 0:
            return None
        return last, _between_captures(ref_step, last).inverse().compose(T), dt_last

    def _twist_span(self, res: RelativePoseResult, ref_step: OdometryStep, dt: float, timestamp: float,
                    ref: FrameData, pairs: PointPairs, gains: tuple[np.ndarray, np.ndarray]) -> _TwistSpan:
        """What the frame's twist (:meth:`_frame_twists`) was taken over: the pair itself (noise
        C_points / dt^2; with the reference frame's own twist, from the pair before, it shares that
        frame's points: ``cross``), or against an older keyframe the motion since the last posed
        frame, whose noise is that of the two pairs to the keyframe it is taken from (as
        independent; C_points / dt^2 each)."""
        since = self._since_last(res.pose, ref_step, timestamp)
        if since is None:
            G_ref, G_cur = gains
            before = self._twist_noise.get(ref_step.timestamp)
            cross = None
            if before is not None and before.gains is not None:
                cross = shared_frame_covariance(before.features, before.gains, pairs.idx_ref, G_ref / dt,
                                                ref.covariances)
            return _TwistSpan(ref_step.timestamp, res.pose, res.covariance / dt**2,
                              self.config.sensor.frame_intervals(dt), pairs.idx_cur, G_cur / dt, cross)
        last, T, dt_last = since
        same_keyframe = last.ref_timestamp == ref_step.timestamp and last.result is not None
        C_last = last.result.covariance if same_keyframe else res.covariance
        Ad = T.inverse().AdjointMap()
        return _TwistSpan(last.timestamp, T, (res.covariance + Ad @ C_last @ Ad.T) / dt_last**2,
                          self.config.sensor.frame_intervals(dt_last))

    def _frame_twists(self, T: gtsam.Pose3, dt: float, ref_step: OdometryStep, timestamp: float
                      ) -> tuple[np.ndarray, np.ndarray]:
        """The camera's twists at the pair's two frames. Against the last posed frame, as
        :func:`~covo_gtsam.rolling_shutter.frame_twists`; against an older keyframe, the current
        frame's from its motion since the last posed frame and the keyframe's own (its pair's), not
        the mean over the whole pair."""
        since = self._since_last(T, ref_step, timestamp)
        own = _trusted_velocity(ref_step)
        if since is None:
            return frame_twists(T, dt, own)
        _, T_last_cur, dt_last = since
        twist_cur = gtsam.Pose3.Logmap(T_last_cur) / dt_last
        twist_ref = twist_cur if own is None else np.asarray(own, dtype=float)
        return twist_ref, twist_cur

    def _solve_pair(self, ref: FrameData, ref_step: OdometryStep, frame: FrameData, pairs: PointPairs, dt: float,
                    timestamp: float, jump: float, captures: tuple[float, float]
                    ) -> tuple[RelativePoseResult, np.ndarray, np.ndarray, PointPairs, _Compensation | None]:
        """``(result, X_ref, X_cur, pairs, compensation)``: the pair's relative pose. With motion (``dt > 0``) the
        points are moved to their frames' timestamps (rolling shutter, depth time) and get the
        depth-lookup variance of the colour-depth offsets, both from the camera's twists at the two
        frames; the twists come from the outlier rejection's pose (``pairs.T_init``) and the pair is
        solved once. Without such a pose (e.g. ``outlier_rejection = "none"`` and no prediction)
        the pair is solved on the unmoved points, the twists are taken from that solution and it is
        solved again. The points and pairs returned are those of the last solve; ``compensation``
        what the reference's and the current frame's points were moved with (None when not moved;
        :meth:`_gyro_compensation`). ``jump`` is the pair's depth-period jump (s, :meth:`_depth_jump`);
        ``captures`` the two frames' capture times on the stamps' clock (s)."""
        X_ref, X_cur = pairs.X_ref, pairs.X_cur
        initial = None if pairs.T_init is None else gtsam.Pose3(pairs.T_init)
        compensate = dt > 0 and (
            self.config.sensor.rolling_shutter_s > 0 or self.config.sensor.depth_time_compensation
            or (self.config.noise.depth_offset_factor > 0 and (ref.depth_offset or frame.depth_offset))
            or self.config.noise.exposure_s > 0)
        if compensate and initial is None:
            initial = self._solve(X_ref, X_cur, pairs, None).pose
        compensation = None
        if compensate:
            compensation = self._gyro_compensation(*self._frame_twists(initial, dt, ref_step, timestamp), captures)
            twist_ref, twist_cur, accelerations = compensation
            accel_ref, accel_cur = accelerations or (None, None)
            pairs = self._with_motion_noise(pairs, ref, frame, twist_ref, twist_cur, jump)
            X_ref = self._to_frame_time(ref, pairs.X_ref, pairs.uv_ref, twist_ref, accel_ref)
            X_cur = self._to_frame_time(frame, pairs.X_cur, pairs.uv_cur, twist_cur, accel_cur)
        return self._solve(X_ref, X_cur, pairs, initial), X_ref, X_cur, pairs, compensation

    def _gyro_compensation(self, twist_ref: np.ndarray, twist_cur: np.ndarray, captures: tuple[float, float]
                           ) -> _Compensation:
        """The twists (6,: rad/s, m/s, camera frame) a pair's rows are moved with: the pairs'
        (:meth:`_frame_twists`), their angular velocities replaced by the gyroscope's at the two
        ``captures`` (s, on the stamps' clock), with its angular accelerations, where its samples cover
        both frames' readouts, frame to frame (keyframe pairs, not checked with one, keep the pairs')."""
        gyro, readout = self.gyro, self.config.sensor.rolling_shutter_s
        margin = 0.5 * readout + 0.5 * ACCELERATION_SPAN_S
        if (gyro is None or readout <= 0 or self.config.tracking.keyframes
                or not all(gyro.covers(t, margin) for t in captures)):
            return _Compensation(twist_ref, twist_cur)
        twists = [np.concatenate([gyro.angular_velocity(t), np.asarray(tw, dtype=float)[3:]])
                  for tw, t in zip((twist_ref, twist_cur), captures)]
        return _Compensation(*twists, tuple(gyro.angular_acceleration(t) for t in captures))

    def _shutter_response(self, G: np.ndarray, X: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """A frame's points' response (6x6) of the estimate to an error of the twist its rows were
        moved with (:func:`~covo_gtsam.frame_errors.rolling_shutter_basis`)."""
        readout, height = self.config.sensor.rolling_shutter_s, self.camera.height
        return rolling_shutter_basis(G, X, row_time_offsets(uv[:, 1], height, readout))

    def _with_motion_noise(self, pairs: PointPairs, ref: FrameData, frame: FrameData, twist_ref: np.ndarray,
                           twist_cur: np.ndarray, jump: float) -> PointPairs:
        """``pairs`` with each point's covariance grown by what the camera's motion does to it: the
        depth image's change over the frame's colour-depth offset (``noise.depth_offset_factor`` times
        the stamped one, or half the pair's depth-period jump where that is more; the depth image saw
        the scene shifted by the point's image velocity times the offset, so the depth read at the
        colour keypoint may belong to a neighbouring surface:
        :func:`~covo_gtsam.noise.depth_lookup_variance`, along the viewing ray) and motion blur over
        ``noise.exposure_s`` (:func:`~covo_gtsam.noise.blur_covariances`)."""
        c, exposure = self.config.noise.depth_offset_factor, self.config.noise.exposure_s
        half_jump = 0.5 * abs(jump)  # each frame's depth image that far off the pair's
        Q = []
        for fd, X, uv, Q_f, twist in ((ref, pairs.X_ref, pairs.uv_ref, pairs.Q_ref, twist_ref),
                                      (frame, pairs.X_cur, pairs.uv_cur, pairs.Q_cur, twist_cur)):
            offset = max(abs(fd.depth_offset), half_jump)
            if not (exposure > 0 or (c > 0 and offset)):
                Q.append(Q_f)
                continue
            velocity = image_velocities(X, twist, self.camera.fx, self.camera.fy)
            if c > 0 and offset:
                ray = X / X[:, 2:3]
                lookup = depth_lookup_variance(fd.depth, uv, (velocity * (c * offset))[None])
                Q_f = Q_f + lookup[:, None, None] * ray[:, :, None] * ray[:, None, :]
            if exposure > 0:
                Q_f = Q_f + blur_covariances(X, velocity, exposure, self.camera.fx, self.camera.fy)
            Q.append(Q_f)
        return replace(pairs, Q_ref=Q[0], Q_cur=Q[1])

    def _implausible(self, T: gtsam.Pose3) -> str:
        """Why ``T_ref,cur`` is not accepted (it moves more than the tracking limits), or ``""``."""
        angle = float(np.rad2deg(np.linalg.norm(gtsam.Rot3.Logmap(T.rotation()))))
        dist = float(np.linalg.norm(T.translation()))
        limits = self.config.tracking
        if angle > limits.max_rotation_deg or dist > limits.max_translation_m:
            return (f"implausible motion ({angle:.1f} deg, {dist:.2f} m to the reference frame; limits "
                    f"{limits.max_rotation_deg:g} deg, {limits.max_translation_m:g} m)")
        return ""

    def _integrity_check(self, step: OdometryStep, T: gtsam.Pose3, X_ref: np.ndarray, X_cur: np.ndarray, pairs):
        """The pair's integrity statistic (:func:`~covo_gtsam.integrity.depth_free_check`) into
        ``step``: quality, flag, and a flagged pair's covariance inflated. Returns the check (None
        without a finite one)."""
        try:
            check = depth_free_check(T.matrix(), X_ref, X_cur, pairs.Q_ref, pairs.Q_cur,
                                     self.camera.fx, self.camera.fy, self.config.noise.pixel_sigma)
        except np.linalg.LinAlgError:
            check = None  # too few well-spread points for a depth-free estimate: no quality value
        if check is not None and np.isfinite(check.statistic) and np.all(np.isfinite(check.inflation())):
            # the run's scale learns from this pair only if the pair is kept (register_frame)
            step.integrity_statistic = check.statistic
            step.quality = self._integrity.normalise(self._per_span(step))
            step.flagged = not step.quality <= self.config.sensor.integrity_threshold
            if step.flagged:  # honest: the covariance covers the disagreement of the two depth-free estimates
                step.covariance = check.inflate(step.covariance, step.quality)
            return check
        return None

    def _per_span(self, step: OdometryStep) -> float:
        """``step``'s raw integrity statistic on the scale of one frame interval
        (:func:`~covo_gtsam.integrity.per_span`): what the run's scale learns from and judges."""
        return per_span(step.integrity_statistic, self.config.sensor.frame_intervals(step.timestamp - step.ref_timestamp))

    def _pose_between_stamps(self, step: OdometryStep, res: RelativePoseResult, ref_step: OdometryStep,
                             twists: tuple[np.ndarray, np.ndarray] | None, r_ref: float, r_cur: float | None
                             ) -> np.ndarray:
        """``step``'s relative pose moved from the captures to the stamps (by ``r_ref``, ``r_cur``:
        :meth:`_capture_interval`), and its pose composed onto the reference's. Returns the adjoint
        (6x6) the covariance was moved with (the identity where the pose was not moved)."""
        step.relative = res.pose
        Ad = np.eye(6)
        if twists is not None:
            # a flagged pair's twist is likely wrong (by metres per second): its frame moves to its
            # stamp with its reference's twist instead
            trusted = _trusted_velocity(ref_step)
            step.stamp_twist = trusted if step.flagged and trusted is not None else step.velocity
            step.stamp_shift = r_cur
        r_cur = r_cur or 0.0
        if twists is not None and (r_ref or r_cur):
            # the pose between the two stamps, as a back end fed with the stamps reads it; the
            # reference frame moves with the twist it was moved with as its own pair's end, so
            # consecutive restamps cancel along the trajectory
            shift_ref = r_ref * (step.velocity if ref_step.stamp_twist is None else ref_step.stamp_twist)
            step.relative, Ad = restamp(res.pose, shift_ref, r_cur * step.stamp_twist)
            step.covariance = Ad @ step.covariance @ Ad.T
            step.error_bases = {k: Ad @ B @ Ad.T for k, B in step.error_bases.items()}
            step.added_covariance = {k: Ad @ C @ Ad.T for k, C in step.added_covariance.items()}
        step.result = res
        step.pose = ref_step.pose.compose(step.relative)
        step.pose_covariance = compose_covariance(ref_step.pose, ref_step.pose_covariance, step.relative,
                                                  step.covariance)
        return Ad

    def _provisional_pair(self, step: OdometryStep, ref_step: OdometryStep, Ad: np.ndarray,
                          shutter: np.ndarray | None, compensation: _Compensation | None,
                          frame_terms: _FrameTerms | None = None) -> _Provisional | None:
        """``step`` as a pair the next pair may settle (:meth:`_settle`): frame to frame, not flagged,
        with its own twist; its latency term with ``sensor.latency_look_ahead`` where the pair before
        has a trusted twist over as many intervals, and its current frame's rolling-shutter
        compensation with ``sensor.rolling_shutter_look_ahead`` where ``shutter`` (the response,
        6x6) and ``compensation`` (the pair's compensation twists, :meth:`_solve_pair`) are given,
        and with that look-ahead its stamp and colour-depth terms where ``frame_terms``
        (:meth:`_error_bases`) is given; None where none of these."""
        sensor = self.config.sensor
        span = self._twist_noise.get(step.timestamp)
        if (self.config.tracking.keyframes or step.flagged or ref_step.flagged or span is None
                or step.velocity is None or span.start != ref_step.timestamp):
            return None
        twist_before = noise_before = None
        before = self._twist_noise.get(ref_step.timestamp)
        measured = compensation is not None and compensation.measured  # (its latency basis measured already)
        if sensor.latency_look_ahead and before is not None and before.intervals == span.intervals and not measured:
            trusted = _trusted_velocity(ref_step)
            if trusted is not None:
                twist_before, noise_before = np.asarray(trusted, dtype=float), before.noise
        if not (sensor.rolling_shutter_look_ahead and shutter is not None and compensation is not None):
            shutter = None
        else:
            shutter = (shutter, compensation)
        if not sensor.rolling_shutter_look_ahead:
            frame_terms = None
        if twist_before is None and shutter is None and frame_terms is None:
            return None
        return _Provisional(step, ref_step, span.motion, span.intervals, Ad, twist_before, noise_before, shutter,
                            frame_terms)

    def _settle(self, ref_step: OdometryStep, step: OdometryStep,
                compensation: _Compensation | None) -> None:
        """The pair ending at ``ref_step`` settled by ``step``, a trusted pair over as many intervals
        right after it whose frames' points were moved with the twists ``compensation``
        (:meth:`_solve_pair`); its pose covariance recomposed (it is the last posed frame: nothing
        was composed onto it yet).

        - Its current frame's rows were moved to the stamp with the twist of its own pair, about
          half an interval early; ``step`` moved the same frame's rows, its reference's, with the
          mean of that twist and its own, about the twist at the stamp. The pose moves by the
          response to the difference, so both pairs read the frame compensated alike
          (docs/derivation.md, "The rolling shutter at the current frame, one frame late").
        - Its latency term is taken from the change of the twist across it
          (:func:`~covo_gtsam.calibration.central_change_basis`: ``step``'s twist minus the pair
          before's) in place of the recent changes' mean.
        - Its stamp and colour-depth terms take the camera's twist at its current frame, the one
          ``step`` moved that frame's rows with, in place of its own pair's mean twist, which
          belongs half an interval before the frame (docs/derivation.md, "The twist at the frame").
        """
        prov = self._provisional
        span = self._twist_noise.get(step.timestamp)
        if (prov is None or prov.step is not ref_step or step.flagged or step.velocity is None or span is None
                or span.start != ref_step.timestamp or span.intervals != prov.intervals):
            return
        pair = prov.step
        # (not next to a pair whose depth images were read a period apart: its twists are what that corrupts)
        if prov.shutter is not None and compensation is not None and not (pair.depth_jump_s or step.depth_jump_s):
            S, used = prov.shutter
            change = compensation.twist_ref - used.twist_cur
            if used.measured:  # its angular velocity was the gyroscope's, not to be replaced by the pairs'
                change[:3] = 0.0
            move = prov.restamp @ S @ change
            pair.relative = pair.relative.compose(gtsam.Pose3.Expmap(move))
            pair.pose = prov.ref_step.pose.compose(pair.relative)
            if "rolling_shutter" in pair.added_covariance:  # the move made: its term as the settled pairs' fit has it
                added = dict(pair.added_covariance)
                pair.covariance = pair.covariance - added.pop("rolling_shutter")
                pair.added_covariance = added
        # (not next to a pair whose depth images were read a period apart: its twist is what that corrupts)
        if prov.frame_terms is not None and not (pair.depth_jump_s or step.depth_jump_s):
            at_frame = (compensation.twist_ref if compensation is not None
                        else 0.5 * (np.asarray(pair.velocity, dtype=float) + np.asarray(step.velocity, dtype=float)))
            self._rebase(pair, prov.restamp, self._frame_twist_bases(prov.frame_terms, at_frame))
        if prov.twist_before is not None:
            B = central_change_basis(prov.motion.matrix(), prov.twist_before, step.velocity, prov.noise_before,
                                     span.noise)
            self._rebase(pair, prov.restamp, {"latency": B})
        pair.pose_covariance = compose_covariance(prov.ref_step.pose, prov.ref_step.pose_covariance, pair.relative,
                                                  pair.covariance)

    def _shutter_unmoved(self, step: OdometryStep) -> bool:
        """Whether ``step``'s covariance carries, besides the rolling-shutter term, that term's basis
        once more at its model's size (factor 1), for the error of the current frame's compensation
        with the pair's mean twist that registering the next frame may take out
        (``sensor.rolling_shutter_look_ahead``, :meth:`_settle`): every pair with the term on, from
        its return until that move is made (a pair never moved, e.g. a run's last, keeps it). The
        term's fitted factor (``sensor.rolling_shutter_factor``) is that of the moved pairs."""
        return (self.config.sensor.rolling_shutter_factor > 0 and step.error_bases is not None
                and "rolling_shutter" in step.error_bases and bool(np.any(step.error_bases["rolling_shutter"])))

    def _add_twist_change(self, last: OdometryStep, step: OdometryStep) -> None:
        """The change of the twist from ``last``'s pair to ``step``'s into the latency term's history:
        only two consecutive pairs of the same number of frame intervals (per interval, so a camera
        that drops every other frame still has the term), neither flagged by the integrity check.
        The noise subtracted is each twist's share of the estimator's own covariance,
        ``C_points / dt^2`` (not scaled by kappa, as in the fit), and what the two share through the
        middle frame's points (``_TwistSpan.cross``), which moves the change twice."""
        prev, cur = self._twist_noise.get(last.timestamp), self._twist_noise.get(step.timestamp)
        self._twist_noise = {step.timestamp: cur} if cur is not None else {}
        if (prev is None or cur is None or prev.intervals != cur.intervals
                or cur.start != last.timestamp or step.flagged or last.flagged
                or step.velocity is None or last.velocity is None):
            return
        self._twist_changes.add(cur.motion.matrix(), last.velocity, step.velocity, prev.noise, cur.noise,
                                cur.intervals, cur.cross)

    def _capture_interval(self, ref_step: OdometryStep, timestamp: float) -> tuple[float, float, float | None]:
        """``(dt, r_ref, r_cur)``: the time between the two frames' captures (s) and the times (s) by
        which the pose is moved from the captures to the stamps. The reference frame moves by what
        its own pair moved it (``ref_step.stamp_shift``), so that consecutive moves cancel along the
        trajectory; the current frame by its offset from the frame clock where the clock placed it
        and that changes the interval by at most half (not, e.g., at a repeated stamp), else not at
        all (``r_cur`` None: taken at its stamp). An interval shorter than a quarter of
        ``frame_interval_s`` counts as 0: no velocity is taken from it."""
        stamp_dt = timestamp - ref_step.timestamp
        r_ref = ref_step.stamp_shift or 0.0
        r_cur = self._clock_offset  # None until the clock places the frame

        def plausible(dt: float) -> bool:
            return stamp_dt > 0 and 0.5 * stamp_dt <= dt <= 2.0 * stamp_dt

        if r_cur is None or not plausible(stamp_dt - r_cur + r_ref):
            r_cur = None
            if not plausible(stamp_dt + r_ref):
                r_ref = 0.0
        dt = stamp_dt - (r_cur or 0.0) + r_ref
        if dt < 0.25 * self.config.sensor.frame_interval_s:
            dt = 0.0
        return dt, r_ref, r_cur

    def _error_bases(self, T: gtsam.Pose3, X_ref: np.ndarray, X_cur: np.ndarray, pairs, ref: FrameData,
                     frame: FrameData, ref_step: OdometryStep, twists: tuple[np.ndarray, np.ndarray] | None,
                     dt: float, timestamp: float, r_cur: float | None, gains: tuple[np.ndarray, np.ndarray],
                     jump: float, compensation: _Compensation | None = None
                     ) -> tuple[dict, np.ndarray, np.ndarray | None, _FrameTerms | None]:
        """The pair's basis of each frame-level error term (:mod:`covo_gtsam.frame_errors`), its
        response ``b`` (6,) to the current frame's depths scaled by ``1 + e`` (per unit ``e``) and
        its response (6x6) to an error of the current frame's rolling-shutter twist (None without
        the compensation or without a twist at the reference), and what the terms driven by the
        twist at the current frame need besides it (:class:`_FrameTerms`; None without motion);
        ``twists`` are the camera's twists at the two frames
        (:func:`~covo_gtsam.rolling_shutter.frame_twists`), None without motion; ``r_cur`` the current
        frame's move to its stamp (:meth:`_capture_interval`); ``gains`` the estimate's response to
        each point of the reference and the current frame (:func:`~covo_gtsam.frame_errors.transfer_gains`);
        ``jump`` the pair's depth-period jump (s, :meth:`_depth_jump`); ``compensation`` what the rows
        were moved with (:meth:`_solve_pair`). Where a gyroscope gave both frames' angular
        velocities, the latency term's rotation basis is their change across the pair and the
        rolling-shutter term is 0: the compensation's error is the gyroscope's (the ``gyro`` term, each
        frame's response to an error of its angular velocity, per (rad/s)^2 on each axis)."""
        gyro = compensation is not None and compensation.measured
        M = T.matrix()
        G_ref, G_cur = gains
        b_ref, b_cur = depth_scale_basis(G_ref, X_ref), depth_scale_basis(G_cur, X_cur)
        bases = {"depth_scale": np.outer(b_ref, b_ref) + np.outer(b_cur, b_cur)}
        # the camera's recent translation per interval, from the last posed frame (not this pair)
        recent = _trusted_velocity(self._last.step)
        step_m = 0.0 if recent is None else float(np.linalg.norm(recent[3:])) * self.config.sensor.frame_interval_s
        bases["span"] = span_basis(step_m, self.config.sensor.frame_intervals(dt))
        if twists is None:
            return bases, b_cur, None, None  # no motion: no timing terms
        twist_ref, velocity = twists
        # the covariance of the twist's change over the pair, from the pairs before this one (over k
        # frame intervals the twist changes k times as much), the latency term's basis; against an
        # older keyframe, the change over the k - m intervals from the keyframe to the last posed
        # frame was measured: it goes on k / (k - m) times as far over the pair, and the change since
        # the last posed frame (m intervals) may also be new, as the pairs before say
        history = self._twist_changes.basis(self._twist_change_prior())
        known = self._known_twist_change(T, ref_step, timestamp)
        k = self.config.sensor.frame_intervals(dt)
        if known is None:
            change_cov = k**2 * history
            bases["latency"] = change_cov
        else:
            measured, m, m_ref = known  # m_ref: the intervals the keyframe's own twist was taken over
            change_cov = m**2 * history  # the current frame's twist was taken over these m intervals
            bases["latency"] = (k / max(k - m, 1)) ** 2 * measured + change_cov
        if gyro:  # in place of the history's: the change across the pair, measured (less the gyroscope's noise)
            noise = np.zeros((6, 6))
            noise[:3, :3] = self.config.sensor.gyro_sigma_rad_s**2 * np.eye(3)
            bases["latency"] = known_change_basis(M, compensation.twist_ref, compensation.twist_cur, noise, noise)
        # a frame's pose keeps its stamp's full jitter unless it was moved to its place on the frame
        # clock, and then the uncertainty of the clock's phase, fitted to n stamps: 1/n of the variance
        n_ref = ref_step.clock_samples if ref_step.stamp_shift is not None else 0
        n_cur = self._clock.samples if r_cur is not None else 0
        # each frame's depths read its stamped colour-depth offset later: through its twist (with a
        # gyroscope, its angular velocity at each frame, as the rows were moved with)
        at_ref, at_cur = (compensation.twist_ref, compensation.twist_cur) if gyro else (twist_ref, velocity)
        frame_terms = _FrameTerms(M, at_ref, (1.0 / max(n_ref, 1), 1.0 / max(n_cur, 1)),
                                  ref.depth_offset * depth_time_response(G_ref, X_ref) @ at_ref,
                                  frame.depth_offset * depth_time_response(G_cur, X_cur))
        bases.update(self._frame_twist_bases(frame_terms, at_cur))
        # the depth images read whole periods apart (the nearest depth image switched to a neighbour):
        # as if the current frame's were read half the change later and the reference's half earlier
        j = np.zeros(6)
        if jump:
            for fd, G, X, uv, twist, shift in ((ref, G_ref, X_ref, pairs.uv_ref, twist_ref, -0.5 * jump),
                                               (frame, G_cur, X_cur, pairs.uv_cur, velocity, 0.5 * jump)):
                dz = depth_read_change(fd.depth, uv, X, twist, shift, self.camera.fx, self.camera.fy)
                j += depth_change_basis(G, X, dz)
        bases["depth_jump"] = np.outer(j, j)
        shutter = None
        if self.config.sensor.rolling_shutter_s > 0:
            # the twist at the current frame may differ from the pair's mean by half the change of
            # the twist over the pair: its size from the recent pairs (as the latency term's, not
            # from this pair's own twist, whose error would enter its own covariance); an older
            # keyframe's twist, its own pair's mean, by as much over the intervals it was taken
            # over; without a twist at the reference (a run's first pair) both frames' twists are
            # off by minus and plus half the change over the pair (a point keeps its row, so the
            # same error at both frames would nearly cancel)
            response = self._shutter_response
            B = response(G_cur, X_cur, pairs.uv_cur)
            if gyro:
                bases["rolling_shutter"] = np.zeros((6, 6))
                shutter = B
                B_ref = response(G_ref, X_ref, pairs.uv_ref)
                bases["gyro"] = B[:, :3] @ B[:, :3].T + B_ref[:, :3] @ B_ref[:, :3].T
            elif _trusted_velocity(ref_step) is None:
                D = B - response(G_ref, X_ref, pairs.uv_ref)
                bases["rolling_shutter"] = 0.25 * D @ change_cov @ D.T
            else:
                bases["rolling_shutter"] = 0.25 * B @ change_cov @ B.T
                shutter = B
                if known is not None:
                    B_ref = response(G_ref, X_ref, pairs.uv_ref)
                    bases["rolling_shutter"] += 0.25 * m_ref**2 * B_ref @ history @ B_ref.T
        return bases, b_cur, shutter, frame_terms

    def _frame_twist_bases(self, terms: _FrameTerms, twist_cur: np.ndarray) -> dict[str, np.ndarray]:
        """The bases of the terms that take the camera's twist ``twist_cur`` at the current frame:
        ``timing`` and ``stamp_jitter`` (each frame off its stamp), ``depth_time`` (each frame's
        colour-depth offset's error on its own: ``h_ref h_ref^T + h_cur h_cur^T``, ``h_f`` the pair's
        response to that frame's depths read its stamped offset later) and ``depth_time_coherent``
        (the offsets' own effect, both frames together; none where the points were moved to their
        colour images' times by the stamped offsets, ``depth_time_compensation``)."""
        h_ref, h_cur = terms.h_ref, terms.A_cur @ twist_cur
        h = np.zeros(6) if self.config.sensor.depth_time_compensation else h_ref + h_cur
        return {"timing": stamp_error_basis(terms.motion, terms.twist_ref, twist_cur),
                "stamp_jitter": stamp_error_basis(terms.motion, terms.twist_ref, twist_cur, terms.jitter_weights),
                "depth_time": np.outer(h_ref, h_ref) + np.outer(h_cur, h_cur), "depth_time_coherent": np.outer(h, h)}

    def _rebase(self, step: OdometryStep, restamp: np.ndarray, bases: dict[str, np.ndarray]) -> None:
        """Replace some of ``step``'s error bases (given between the captures; moved to the stamps by
        ``restamp``, 6x6) and its covariance by their terms' change."""
        sigmas = self.config.sensor.term_sigmas()
        new = dict(step.error_bases)
        for name, B in bases.items():
            B = restamp @ B @ restamp.T
            step.covariance = step.covariance + sigmas[name] ** 2 * (B - new[name])
            new[name] = B
        step.error_bases = new

    def _twist_change_prior(self) -> np.ndarray:
        """The latency basis (6, 6) until the run has measured a change of its twist: the change over
        one frame interval at ``sensor.angular_acceleration_prior``, in any direction."""
        sensor = self.config.sensor
        prior = np.zeros((6, 6))
        prior[:3, :3] = np.eye(3) * (sensor.angular_acceleration_prior * sensor.frame_interval_s) ** 2 / 3.0
        return prior

    def _depth_jump(self, ref: FrameData, frame: FrameData) -> float:
        """The change (s) of the colour-depth offset from ``ref`` to ``frame`` in whole periods
        (:func:`~covo_gtsam.frame_errors.depth_period_jump`): the depth images read that far apart."""
        return depth_period_jump(ref.depth_offset, frame.depth_offset, self.config.sensor.frame_interval_s)

    def _known_twist_change(self, T: gtsam.Pose3, ref_step: OdometryStep, timestamp: float
                            ) -> tuple[np.ndarray, int, int] | None:
        """Against an older keyframe (``T`` is ``T_ref,cur``): the latency basis of the measured change
        of the twist from the keyframe to the last posed frame, both twists from their own pairs, not
        this one (:func:`~covo_gtsam.calibration.known_change_basis`, carried to the current frame),
        the frame intervals since the last posed frame and those the keyframe's twist was taken
        over; None against the last posed frame, after a flagged keyframe (its twist is then its
        reference's, not the one whose noise is kept) or without both twists and their noise."""
        since = self._since_last(T, ref_step, timestamp)
        if since is None or ref_step.flagged:
            return None
        last, T_last_cur, dt_last = since
        twist_ref, twist_last = _trusted_velocity(ref_step), _trusted_velocity(last)
        span_ref, span_last = self._posed_twists.get(ref_step.timestamp), self._posed_twists.get(last.timestamp)
        if twist_ref is None or twist_last is None or span_ref is None or span_last is None:
            return None
        B = known_change_basis(_between_captures(ref_step, last).matrix(), twist_ref, twist_last, span_ref.noise,
                               span_last.noise)
        R = T_last_cur.rotation().matrix().T  # the last frame's axes in the current frame's
        B[:3, :3] = R @ B[:3, :3] @ R.T
        return B, self.config.sensor.frame_intervals(dt_last), span_ref.intervals

    def _to_frame_time(self, fd: FrameData, X: np.ndarray, uv: np.ndarray, twist: np.ndarray,
                       acceleration: np.ndarray | None = None) -> np.ndarray:
        """A frame's points moved to its colour image's timestamp: the depths along their rays to
        the bearings' time (:func:`covo_gtsam.frame_errors.depth_time_shift`), then each row to the
        timestamp (:func:`covo_gtsam.rolling_shutter.compensate_points`; ``acceleration``, rad/s^2,
        a gyroscope's)."""
        if self.config.sensor.depth_time_compensation and fd.depth_offset:
            X = depth_time_shift(X, twist, fd.depth_offset)
        if self.config.sensor.rolling_shutter_s > 0:
            X = compensate_points(X, uv[:, 1], twist, self.camera.height, self.config.sensor.rolling_shutter_s,
                                  acceleration)
        return X

    def _solve(self, X_ref: np.ndarray, X_cur: np.ndarray, pairs, initial: gtsam.Pose3 | None) -> RelativePoseResult:
        return estimate_relative_pose(
            X_ref, X_cur, pairs.Q_ref, pairs.Q_cur, weighting=self.config.estimator.weighting,
            scale=self.config.estimator.scale, robust=self.config.estimator.robust,
            variance_factor=self.config.estimator.variance_factor, initial=initial, reweight_tol=REWEIGHT_TOL_RAD)

    def gyro_summary(self) -> dict | None:
        """The gyroscope the run was given (None without one): its samples, their time span (s, on
        the frames' clock), how many pairs it compensated (both frames' readouts covered by its
        samples), and how far its stamps lie behind the frames' clock by the pairs' own turns, with
        its standard error (s; :func:`~covo_gtsam.gyro.clock_offset`; None with too few pairs)."""
        if self.gyro is None:
            return None
        offset = None
        if self._turns:
            a, b, w = (np.array(x) for x in zip(*self._turns))
            offset = clock_offset(self.gyro, a, b, w)
        return {"samples": len(self.gyro.stamps), "span_s": list(self.gyro.span), "pairs": self._gyro_pairs,
                "clock_offset_s": None if offset is None else offset[0],
                "clock_offset_se_s": None if offset is None else offset[1]}

    def self_calibration(self) -> dict:
        """What the run learnt about its sensor without ground truth: the frame clock's period (s),
        the scatter of the stamps around it (s.d. of the clock offsets, s), the integrity
        statistic's scale (median over the run's pairs, each on the scale of one frame interval,
        / median of chi2(6)) and the share of the
        twist changes' basis spread over all axes (:class:`~covo_gtsam.calibration.TwistChanges`),
        how many posed pairs had their depth images read whole depth periods apart (the nearest
        depth image switched to a neighbour: the ``depth_jump`` term), and the depth images' own
        clock period (s; None when no depth image was stamped apart from its colour image): where it
        differs from the colour clock's the colour-depth offset drifts by the difference per frame,
        and a switch comes wherever the offset passes half a period; and the RMS of the depth-drift
        corrections per frame interval (m; None when none was applied: the correction off, keyframe
        mode, or fewer than two kept pairs)."""
        offsets = self._placed_offsets
        return {"frame_period_s": self._clock.period_s,
                "stamp_jitter_s": float(np.std(offsets)) if len(offsets) > 2 else None,
                "integrity_scale": self._integrity.scale,
                "twist_change_isotropic_share": self._twist_changes.share,
                "depth_period_jumps": self._depth_jumps,
                "depth_frame_period_s": self._depth_clock.period_s if self._depth_stamped else None,
                "depth_drift_rms_m": float(np.sqrt(self._drift_moves[0] / self._drift_moves[1]))
                if self._drift_moves[1] else None}
