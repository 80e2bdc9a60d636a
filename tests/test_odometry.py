"""Visual odometry (covo_gtsam.odometry): lost frames and restarts, bad frames and stamps through
the library API, the configuration's checks, the frame-level covariance term."""

from __future__ import annotations

import cv2
import gtsam
import numpy as np
import pytest

from covo_gtsam.camera import Camera
from covo_gtsam.odometry import OdometryConfig, VisualOdometry


def test_run_restarts_after_a_run_of_lost_frames(sample_dir):
    """Frames 3..4 are blank, then the view jumps (flipped images, which cannot be matched to the
    last good frame): after restart_after lost frames the next frame starts a new segment and
    the frames after it are tracked again instead of being lost for good."""
    from covo_gtsam.datasets.images import load_depth
    from covo_gtsam.datasets.tum import TumSequence
    from covo_gtsam.graph import between_factors
    from covo_gtsam.odometry import OdometryConfig

    seq = TumSequence(sample_dir)
    cfg = OdometryConfig().replace(tracking={"restart_after": 3})
    vo = VisualOdometry(seq.camera, cfg)
    steps = []
    for i in range(10):
        img = cv2.imread(seq.rgb_paths[i])
        if i in (3, 4):
            img = np.full_like(img, 128)
        elif i >= 5:
            img = np.ascontiguousarray(np.roll(img[::-1, ::-1], 200, axis=1))
        steps.append(vo.register_frame(img, load_depth(seq.depth_paths[i]), seq.timestamps[i]))
    statuses = [s.status for s in steps]
    # 3, 4 blank and 5 (flipped) lost; 6 cannot be matched to frame 2 either and restarts
    assert statuses == ["first", "tracked", "tracked", "lost", "lost", "lost", "restart",
                        "tracked", "tracked", "tracked"], statuses
    last, restart = steps[2], steps[6]
    assert restart.relative is None and "3 lost frames" in restart.reason
    assert np.allclose(restart.pose.matrix(), last.pose.matrix())
    assert np.allclose(restart.pose_covariance, last.pose_covariance + cfg.gap_noise())
    assert steps[7].ref_timestamp == pytest.approx(restart.timestamp)
    factors, initial = between_factors(steps)
    assert len(factors) == 2 + 3 and initial.size() == 7  # no factor across the gap


def test_register_frame_with_zero_depth_is_lost():
    vo = VisualOdometry(Camera.preset("fr1"))
    img = (np.random.default_rng(0).random((480, 640)) * 255).astype(np.uint8)
    step = vo.register_frame(img, np.zeros((480, 640), np.uint16), 1.0)
    assert step.status == "lost" and step.reason.endswith("; the depth image has no depth within [0.5, 5] m "
                                                          "(all zero or out of range)")
    # depth in range, but only where no feature is: the features lack depth, the depth image is not empty
    depth = np.zeros((480, 640), np.uint16)
    depth[0, 0] = 5000
    step = vo.register_frame(img, depth, 2.0)
    assert step.status == "lost" and step.reason.startswith("only 0 features") and "depth image" not in step.reason


def test_register_frame_with_wrong_shapes_is_lost():
    vo = VisualOdometry(Camera.preset("fr1"))
    step = vo.register_frame(np.zeros((240, 320), np.uint8), np.zeros((240, 320), np.uint16), 1.0)
    assert step.status == "lost" and "size" in step.reason


def test_register_frame_rejects_bad_timestamps(sample_dir):
    from covo_gtsam.datasets.tum import TumSequence
    from covo_gtsam.errors import InputError

    seq = TumSequence(sample_dir)
    vo = VisualOdometry(seq.camera)
    frame = vo.prepare(*seq.load(0))
    assert vo.register_frame(frame, timestamp=10.0).status == "first"
    for bad, needle in ((float("nan"), "finite"), (float("inf"), "finite"), (9.5, "earlier"), ("11", "number"),
                        (None, "number")):
        with pytest.raises(InputError, match=needle):
            vo.register_frame(frame, timestamp=bad)
    with pytest.raises(InputError, match="earlier"):
        vo.mark_lost(9.0, "unreadable")
    assert vo._last_stamp == 10.0  # rejected frames are not recorded
    # a repeated stamp is accepted (no velocity over a zero interval); the same image again is lost
    step = vo.register_frame(vo.prepare(*seq.load(1)), timestamp=10.0)
    assert step.tracked and step.velocity is None and np.all(np.isfinite(step.covariance))
    again = vo.register_frame(vo.prepare(*seq.load(1)), timestamp=10.1)
    assert again.status == "lost" and "repeats its reference frame's exactly" in again.reason


def test_camera_preset_names_are_accepted(small_seq):
    from covo_gtsam.datasets.tum import TumSequence
    from covo_gtsam.errors import ConfigError

    assert TumSequence(small_seq, camera="fr2").camera == Camera.preset("fr2")
    assert TumSequence(small_seq, camera="freiburg3").camera == Camera.preset("fr3")
    with pytest.raises(ConfigError, match="fr9"):
        TumSequence(small_seq, camera="fr9")
    assert VisualOdometry("fr1").camera == Camera.preset("fr1")
    with pytest.raises(ConfigError, match="camera must be a Camera or a preset name"):
        VisualOdometry(5)
    with pytest.raises(ConfigError, match="config must be an OdometryConfig"):
        VisualOdometry("fr1", {"keyframes": True})


# -- configuration values: every field type- and range-checked -----------------------------------

