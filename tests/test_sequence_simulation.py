"""The realistic simulation: the whole odometry on a synthetic sequence with known error sources.
The truth is known, so the mechanisms must recover what was injected."""


import gtsam
import numpy as np
import pytest

from covo_gtsam.calibration import ERROR_TERMS
from covo_gtsam.metrics import chi2_quantile, relative_pose_tangent_errors
from covo_gtsam.sequence_simulation import SequenceSimulationConfig, simulate_sequence

#: the odometry's defaults told the simulated sensor's readout
DEFAULTS = SequenceSimulationConfig().odometry_defaults()
#: the odometry told the simulated sensor's true noise, with no sensor-level terms and no depth-drift
#: correction (the simulated depths do not drift unless a test injects a drift)
TRUTH = DEFAULTS.replace(noise={"pixel_sigma": 1.0, "depth_sigma_scale": 1.0}, sensor={
    "correlation_factor": 1.0, "frame_sigma_rot_deg": 0.0, "frame_sigma_trans_m": 0.0, "depth_drift_pairs": 0,
    **{name: 0.0 for name in ERROR_TERMS.values()}})
#: no error source but pixel and depth noise
CLEAN = dict(stamp_jitter_s=0.0, readout_s=0.0, depth_offset_s=(0.0, 0.0), depth_scale_sigma=0.0, bad_frame_rate=0.0)


@pytest.mark.slow
def test_clean_sequence_is_consistent():
    """Pixel and depth noise only, the odometry told their true size: ANEES within the 95 % band."""
    r = simulate_sequence(SequenceSimulationConfig(frames=120, **CLEAN),
                          TRUTH.replace(sensor={"rolling_shutter_s": 0.0}))
    nt, nr = r.nees()
    n = len(nt)
    assert r.lost == 0 and n == 119
    lo, hi = chi2_quantile(0.025, 3 * n) / n, chi2_quantile(0.975, 3 * n) / n
    assert lo <= nt.mean() <= hi and lo <= nr.mean() <= hi


@pytest.mark.slow
def test_injected_sources_make_the_per_point_model_overconfident():
    """The same odometry on a sequence with stamp jitter, colour-depth offsets and a rolling
    shutter: far outside the band (so the check above can fail)."""
    r = simulate_sequence(SequenceSimulationConfig(frames=120, bad_frame_rate=0.0), TRUTH)
    nt, nr = r.nees()
    assert max(nt.mean(), nr.mean()) > 6


@pytest.mark.slow
def test_frame_clock_recovers_the_injected_period_and_stamp_offsets():
    cfg = SequenceSimulationConfig(frames=150, period_s=1 / 29.5, stamp_jitter_s=0.003, bad_frame_rate=0.0)
    r = simulate_sequence(cfg, DEFAULTS)
    assert r.clock_period_s == pytest.approx(1 / 29.5, abs=1e-4)  # the nominal is 1/30
    late = slice(60, None)
    truth = r.true_stamp_offsets[late] - r.true_stamp_offsets[late].mean()
    assert np.std(r.clock_offsets[late] - truth) < 0.25 * cfg.stamp_jitter_s


@pytest.mark.slow
def test_integrity_check_catches_bad_frames_at_few_false_alarms():
    """Depth images delivered with the wrong colour image (100 ms away) at 5 %: at least 90 % of
    the pairs left with such a frame are flagged, at most 2 % of the others; per bad frame, at
    least 85 % are caught, lost (no consensus) or flagged in every pair (17 of 19 on these seeds:
    2 lost, 15 flagged), and no other frame is lost (default settings)."""
    flagged_bad, flagged_good, caught = [], [], []
    for seed in (0, 1):
        r = simulate_sequence(SequenceSimulationConfig(frames=200, seed=seed, depth_scale_sigma=0.0005,
                                                       bad_frame_rate=0.05), DEFAULTS)
        flagged_bad += list(r.flagged[r.bad])
        flagged_good += list(r.flagged[~r.bad])
        caught += [r.detection_rate] * int(r.bad_frames.sum())
        assert r.false_loss_rate == 0.0 and set(r.lost_frames) <= set(np.flatnonzero(r.bad_frames))
    assert len(flagged_bad) >= 20 and len(caught) >= 15
    assert np.mean(flagged_bad) >= 0.9
    assert np.mean(flagged_good) <= 0.02
    assert np.mean(caught) >= 0.85


