"""The gyroscope: its conventions (axes, quaternion order, clock), the compensation of a turn that
changes within the readout, and its effect in the realistic simulation, where the truth is known."""

from __future__ import annotations

import dataclasses
import json

import gtsam
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from covo_gtsam.errors import DatasetError, InputError
from covo_gtsam.gyro import Gyroscope
from covo_gtsam.rolling_shutter import compensate_points, row_time_offsets
from covo_gtsam.sequence_simulation import SequenceSimulationConfig, simulate_sequence


def test_rotation_takes_the_gyroscopes_axes_into_the_cameras():
    """``rotation`` is R_cam_gyro as (qx, qy, qz, qw): a camera turning about its own axis ``w``
    reads ``R_gyro_cam w`` in the gyroscope's axes, and the gyroscope gives back ``w``. The oracle
    is SciPy's rotation (scalar-last quaternions), not covo's conversion."""
    R = Rotation.from_euler("zyx", [30, -50, 110], degrees=True)  # R_cam_gyro
    w_cam = np.array([0.3, -1.2, 0.7])
    t = np.linspace(0.0, 1.0, 11)
    rates = np.tile(R.inv().apply(w_cam), (len(t), 1))
    gyro = Gyroscope(t, rates, rotation=R.as_quat())
    np.testing.assert_allclose(gyro.angular_velocity(0.55), w_cam, atol=1e-12)
    wrong = Gyroscope(t, rates, rotation=R.inv().as_quat())  # the inverse rotation: not the camera's axes
    assert np.linalg.norm(wrong.angular_velocity(0.55) - w_cam) > 0.5
    np.testing.assert_allclose(Gyroscope(t, rates, rotation=R.as_matrix()).angular_velocity(0.3), w_cam, atol=1e-12)


def test_time_offset_puts_the_samples_on_the_frames_clock_and_velocity_is_linear_between_samples():
    t = np.array([0.0, 0.01, 0.02, 0.03])
    rates = np.column_stack([t * 10.0, -t, np.ones_like(t)])
    gyro = Gyroscope(t, rates, time_offset_s=0.5)
    np.testing.assert_allclose(gyro.angular_velocity(0.515), [0.15, -0.015, 1.0], atol=1e-12)
    assert gyro.span == (0.5, 0.53)


def test_angular_acceleration_is_the_slope_of_the_samples():
    """Exact for a linear ramp; near the truth under sample noise (MEMS-like 0.005 rad/s at 1 kHz)."""
    t = np.arange(0.0, 0.2, 0.001)
    alpha = np.array([12.0, -3.0, 30.0])
    gyro = Gyroscope(t, np.outer(t, alpha) + 0.2)
    np.testing.assert_allclose(gyro.angular_acceleration(0.1), alpha, rtol=1e-9)
    np.testing.assert_allclose(gyro.angular_acceleration(0.0), alpha, rtol=1e-9)  # at the first sample
    rng = np.random.default_rng(0)
    noisy = Gyroscope(t, np.outer(t, alpha) + rng.normal(0.0, 0.005, (len(t), 3)))
    assert np.abs(noisy.angular_acceleration(0.1) - alpha).max() < 2.0


def test_covers_needs_samples_around_the_readout_without_a_gap():
    t = np.concatenate([np.arange(0.0, 1.0, 0.005), np.arange(1.2, 2.0, 0.005)])
    gyro = Gyroscope(t, np.zeros((len(t), 3)))
    assert gyro.covers(0.5, 0.02) and gyro.covers(1.5, 0.02)
    assert not gyro.covers(1.0, 0.02)  # the 0.2 s gap
    assert not gyro.covers(0.01, 0.02) and not gyro.covers(1.99, 0.02)  # beyond the ends


