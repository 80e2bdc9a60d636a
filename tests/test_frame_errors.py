"""Frame-level error terms: the estimator's gains against re-solving with GTSAM, the terms' covariances
against Monte Carlo draws of the frame-level errors."""

import gtsam
import numpy as np
import pytest

from covo_gtsam.camera import Camera
from covo_gtsam.estimator import estimate_relative_pose
from covo_gtsam.frame_errors import (
    depth_period_jump,
    depth_rates,
    depth_read_change,
    depth_scale_basis,
    depth_time_basis,
    depth_time_response,
    depth_time_shift,
    rolling_shutter_basis,
    transfer_gains,
)
from covo_gtsam.noise import PointNoiseModel
from covo_gtsam.simulation import SimulationConfig, make_scene, noisy_measurements

SMALL_MOTION = (0.02, 0.01, 0.01, 0.0131, 0.0, 0.0, 0.99991)


def _pair(seed=0, n=200):
    rng = np.random.default_rng(seed)
    scene = make_scene(SimulationConfig(num_points=n, motion=SMALL_MOTION), rng)
    model = PointNoiseModel()
    X0, Q0 = noisy_measurements(scene.X0, scene.camera, model, rng)
    X1, Q1 = noisy_measurements(scene.X1, scene.camera, model, rng)
    ok = np.all(np.isfinite(X0), 1) & np.all(np.isfinite(X1), 1)
    return X0[ok], X1[ok], Q0[ok], Q1[ok], rng


def test_gains_predict_how_the_gtsam_estimate_moves():
    """Displace the points along a random pattern, re-solve with GTSAM: the estimate moves by
    sum G dX (first order)."""
    X0, X1, Q0, Q1, rng = _pair()
    res = estimate_relative_pose(X0, X1, Q0, Q1)
    T = res.pose.matrix()
    G0, G1 = transfer_gains(T[:3, :3], T[:3, 3], X0, X1, Q0, Q1)
    for _ in range(3):
        d0, d1 = rng.normal(size=X0.shape) * 1e-3, rng.normal(size=X1.shape) * 1e-3
        moved = estimate_relative_pose(X0 + d0, X1 + d1, Q0, Q1, initial=res.pose)
        actual = gtsam.Pose3.Logmap(res.pose.between(moved.pose))
        predicted = np.einsum("nij,nj->i", G0, d0) + np.einsum("nij,nj->i", G1, d1)
        # first order with the weights held fixed; the estimator re-evaluates its weights at its
        # solution (a fixed point whose derivative has a small extra term along the weakly
        # determined rotation-translation direction): about 8 % apart here
        assert np.linalg.norm(actual - predicted) < 0.12 * np.linalg.norm(predicted)


def test_gain_covariance_is_the_estimators_covariance():
    """sum G Q G^T over both frames is the estimator's (Marginals) covariance."""
    X0, X1, Q0, Q1, _ = _pair(1)
    res = estimate_relative_pose(X0, X1, Q0, Q1)
    T = res.pose.matrix()
    G0, G1 = transfer_gains(T[:3, :3], T[:3, 3], X0, X1, Q0, Q1)
    C = np.einsum("nij,njk,nlk->il", G0, Q0, G0) + np.einsum("nij,njk,nlk->il", G1, Q1, G1)
    # the estimator evaluates its weights at its previous solution's rotation: a few per cent apart
    assert np.linalg.norm(C - res.covariance) < 0.01 * np.linalg.norm(res.covariance)


def test_depth_scale_term_matches_monte_carlo():
    """Each frame's depths scaled by 1 + e, e ~ N(0, s^2): the estimates scatter with
    s^2 (b0 b0^T + b1 b1^T)."""
    X0, X1, Q0, Q1, rng = _pair(2)
    res = estimate_relative_pose(X0, X1, Q0, Q1)
    T = res.pose.matrix()
    G0, G1 = transfer_gains(T[:3, :3], T[:3, 3], X0, X1, Q0, Q1)
    b0, b1 = depth_scale_basis(G0, X0), depth_scale_basis(G1, X1)
    s = 0.002
    xs = []
    for e0, e1 in rng.normal(0, s, size=(150, 2)):
        r = estimate_relative_pose(X0 * (1 + e0), X1 * (1 + e1), Q0, Q1, initial=res.pose)
        xs.append(gtsam.Pose3.Logmap(res.pose.between(r.pose)))
    emp = np.cov(np.array(xs).T)
    pred = s**2 * (np.outer(b0, b0) + np.outer(b1, b1))
    # 150 draws: about 12 % sampling error on the dominant variances
    np.testing.assert_allclose(np.diag(emp)[3:], np.diag(pred)[3:], rtol=0.3)


