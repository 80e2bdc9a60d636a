"""A camera that stamps its depth images with their colour images' stamps (as the freiburg3
sequences of TUM RGB-D do): no colour-depth offset is known, so the terms built on it vanish, and
the covariance must hold without them (docs/results.md, "Real data")."""

import numpy as np
import pytest


@pytest.mark.slow
@pytest.mark.realdata
def test_real_frames_stamped_as_synchronised_keep_a_consistent_covariance(fr1_rpy_dir):
    """fr1_rpy's 240 frames with every depth image stamped at its colour image's time. The
    ``depth_time`` and ``depth_time_coherent`` bases are zero, no depth image is read a period
    apart, and the run learns no depth clock. The per-pair NEES against the reference (with its
    jitter) must meet the bounds a consistent covariance should: ANEES of both blocks in
    [1.5, 3.5], at most 5 % above chi2(3)'s 97.5 % quantile, none above 100. It read 3.03 / 3.11,
    3.3 % / 4.2 % above 9.35, largest 13.0 / 26.4 (with the stamped offsets 2.37 / 2.95, 1.3 % /
    3.3 %)."""
    from covo_gtsam.chi2 import CHI2_3_975
    from covo_gtsam.datasets.tum import TumSequence
    from covo_gtsam.evaluation import evaluate_run

    seq = TumSequence(fr1_rpy_dir)
    vo, steps = _register(seq, range(len(seq.timestamps)), synchronised=True)
    posed = [s for s in steps if s.has_relative_pose]
    assert len(posed) >= 235
    for name in ("depth_time", "depth_time_coherent", "depth_jump"):
        assert all(not np.any(s.error_bases[name]) for s in posed), name
    calibration = vo.self_calibration()
    assert calibration["depth_frame_period_s"] is None and calibration["depth_period_jumps"] == 0

    ev = evaluate_run(steps, seq, 1.0)  # as metrics.json: against the reference, its jitter added
    for n in (np.asarray(ev.nees_translation), np.asarray(ev.nees_rotation)):
        assert len(n) >= 235
        assert 1.5 <= n.mean() <= 3.5
        assert np.mean(n > CHI2_3_975) <= 0.05
        assert n.max() < 100


def _register(seq, frames: range, synchronised: bool) -> tuple:
    """A new odometry run over ``frames`` of ``seq``, each depth image stamped at its colour image's
    time if ``synchronised``, else as stamped: the odometry and its steps."""
    from covo_gtsam.odometry import VisualOdometry

    vo = VisualOdometry(seq.camera_name)
    stamps = seq.timestamps if synchronised else seq.depth_timestamps
    return vo, [vo.register_frame(*seq.load(i), seq.timestamps[i], depth_timestamp=stamps[i]) for i in frames]


def _short_runs(fr1_rpy_dir, synchronised: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """fr1_rpy's 240 frames as 15 runs of 16 frames each (depth images stamped at their colour
    images' times if ``synchronised``, else as stamped): translation and rotation NEES of every
    pair as ``metrics.json`` has them, and each pair's place in its run (1: the first)."""
    from covo_gtsam.datasets.tum import TumSequence
    from covo_gtsam.evaluation import evaluate_run

    seq = TumSequence(fr1_rpy_dir)
    nt, nr = [], []
    for start in range(0, 240, 16):
        _, steps = _register(seq, range(start, start + 16), synchronised)
        ev = evaluate_run(steps, seq, 1.0)
        assert not ev.lost and len(ev.nees_translation) == 15  # every pair posed, in order
        nt.append(ev.nees_translation)
        nr.append(ev.nees_rotation)
    return np.concatenate(nt), np.concatenate(nr), np.tile(np.arange(1, 16), 15)


@pytest.mark.slow
@pytest.mark.realdata
def test_short_runs_cover_the_depths_drift_from_their_second_pair(fr1_rpy_dir):
    """Short runs (a short excerpt of a sequence is one) on the real frames. The depth's drift, which
    the 3D-3D estimates carry along the optical axis, is corrected by the mean of the depth-free
    estimates' disagreement from a run's second pair on, with that mean's standard error in the
    covariance (docs/derivation.md, "The depth's drift"). Pairs 2-10 of the runs as stamped then
    read translation ANEES 3.10 (3.79 with the correction held back until its window of 10 was
    full: the drift neither corrected nor covered), and the 225 pairs of the runs stamped as
    synchronised 3.38 / 3.17 (4.23 / 3.17 held back; their pairs 2-10 3.68, 5.11 held back; the
    held-back figures measured before the stamp and colour-depth terms took the twist at the
    current frame)."""
    nt, _, position = _short_runs(fr1_rpy_dir, synchronised=False)
    assert len(nt) >= 220
    assert nt[(position >= 2) & (position <= 10)].mean() <= 3.5
    nt, nr, _ = _short_runs(fr1_rpy_dir, synchronised=True)
    assert 1.5 <= nt.mean() <= 3.5 and 1.5 <= nr.mean() <= 3.5