@pytest.mark.slow
def test_fit_recovers_the_injected_depth_scale_error():
    """Each frame's depths scaled by 1 + e, e ~ N(0, 0.05 %^2), on top of the 25 ms readout and the
    stamps' jitter: the maximum-likelihood fit of the frame-level terms against the known truth gives
    back 0.05 % (three seeds, each within 20 %: 0.053 / 0.045 / 0.052 %), and the rolling-shutter
    residual's factor is about 1 (its model's size, the compensation's error with the pair's own
    twist at the current frame, ``rolling_shutter_look_ahead`` off; a basis twice as large gives
    0.48). With the look-ahead moving the poses (the default), the same basis fits less than half its
    size (0.25 for seed 0): the next twist took most of that error out. With colour-depth offsets
    as well, :func:`test_fit_puts_true_colour_depth_offsets_on_the_coherent_term`."""
    for seed in range(3):
        for ahead in (False, True) if seed == 0 else (False,):
            r = simulate_sequence(SequenceSimulationConfig(frames=300, seed=seed, depth_scale_sigma=0.0005,
                                                           depth_offset_s=(0.0, 0.0), bad_frame_rate=0.0),
                                  TRUTH.replace(sensor={"rolling_shutter_look_ahead": ahead}))
            fit = r.fit_terms()
            assert fit.sigmas["depth_scale"] == pytest.approx(0.0005, rel=0.2)
            if ahead:
                assert fit.sigmas["rolling_shutter"] < 0.5
            else:
                assert 0.7 < fit.sigmas["rolling_shutter"] < 1.3


@pytest.mark.slow
def test_fit_puts_true_colour_depth_offsets_on_the_coherent_term():
    """Colour-depth offsets uniform in 0-15 ms, stamped as they are (the true ones) and not
    compensated, on top of the readout, the stamps' jitter and the depth-scale error: the fit puts
    them on the coherent term, the offsets' own effect at both frames together, at about 1 (within
    25 %; 1.08-1.14 over seeds 0-2, of which the test runs two), not on the independent one (an
    error of each offset; below 0.25, 0-0.03). With the reference frame's effect taken with the
    wrong sign the coherent term fits 0 and the independent one 0.58-0.61. The offsets also raise
    the fitted kappa (1.07-1.11, 0.99-1.05 without them) and lower the depth scale (0.039-0.047 %
    for 0.05 %; the depth-scale recovery is therefore checked without offsets, above): part of
    their effect is not the first-order one the terms hold (docs/derivation.md, "Colour-depth
    offsets at fast turns")."""
    for seed in range(2):
        r = simulate_sequence(SequenceSimulationConfig(frames=300, seed=seed, depth_scale_sigma=0.0005,
                                                       bad_frame_rate=0.0),
                              TRUTH.replace(sensor={"rolling_shutter_look_ahead": False}))
        fit = r.fit_terms()
        assert fit.sigmas["depth_time_coherent"] == pytest.approx(1.0, rel=0.25)
        assert fit.sigmas["depth_time"] < 0.25