def test_depth_time_shift_and_basis():
    """A camera turning at 2 rad/s: points read 10 ms late along their rays are put back by the
    shift, and the basis is the estimate's response to a unit offset."""
    X0, X1, Q0, Q1, _ = _pair(3)
    twist = np.array([0.3, 2.0, -0.2, 0.05, 0.0, 0.1])
    # the depth read 10 ms later: the point's depth after the camera moved by Exp(0.01 twist), put on
    # the colour pixel's ray (gtsam's exponential map, not the code's rate formula)
    moved_cam = gtsam.Pose3.Expmap(0.01 * twist).inverse()
    z_late = np.array([moved_cam.transformFrom(x)[2] for x in X1])
    late = X1 / X1[:, 2:3] * z_late[:, None]
    shift = np.linalg.norm(late - X1, axis=1)
    assert shift.max() > 0.01  # centimetres at this speed
    # first order in the offset: what remains is of second order, d^2 (|w|^2 |X| + |w| |v|) at most
    resid = np.linalg.norm(depth_time_shift(late, twist, 0.01) - X1, axis=1)
    w, v = np.linalg.norm(twist[:3]), np.linalg.norm(twist[3:])
    assert np.all(resid <= 0.01**2 * (w**2 * np.linalg.norm(X1, axis=1) + w * v))
    assert np.sqrt(np.mean(resid**2)) < 0.1 * np.sqrt(np.mean(shift**2))
    res = estimate_relative_pose(X0, X1, Q0, Q1)
    T = res.pose.matrix()
    G0, G1 = transfer_gains(T[:3, :3], T[:3, 3], X0, X1, Q0, Q1)
    b = depth_time_basis(G1, X1, twist)
    eps = 1e-3
    moved = depth_time_shift(X1, twist, -eps)  # depths as if read eps later
    r = estimate_relative_pose(X0, moved, Q0, Q1, initial=res.pose)
    actual = gtsam.Pose3.Logmap(res.pose.between(r.pose))
    assert np.linalg.norm(actual - b * eps) < 0.05 * np.linalg.norm(b * eps)


def test_depth_time_response_is_the_estimates_response_per_unit_twist():
    """``depth_time_response(G, X) @ twist`` is the estimate's response to the depths read one
    second late under that twist, re-solved with GTSAM (as above) for two twists, and linear:
    the response to their sum is the sum of the responses."""
    X0, X1, Q0, Q1, rng = _pair(5)
    res = estimate_relative_pose(X0, X1, Q0, Q1)
    T = res.pose.matrix()
    _, G1 = transfer_gains(T[:3, :3], T[:3, 3], X0, X1, Q0, Q1)
    A = depth_time_response(G1, X1)
    assert A.shape == (6, 6)
    eps = 1e-3
    twists = [np.array([0.3, 2.0, -0.2, 0.05, 0.0, 0.1]), np.array([-1.0, 0.2, 0.5, 0.0, -0.2, 0.3])]
    for twist in (*twists, twists[0] + twists[1]):
        moved = depth_time_shift(X1, twist, -eps)  # depths as if read eps later
        r = estimate_relative_pose(X0, moved, Q0, Q1, initial=res.pose)
        actual = gtsam.Pose3.Logmap(res.pose.between(r.pose))
        assert np.linalg.norm(actual - A @ twist * eps) < 0.05 * np.linalg.norm(A @ twist * eps)
        np.testing.assert_allclose(A @ twist, depth_time_basis(G1, X1, twist), rtol=1e-12, atol=1e-15)


def test_rolling_shutter_basis_is_the_response_to_a_twist_error():
    X0, X1, Q0, Q1, rng = _pair(4)
    res = estimate_relative_pose(X0, X1, Q0, Q1)
    T = res.pose.matrix()
    G0, G1 = transfer_gains(T[:3, :3], T[:3, 3], X0, X1, Q0, Q1)
    d = rng.uniform(-0.0125, 0.0125, len(X1))
    B = rolling_shutter_basis(G1, X1, d)
    dtw = np.array([0.2, -0.1, 0.3, 0.02, 0.01, -0.03])
    moved = X1 + d[:, None] * (np.cross(dtw[:3], X1) + dtw[3:])
    r = estimate_relative_pose(X0, moved, Q0, Q1, initial=res.pose)
    actual = gtsam.Pose3.Logmap(res.pose.between(r.pose))
    assert np.linalg.norm(actual - B @ dtw) < 0.05 * np.linalg.norm(B @ dtw)