def _bad_values(default) -> list:
    """Values of the wrong type (or out of range) for a field with this default."""
    if isinstance(default, bool):
        return ["false", "true", 0, 1, None]
    if isinstance(default, int):
        return [True, 2.5, "3", None, -1]
    if isinstance(default, float):
        return [True, "1.0", None, float("nan"), -1.0]
    if isinstance(default, str):
        return [5, "no-such-choice", None, ["rigid3d"]]
    return [True, "x", -1, 2.5]  # robust/max_hamming (None by default)


def _config_cases():
    import dataclasses

    from covo_gtsam.config import GROUPS

    for group, cls in GROUPS.items():
        for f in dataclasses.fields(cls):
            default = getattr(cls(), f.name)
            for bad in _bad_values(default):
                if f.name == "robust" and bad is None:
                    continue  # None is a valid kernel choice
                yield pytest.param(group, f.name, bad, id=f"{group}.{f.name}={bad!r}")


@pytest.mark.parametrize("group,name,bad", list(_config_cases()))
def test_every_config_field_rejects_wrong_types(group, name, bad):
    from covo_gtsam.errors import ConfigError
    from covo_gtsam.odometry import OdometryConfig

    with pytest.raises(ConfigError) as info:
        OdometryConfig.from_dict({group: {name: bad}})
    assert f"{group}.{name}" in str(info.value)


def test_config_accepts_its_own_dict_and_numpy_scalars():
    from covo_gtsam.odometry import OdometryConfig

    cfg = OdometryConfig()
    assert OdometryConfig.from_dict(cfg.to_dict()) == cfg
    assert OdometryConfig.from_dict({"frontend": None}) == cfg
    OdometryConfig.from_dict({"noise": {"pixel_sigma": np.float32(1.5)},
                              "tracking": {"restart_after": np.int64(3), "keyframes": np.bool_(True)},
                              "frontend": {"n_features": np.int32(500), "scale_factor": 2}})


def test_orb_pyramid_and_patch_must_fit_the_camera():
    from covo_gtsam.errors import ConfigError
    from covo_gtsam.frontend import FrontendConfig
    from covo_gtsam.odometry import OdometryConfig

    with pytest.raises(ConfigError, match="frontend.n_levels 40 .*pyramid"):
        VisualOdometry(Camera.preset("fr1"), OdometryConfig(frontend=FrontendConfig(n_levels=40, scale_factor=2.0)))
    with pytest.raises(ConfigError, match="frontend.patch_size 240"):
        VisualOdometry(Camera.preset("fr1"), OdometryConfig(frontend=FrontendConfig(patch_size=240)))
    VisualOdometry(Camera.preset("fr1"), OdometryConfig(frontend=FrontendConfig(n_levels=9, scale_factor=2.0)))


# -- the frame-level term of the covariance -------------------------------------------------------

def test_frame_term_grows_with_the_frame_intervals_a_pair_spans(sample_dir):
    """Frames 0, 1 and then 3 (frame 2 skipped): the pair (1, 3) spans two intervals, so its frame
    term has twice the per-interval rotation variance and four times the translation variance;
    the reported covariance is kappa times the estimator's plus that term."""
    from covo_gtsam.calibration import ERROR_TERMS
    from covo_gtsam.datasets.tum import TumSequence
    from covo_gtsam.odometry import OdometryConfig

    seq = TumSequence(sample_dir)
    # the frame term alone: no frame-level terms, no restamping by the frame clock, no depth-drift
    # correction (from the second pair on it adds its estimate's covariance)
    cfg = OdometryConfig().replace(sensor={"frame_clock": False, "depth_drift_pairs": 0,
                                           **{name: 0.0 for name in ERROR_TERMS.values()}})
    vo = VisualOdometry(seq.camera, cfg)
    steps = [vo.register_frame(*seq.load(i), seq.timestamps[i]) for i in (0, 1, 3)]
    assert [s.status for s in steps] == ["first", "tracked", "tracked"]
    for step, k in ((steps[1], 1), (steps[2], 2)):
        assert cfg.frame_intervals(step.timestamp - step.ref_timestamp) == k
        r2, t2 = np.deg2rad(cfg.sensor.frame_sigma_rot_deg) ** 2, cfg.sensor.frame_sigma_trans_m**2
        frame = np.diag([r2 * k] * 3 + [t2 * k * k] * 3)
        np.testing.assert_allclose(cfg.frame_noise(step.timestamp - step.ref_timestamp), frame, rtol=1e-12)
        np.testing.assert_allclose(step.covariance, cfg.sensor.correlation_factor * step.result.covariance + frame,
                                   rtol=1e-12)
    assert cfg.frame_intervals(0.0) == 1 and cfg.frame_intervals(0.040) == 1 and cfg.frame_intervals(0.1) == 3


