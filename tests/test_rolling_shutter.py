"""Rolling-shutter compensation: row timing convention, first-order point transfer, effect on a
simulated pair, and the odometry's use of it on real frames."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from covo_gtsam.camera import Camera
from covo_gtsam.estimator import estimate_relative_pose
from covo_gtsam.rolling_shutter import compensate_points, frame_twists, row_time_offsets

TWIST = np.array([0.4, -0.9, 0.3, 0.05, -0.02, 0.04])  # [ω rad/s, v m/s], a fast hand-held turn
READOUT = 0.025
CAM = Camera.preset("fr1")


def test_row_times_middle_row_at_timestamp_lower_rows_later():
    d = row_time_offsets(np.array([0.0, 240.0, 480.0]), 480, READOUT)
    np.testing.assert_allclose(d, [-READOUT / 2, 0.0, READOUT / 2])


def observe(X_t: np.ndarray, twist: np.ndarray, readout: float) -> tuple[np.ndarray, np.ndarray]:
    """Points seen by a rolling-shutter camera: each in the camera frame at its own row's time.

    A point is captured when the row it projects to is read out; the row depends on that time,
    so the fixed point is found by iteration. Returns the points X_δ (N, 3) and their rows v (N,).
    """
    v = CAM.project(X_t)[:, 1]
    for _ in range(20):
        d = row_time_offsets(v, CAM.height, readout)
        X_d = np.array([gtsam.Pose3.Expmap(di * twist).transformTo(x) for di, x in zip(d, X_t)])
        v = CAM.project(X_d)[:, 1]
    return X_d, v


def scene(n: int = 300, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    uv = rng.uniform([20, 20], [620, 460], (n, 2))
    return CAM.backproject(uv, rng.uniform(0.8, 3.5, n))


def test_compensation_moves_points_to_the_image_timestamp():
    X_t = scene()
    X_d, v = observe(X_t, TWIST, READOUT)
    before = np.linalg.norm(X_d - X_t, axis=1)
    after = np.linalg.norm(compensate_points(X_d, v, TWIST, CAM.height, READOUT) - X_t, axis=1)
    assert before.max() > 5e-3  # the effect is millimetres to centimetres
    # only the second-order remainder is left: relative size about max|δ| |ω|
    assert after.max() < READOUT / 2 * np.linalg.norm(TWIST[:3]) * before.max()
    # no motion or no readout time: nothing moves
    np.testing.assert_array_equal(compensate_points(X_d, v, np.zeros(6), CAM.height, READOUT), X_d)
    np.testing.assert_array_equal(compensate_points(X_d, v, TWIST, CAM.height, 0.0), X_d)


def test_compensated_pair_recovers_the_motion():
    """Two rolling-shutter frames 1/30 s apart while the camera's turn reverses (different
    twists at the two frames; under equal twists the skews of the two images nearly cancel):
    without compensation the estimate is off by the skew; with it, by the remainder only."""
    twist_k1 = np.array([-0.6, 0.5, -0.2, -0.03, 0.02, 0.0])
    T = gtsam.Pose3.Expmap(1 / 30 * 0.5 * (TWIST + twist_k1))  # T_k,k1
    X_k = scene(seed=1)
    X_k1 = np.array([T.transformTo(x) for x in X_k])
    Xd_k, v_k = observe(X_k, TWIST, READOUT)
    Xd_k1, v_k1 = observe(X_k1, twist_k1, READOUT)
    Q = np.tile(np.eye(3) * 1e-6, (len(X_k), 1, 1))

    def error(A, B):
        E = T.between(estimate_relative_pose(A, B, Q, Q).pose)
        return np.linalg.norm(gtsam.Rot3.Logmap(E.rotation())), np.linalg.norm(E.translation())

    raw = error(Xd_k, Xd_k1)
    fixed = error(compensate_points(Xd_k, v_k, TWIST, CAM.height, READOUT),
                  compensate_points(Xd_k1, v_k1, twist_k1, CAM.height, READOUT))
    assert raw[0] > np.deg2rad(0.1)  # the skew biases the rotation by a tenth of a degree or more
    assert fixed[0] < 0.02 * raw[0] and fixed[1] < 0.02 * raw[1] + 1e-6


def test_pair_twists_current_from_the_pose_reference_averaged():
    """frame_twists: the current frame gets Log(T)/dt, the reference the mean with its own twist."""
    T, dt, prev = gtsam.Pose3.Expmap(TWIST / 30), 1 / 30, np.array([0.2, 0.1, -0.3, 0.0, 0.01, 0.02])
    twist_ref, twist_cur = frame_twists(T, dt, prev)
    np.testing.assert_allclose(twist_cur, TWIST, atol=1e-12)
    np.testing.assert_allclose(twist_ref, 0.5 * (TWIST + prev), atol=1e-12)
    twist_ref, _ = frame_twists(T, dt)
    np.testing.assert_allclose(twist_ref, TWIST, atol=1e-12)


@pytest.mark.slow
def test_odometry_compensation_on_real_frames(sample_dir):
    """On the sample's fast turn, compensation changes the relative poses (by far less than the
    motion) and stores each tracked frame's twist; with readout 0 the old path runs unchanged."""
    from covo_gtsam.datasets.tum import TumSequence
    from covo_gtsam.odometry import OdometryConfig, VisualOdometry

    seq = TumSequence(sample_dir)
    frames = [(*seq.load(i), seq.timestamps[i]) for i in range(12)]
    runs = {}
    for readout in (0.0, 0.025):
        # without the frame clock, relative poses stay between the captures (velocity = Log(T) / dt)
        # (and without the depth-drift correction and the look-ahead, which move the pose and not the twist)
        vo = VisualOdometry(seq.camera, OdometryConfig().replace(sensor={"rolling_shutter_s": readout,
                                                                         "frame_clock": False,
                                                                         "depth_drift_pairs": 0,
                                                                         "rolling_shutter_look_ahead": False}))
        runs[readout] = [vo.register_frame(*f) for f in frames][1:]
    for off, on in zip(runs[0.0], runs[0.025]):
        assert off.tracked and on.tracked
        dt = on.timestamp - on.ref_timestamp
        np.testing.assert_allclose(on.velocity, gtsam.Pose3.Logmap(on.relative) / dt, rtol=1e-12, atol=1e-12)
        moved = np.linalg.norm(gtsam.Rot3.Logmap(off.relative.rotation().between(on.relative.rotation())))
        motion = np.linalg.norm(gtsam.Rot3.Logmap(on.relative.rotation()))
        assert 0 < moved < 0.2 * motion



