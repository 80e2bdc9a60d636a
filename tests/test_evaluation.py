"""The run evaluation: one result object that metrics.json and the figures both read."""

import json

import numpy as np
import pytest

from covo_gtsam.errors import InputError
from covo_gtsam.evaluation import CONSISTENCY_KEYS, RPE_DELTAS, RunEvaluation, evaluate_run

from conftest import SAMPLE_DIR

BASE_KEYS = ["sequence", "frames", "tracked_frames", "lost_frames", "lost", "restarts", "unassociated", "elapsed_s",
             "frames_per_second", "mean_pairs", "flagged_pairs", "flagged", "weak_consensus_pairs"]
GT_KEYS = ["not_computed", "segments", *(f"rpe_{d}" for d in RPE_DELTAS), "ate", *CONSISTENCY_KEYS, "chains",
           "nees_breakdown", "reference_jitter", "reference_axes", "twist_change_response",
           "nees_with_reference_jitter", "without_reference_jitter"]


@pytest.fixture(scope="module")
def sample_run(tmp_path_factory):
    from covo_gtsam.datasets.tum import TumSequence
    from covo_gtsam.pipeline import run_sequence

    from conftest import SAMPLE_DIR

    out = tmp_path_factory.mktemp("run")
    return run_sequence(TumSequence(SAMPLE_DIR), out, max_frames=35, plots=False, progress=False)


def test_metrics_json_is_the_result_object_serialised(sample_run):
    ev = sample_run.evaluation
    assert isinstance(ev, RunEvaluation)
    written = json.loads((sample_run.out_dir / "metrics.json").read_text())
    assert list(written) == [*BASE_KEYS, *GT_KEYS, "self_calibration", "covariance_parts", "camera", "version"]
    assert written == json.loads(json.dumps(ev.to_dict())) == json.loads(json.dumps(sample_run.metrics))
    assert ev.to_dict() is not ev.to_dict() and ev.to_dict()["lost"] is not ev.lost  # copies


def test_statistics_summarise_the_arrays_kept(sample_run):
    ev = sample_run.evaluation
    for delta in RPE_DELTAS:
        tr, rot = ev.rpe_errors[delta]
        assert ev.rpe[delta]["n"] == tr.size == rot.size > 0
        assert ev.rpe[delta]["trans_rmse"] == pytest.approx(np.sqrt(np.mean(tr**2)), rel=1e-15)
        assert ev.rpe[delta]["rot_mean_deg"] == pytest.approx(np.rad2deg(np.mean(rot)), rel=1e-15)
    assert ev.ate["n"] == ev.ate_errors.size and ev.ate["max"] == np.max(ev.ate_errors)
    assert ev.consistency["nees_pairs"] == ev.nees_translation.size == ev.nees_rotation.size
    assert ev.consistency["anees_translation"] == np.mean(ev.nees_translation)
    assert ev.consistency["anees_rotation"] == np.mean(ev.nees_rotation)
    # the band of 34 independent pairs' ANEES (scipy as the oracle); none for the overlapping chains
    from scipy.stats import chi2

    np.testing.assert_allclose(ev.consistency["anees_band_95"], chi2.ppf([0.025, 0.975], 3 * 34) / 34, rtol=1e-6)
    assert "anees_band_95" not in ev.chains
    # 34 consecutive pairs, none lost: 5 chains of 30
    assert ev.chains["nees_pairs"] == 5 and ev.chains["pairs_per_chain"] == 30
    assert ev.to_dict()["chains"] == ev.chains and ev.chains["anees_translation"] > 0
    assert ev.chain_nees_translation.size == ev.chain_nees_rotation.size == 5
    assert ev.chains["anees_translation"] == np.mean(ev.chain_nees_translation)
    # the breakdown covers every pair once per binning (the first has no acceleration); 34 pairs, no full window
    bd = ev.breakdown
    assert sum(b["pairs"] for b in bd["by_angular_speed_rad_s"]) == ev.consistency["nees_pairs"] == 34
    assert sum(b["pairs"] for b in bd["by_angular_acceleration_rad_s2"]) == 33
    assert bd["tails_translation"]["largest"] == ev.nees_translation.max() and bd["windows"] is None
    assert ev.tracked_frames + ev.lost_frames == ev.frames == 35
    assert set(ev.ground_truth) >= {s.timestamp for s in sample_run.steps if s.tracked}
    # the figure's points are the pairs of the twist-change fit (a pair before and after: 34 - 2)
    assert ev.twist_change["pairs"] == len(ev.twist_change_points) == 32
    assert np.all(ev.twist_change_points[:, 0] >= 0)