def test_latency_basis_of_a_pair_comes_from_the_pairs_before_it(sample_dir):
    """A pair's latency basis is built from the twist changes of the pairs before it, never from
    its own estimate (whose error would then enter its own covariance): two runs that share frames
    0-5 and then see different frames give their next pairs the same basis (times k^2 for a pair
    over k = 2 frame intervals) although those pairs' twists differ; until a change has been seen
    (the first two pairs) the basis is the prior, ``sensor.angular_acceleration_prior`` over one
    frame interval in any direction, whatever the twist; a pair over two intervals adds no change, a
    one-interval pair after a one-interval pair does. (The basis as the pair is returned: the
    look-ahead, tested below, replaces it when the next frame comes.)"""
    from covo_gtsam.datasets.images import load_depth
    from covo_gtsam.datasets.tum import TumSequence

    seq = TumSequence(sample_dir)
    frames = [(cv2.imread(seq.rgb_paths[i]), load_depth(seq.depth_paths[i]), seq.timestamps[i]) for i in range(9)]

    def run(indices):
        vo = VisualOdometry(seq.camera, OdometryConfig().replace(sensor={"latency_look_ahead": False}))
        return [vo.register_frame(*frames[i]) for i in indices]

    a, b = run([0, 1, 2, 3, 4, 5, 6, 7]), run([0, 1, 2, 3, 4, 5, 7, 8])  # b skips frame 6
    assert all(s.status == "tracked" for s in a[1:] + b[1:])
    sensor = OdometryConfig().sensor
    prior = np.zeros((6, 6))
    prior[:3, :3] = np.eye(3) * (sensor.angular_acceleration_prior * sensor.frame_interval_s) ** 2 / 3
    assert sensor.angular_acceleration_prior == 10.0 and not np.allclose(a[1].velocity, a[2].velocity)
    np.testing.assert_allclose(a[1].error_bases["latency"], prior, rtol=1e-12)
    np.testing.assert_allclose(a[2].error_bases["latency"], prior, rtol=1e-12)
    assert not np.allclose(a[3].error_bases["latency"], prior)  # from the history now
    # the rolling-shutter residual takes the size of the twist's change from the same basis
    for k in (1, 2, 3):
        assert np.abs(a[k].error_bases["rolling_shutter"]).max() > 0
    assert np.abs(a[3].error_bases["latency"]).max() > 0
    for k in range(1, 6):
        assert np.array_equal(a[k].error_bases["latency"], b[k].error_bases["latency"])
    assert not np.allclose(a[6].velocity, b[6].velocity)
    np.testing.assert_allclose(b[6].error_bases["latency"], 4 * a[6].error_bases["latency"], rtol=1e-12)
    np.testing.assert_array_equal(b[7].error_bases["latency"], a[6].error_bases["latency"])
    assert not np.allclose(a[7].error_bases["latency"], a[6].error_bases["latency"])
    # a camera that delivers every other frame: its pairs are two intervals long, alike, so their
    # changes enter the history (per interval) and the third pair on has the latency and
    # rolling-shutter terms
    c = run([0, 2, 4, 6, 8])
    assert all(s.status == "tracked" for s in c[1:])
    np.testing.assert_allclose(c[2].error_bases["latency"], 4 * prior, rtol=1e-12)
    for s in c[3:]:
        assert np.abs(s.error_bases["latency"]).max() > 0
        assert np.abs(s.error_bases["rolling_shutter"]).max() > 0
    # per interval: the same run told its frames come every other interval (pairs of one interval)
    # gives its pairs the same bases (a change over two intervals counts a quarter, a two-interval
    # pair four times the basis)
    vo = VisualOdometry(seq.camera, OdometryConfig().replace(sensor={"frame_interval_s": 2 / 30,
                                                                     "latency_look_ahead": False}))
    d = [vo.register_frame(*frames[i]) for i in (0, 2, 4, 6, 8)]
    for s, t in zip(c[3:], d[3:]):
        np.testing.assert_allclose(s.error_bases["latency"], t.error_bases["latency"], rtol=1e-9, atol=1e-15)