def test_odometry_compensates_with_the_ransac_pose_in_one_solve(sample_dir, monkeypatch):
    """With the outlier rejection's pose the twists come from it and each pair is solved once;
    without one (``outlier_rejection = "none"``, no prediction) the pair is solved, moved with that
    solution's twists and solved again. The points and pairs returned are those of the last solve
    (with the depth-lookup variance of the colour-depth offset)."""
    from covo_gtsam.datasets.tum import TumSequence
    from covo_gtsam.frontend import associate_frames
    from covo_gtsam.odometry import OdometryConfig, VisualOdometry

    seq = TumSequence(sample_dir)

    def solve_pair(rejection):
        vo = VisualOdometry(seq.camera, OdometryConfig().replace(frontend={"outlier_rejection": rejection}))
        ref, cur = (vo.prepare(*seq.load(i), depth_offset=0.02) for i in range(2))
        ref_step = vo.register_frame(ref, timestamp=seq.timestamps[0])
        calls, solve = [], vo._solve
        monkeypatch.setattr(vo, "_solve", lambda X_ref, X_cur, pairs, initial: calls.append(
            (X_ref, pairs, initial)) or solve(X_ref, X_cur, pairs, initial))
        pairs = associate_frames(ref, cur, vo.config.frontend)
        return pairs, vo._solve_pair(ref, ref_step, cur, pairs, seq.timestamps[1] - seq.timestamps[0],
                                     seq.timestamps[1], vo._depth_jump(ref, cur),
                                     (seq.timestamps[0], seq.timestamps[1])), calls

    pairs, (_, X_ref, _, solved, _), calls = solve_pair("rigid3d")
    assert len(calls) == 1 and calls[0][2] is not None  # one solve, from the RANSAC's pose
    assert calls[0][0] is X_ref and calls[0][1] is solved
    assert not np.array_equal(X_ref, pairs.X_ref) and np.all(solved.Q_ref[:, 2, 2] >= pairs.Q_ref[:, 2, 2])
    pairs, (_, X_ref, _, solved, _), calls = solve_pair("none")
    assert pairs.T_init is None and len(calls) == 2 and calls[0][2] is None and calls[1][2] is not None
    assert calls[0][1] is pairs and calls[1][0] is X_ref and calls[1][1] is solved
    assert not np.array_equal(X_ref, pairs.X_ref) and np.any(solved.Q_ref != pairs.Q_ref)
