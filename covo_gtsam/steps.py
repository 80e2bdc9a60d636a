"""What :meth:`VisualOdometry.register_frame <covo_gtsam.odometry.VisualOdometry.register_frame>`
returns for each frame (:class:`OdometryStep`, its :class:`StepStatus`), and the record of a run
that a caller keeps (:class:`StepHistory`)."""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import gtsam
import numpy as np

from .choices import Choice
from .errors import InputError
from .estimator import RelativePoseResult
from .metrics import block_traces

if TYPE_CHECKING:
    from .config import SensorConfig


class StepStatus(Choice):
    """What a registered frame got. Each value is the string written to the results (and compared
    by earlier code: ``step.status == "tracked"`` still works)."""

    #: The first frame with a pose: it defines the world frame (identity pose); no relative pose.
    ORIGIN = "first"
    #: Matched to its reference frame: a relative pose with covariance, and a pose.
    RELATIVE_POSE = "tracked"
    #: The first frame of a new segment after ``restart_after`` lost frames: the motion across the
    #: gap is unknown, so no relative pose; the pose is carried over the gap.
    NEW_SEGMENT = "restart"
    #: No pose; ``reason`` says why.
    LOST = "lost"

    @property
    def has_pose(self) -> bool:
        return self is not StepStatus.LOST


#: Statuses that carry a pose (:attr:`OdometryStep.has_pose`).
POSED_STATUSES = (StepStatus.ORIGIN, StepStatus.RELATIVE_POSE, StepStatus.NEW_SEGMENT)