def test_opposite_twist_errors_at_the_two_frames_move_the_pose_by_the_difference_of_their_bases():
    """A run's first pair compensates both frames' readout with the pair's mean twist, which errs by
    ``-c/2`` at the reference and ``+c/2`` at the current frame (``c``: the twist's change over the
    pair). Re-solved with GTSAM, the pose moves by ``(B_cur - B_ref) c/2`` (each frame's basis from its
    points' rows); a point keeps its row from frame to frame under a small motion, so the sum
    ``(B_cur + B_ref) c/2`` (the same error at both frames) nearly cancels and would understate it."""
    X0, X1, Q0, Q1, _ = _pair(5)
    res = estimate_relative_pose(X0, X1, Q0, Q1)
    T = res.pose.matrix()
    G0, G1 = transfer_gains(T[:3, :3], T[:3, 3], X0, X1, Q0, Q1)
    cam = Camera.preset("fr1")

    def rows(X):  # capture time of each point's image row after the stamp, 25 ms readout
        v = cam.fy * X[:, 1] / X[:, 2] + cam.cy
        return (v / cam.height - 0.5) * 0.025

    d0, d1 = rows(X0), rows(X1)
    B0, B1 = rolling_shutter_basis(G0, X0, d0), rolling_shutter_basis(G1, X1, d1)
    c = np.array([0.3, -0.2, 0.25, 0.02, -0.01, 0.03])

    def moved(X, d, err):
        return X + d[:, None] * (np.cross(err[:3], X) + err[3:])

    r = estimate_relative_pose(moved(X0, d0, -c / 2), moved(X1, d1, c / 2), Q0, Q1, initial=res.pose)
    actual = gtsam.Pose3.Logmap(res.pose.between(r.pose))
    expected = (B1 - B0) @ (c / 2)
    assert np.linalg.norm(actual - expected) < 0.05 * np.linalg.norm(expected)
    assert np.linalg.norm((B1 + B0) @ (c / 2)) < 0.2 * np.linalg.norm(expected)


def test_depth_period_jump_counts_the_whole_periods_the_depth_image_moved_by():
    """Colour and depth images on clocks 0.5 % apart, stamps jittered by 2 ms, each colour frame
    taking the depth image with the nearest stamp: from the stamps alone, the jump is the change of
    the true capture offset between two frames to within the clocks' drift, including where the
    association switches back and forth near half a period."""
    rng = np.random.default_rng(4)
    P, Pd, n = 1 / 30, 1.005 / 30, 600
    colour = np.arange(n) * P
    depth = rng.uniform(0, Pd) - Pd + np.arange(n + 3) * Pd
    colour_stamps, depth_stamps = colour + rng.normal(0, 0.002, n), depth + rng.normal(0, 0.002, n + 3)
    nearest = np.argmin(np.abs(depth_stamps[None, :] - colour_stamps[:, None]), axis=1)
    true_offset, stamped = depth[nearest] - colour, depth_stamps[nearest] - colour_stamps
    for gap in (1, 5):
        change = true_offset[gap:] - true_offset[:-gap]
        jumps = np.array([depth_period_jump(a, b, P) for a, b in zip(stamped[:-gap], stamped[gap:])])
        assert np.all(np.abs(jumps - change) <= (gap + 1) * (Pd - P) + 1e-9)  # the drift over the gap
        assert np.sum(np.abs(jumps) > P / 2) >= 10  # the association switched, both ways
        assert np.any(jumps > 0) and np.any(jumps < 0)
    assert depth_period_jump(0.004, 0.015, P) == 0.0  # the stamps' scatter alone is no jump
    assert depth_period_jump(0.016, -0.017, P) == pytest.approx(-P)
    assert depth_period_jump(0.0, 0.02, 0.0) == 0.0  # no period: no jump


