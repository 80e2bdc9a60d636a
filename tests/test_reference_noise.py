"""The reference's own noise (covo_gtsam.reference_noise): recovered on a simulated reference whose
noise is known, nothing reported for a noise-free one however fast it turns, and the fr1 mocap's
jitter measured from its file; a reference whose axes are turned against the camera's, its
rotation recovered with the spread a Monte Carlo gives it."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from covo_gtsam.errors import InputError
from covo_gtsam.io import load_tum_trajectory
from covo_gtsam.reference_noise import axes_rotation, reference_jitter

ROT_SD = np.deg2rad([0.08, 0.03, 0.02])  # about the body's x, y, z
TRANS_SD = np.array([0.3e-3, 0.1e-3, 0.15e-3])  # along the body's axes, m


def hand_held(n: int = 4000, rate: float = 100.0, seed: int = 0) -> tuple[np.ndarray, Rotation, np.ndarray]:
    """Stamps, rotations and positions of a smooth hand-held motion sampled at ``rate`` Hz: sums of
    0.3-2 Hz sines, turns of up to about 7 rad/s and speeds up to 1.7 m/s."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate
    freq, phase = rng.uniform(0.3, 2.0, (3, 3)), rng.uniform(0, 2 * np.pi, (3, 3))
    amp = 0.25 / freq  # rad: about 1.5 rad/s per sine at its peak
    angles = (amp[:, :, None] * np.sin(2 * np.pi * freq[:, :, None] * t + phase[:, :, None])).sum(axis=1)
    R = Rotation.from_euler("xyz", angles.T)
    p = (0.05 * np.sin(2 * np.pi * freq[:, :, None] * t + phase[:, :, None]).sum(axis=1)).T
    return t, R, p


def poses(R: Rotation, p: np.ndarray) -> np.ndarray:
    T = np.tile(np.eye(4), (len(p), 1, 1))
    T[:, :3, :3], T[:, :3, 3] = R.as_matrix(), p
    return T


def noisy(R: Rotation, p: np.ndarray, seed: int = 1) -> np.ndarray:
    """The poses with independent noise of :data:`ROT_SD` / :data:`TRANS_SD` about / along each
    sample's own axes."""
    rng = np.random.default_rng(seed)
    Rn = R * Rotation.from_rotvec(rng.normal(size=(len(p), 3)) * ROT_SD)
    return poses(Rn, p + R.apply(rng.normal(size=(len(p), 3)) * TRANS_SD))


def test_injected_noise_is_recovered_per_axis():
    t, R, p = hand_held()
    out = reference_jitter(t, noisy(R, p))
    assert out["samples"] == len(t) - 6
    # 3994 samples: the estimate's relative s.d. is about 2 % per axis
    np.testing.assert_allclose(out["rotation_rad"], ROT_SD, rtol=0.06)
    np.testing.assert_allclose(out["translation_m"], TRANS_SD, rtol=0.06)


def test_a_smooth_reference_has_no_noise_however_fast_it_turns():
    """The quadratic takes the motion: a straight line through the neighbours would report the
    turn's curvature as noise (about 0.2 degrees per axis here)."""
    t, R, p = hand_held()
    out = reference_jitter(t, poses(R, p))
    assert np.all(out["rotation_rad"] < np.deg2rad(0.002))
    assert np.all(out["translation_m"] < 1e-5)


def test_gaps_are_not_bridged_and_short_references_give_none():
    t, R, p = hand_held(n=400)
    T = noisy(R, p)
    keep = np.ones(len(t), bool)
    keep[200:230] = False  # a 0.3 s gap: the samples next to it have no neighbours on one side
    out = reference_jitter(t[keep], T[keep])
    assert out["samples"] == len(t) - 30 - 6 - 2 * 3
    assert reference_jitter(t[:12], T[:12]) is None
    # time order is the stamps', not the file's; a repeated stamp is no distinct time for the quadratic
    shuffled = np.random.default_rng(3).permutation(len(t))
    a, b = reference_jitter(t[shuffled], T[shuffled]), reference_jitter(t, T)
    assert a["samples"] == b["samples"] == len(t) - 6
    for key in ("rotation_rad", "translation_m"):
        np.testing.assert_array_equal(a[key], b[key])
    repeated = np.repeat(t[:60], 3)
    assert reference_jitter(repeated, np.repeat(T[:60], 3, axis=0)) is None
    with pytest.raises(InputError):
        reference_jitter(t, T[:-1])
    with pytest.raises(InputError):
        reference_jitter(t, T, neighbours=1)


