"""Monte Carlo simulation of the thesis (section 5.2) and its consistency metrics.

Scene: ``num_points`` points in view of both cameras, freiburg1 intrinsics, relative motion
``T_0,1 = [0.6, 0.6, 0.05 | -0.183, -0.183, 0, 0.966]`` (``tx ty tz qx qy qz qw``; maps points of
camera 1 into camera 0). Each run adds Gaussian noise to the pixel coordinates (``sigma_u``,
``sigma_v`` pixels) and to the depth (``sigma_Z`` from (4.7), theta = 0) of both views,
back-projects the noisy measurements, forms their covariances from the same noisy measurements
and estimates ``T_0,1`` with its covariance.

Errors are ``xi = Log(T_est^-1 T_true)`` in GTSAM's tangent ``[omega, v]``; NEES per block
(3 dof each) uses the matching block of the estimated covariance.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import gtsam
import numpy as np

from .camera import Camera
from .errors import ConfigError, EstimationError
from .estimator import estimate_relative_pose
from .geometry import pose_from_tum
from .noise import KinectAxialNoise, PixelNoise, PointNoiseModel
from .choices import Weighting
from .validation import (MAX_PIXEL_SIGMA, MAX_SCALE, MIN_PIXEL_SIGMA, MIN_SCALE, check_real, check_settings, choice,
                         integer, is_real, number)

#: The thesis's motion, TUM order tx ty tz qx qy qz qw (quaternion normalised on use).
THESIS_MOTION = (0.6, 0.6, 0.05, -0.183, -0.183, 0.0, 0.966)


#: Limits of :class:`SimulationConfig` (memory: (runs, 6, 6) covariances and (6 N, 6) Jacobians;
#: below 0.01 px the propagated 3x3 point covariances are no longer numerically positive definite;
#: beyond 100 m the Kinect depth model's sigma exceeds 19 m and is meaningless).
MAX_RUNS = 1_000_000
MAX_POINTS = 100_000
MAX_DEPTH = 100.0


@dataclass(frozen=True)
class SimulationConfig:
    """Settings of :func:`run_simulation`; each scalar field declares its default, unit, range and
    meaning and is checked on construction (:class:`ConfigError` naming the field), as are
    ``depth_range`` ``(min, max)`` metres with ``0 < min < max <= MAX_DEPTH``, ``motion``
    (``tx ty tz qx qy qz qw``), ``camera`` (a preset name) and ``depth_model`` (with a
    ``sigma(z, theta)`` method).
    """

    section: ClassVar[str] = ""

    runs: int = integer(1000, "Monte Carlo runs", 1, MAX_RUNS, "runs")
    seed: int = integer(0, "random seed", 0)
    num_points: int = integer(500, "points per run", 3, MAX_POINTS, "points")
    pixel_sigma: float = number(8.0, "standard deviation of the pixel noise", "px", minimum=MIN_PIXEL_SIGMA,
                                maximum=MAX_PIXEL_SIGMA)
    depth_range: tuple[float, float] = (0.5, 5.0)
    weighting: Weighting = choice(Weighting.CONSISTENT, "weighting of the residuals", Weighting)
    scale: float = number(1.0, "the thesis's covariance scale phi", "factor", minimum=MIN_SCALE,
                          maximum=MAX_SCALE)
    motion: tuple[float, ...] = THESIS_MOTION
    camera: str = "fr1"
    depth_model: KinectAxialNoise = field(default_factory=KinectAxialNoise)
    bias_draws: int = integer(0, "parametric-bootstrap draws per run that correct the estimate for its bias "
                              "(:func:`bootstrap_bias`; 0: none)", 0, 10_000, "draws")

    def __post_init__(self) -> None:
        check_settings(self, self.section)
        try:
            zmin, zmax = self.depth_range
        except (TypeError, ValueError):
            raise ConfigError(
                f"depth_range must be a pair (min, max) of depths in metres, got {self.depth_range!r}") from None
        check_real("depth_range min", zmin, "positive")
        check_real("depth_range max", zmax, "positive", maximum=MAX_DEPTH)
        if not zmin < zmax:
            raise ConfigError(f"depth_range needs min < max, got ({zmin!r}, {zmax!r})")
        motion = np.asarray(self.motion, dtype=object).reshape(-1)
        if motion.shape != (7,) or not all(is_real(v) and np.isfinite(v) for v in motion):
            raise ConfigError(f"motion must be 7 finite numbers tx ty tz qx qy qz qw, got {self.motion!r}")
        if not np.linalg.norm(np.asarray(motion[3:], dtype=float)) > 1e-9:
            raise ConfigError(f"motion's quaternion qx qy qz qw must not be zero, got {self.motion!r}")
        if not isinstance(self.camera, str):
            raise ConfigError(f"camera must be a preset name, got {self.camera!r}")
        Camera.preset(self.camera)
        if not callable(getattr(self.depth_model, "sigma", None)):
            raise ConfigError(f"depth_model must have a sigma(z, theta) method, got {self.depth_model!r}")


@dataclass(frozen=True)
class Scene:
    """Noise-free scene: points in both camera frames and the true ``T_0,1`` (4x4)."""

    X0: np.ndarray
    X1: np.ndarray
    T01: np.ndarray
    camera: Camera


def make_scene(cfg: SimulationConfig, rng: np.random.Generator) -> Scene:
    """Sample ``num_points`` points seen by both cameras (uniform pixel in view 0, uniform depth)."""
    camera = Camera.preset(cfg.camera)
    T01 = pose_from_tum(np.asarray(cfg.motion))
    R, t = T01[:3, :3], T01[:3, 3]
    zmin, zmax = cfg.depth_range
    chunks: list[np.ndarray] = []
    count = 0
    for _ in range(1000):
        m = 4 * cfg.num_points
        uv = rng.uniform([0, 0], [camera.width - 1, camera.height - 1], size=(m, 2))
        z = rng.uniform(zmin, zmax, size=m)
        X0 = camera.backproject(uv, z)
        X1 = (X0 - t) @ R
        ok = (X1[:, 2] >= zmin) & (X1[:, 2] <= zmax)
        ok[ok] = camera.in_image(camera.project(X1[ok]))
        chunks.append(X0[ok])
        count += int(ok.sum())
        if count >= cfg.num_points:
            break
    X0 = np.concatenate(chunks)[: cfg.num_points]
    if X0.shape[0] < cfg.num_points:
        raise EstimationError(
            f"could not place {cfg.num_points} points in view of both cameras with depths in "
            f"[{zmin:g}, {zmax:g}] m under the simulated motion; widen the depth range")
    return Scene(X0=X0, X1=(X0 - t) @ R, T01=T01, camera=camera)


def noisy_measurements(
    X: np.ndarray, camera: Camera, model: PointNoiseModel, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Noisy back-projected points (N, 3) and their covariances (N, 3, 3) at the noisy measurement.

    A noisy depth <= 0 (possible when the depth noise is large) is no measurement, as a depth
    camera reports 0 and the front end drops the keypoint: its rows are NaN (points and
    covariances); :func:`run_simulation` drops such pairs.
    """
    uv = camera.project(X)
    z = X[:, 2]
    n = X.shape[0]
    uv_n = uv + rng.standard_normal((n, 2)) * [model.pixel.sigma_u, model.pixel.sigma_v]
    z_n = z + rng.standard_normal(n) * model.depth.sigma(z)
    valid = z_n > 0
    if valid.all():
        return camera.backproject(uv_n, z_n), model.point_covariances(camera, uv_n, z_n)
    points, covs = np.full((n, 3), np.nan), np.full((n, 3, 3), np.nan)
    points[valid] = camera.backproject(uv_n[valid], z_n[valid])
    covs[valid] = model.point_covariances(camera, uv_n[valid], z_n[valid])
    return points, covs