def test_a_depth_image_a_period_away_moves_the_pair_by_the_jump_basis():
    """A camera turning at 1 rad/s: the reference frame's depths read 16.5 ms late and the current
    frame's 16.8 ms early (the nearest depth image switched to its neighbour between them). The
    estimate re-solved on the depths so read (gtsam's exponential map, not the rate formula) moves
    by (J/2)(u_cur - u_ref) plus the small common part; the jump part alone is most of it, and with
    the reference's sign turned or the half left out it is not."""
    rng = np.random.default_rng(2)
    camera = Camera.preset("fr3")
    uv = np.column_stack([rng.uniform(0, camera.width, 300), rng.uniform(0, camera.height, 300)])
    world = camera.backproject(uv, rng.uniform(1.0, 4.0, 300))  # the reference camera at t = 0
    twist, P = np.array([0.3, 1.0, -0.2, 0.05, 0.02, 0.1]), 1 / 30

    def seen(t, late=0.0):  # points in the camera at t, their depths read `late` s later, on the same rays
        X = np.array([gtsam.Pose3.Expmap(twist * t).transformTo(x) for x in world])
        Z = np.array([gtsam.Pose3.Expmap(twist * (t + late)).transformTo(x)[2] for x in world])
        return X / X[:, 2:3] * Z[:, None]

    X0, X1 = seen(0.0), seen(P)
    model = PointNoiseModel()
    Q0 = model.point_covariances(camera, camera.project(X0), X0[:, 2])
    Q1 = model.point_covariances(camera, camera.project(X1), X1[:, 2])
    T = gtsam.Pose3.Expmap(twist * P)
    G0, G1 = transfer_gains(T.rotation().matrix(), T.translation(), X0, X1, Q0, Q1)
    u_ref, u_cur = depth_time_basis(G0, X0, twist), depth_time_basis(G1, X1, twist)
    d_ref, d_cur = 0.0165, -0.0168
    J = depth_period_jump(d_ref, d_cur, P)
    assert J == pytest.approx(-P)
    base = estimate_relative_pose(X0, X1, Q0, Q1, initial=T)
    moved = estimate_relative_pose(seen(0.0, d_ref), seen(P, d_cur), Q0, Q1, initial=T)
    actual = gtsam.Pose3.Logmap(base.pose.between(moved.pose))
    jump = 0.5 * J * (u_cur - u_ref)
    common = 0.5 * (d_ref + d_cur) * (u_ref + u_cur)
    size = np.linalg.norm(actual)
    assert np.linalg.norm(actual[3:]) > 1e-3  # millimetres: the change is not negligible
    assert np.linalg.norm(actual - jump - common) < 0.02 * size
    assert np.linalg.norm(actual - jump) < 0.1 * size
    for wrong in (0.5 * J * (u_cur + u_ref), J * (u_cur - u_ref), 0.25 * J * (u_cur - u_ref)):
        assert np.linalg.norm(actual - wrong) > 0.4 * size


def _plane_depth(camera: Camera, pose: gtsam.Pose3, normal: np.ndarray, offset: float) -> np.ndarray:
    """Depth image (H, W; metres) of the plane ``normal . P = offset`` (world) seen from ``pose``
    (T_world,cam), rendered ray by ray: an oracle independent of the code's rate formulas."""
    v, u = np.mgrid[0:camera.height, 0:camera.width].astype(float)
    rays = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(u)], axis=-1)
    R, o = pose.rotation().matrix(), pose.translation()
    return (offset - normal @ o) / (rays @ (R.T @ normal))


def test_depth_read_change_is_what_a_later_depth_image_reads_at_the_pixel():
    """A slanted wall and a camera turning at 1 rad/s: the depth image rendered 16.7 ms later, read
    at the same pixels, differs from the first by what depth_read_change predicts (the point's own
    depth change and the image's change at the fixed pixel, to first order), not by the point's own
    change alone."""
    camera = Camera.preset("fr3")
    normal, offset = np.array([0.4, 0.1, 1.0]) / np.linalg.norm([0.4, 0.1, 1.0]), 2.5
    twist, shift = np.array([0.3, 1.0, -0.2, 0.05, 0.02, 0.1]), 1 / 60
    D0 = _plane_depth(camera, gtsam.Pose3(), normal, offset)
    D1 = _plane_depth(camera, gtsam.Pose3.Expmap(twist * shift), normal, offset)
    rng = np.random.default_rng(5)
    uv = np.column_stack([rng.integers(80, camera.width - 80, 300), rng.integers(80, camera.height - 80, 300)])
    uv = uv.astype(float)
    X = camera.backproject(uv, D0[uv[:, 1].astype(int), uv[:, 0].astype(int)])
    actual = D1[uv[:, 1].astype(int), uv[:, 0].astype(int)] - D0[uv[:, 1].astype(int), uv[:, 0].astype(int)]
    predicted = depth_read_change(D0, uv, X, twist, shift, camera.fx, camera.fy)
    own = depth_rates(X, twist) * shift
    rms = np.sqrt(np.mean(actual**2))
    assert rms > 0.01  # centimetres
    assert np.sqrt(np.mean((predicted - actual) ** 2)) < 0.1 * rms
    assert np.sqrt(np.mean((own - actual) ** 2)) > 0.3 * rms  # the image's own change matters
    hole = D0.copy()
    hole[:, :] = 0.0  # no depth to read: only the point's own change is left
    assert np.allclose(depth_read_change(hole, uv, X, twist, shift, camera.fx, camera.fy), own)