@pytest.mark.realdata
def test_fr1_mocap_jitters_most_about_the_cameras_x_axis(fr1_rpy_dir):
    """The freiburg1 reference: about 0.07 degrees about the camera's x axis, 0.02-0.03 about y and
    z, and 0.1 mm along each axis, per 100 Hz sample (docs/derivation.md)."""
    out = reference_jitter(*load_tum_trajectory(fr1_rpy_dir / "groundtruth.txt"))
    rot = np.rad2deg(out["rotation_rad"])
    assert 0.05 < rot[0] < 0.09 and np.all(rot[1:] < 0.04) and rot[0] > 2 * rot[1:].max()
    assert np.all(out["translation_m"] < 0.2e-3)


def test_pair_jitter_covariance_matches_a_monte_carlo_of_interpolated_sample_noise():
    """The reference interpolated at a frame stamp keeps (1 - a)^2 + a^2 of a sample's variance;
    a pair measured against it the sum over its two frames. Oracle: independent noise drawn per
    sample, interpolated linearly at the frames (np.interp), differenced; the stamps in any order."""
    from covo_gtsam.reference_noise import pair_jitter_covariances

    rng = np.random.default_rng(4)
    t = np.cumsum(rng.uniform(0.008, 0.012, 100))  # about 100 Hz, uneven
    sd = np.array([0.0012, 0.0005, 0.0004])  # rad per axis
    ref = rng.uniform(t[5], t[-10], 6)
    cur = ref + 1 / 30
    draws = rng.normal(size=(20000, len(t), 3)) * sd

    def weights(q: float) -> np.ndarray:  # np.interp's weight of each sample at q
        return np.array([np.interp(q, t, e) for e in np.eye(len(t))])

    C = pair_jitter_covariances(rng.permutation(t), sd, ref, cur)
    for i in range(len(ref)):
        err = np.einsum("dsk,s->dk", draws, weights(ref[i]) - weights(cur[i]))  # (draws, 3)
        np.testing.assert_allclose(np.var(err, axis=0), np.diag(C[i])[:3], rtol=0.05)
        assert np.all(C[i][3:, :] == 0) and np.all(C[i][:, 3:] == 0)


def turned_reference_pairs(d: np.ndarray, n: int, rng, axis_only: int | None = None, noise: float = 1.0):
    """``n`` pairs turning up to about 4 degrees about random axes (or about ``axis_only`` alone),
    their estimates off by rotation noise drawn from random covariances (times ``noise`` in s.d.;
    right perturbation), and a
    reference that reports each as ``D T D^-1`` with ``D = Exp(d)`` (an exact conjugation)."""
    turns = rng.normal(0.0, np.deg2rad(2.0), (n, 3))
    turns[:, 1] += 1.5 * turns[:, 0]  # turns about x come with turns about y: d_x and d_y correlate
    if axis_only is not None:
        turns[:, [a for a in range(3) if a != axis_only]] = 0.0
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(turns).as_matrix()
    T[:, :3, 3] = rng.normal(0.0, 0.01, (n, 3))
    # sizes spread over a factor of 30 and strongly correlated axes: weights that matter
    A = rng.normal(0.0, 1.0, (n, 3, 3)) * np.deg2rad(10 ** rng.uniform(-1.5, 0.0, n))[:, None, None]
    A[:, :, 0] += 4.0 * A[:, :, 1]
    covs = np.zeros((n, 6, 6))
    covs[:, :3, :3] = A @ A.transpose(0, 2, 1) + np.eye(3) * np.deg2rad(0.01) ** 2
    covs[:, 3:, 3:] = np.eye(3) * 1e-6
    drawn = noise * np.einsum("nij,nj->ni", np.linalg.cholesky(covs[:, :3, :3]), rng.standard_normal((n, 3)))
    T_est = T.copy()
    T_est[:, :3, :3] = T[:, :3, :3] @ Rotation.from_rotvec(drawn).as_matrix()
    D = np.eye(4)
    D[:3, :3] = Rotation.from_rotvec(d).as_matrix()
    return T_est, D @ T @ np.linalg.inv(D), covs