@pytest.mark.slow
def test_colour_depth_offsets_told_their_true_size_are_covered_at_fast_turns():
    """Colour-depth offsets uniform in 0-15 ms the only error source besides pixel and depth noise,
    turning at up to 6 rad/s, the odometry told everything's true size (the coherent term at 1): the
    pairs' ANEES stays near 3 (3.3-4.0 t, 3.3-3.6 r over seeds 0-2, 200 frames; the test runs two
    and bounds their mean), since the terms take the camera's twist at the frame, the one the next
    pair moves the frame's rows with. With each pair's own mean twist, half an interval before its
    current frame, the offsets' effect is missed where the turn changes: 4.3-4.7 t, 4.1-4.4 r
    (docs/derivation.md, "The twist at the frame")."""
    anees = []
    for seed in range(2):
        r = simulate_sequence(SequenceSimulationConfig(frames=200, seed=seed, max_angular_speed=6.0,
                                                       **{**CLEAN, "depth_offset_s": (0.0, 0.015)}),
                              TRUTH.replace(sensor={"rolling_shutter_s": 0.0, "depth_time_coherent_factor": 1.0}))
        nt, nr = r.nees()
        anees.append((nt.mean(), nr.mean()))
    t, rot = np.mean(anees, axis=0)
    assert 2.5 < t < 3.9 and 2.5 < rot < 3.9


@pytest.mark.slow
def test_fit_recovers_an_injected_stamp_latency():
    """All stamps 10 ms late (the frame clock cannot see it: it fits its phase to the stamps): the
    fit of the latency term against the truth between the stamps gives back 10 ms (two seeds, each
    within 10 %), and less than a fifth of it when the stamps are not late."""
    for seed in range(2):
        fitted = {}
        for latency in (0.01, 0.0):
            r = simulate_sequence(SequenceSimulationConfig(frames=300, seed=seed, depth_scale_sigma=0.0005,
                                                           stamp_latency_s=latency, bad_frame_rate=0.0), TRUTH)
            fit = r.fit_terms()
            fitted[latency] = fit.sigmas["latency"]
        assert fitted[0.01] == pytest.approx(0.01, rel=0.1)
        assert fitted[0.0] < 0.002


@pytest.mark.slow
def test_latency_basis_has_the_size_of_the_delays_error():
    """Stamps 10 ms late and no other error source but pixel and depth noise: each pair's error
    splits into the estimate's own (consistent under the per-point covariance) and the delay's part,
    whose mean square the latency basis times the delay squared matches (the basis's twist change,
    its per-interval scaling and its noise subtraction together). The basis is checked against the
    trajectory's own motion, not against the formula that built it."""
    cfg = SequenceSimulationConfig(frames=200, seed=3, stamp_latency_s=0.01, period_s=1 / 30, **CLEAN)
    r = simulate_sequence(cfg, TRUTH.replace(sensor={"rolling_shutter_s": 0.0}))
    m = r.kept_consecutive
    m[:TRUTH.sensor.twist_history + 2] = False  # the basis's history filled
    own = r.errors[m] - r.stamp_errors[m]
    n_own = np.mean(np.einsum("ni,nij,nj->n", own[:, :3], np.linalg.inv(r.covariances[m][:, :3, :3]), own[:, :3]))
    delay = r.stamp_errors[m, :3]
    predicted = np.trace(0.01**2 * r.bases["latency"][m][:, :3, :3], axis1=1, axis2=2)
    assert np.sqrt(np.mean(np.sum(delay**2, axis=1))) > 3 * np.sqrt(np.mean(np.trace(
        r.covariances[m][:, :3, :3], axis1=1, axis2=2)))  # the delay's part dominates the rotation error
    assert 0.8 < np.mean(np.sum(delay**2, axis=1)) / np.mean(predicted) < 1.25
    assert 2.4 < n_own < 3.7


