"""Depth-edge simulation: frame pairs whose depth is read from rendered depth images.

The thesis's simulation draws each point's depth error from the sensor model alone. A real RGB-D
front end reads the depth from the depth image at the *measured* keypoint, so a keypoint off by its
pixel noise reads the depth of a neighbouring pixel: on a slanted surface a little off, beside a
depth edge possibly the far surface. Here the truth is known: a scene of boxes in front of a wall
is rendered into depth images at two camera poses, keypoints on the faces and along the boxes'
edges (where corner detectors fire) get pixel noise, and each depth is read from the rendered image
at the noisy pixel plus the Kinect depth noise. The relative pose is estimated with point
covariances with and without :func:`covo_gtsam.noise.depth_lookup_variance`; the NEES against the
true pose tells which covariance is honest.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from .camera import Camera
from .estimator import estimate_relative_pose
from .metrics import nees, relative_pose_tangent_errors
from .noise import KinectAxialNoise, PixelNoise, PointNoiseModel, depth_lookup_variance

#: boxes' front faces: (x0, x1, y0, y1, depth) in the world frame (metres), a wall behind them
BOXES = ((-0.9, -0.2, -0.5, 0.3, 1.4), (0.1, 0.7, -0.2, 0.6, 1.9), (-0.3, 0.3, 0.35, 0.8, 1.1))
WALL_Z = 3.2


@dataclass(frozen=True)
class EdgeSimulationConfig:
    runs: int = 200
    seed: int = 0
    pixel_sigma: float = 1.0  #: keypoint noise (px)
    points: int = 300  #: keypoints per frame pair
    edge_share: float = 0.3  #: share of the keypoints on the boxes' edges
    rotation_deg: float = 3.0  #: rotation of the current frame against the reference
    translation_m: float = 0.05  #: translation of the current frame


def render_depth(camera: Camera, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Depth image (H, W; metres along the optical axis) of the boxes and the wall seen by a camera
    at pose ``(R, t)`` (camera to world); pinhole, no distortion."""
    v, u = np.mgrid[0:camera.height, 0:camera.width].astype(float)
    rays = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(u)], -1)
    d = rays @ R.T  # world directions of rays with unit optical-axis depth
    depth = np.full(u.shape, np.inf)
    for x0, x1, y0, y1, z in BOXES + ((-np.inf, np.inf, -np.inf, np.inf, WALL_Z),):
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (z - t[2]) / d[..., 2]
            px, py = t[0] + s * d[..., 0], t[1] + s * d[..., 1]
            hit = (s > 0) & (px >= x0) & (px <= x1) & (py >= y0) & (py <= y1)
        depth = np.where(hit & (s < depth), s, depth)
    return np.where(np.isfinite(depth), depth, 0.0)


def _scene_points(rng: np.random.Generator, cfg: EdgeSimulationConfig) -> np.ndarray:
    """World points on the faces and along the edges of the boxes and on the wall."""
    n_edge = int(round(cfg.edge_share * cfg.points))
    n_face = cfg.points - n_edge
    out = []
    box = rng.integers(len(BOXES), size=n_edge)
    for k in box:  # a point on one of the four edges of a box's face
        x0, x1, y0, y1, z = BOXES[k]
        side = rng.integers(4)
        a = rng.uniform()
        x, y = ((x0 + a * (x1 - x0), y0), (x0 + a * (x1 - x0), y1), (x0, y0 + a * (y1 - y0)),
                (x1, y0 + a * (y1 - y0)))[side]
        out.append((x, y, z))
    for _ in range(n_face):  # a point on a face or the wall
        k = rng.integers(len(BOXES) + 1)
        if k == len(BOXES):
            out.append((rng.uniform(-1.8, 1.8), rng.uniform(-1.3, 1.3), WALL_Z))
        else:
            x0, x1, y0, y1, z = BOXES[k]
            out.append((rng.uniform(x0, x1), rng.uniform(y0, y1), z))
    return np.array(out)


def simulate_edge_pairs(cfg: EdgeSimulationConfig | None = None) -> dict[str, np.ndarray]:
    """NEES (runs, 2: translation, rotation) of the relative pose with the depth-lookup variance
    (``"lookup"``) and without it (``"sensor_only"``), on ``cfg.runs`` noisy draws of one scene."""
    cfg = cfg or EdgeSimulationConfig()
    rng = np.random.default_rng(cfg.seed)
    camera = Camera(fx=517.3, fy=516.5, cx=318.6, cy=255.3)  # fr1 intrinsics, no distortion
    axis = rng.normal(size=3)
    angle = np.deg2rad(cfg.rotation_deg)
    pose_ref = gtsam.Pose3()
    pose_cur = gtsam.Pose3(gtsam.Rot3.Rodrigues(axis / np.linalg.norm(axis) * angle),
                           cfg.translation_m * rng.normal(size=3) / np.sqrt(3))
    T_true = pose_ref.between(pose_cur).matrix()
    depths = [render_depth(camera, p.rotation().matrix(), p.translation()) for p in (pose_ref, pose_cur)]
    Pw = _scene_points(rng, cfg)
    uv_true, keep = [], np.ones(len(Pw), bool)
    for pose, depth in zip((pose_ref, pose_cur), depths):
        Xc = np.array([pose.transformTo(p) for p in Pw])
        uv = camera.project(Xc)
        ui, vi = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
        on = (ui >= 2) & (ui < camera.width - 2) & (vi >= 2) & (vi < camera.height - 2) & (Xc[:, 2] > 0)
        seen = np.zeros(len(Pw), bool)
        seen[on] = depth[vi[on], ui[on]] > Xc[on, 2] - 0.01  # not hidden behind a box
        keep &= seen
        uv_true.append(uv)
    uv_true = [uv[keep] for uv in uv_true]
    sensor = KinectAxialNoise()
    model = PointNoiseModel(pixel=PixelNoise(cfg.pixel_sigma, cfg.pixel_sigma), depth=sensor)
    offsets = np.array([[cfg.pixel_sigma, 0.0], [0.0, cfg.pixel_sigma]])
    out = {"lookup": [], "sensor_only": []}
    for _ in range(cfg.runs):
        X, Q, Q0 = [], [], []
        for uv_t, depth in zip(uv_true, depths):
            uv = uv_t + rng.normal(0.0, cfg.pixel_sigma, uv_t.shape)
            ui = np.clip(np.rint(uv[:, 0]).astype(int), 0, camera.width - 1)
            vi = np.clip(np.rint(uv[:, 1]).astype(int), 0, camera.height - 1)
            z_read = depth[vi, ui]
            z = z_read + rng.normal(0.0, 1.0, z_read.shape) * sensor.sigma(z_read)
            X.append(camera.backproject(uv, z))
            Q0.append(model.point_covariances(camera, uv, z))
            Q.append(model.point_covariances(camera, uv, z, lookup_variance=depth_lookup_variance(depth, uv, offsets)))
        for name, covs in (("lookup", Q), ("sensor_only", Q0)):
            res = estimate_relative_pose(X[0], X[1], covs[0], covs[1])
            err = relative_pose_tangent_errors(res.pose.matrix()[None], T_true[None])
            C = res.covariance[None]
            out[name].append([nees(err[:, 3:], C[:, 3:, 3:])[0], nees(err[:, :3], C[:, :3, :3])[0]])
    return {k: np.array(v) for k, v in out.items()}