def test_axes_rotation_is_recovered_with_the_spread_of_a_monte_carlo():
    d = np.deg2rad([1.5, -0.5, 0.3])
    rng = np.random.default_rng(3)
    fits = [axes_rotation(*turned_reference_pairs(d, 150, rng)) for _ in range(1000)]
    est = np.array([f["rotation_rad"] for f in fits])
    se = np.array([f["standard_error_rad"] for f in fits]).mean(axis=0)
    assert fits[0]["pairs"] == 150
    # unbiased within the Monte Carlo mean's own error, and the reported error is the spread
    np.testing.assert_array_less(np.abs(est.mean(axis=0) - d), 4 * se / np.sqrt(len(fits)))
    np.testing.assert_allclose(est.std(axis=0) / se, 1.0, atol=0.07)  # the ratio's own s.d. is about 0.022
    # a reference without a turn of its axes: d within its error of zero
    zero = axes_rotation(*turned_reference_pairs(np.zeros(3), 150, rng))
    np.testing.assert_array_less(np.abs(zero["rotation_rad"]), 4 * zero["standard_error_rad"])


@pytest.mark.parametrize("noise", [2.0, 0.5])
def test_axes_rotation_errors_grow_with_covariances_that_understate_and_do_not_shrink(noise):
    """Errors twice as large as the covariances say: the reduced chi-square reads about 4 and the
    standard errors follow the fits' spread; half as large: they stay those of the covariances,
    twice the spread."""
    rng = np.random.default_rng(5)
    fits = [axes_rotation(*turned_reference_pairs(np.deg2rad([1.0, 0.5, -0.5]), 150, rng, noise=noise))
            for _ in range(400)]
    est = np.array([f["rotation_rad"] for f in fits])
    se = np.array([f["standard_error_rad"] for f in fits]).mean(axis=0)
    assert np.mean([f["reduced_chi2"] for f in fits]) == pytest.approx(noise**2, rel=0.05)
    np.testing.assert_allclose(est.std(axis=0) / se, min(noise, 1.0), rtol=0.1)


def test_axes_rotation_about_the_axis_of_every_turn_is_not_observed():
    rng = np.random.default_rng(4)
    with pytest.raises(InputError, match="one axis only"):
        axes_rotation(*turned_reference_pairs(np.deg2rad([1.0, 0.0, 0.0]), 50, rng, axis_only=0))
    with pytest.raises(InputError, match="two or more pairs"):
        axes_rotation(*(a[:1] for a in turned_reference_pairs(np.zeros(3), 5, rng)))


FRAME_DT = 1.0 / 30.0
KEYS = ("backward_s", "forward_s", "rotation_scale")


def turning_camera(seed: int = 0, speed: float = 0.3):
    """A camera turning by sums of 0.3-1.5 Hz sines, each up to ``speed`` rad/s (by default up to
    about 1.5 rad/s in all): its exact pose (4, 4) at any time ``t`` (s), and its frames' stamps at
    30 Hz."""
    rng = np.random.default_rng(seed)
    freq, phase = rng.uniform(0.3, 1.5, (3, 3)), rng.uniform(0, 2 * np.pi, (3, 3))
    amp = speed / (2 * np.pi * freq)  # rad

    def pose(t: float) -> np.ndarray:
        G = np.eye(4)
        G[:3, :3] = Rotation.from_euler("xyz", (amp * np.sin(2 * np.pi * freq * t + phase)).sum(axis=1)).as_matrix()
        G[:3, 3] = 0.1 * np.sin(2 * np.pi * freq[:, 0] * t)
        return G

    return pose, np.arange(301) * FRAME_DT


def pairs_of(frame_poses: list) -> np.ndarray:
    """Consecutive relative poses ``T_ref,cur`` (N, 4, 4) of frame poses (4, 4) ``T_world,cam``."""
    G = np.array(frame_poses)
    return np.linalg.inv(G[:-1]) @ G[1:]


def blended_pairs(pose, t: np.ndarray, beta: float) -> np.ndarray:
    """The pairs of images each posed a share ``beta`` of the way back along the frame interval
    before it (along that interval's own motion, exactly), at the stamps ``t``."""
    import gtsam

    return pairs_of([pose(s) @ gtsam.Pose3.Expmap(-beta * gtsam.Pose3.Logmap(gtsam.Pose3(
        np.linalg.inv(pose(s - FRAME_DT)) @ pose(s)))).matrix() for s in t])


