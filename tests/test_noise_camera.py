"""Camera model and per-point noise models against hand-computed values of the thesis's equations."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from covo_gtsam.camera import Camera
from covo_gtsam.errors import ConfigError
from covo_gtsam.noise import KinectAxialNoise, KinectLateralNoise, PixelNoise, PointNoiseModel, surface_angles


def test_presets():
    fr3 = Camera.preset("fr3")
    assert (fr3.fx, fr3.fy, fr3.cx, fr3.cy) == (535.4, 539.2, 320.1, 247.6) and not fr3.has_distortion
    fr1 = Camera.preset("freiburg1")
    assert fr1.dist == (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)
    assert Camera.preset("fr2").fx == 520.9
    with pytest.raises(ConfigError):
        Camera.preset("fr9")


def test_projection_round_trip_and_distortion():
    cam = Camera.preset("fr1")
    rng = np.random.default_rng(0)
    uv = rng.uniform([0, 0], [639, 479], size=(200, 2))
    z = rng.uniform(0.5, 5, 200)
    np.testing.assert_allclose(cam.project(cam.backproject(uv, z)), uv, atol=1e-9)
    d = cam.distort(uv)
    norm = np.c_[(uv - [cam.cx, cam.cy]) / [cam.fx, cam.fy], np.ones(200)]
    ref = cv2.projectPoints(norm, np.zeros(3), np.zeros(3), cam.K, np.array(cam.dist))[0].reshape(-1, 2)
    np.testing.assert_allclose(d, ref, atol=1e-6)
    np.testing.assert_allclose(cam.undistort(d), uv, atol=1e-3)


def test_backprojection_jacobian_numerically():
    cam = Camera.preset("fr1")
    uv = np.array([[100.0, 400.0], [320.0, 240.0]])
    z = np.array([1.3, 3.1])
    J = cam.backprojection_jacobian(uv, z)
    h = 1e-6
    for k in range(3):
        d = np.zeros(3)
        d[k] = h
        num = (cam.backproject(uv + d[:2], z + d[2]) - cam.backproject(uv - d[:2], z - d[2])) / (2 * h)
        np.testing.assert_allclose(J[:, :, k], num, atol=1e-7)


def test_axial_noise_hand_values():
    m = KinectAxialNoise()
    assert m.sigma(np.array([1.0]))[0] == pytest.approx(0.0012 + 0.0019 * 0.36)
    assert m.sigma(np.array([3.0]), np.deg2rad(30))[0] == pytest.approx(0.0012 + 0.0019 * 2.6**2)
    th = np.deg2rad(70.0)
    expected = 0.0012 + 0.0019 * 1.6**2 + 0.0001 / np.sqrt(2.0) * th**2 / (np.pi / 2 - th) ** 2
    assert m.sigma(np.array([2.0]), th)[0] == pytest.approx(expected)


def test_axial_noise_rejects_invalid_depths_without_warnings():
    import warnings

    from covo_gtsam.errors import InputError

    m = KinectAxialNoise()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # np.sqrt of a negative depth warned before
        s = m.sigma(np.array([0.5, 2.0, 4.0]), np.deg2rad([0.0, 70.0, 89.5]))
        assert np.all(np.isfinite(s)) and s[1] > m.sigma(np.array([2.0]))[0]
        assert m.sigma(1.0).shape == ()
        for bad in ([-0.3], [1.0, 0.0], [np.nan], [np.inf]):
            with pytest.raises(InputError, match="depth must be positive"):
                m.sigma(np.array(bad), np.deg2rad(70.0))


def test_lateral_noise_hand_values():
    m = KinectLateralNoise()
    assert m.sigma(0.0) == pytest.approx(0.8)
    th = np.deg2rad(45)
    assert m.sigma(th) == pytest.approx(0.8 + 0.035 * th / (np.pi / 2 - th))


def test_point_covariance_is_j_q_jt_and_matches_monte_carlo():
    cam = Camera.preset("fr1")
    model = PointNoiseModel(pixel=PixelNoise(1.0, 2.0))
    uv = np.array([[150.0, 100.0]])
    z = np.array([2.0])
    Q = model.point_covariances(cam, uv, z)[0]
    J = cam.backprojection_jacobian(uv, z)[0]
    Quvz = np.diag([1.0, 4.0, model.depth.sigma(z)[0] ** 2])
    np.testing.assert_allclose(Q, J @ Quvz @ J.T, rtol=1e-12)
    rng = np.random.default_rng(0)
    n = 200000
    s = rng.standard_normal((n, 3)) * np.sqrt(np.diag(Quvz))
    X = cam.backproject(uv + s[:, :2], z + s[:, 2])
    emp = np.cov(X.T)
    np.testing.assert_allclose(emp, Q, rtol=0.03, atol=1e-3 * np.abs(Q).max())


def test_surface_angle_of_tilted_plane():
    cam = Camera.preset("fr3")
    tilt = np.deg2rad(40.0)
    # plane through (0, 0, 2) with normal (sin, 0, -cos) rotated about y: z = 2 + x tan(tilt)
    v, u = np.mgrid[0:480, 0:640].astype(float)
    xn = (u - cam.cx) / cam.fx
    depth = 2.0 / (1 - xn * np.tan(tilt))
    uv = np.array([[320.1, 247.6], [1.0, 1.0]])
    theta = surface_angles(depth.astype(np.float32), uv, cam)
    assert theta[0] == pytest.approx(tilt, abs=1e-3)  # at the principal point the ray is the optical axis
    assert theta[1] == 0.0  # too close to the border
    depth[240:260, 310:330] = 0.0
    assert surface_angles(depth.astype(np.float32), uv[:1], cam)[0] == 0.0  # invalid depth around