@dataclass
class OdometryStep:
    """Outcome of one :meth:`~covo_gtsam.odometry.VisualOdometry.register_frame` call.

    ``status`` (:class:`StepStatus`; its string is accepted): with ``RELATIVE_POSE``, ``relative``
    is T_ref,cur (points of this frame into the reference frame at ``ref_timestamp``) with
    ``covariance`` in GTSAM's tangent ``[rx ry rz tx ty tz]`` (rad, m; right perturbation).
    ``pose`` is T_world,cur (world = the first posed camera frame) with ``pose_covariance``
    composed to first order along the trajectory as if the pairs were independent (over some 30
    pairs this understates the translation drift on real data; docs/consistency.md, finding 7).
    A ``NEW_SEGMENT`` step has the last pose and its covariance plus
    :meth:`~covo_gtsam.config.TrackingConfig.gap_noise`. ``velocity`` is the camera's mean body
    twist ``[omega, v]`` (rad/s, m/s) over the pair, ``Log(T_ref,cur) / dt`` of the 3D-3D estimate
    (before the depth-drift correction moves ``relative``). ``quality`` is the
    pair's integrity statistic (:mod:`covo_gtsam.integrity`: a pair at the run's running median reads
    chi2(6)'s median, 5.35, and the tail is heavier; a pair over k frame intervals taken on the scale of one; None
    when it could not be formed) and ``flagged`` tells that it exceeded
    ``sensor.integrity_threshold``: the covariance then also covers the disagreement of the pair's
    two depth-free estimates. A back end can gate on either.
    """

    timestamp: float
    status: StepStatus
    reason: str = ""
    ref_timestamp: float | None = None
    relative: gtsam.Pose3 | None = None
    covariance: np.ndarray | None = None
    pose: gtsam.Pose3 | None = None
    pose_covariance: np.ndarray | None = None
    num_matches: int = 0
    num_pairs: int = 0
    velocity: np.ndarray | None = None
    #: the twist this frame was moved from its capture to its stamp with (None: not moved): the
    #: pair's own ``velocity``, or for a flagged pair its reference's (its own is likely wrong)
    stamp_twist: np.ndarray | None = field(default=None, repr=False)
    #: the time (s) this frame's pose was moved from its capture to its stamp by (its offset from the
    #: frame clock); None: not moved, the pose is taken at the stamp (before the clock places the
    #: stamps, for a frame without a pair or without an interval to its reference, and where the
    #: offset would change the interval to its reference by more than half)
    stamp_shift: float | None = field(default=None, repr=False)
    #: the change (s) of the colour-depth capture offset from the reference frame in whole depth
    #: periods: the two depth images were read that far apart (the ``depth_jump`` term); 0 for most pairs
    #: (set for every pair the odometry matched, lost ones too)
    depth_jump_s: float = field(default=0.0, repr=False)
    #: False while registering the next frame may still revise ``covariance``, ``pose_covariance``
    #: and ``error_bases["latency"]`` (``sensor.latency_look_ahead``: the latency term is then taken
    #: from the change of the twist across the pair, the next pair's twist minus the one before),
    #: the bases of the terms driven by the camera's twist at the current frame (``timing``,
    #: ``stamp_jitter``, ``depth_time``, ``depth_time_coherent``: then built with the twist at the
    #: frame, the mean of this pair's and the next pair's, in place of this pair's own),
    #: and ``relative`` and ``pose`` (``sensor.rolling_shutter_look_ahead``: the current frame's
    #: compensation with the twist at its stamp, the mean of this pair's and the next pair's)
    settled: bool = True
    quality: float | None = None
    flagged: bool = False
    integrity_statistic: float | None = None
    clock_offset: float = 0.0
    clock_samples: int = 0
    error_bases: dict | None = field(default=None, repr=False)
    #: what the odometry added to ``covariance`` besides the per-point model and the sensor terms
    #: (name -> 6x6, in ``covariance``'s frame): ``depth_drift``, the depth-drift correction's own
    #: uncertainty, and ``rolling_shutter``, that term's model once more while the look-ahead has
    #: not moved the pose (:attr:`settled`; every pair in keyframe mode or without the look-ahead);
    #: not what the integrity check adds to a flagged pair's
    added_covariance: dict | None = field(default=None, repr=False)
    result: RelativePoseResult | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        self.status = StepStatus(self.status)

    @property
    def has_pose(self) -> bool:
        """The frame has a pose: status ``ORIGIN``, ``RELATIVE_POSE`` or ``NEW_SEGMENT``."""
        return self.status.has_pose

    @property
    def has_relative_pose(self) -> bool:
        """The frame was matched to its reference frame (status ``RELATIVE_POSE``, ``"tracked"``)."""
        return self.status is StepStatus.RELATIVE_POSE

    @property
    def tracked(self) -> bool:
        """Deprecated name of :attr:`has_pose` (it is not ``status == "tracked"``)."""
        return self.status.has_pose