def change_response(T_est: np.ndarray, T_true: np.ndarray, stamps: np.ndarray, covs: np.ndarray | None = None):
    from covo_gtsam.reference_noise import twist_change_response

    if covs is None:
        covs = np.tile(np.eye(6) * np.deg2rad(0.1) ** 2, (len(T_true), 1, 1))
    return twist_change_response(T_est, T_true, covs, stamps[:-1], stamps[1:])


def test_twist_change_response_of_a_common_delay_and_of_a_blend_of_motions():
    """Exact poses (no first-order formula): images taken 10 ms before their stamps respond to the
    changes before and after the pair, ``a + c = L`` with ``c / a = (dt - L) / (dt + L)`` (the
    change centred ``L / 2`` before the pair's middle); images each posed 0.3 of the way back along
    the interval before them respond to the change from the pair before alone, ``a = 0.3 dt``; turns
    estimated short show as the rotation scale alone."""
    pose, t = turning_camera()
    T_true = pairs_of([pose(s) for s in t])
    L = 0.010
    delayed = change_response(pairs_of([pose(s - L) for s in t]), T_true, t)
    assert delayed["pairs"] == len(t) - 3
    assert delayed["delay_s"] == pytest.approx(L, rel=0.015)
    assert delayed["backward_s"] + delayed["forward_s"] == pytest.approx(delayed["delay_s"], rel=1e-12)
    assert delayed["forward_s"] / delayed["backward_s"] == pytest.approx((FRAME_DT - L) / (FRAME_DT + L), rel=0.01)
    beta = 0.3
    blend = change_response(blended_pairs(pose, t, beta), T_true, t)
    assert blend["backward_s"] == pytest.approx(beta * FRAME_DT, rel=0.005)
    assert abs(blend["forward_s"]) < 0.005 * beta * FRAME_DT
    assert abs(delayed["rotation_scale"]) < 1e-3 and abs(blend["rotation_scale"]) < 1e-3
    assert change_response(T_true, T_true, t)["backward_s"] == pytest.approx(0.0, abs=1e-9)
    # every turn estimated 3 % short (about its own axis): the scale alone, not a response to changes
    short = T_true.copy()
    short[:, :3, :3] = Rotation.from_rotvec(0.97 * Rotation.from_matrix(T_true[:, :3, :3]).as_rotvec()).as_matrix()
    scaled = change_response(short, T_true, t)
    assert scaled["rotation_scale"] == pytest.approx(0.03, rel=1e-3)
    assert abs(scaled["backward_s"]) < 1e-3 * L and abs(scaled["forward_s"]) < 1e-3 * L


def test_a_jittering_reference_biases_the_fit():
    """Images 10 ms before their stamps against a reference that jitters as fr1's does (0.07 / 0.03 /
    0.02 deg about x / y / z per frame): the jitter is in both the errors and the changes. Where the
    turn changes as fast as on fr1_rpy (about 0.2 rad/s per frame) the delay stays within a few per
    cent, while the split turns over: ``a`` / ``c`` go from 6.6 / 3.5 ms to about 14 / -4 ms, since
    it rests on the difference of the changes before and after, which the jitter dominates; where
    the turn changes three times slower the delay too is pulled toward zero (about 9.3 ms)."""
    sd = np.deg2rad([0.07, 0.03, 0.02])
    L = 0.010

    def mean_fit(speed: float) -> tuple[dict, dict]:
        pose, t = turning_camera(speed=speed)
        delayed = pairs_of([pose(s - L) for s in t])
        rng = np.random.default_rng(7)
        fits = []
        for _ in range(40):
            jittered = []
            for s in t:
                G = pose(s)
                G[:3, :3] = G[:3, :3] @ Rotation.from_rotvec(rng.normal(0.0, sd)).as_matrix()
                jittered.append(G)
            fits.append(change_response(delayed, pairs_of(jittered), t))
        mean = {k: float(np.mean([f[k] for f in fits])) for k in ("backward_s", "forward_s", "delay_s")}
        return mean, change_response(delayed, pairs_of([pose(s) for s in t]), t)

    fast, exact = mean_fit(0.9)  # changes of the angular velocity about 0.2 rad/s per frame, as on fr1_rpy
    assert fast["delay_s"] == pytest.approx(exact["delay_s"], rel=0.05)
    assert fast["backward_s"] > exact["backward_s"] + 5e-3 and fast["forward_s"] < 0.0 < exact["forward_s"]
    slow, exact = mean_fit(0.3)
    assert slow["delay_s"] < 0.95 * exact["delay_s"]