def test_consecutive_pairs_share_the_middle_frames_noise_as_the_cross_covariance_says():
    """Three frames, each measured once: the pairs (0, 1) and (1, 2) share frame 1's measured points,
    which move the first pair's twist as its current frame and the second's as its reference.
    Monte Carlo of the package's estimator: the cross-covariance of the two twists is
    ``shared_frame_covariance``, and the change of the twist from one pair to the next has the
    noise ``N_b + A N_a A^T - A X - X^T A^T`` (about 1.5 times what independent twists give)."""
    from covo_gtsam.calibration import _change_and_noise
    from covo_gtsam.frame_errors import shared_frame_covariance

    rng = np.random.default_rng(11)
    scene = make_scene(SimulationConfig(num_points=150, motion=SMALL_MOTION), rng)
    T = scene.T01
    X0, X1 = scene.X0, scene.X1
    X2 = (X1 - T[:3, 3]) @ T[:3, :3]  # the same motion again: frame 2 = frame 1 moved by T01
    ok = X2[:, 2] > 0.5
    X0, X1, X2 = X0[ok], X1[ok], X2[ok]
    model, dt = PointNoiseModel(), 1 / 30
    Q = [model.point_covariances(scene.camera, scene.camera.project(X), X[:, 2]) for X in (X0, X1, X2)]
    Ga = transfer_gains(T[:3, :3], T[:3, 3], X0, X1, Q[0], Q[1])
    Gb = transfer_gains(T[:3, :3], T[:3, 3], X1, X2, Q[1], Q[2])
    idx = np.arange(len(X1))
    cross = shared_frame_covariance(idx, Ga[1] / dt, idx, Gb[0] / dt, Q[1])
    xa, xb = [], []
    for _ in range(500):
        (Y0, R0), (Y1, R1), (Y2, R2) = (noisy_measurements(X, scene.camera, model, rng) for X in (X0, X1, X2))
        xa.append(gtsam.Pose3.Logmap(estimate_relative_pose(Y0, Y1, R0, R1).pose) / dt)
        xb.append(gtsam.Pose3.Logmap(estimate_relative_pose(Y1, Y2, R1, R2).pose) / dt)
    xa, xb = np.array(xa), np.array(xb)
    emp_cross = (xa - xa.mean(0)).T @ (xb - xb.mean(0)) / (len(xa) - 1)
    scale = np.sqrt(np.outer(np.diag(np.cov(xa.T)), np.diag(np.cov(xb.T))))
    assert np.abs(emp_cross - cross).max() / scale.max() < 0.12  # the correlations agree
    assert np.abs(cross).max() / scale.max() > 0.3  # and are far from zero
    Na = np.einsum("nij,njk,nlk->il", Ga[0], Q[0], Ga[0]) + np.einsum("nij,njk,nlk->il", Ga[1], Q[1], Ga[1])
    Nb = np.einsum("nij,njk,nlk->il", Gb[0], Q[1], Gb[0]) + np.einsum("nij,njk,nlk->il", Gb[1], Q[2], Gb[1])
    Ad = gtsam.Pose3(T).inverse().AdjointMap()
    change = xb - xa @ Ad.T
    emp = np.trace(np.cov(change.T)[:3, :3])
    with_cross = np.trace(_change_and_noise(T, xa[0], xb[0], Na / dt**2, Nb / dt**2, cross)[1][:3, :3])
    independent = np.trace(_change_and_noise(T, xa[0], xb[0], Na / dt**2, Nb / dt**2)[1][:3, :3])
    assert 0.9 < emp / with_cross < 1.1
    assert emp / independent > 1.3