def test_the_next_frame_settles_a_pairs_latency_term_from_the_change_across_it(sample_dir, monkeypatch):
    """With ``sensor.latency_look_ahead`` a pair is returned with the latency basis of the recent
    changes (as without it) and ``settled`` False; registering the next frame replaces that basis by
    the change across the pair (:func:`~covo_gtsam.calibration.central_change_basis` of the twists
    of the pair before and the pair after, never the pair's own), moved to the stamps with the
    adjoint the pair's covariance was moved with (from frame 19 on the frame clock moves them), and
    revises its covariance by exactly the latency term's difference, and its pose covariance with
    it, before the next pose is composed onto it. The poses do not change; the run's pose
    covariances are the chain of the revised pair covariances; a history keeps the revised steps;
    only the last pair stays unsettled. (The rolling-shutter look-ahead, tested below, is off.)"""
    from covo_gtsam import calibration, odometry
    from covo_gtsam.covariance import compose_covariance
    from covo_gtsam.datasets.tum import TumSequence
    from covo_gtsam.steps import StepHistory

    calls, restamps = [], []
    original_restamp = odometry.restamp

    def central(T, before, after, noise_before, noise_after):
        out = calibration.central_change_basis(T, before, after, noise_before, noise_after)
        calls.append((np.array(before), np.array(after), out))
        return out

    def restamp(T, shift_ref, shift_cur):
        out = original_restamp(T, shift_ref, shift_cur)
        restamps.append(out[1])
        return out

    seq = TumSequence(sample_dir)
    frames = [(*seq.load(i), seq.timestamps[i], seq.depth_timestamps[i]) for i in range(30)]
    runs, returned = {}, []
    history = StepHistory()
    for on in (False, True):
        vo = VisualOdometry(seq.camera_name, OdometryConfig().replace(sensor={"latency_look_ahead": on,
                                                                             "rolling_shutter_look_ahead": False}))
        if on:
            monkeypatch.setattr(odometry, "central_change_basis", central)
            monkeypatch.setattr(odometry, "restamp", restamp)
        steps, moved = [], []
        for c, d, t, dt in frames:
            n = len(restamps)
            step = vo.register_frame(c, d, t, depth_timestamp=dt)
            moved.append(restamps[n] if len(restamps) > n else np.eye(6))
            if on:
                returned.append((step.settled, step.covariance.copy() if step.covariance is not None else None,
                                 None if step.error_bases is None else step.error_bases["latency"].copy()))
                history.add(step)
            steps.append(step)
        runs[on] = steps
    off, on = runs[False], runs[True]
    sigma = OdometryConfig().sensor.latency_sigma_s
    revised = iter(calls)
    n_revised = n_moved = 0
    for k, (a, b) in enumerate(zip(on, off)):
        assert a.status == b.status
        if not a.has_relative_pose:
            continue
        np.testing.assert_array_equal(a.pose.matrix(), b.pose.matrix())
        settled, cov_then, lat_then = returned[k]
        np.testing.assert_array_equal(cov_then, b.covariance)  # as returned: the recent changes' basis
        np.testing.assert_array_equal(lat_then, b.error_bases["latency"])
        # a pair waits for the next frame when the pair before it has a twist (not the run's first pair)
        assert settled == (k == 1 or a.flagged or on[k - 1].flagged)
        D = a.covariance - b.covariance
        np.testing.assert_allclose(D, sigma**2 * (a.error_bases["latency"] - b.error_bases["latency"]),
                                   atol=1e-12 * np.abs(b.covariance).max())
        if not settled and k < len(on) - 1:  # settled by the next frame: the pairs around it, moved as the pair
            before, after, B = next(revised)
            np.testing.assert_array_equal(before, on[k - 1].velocity)
            np.testing.assert_array_equal(after, on[k + 1].velocity)
            assert not np.allclose(after, a.velocity)
            Ad = moved[k]
            np.testing.assert_allclose(a.error_bases["latency"], Ad @ B @ Ad.T, rtol=1e-12, atol=1e-18)
            n_moved += not np.allclose(Ad, np.eye(6), atol=1e-4)
            n_revised += 1
        assert a.settled == (k < len(on) - 1)
        ref = next(s for s in on if s.timestamp == a.ref_timestamp)
        np.testing.assert_allclose(a.pose_covariance, compose_covariance(ref.pose, ref.pose_covariance, a.relative,
                                                                         a.covariance), rtol=1e-9, atol=1e-15)
        kept = history.steps[k]
        np.testing.assert_array_equal(kept.covariance, a.covariance)
        np.testing.assert_array_equal(kept.pose_covariance, a.pose_covariance)
    assert n_revised >= 20 and n_moved >= 5