@pytest.mark.slow
def test_keyframe_pairs_latency_basis_has_the_size_of_the_delays_error():
    """Keyframe mode with a new keyframe whenever the overlap drops a little (pairs over 2-6
    intervals), stamps 10 ms late and nothing else: over pairs against an older keyframe, the delay's
    part of the rotation error has the mean square that the latency basis (the measured change from
    the keyframe to the last posed frame, carried on over the whole pair, and the recent changes for
    the intervals since) times the delay squared predicts: 0.93-0.98 over seeds 0-3 (1.64-1.84 when
    the measured change was taken as the whole pair's but for the last interval's new change, 1.18-1.40
    with k^2 times the recent changes alone, 1.40 for this seed)."""
    cfg = SequenceSimulationConfig(frames=200, seed=0, stamp_latency_s=0.01, period_s=1 / 30, **CLEAN)
    r = simulate_sequence(cfg, TRUTH.replace(sensor={"rolling_shutter_s": 0.0},
                                             tracking={"keyframes": True, "keyframe_ratio": 0.97}))
    k = r.frames[:, 1] - r.frames[:, 0]
    m = (k >= 2) & (k <= 6) & ~r.flagged
    m[:TRUTH.sensor.twist_history + 4] = False  # the basis's history filled
    assert m.sum() >= 50
    delay = r.stamp_errors[m, :3]
    predicted = np.trace(0.01**2 * r.bases["latency"][m][:, :3, :3], axis1=1, axis2=2)
    assert 0.75 < np.mean(np.sum(delay**2, axis=1)) / np.mean(predicted) < 1.2


@pytest.mark.slow
def test_latency_basis_covers_the_delay_when_the_turn_axis_wanders():
    """Turns up to 6 rad/s whose axis changes within a few frames, stamps 10 ms late, nothing else:
    the mean of the recent twist changes is thin across the next change's direction, so the basis
    spreads part of its size over all axes, as much as the run's own twist changes call for. The
    delay's part of the rotation error then has a NEES about 3 under ``L^2 B + C_points`` (6.4,
    two seeds, when the basis kept the recent direction alone). The basis as a pair is returned,
    before the next frame settles it (``latency_look_ahead`` off; the look-ahead is tested below)."""
    from covo_gtsam.metrics import nees

    for seed in (0, 1):
        cfg = SequenceSimulationConfig(frames=300, seed=seed, stamp_latency_s=0.01, period_s=1 / 30,
                                       max_angular_speed=6.0, **CLEAN)
        r = simulate_sequence(cfg, TRUTH.replace(sensor={"rolling_shutter_s": 0.0, "latency_look_ahead": False}))
        m = r.kept_consecutive
        m[:TRUTH.sensor.twist_history + 2] = False
        C = r.covariances[m][:, :3, :3]
        delay_nees = nees(r.stamp_errors[m, :3], 0.01**2 * r.bases["latency"][m][:, :3, :3] + C).mean()
        assert 2.0 < delay_nees < 3.8, seed


@pytest.mark.slow
def test_the_change_across_the_pair_gives_the_delays_part_its_size_and_direction():
    """Stamps 10 ms late, nothing else, turns up to 6 rad/s: the basis the next frame settles (the
    change of the twist across the pair, ``latency_look_ahead``) has the delay's part's size (mean
    square over ``L^2 tr B`` about 1) and its direction: that part, one degree of freedom along the
    change, has a NEES about 1 under ``L^2 B + C_points`` (the recent changes' spread basis: about
    2.8, the size spread over all axes), and the pairs' whole rotation error about 3."""
    from covo_gtsam.metrics import nees

    for seed in (0, 1):
        cfg = SequenceSimulationConfig(frames=300, seed=seed, stamp_latency_s=0.01, period_s=1 / 30,
                                       max_angular_speed=6.0, **CLEAN)
        r = simulate_sequence(cfg, TRUTH.replace(sensor={"rolling_shutter_s": 0.0}))
        m = r.kept_consecutive
        m[:TRUTH.sensor.twist_history + 2] = False
        C, B, d = r.covariances[m][:, :3, :3], 0.01**2 * r.bases["latency"][m][:, :3, :3], r.stamp_errors[m, :3]
        assert 0.85 < np.mean(np.sum(d**2, axis=1)) / np.mean(np.trace(B, axis1=1, axis2=2)) < 1.15, seed
        assert 0.8 < nees(d, B + C).mean() < 2.0, seed
        assert 2.5 < nees(r.errors[m, :3], B + C).mean() < 3.8, seed