def mean_error_z(errors: np.ndarray) -> np.ndarray:
    """Each column's mean over its standard error (``sqrt(n)`` mean / s.d., ddof 1) of errors (n, k):
    how many standard errors the estimate's bias lies from zero; NaN with fewer than two runs."""
    errors = np.asarray(errors, dtype=float)
    if len(errors) < 2:
        return np.full(errors.shape[1:], np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        return errors.mean(axis=0) / errors.std(axis=0, ddof=1) * np.sqrt(len(errors))


def bootstrap_bias(T: gtsam.Pose3, X0: np.ndarray, X1: np.ndarray, camera: Camera, model: PointNoiseModel,
                   draws: int, rng: np.random.Generator, **estimator) -> np.ndarray:
    """The estimator's bias at ``T`` (T_0,1) as a tangent ``[omega, v]`` (6,), by parametric bootstrap:
    the mean of ``Log(T^-1 T_b)`` over ``draws`` estimates ``T_b`` from measurements drawn
    (:func:`noisy_measurements`) around the fused points, the midpoint of ``X0`` and ``T X1`` (camera-0
    frame, m) and its copy in camera 1. ``T Exp(-bias)`` is the estimate corrected to second order; the
    correction carries its own noise, about ``1/draws`` of the estimate's covariance, which the
    covariance reported with it leaves out."""
    R, t = T.rotation().matrix(), T.translation()
    P0 = 0.5 * (X0 + X1 @ R.T + t)
    P1 = (P0 - t) @ R
    bias = np.zeros(6)
    for _ in range(draws):
        B0, Q0 = noisy_measurements(P0, camera, model, rng)
        B1, Q1 = noisy_measurements(P1, camera, model, rng)
        ok = np.isfinite(B0[:, 2]) & np.isfinite(B1[:, 2])
        T_b = estimate_relative_pose(B0[ok], B1[ok], Q0[ok], Q1[ok], **estimator).pose
        bias += gtsam.Pose3.Logmap(T.between(T_b))
    return bias / draws


@dataclass
class SimulationResult:
    config: SimulationConfig
    errors: np.ndarray  # (runs, 6) xi = Log(T_est^-1 T_true), [omega, v]
    covariances: np.ndarray  # (runs, 6, 6)
    nees_rotation: np.ndarray  # (runs,)
    nees_translation: np.ndarray  # (runs,)
    iterations: np.ndarray  # (runs,)
    dropped_pairs: np.ndarray | None = None  # (runs,) pairs without a measurement (noisy depth <= 0)

    @property
    def anees_rotation(self) -> float:
        return float(np.mean(self.nees_rotation))

    @property
    def anees_translation(self) -> float:
        return float(np.mean(self.nees_translation))

    def empirical_covariance(self) -> np.ndarray:
        """Monte Carlo covariance (6x6) of the errors about zero (the true pose)."""
        return self.errors.T @ self.errors / self.errors.shape[0]

    def mean_predicted_covariance(self) -> np.ndarray:
        return self.covariances.mean(axis=0)

    def summary(self) -> dict:
        """JSON-ready metrics: ANEES, share outside chi^2(3) bounds, predicted vs empirical sigmas."""
        from .chi2 import CHI2_3_975 as upper

        emp = self.empirical_covariance()
        pred = self.mean_predicted_covariance()
        sig = np.sqrt(np.einsum("nii->ni", self.covariances))
        within1 = np.mean(np.abs(self.errors) <= sig, axis=0)
        within3 = np.mean(np.abs(self.errors) <= 3 * sig, axis=0)
        axes = ["rx", "ry", "rz", "tx", "ty", "tz"]
        c = self.config
        return {
            "runs": int(self.errors.shape[0]),
            "seed": c.seed,
            "weighting": c.weighting,
            "scale": c.scale,
            "pixel_sigma": c.pixel_sigma,
            "num_points": c.num_points,
            "depth_range": list(c.depth_range),
            "bias_draws": c.bias_draws,
            "anees_translation": self.anees_translation,
            "anees_rotation": self.anees_rotation,
            "share_nees_translation_above_chi2_975": float(np.mean(self.nees_translation > upper)),
            "share_nees_rotation_above_chi2_975": float(np.mean(self.nees_rotation > upper)),
            "chi2_3_975": float(upper),
            "mean_error_over_standard_error": dict(zip(axes, mean_error_z(self.errors).tolist())),
            "sigma_empirical": dict(zip(axes, np.sqrt(np.diag(emp)).tolist())),
            "sigma_predicted_mean": dict(zip(axes, np.sqrt(np.diag(pred)).tolist())),
            "share_within_1sigma": dict(zip(axes, within1.tolist())),
            "share_within_3sigma": dict(zip(axes, within3.tolist())),
            "mean_iterations": float(np.mean(self.iterations)),
            "dropped_pairs": 0 if self.dropped_pairs is None else int(np.sum(self.dropped_pairs)),
        }


def simulate_runs(cfg: SimulationConfig, start: int = 0, stop: int | None = None, progress: bool = False):
    """Runs ``start`` to ``stop - 1`` of :func:`run_simulation`: ``(errors, covariances, iterations,
    dropped)`` for those runs, the same numbers as in the whole study. The random stream is the
    study's: the scene and the noise of the runs before ``start`` are drawn and discarded."""
    stop = cfg.runs if stop is None else stop
    rng = np.random.default_rng(cfg.seed)
    scene = make_scene(cfg, rng)
    model = PointNoiseModel(pixel=PixelNoise(cfg.pixel_sigma, cfg.pixel_sigma), depth=cfg.depth_model)
    for _ in range(start):
        noisy_measurements(scene.X0, scene.camera, model, rng)
        noisy_measurements(scene.X1, scene.camera, model, rng)
    T_true = gtsam.Pose3(scene.T01)
    m = stop - start
    errors = np.empty((m, 6))
    covs = np.empty((m, 6, 6))
    iters = np.empty(m, dtype=int)
    dropped = np.zeros(m, dtype=int)
    runs = range(m)
    if progress:
        from tqdm import tqdm

        runs = tqdm(runs, desc="simulate", unit="run")
    for i in runs:
        X0, Q0 = noisy_measurements(scene.X0, scene.camera, model, rng)
        X1, Q1 = noisy_measurements(scene.X1, scene.camera, model, rng)
        measured = np.isfinite(X0[:, 2]) & np.isfinite(X1[:, 2])  # noisy depth <= 0: no measurement
        if not measured.all():
            dropped[i] = int(np.count_nonzero(~measured))
            X0, Q0, X1, Q1 = X0[measured], Q0[measured], X1[measured], Q1[measured]
        res = estimate_relative_pose(X0, X1, Q0, Q1, weighting=cfg.weighting, scale=cfg.scale)
        pose = res.pose
        if cfg.bias_draws:  # its own stream per run, so the measurements stay those of the plain study
            bias = bootstrap_bias(pose, X0, X1, scene.camera, model, cfg.bias_draws,
                                  np.random.default_rng([cfg.seed, 1, start + i]), weighting=cfg.weighting,
                                  scale=cfg.scale)
            pose = pose.compose(gtsam.Pose3.Expmap(-bias))
        errors[i] = gtsam.Pose3.Logmap(pose.between(T_true))
        covs[i] = res.covariance
        iters[i] = res.iterations
    return errors, covs, iters, dropped


def simulation_result(cfg: SimulationConfig, errors: np.ndarray, covs: np.ndarray, iters: np.ndarray,
                      dropped: np.ndarray) -> SimulationResult:
    """The :class:`SimulationResult` (with NEES) of all runs' errors, covariances, iterations, drops."""
    nees_rot = np.einsum("ni,ni->n", errors[:, :3], np.linalg.solve(covs[:, :3, :3], errors[:, :3, None])[..., 0])
    nees_tr = np.einsum("ni,ni->n", errors[:, 3:], np.linalg.solve(covs[:, 3:, 3:], errors[:, 3:, None])[..., 0])
    return SimulationResult(cfg, errors, covs, nees_rot, nees_tr, iters, dropped)


def run_simulation(cfg: SimulationConfig, progress: bool = False) -> SimulationResult:
    """Run ``cfg.runs`` Monte Carlo trials; deterministic for a given ``cfg.seed``."""
    return simulation_result(cfg, *simulate_runs(cfg, progress=progress))


def run_simulation_parallel(cfg: SimulationConfig, workers: int | None = None, scheduler: str | None = None,
                            chunks: int | None = None, timeout: float | None = None) -> SimulationResult:
    """:func:`run_simulation` split into ``chunks`` blocks of consecutive runs (default: two per
    worker) run by :func:`covo_gtsam.parallel.map_tasks`; the same numbers as the serial study."""
    from .parallel import CONNECT_TIMEOUT, default_workers, map_tasks

    n_workers = workers or (2 if scheduler else default_workers(cfg.runs))
    chunks = max(1, min(cfg.runs, chunks or 2 * n_workers))
    edges = np.linspace(0, cfg.runs, chunks + 1).round().astype(int)
    parts = map_tasks(simulate_runs, [(cfg, int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a],
                      workers=workers, scheduler=scheduler, timeout=timeout or CONNECT_TIMEOUT)
    return simulation_result(cfg, *(np.concatenate(x) for x in zip(*parts)))
