"""The frame clock learnt from stamps, and relative poses moved from capture times to stamps."""

import gtsam
import numpy as np
import pytest

from covo_gtsam.clock import FrameClock, restamp


def _stamps(rng, n=200, period=1 / 29.5, jitter=0.002, drop_every=None):
    k = np.arange(n)
    if drop_every:
        k = k[k % drop_every != 0]  # dropped frames
    offsets = rng.normal(0.0, jitter, len(k))
    return 1305031102.0 + k * period + offsets, offsets


@pytest.mark.parametrize("drop_every", [None, 7])
def test_clock_recovers_period_and_each_stamps_offset(drop_every):
    rng = np.random.default_rng(0)
    stamps, offsets = _stamps(rng, drop_every=drop_every)
    clock = FrameClock(1 / 30)
    got = np.array([np.nan if (r := clock.offset(t)) is None else r for t in stamps])
    # no offsets before 20 stamps: a fit to fewer invents offsets when the period is not the nominal
    assert np.isnan(got[:19]).all() and not np.isnan(got[19:]).any()
    # a camera running at 29.5 Hz, not its nominal 30 Hz; the fit over 60 stamps with 2 ms jitter
    # has a standard error of about 15 us
    assert clock.period_s == pytest.approx(1 / 29.5, abs=6e-5)
    # the fit's phase absorbs the mean offset of its window; what remains of each stamp's offset
    # is found to within the phase's uncertainty (2 ms / sqrt(60) = 0.26 ms)
    late = slice(60, None)
    resid = got[late] - (offsets[late] - np.mean(offsets[late]))
    assert np.std(resid) < 0.5e-3
    assert np.corrcoef(got[late], offsets[late])[0, 1] > 0.95
    assert clock.samples == 60


def test_clock_gives_no_offset_without_a_regular_clock_and_restarts_after_a_gap():
    rng = np.random.default_rng(1)
    irregular = np.cumsum(rng.uniform(0.005, 0.2, 100))
    clock = FrameClock(1 / 30)
    got = [clock.offset(t) for t in irregular]
    assert sum(r is not None for r in got) < 0.2 * len(got)
    clock = FrameClock(1 / 30)
    for t in np.arange(30) / 30:
        clock.offset(t)
    assert clock.offset(1e6) is None  # beyond any count of frames: starts over
    again = [clock.offset(1e6 + i / 30) for i in range(1, 20)]
    assert all(r is None for r in again[:18]) and again[18] is not None
    assert clock.offset(1e300) is None  # no overflow


def test_clock_invents_no_offsets_for_a_camera_off_its_nominal_rate():
    """Exactly regular stamps of a 29.5 Hz camera, nominal 30 Hz: every offset is 0."""
    clock = FrameClock(1 / 30)
    got = [clock.offset(t) for t in np.arange(100) / 29.5]
    assert all(r is None for r in got[:19])
    assert max(abs(r) for r in got[19:]) < 1e-9


def test_restamp_gives_the_motion_between_the_stamps():
    """Constant body twist: the camera at time t is Exp(t xi). Restamping the motion between the
    captures with each frame's offset gives exactly the motion between the stamps."""
    xi = np.array([0.4, -1.1, 0.3, 0.1, -0.05, 0.2])
    c_ref, c_cur, r_ref, r_cur = 0.0, 1 / 30, 0.003, -0.002
    pose = lambda t: gtsam.Pose3.Expmap(t * xi)  # noqa: E731
    T_capture = pose(c_ref).between(pose(c_cur))
    T, Ad = restamp(T_capture, r_ref * xi, r_cur * xi)
    T_stamps = pose(c_ref + r_ref).between(pose(c_cur + r_cur))
    np.testing.assert_allclose(T.matrix(), T_stamps.matrix(), atol=1e-12)
    # the covariance follows the right perturbation: sample, restamp, measure
    rng = np.random.default_rng(2)
    C = np.diag([1e-4, 2e-4, 1e-4, 4e-4, 1e-4, 9e-4])
    L = np.linalg.cholesky(C)
    errs = [gtsam.Pose3.Logmap(T.between(restamp(T_capture.compose(gtsam.Pose3.Expmap(L @ rng.normal(size=6))),
                                                 r_ref * xi, r_cur * xi)[0])) for _ in range(20000)]
    emp = np.cov(np.array(errs).T)
    np.testing.assert_allclose(emp, Ad @ C @ Ad.T, atol=0.03 * C.max())


@pytest.mark.slow
def test_repeated_stamp_with_the_clock_gives_no_velocity(sample_dir):
    """A frame that repeats the previous frame's stamp, once the clock is running: tracked, with no
    velocity (no interval to divide by) and a finite covariance; the next frame tracks as usual."""
    from covo_gtsam.datasets.tum import TumSequence
    from covo_gtsam.odometry import VisualOdometry

    seq = TumSequence(sample_dir)
    vo = VisualOdometry(seq.camera)
    frames = [seq.load(i) for i in range(27)]
    steps = [vo.register_frame(*frames[i], float(seq.timestamps[i])) for i in range(25)]
    assert steps[-1].clock_samples > 0
    repeat = vo.register_frame(*frames[25], float(seq.timestamps[24]))
    assert repeat.status == "tracked" and repeat.velocity is None
    assert np.all(np.isfinite(repeat.covariance))
    assert np.linalg.norm(gtsam.Rot3.Logmap(repeat.relative.rotation())) < 0.1
    after = vo.register_frame(*frames[26], float(seq.timestamps[26]))
    assert after.status == "tracked" and after.velocity is not None
    assert np.linalg.norm(after.velocity[:3]) < 10  # rad/s: a hand-held camera, not 1/dt of a stamp glitch


@pytest.mark.parametrize("keyframes", [False, True])
def test_each_frame_is_moved_to_its_stamp_once_along_the_trajectory(sample_dir, keyframes):
    """World poses at the stamps are the poses at the captures (the chain of each pair's estimate
    between its two captures) with each frame moved once, by its own ``stamp_shift`` along its
    ``stamp_twist``: a pair moves its reference frame exactly as that frame's own pair moved it,
    also where the frame clock places its first frame (whose reference it has not placed). (The
    rolling-shutter look-ahead, which moves a pair's pose once more one frame late, is off here.)"""
    from covo_gtsam.datasets.tum import TumSequence
    from covo_gtsam.odometry import OdometryConfig, VisualOdometry

    seq = TumSequence(sample_dir)
    vo = VisualOdometry(seq.camera, OdometryConfig().replace(tracking={"keyframes": keyframes},
                                                             sensor={"rolling_shutter_look_ahead": False}))
    captured, moved = {}, 0
    for i in range(28):
        step = vo.register_frame(*seq.load(i), float(seq.timestamps[i]))
        assert step.has_pose
        if not step.has_relative_pose:
            captured[step.timestamp] = gtsam.Pose3()
            continue
        captured[step.timestamp] = captured[step.ref_timestamp].compose(step.result.pose)
        shift = np.zeros(6) if step.stamp_shift is None else step.stamp_shift * step.stamp_twist
        at_stamp = captured[step.timestamp].compose(gtsam.Pose3.Expmap(shift))
        np.testing.assert_allclose(step.pose.matrix(), at_stamp.matrix(), atol=1e-9)
        if step.stamp_shift is not None:
            moved += 1
            assert step.stamp_shift == step.clock_offset and step.clock_samples > 0
        else:
            assert step.clock_samples == 0  # here every frame the clock placed is moved
    assert moved >= 5