@pytest.mark.slow
def test_a_flagged_pair_does_not_spoil_the_next_pair():
    """Bad frames at 5 % (default settings): the pair that starts at the frame after a bad frame
    (its reference's stamp shift must not take the flagged pair's twist) is as consistent as the
    pairs further on: its translation ANEES at most twice theirs (two seeds; 5.5 and 19.5 against
    1.5 and 1.3 when the shift took the flagged pair's twist)."""
    from covo_gtsam.metrics import nees

    for seed in range(2):
        r = simulate_sequence(SequenceSimulationConfig(frames=300, seed=seed, depth_scale_sigma=0.0005,
                                                       bad_frame_rate=0.05), DEFAULTS)
        bad = np.flatnonzero(r.bad_frames)
        after = np.array([min((j - b for b in bad if j >= b), default=len(r.bad_frames)) for j in r.frames[:, 1]])
        nt = nees(r.errors[:, 3:], r.covariances[:, 3:, 3:])
        assert (after == 2).sum() >= 8
        assert nt[after == 2].mean() <= 2.0 * nt[after > 3].mean()


@pytest.mark.slow
def test_depth_period_jump_term_covers_a_depth_image_read_a_period_away():
    """Depth images on a clock of their own, 0.5 % slower than the colour clock: the offset drifts
    through half a period, where the nearest depth image switches to its neighbour from frame to
    frame, and a pair's two depth images are read a whole period apart. No other error source but
    the stamps' jitter (which makes the switching), pixel and depth noise; the integrity check off,
    so the covariance is the terms' own. Without the jump term those pairs' errors are tens of
    times what their covariance says, with it a few times the other pairs' (the basis takes its
    twists from the pair, whose own error the jump corrupts); along the term's basis b the error
    has b's size."""
    period = 1 / 30
    cfg = SequenceSimulationConfig(frames=300, seed=0, depth_period_s=1.005 * period, max_angular_speed=1.0,
                                   **{**CLEAN, "stamp_jitter_s": 0.002, "depth_offset_s": (0.0, 0.0)})
    anees = {}
    for factor in (0.0, 1.0):
        r = simulate_sequence(cfg, TRUTH.replace(sensor={"rolling_shutter_s": 0.0, "depth_jump_factor": factor,
                                                         "integrity_threshold": 1e12}))
        jump = np.abs(np.diff(r.depth_offsets[r.frames], axis=1)[:, 0]) > period / 2
        assert jump.sum() >= 10 and r.lost == 0
        nt, _ = r.nees(good_only=False)
        anees[factor] = nt[jump].mean(), nt[~jump].mean()
    assert anees[0.0][0] > 10 * anees[0.0][1]  # uncovered without the term
    assert anees[0.0][0] > 5 * anees[1.0][0]
    w, V = np.linalg.eigh(r.bases["depth_jump"][jump])  # B = b b^T
    b = V[:, 3:, -1] * np.sqrt(w[:, -1:])
    along = np.abs(np.sum(b * r.errors[jump, 3:], axis=1)) / np.sum(b**2, axis=1)
    assert 0.75 < np.median(along) < 1.35