@pytest.mark.parametrize("stamps, rates, kwargs, message", [
    ([0.0, 0.1], np.zeros((3, 3)), {}, "rates of shape"),
    ([0.0], np.zeros((1, 3)), {}, "at least 2"),
    ([0.0, 0.1, 0.1], np.zeros((3, 3)), {}, "must increase"),
    ([0.0, np.nan], np.zeros((2, 3)), {}, "finite"),
    ([0.0, 0.1], [[0, 0, 0], [0, np.inf, 0]], {}, "finite"),
    ([0.0, 0.1], np.zeros((2, 3)), {"rotation": np.diag([1.0, 1.0, -1.0])}, "rotation matrix"),
    ([0.0, 0.1], np.zeros((2, 3)), {"rotation": [0.0, 0.0, 0.0, 0.0]}, "unit"),
    ([0.0, 0.1], np.zeros((2, 3)), {"time_offset_s": 5.0}, "within 1 s"),
])
def test_bad_samples_are_refused_with_a_clear_error(stamps, rates, kwargs, message):
    with pytest.raises(InputError, match=message):
        Gyroscope(stamps, rates, **kwargs)


def test_file_reads_t_wx_wy_wz_and_names_a_bad_line(tmp_path):
    good = tmp_path / "gyro.txt"
    good.write_text("# gyroscope\n# t wx wy wz\n1.0 0.1 0.2 0.3\n1.005 0.1 0.2 0.3\n")
    gyro = Gyroscope.from_file(good, time_offset_s=-0.5)
    assert gyro.span == pytest.approx((0.5, 0.505), abs=1e-12)
    np.testing.assert_allclose(gyro.angular_velocity(0.502), [0.1, 0.2, 0.3])
    bad = tmp_path / "bad.txt"
    bad.write_text("1.0 0.1 0.2 0.3\n1.005 0.1 0.2\n")
    with pytest.raises(DatasetError, match=r"bad.txt:2: expected 4 values"):
        Gyroscope.from_file(bad)
    backwards = tmp_path / "backwards.txt"
    backwards.write_text("1.0 0 0 0\n0.9 0 0 0\n")
    with pytest.raises(DatasetError, match=r"backwards.txt: gyroscope: stamps must increase"):
        Gyroscope.from_file(backwards)


def _integrated(X: np.ndarray, d: np.ndarray, w0: np.ndarray, alpha: np.ndarray, steps: int = 400) -> np.ndarray:
    """Points seen at their rows' times ``d`` moved to the frame's time by integrating the turn
    ``w(s) = w0 + alpha s`` over ``[0, d]`` in small exponential steps (the oracle)."""
    out = np.empty_like(X)
    for i, (x, di) in enumerate(zip(X, d)):
        R = gtsam.Rot3()
        h = di / steps
        for k in range(steps):
            R = R.compose(gtsam.Rot3.Expmap((w0 + alpha * (k + 0.5) * h) * h))
        out[i] = R.matrix() @ x
    return out


@pytest.mark.parametrize("w0", [[0.2, -0.3, 0.1], [2.0, -4.5, 1.5]])
def test_compensation_with_the_angular_acceleration_follows_a_turn_that_changes_within_the_readout(w0):
    """Rows read over 35 ms while the turn speeds up by about 40 rad/s^2, from a slow and from a fast
    turn (5 rad/s, where the first-order rotation's own error is as large): the first-order
    compensation with the angular velocity at the frame misses the change, the gyroscope's form
    takes it (the oracle integrates the turn in small steps)."""
    rng = np.random.default_rng(1)
    v = rng.uniform(0, 480, 200)
    X = np.column_stack([rng.uniform(-1, 1, 200), rng.uniform(-1, 1, 200), rng.uniform(1, 4, 200)])
    w0, alpha = np.array(w0), np.array([-25.0, 30.0, 10.0])
    d = row_time_offsets(v, 480, 0.035)
    truth = _integrated(X, d, w0, alpha)
    twist = np.concatenate([w0, np.zeros(3)])
    first = compensate_points(X, v, twist, 480, 0.035)
    second = compensate_points(X, v, twist, 480, 0.035, alpha)
    err_first, err_second = (np.abs(Y - truth).max() for Y in (first, second))
    assert err_first > 1e-2 and err_second < 1e-3