def test_twist_change_response_has_the_spread_of_a_monte_carlo():
    """Rotation noise drawn from each pair's covariance (sizes spread over a factor of 10, axes
    correlated) on the blend above: the fits scatter by their standard errors."""
    pose, t = turning_camera(1)
    T_true = pairs_of([pose(s) for s in t])
    blended = blended_pairs(pose, t, 0.3)
    rng = np.random.default_rng(2)
    n = len(T_true)
    A = rng.normal(0.0, 1.0, (n, 3, 3)) * np.deg2rad(0.1 * 10 ** rng.uniform(-0.5, 0.5, n))[:, None, None]
    A[:, :, 0] += 2.0 * A[:, :, 1]
    covs = np.tile(np.eye(6) * 1e-6, (n, 1, 1))
    covs[:, :3, :3] = A @ A.transpose(0, 2, 1) + np.eye(3) * np.deg2rad(0.01) ** 2
    L_chol = np.linalg.cholesky(covs[:, :3, :3])
    fits = []
    for _ in range(300):
        T_est = blended.copy()
        noise = np.einsum("nij,nj->ni", L_chol, rng.standard_normal((n, 3)))
        T_est[:, :3, :3] = blended[:, :3, :3] @ Rotation.from_rotvec(noise).as_matrix()
        fits.append(change_response(T_est, T_true, t, covs))
    est = np.array([[f[k] for k in KEYS] for f in fits])
    se = np.array([f["standard_error"] for f in fits]).mean(axis=0)
    np.testing.assert_allclose(est.std(axis=0) / se, 1.0, atol=0.12)  # the ratio's own s.d. is about 0.04
    # the delay a + c too: its standard error takes the correlation of a and c
    delay_se = np.mean([f["delay_standard_error_s"] for f in fits])
    assert np.std([f["delay_s"] for f in fits]) / delay_se == pytest.approx(1.0, abs=0.12)
    exact = change_response(blended, T_true, t, covs)  # without noise
    np.testing.assert_array_less(np.abs(est.mean(axis=0) - [exact[k] for k in KEYS]), 4 * se / np.sqrt(len(fits)))
    assert np.mean([f["reduced_chi2"] for f in fits]) == pytest.approx(1.0, rel=0.05)


def test_twist_change_response_needs_linked_pairs_and_changes():
    pose, t = turning_camera()
    T = pairs_of([pose(s) for s in t[:4]])
    with pytest.raises(InputError, match="three or more pairs linked"):
        change_response(T[:3], T[:3], t[:4])
    steady = np.tile(np.eye(4), (10, 1, 1))
    steady[:, :3, :3] = Rotation.from_rotvec([0.03, 0.0, 0.0]).as_matrix()
    with pytest.raises(InputError, match="changes too little"):
        change_response(steady, steady, np.arange(11) / 32.0)  # stamps exact in binary: no change at all
    # pairs that do not link (a lost frame between them) are left out
    stamps = np.arange(10) * FRAME_DT
    T = pairs_of([pose(s) for s in stamps])
    fit = change_response(T, T, stamps)
    from covo_gtsam.reference_noise import twist_change_response

    keep = [0, 1, 2, 3, 5, 6, 7, 8]  # the pair from frame 4 to 5 lost
    gap = twist_change_response(T[keep], T[keep], np.tile(np.eye(6), (8, 1, 1)), stamps[keep], stamps[1:][keep])
    assert fit["pairs"] == 7 and gap["pairs"] == 4


def test_metrics_json_reports_the_twist_change_response_in_milliseconds():
    from covo_gtsam.evaluation import twist_change_statistics

    pose, t = turning_camera()
    delayed, true = pairs_of([pose(s - 0.010) for s in t]), pairs_of([pose(s) for s in t])
    out = twist_change_statistics(change_response(delayed, true, t))
    assert out["delay_ms"] == pytest.approx(10.0, rel=0.015)
    assert out["backward_ms"] + out["forward_ms"] == pytest.approx(out["delay_ms"])
    assert out["pairs"] == len(t) - 3 and len(out["standard_error_ms"]) == 2
    assert all(isinstance(v, float) for v in [*out["standard_error_ms"], out["rotation_scale_standard_error"]])