def test_the_reference_jitter_is_that_of_all_its_samples(sample_run):
    from covo_gtsam.datasets.tum import TumSequence
    from covo_gtsam.reference_noise import reference_jitter

    stamps, poses = TumSequence(SAMPLE_DIR).gt_samples
    direct = reference_jitter(stamps, poses)
    ref = sample_run.evaluation.reference
    assert ref["samples"] == direct["samples"]
    np.testing.assert_allclose(ref["rotation_deg"], np.rad2deg(direct["rotation_rad"]), rtol=1e-12)
    np.testing.assert_allclose(ref["translation_mm"], 1e3 * direct["translation_m"], rtol=1e-12)


def test_the_nees_adds_the_references_jitter_to_each_covariance(sample_run):
    """Each pair's NEES is its error against the ground truth under the pair's covariance plus the
    reference's own rotation variance at its two frames (interpolated between samples), computed
    here directly from relative.txt's covariances; without the reference's samples, the plain NEES."""
    import gtsam

    from covo_gtsam.datasets.tum import TumSequence
    from covo_gtsam.evaluation import pairs_with_truth

    ev = sample_run.evaluation
    assert ev.nees_with_reference_jitter and ev.to_dict()["nees_with_reference_jitter"] is True
    stamps, _ = TumSequence(SAMPLE_DIR).gt_samples
    var = np.deg2rad(ev.reference["rotation_deg"]) ** 2

    def kept(t):  # share of one sample's variance an interpolated pose keeps
        i = np.searchsorted(stamps, t)
        a = (t - stamps[i - 1]) / (stamps[i] - stamps[i - 1])
        return (1 - a) ** 2 + a**2

    pairs = pairs_with_truth(sample_run.steps, ev.ground_truth)
    for k in (0, 7, len(pairs) - 1):
        s = pairs[k]
        C = s.covariance[:3, :3] + np.diag(var) * (kept(s.ref_timestamp) + kept(s.timestamp))
        true = np.linalg.inv(ev.ground_truth[s.ref_timestamp]) @ ev.ground_truth[s.timestamp]
        xi = gtsam.Pose3.Logmap(s.relative.between(gtsam.Pose3(true)))[:3]
        assert ev.nees_rotation[k] == pytest.approx(xi @ np.linalg.solve(C, xi), rel=1e-9)
        assert ev.nees_rotation[k] < xi @ np.linalg.solve(s.covariance[:3, :3], xi)
    seq = TumSequence(SAMPLE_DIR)
    seq.gt_samples = None
    plain = evaluate_run(sample_run.steps, seq, 1.0)
    assert not plain.nees_with_reference_jitter and np.all(plain.nees_rotation > ev.nees_rotation)
    # metrics.json keeps the plain statistics beside the ones with the jitter
    assert plain.without_reference_jitter is None and ev.without_reference_jitter == plain.consistency
    np.testing.assert_allclose(plain.nees_translation, ev.nees_translation, rtol=1e-12)  # rotation block only
    assert np.all(plain.chain_nees_rotation > ev.chain_nees_rotation)
    # a chain's reference error is that of its two end frames: the intermediate references cancel
    from covo_gtsam.covariance import compose_chains

    T = np.array([s.relative.matrix() for s in pairs])
    C = np.array([s.covariance for s in pairs])
    est, C_chain = compose_chains(T, C, 30)
    for m in range(len(est)):
        first, last = pairs[m].ref_timestamp, pairs[m + 29].timestamp
        Cr = C_chain[m][:3, :3] + np.diag(var) * (kept(first) + kept(last))
        true = np.linalg.inv(ev.ground_truth[first]) @ ev.ground_truth[last]
        xi = gtsam.Pose3.Logmap(gtsam.Pose3(est[m]).between(gtsam.Pose3(true)))[:3]
        assert ev.chain_nees_rotation[m] == pytest.approx(xi @ np.linalg.solve(Cr, xi), rel=1e-9)