@pytest.mark.slow
def test_the_depth_images_own_clock_is_recovered_from_their_stamps():
    """Depth images on a clock 0.5 % slower than the colour clock, both stamped with 2 ms of jitter:
    the run reports the depth clock's period to within 0.05 ms (the offset's drift per frame is
    0.17 ms), and the colour clock's as before; a camera with depth stamped with its colour image
    reports none."""
    period = 1 / 30
    cfg = SequenceSimulationConfig(frames=120, seed=1, depth_period_s=1.005 * period,
                                   **{**CLEAN, "stamp_jitter_s": 0.002, "depth_offset_s": (0.0, 0.0)})
    vo_config = TRUTH.replace(sensor={"rolling_shutter_s": 0.0})
    calibration = simulate_sequence(cfg, vo_config).self_calibration
    assert abs(calibration["depth_frame_period_s"] - 1.005 * period) < 5e-5
    assert abs(calibration["frame_period_s"] - period) < 5e-5
    synchronised = simulate_sequence(SequenceSimulationConfig(frames=40, **CLEAN), vo_config).self_calibration
    assert synchronised["depth_frame_period_s"] is None


def _chain_rms(r, w: int = 30) -> float:
    """Translation RMS (m) of the chains of ``w`` consecutive pairs (stamps at the captures)."""
    from covo_gtsam.covariance import compose_chains

    T_est = r.capture_truth @ np.array([gtsam.Pose3.Expmap(-e).matrix() for e in r.errors])
    est, _ = compose_chains(T_est, r.covariances, w)
    true, _ = compose_chains(r.capture_truth, r.covariances, w)
    return float(np.sqrt(np.mean(np.sum(relative_pose_tangent_errors(est, true)[:, 3:] ** 2, axis=1))))


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1])
def test_the_depth_drift_correction_removes_an_injected_drift(seed):
    """Each frame's depths scaled by 1 + 1 % sin(2 pi t / 3 s): the 30-pair chains drift by 13 mm
    RMS and their pairs' ANEES is 6.8; the correction takes them to 4-5 mm and 3.0. Without a drift
    it costs little (chains 1.7 -> 1.9 mm)."""
    rms, anees, reported = {}, {}, {}
    for amplitude in (0.0, 0.01):
        cfg = SequenceSimulationConfig(frames=300, seed=seed, depth_drift=amplitude, **CLEAN)
        for window in (0, 10):
            r = simulate_sequence(cfg, TRUTH.replace(sensor={"rolling_shutter_s": 0.0, "depth_drift_pairs": window}))
            rms[amplitude, window], anees[amplitude, window] = _chain_rms(r), r.nees()[0].mean()
            reported[amplitude, window] = r.self_calibration["depth_drift_rms_m"]
    assert rms[0.01, 10] < 0.5 * rms[0.01, 0]
    assert anees[0.01, 10] < 4.0 < 5.0 < anees[0.01, 0]
    assert rms[0.0, 10] < 1.3 * rms[0.0, 0]
    # metrics.json's report of the drift: several times larger where the depths drift
    assert reported[0.0, 0] is None and reported[0.01, 10] > 3 * reported[0.0, 10]


@pytest.mark.slow
def test_the_next_twist_takes_most_of_the_rolling_shutters_error_out_of_the_pose():
    """A rolling shutter (25 ms readout) as the only error source but a tenth of the usual point
    noise: a pair's current frame is compensated with the pair's own twist, about half an interval
    early, and moving the pose one frame late by the response to the difference from the twist the
    next pair compensated the same frame with, about the one at its stamp
    (``sensor.rolling_shutter_look_ahead``), takes most of the error out: the rotation's RMS falls
    to 0.31-0.35 of what it is without (translation 0.54-0.73; two seeds). With the move's sign
    turned the error would not fall below half."""
    for seed in (0, 1):
        cfg = SequenceSimulationConfig(frames=120, seed=seed, period_s=1 / 30, pixel_sigma=0.1, depth_noise_scale=0.1,
                                       **{**CLEAN, "readout_s": 0.025})
        rms = []
        for on in (False, True):
            r = simulate_sequence(cfg, TRUTH.replace(noise={"pixel_sigma": 0.1, "depth_sigma_scale": 0.1},
                                                     sensor={"rolling_shutter_look_ahead": on}))
            e = r.errors[r.kept_consecutive]
            rms.append([np.sqrt(np.mean(np.sum(e[:, b] ** 2, axis=1))) for b in (slice(0, 3), slice(3, 6))])
        (rot_off, trans_off), (rot_on, trans_on) = rms
        assert rot_on < 0.5 * rot_off, seed
        assert trans_on < 0.85 * trans_off, seed