def test_the_next_frame_moves_a_pairs_pose_to_the_twist_the_next_pair_compensated_the_frame_with(
        sample_dir, monkeypatch):
    """With ``sensor.rolling_shutter_look_ahead`` registering the next frame moves the last pair's
    relative pose by its current frame's rolling-shutter response ``S`` (the one its covariance's
    term was built with) to the difference of the twists that frame's rows were moved with: by the
    next pair, as its reference (the mean of the next pair's own and this pair's final twist), less
    by this pair (its own, from the outlier rejection's pose, not its final twist), moved to the
    stamps with the pair's restamp adjoint: ``T <- T Exp(Ad S (c_ref,next - c_cur))``; its pose is
    the reference's composed with it, before the next pose is composed onto it, and a history keeps
    the moved step.
    A pair is returned with the term's basis once more in its covariance (the error the move takes
    out, at the model's size) and the move takes exactly that out; a pair not moved keeps it.
    With the look-ahead the terms that take the camera's twist at the current frame (``timing``,
    ``stamp_jitter`` and the two colour-depth terms) are also built again with the twist the next
    pair moved that frame's rows with (its reference's: the mean of its own twist and this pair's),
    moved to the stamps, in place of the pair's own twist, and the covariance changes by exactly
    their terms' difference. Without the look-ahead the relative pose and covariance stay as
    returned. (The latency look-ahead, which also revises the covariance, is off.)"""
    from covo_gtsam import odometry
    from covo_gtsam.calibration import stamp_error_basis
    from covo_gtsam.datasets.tum import TumSequence
    from covo_gtsam.steps import StepHistory

    responses, restamps, used, twist_bases = {}, [], {}, []
    original_bases, original_restamp = VisualOdometry._error_bases, odometry.restamp
    original_solve = VisualOdometry._solve_pair
    original_twist_bases = VisualOdometry._frame_twist_bases

    def frame_twist_bases(self, terms, twist_cur):
        out = original_twist_bases(self, terms, twist_cur)
        twist_bases.append((np.array(twist_cur), out, terms))
        return out

    def solve_pair(self, *args):
        out = original_solve(self, *args)
        used[args[5]] = out[4][:2]  # by the pair's timestamp: the two frames' compensation twists
        return out

    def error_bases(self, *args):
        out = original_bases(self, *args)
        responses[args[9]] = out[2]  # by the pair's timestamp
        return out

    def restamp(T, shift_ref, shift_cur):
        out = original_restamp(T, shift_ref, shift_cur)
        restamps.append(out[1])
        return out

    monkeypatch.setattr(VisualOdometry, "_error_bases", error_bases)
    monkeypatch.setattr(VisualOdometry, "_solve_pair", solve_pair)
    monkeypatch.setattr(VisualOdometry, "_frame_twist_bases", frame_twist_bases)
    twist_terms = ("timing", "stamp_jitter", "depth_time", "depth_time_coherent")
    sigmas = OdometryConfig().sensor.term_sigmas()
    monkeypatch.setattr(odometry, "restamp", restamp)
    seq = TumSequence(sample_dir)
    frames = [(*seq.load(i), seq.timestamps[i], seq.depth_timestamps[i]) for i in range(30)]
    for on in (False, True):
        vo = VisualOdometry(seq.camera_name, OdometryConfig().replace(sensor={"rolling_shutter_look_ahead": on,
                                                                             "latency_look_ahead": False}))
        history = StepHistory()
        twist_bases.clear()
        steps, returned, covs, moved, bases = [], [], [], [], []
        for c, d, t, dt in frames:
            n = len(restamps)
            step = history.add(vo.register_frame(c, d, t, depth_timestamp=dt))
            moved.append(restamps[n] if len(restamps) > n else np.eye(6))
            returned.append(step.relative)
            covs.append(None if step.covariance is None else step.covariance.copy())
            bases.append(step.error_bases)
            steps.append(step)
        n_moved = n_restamped = n_twist = n_ref_checked = 0
        for k, a in enumerate(steps[:-1]):
            if not a.has_relative_pose:
                continue
            nxt = steps[k + 1]
            S = responses[a.timestamp]
            expected, expected_cov = returned[k], covs[k]
            if on and nxt.has_relative_pose and nxt.ref_timestamp == a.timestamp and not (a.flagged or nxt.flagged):
                at_frame = used[nxt.timestamp][0]  # the twist the next pair moved this frame's rows with
                np.testing.assert_allclose(at_frame, 0.5 * (used[nxt.timestamp][1] + a.velocity), rtol=1e-12,
                                           atol=1e-12)
                rebuilt = [(out, terms) for twist, out, terms in twist_bases if np.array_equal(twist, at_frame)]
                assert len(rebuilt) == 1 and not np.allclose(at_frame, a.velocity)
                out, terms = rebuilt[0]
                # what the terms were given besides that twist: the pair's own motion between the
                # captures (its twist over the interval) and, after a trusted pair, the twist at the
                # reference frame, the mean of the two pairs' twists; the stamp terms as
                # calibration.stamp_error_basis has them with those twists
                xi = gtsam.Pose3.Logmap(gtsam.Pose3(terms.motion))
                c = float(xi @ a.velocity / (a.velocity @ a.velocity))
                np.testing.assert_allclose(xi, c * a.velocity, rtol=1e-9, atol=1e-12)
                assert 0.02 < c < 0.05  # the interval, about 1/30 s
                prev = steps[k - 1]
                if prev.has_relative_pose and not prev.flagged and prev.velocity is not None:
                    np.testing.assert_allclose(terms.twist_ref, 0.5 * (prev.velocity + a.velocity), rtol=1e-12,
                                               atol=1e-12)
                    np.testing.assert_allclose(
                        out["timing"], stamp_error_basis(terms.motion, 0.5 * (prev.velocity + a.velocity), at_frame),
                        rtol=1e-12, atol=1e-24)
                    n_ref_checked += 1
                for name in twist_terms:
                    np.testing.assert_allclose(a.error_bases[name], moved[k] @ out[name] @ moved[k].T,
                                               rtol=1e-12, atol=1e-24)
                    expected_cov = expected_cov + sigmas[name] ** 2 * (a.error_bases[name] - bases[k][name])
                n_twist += bool(np.any(a.error_bases["depth_time"] != bases[k]["depth_time"]))
            if (on and S is not None and nxt.has_relative_pose and nxt.ref_timestamp == a.timestamp and not nxt.flagged
                    and not (a.depth_jump_s or nxt.depth_jump_s)):
                (_, c_cur), (c_ref_next, c_cur_next) = used[a.timestamp], used[nxt.timestamp]
                np.testing.assert_allclose(c_ref_next, 0.5 * (c_cur_next + a.velocity), rtol=1e-12, atol=1e-12)
                assert not np.allclose(c_cur, a.velocity)
                move = moved[k] @ S @ (c_ref_next - c_cur)
                expected = returned[k].compose(gtsam.Pose3.Expmap(move))
                expected_cov = expected_cov - a.error_bases["rolling_shutter"]
                assert np.abs(a.error_bases["rolling_shutter"]).max() > 1e-3 * np.abs(a.covariance).max()
                assert np.linalg.norm(move) > 1e-6
                n_moved += 1
                n_restamped += not np.allclose(moved[k], np.eye(6), atol=1e-4)
            np.testing.assert_allclose(a.relative.matrix(), expected.matrix(), atol=1e-12)
            np.testing.assert_allclose(a.covariance, expected_cov, rtol=1e-9, atol=1e-18)
            ref = next(s for s in steps if s.timestamp == a.ref_timestamp)
            np.testing.assert_allclose(a.pose.matrix(), ref.pose.compose(a.relative).matrix(), atol=1e-12)
            np.testing.assert_array_equal(history.steps[k].relative.matrix(), a.relative.matrix())
        assert n_moved >= (20 if on else 0) and n_restamped >= (5 if on else 0) and n_twist >= (20 if on else 0)
        assert n_ref_checked >= (20 if on else 0)