def _readout_run(gyro_rate_hz: float, **changes):
    cfg = SequenceSimulationConfig(frames=100, seed=0, period_s=1 / 29.7, max_angular_speed=6.0, stamp_jitter_s=0.0,
                                   stamp_latency_s=0.0,
                                   depth_offset_s=(0.0, 0.0), depth_scale_sigma=0.0, bad_frame_rate=0.0,
                                   gyro_rate_hz=gyro_rate_hz, gyro_noise_rad_s=0.002)
    cfg = dataclasses.replace(cfg, **changes)
    # told the true point noise; no depth-drift correction (nothing drifts), which would move the poses
    told = cfg.odometry_defaults().replace(noise={"pixel_sigma": 1.0, "depth_sigma_scale": 1.0},
                                           sensor={"depth_drift_pairs": 0})
    return simulate_sequence(cfg, told)


def test_a_simulated_gyroscope_takes_out_most_of_the_compensations_error():
    """The readout the only error source, a fast turn (up to 6 rad/s), three seeds: with the pairs'
    twists the compensation misses the change of the turn around each frame; with the gyroscope's
    angular velocity at the frame the rotation error about the optical axis falls by a third or more
    (pooled over the seeds; 0.064 -> 0.026 deg on seed 0, 0.034 -> 0.026 and 0.036 -> 0.030 on seeds 1
    and 2, whose sines change less within a few frames) and no axis gets worse; the rolling-shutter
    term is then zero and the gyroscope's own part is in each pair's added covariance."""
    sq = np.zeros((2, 3))
    for seed in range(3):
        runs = (_readout_run(0.0, seed=seed), _readout_run(200.0, seed=seed))
        for k, q in enumerate(runs):
            sq[k] += np.mean(q.errors[q.consecutive][2:, :3] ** 2, axis=0)
    rms = np.sqrt(sq / 3)
    assert rms[1, 2] < 0.67 * rms[0, 2], rms
    assert np.all(rms[1] < 1.05 * rms[0]), rms
    without, with_gyro = runs
    assert np.all(with_gyro.bases["rolling_shutter"] == 0) and np.any(without.bases["rolling_shutter"] != 0)
    moving = with_gyro.consecutive.copy()
    moving[0] = False  # (the run's first pair: its reference frame has no capture time yet)
    assert np.all(np.trace(with_gyro.bases["gyro"][moving][:, :3, :3], axis1=1, axis2=2) > 0)
    assert np.all(without.bases["gyro"] == 0)


def test_a_gyroscope_that_misses_the_frames_leaves_the_pairs_twists(monkeypatch):
    """Samples that stop before the frames (no coverage): the run is that without a gyroscope."""
    from covo_gtsam import sequence_simulation as sim

    plain = _readout_run(0.0)
    original = sim._gyroscope

    def early(cfg, traj):
        g = original(cfg, traj)
        return Gyroscope(g.stamps - 100.0, g.rates)

    monkeypatch.setattr(sim, "_gyroscope", early)
    shifted = _readout_run(200.0)
    np.testing.assert_array_equal(shifted.errors, plain.errors)
    np.testing.assert_array_equal(shifted.covariances, plain.covariances)


def test_the_last_pair_a_gyroscope_covers_keeps_its_angular_velocity_when_the_next_pair_has_none(monkeypatch):
    """Samples that stop mid-run: the next frame's pair, compensated with the pairs' twists, settles
    the last pair the gyroscope covered by the look-ahead's translation part only, so that pair reads
    as in a run with the gyroscope throughout (its angular velocity at the frame is not replaced by
    the pairs'; replaced, it moves by 0.02 deg)."""
    from covo_gtsam import sequence_simulation as sim

    original = sim._gyroscope
    full = _readout_run(200.0)

    def stops(cfg, traj):
        g = original(cfg, traj)
        keep = g.stamps < 50 * cfg.period_s  # frame 49's readout covered, frame 50's not
        return Gyroscope(g.stamps[keep], g.rates[keep])

    monkeypatch.setattr(sim, "_gyroscope", stops)
    cut = _readout_run(200.0)
    k = int(np.flatnonzero(cut.frames[:, 1] == 49)[0])
    assert np.all(cut.frames[k:k + 2] == [[48, 49], [49, 50]])
    np.testing.assert_array_equal(cut.errors[:k + 1], full.errors[:k + 1])
    assert np.linalg.norm(cut.errors[k + 1] - full.errors[k + 1]) > 1e-4  # (50 is compensated without it)