def test_without_the_references_samples_the_jitter_says_why(sample_run):
    from covo_gtsam.datasets.tum import TumSequence

    seq = TumSequence(SAMPLE_DIR)
    seq.gt_samples = None  # as a bag's ground truth: poses at the frames only
    ev = evaluate_run(sample_run.steps, seq, 1.0)
    assert ev.reference is None and "samples" in ev.not_computed["reference_jitter"]
    assert ev.consistency is not None
    stamps, poses = TumSequence(SAMPLE_DIR).gt_samples
    far = poses.copy()
    far[:, :3, 3] += 1e170  # beyond any room: dropped, as the ground truth at the frames is
    seq.gt_samples = (stamps, far)
    ev = evaluate_run(sample_run.steps, seq, 1.0)
    assert ev.reference is None and "too few" in ev.not_computed["reference_jitter"]
    assert evaluate_run([], seq, 1.0).not_computed["reference_jitter"] == "no frame was processed"


def test_figures_read_the_result_object_not_a_second_computation(sample_run, tmp_path, monkeypatch):
    pytest.importorskip("matplotlib")
    from covo_gtsam import evaluation, metrics
    from covo_gtsam.plots import RUN_PLOTS, plot_run

    def fail(*args, **kwargs):
        raise AssertionError("the figures recomputed a metric")

    for module in (evaluation, metrics):
        for name in ("relative_pose_nees", "relative_pose_errors", "ate_errors", "segment_rpe_errors",
                     "relative_ground_truth", "tracked_segments", "ground_truth_lookup", "chain_nees",
                     "compose_chains", "twist_change_response"):
            if hasattr(module, name):
                monkeypatch.setattr(module, name, fail)
    written = plot_run(sample_run.steps, sample_run.evaluation, tmp_path)
    assert sorted(p.name for p in written) == sorted(RUN_PLOTS)
    assert all(p.stat().st_size > 0 for p in written)


def test_without_ground_truth_only_the_counts_and_null_statistics():
    from types import SimpleNamespace

    import gtsam

    from covo_gtsam.odometry import OdometryStep

    steps = [OdometryStep(0.0, "first", pose=gtsam.Pose3()), OdometryStep(0.1, "lost", reason="no depth")]
    ev = evaluate_run(steps, SimpleNamespace(name="x", groundtruth=None), 2.0)
    assert not ev.has_ground_truth and ev.rpe == {} and ev.ate is None and ev.nees_translation.size == 0
    d = ev.to_dict()
    assert list(d) == [*BASE_KEYS, *GT_KEYS]  # the same keys as with ground truth, null, with the reason
    assert all(d[k] is None for k in GT_KEYS if k not in ("not_computed", "segments", "nees_with_reference_jitter"))
    assert d["not_computed"]["ate"] == d["not_computed"]["chains"] == "the sequence has no ground truth"
    assert d["frames_per_second"] == 1.0 and d["lost"] == [{"timestamp": 0.1, "reason": "no depth"}]
    assert evaluate_run(steps, SimpleNamespace(name="x", groundtruth=None), 0.0).frames_per_second is None


def _synthetic_run(n: int, persistent: bool, seed: int = 0):
    """Steps of a run whose pairs' errors are drawn from their covariances: independent, or the same
    error in every pair (a persistent one), and the ground truth they are errors against."""
    import gtsam

    from covo_gtsam.odometry import OdometryStep

    rng = np.random.default_rng(seed)
    C = np.diag([1e-5] * 3 + [4e-6] * 3)
    same = rng.multivariate_normal(np.zeros(6), C)
    gt, steps, truth = {0.0: np.eye(4)}, [OdometryStep(0.0, "first")], gtsam.Pose3()
    for k in range(1, n + 1):
        motion = gtsam.Pose3.Expmap(np.r_[rng.normal(scale=0.03, size=3), rng.normal(scale=0.01, size=3)])
        truth = truth.compose(motion)
        gt[float(k)] = truth.matrix()
        err = same if persistent else rng.multivariate_normal(np.zeros(6), C)
        # T_true = T_est Exp(err): the estimate is the truth moved by -err
        steps.append(OdometryStep(float(k), "tracked", ref_timestamp=float(k - 1),
                                  relative=motion.compose(gtsam.Pose3.Expmap(-err)), covariance=C))
    return steps, gt


def chain_statistics(steps, gt, length):
    """metrics.json's chains of a run's steps."""
    from covo_gtsam.evaluation import chain_nees
    from covo_gtsam.evaluation import chain_statistics as statistics

    return statistics(*chain_nees(steps, gt, length), length)