@pytest.mark.slow
def test_a_pose_the_next_twist_has_not_moved_carries_the_rolling_shutters_whole_error():
    """A rolling shutter (25 ms readout) as the only error source: the term's factor fitted on the
    poses the next twist moved (about 0.27 here) covers them (ANEES about 3), and a pair returned
    as estimated carries the term's basis once more at its model's size, so the same factor covers
    poses no next frame moved (``rolling_shutter_look_ahead`` off: 2.9-3.3, two seeds); without any
    term those read 4-5 in translation and 6-9 in rotation."""
    from covo_gtsam.metrics import nees

    for seed in (0, 1):
        cfg = SequenceSimulationConfig(frames=300, seed=seed, period_s=1 / 30, **{**CLEAN, "readout_s": 0.025})
        r = simulate_sequence(cfg, TRUTH)
        factor = r.fit_terms().sigmas["rolling_shutter"]
        assert 0.1 < factor < 0.5, seed
        for ahead, factor_used, low, high in ((True, factor, 2.4, 3.7), (False, factor, 2.4, 3.7),
                                              (False, 0.0, 3.7, np.inf)):
            q = simulate_sequence(cfg, TRUTH.replace(sensor={"rolling_shutter_factor": factor_used,
                                                             "rolling_shutter_look_ahead": ahead}))
            m = q.kept_consecutive
            nt = nees(q.errors[m, 3:], q.covariances[m][:, 3:, 3:]).mean()
            nr = nees(q.errors[m, :3], q.covariances[m][:, :3, :3]).mean()
            assert low < nt < high and low < nr < high, (seed, ahead, factor_used, nt, nr)


@pytest.mark.slow
def test_terms_fitted_on_a_brisk_turn_hold_on_a_gentle_one():
    """Stamps 10 ms late and a per-frame depth-scale error: the terms fitted at turns up to 2 rad/s
    cover the same sensor turning at up to 0.25 rad/s (ANEES t and r in [2, 4.5]), since the delay's
    term shrinks with the twist's changes. Fitted without the latency term, a constant frame term of
    about 0.06 deg (the size fitted on the freiburg1 frames) stands in for the delay and leaves the
    gentle turn's rotation far too conservative (below 1): what the check would see if a term did not
    follow the motion."""
    import dataclasses

    from covo_gtsam.calibration import fit_sensor_terms
    from covo_gtsam.metrics import nees

    base = SequenceSimulationConfig(frames=200, seed=0, stamp_latency_s=0.01, depth_scale_sigma=0.0005,
                                    bad_frame_rate=0.0)
    r = simulate_sequence(base, TRUTH)
    m = r.kept_consecutive
    fits = {"all": r.fit_terms(),
            "no latency": fit_sensor_terms(r.errors[m], r.covariances[m],
                                           bases={k: v[m] for k, v in r.bases.items() if k != "latency"})}
    assert fits["all"].frame_sigma_rot_deg < 0.01
    assert 0.03 < fits["no latency"].frame_sigma_rot_deg < 0.1
    gentle = simulate_sequence(dataclasses.replace(base, max_angular_speed=0.25), TRUTH)
    m = gentle.kept_consecutive
    anees = {}
    e = gentle.errors[m]
    for label, fit in fits.items():
        C = gentle.kept_covariances(fit)
        anees[label] = (nees(e[:, 3:], C[:, 3:, 3:]).mean(), nees(e[:, :3], C[:, :3, :3]).mean())
    assert 2.0 < anees["all"][0] < 4.5 and 2.0 < anees["all"][1] < 4.5, anees
    assert anees["no latency"][1] < 1.0, anees