def test_a_gyroscope_pairs_stamp_and_colour_depth_terms_take_its_angular_velocity_at_both_frames(monkeypatch):
    """Where the gyroscope covers a pair, the terms driven by the camera's twist at its frames
    (``timing``, ``stamp_jitter`` and the colour-depth terms) take the twists its rows were moved
    with, the gyroscope's angular velocity at each frame, as returned; when the next pair settles
    it, the current frame's is the one that pair moved the frame's rows with. (With the pairs'
    mean twists at return, the reference frame would keep them while the current frame took the
    gyroscope's at settling.)"""
    from covo_gtsam.odometry import VisualOdometry

    calls, used = [], []
    original_bases, original_solve = VisualOdometry._frame_twist_bases, VisualOdometry._solve_pair

    def frame_twist_bases(self, terms, twist_cur):
        calls.append((terms, np.array(twist_cur)))
        return original_bases(self, terms, twist_cur)

    def solve_pair(self, *args):
        out = original_solve(self, *args)
        used.append(out[4])
        return out

    monkeypatch.setattr(VisualOdometry, "_frame_twist_bases", frame_twist_bases)
    monkeypatch.setattr(VisualOdometry, "_solve_pair", solve_pair)
    _readout_run(200.0, frames=30)
    measured = [c for c in used if c is not None and c.measured]
    assert len(measured) >= 25
    returned = [(terms, tw) for terms, tw in calls
                if any(np.array_equal(terms.twist_ref, c.twist_ref) for c in measured)]
    assert len(returned) >= 25
    for terms, twist_cur in returned:
        c = next(c for c in measured if np.array_equal(terms.twist_ref, c.twist_ref))
        assert any(np.array_equal(twist_cur, x) for x in (c.twist_cur, *(m.twist_ref for m in measured)))
    # as returned, the current frame's twist is the gyroscope-compensated one of the pair itself
    assert sum(any(np.array_equal(tw, c.twist_cur) for c in measured) for _, tw in returned) >= 25


def _reference_gyro(sample_dir, path, smooth_s: float = 0.02) -> None:
    """A gyroscope file from a sequence's ground truth: the angular velocity of its motion smoothed
    over ``smooth_s``, at 200 Hz, on the ground truth's clock (which TUM aligns with the frames')."""
    from covo_gtsam.io import load_tum_trajectory
    from covo_gtsam.sequence_simulation import RecordedMotion

    gt = sample_dir / "groundtruth.txt"
    motion = RecordedMotion.from_tum(gt, 0.0, smooth_s)
    first = float(load_tum_trajectory(gt)[0][0])
    t = np.arange(motion.span[0] + 0.01, motion.span[1] - 0.01, 0.005)
    np.savetxt(path, np.column_stack([t + first, motion.angular_velocity(t)]), fmt="%.6f")