def test_chains_are_consistent_for_independent_errors_and_not_for_persistent_ones():

    # 3000 pairs: 100 disjoint chains, so the chains' ANEES is 3 within about 0.25 (one s.d.)
    steps, gt = _synthetic_run(3000, persistent=False)
    out = chain_statistics(steps, gt, 30)
    assert out["pairs_per_chain"] == 30 and out["nees_pairs"] == 2971
    assert 2.4 < out["anees_translation"] < 3.6 and 2.4 < out["anees_rotation"] < 3.6
    single = chain_statistics(steps, gt, 1)
    assert 2.8 < single["anees_translation"] < 3.2 and single["nees_pairs"] == 3000
    # one error in every pair: a chain's error is about 30 times a pair's, its covariance 30 times
    steps, gt = _synthetic_run(600, persistent=True)
    chains, pairs = chain_statistics(steps, gt, 30), chain_statistics(steps, gt, 1)
    for key in ("anees_translation", "anees_rotation"):
        assert 25 < chains[key] / pairs[key] < 32


def test_chains_run_through_lost_frames_but_not_across_restarts_or_missing_truth():
    from covo_gtsam.odometry import OdometryStep

    steps, gt = _synthetic_run(40, persistent=False)
    assert chain_statistics(steps, gt, 30)["nees_pairs"] == 11
    # frame 10 lost: the pair to frame 11 starts at frame 9 (here: the same motion, composed)
    lost = steps[:10] + [OdometryStep(10.0, "lost", reason="test")] + steps[11:]
    lost[11] = OdometryStep(11.0, "tracked", ref_timestamp=9.0, relative=steps[10].relative.compose(steps[11].relative),
                            covariance=steps[11].covariance)
    assert chain_statistics(lost, gt, 30)["nees_pairs"] == 10
    restarted = steps[:20] + [OdometryStep(20.0, "restart", reason="test")] + steps[21:]
    with pytest.raises(InputError, match="no chain of 30"):
        chain_statistics(restarted, gt, 30)
    no_truth = {t: g for t, g in gt.items() if t != 25.0}
    with pytest.raises(InputError):
        chain_statistics(steps, no_truth, 30)
    assert chain_statistics(steps, no_truth, 20)["nees_pairs"] == 5  # pairs ending in frames 1-24 only


def test_keyframe_chains_follow_each_pair_to_its_reference():
    """Keyframes 0, 2, 4, 6: each pair links to the pair that ends at its keyframe, so frame 7's
    chain of four is 0-2, 2-4, 4-6, 6-7; with exact poses every chain's error is zero, which a
    wrong order of composition or a wrong ground-truth start would not give."""
    import gtsam

    from covo_gtsam.odometry import OdometryStep

    rng = np.random.default_rng(1)
    gt = {float(k): gtsam.Pose3.Expmap(rng.normal(scale=0.2, size=6)).matrix() for k in range(8)}
    refs = {1: 0, 2: 0, 3: 2, 4: 2, 5: 4, 6: 4, 7: 6}
    steps = [OdometryStep(0.0, "first")] + [
        OdometryStep(float(k), "tracked", ref_timestamp=float(r),
                     relative=gtsam.Pose3(np.linalg.inv(gt[float(r)]) @ gt[float(k)]), covariance=np.eye(6) * 1e-4)
        for k, r in refs.items()]
    three, four = chain_statistics(steps, gt, 3), chain_statistics(steps, gt, 4)
    assert three["nees_pairs"] == 3 and four["nees_pairs"] == 1  # 5, 6, 7; and 7
    for out in (three, four):
        assert out["anees_translation"] < 1e-12 and out["anees_rotation"] < 1e-12