@pytest.mark.parametrize("frame_clock", [False, True])
def test_keyframe_pairs_take_the_current_twist_from_the_last_posed_frame(sample_dir, frame_clock):
    """Against an older keyframe, a frame's twist (used for its rolling-shutter compensation, its
    error bases and its ``velocity``) is its motion since the last posed frame over that interval,
    not the mean over the whole pair: ``velocity`` equals ``Log(T_last,cur) / dt`` between the two
    frames' captures (the chain of the pairs' own estimates, each between its captures; with the
    frame clock on, the poses at the stamps are moved off the captures), and differs from the pair's
    mean twist."""
    from covo_gtsam.datasets.tum import TumSequence

    seq = TumSequence(sample_dir)
    vo = VisualOdometry(seq.camera_name, OdometryConfig().replace(tracking={"keyframes": True},
                                                                  sensor={"frame_clock": frame_clock}))
    last, checked, differ, moved = None, 0, 0, 0
    captured = {}  # stamp -> the frame's pose at its capture
    for i in range(len(seq.timestamps)):
        step = vo.register_frame(*seq.load(i), seq.timestamps[i], depth_timestamp=seq.depth_timestamps[i])
        if step.status == "tracked":
            captured[step.timestamp] = captured[step.ref_timestamp].compose(step.result.pose)
        elif step.has_pose:
            captured[step.timestamp] = step.pose
        # (after a flagged last frame the twist is the pair's mean: its motion since then is likely off)
        if step.status == "tracked" and last is not None and step.ref_timestamp < last.timestamp and not last.flagged:
            dt = (step.timestamp - (step.stamp_shift or 0.0)) - (last.timestamp - (last.stamp_shift or 0.0))
            expected = gtsam.Pose3.Logmap(captured[last.timestamp].between(captured[step.timestamp])) / dt
            # (to 1e-5: taken at the stamps instead, the twists were up to 27 % off)
            np.testing.assert_allclose(step.velocity, expected, rtol=1e-5, atol=1e-7)
            mean = gtsam.Pose3.Logmap(step.relative) / (step.timestamp - step.ref_timestamp)
            checked += 1
            differ += np.linalg.norm(mean[:3] - step.velocity[:3]) > 0.01
            moved += step.stamp_shift is not None
        if step.has_pose:
            last = step
    assert checked >= 10 and differ >= checked // 2
    assert (moved >= 5) == frame_clock


def test_keyframe_pairs_feed_and_get_the_latency_term(sample_dir):
    """In keyframe mode a frame's twist is its motion since the last posed frame, so the changes
    between consecutive frames' twists feed the latency term's history as frame-to-frame pairs do:
    from frame 10 on every pair against an older keyframe has a latency basis (none did when only
    pairs whose reference was the last frame fed it)."""
    from covo_gtsam.datasets.tum import TumSequence

    seq = TumSequence(sample_dir)
    vo = VisualOdometry(seq.camera_name, OdometryConfig().replace(tracking={"keyframes": True}))
    last, with_basis = None, []
    for i in range(len(seq.timestamps)):
        step = vo.register_frame(*seq.load(i), seq.timestamps[i], depth_timestamp=seq.depth_timestamps[i])
        if step.status == "tracked" and last is not None and step.ref_timestamp < last.timestamp and i >= 10:
            with_basis.append(bool(np.any(step.error_bases["latency"])))
        if step.has_pose:
            last = step
    assert len(with_basis) >= 10 and all(with_basis)


def test_keyframe_pairs_take_the_twist_change_to_the_last_frame_as_measured(sample_dir):
    """Against an older keyframe the latency basis is the change of the twist from the keyframe to
    the last posed frame, as measured by their own pairs over ``k - m`` intervals and carried on
    over the pair's ``k`` (``(k / (k - m))^2`` times it), plus ``m^2`` times the recent changes'
    basis for the ``m`` intervals since the last posed frame, not ``k^2`` times that basis alone:
    two runs that share frames 0-12 and then see frame 13 (k = 4, m = 1) or 14 (k = 5, m = 2), both
    against keyframe 9, give the same measured part once it is turned back into the last posed
    frame's axes (it does not depend on the current pair; turned the other way, or taken from the
    current pair, it would differ); it is the keyframe's and frame 12's own twists' change with
    their noise taken off (the size of ``(k / (k - m))^2`` pinned), and it is not zero. (Before
    frame 20 the frame clock does not move the poses, so the bases are as built.)"""
    from covo_gtsam.calibration import known_change_basis
    from covo_gtsam.datasets.tum import TumSequence

    seq = TumSequence(sample_dir)
    cfg = OdometryConfig().replace(tracking={"keyframes": True})
    frames = [(*seq.load(i), seq.timestamps[i]) for i in range(15)]
    measured, history = {}, None
    for last in (13, 14):
        vo = VisualOdometry(seq.camera_name, cfg)
        steps = [vo.register_frame(*frames[i]) for i in range(13)]
        H = vo._twist_changes.basis()
        kf, prev = steps[9], steps[12]
        spans = vo._posed_twists  # what the two frames' own twists were taken over, and their noise
        change = known_change_basis(kf.pose.between(prev.pose).matrix(), kf.velocity, prev.velocity,
                                    spans[kf.timestamp].noise, spans[prev.timestamp].noise)[:3, :3]
        assert history is None or np.array_equal(H, history)
        history = H
        step = vo.register_frame(*frames[last])
        assert all(s.status == "tracked" for s in steps[1:]) and step.status == "tracked"
        assert step.ref_timestamp == seq.timestamps[9] and steps[-1].ref_timestamp == seq.timestamps[9]
        m = cfg.frame_intervals(step.timestamp - steps[-1].timestamp)
        k = cfg.frame_intervals(step.timestamp - step.ref_timestamp)
        assert m == last - 12 and k == last - 9
        R = steps[-1].pose.rotation().between(step.pose.rotation()).matrix()  # R_last,cur
        measured[last] = R @ (step.error_bases["latency"] - m**2 * H)[:3, :3] @ R.T / (k / (k - m)) ** 2
        np.testing.assert_allclose(measured[last], change, rtol=1e-6, atol=1e-9 * np.abs(change).max())
    assert np.trace(history) > 0
    np.testing.assert_allclose(measured[14], measured[13], rtol=1e-9, atol=1e-12 * np.abs(measured[13]).max())
    assert np.trace(measured[13]) > 0.01 * np.trace(history)


