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

import gtsam
import numpy as np

from .camera import Camera
from .errors import EstimationError
from .estimator import estimate_relative_pose
from .geometry import pose_from_tum
from .noise import KinectAxialNoise, PixelNoise, PointNoiseModel

#: The thesis's motion, TUM order tx ty tz qx qy qz qw (quaternion normalised on use).
THESIS_MOTION = (0.6, 0.6, 0.05, -0.183, -0.183, 0.0, 0.966)


@dataclass(frozen=True)
class SimulationConfig:
    runs: int = 1000
    seed: int = 0
    num_points: int = 500
    pixel_sigma: float = 8.0
    depth_range: tuple[float, float] = (0.5, 5.0)
    weighting: str = "consistent"
    scale: float = 1.0
    motion: tuple[float, ...] = THESIS_MOTION
    camera: str = "fr1"
    depth_model: KinectAxialNoise = field(default_factory=KinectAxialNoise)


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
        raise EstimationError("could not place the requested points in view of both cameras")
    return Scene(X0=X0, X1=(X0 - t) @ R, T01=T01, camera=camera)


def noisy_measurements(
    X: np.ndarray, camera: Camera, model: PointNoiseModel, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Noisy back-projected points (N, 3) and their covariances (N, 3, 3) at the noisy measurement."""
    uv = camera.project(X)
    z = X[:, 2]
    n = X.shape[0]
    uv_n = uv + rng.standard_normal((n, 2)) * [model.pixel.sigma_u, model.pixel.sigma_v]
    z_n = z + rng.standard_normal(n) * model.depth.sigma(z)
    return camera.backproject(uv_n, z_n), model.point_covariances(camera, uv_n, z_n)


@dataclass
class SimulationResult:
    config: SimulationConfig
    errors: np.ndarray  # (runs, 6) xi = Log(T_est^-1 T_true), [omega, v]
    covariances: np.ndarray  # (runs, 6, 6)
    nees_rotation: np.ndarray  # (runs,)
    nees_translation: np.ndarray  # (runs,)
    iterations: np.ndarray  # (runs,)

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
        from .metrics import chi2_quantile

        upper = chi2_quantile(0.975, 3)
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
            "anees_translation": self.anees_translation,
            "anees_rotation": self.anees_rotation,
            "share_nees_translation_above_chi2_975": float(np.mean(self.nees_translation > upper)),
            "share_nees_rotation_above_chi2_975": float(np.mean(self.nees_rotation > upper)),
            "chi2_3_975": float(upper),
            "sigma_empirical": dict(zip(axes, np.sqrt(np.diag(emp)).tolist())),
            "sigma_predicted_mean": dict(zip(axes, np.sqrt(np.diag(pred)).tolist())),
            "share_within_1sigma": dict(zip(axes, within1.tolist())),
            "share_within_3sigma": dict(zip(axes, within3.tolist())),
            "mean_iterations": float(np.mean(self.iterations)),
        }


def run_simulation(cfg: SimulationConfig, progress: bool = False) -> SimulationResult:
    """Run ``cfg.runs`` Monte Carlo trials; deterministic for a given ``cfg.seed``."""
    rng = np.random.default_rng(cfg.seed)
    scene = make_scene(cfg, rng)
    model = PointNoiseModel(pixel=PixelNoise(cfg.pixel_sigma, cfg.pixel_sigma), depth=cfg.depth_model)
    T_true = gtsam.Pose3(scene.T01)
    errors = np.empty((cfg.runs, 6))
    covs = np.empty((cfg.runs, 6, 6))
    iters = np.empty(cfg.runs, dtype=int)
    runs = range(cfg.runs)
    if progress:
        from tqdm import tqdm

        runs = tqdm(runs, desc="simulate", unit="run")
    for i in runs:
        X0, Q0 = noisy_measurements(scene.X0, scene.camera, model, rng)
        X1, Q1 = noisy_measurements(scene.X1, scene.camera, model, rng)
        res = estimate_relative_pose(X0, X1, Q0, Q1, weighting=cfg.weighting, scale=cfg.scale)
        errors[i] = gtsam.Pose3.Logmap(res.pose.between(T_true))
        covs[i] = res.covariance
        iters[i] = res.iterations
    nees_rot = np.einsum("ni,ni->n", errors[:, :3], np.linalg.solve(covs[:, :3, :3], errors[:, :3, None])[..., 0])
    nees_tr = np.einsum("ni,ni->n", errors[:, 3:], np.linalg.solve(covs[:, 3:, 3:], errors[:, 3:, None])[..., 0])
    return SimulationResult(cfg, errors, covs, nees_rot, nees_tr, iters)