def test_the_jitter_is_not_measured_from_samples_too_far_apart(sample_run):
    """Every 3rd sample of the fr1 reference (33 Hz): the quadratic through the neighbours no longer
    follows the motion, so no jitter is reported and the NEES is the plain one."""
    from covo_gtsam.datasets.tum import TumSequence

    seq = TumSequence(SAMPLE_DIR)
    stamps, poses = seq.gt_samples
    for step in (2, 3):  # 50 and 33 Hz
        seq.gt_samples = (stamps[::step], poses[::step])
        ev = evaluate_run(sample_run.steps, seq, 1.0)
        assert ev.reference is None and "too far apart" in ev.not_computed["reference_jitter"]
        assert not ev.nees_with_reference_jitter
    # a stamp that is not a number neither hides the sparse samples nor reaches the NEES
    sparse = stamps[::3].copy()
    sparse[5] = np.nan
    seq.gt_samples = (sparse, poses[::3])
    assert "too far apart" in evaluate_run(sample_run.steps, seq, 1.0).not_computed["reference_jitter"]
    dense = stamps.copy()
    dense[-1] = np.nan
    seq.gt_samples = (dense, poses)
    ev = evaluate_run(sample_run.steps, seq, 1.0)
    assert ev.nees_with_reference_jitter and np.all(np.isfinite(ev.nees_rotation))
    seq.gt_samples = (stamps[::1], poses[::1])
    assert evaluate_run(sample_run.steps, seq, 1.0).nees_with_reference_jitter


@pytest.mark.parametrize("filled", [(), (0,), (5,), (0, 1, 2, 3, 4, 5)])
def test_the_motion_figure_draws_any_bins(tmp_path, filled):
    """ANEES bars by motion: no bin, only the first, only the open-ended last, or all filled."""
    pytest.importorskip("matplotlib")
    from covo_gtsam.nees_breakdown import SPEED_EDGES, by_bins
    from covo_gtsam.plots import _plt, anees_bars, save_figure

    centres = np.array([0.25, 0.75, 1.25, 1.75, 2.5, 4.0])
    values = np.repeat(centres[list(filled)], 7) if filled else np.full(3, np.nan)
    nees = np.full(values.shape, 3.0)
    bins = by_bins(values, SPEED_EDGES, nees, nees)
    assert sum(b["pairs"] for b in bins) == 7 * len(filled)
    fig, ax = _plt().subplots()
    anees_bars(ax, bins, "ANEES by speed", "rad/s")
    assert len(ax.get_xticks()) == len(filled)
    assert save_figure(fig, tmp_path / "bars.png").stat().st_size > 0


def test_a_reference_turned_against_the_camera_shows_in_reference_axes():
    """A ground truth whose axes are turned by ``D`` (each pose ``G D^-1``, so each pair reads
    ``D T D^-1``) is fitted that rotation within its standard errors, and against it turned back
    by the fit the chains' rotation NEES are about what they are against the unturned one, while
    against the turned one they are several times that; with the rotation not observed about every
    axis the chains are not turned back."""
    import gtsam

    from covo_gtsam.evaluation import AXES_OBSERVED_DEG, reference_axes, relative_ground_truth

    steps, gt = _synthetic_run(300, persistent=False)
    d = np.deg2rad([6.0, -6.0, 5.0])  # large: a chain of 30 random turns of 1.7 deg has only about 9 deg to turn
    D_inv = np.linalg.inv(gtsam.Pose3(gtsam.Rot3.Expmap(d), np.zeros(3)).matrix())
    turned = {t: G @ D_inv for t, G in gt.items()}
    fit = reference_axes(steps, turned, *relative_ground_truth(steps, turned))
    assert fit["pairs"] == 300 and max(fit["standard_error_deg"]) < AXES_OBSERVED_DEG
    np.testing.assert_array_less(np.abs(np.subtract(fit["rotation_vector_deg"], np.rad2deg(d))),
                                 4 * np.array(fit["standard_error_deg"]))
    as_is = chain_statistics(steps, gt, 30)["anees_rotation"]
    assert chain_statistics(steps, turned, 30)["anees_rotation"] > 2 * as_is
    assert fit["chains_anees_rotation"] == pytest.approx(as_is, rel=0.15)
    # the reference's jitter at the chains' ends lowers their NEES
    jitter = lambda a, b: np.tile(np.diag([1e-3] * 3 + [0.0] * 3), (len(a), 1, 1))  # noqa: E731
    assert reference_axes(steps, turned, *relative_ground_truth(steps, turned), jitter)["chains_anees_rotation"] < (
        0.5 * fit["chains_anees_rotation"])
    # pairs turning (nearly) about x alone: d_x is not observed, nothing is turned back
    T_est, T_true, covs = relative_ground_truth(steps, turned)
    about_x = np.tile(np.eye(4), (len(T_est), 1, 1))
    about_x[:, :3, :3] = [gtsam.Rot3.Rx(a).matrix() for a in np.linspace(-0.05, 0.05, len(T_est))]
    about_x[:, :3, :3] = about_x[:, :3, :3] @ gtsam.Rot3.Ry(1e-3).matrix()
    weak = reference_axes(steps, turned, T_est, about_x, covs)
    assert weak["standard_error_deg"][0] > AXES_OBSERVED_DEG and weak["chains_anees_rotation"] is None