def test_covo_run_with_a_gyroscope_file(sample_dir, tmp_path, capsys):
    """``covo run --gyro FILE``: every pair whose readouts the samples cover is compensated with them,
    metrics.json says how many, and each pair's covariance holds the gyroscope's term
    (``sensor.gyro_sigma_rad_s``) in place of the rolling-shutter term; the settings of the
    gyroscope without a file are refused in one line."""
    from covo_gtsam.cli import main

    _reference_gyro(sample_dir, tmp_path / "gyro.txt")
    base = ["run", str(sample_dir), "--max-frames", "12", "--no-plots", "--quiet"]
    assert main([*base, "--out", str(tmp_path / "g"), "--gyro", str(tmp_path / "gyro.txt")]) == 0
    m = json.loads((tmp_path / "g" / "metrics.json").read_text())
    assert m["gyro"]["pairs"] == m["nees_pairs"] == 11
    assert ("note: the sensor terms are the defaults, fitted without a gyroscope; 11 pairs were compensated"
            in capsys.readouterr().out)
    assert m["covariance_parts"]["rotation"]["gyro"] > 0 and m["covariance_parts"]["rotation"]["rolling_shutter"] == 0
    assert main([*base, "--out", str(tmp_path / "plain")]) == 0
    plain = json.loads((tmp_path / "plain" / "metrics.json").read_text())
    assert "gyro" not in plain and plain["covariance_parts"]["rotation"]["rolling_shutter"] > 0
    capsys.readouterr()
    assert main([*base, "--out", str(tmp_path / "x"), "--gyro-rotation", "0", "0", "0", "1"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--gyro-rotation needs --gyro FILE" in err[0]
    (tmp_path / "bad.txt").write_text("1 2 3\n")
    assert main([*base, "--out", str(tmp_path / "y"), "--gyro", str(tmp_path / "bad.txt")]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "bad.txt:1: expected 4 values" in err[0]


def test_latency_basis_of_a_gyroscope_pair_is_the_change_of_the_turn_both_stamps_late_would_make(sample_dir):
    """Both frames of a pair stamped ``L`` late put the pair at ``T Exp(L b)`` (right perturbation);
    with a gyroscope the latency term's rotation basis is ``c c^T`` for the measured change ``c``. The
    oracle is the motion the stand-in gyroscope was made from: ``b = Log(R(t_ref)^T R(t_cur))``'s change
    when both times move by ``L``, over ``L``: the gyroscope's rates at the two captures, in the current
    frame's axes (the axes' convention is :func:`~covo_gtsam.calibration.twist_change`'s, checked on its
    own; on this motion, which turns about its angular velocity, the other convention errs by 1-2 % more)."""
    from covo_gtsam.config import OdometryConfig
    from covo_gtsam.datasets.tum import TumSequence
    from covo_gtsam.io import load_tum_trajectory
    from covo_gtsam.odometry import VisualOdometry
    from covo_gtsam.sequence_simulation import RecordedMotion

    gt = sample_dir / "groundtruth.txt"
    motion = RecordedMotion.from_tum(gt, 0.0, 0.02)
    first = float(load_tum_trajectory(gt)[0][0])
    t = np.arange(motion.span[0] + 0.01, motion.span[1] - 0.01, 0.002)
    gyro = Gyroscope(t + first, motion.angular_velocity(t))
    seq = TumSequence(sample_dir)
    # the frame clock off, so that a frame's capture is its stamp, where the oracle takes it
    vo = VisualOdometry(seq.camera, OdometryConfig().replace(sensor={"frame_clock": False}), gyro=gyro)
    L, errors = 1e-3, []
    for i in range(12):
        step = vo.register_frame(*seq.load(i), seq.timestamps[i], depth_timestamp=seq.depth_timestamps[i])
        if step.error_bases is None or "gyro" not in step.error_bases:
            continue
        a, b = step.ref_timestamp - first, step.timestamp - first

        def turn(shift, a=a, b=b):
            return motion.pose(a + shift).rotation().between(motion.pose(b + shift).rotation())

        change = gtsam.Rot3.Logmap(turn(0.0).between(turn(L))) / L
        w, U = np.linalg.eigh(step.error_bases["latency"][:3, :3])
        c = U[:, -1] * np.sqrt(w[-1])
        errors.append(min(np.linalg.norm(c - change), np.linalg.norm(c + change)) / np.linalg.norm(change))
    # (a few per cent: the estimate's turn in place of the true one, the gyroscope read between samples; read a
    # frame interval off, half to three times the change)
    assert len(errors) >= 8 and np.median(errors) < 0.05 and max(errors) < 0.1, errors
    # the gyroscope's noise comes off the measured change: at 10 rad/s of it nothing is left
    noisy = VisualOdometry(seq.camera, OdometryConfig().replace(sensor={"frame_clock": False,
                                                                       "gyro_sigma_rad_s": 10.0}), gyro=gyro)
    steps = [noisy.register_frame(*seq.load(i), seq.timestamps[i], depth_timestamp=seq.depth_timestamps[i])
             for i in range(6)]
    latency = [s.error_bases["latency"] for s in steps if s.error_bases is not None and "gyro" in s.error_bases]
    assert len(latency) >= 4 and np.all(np.array(latency) == 0)


def test_keyframe_pairs_keep_the_pairs_twists(sample_dir, tmp_path, capsys):
    """Keyframe mode is not checked with a gyroscope: its pairs are compensated as without one, and a
    warning says so."""
    from covo_gtsam.cli import main

    _reference_gyro(sample_dir, tmp_path / "gyro.txt")
    (tmp_path / "k.toml").write_text("[tracking]\nkeyframes = true\n")
    base = ["run", str(sample_dir), "--max-frames", "8", "--no-plots", "--quiet", "--config", str(tmp_path / "k.toml")]
    capsys.readouterr()
    assert main([*base, "--out", str(tmp_path / "g"), "--gyro", str(tmp_path / "gyro.txt")]) == 0
    assert "covo: warning: keyframe mode does not use the gyroscope" in capsys.readouterr().err
    assert main([*base, "--out", str(tmp_path / "p")]) == 0
    assert json.loads((tmp_path / "g" / "metrics.json").read_text())["gyro"]["pairs"] == 0
    assert (tmp_path / "g" / "relative.txt").read_text() == (tmp_path / "p" / "relative.txt").read_text()


def test_a_simulated_gyroscopes_clock_offset_reaches_the_poses_and_its_bias_cancels_in_a_pair():
    """The simulation's gyroscope imperfections, unknown to the odometry (seed 0, the readout alone, up to
    6 rad/s): stamps 20 ms late read the angular velocity at the wrong instant and leave more rotation
    error than the plain gyroscope; a constant bias of 0.05 rad/s moves both frames of a pair alike, so
    that the pair's rotation error hardly changes."""
    def rms(q):
        return np.sqrt(np.mean(q.errors[q.consecutive][2:, :3] ** 2))

    plain = rms(_readout_run(200.0))
    late, biased = rms(_readout_run(200.0, gyro_clock_offset_s=0.02)), rms(_readout_run(200.0, gyro_bias_rad_s=0.05))
    assert late > 1.2 * plain and abs(biased / plain - 1.0) < 0.1, (plain, late, biased)


@pytest.mark.parametrize("late", [0.0, 0.003, -0.008])
def test_the_gyroscopes_clock_offset_is_found_from_the_pairs_own_turns(late):
    """Simulated gyroscope stamps ``late`` seconds behind the frames' (unknown to the odometry): the
    run finds the offset from its pairs' mean angular velocities alone, within half a millisecond."""
    g = _readout_run(200.0, gyro_clock_offset_s=late).gyro
    assert g["pairs"] > 90 and g["clock_offset_se_s"] < 0.0003
    assert abs(g["clock_offset_s"] - late) < 0.0005, g


def test_covo_run_says_when_the_gyroscopes_clock_is_off_and_by_how_much(sample_dir, tmp_path, capsys):
    """On the 40 real frames, the stand-in gyroscope's stamps moved 30 ms later are found about 30 ms
    later (the sign and size of the offset against the run's own turns, within twice its standard
    error, about 3 ms here), and ``covo run`` names the ``--gyro-time-offset`` that aligns them."""
    from covo_gtsam.cli import main

    _reference_gyro(sample_dir, tmp_path / "gyro.txt")
    rows = np.loadtxt(tmp_path / "gyro.txt")
    rows[:, 0] += 0.03
    np.savetxt(tmp_path / "late.txt", rows, fmt="%.6f")
    base = ["run", str(sample_dir), "--no-plots", "--quiet"]
    found = {}
    for name in ("gyro", "late"):
        capsys.readouterr()
        assert main([*base, "--out", str(tmp_path / name), "--gyro", str(tmp_path / f"{name}.txt")]) == 0
        found[name] = json.loads((tmp_path / name / "metrics.json").read_text())["gyro"]
        out = capsys.readouterr().out
    shift = found["late"]["clock_offset_s"] - found["gyro"]["clock_offset_s"]
    se = np.hypot(found["late"]["clock_offset_se_s"], found["gyro"]["clock_offset_se_s"])
    assert abs(shift - 0.03) < 2 * se and se < 0.005, found
    assert f"run again with --gyro-time-offset {-found['late']['clock_offset_s']:.4f}" in out
