"""Rolling-shutter compensation of back-projected points.

A rolling-shutter camera exposes its rows one after another: row ``v`` of an image with
timestamp ``t`` is captured at ``t + δ(v)``, ``δ(v) = readout * (v - H/2) / H`` (seconds; the
middle row is captured at the timestamp, rows below it later). While the camera moves with the
body twist ``ξ = [ω, v]`` (rad/s, m/s, expressed in the camera frame at ``t``; GTSAM's Pose3
tangent order), the camera pose at ``t + δ`` relative to the pose at ``t`` is
``T(δ) = Exp(δ ξ)``. A point back-projected from row ``v`` is therefore expressed in the camera
frame at ``t + δ(v)``; in the frame at ``t`` it is

    X_t = T(δ) X_δ ≈ X_δ + δ (ω × X_δ + v)          (first order in δ ξ).

The Kinect v1 of the TUM freiburg1 sequences reads its colour rows out over about 35 ms (most of
a frame period; the most accurate poses on fr1_rpy, ``sensor.rolling_shutter_s``), so a camera
turning at 1 rad/s moves rows at the top and bottom of the image about 2 deg apart. The registered
depth image is treated as captured with the same row timing.
"""

from __future__ import annotations

import gtsam
import numpy as np

from .errors import InputError
from .geometry import cross, rotation_matrices


def row_time_offsets(v: np.ndarray, height: int, readout_s: float) -> np.ndarray:
    """Capture time (N,) of pixel rows ``v`` relative to the image timestamp (seconds):
    ``readout_s * (v - height / 2) / height``."""
    if not (height > 0):
        raise InputError(f"image height must be positive, got {height!r}")
    return float(readout_s) * (np.asarray(v, dtype=float) - 0.5 * height) / float(height)


def compensate_points(
    X: np.ndarray, v: np.ndarray, twist: np.ndarray, height: int, readout_s: float,
    angular_acceleration: np.ndarray | None = None,
) -> np.ndarray:
    """Points (N, 3) moved from the camera frame at their row's capture time into the frame at
    the image timestamp: ``X + δ (ω × X + v_lin)`` with ``δ`` from :func:`row_time_offsets`; with
    an angular acceleration ``α`` (a gyroscope's), ``Exp(ω δ + α δ²/2) X + δ v_lin``, the turn over
    ``δ`` to second order and its rotation exact (at a gyroscope's fast turns the first-order
    rotation's own error is as large as the acceleration's).

    Args:
        X: (N, 3) camera-frame points (metres), back-projected from pixel rows ``v`` (N,).
        twist: (6,) body twist ``[ω, v]`` of the camera at the image timestamp (rad/s, m/s).
        height: image height (pixels); readout_s: time from the top row to the bottom row (s).
        angular_acceleration: (3,) rad/s^2 in the camera frame, or None (0).
    """
    X = np.asarray(X, dtype=float)
    twist = np.asarray(twist, dtype=float).reshape(6)
    d = row_time_offsets(v, height, readout_s)[:, None]
    if angular_acceleration is None:
        return X + d * (cross(twist[:3], X) + twist[3:])
    turn = d * twist[:3] + (0.5 * d**2) * np.asarray(angular_acceleration, dtype=float).reshape(3)
    return np.einsum("nij,nj->ni", rotation_matrices(turn), X) + d * twist[3:]


def frame_twists(T_ref_cur: gtsam.Pose3, dt: float, ref_velocity: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The camera's body twist (6,) at the reference and the current frame of a pair (rad/s, m/s).

    At the current frame it is the pair's mean twist ``Log(T_ref,cur) / dt``; at the reference it
    is averaged with ``ref_velocity`` (the reference's own pair twist, a central estimate) when
    given. (Extrapolating the current frame's twist by half the change made the shared fr1 frames
    less accurate; docs/consistency.md.)
    """
    twist = gtsam.Pose3.Logmap(T_ref_cur) / dt
    if ref_velocity is None:
        return twist, twist
    return 0.5 * (twist + np.asarray(ref_velocity, dtype=float)), twist