def test_a_runs_first_pair_takes_its_frames_twist_errors_with_opposite_signs(sample_dir, monkeypatch):
    """A run's first pair compensates both frames with the pair's mean twist, which is off by -c/2
    at the reference and +c/2 at the current frame (``c`` the twist's change over the pair): with
    the two frames responding alike to a twist error (every response replaced by the identity) the
    two effects cancel and the first pair has no rolling-shutter term (the same error at both frames
    would have given one as large as the twist); the second pair, whose reference has a twist,
    takes the current frame's alone, a quarter of its latency basis; both take the prior as their
    latency basis, the twist's change at ``sensor.angular_acceleration_prior``."""
    import covo_gtsam.odometry as odometry_module
    from covo_gtsam.datasets.tum import TumSequence

    monkeypatch.setattr(odometry_module, "rolling_shutter_basis", lambda G, X, rows: np.eye(6))
    seq = TumSequence(sample_dir)
    vo = VisualOdometry(seq.camera)
    steps = [vo.register_frame(*seq.load(i), seq.timestamps[i], depth_timestamp=seq.depth_timestamps[i])
             for i in range(3)]
    assert [s.status for s in steps] == ["first", "tracked", "tracked"]
    first, second = steps[1].error_bases, steps[2].error_bases
    assert np.linalg.norm(steps[1].velocity[:3]) > 0.5  # turning: a same-sign error would not vanish
    np.testing.assert_array_equal(first["rolling_shutter"], np.zeros((6, 6)))
    np.testing.assert_allclose(second["rolling_shutter"], second["latency"] / 4, rtol=1e-12)
    np.testing.assert_allclose(first["latency"], second["latency"], rtol=1e-12)
    assert second["latency"][0, 0] == pytest.approx((10.0 / 30.0) ** 2 / 3, rel=1e-12)


def test_keyframe_pairs_rolling_shutter_term_counts_both_frames_twist_errors(sample_dir, monkeypatch):
    """The rolling-shutter term of a pair is ``1/4 B H B^T`` per frame whose compensation twist may
    be off by half a recent change (``H`` the history's basis, ``B`` the frame's response to a twist
    error): frame to frame only the current frame's (the reference's twist is a central estimate),
    against an older keyframe also the keyframe's (its own pair's mean). With every response ``B``
    replaced by the identity the term is ``H / 4`` frame to frame and ``H / 2`` against keyframe 9."""
    import covo_gtsam.odometry as odometry_module
    from covo_gtsam.datasets.tum import TumSequence

    monkeypatch.setattr(odometry_module, "rolling_shutter_basis", lambda G, X, rows: np.eye(6))
    seq = TumSequence(sample_dir)
    frames = [(*seq.load(i), seq.timestamps[i]) for i in range(14)]
    for keyframes, share in ((False, 0.25), (True, 0.5)):
        vo = VisualOdometry(seq.camera_name, OdometryConfig().replace(tracking={"keyframes": keyframes}))
        for i in range(13):
            vo.register_frame(*frames[i])
        H = vo._twist_changes.basis()
        step = vo.register_frame(*frames[13])
        assert step.status == "tracked" and np.trace(H) > 0
        assert (step.ref_timestamp == seq.timestamps[9]) == keyframes
        np.testing.assert_allclose(step.error_bases["rolling_shutter"], share * H, rtol=1e-12, atol=1e-15)


def test_span_basis_of_a_pair_comes_from_the_frame_before_it(sample_dir):
    """A pair over k > 1 intervals gets the span basis ``d^2 (k^2 - 1)`` per translation axis with
    ``d`` the translation per interval of the last posed frame's own pair, not of the pair itself
    (whose error would then enter its own covariance): runs sharing frames 0-2 and then seeing frame
    4 or 5 take the same ``d``; consecutive pairs have none; the reported covariance adds
    ``span_factor^2`` times it."""
    from covo_gtsam.calibration import span_basis
    from covo_gtsam.datasets.tum import TumSequence

    seq = TumSequence(sample_dir)
    # no restamping: the bases as built; no depth-drift correction, whose covariance the pairs would add
    cfg = OdometryConfig().replace(sensor={"frame_clock": False, "depth_drift_pairs": 0})
    bases = {}
    for last in (4, 5):
        vo = VisualOdometry(seq.camera, cfg)
        steps = [vo.register_frame(*seq.load(i), seq.timestamps[i]) for i in (0, 1, 2, last)]
        assert [s.status for s in steps] == ["first", "tracked", "tracked", "tracked"]
        assert not np.any(steps[1].error_bases["span"]) and not np.any(steps[2].error_bases["span"])
        d = np.linalg.norm(steps[2].velocity[3:]) * cfg.sensor.frame_interval_s
        k = cfg.frame_intervals(steps[3].timestamp - steps[3].ref_timestamp)
        assert k == last - 2 and 0.0005 < d < 0.05
        np.testing.assert_allclose(steps[3].error_bases["span"], span_basis(d, k), rtol=1e-12)
        own = np.linalg.norm(steps[3].velocity[3:]) * cfg.sensor.frame_interval_s
        assert abs(own - d) > 1e-6  # the pair's own translation per interval would have given another basis
        without = cfg.replace(sensor={"span_factor": 0.0}).sensor.sensor_covariance(
            steps[3].result.covariance, steps[3].timestamp - steps[3].ref_timestamp, steps[3].error_bases)
        without = without + steps[3].error_bases["rolling_shutter"]  # the run's last pair, its pose not yet moved
        np.testing.assert_allclose(steps[3].covariance - without, cfg.sensor.span_factor**2 * span_basis(d, k),
                                   rtol=1e-9, atol=1e-15)
        bases[last] = steps[3].error_bases["span"] / (k * k - 1)
    np.testing.assert_allclose(bases[4], bases[5], rtol=1e-12)


