"""The realistic simulation driven by a recorded motion (:class:`RecordedMotion`), checked against a
motion known in closed form."""

import dataclasses

import gtsam
import numpy as np
import pytest

from covo_gtsam.errors import InputError
from covo_gtsam.io import write_tum_trajectory
from covo_gtsam.sequence_simulation import RecordedMotion, SequenceSimulationConfig, simulate_sequence

START = gtsam.Pose3(gtsam.Rot3.RzRyRx(0.4, -0.3, 1.2), gtsam.Point3(1.0, -2.0, 0.5))


def true_pose(t: float) -> gtsam.Pose3:
    """A hand-held-like motion in closed form, T_world,cam(t), starting at ``START``."""
    w = np.array([0.3 * np.sin(2 * np.pi * 0.5 * t), 0.2 * np.sin(2 * np.pi * 0.7 * t + 1) - 0.2 * np.sin(1),
                  0.1 * t])
    p = np.array([0.1 * np.sin(t), 0.05 * (np.cos(1.3 * t) - 1), 0.02 * t])
    return START.compose(gtsam.Pose3(gtsam.Rot3.Expmap(w), p))


def recording(duration: float = 4.0, rate: float = 100.0, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Samples of :func:`true_pose` at ``rate`` Hz with a little scatter of the stamps, from t = 0."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, duration, 1 / rate) + rng.uniform(-1e-4, 1e-4, int(duration * rate))
    t[0] = 0.0
    return t + 1000.0, np.array([true_pose(x).matrix() for x in t])


def angle_between(a: gtsam.Pose3, b: gtsam.Pose3) -> tuple[float, float]:
    d = a.between(b)
    return float(np.linalg.norm(gtsam.Rot3.Logmap(d.rotation()))), float(np.linalg.norm(d.translation()))


def test_recorded_motion_follows_the_recording_between_its_samples():
    """Unsmoothed, the interpolated motion is the recorded one relative to the pose at ``start``,
    also half-way between samples (resampled evenly and cubic Hermite: errors below a tenth of a
    milliradian for a hand's motion sampled at 100 Hz, against a reference's jitter of about one),
    and ``in_camera`` puts a world point where the pose does."""
    stamps, poses = recording()
    motion = RecordedMotion(stamps, poses, start=0.5, smooth_s=0.0)
    t0 = stamps[np.searchsorted(stamps, stamps[0] + 0.5)] - 1000.0  # the first sample at or after the start
    assert motion.span[0] == pytest.approx(-t0, abs=1e-3) and motion.span[1] == pytest.approx(4.0 - t0, abs=0.02)
    origin = true_pose(t0)
    for t in (0.0, 0.005, 1.234, 2.9999):
        want = origin.between(true_pose(t0 + t))
        rot, trans = angle_between(motion.pose(t), want)
        assert rot < 1e-4 and trans < 1e-5, t  # resampled evenly: linear between the scattered stamps
    rng = np.random.default_rng(1)
    points, times = rng.uniform(-2, 2, (20, 3)), rng.uniform(0, 3, 20)
    expected = np.array([motion.pose(t).transformTo(p) for p, t in zip(points, times)])
    np.testing.assert_allclose(motion.in_camera(points, times), expected, atol=1e-12)


def test_smoothing_takes_out_the_recordings_jitter():
    """White jitter on each sample (0.1 deg, 0.1 mm, as a motion-capture reference's) is mostly
    taken out by the default smoothing (20 ms), while the motion itself is kept."""
    stamps, poses = recording()
    rng = np.random.default_rng(2)
    noisy = np.array([(gtsam.Pose3(P).compose(gtsam.Pose3.Expmap(np.r_[rng.normal(0, np.deg2rad(0.1), 3),
                                                                       rng.normal(0, 1e-4, 3)]))).matrix()
                      for P in poses])
    raw, smooth = RecordedMotion(stamps, noisy, smooth_s=0.0), RecordedMotion(stamps, noisy)
    dt = 1 / 30  # the motion over a frame interval (free of the start sample's own jitter)
    t = np.arange(0.1, 3.8, 0.0137)
    want = [true_pose(x).between(true_pose(x + dt)) for x in t]
    rms = {}
    for name, m in (("raw", raw), ("smooth", smooth)):
        err = np.array([angle_between(m.pose(x).between(m.pose(x + dt)), w) for x, w in zip(t, want)])
        rms[name] = np.sqrt(np.mean(err**2, axis=0))
    assert rms["raw"][0] > np.deg2rad(0.1)
    assert rms["smooth"][0] < 0.5 * rms["raw"][0] and rms["smooth"][1] < 0.5 * rms["raw"][1]


def test_a_steady_motion_passes_unchanged_to_the_ends():
    """A constant turn and a constant velocity are kept exactly by the smoothing, also at the
    recording's ends (odd reflection), and a time outside the recording is refused."""
    t = np.arange(0.0, 2.0, 0.01)
    axis = np.array([0.6, -0.8, 0.0])
    poses = np.array([gtsam.Pose3(gtsam.Rot3.Expmap(1.0 * x * axis), np.array([0.3, 0.0, -0.1]) * x).matrix()
                      for x in t])
    motion = RecordedMotion(t, poses, smooth_s=0.02)
    for x in (0.0, 0.003, 0.5, 1.985, 1.99):
        want = gtsam.Pose3(gtsam.Rot3.Expmap(1.0 * x * axis), np.array([0.3, 0.0, -0.1]) * x)
        rot, trans = angle_between(motion.pose(x), want)
        assert rot < 1e-9 and trans < 1e-10, x
    with pytest.raises(InputError, match="known from"):
        motion.pose(2.5)
    with pytest.raises(InputError, match="known from"):
        motion.in_camera(np.zeros((1, 3)), np.array([-0.01]))


def test_a_gap_in_the_recording_is_bridged_and_reported():
    """Samples missing for 130 ms (as in fr1_rpy's reference): the gap is listed, and the motion
    across it is the straight line the unsmoothed samples on either side span (no spike)."""
    stamps, poses = recording()
    keep = (stamps - 1000.0 < 1.0) | (stamps - 1000.0 > 1.13)
    motion = RecordedMotion(stamps[keep], poses[keep], smooth_s=0.0)
    np.testing.assert_allclose(motion.gaps, [stamps[keep][stamps[keep] - 1000.0 < 1.0][-1] - 1000.0], atol=1e-9)
    a, b = motion.pose(0.995).translation(), motion.pose(1.135).translation()
    mid = motion.pose(1.065).translation()
    assert np.linalg.norm(mid - 0.5 * (a + b)) < 2e-4


def test_recorded_motion_refuses_what_it_cannot_represent():
    stamps, poses = recording(duration=0.5)
    with pytest.raises(InputError, match="ends before"):
        RecordedMotion(stamps, poses, start=0.6)
    with pytest.raises(InputError, match="must differ"):
        RecordedMotion(np.r_[stamps, stamps[-1]], np.concatenate([poses, poses[-1:]]))
    t = np.arange(0.0, 2.0, 0.01)  # a turn about z at 3 rad/s passes 180 deg after about a second
    spin = np.array([gtsam.Pose3(gtsam.Rot3.Rz(3.0 * x), np.zeros(3)).matrix() for x in t])
    with pytest.raises(InputError, match="beyond 180 deg"):
        RecordedMotion(t, spin, smooth_s=0.0)
    spin[5, 0, 3] = np.nan
    with pytest.raises(InputError, match="finite"):
        RecordedMotion(t, spin)


def test_the_scene_surrounds_the_start_when_asked():
    """Beyond 90 deg the scene's points lie all around the start, some behind it; by default within
    70 deg of its optical axis, all in front."""
    from covo_gtsam.sequence_simulation import _world_points

    front = _world_points(np.random.default_rng(0), 4000)
    around = _world_points(np.random.default_rng(0), 4000, 180.0)
    r = np.linalg.norm(front, axis=1)
    assert np.all(front[:, 2] >= np.cos(np.deg2rad(70)) * r - 1e-12)
    assert len(around) == 4000 and np.mean(around[:, 2] < 0) == pytest.approx(0.5, abs=0.05)
    assert np.all((np.linalg.norm(around, axis=1) >= 1.0) & (np.linalg.norm(around, axis=1) <= 4.0))


def test_simulation_runs_on_a_recorded_motion(tmp_path):
    """The simulated sequence follows the recorded motion: the odometry's pairs are consistent with
    their truth (the per-point model told the true noise, no other error source), and a recording
    too short for the frames asked for is refused before any frame is made."""
    stamps, poses = recording(duration=3.0)
    path = tmp_path / "motion.txt"
    write_tum_trajectory(path, stamps, poses)
    cfg = SequenceSimulationConfig(frames=60, seed=0, motion_file=str(path), motion_start_s=0.2, motion_smooth_s=0.0,
                                   stamp_jitter_s=0.0,
                                   readout_s=0.0, depth_offset_s=(0.0, 0.0), depth_scale_sigma=0.0, bad_frame_rate=0.0,
                                   period_s=1 / 30)
    odometry = cfg.odometry_defaults().replace(noise={"pixel_sigma": 1.0, "depth_sigma_scale": 1.0}, sensor={
        "frame_sigma_rot_deg": 0.0, "frame_sigma_trans_m": 0.0, "depth_drift_pairs": 0, "latency_sigma_s": 0.0,
        "rolling_shutter_factor": 0.0, "stamp_jitter_s": 0.0, "depth_time_factor": 0.0,
        "depth_time_coherent_factor": 0.0, "depth_scale_sigma": 0.0})
    result = simulate_sequence(cfg, odometry)
    assert result.lost == 0 and len(result.errors) == 59
    nt, nr = result.nees()
    assert 1.5 < nt.mean() < 5.0 and 1.5 < nr.mean() < 5.0
    # the truth is the recorded motion: the pairs' true turns are those of the closed form
    turn = np.linalg.norm([gtsam.Rot3.Logmap(gtsam.Pose3(T).rotation()) for T in result.capture_truth], axis=1)
    t0 = stamps[np.searchsorted(stamps, stamps[0] + 0.2)] - 1000.0
    want = [angle_between(true_pose(t0 + k / 30), true_pose(t0 + (k + 1) / 30))[0] for k in range(59)]
    np.testing.assert_allclose(turn, want, atol=2e-5)
    with pytest.raises(InputError, match="need the motion"):
        simulate_sequence(dataclasses.replace(cfg, frames=90), odometry)
    with pytest.raises(InputError, match="need the motion"):  # the first frame's rows begin before the recording
        simulate_sequence(dataclasses.replace(cfg, motion_start_s=0.0, readout_s=0.02), odometry)