class StepHistory:
    """The steps of a run in time order, as a caller keeps them: each without its estimator
    ``result`` and, unless ``keep_error_bases``, without its ``error_bases`` (what
    :func:`covo_gtsam.pipeline.calibrate_sequence` fits), so memory stays small on long runs.

    Given the run's ``sensor`` settings, it also records what each pair's covariance is made of,
    before the bases are dropped: ``variance_parts``, one entry per step, None for a step without a
    relative pose or flagged by the integrity check, else ``(names, variances)``, the names of the
    sensor terms (:meth:`~covo_gtsam.config.SensorConfig.sensor_terms`, with what the odometry
    added to each, :attr:`OdometryStep.added_covariance`) and their rotation and translation
    variance (len(names) + 1, 2) (the trace of each 3x3 block, rad^2 and m^2), the last row that of
    the whole covariance (:func:`covo_gtsam.evaluation.covariance_parts` summarises them).

    >>> history = StepHistory()
    >>> step = history.add(vo.register_frame(colour, depth, stamp))   # doctest: +SKIP
    """

    def __init__(self, keep_error_bases: bool = False, sensor: SensorConfig | None = None) -> None:
        self.keep_error_bases = keep_error_bases
        self.sensor = sensor
        self.steps: list[OdometryStep] = []
        self.variance_parts: list[tuple[tuple[str, ...], np.ndarray] | None] = []
        self._unsettled: OdometryStep | None = None  # the last step added, while the next frame may revise it

    def add(self, step: OdometryStep) -> OdometryStep:
        """Record ``step`` (a slim copy; the step before it copied again, as the next frame settled
        it: :attr:`OdometryStep.settled`); returns ``step`` itself."""
        if self._unsettled is not None and self.steps:
            self.steps[-1] = self._slim(self._unsettled)
            self.variance_parts[-1] = self._variance_parts(self._unsettled)
        self.steps.append(self._slim(step))
        self.variance_parts.append(self._variance_parts(step))
        self._unsettled = None if step.settled else step
        return step

    def _slim(self, step: OdometryStep) -> OdometryStep:
        keep = self.keep_error_bases
        return dataclasses.replace(step, result=None, error_bases=step.error_bases if keep else None,
                                   added_covariance=step.added_covariance if keep else None)

    def _variance_parts(self, step: OdometryStep) -> tuple[tuple[str, ...], np.ndarray] | None:
        if (self.sensor is None or not step.has_relative_pose or step.flagged or step.covariance is None
                or step.error_bases is None or step.ref_timestamp is None):
            return None
        try:
            terms = self.sensor.sensor_terms(step.timestamp - step.ref_timestamp, step.error_bases)
        except InputError:  # an interval no camera has (the odometry refuses such pairs)
            return None
        for name, C in (step.added_covariance or {}).items():
            terms[name] = terms.get(name, 0.0) + C
        return tuple(terms), block_traces(np.array([*terms.values(), step.covariance]))

    def __len__(self) -> int:
        return len(self.steps)

    def __iter__(self):
        return iter(self.steps)

    def __getitem__(self, i):
        return self.steps[i]

    @property
    def posed_steps(self) -> list[OdometryStep]:
        return [s for s in self.steps if s.has_pose]

    @property
    def lost_steps(self) -> list[OdometryStep]:
        return [s for s in self.steps if not s.has_pose]

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """Timestamps (K,) and poses T_world,cur (K, 4, 4) of the frames with a pose."""
        posed = self.posed_steps
        stamps = np.array([s.timestamp for s in posed])
        poses = np.array([s.pose.matrix() for s in posed]).reshape(-1, 4, 4)
        return stamps, poses


class DeprecatedStepAccess:
    """The history :class:`~covo_gtsam.odometry.VisualOdometry` kept of its steps until this release
    (``steps``, ``tracked_steps``, ``lost_steps``, ``trajectory()``, ``keep_error_bases``): still
    there, from the :class:`StepHistory` ``_history`` it fills, with a :class:`DeprecationWarning`;
    removed in the next release. A caller keeps the steps ``register_frame`` returns instead."""

    _history: StepHistory

    def _deprecated(self, name: str) -> StepHistory:
        warnings.warn(f"VisualOdometry.{name} is deprecated and will be removed in the next release; keep the "
                      "steps register_frame returns (covo_gtsam.steps.StepHistory)", DeprecationWarning, stacklevel=3)
        return self._history

    @property
    def steps(self) -> list[OdometryStep]:
        return self._deprecated("steps").steps

    @property
    def tracked_steps(self) -> list[OdometryStep]:
        return self._deprecated("tracked_steps").posed_steps

    @property
    def lost_steps(self) -> list[OdometryStep]:
        return self._deprecated("lost_steps").lost_steps

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """Timestamps (K,) and poses T_world,cur (K, 4, 4) of the posed frames."""
        return self._deprecated("trajectory()").trajectory()

    @property
    def keep_error_bases(self) -> bool:
        return self._deprecated("keep_error_bases").keep_error_bases

    @keep_error_bases.setter
    def keep_error_bases(self, keep: bool) -> None:
        self._deprecated("keep_error_bases").keep_error_bases = keep