def test_the_twist_passed_on_from_a_flagged_pair_is_never_its_own():
    """The next pair takes a frame's twist from its own pair unless the integrity check flagged it:
    then the twist the frame was moved to its stamp with (its reference's), and none when that was
    the flagged pair's own (its reference had no twist, e.g. right after a restart)."""
    import dataclasses

    from covo_gtsam.odometry import _trusted_velocity
    from covo_gtsam.steps import OdometryStep, StepStatus

    own, reference = np.arange(6.0), np.ones(6)
    step = OdometryStep(1.0, StepStatus.RELATIVE_POSE, velocity=own, stamp_twist=own)
    assert _trusted_velocity(step) is own
    assert _trusted_velocity(dataclasses.replace(step, flagged=True, stamp_twist=reference)) is reference
    assert _trusted_velocity(dataclasses.replace(step, flagged=True)) is None


def test_two_flagged_pairs_in_a_row_after_a_frame_without_a_twist_pass_none_on():
    """After the first frame (no twist), two flagged pairs in a row: the first's own twist moved
    its frame to its stamp and is not passed on; the second, with no trusted twist from it either,
    passes none on (not the first's untrusted one)."""
    from types import SimpleNamespace

    from covo_gtsam.odometry import _trusted_velocity
    from covo_gtsam.steps import OdometryStep, StepStatus

    vo = VisualOdometry("fr1")
    res = SimpleNamespace(pose=gtsam.Pose3())
    origin = OdometryStep(0.0, StepStatus.ORIGIN, pose=gtsam.Pose3(), pose_covariance=np.zeros((6, 6)))
    first, second = np.arange(6.0), np.ones(6)
    steps = [OdometryStep(t, StepStatus.RELATIVE_POSE, velocity=v, flagged=True, covariance=np.eye(6))
             for t, v in ((1.0, first), (2.0, second))]
    vo._pose_between_stamps(steps[0], res, origin, (first, first), 0.0, 0.0)
    vo._pose_between_stamps(steps[1], res, steps[0], (second, second), 0.0, 0.0)
    assert steps[0].stamp_twist is first and _trusted_velocity(steps[0]) is None
    assert steps[1].stamp_twist is second and _trusted_velocity(steps[1]) is None


@pytest.mark.slow
@pytest.mark.realdata
def test_a_runs_first_two_pairs_are_covered_without_a_twist_history(fr1_rpy_dir):
    """Runs started at every 8th of the shared fr1_rpy frames (29 starts): their first two pairs have
    no measured change of the twist, so the latency and rolling-shutter terms take the prior, and
    the first pair compensates both frames' readout with its own mean twist, which errs by minus
    and plus half the change. The mean NEES of the first pairs and of the second pairs, translation
    and rotation, lies in [1.5, 4.5] (a consistent covariance gives 3 +- 0.5 over 29 pairs; 2.0 /
    2.0 and 3.3 / 2.9 here). With both frames' twist errors taken with the same sign, whose
    responses nearly cancel, and the change taken as large as the twist itself, the first pairs'
    translation read 8.3 and the second pairs' rotation 1.0; with the same-sign errors mended but
    the change still as large as the twist, the first pairs read 1.1 / 0.6 (starts from frame 8)."""
    from covo_gtsam.datasets.tum import TumSequence
    from covo_gtsam.evaluation import ground_truth_lookup
    from covo_gtsam.geometry import invert_pose

    seq = TumSequence(fr1_rpy_dir)
    gt = ground_truth_lookup(seq)
    nees = []  # per start: first pair t, r, second pair t, r
    for start in range(0, 232, 8):
        vo = VisualOdometry(seq.camera)
        row = []
        for i in (start, start + 1, start + 2):
            step = vo.register_frame(*seq.load(i), seq.timestamps[i], depth_timestamp=seq.depth_timestamps[i])
            if i == start:
                continue
            assert step.status == "tracked"
            e = gtsam.Pose3.Logmap(gtsam.Pose3(invert_pose(gt[step.ref_timestamp]) @ gt[step.timestamp])
                                   .between(step.relative))
            row += [e[3:] @ np.linalg.solve(step.covariance[3:, 3:], e[3:]),
                    e[:3] @ np.linalg.solve(step.covariance[:3, :3], e[:3])]
        nees.append(row)
    mean = np.mean(nees, axis=0)
    assert len(nees) == 29 and np.all((mean >= 1.5) & (mean <= 4.5)), mean