def test_docs_metrics_md_names_every_key_metrics_json_writes(sample_run):
    """docs/metrics.md documents each key of metrics.json, and each key of its nested statistics."""
    import re
    from pathlib import Path

    page = (Path(__file__).resolve().parent.parent / "docs" / "metrics.md").read_text()
    documented = set(re.findall(r"`([a-z_0-9]+)`", page))
    written = json.loads((sample_run.out_dir / "metrics.json").read_text())
    keys = set(written)
    for name in ("rpe_1", "ate", "chains", "nees_breakdown", "reference_jitter", "reference_axes",
                 "twist_change_response", "self_calibration", "covariance_parts", "camera"):
        assert isinstance(written[name], dict), name  # the sample run has them all
        keys |= set(written[name])
    from covo_gtsam.nees_breakdown import window_statistics

    windows = window_statistics(np.full(120, 3.0), np.full(120, 3.0))  # the sample run is too short for one
    keys |= set(windows) | set(windows["anees_rotation"]) | set(written["nees_breakdown"]["tails_rotation"])
    keys |= set(written["nees_breakdown"]["by_angular_speed_rad_s"][0])
    assert sorted(keys - documented) == []
    # and the other way round: every key the page's tables list is written
    listed = {name for row in re.findall(r"^\| (`[^|]+) \|", page, flags=re.M)
              for name in re.findall(r"`([a-z_0-9]+)`", row)}
    assert listed and sorted(listed - set(written) - set(written["self_calibration"])) == []
    # the camera it records is the one it ran with: the fr1 preset, named by the folder
    from covo_gtsam.camera import Camera

    fr1 = Camera.preset("fr1")
    assert written["camera"] == {"name": "fr1", "fx": fr1.fx, "fy": fr1.fy, "cx": fr1.cx, "cy": fr1.cy,
                                 "distortion": list(fr1.dist), "width": 640, "height": 480, "depth_scale": 5000.0}


def test_covariance_parts_are_each_terms_share_of_each_block():
    """What each pair's covariance is made of, as the history records it before the bases are
    dropped: for covariances built as known parts (points, frame term, a latency term, what the
    odometry added) the mean shares are known. A pair over two intervals takes the frame term's
    rotation variance twice and its translation variance four times; a flagged pair and steps
    without a relative pose do not count; a step the next frame settles (its covariance and
    latency basis revised) counts as settled; a part only some pairs have counts 0 in the others."""
    import gtsam

    from covo_gtsam.config import SensorConfig
    from covo_gtsam.evaluation import covariance_parts
    from covo_gtsam.odometry import OdometryStep
    from covo_gtsam.steps import StepHistory

    sensor = SensorConfig(frame_sigma_rot_deg=0.1, frame_sigma_trans_m=0.002, latency_sigma_s=0.01)
    r2, t2 = np.deg2rad(0.1) ** 2, 0.002**2
    unit = np.diag([r2] * 3 + [t2] * 3)
    dt = sensor.frame_interval_s
    B = unit / 0.01**2  # the latency term sigma^2 B: r2 and t2 per axis

    def pair(k, intervals, points, flagged=False, settled=True, added=None):
        added = added or {}
        return OdometryStep(k * dt, "tracked", ref_timestamp=(k - intervals) * dt, relative=gtsam.Pose3(),
                            covariance=sensor.frame_noise(intervals * dt) + 0.01**2 * B + points + sum(added.values()),
                            flagged=flagged, settled=settled, error_bases={"latency": B}, added_covariance=added)

    history = StepHistory(sensor=sensor)  # the bases are dropped from the steps kept
    history.add(OdometryStep(0.0, "first"))
    history.add(pair(1, 1, 2 * unit))  # shares 1/4, 1/4, 1/2 in both blocks
    unsettled = history.add(pair(3, 2, np.diag([r2] * 3 + [0.0] * 3), settled=False))
    # as the next frame settles it: the latency basis doubled, the covariance with it, one r2 + t2 more of points
    unsettled.error_bases = {"latency": 2 * B}
    unsettled.covariance = unsettled.covariance + 0.01**2 * B + unit
    history.add(pair(4, 1, 50 * unit, flagged=True))
    history.add(pair(5, 1, 0 * unit, added={"depth_drift": 2 * unit}))  # 1/4, 1/4, drift 1/2, points 0
    history.add(OdometryStep(6 * dt, "lost", reason="too few matches"))
    assert history[1].error_bases is None and history[1].added_covariance is None
    assert history.variance_parts[0] is None and history.variance_parts[3] is None
    out = covariance_parts(history.variance_parts)
    # the settled two-interval pair: rotation 2 r2 (frame) + 2 r2 (latency) + 2 r2 (points) -> 1/3 each;
    # translation 4 t2 (frame, k^2) + 2 t2 + t2 -> 4/7, 2/7, 1/7
    assert out["pairs"] == 3
    assert out["rotation"] == pytest.approx({"frame_term": (1 / 4 + 1 / 3 + 1 / 4) / 3,
                                             "latency": (1 / 4 + 1 / 3 + 1 / 4) / 3,
                                             "depth_drift": (0 + 0 + 1 / 2) / 3, "points": (1 / 2 + 1 / 3 + 0) / 3})
    assert out["translation"] == pytest.approx({"frame_term": (1 / 4 + 4 / 7 + 1 / 4) / 3,
                                                "latency": (1 / 4 + 2 / 7 + 1 / 4) / 3,
                                                "depth_drift": (0 + 0 + 1 / 2) / 3,
                                                "points": (1 / 2 + 1 / 7 + 0) / 3})
    for block in ("rotation", "translation"):
        assert sum(out[block].values()) == pytest.approx(1.0)
    # a term whose sigma is 0 is no part; nothing recorded without the sensor or without such a pair
    off = StepHistory(sensor=SensorConfig(frame_sigma_rot_deg=0.1, frame_sigma_trans_m=0.002, latency_sigma_s=0.0))
    off.add(pair(1, 1, np.zeros((6, 6))))
    assert set(covariance_parts(off.variance_parts)["rotation"]) == {"frame_term", "points"}
    plain = StepHistory()
    plain.add(pair(1, 1, np.zeros((6, 6))))
    assert plain.variance_parts == [None] and covariance_parts(plain.variance_parts) is None


