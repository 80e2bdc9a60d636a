"""The depth a keypoint reads from the depth image: its variance from the keypoint's pixel noise and
from the colour-depth offset under motion (covo_gtsam.noise.depth_lookup_variance), checked against
Monte Carlo lookups and finite differences."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from covo_gtsam.geometry import image_velocities
from covo_gtsam.noise import GAUSS_HERMITE_5, depth_lookup_variance
from covo_gtsam.odometry import OdometryConfig, VisualOdometry


def _surface(h=120, w=160):
    v, u = np.mgrid[0:h, 0:w].astype(float)
    return 1.5 + 0.004 * (u - 80) + 0.002 * (v - 60) + 2e-5 * (u - 80) ** 2


def test_smooth_surface_matches_monte_carlo_lookups():
    depth = _surface()
    uv = np.array([[40.0, 30.0], [80.0, 60.0], [120.0, 90.0]])
    sigma = 3.0
    var = depth_lookup_variance(depth, uv, np.array([[sigma, 0.0], [0.0, sigma]]))
    # oracle: the keypoint's true position drawn from its pixel noise, the depth read there (nearest pixel)
    rng = np.random.default_rng(1)
    d = rng.normal(0.0, sigma, size=(200_000, 2))
    for k, (u, v) in enumerate(uv):
        ui = np.floor(u + d[:, 0] + 0.5).astype(int)
        vi = np.floor(v + d[:, 1] + 0.5).astype(int)
        z = depth[vi, ui]
        mc = np.mean((z - depth[int(v), int(u)]) ** 2)
        assert var[k] == pytest.approx(mc, rel=0.08)


def test_edge_gives_the_weight_of_the_far_side_times_the_squared_jump_and_holes_are_left_out():
    depth = np.full((50, 50), 1.0)
    depth[:, 26:] = 3.0  # a 2 m step between columns 25 and 26
    offsets = np.array([[2.0, 0.0], [0.0, 2.0]])
    var = depth_lookup_variance(depth, np.array([[25.0, 20.0], [10.0, 20.0]]), offsets)
    # the positive nodes along u land across the edge: their weights times the squared jump
    assert var[0] == pytest.approx(4.0 * sum(w for _, w in GAUSS_HERMITE_5))
    assert var[1] == 0.0  # flat, far from the edge
    holes = depth.copy()
    holes[:, 26:] = 0.0  # no depth beyond the edge: no information, not an error
    assert depth_lookup_variance(holes, np.array([[25.0, 20.0]]), offsets)[0] == 0.0
    # per-point offsets (K, N, 2): zero offsets, zero variance
    assert depth_lookup_variance(depth, np.array([[25.0, 20.0]]), np.zeros((1, 1, 2)))[0] == 0.0


def test_image_velocities_match_finite_differences_of_the_projection():
    rng = np.random.default_rng(2)
    X = np.c_[rng.uniform(-1, 1, (20, 2)), rng.uniform(0.8, 4, 20)]
    twist = np.array([0.3, -0.8, 0.5, 0.2, -0.1, 0.4])
    fx, fy, h = 520.0, 515.0, 1e-6

    def project(P):
        return np.c_[fx * P[:, 0] / P[:, 2], fy * P[:, 1] / P[:, 2]]

    # the camera moves by Exp(twist h) in its own frame: a static point's coordinates become Exp(twist h)^-1 X
    moved = gtsam.Pose3.Expmap(twist * h).inverse()
    Xh = np.array([moved.transformFrom(x) for x in X])
    np.testing.assert_allclose(image_velocities(X, twist, fx, fy), (project(Xh) - project(X)) / h, rtol=1e-4, atol=1e-3)


def test_depth_edges_widen_the_point_covariances_of_a_real_frame(sample_dir):
    from covo_gtsam.datasets.tum import TumSequence

    grey, depth = TumSequence(sample_dir).load(0)
    plain = VisualOdometry("fr1", OdometryConfig().replace(noise={"depth_lookup_noise": False})).prepare(grey, depth)
    edges = VisualOdometry("fr1", OdometryConfig()).prepare(grey, depth)
    v = plain.valid
    zz_plain, zz = plain.covariances[v, 2, 2], edges.covariances[v, 2, 2]
    assert np.all(zz >= zz_plain - 1e-15)
    lookup = depth_lookup_variance(plain.depth, plain.features.uv[v], np.array([[2.0, 0.0], [0.0, 2.0]]))
    at_edge = lookup > 0.05**2  # the depth changes by more than 5 cm within the pixel noise
    assert at_edge.sum() >= 5 and (~at_edge).sum() >= 50
    # beside an edge the lookup dominates the depth variance (the sensor model says millimetres);
    # elsewhere the local spread of the depth image (its noise and the surface's slope) is of the
    # order of the sensor model
    assert np.median(zz[at_edge] / zz_plain[at_edge]) > 20.0
    assert 1.0 < np.median(zz[~at_edge] / zz_plain[~at_edge]) < 4.0


def test_a_colour_depth_offset_under_motion_widens_the_pair_covariance(sample_dir):
    from covo_gtsam.datasets.tum import TumSequence

    seq = TumSequence(sample_dir)

    def run(offset_s, factor, depth_time=0.0, coherent=0.0, odd_only=False, compensated=False):
        vo = VisualOdometry("fr1", OdometryConfig().replace(noise={"depth_offset_factor": factor},
                                                          sensor={"frame_clock": False,
                                                                  "depth_time_factor": depth_time,
                                                                  "depth_time_coherent_factor": coherent,
                                                                  "depth_time_compensation": compensated}))
        steps = [vo.register_frame(*seq.load(i), seq.timestamps[i],
                                   depth_timestamp=seq.timestamps[i] + (offset_s if i % 2 or not odd_only else 0.0))
                 for i in range(4)]
        return steps[-1]

    base, off, off_ignored = run(0.0, 1.0), run(0.02, 1.0), run(0.02, 0.0)
    # the estimator's covariance (the reported one adds frame-level terms that depend on the run's
    # recent motion estimates, which the offsets also move)
    assert off.result.covariance[3:, 3:].trace() > 1.05 * base.result.covariance[3:, 3:].trace()
    np.testing.assert_allclose(off_ignored.covariance, base.covariance, rtol=1e-12, atol=1e-18)
    # the frame-level depth-time term (its basis grows with the offset) widens the reported one
    timed = run(0.02, 0.0, depth_time=0.324)
    assert timed.covariance[3:, 3:].trace() > 1.02 * off_ignored.covariance[3:, 3:].trace()
    # ... and so does its coherent form, the offsets' own effect at both frames together (by 23 % here)
    coherent = run(0.02, 0.0, coherent=1.0)
    assert coherent.covariance[3:, 3:].trace() > 1.05 * off_ignored.covariance[3:, 3:].trace()
    # ... not where the points were moved by the stamped offsets: that effect is compensated
    moved = run(0.02, 0.0, compensated=True)
    assert not np.any(moved.error_bases["depth_time_coherent"])
    np.testing.assert_allclose(run(0.02, 0.0, coherent=5.0, compensated=True).covariance, moved.covariance,
                               rtol=1e-12, atol=1e-18)
    # where only the current frame's depth image is off, the two forms are one: h_cur h_cur^T
    np.testing.assert_allclose(run(0.02, 0.0, coherent=1.0, odd_only=True).covariance,
                               run(0.02, 0.0, depth_time=1.0, odd_only=True).covariance, rtol=1e-12, atol=1e-18)
    # ... and both vanish for depth images stamped with their colour images
    np.testing.assert_allclose(run(0.0, 1.0, depth_time=0.324, coherent=1.0).covariance, base.covariance,
                               rtol=1e-12, atol=1e-18)


def test_gauss_hermite_nodes_integrate_the_normal_moments():
    from statistics import NormalDist

    # with the centre node (weight 8/15): total weight 1, variance 1, fourth moment 3
    w0 = 1.0 - 2.0 * sum(w for _, w in GAUSS_HERMITE_5)
    assert w0 == pytest.approx(8.0 / 15.0)
    assert 2.0 * sum(w * a**2 for a, w in GAUSS_HERMITE_5) == pytest.approx(1.0)
    assert 2.0 * sum(w * a**4 for a, w in GAUSS_HERMITE_5) == pytest.approx(3.0)
    assert NormalDist().cdf(-GAUSS_HERMITE_5[-1][0]) < 0.01  # the outer node reaches into the tails


@pytest.mark.slow
def test_depth_edge_simulation_recovers_an_honest_covariance():
    """Frame pairs whose depths are read from rendered depth images at noisy keypoints: with the
    depth-lookup variance the NEES follows chi2(3); with the sensor model alone it is far too large."""
    from covo_gtsam.edge_simulation import EdgeSimulationConfig, simulate_edge_pairs

    r = simulate_edge_pairs(EdgeSimulationConfig(runs=100, pixel_sigma=2.0, edge_share=0.1))
    anees = r["lookup"].mean(axis=0)
    assert np.all((2.3 < anees) & (anees < 4.0)), anees  # 100 runs: about 3 +- 0.5
    assert np.all(r["sensor_only"].mean(axis=0) > 30)


def test_blur_covariance_matches_a_monte_carlo_of_smeared_keypoints():
    """Motion blur: each keypoint placed uniformly along its smear (exposure times its image
    velocity, from a twist through geometry.image_velocities) and back-projected at its depth; the
    scatter of the points matches blur_covariances within 5 %, and is zero along the depth."""
    from covo_gtsam.camera import Camera
    from covo_gtsam.noise import blur_covariances

    cam = Camera.preset("fr1")
    rng = np.random.default_rng(4)
    uv = rng.uniform([50, 50], [590, 430], size=(5, 2))
    z = rng.uniform(0.8, 3.0, size=5)
    X = cam.backproject(uv, z)
    twist = np.array([0.4, -1.2, 0.3, 0.1, 0.05, -0.2])
    vel = image_velocities(X, twist, cam.fx, cam.fy)
    exposure = 0.015
    Q = blur_covariances(X, vel, exposure, cam.fx, cam.fy)
    s = rng.uniform(-0.5, 0.5, size=(40000, 1))
    for i in range(5):
        samples = cam.backproject(uv[i] + s * vel[i] * exposure, np.full(len(s), z[i]))
        mc = np.cov(samples.T)
        np.testing.assert_allclose(mc[:2, :2], Q[i, :2, :2], rtol=0.05, atol=1e-12)
        assert np.all(Q[i, 2] == 0) and np.all(Q[i, :, 2] == 0)
    assert np.all(blur_covariances(X, vel, 0.0, cam.fx, cam.fy) == 0)


def test_exposure_widens_the_pair_covariance(sample_dir):
    from covo_gtsam.datasets.tum import TumSequence

    seq = TumSequence(sample_dir)

    def run(exposure):
        vo = VisualOdometry("fr1", OdometryConfig().replace(noise={"exposure_s": exposure}))
        return [vo.register_frame(*seq.load(i), seq.timestamps[i]) for i in range(4)][-1]

    base, blurred = run(0.0), run(0.02)
    assert blurred.result.covariance[:3, :3].trace() > 1.05 * base.result.covariance[:3, :3].trace()
