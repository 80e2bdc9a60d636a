"""Realistic simulation: the whole odometry on a synthetic RGB-D sequence whose truth is known.

Where the thesis's simulation (:mod:`covo_gtsam.simulation`) draws independent noise for one
frame pair, this one runs :class:`~covo_gtsam.odometry.VisualOdometry` over a sequence of frames
with the error sources of a real unsynchronised RGB-D camera, each with a stated parameter:

* a hand-held motion: a rotation vector and a position that are sums of sines (angular speeds up
  to ``max_angular_speed`` rad/s), or a recorded one (``motion_file``, a TUM-format trajectory such
  as a sequence's ``groundtruth.txt``, from ``motion_start_s`` on, smoothed over
  ``motion_smooth_s``: :class:`RecordedMotion`); frames captured on a regular clock of period
  ``period_s``;
* timestamps off their capture by a white jitter of s.d. ``stamp_jitter_s`` (s), all of them
  ``stamp_latency_s`` (s) late (a driver's delay, which no stamp shows);
* a rolling shutter: row ``v`` of a colour image is captured ``readout_s (v - H/2) / H`` after the
  frame's capture time;
* the depth image taken ``depth_offset_s`` later than the colour image (uniform per frame in the
  given range; the depth rows with the same readout), or, with ``depth_period_s``, depth images
  captured on a clock of their own (that period, a random phase, stamped with the same latency and
  their own jitter), each colour frame taking the depth image whose stamp is nearest its own: the
  offset drifts by the difference of the periods per frame and, near half a period, the nearest
  depth image switches to its neighbour from frame to frame, as in the TUM freiburg1 sequences;
* pixel noise ``pixel_sigma`` (px) and the Kinect depth model times ``depth_noise_scale``;
* a depth error shared by all points of a frame: the depths scaled by ``1 + e``,
  ``e ~ N(0, depth_scale_sigma^2)`` per frame, plus a drift ``depth_drift * sin(2 pi t /
  depth_drift_period_s + phase)`` (random phase; 0 by default) that carries the error over frames;
* bad frames at rate ``bad_frame_rate``: their depth image belongs to an instant
  ``bad_frame_offset_s`` away (a depth image that was delivered with the wrong colour image);
* with ``gyro_rate_hz`` > 0, a gyroscope in the camera's axes sampling the true angular velocity at
  that rate with white noise of s.d. ``gyro_noise_rad_s`` per axis and a constant bias of
  ``gyro_bias_rad_s`` on each axis (random signs), stamped on the frames' clock (as late as the
  frames' stamps) and ``gyro_clock_offset_s`` later still, which the odometry is given.

The scene is a cloud of static points in front of the start pose (within ``scene_half_angle_deg``
of its optical axis, 1-4 m away); each point has a fixed random
descriptor, so matching is exact and what is measured is the estimator and its covariance. The
truth for a pair is the camera motion between the two frames' *stamps*, as a back end or the TUM
benchmark's ground truth sees it. Everything is drawn from ``seed``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np

from .camera import Camera
from .frontend import DESCRIPTOR_BYTES, Features, FrameData
from .metrics import nees, relative_pose_tangent_errors
from .config import OdometryConfig
from .errors import InputError
from .geometry import rotation_matrices
from .gyro import Gyroscope
from .odometry import VisualOdometry
from .pipeline import stacked_bases


@dataclass(frozen=True)
class SequenceSimulationConfig:
    """Parameters of :func:`simulate_sequence` (units in the module docstring)."""

    frames: int = 300
    seed: int = 0
    camera: str = "fr3"  # no lens distortion
    points: int = 4000
    #: the scene's points lie within this angle (deg) of the start's optical axis (180: all around,
    #: for a motion that turns far)
    scene_half_angle_deg: float = 70.0
    period_s: float = 1.0 / 30.0
    stamp_jitter_s: float = 0.002
    stamp_latency_s: float = 0.0
    readout_s: float = 0.025  # the simulated sensor's, not the odometry's default (odometry_defaults)
    depth_offset_s: tuple[float, float] = (0.0, 0.015)
    depth_period_s: float | None = None
    pixel_sigma: float = 1.0
    depth_noise_scale: float = 1.0
    depth_scale_sigma: float = 0.002
    depth_drift: float = 0.0
    depth_drift_period_s: float = 3.0
    bad_frame_rate: float = 0.03
    bad_frame_offset_s: float = 0.1
    max_angular_speed: float = 2.0
    max_speed: float = 0.3
    #: a recorded motion in place of the sines (TUM format: ``t tx ty tz qx qy qz qw``), the time
    #: (s after its first sample) the simulated sequence starts at, and the s.d. (s) of the Gaussian
    #: that smooths it (:class:`RecordedMotion`)
    motion_file: str | None = None
    motion_start_s: float = 0.0
    motion_smooth_s: float = 0.02
    gyro_rate_hz: float = 0.0
    gyro_noise_rad_s: float = 0.0
    gyro_bias_rad_s: float = 0.0
    gyro_clock_offset_s: float = 0.0

    def odometry_defaults(self) -> OdometryConfig:
        """The package's default settings told this sensor's readout (``sensor.rolling_shutter_s``, a
        property of the camera as its intrinsics are; the default is the fr1 Kinect's)."""
        return OdometryConfig().replace(sensor={"rolling_shutter_s": self.readout_s})


@dataclass
class SequenceSimulationResult:
    """Per tracked pair: errors (N, 6) against the truth between the stamps, reported covariances
    (N, 6, 6), ``flagged`` (N,), ``bad`` (N,: a frame of the pair is a bad frame), ``quality`` (N,);
    the frames' true stamp offsets (K,) and the clock offsets the odometry estimated (K,); the
    fitted frame period (s); frames lost (their count; ``lost_frames`` their indices); each pair's frame-level error bases; each pair's frame
    indices (N, 2), its true motion between the two *captures* (N, 4, 4) and the part of its error
    that the stamps' displacement from the captures makes, ``Log(T_capture^-1 T_stamps)`` (N, 6)."""

    errors: np.ndarray
    covariances: np.ndarray
    flagged: np.ndarray
    bad: np.ndarray
    quality: np.ndarray
    true_stamp_offsets: np.ndarray
    clock_offsets: np.ndarray
    clock_period_s: float | None
    lost: int
    config: SequenceSimulationConfig = field(repr=False)
    #: frame-level error bases of each pair (name -> (N, 6, 6)) and whether the pair has a velocity
    bases: dict = field(default_factory=dict, repr=False)
    consecutive: np.ndarray | None = field(default=None, repr=False)
    frames: np.ndarray | None = field(default=None, repr=False)
    capture_truth: np.ndarray | None = field(default=None, repr=False)
    stamp_errors: np.ndarray | None = field(default=None, repr=False)
    #: which frames (K,) are bad frames
    bad_frames: np.ndarray | None = field(default=None, repr=False)
    #: indices of the frames lost
    lost_frames: np.ndarray = field(default_factory=lambda: np.zeros(0, int), repr=False)
    #: each frame's stamped colour-depth offset (K,: depth minus colour stamp, s; the true one
    #: unless ``depth_period_s`` is set)
    depth_offsets: np.ndarray | None = field(default=None, repr=False)
    #: what the run learnt without ground truth (:meth:`VisualOdometry.self_calibration`)
    self_calibration: dict | None = field(default=None, repr=False)
    #: the simulated gyroscope as the run saw it (:meth:`VisualOdometry.gyro_summary`; None without one)
    gyro: dict | None = field(default=None, repr=False)

    @property
    def kept_consecutive(self) -> np.ndarray:
        """Mask (N,) of the consecutive pairs (one frame interval, with a velocity) the integrity check
        did not flag: the pairs a fit of the frame-level terms against the truth uses."""
        return self.consecutive & ~self.flagged

    def _kept_bases(self) -> dict[str, np.ndarray]:
        """Each frame-level term's bases (M, 6, 6) of the :attr:`kept_consecutive` pairs."""
        m = self.kept_consecutive
        return {k: v[m] for k, v in self.bases.items()}

    def fit_terms(self):
        """The maximum-likelihood fit of kappa, the frame term and every frame-level term against the
        truth on :attr:`kept_consecutive` (:func:`~covo_gtsam.calibration.fit_sensor_terms`; needs
        SciPy): a :class:`~covo_gtsam.calibration.SensorTerms`."""
        from .calibration import fit_sensor_terms

        m = self.kept_consecutive
        return fit_sensor_terms(self.errors[m], self.covariances[m], bases=self._kept_bases())

    def kept_covariances(self, terms) -> np.ndarray:
        """The covariances (M, 6, 6) of the :attr:`kept_consecutive` pairs under fitted sensor terms
        (a :class:`~covo_gtsam.calibration.SensorTerms`, e.g. :meth:`fit_terms` of another run)."""
        return terms.covariances(self.covariances[self.kept_consecutive], self._kept_bases())

    def nees(self, good_only: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """NEES of translation and rotation (3 dof each) of the pairs (without bad ones by default)."""
        m = ~self.bad if good_only else np.ones(len(self.bad), bool)
        e, C = self.errors[m], self.covariances[m]
        return nees(e[:, 3:], C[:, 3:, 3:]), nees(e[:, :3], C[:, :3, :3])

    @property
    def detection_rate(self) -> float:
        """Share of the bad frames that were caught: lost, or flagged in every pair they are in (NaN
        without bad frames; a bad frame in no pair and not lost is not caught)."""
        bad = np.flatnonzero(self.bad_frames)
        if not bad.size:
            return float("nan")
        lost = set(self.lost_frames.tolist())
        caught = []
        for k in bad:
            mine = (self.frames == k).any(axis=1)
            caught.append(k in lost or bool(mine.any() and self.flagged[mine].all()))
        return float(np.mean(caught))

    @property
    def false_alarm_rate(self) -> float:
        """Share of pairs without a bad frame that were flagged."""
        return float(np.mean(self.flagged[~self.bad]))

    @property
    def false_loss_rate(self) -> float:
        """Share of the frames that are not bad that were lost."""
        good = ~self.bad_frames
        return float(np.isin(np.flatnonzero(good), self.lost_frames).mean()) if good.any() else float("nan")


class _Motion:
    """A camera motion T_world,cam(t) given as its rotation vector and position at each time
    (``_state``, (N, 6)), which :meth:`pose` and :meth:`in_camera` read."""

    def _state(self, t: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def pose(self, t: float) -> gtsam.Pose3:
        s = self._state(np.array([t]))[0]
        return gtsam.Pose3(gtsam.Rot3.Expmap(s[:3]), s[3:])

    def in_camera(self, Pw: np.ndarray, t: np.ndarray) -> np.ndarray:
        """World points (N, 3) in the camera frame at their times ``t`` (N,)."""
        s = self._state(t)
        return np.einsum("nji,nj->ni", rotation_matrices(s[:, :3]), Pw - s[:, 3:])

    def angular_velocity(self, t: np.ndarray, h: float = 1e-4) -> np.ndarray:
        """The camera's body angular velocity (N, 3) at times ``t`` (N,) (rad/s, camera frame):
        ``Log(R(t - h)^T R(t + h)) / 2h``."""
        t = np.asarray(t, dtype=float)
        R0, R1 = rotation_matrices(self._state(t - h)[:, :3]), rotation_matrices(self._state(t + h)[:, :3])
        return np.array([gtsam.Rot3.Logmap(gtsam.Rot3(a.T @ b)) for a, b in zip(R0, R1)]) / (2 * h)


class _Trajectory(_Motion):
    """Smooth camera motion T_world,cam(t): sums of three sines per axis."""

    def __init__(self, rng: np.random.Generator, max_angular_speed: float, max_speed: float) -> None:
        self.f = rng.uniform(0.3, 1.5, size=(2, 3, 3)) * 2 * np.pi  # rad/s: rotation/position, axis, term
        self.phase = rng.uniform(0, 2 * np.pi, size=(2, 3, 3))
        # amplitudes so that each axis's speed stays below the maximum / sqrt(3)
        self.amp = np.empty((2, 3, 3))
        for i, vmax in enumerate((max_angular_speed, max_speed)):
            a = rng.uniform(0.5, 1.0, size=(3, 3))
            self.amp[i] = a * (vmax / np.sqrt(3)) / (a * self.f[i]).sum(axis=1, keepdims=True)

    def _state(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        s = (self.amp[None] * np.sin(self.f[None] * t[:, None, None, None] + self.phase[None])).sum(axis=3)
        return s.reshape(len(t), 6)


class RecordedMotion(_Motion):
    """A recorded camera motion T_world,cam(t), relative to the recorded pose at the first sample at
    or after ``start`` (s after the recording's first sample), ``t`` in seconds from that sample.

    The rotation vector and the position are resampled evenly at the recording's median spacing
    (linearly, also across a gap: ``gaps`` lists the times (s) where one begins, samples more than
    three spacings apart), smoothed with a Gaussian of s.d. ``smooth_s`` (s; it takes out the
    recording's own jitter, which a camera would not follow; odd reflection at the ends, so that a
    steady motion passes unchanged) and interpolated by cubic Hermite splines (the velocity
    continuous). A time outside the recording is an :class:`InputError`, as is a rotation that
    turns beyond 180 deg from the start's (its rotation vector would wrap)."""

    def __init__(self, stamps: np.ndarray, poses: np.ndarray, start: float = 0.0, smooth_s: float = 0.02) -> None:
        stamps, poses = np.asarray(stamps, dtype=float), np.asarray(poses, dtype=float)
        if not (np.all(np.isfinite(stamps)) and np.all(np.isfinite(poses))):
            raise InputError("the recorded motion's stamps and poses must be finite")
        order = np.argsort(stamps, kind="stable")
        stamps, poses = stamps[order], poses[order]
        if np.any(np.diff(stamps) <= 0):
            raise InputError("the recorded motion's stamps must differ (one pose per stamp)")
        i0 = int(np.searchsorted(stamps, stamps[0] + start))
        if i0 >= len(stamps) - 4:
            raise InputError(f"the recorded motion ends before {start} s")
        rel = np.linalg.inv(poses[i0]) @ poses
        t_raw = stamps - stamps[i0]
        w = np.array([gtsam.Rot3.Logmap(gtsam.Rot3(R)) for R in rel[:, :3, :3]])
        if np.any(np.linalg.norm(np.diff(w, axis=0), axis=1) > 1.0):
            raise InputError("the recorded motion turns beyond 180 deg from its start (its rotation vector wraps)")
        x_raw = np.concatenate([w, rel[:, :3, 3]], axis=1)
        h = float(np.median(np.diff(t_raw)))
        self.gaps = t_raw[:-1][np.diff(t_raw) > 3 * h]
        self.t = t_raw[0] + h * np.arange(int(np.floor((t_raw[-1] - t_raw[0]) / h + 1e-6)) + 1)
        x = np.stack([np.interp(self.t, t_raw, x_raw[:, j]) for j in range(6)], axis=1)
        if smooth_s > 0:
            sd = smooth_s / h
            k = np.arange(-int(np.ceil(4 * sd)), int(np.ceil(4 * sd)) + 1)
            g = np.exp(-0.5 * (k / sd) ** 2)
            padded = np.pad(x, ((k[-1], k[-1]), (0, 0)), mode="reflect", reflect_type="odd")
            x = np.stack([np.convolve(padded[:, j], g / g.sum(), mode="valid") for j in range(6)], axis=1)
        self.x = x
        self.dx = np.gradient(x, h, axis=0)  # the tangents at the samples

    @classmethod
    def from_tum(cls, path: str, start: float = 0.0, smooth_s: float = 0.02) -> "RecordedMotion":
        from .io import load_tum_trajectory

        stamps, poses = load_tum_trajectory(path, skip_invalid=True)
        return cls(stamps, poses, start, smooth_s)

    @property
    def span(self) -> tuple[float, float]:
        """The first and last time (s) the motion is known at."""
        return float(self.t[0]), float(self.t[-1])

    def _state(self, t: np.ndarray) -> np.ndarray:
        """Rotation vector and position (N, 6) at times ``t`` (N,), cubic Hermite between samples."""
        t = np.asarray(t, dtype=float)
        if np.any(t < self.t[0] - 1e-9) or np.any(t > self.t[-1] + 1e-9):
            raise InputError(f"the recorded motion is known from {self.t[0]:.3f} to {self.t[-1]:.3f} s, "
                             f"asked at {t.min():.3f} to {t.max():.3f} s")
        i = np.clip(np.searchsorted(self.t, t, side="right") - 1, 0, len(self.t) - 2)
        h = self.t[i + 1] - self.t[i]
        u = ((t - self.t[i]) / h)[:, None]
        h00, h10, h01, h11 = 2 * u**3 - 3 * u**2 + 1, u**3 - 2 * u**2 + u, -2 * u**3 + 3 * u**2, u**3 - u**2
        return (h00 * self.x[i] + h10 * h[:, None] * self.dx[i] + h01 * self.x[i + 1]
                + h11 * h[:, None] * self.dx[i + 1])


def _world_points(rng: np.random.Generator, n: int, half_angle_deg: float = 70.0) -> np.ndarray:
    """Points 1-4 m from the start, within ``half_angle_deg`` of its optical axis (+z): of ``n``
    directions drawn over the half sphere in front (over the whole sphere beyond 90 deg), those inside."""
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    if half_angle_deg <= 90.0:
        d[:, 2] = np.abs(d[:, 2])
    keep = d[:, 2] >= np.cos(np.deg2rad(half_angle_deg))
    d = d[keep]
    return d * rng.uniform(1.0, 4.0, size=(len(d), 1))


#: fixed-point steps that place a point at the time its rolling-shutter row is read
ROW_TIME_STEPS = 4


def _observe(traj: _Trajectory, Pw: np.ndarray, t_capture: float, readout: float, camera: Camera,
             depth_offset: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """True pixels (N, 2) at each point's row time, depths (N,) at the depth image's row time, and
    the mask of points in view with depth in [0.5, 5] m."""
    n = len(Pw)
    X = traj.in_camera(Pw, np.full(n, t_capture))
    front = X[:, 2] > 0.1
    uv = np.full((n, 2), -1.0)
    uv[front] = camera.project(X[front])
    # fixed-point steps: the capture time of the point's row, then the point seen then (each step
    # shrinks the error by the row speed times the readout over the height: 0.16 at 3000 px/s, so
    # four steps leave hundredths of a pixel where one left pixels)
    uv_r = uv
    for _ in range(ROW_TIME_STEPS):
        t_rows = t_capture + readout * (np.clip(uv_r[:, 1], 0, camera.height) - camera.height / 2) / camera.height
        Xr = traj.in_camera(Pw, t_rows)
        front &= Xr[:, 2] > 0.1
        uv_r = np.full((n, 2), -1.0)
        uv_r[front] = camera.project(Xr[front])
    z_d = traj.in_camera(Pw, t_rows + depth_offset)[:, 2]
    valid = front & camera.in_image(uv_r) & (z_d >= 0.5) & (z_d <= 5.0)
    return uv_r, z_d, valid


def simulate_sequence(cfg: SequenceSimulationConfig | None = None,
                      odometry: OdometryConfig | None = None) -> SequenceSimulationResult:
    """Run the odometry (``odometry`` settings, default: the package's told the sensor's readout,
    :meth:`SequenceSimulationConfig.odometry_defaults`) over a simulated sequence."""
    cfg = cfg or SequenceSimulationConfig()
    odometry = odometry or cfg.odometry_defaults()
    rng = np.random.default_rng(cfg.seed)
    camera = Camera.preset(cfg.camera)
    traj = _Trajectory(rng, cfg.max_angular_speed, cfg.max_speed)
    if cfg.motion_file is not None:  # (the sines drawn all the same, so the other draws stay those of a run)
        traj = RecordedMotion.from_tum(cfg.motion_file, cfg.motion_start_s, cfg.motion_smooth_s)
        # every instant a frame may be looked at: its rows, its stamp, its depth image (a bad frame's too)
        reach = (cfg.readout_s / 2 + cfg.stamp_latency_s + 5 * cfg.stamp_jitter_s + max(cfg.depth_offset_s)
                 + (cfg.bad_frame_offset_s if cfg.bad_frame_rate > 0 else 0.0) + (cfg.depth_period_s or 0.0)
                 + cfg.period_s)
        need = (-reach, (cfg.frames - 1) * cfg.period_s + reach)
        have = traj.span
        if need[0] < have[0] or need[1] > have[1]:
            raise InputError(f"{cfg.motion_file}: {cfg.frames} frames from {cfg.motion_start_s} s need the motion from "
                             f"{need[0]:.2f} to {need[1]:.2f} s around that start; it is known from {have[0]:.2f} "
                             f"to {have[1]:.2f} s")
    Pw = _world_points(rng, cfg.points, cfg.scene_half_angle_deg)
    descriptors = rng.integers(0, 256, size=(len(Pw), DESCRIPTOR_BYTES), dtype=np.uint8)
    noise = odometry.noise_model()
    vo = VisualOdometry(camera, odometry, gyro=_gyroscope(cfg, traj))

    captures = np.arange(cfg.frames) * cfg.period_s
    stamp_offsets = cfg.stamp_latency_s + rng.normal(0.0, cfg.stamp_jitter_s, cfg.frames)
    stamps = captures + stamp_offsets
    order_ok = np.all(np.diff(stamps) > 0)
    if not order_ok:  # keep the stamps in time order, as a driver does
        stamps = np.maximum.accumulate(stamps) + np.arange(cfg.frames) * 1e-6
        stamp_offsets = stamps - captures
    bad = rng.uniform(size=cfg.frames) < cfg.bad_frame_rate
    bad[:2] = False  # the run's first pairs set the integrity scale
    clocked = None if cfg.depth_period_s is None else _depth_clock(rng, cfg, captures, stamps)
    # the depths' drift: its own generator, so that the other draws stay those of a run without it
    phase = np.random.default_rng([cfg.seed, 1]).uniform(0.0, 2 * np.pi) if cfg.depth_drift else 0.0
    drift = cfg.depth_drift * np.sin(2 * np.pi * captures / cfg.depth_drift_period_s + phase)
    steps, frame_bad, stamped = [], [], []
    for k in range(cfg.frames):
        offset = rng.uniform(*cfg.depth_offset_s) if clocked is None else clocked[0][k]
        stamp = offset if clocked is None else clocked[1][k]
        if bad[k]:  # stamped as taken then
            offset, stamp = offset + cfg.bad_frame_offset_s, stamp + cfg.bad_frame_offset_s
        stamped.append(stamp)
        uv, z, valid = _observe(traj, Pw, captures[k], cfg.readout_s, camera, offset)
        idx = np.flatnonzero(valid)
        uv_m = uv[idx] + rng.normal(0.0, cfg.pixel_sigma, size=(len(idx), 2))
        z_m = z[idx] * (1.0 + rng.normal(0.0, cfg.depth_scale_sigma) + drift[k])
        z_m = z_m + rng.normal(size=len(idx)) * cfg.depth_noise_scale * noise.depth.sigma(z_m) / noise.depth.scale
        ok = z_m > 0
        idx, uv_m, z_m = idx[ok], uv_m[ok], z_m[ok]
        n = len(idx)
        frame = FrameData(
            features=Features(uv_m, descriptors[idx]), depth=np.zeros((1, 1), np.float32),
            points=camera.backproject(uv_m, z_m), covariances=noise.point_covariances(camera, uv_m, z_m),
            valid=np.ones(n, bool), depths=z_m, uv_undistorted=uv_m, theta=np.zeros(n), depth_offset=stamped[k])
        steps.append(vo.register_frame(frame, timestamp=float(stamps[k])))
        frame_bad.append(bad[k])

    index = {s: k for k, s in enumerate(stamps)}
    errors, covs, flagged, pair_bad, quality, kept, frames, T_captures, T_stamps = [], [], [], [], [], [], [], [], []
    for st in steps:
        if not st.has_relative_pose:
            continue
        i, j = index[st.ref_timestamp], index[st.timestamp]
        T_true = traj.pose(stamps[i]).between(traj.pose(stamps[j])).matrix()
        frames.append((i, j))
        T_captures.append(traj.pose(captures[i]).between(traj.pose(captures[j])).matrix())
        T_stamps.append(T_true)
        errors.append(relative_pose_tangent_errors(st.relative.matrix()[None], T_true[None])[0])
        covs.append(st.covariance)
        flagged.append(st.flagged)
        pair_bad.append(bool(bad[i] or bad[j]))
        quality.append(np.nan if st.quality is None else st.quality)
        kept.append(st)
    T_captures = np.array(T_captures).reshape(-1, 4, 4)
    return SequenceSimulationResult(
        errors=np.array(errors).reshape(-1, 6), covariances=np.array(covs).reshape(-1, 6, 6),
        flagged=np.array(flagged, bool), bad=np.array(pair_bad, bool), quality=np.array(quality),
        true_stamp_offsets=stamp_offsets, clock_offsets=np.array([s.clock_offset for s in steps]),
        clock_period_s=vo._clock.period_s, lost=sum(1 for s in steps if not s.has_pose), config=cfg,
        lost_frames=np.array([k for k, s in enumerate(steps) if not s.has_pose], int),
        bases=stacked_bases(kept), consecutive=np.array([s.velocity is not None for s in kept], bool),
        frames=np.array(frames, int).reshape(-1, 2), bad_frames=bad, capture_truth=T_captures,
        stamp_errors=relative_pose_tangent_errors(T_captures, np.array(T_stamps).reshape(-1, 4, 4)),
        depth_offsets=np.array(stamped), self_calibration=vo.self_calibration(), gyro=vo.gyro_summary())


def _gyroscope(cfg: SequenceSimulationConfig, traj: _Motion) -> Gyroscope | None:
    """The simulated gyroscope (``cfg.gyro_rate_hz``; None at 0): the true angular velocity sampled
    from a frame period before the first frame to one after the last, plus white noise (its own
    generator, so that the other draws stay those of a run without it), stamped as late as the frames."""
    if cfg.gyro_rate_hz <= 0:
        return None
    t = np.arange(-cfg.period_s, cfg.frames * cfg.period_s, 1.0 / cfg.gyro_rate_hz)
    rng = np.random.default_rng([cfg.seed, 2])
    noise = rng.normal(0.0, cfg.gyro_noise_rad_s, (len(t), 3))
    bias = cfg.gyro_bias_rad_s * rng.choice([-1.0, 1.0], 3)
    return Gyroscope(t + cfg.stamp_latency_s + cfg.gyro_clock_offset_s, traj.angular_velocity(t) + noise + bias)


def _depth_clock(rng: np.random.Generator, cfg: SequenceSimulationConfig, captures: np.ndarray,
                 stamps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Depth images on their own clock (``cfg.depth_period_s``, random phase; stamped with the colour
    stamps' latency and jitter), each colour frame taking the one with the nearest stamp: each
    frame's true and stamped colour-depth offsets (K,), s."""
    n = int(np.ceil((captures[-1] + cfg.period_s) / cfg.depth_period_s)) + 2
    depth_captures = rng.uniform(0.0, cfg.depth_period_s) - cfg.depth_period_s + np.arange(n) * cfg.depth_period_s
    depth_stamps = depth_captures + cfg.stamp_latency_s + rng.normal(0.0, cfg.stamp_jitter_s, n)
    nearest = np.argmin(np.abs(depth_stamps[None, :] - stamps[:, None]), axis=1)
    return depth_captures[nearest] - captures, depth_stamps[nearest] - stamps