@pytest.mark.parametrize("settings", [{}, {"tracking": {"keyframes": True}},
                                      {"sensor": {"rolling_shutter_look_ahead": False}}],
                         ids=["default", "keyframes", "no look-ahead"])
def test_covariance_parts_points_are_the_per_point_model_on_real_frames(sample_dir, settings):
    """On real frames, whatever the odometry adds to a pair's covariance besides the per-point model
    is counted in a sensor part, not in ``points``: the ``points`` share of each pair equals that of
    ``kappa`` times the estimator's own covariance (``step.result``), taken from the steps as
    returned (in keyframe mode and without the look-ahead every pair keeps the rolling-shutter
    model once more; the pose's restamp moves the per-point part too, hence the tolerance)."""
    from covo_gtsam.config import OdometryConfig
    from covo_gtsam.datasets.tum import TumSequence
    from covo_gtsam.evaluation import covariance_parts
    from covo_gtsam.metrics import block_shares
    from covo_gtsam.odometry import VisualOdometry
    from covo_gtsam.steps import StepHistory

    seq = TumSequence(sample_dir)
    cfg = OdometryConfig().replace(**settings)
    vo = VisualOdometry(seq.camera, cfg)
    history, steps = StepHistory(sensor=cfg.sensor), []
    for i in range(16):
        colour, depth = seq.load(i)
        steps.append(history.add(vo.register_frame(colour, depth, seq.timestamps[i],
                                                   depth_timestamp=seq.depth_timestamps[i])))
    out = covariance_parts(history.variance_parts)
    kept = [s for s in steps if s.has_relative_pose and not s.flagged]
    assert out["pairs"] == len(kept) >= 12
    points = block_shares(np.array([cfg.sensor.correlation_factor * s.result.covariance for s in kept]),
                          np.array([s.covariance for s in kept])).mean(axis=0)
    assert [out["rotation"]["points"], out["translation"]["points"]] == pytest.approx(points, abs=0.01)
    assert out["rotation"]["rolling_shutter"] > 0.1  # the share that was once hidden in points
    for block in ("rotation", "translation"):
        assert sum(out[block].values()) == pytest.approx(1.0)
        assert all(0.0 <= v <= 1.0 for v in out[block].values())
