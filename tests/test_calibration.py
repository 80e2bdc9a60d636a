"""Sensor terms of the reported covariance: growth law, likelihood, maximum-likelihood fit."""

import numpy as np
import pytest

from covo_gtsam.calibration import fit_sensor_terms, frame_covariance, log_likelihood, sensor_covariance
from covo_gtsam.errors import InputError
from covo_gtsam.odometry import OdometryConfig


def _random_spd(rng, n):
    A = rng.normal(size=(n, 6, 6)) * np.array([1e-3] * 3 + [1e-3] * 3)
    return A @ A.transpose(0, 2, 1) + 1e-8 * np.eye(6)


def test_frame_covariance_rotation_random_walk_translation_persistent():
    s_r, s_t = 0.004, 0.002
    for k in (1, 2, 5):
        C = frame_covariance(s_r, s_t, k)
        np.testing.assert_allclose(np.diag(C), [s_r**2 * k] * 3 + [s_t**2 * k**2] * 3)
        assert np.count_nonzero(C - np.diag(np.diag(C))) == 0
    batch = frame_covariance(s_r, s_t, np.array([1, 3]))
    np.testing.assert_allclose(batch[1], frame_covariance(s_r, s_t, 3))


def test_sensor_covariance_scales_points_and_adds_frame_term():
    rng = np.random.default_rng(0)
    P = _random_spd(rng, 4)
    C = sensor_covariance(P, 10.0, 0.004, 0.002, np.array([1, 1, 2, 3]))
    for i, k in enumerate([1, 1, 2, 3]):
        np.testing.assert_allclose(C[i], 10.0 * P[i] + frame_covariance(0.004, 0.002, k))


def test_config_sensor_covariance_uses_the_interval_count():
    cfg = OdometryConfig()
    sensor = cfg.sensor
    P = np.diag([1e-6] * 3 + [1e-6] * 3)
    dt = 2 * sensor.frame_interval_s
    expected = sensor_covariance(P, sensor.correlation_factor, np.deg2rad(sensor.frame_sigma_rot_deg),
                                 sensor.frame_sigma_trans_m, 2)
    np.testing.assert_allclose(cfg.sensor_covariance(P, dt), expected)
    np.testing.assert_allclose(cfg.sensor_covariance(P, dt) - sensor.correlation_factor * P, cfg.frame_noise(dt))


def test_log_likelihood_matches_gaussian_density():
    rng = np.random.default_rng(1)
    C = _random_spd(rng, 3)
    e = rng.normal(size=(3, 6)) * 1e-3
    ref = np.mean([-0.5 * x @ np.linalg.solve(c, x) - 0.5 * np.log(np.linalg.det(c)) for x, c in zip(e, C)])
    assert log_likelihood(e, C) == pytest.approx(ref, rel=1e-10)
    with pytest.raises(InputError):
        log_likelihood(e, C[:, :5, :5])


@pytest.mark.slow
def test_fit_recovers_the_terms_errors_were_drawn_with():
    """Errors drawn from kappa*P + frame term (2000 pairs) give back kappa, s_r and s_t."""
    rng = np.random.default_rng(2)
    n = 2000
    # per-point covariances of varying size and shape, like real pairs
    P = _random_spd(rng, n) * rng.uniform(0.2, 3.0, size=(n, 1, 1)) * 0.02
    kappa, s_r, s_t = 8.0, np.deg2rad(0.2), 0.002
    C = sensor_covariance(P, kappa, s_r, s_t)
    e = np.einsum("nij,nj->ni", np.linalg.cholesky(C), rng.normal(size=(n, 6)))
    fit = fit_sensor_terms(e, P)
    assert fit.pairs == n
    assert fit.correlation_factor == pytest.approx(kappa, rel=0.15)
    assert fit.frame_sigma_rot_deg == pytest.approx(0.2, rel=0.1)
    assert fit.frame_sigma_trans_m == pytest.approx(0.002, rel=0.1)
    assert fit.log_likelihood == pytest.approx(log_likelihood(e, fit.covariances(P)))
    # the fit is a maximum: the true parameters do not score higher
    assert fit.log_likelihood >= log_likelihood(e, C) - 1e-9


def test_fit_of_pairs_spanning_several_intervals_uses_the_growth_laws():
    """Pairs 1-5 intervals long drawn with the frame term's growth (rotation variance k times,
    translation k^2 times) give back s_r and s_t when the fit is told each pair's intervals; told
    they are all consecutive, it overstates both."""
    rng = np.random.default_rng(5)
    n = 1200
    P = _random_spd(rng, n) * 0.002
    k = rng.integers(1, 6, size=n)
    s_r, s_t = np.deg2rad(0.1), 0.001
    C = sensor_covariance(P, 1.0, s_r, s_t, k)
    e = np.einsum("nij,nj->ni", np.linalg.cholesky(C), rng.normal(size=(n, 6)))
    fit = fit_sensor_terms(e, P, False, intervals=k)
    assert fit.frame_sigma_rot_deg == pytest.approx(0.1, rel=0.1)
    assert fit.frame_sigma_trans_m == pytest.approx(0.001, rel=0.1)
    with pytest.raises(InputError, match="intervals"):
        fit_sensor_terms(e, P, False, intervals=k[:-1])
    with pytest.raises(InputError, match="intervals"):
        fit_sensor_terms(e, P, False, intervals=np.zeros(n))
    as_consecutive = fit_sensor_terms(e, P, False)
    assert as_consecutive.frame_sigma_trans_m > 1.5 * fit.frame_sigma_trans_m
    assert as_consecutive.frame_sigma_rot_deg > 1.2 * fit.frame_sigma_rot_deg


def test_fit_rejects_bad_input():
    rng = np.random.default_rng(3)
    P = _random_spd(rng, 5)
    with pytest.raises(InputError, match="at least 10"):
        fit_sensor_terms(np.zeros((5, 6)), P)
    with pytest.raises(InputError, match=r"\(N, 6\)"):
        fit_sensor_terms(np.zeros((12, 3)), _random_spd(rng, 12))
    e = np.zeros((12, 6))
    e[0, 0] = np.nan
    with pytest.raises(InputError, match="finite"):
        fit_sensor_terms(e, _random_spd(rng, 12))


def test_timing_term_matches_monte_carlo_of_stamp_errors():
    """Two frames captured tau_ref and tau_cur seconds after their stamps (tau ~ N(0, s^2)) of a
    camera moving with constant body twist xi: the relative pose between the stamps differs from
    the captured one by the right perturbation Log(T_stamps^-1 T_captured); its covariance is the
    timing term s^2 (xi xi^T + xi xi^T)."""
    import gtsam

    from covo_gtsam.calibration import timing_covariance

    rng = np.random.default_rng(5)
    xi = np.array([0.3, -1.2, 0.5, 0.05, 0.2, -0.1])  # rad/s, m/s
    dt, s = 1 / 30, 0.003
    T_stamps = gtsam.Pose3.Expmap(dt * xi)
    errs = []
    for tau_ref, tau_cur in rng.normal(0, s, size=(20000, 2)):
        T_cap = gtsam.Pose3.Expmap(tau_ref * xi).inverse() * gtsam.Pose3.Expmap((dt + tau_cur) * xi)
        errs.append(gtsam.Pose3.Logmap(T_stamps.between(T_cap)))
    emp = np.cov(np.array(errs).T)
    pred = timing_covariance(np.stack([xi, xi]), s)
    np.testing.assert_allclose(emp, pred, atol=0.03 * np.abs(pred).max())
    # the full model adds it to kappa * C_points + frame term
    P = np.eye(6) * 1e-6
    C = sensor_covariance(P, 2.0, 0.001, 0.002, 1, {"timing": timing_covariance(np.stack([xi, xi]))}, {"timing": s})
    np.testing.assert_allclose(C, sensor_covariance(P, 2.0, 0.001, 0.002) + pred)


def test_stamp_error_basis_matches_monte_carlo_with_the_twist_changing_over_a_turn():
    """As above, but the twists at the two frames differ and the pair turns by 40 deg, so the
    reference's twist must be carried into the current frame (a constant twist cannot tell): each
    frame captured tau_f ~ N(0, w_f s^2) off its stamp moves the pair to
    Exp(tau_ref xi_ref)^-1 T Exp(tau_cur xi_cur); the covariance of the right perturbation."""
    import gtsam

    from covo_gtsam.calibration import stamp_error_basis, timing_covariance

    rng = np.random.default_rng(8)
    xi_ref = np.array([0.3, -1.2, 0.5, 0.05, 0.2, -0.1])  # rad/s, m/s
    xi_cur = np.array([-0.8, 0.4, 1.1, 0.3, -0.1, 0.2])
    T = gtsam.Pose3(gtsam.Rot3.Rodrigues(0.4, -0.5, 0.3), np.array([0.2, -0.1, 0.3]))
    s, weights = 0.003, (1.0, 0.25)
    errs = []
    for tau_ref, tau_cur in rng.normal(0, s, size=(20000, 2)) * np.sqrt(weights):
        moved = gtsam.Pose3.Expmap(tau_ref * xi_ref).inverse() * T * gtsam.Pose3.Expmap(tau_cur * xi_cur)
        errs.append(gtsam.Pose3.Logmap(T.between(moved)))
    emp = np.cov(np.array(errs).T)
    pred = s**2 * stamp_error_basis(T.matrix(), xi_ref, xi_cur, weights)
    np.testing.assert_allclose(emp, pred, atol=0.03 * np.abs(pred).max())
    # the reference's twist as it is, in its own frame, is off by far more than the sampling
    wrong = s**2 * timing_covariance(np.stack([xi_ref, xi_cur]) * np.sqrt(weights)[:, None])
    assert np.abs(wrong - emp).max() > 0.2 * np.abs(pred).max()


def test_latency_term_matches_monte_carlo_of_a_common_stamp_delay():
    """Both frames' stamps L seconds off their captures (one L ~ N(0, s^2) for the pair) on a
    trajectory whose twist changes between the frames: the relative pose between the shifted
    times differs from the captured one by Log(T^-1 T_shifted), with covariance s^2 b b^T,
    b = xi_cur - Ad(T^-1) xi_ref. The twists at the frames come from finite differences of the
    trajectory (not from the formula's assumptions); a delay shared by both frames gives a
    smaller error than independent ones (the timing term) when the twist hardly changes."""
    import gtsam

    from covo_gtsam.calibration import latency_basis, twist_change

    xi0 = np.array([0.3, -1.2, 0.5, 0.05, 0.2, -0.1])  # rad/s, m/s
    acc = np.array([-2.0, 3.5, 1.0, 0.15, -0.2, 0.05])  # rad/s^2, m/s^2

    def pose(t: float) -> gtsam.Pose3:
        return gtsam.Pose3.Expmap(t * xi0 + 0.5 * t * t * acc)

    def twist(t: float, h: float = 1e-6) -> np.ndarray:
        return gtsam.Pose3.Logmap(pose(t - h).between(pose(t + h))) / (2 * h)

    t0, t1, s = 0.0, 0.3, 0.01  # a keyframe pair: the frames' axes differ by 0.28 rad
    T = pose(t0).between(pose(t1))
    rng = np.random.default_rng(8)
    errs = np.array([gtsam.Pose3.Logmap(T.between(pose(t0 + L).between(pose(t1 + L))))
                     for L in rng.normal(0, s, size=20000)])
    B = latency_basis(T.matrix(), twist(t0), twist(t1))
    np.testing.assert_allclose(np.cov(errs.T), s**2 * B, atol=0.05 * s**2 * np.abs(B).max())
    # one fixed delay: the pair moves by L b, sign included
    b = twist_change(T.matrix(), twist(t0), twist(t1))
    L = 0.002
    moved = gtsam.Pose3.Logmap(T.between(pose(t0 + L).between(pose(t1 + L))))
    np.testing.assert_allclose(moved, L * b, atol=0.02 * L * np.abs(b).max())
    # the wrong conventions fail that check: no adjoint, the adjoint of T, the roles swapped
    Ad_inv, Ad = T.inverse().AdjointMap(), T.AdjointMap()
    for wrong in (twist(t1) - twist(t0), twist(t1) - Ad @ twist(t0), twist(t0) - Ad @ twist(t1)):
        assert not np.allclose(moved, L * wrong, atol=0.02 * L * np.abs(b).max())
    assert not np.allclose(moved, -L * b, atol=0.02 * L * np.abs(b).max())
    assert np.allclose(Ad_inv @ Ad, np.eye(6))
    # the same twist at both frames (constant velocity): the common delay cancels to first order
    xi = twist(t0)
    T_cv = gtsam.Pose3.Expmap(xi / 30)
    assert np.abs(latency_basis(T_cv.matrix(), xi, xi)).max() < 1e-12 * np.abs(xi).max() ** 2


def test_twist_changes_subtract_the_estimation_noise_and_use_only_past_pairs():
    """The latency term's basis from consecutive pairs' twists drawn around a true twist change
    Delta with anisotropic estimation noise, the later pair rotated against the earlier one: the
    basis gives back Delta Delta^T (rotation block) within the sampling error; subtracting the
    noise without carrying the earlier twist's noise by Ad, or three times too much of it, or none,
    misses it. Pure noise gives a basis far below the raw outer products. The basis is the mean of
    what was added before."""
    import gtsam

    from covo_gtsam.calibration import TwistChanges, twist_change

    rng = np.random.default_rng(3)
    T = gtsam.Pose3(gtsam.Rot3.Rodrigues(0.0, 0.0, 1.2), np.array([0.1, 0.0, 0.0]))  # a large turn
    Ad = T.inverse().AdjointMap()
    N_ref = np.diag([4.0, 0.25, 1.0, 1.0, 1.0, 1.0]) * 0.01  # (rad/s)^2, (m/s)^2: noise of each twist
    N_cur = np.diag([0.25, 1.0, 4.0, 1.0, 1.0, 1.0]) * 0.01
    xi_ref = np.array([0.2, -1.0, 0.3, 0.05, 0.0, 0.1])
    delta = np.array([0.3, 0.1, -0.2, 0.0, 0.0, 0.0])  # rad/s: the true change, about the noise's size
    xi_cur = Ad @ xi_ref + delta
    n = 20000
    a = xi_ref + rng.multivariate_normal(np.zeros(6), N_ref, n)
    b = xi_cur + rng.multivariate_normal(np.zeros(6), N_cur, n)

    def basis(noise_ref, noise_cur, pairs=n):
        tc = TwistChanges(window=pairs)
        for x, y in zip(a[:pairs], b[:pairs]):
            tc.add(T.matrix(), x, y, noise_ref, noise_cur)
        return tc.basis()

    expected = np.zeros((6, 6))
    expected[:3, :3] = np.outer(delta[:3], delta[:3])
    got = basis(N_ref, N_cur)
    np.testing.assert_allclose(got, expected, atol=0.006)  # sampling error about 0.002
    # the same changes between pairs two intervals long: per interval, a quarter
    two = TwistChanges(window=n)
    for x, y in zip(a, b):
        two.add(T.matrix(), x, y, N_ref, N_cur, intervals=2)
    np.testing.assert_allclose(two.basis(), got / 4, rtol=1e-9, atol=1e-15)
    assert np.all(got[3:] == 0) and np.all(got[:, 3:] == 0)
    tol = 0.006
    assert np.abs(basis(np.zeros((6, 6)), np.zeros((6, 6))) - expected).max() > 3 * tol  # no subtraction
    assert np.abs(basis(3 * N_ref, 3 * N_cur) - expected).max() > 3 * tol  # too much
    # without Ad: the earlier twist's noise subtracted in the wrong axes
    wrong = np.mean([np.outer(twist_change(T.matrix(), x, y), twist_change(T.matrix(), x, y))[:3, :3]
                     - (N_cur + N_ref)[:3, :3] for x, y in zip(a, b)], axis=0)
    assert np.abs(np.pad(wrong, ((0, 3), (0, 3))) - expected).max() > 3 * tol
    # pure noise (no change): far below the raw outer products
    noise_only = TwistChanges(window=n)
    raw = np.zeros((3, 3))
    for x, y in zip(a[:2000], (Ad @ xi_ref) + rng.multivariate_normal(np.zeros(6), N_cur, 2000)):
        noise_only.add(T.matrix(), x, y, N_ref, N_cur)
        d = twist_change(T.matrix(), x, y)[:3]
        raw += np.outer(d, d) / 2000
    assert np.trace(noise_only.basis()) < 0.1 * np.trace(raw)
    # the mean of what was added before, nothing else
    tc = TwistChanges(window=2)
    assert np.all(tc.basis() == 0)
    tc.add(T.matrix(), a[0], b[0], N_ref, N_cur)
    first = tc.basis()
    tc.add(T.matrix(), a[1], b[1], N_ref, N_cur)
    assert not np.allclose(tc.basis(), first)


def test_central_change_basis_matches_monte_carlo_of_a_common_stamp_delay():
    """The latency basis a pair gets one frame later (:func:`central_change_basis`) from the mean
    twists of the pair before and the pair after it (each ``Log(T) / dt`` over its own interval,
    never the pair's own): on a trajectory whose twist changes, a delay ``L ~ N(0, s^2)`` shared by
    the pair's two frames moves the pair with a covariance (Monte Carlo) that ``s^2`` times the
    basis matches. Half the change from the pair before to the pair after is the change across the
    pair; the whole change (no quarter), or the pair's own twist in place of the one after, fails.
    The twists' noise is taken off as for one measured change (:func:`known_change_basis`, tested
    below with the same subtraction)."""
    import gtsam

    from covo_gtsam.calibration import central_change_basis

    xi0 = np.array([0.3, -1.2, 0.5, 0.05, 0.2, -0.1])  # rad/s, m/s
    acc = np.array([-20.0, 35.0, 10.0, 1.5, -2.0, 0.5])  # rad/s^2, m/s^2: a hand-held camera's bursts

    def pose(t: float) -> gtsam.Pose3:
        return gtsam.Pose3.Expmap(t * xi0 + 0.5 * t * t * acc)

    dt, s = 1 / 30, 0.01
    T = pose(0.0).between(pose(dt))
    w_before = gtsam.Pose3.Logmap(pose(-dt).between(pose(0.0))) / dt
    w_own = gtsam.Pose3.Logmap(T) / dt
    w_after = gtsam.Pose3.Logmap(pose(dt).between(pose(2 * dt))) / dt
    zero = np.zeros((6, 6))
    B = central_change_basis(T.matrix(), w_before, w_after, zero, zero)
    rng = np.random.default_rng(3)
    errs = np.array([gtsam.Pose3.Logmap(T.between(pose(L).between(pose(dt + L)))) for L in rng.normal(0, s, 20000)])
    C = np.cov(errs.T)

    def close(M: np.ndarray) -> bool:  # block by block: the translation's entries are ten times smaller
        return all(np.allclose(M[a, b], C[a, b], atol=0.05 * np.abs(C[a, b]).max())
                   for a in (slice(0, 3), slice(3, 6)) for b in (slice(0, 3), slice(3, 6)))

    assert close(s**2 * B)
    assert not close(4 * s**2 * B)
    assert not close(s**2 * central_change_basis(T.matrix(), w_before, w_own, zero, zero))
    wrong_translation = s**2 * B
    wrong_translation[3:, 3:] *= 10
    assert not close(wrong_translation)  # the translation block is checked too
    # the twists' noise is taken off: a noise-free change given noise loses some of its size
    N = np.eye(6) * 1e-3
    assert np.trace(central_change_basis(T.matrix(), w_before, w_after, N, N)) < np.trace(B) - 1e-4


def test_known_change_basis_gives_back_a_measured_change_without_its_noise():
    """One measured change of the twist from a keyframe to a later frame (the later frame turned
    1.2 rad against it), both twists drawn around the truth with anisotropic noise: averaged over
    draws, the basis is the true change's ``b b^T`` (rotation block) plus the noise across the
    change's direction, which one change cannot tell from the change (conservative; the twists'
    noise carried by Ad, as the Monte Carlo of a delay above checks :func:`twist_change`). Without
    the noise subtracted, or without Ad on the keyframe's noise, it is not. Noise-free it is the
    latency basis's rotation block, and every draw is positive semidefinite."""
    import gtsam

    from covo_gtsam.calibration import known_change_basis, latency_basis, twist_change

    rng = np.random.default_rng(5)
    T = gtsam.Pose3(gtsam.Rot3.Rodrigues(0.0, 0.0, 1.2), np.array([0.1, 0.0, 0.0])).matrix()
    Ad = gtsam.Pose3(T).inverse().AdjointMap()
    N_ref = np.diag([4.0, 0.25, 1.0, 1.0, 1.0, 1.0]) * 0.04  # (rad/s)^2: 0.1-0.4 rad/s per axis
    N_cur = np.diag([0.25, 1.0, 4.0, 1.0, 1.0, 1.0]) * 0.04
    xi_ref = np.array([0.2, -1.0, 0.3, 0.05, 0.0, 0.1])
    delta = np.array([1.5, 0.5, -1.0, 0.0, 0.0, 0.0])  # rad/s: well above the noise
    xi_cur = Ad @ xi_ref + delta
    zero = np.zeros((6, 6))
    np.testing.assert_allclose(known_change_basis(T, xi_ref, xi_cur, zero, zero)[:3, :3],
                               latency_basis(T, xi_ref, xi_cur)[:3, :3], rtol=1e-12)
    assert np.all(known_change_basis(T, xi_ref, xi_cur, zero, zero)[3:] == 0)
    n = 20000
    a = xi_ref + rng.multivariate_normal(np.zeros(6), N_ref, n)
    b = xi_cur + rng.multivariate_normal(np.zeros(6), N_cur, n)
    draws = np.array([known_change_basis(T, x, y, N_ref, N_cur) for x, y in zip(a, b)])
    assert np.linalg.eigvalsh(draws[:, :3, :3]).min() > -1e-12
    N = (N_cur + Ad @ N_ref @ Ad.T)[:3, :3]
    u = delta[:3] / np.linalg.norm(delta[:3])
    P = np.eye(3) - np.outer(u, u)
    expected = np.outer(delta[:3], delta[:3]) + P @ N @ P
    tol = 0.025  # sampling error about 0.01
    np.testing.assert_allclose(draws.mean(axis=0)[:3, :3], expected, atol=tol)
    raw = np.mean([np.outer(d, d) for d in (twist_change(T, x, y)[:3] for x, y in zip(a, b))], axis=0)
    assert np.abs(raw - expected).max() > 2 * tol  # the noise left in
    no_ad = np.mean([known_change_basis(T, x, y, zero, N_cur + N_ref) for x, y in zip(a, b)], axis=0)
    assert np.abs(no_ad[:3, :3] - expected).max() > 2 * tol  # the keyframe's noise in the wrong axes
    # pure noise: about two thirds of it stays (noise along the drawn direction is taken off, the
    # rest cannot be told from a change), against all of it without the subtraction
    y = Ad @ xi_ref + rng.multivariate_normal(np.zeros(6), N_cur, 2000)
    pure = np.mean([known_change_basis(T, x, z, N_ref, N_cur) for x, z in zip(a, y)], axis=0)
    unsubtracted = np.mean([np.outer(d, d) for d in (twist_change(T, x, z)[:3] for x, z in zip(a, y))], axis=0)
    assert np.trace(pure) < 0.75 * np.trace(unsubtracted)


@pytest.mark.slow
def test_fit_recovers_frame_level_terms():
    """Errors drawn with a timing term (tau 3 ms, over twists of varying speed) and a rank-one
    depth-scale term (0.2 %) give back both sigmas and kappa."""
    from covo_gtsam.calibration import timing_covariance

    rng = np.random.default_rng(6)
    n = 2000
    P = _random_spd(rng, n) * rng.uniform(0.2, 3.0, size=(n, 1, 1)) * 0.02
    twists = rng.normal(size=(n, 2, 6)) * np.array([1.0] * 3 + [0.3] * 3)
    b = rng.normal(size=(n, 6)) * np.array([0.1] * 3 + [2.0] * 3)  # rad, m per unit scale error
    bases = {"timing": timing_covariance(twists), "depth_scale": np.einsum("ni,nj->nij", b, b)}
    C = sensor_covariance(P, 2.0, np.deg2rad(0.1), 0.0005, 1, bases, {"timing": 0.003, "depth_scale": 0.002})
    e = np.einsum("nij,nj->ni", np.linalg.cholesky(C), rng.normal(size=(n, 6)))
    fit = fit_sensor_terms(e, P, bases=bases)
    assert fit.sigmas["timing"] == pytest.approx(0.003, rel=0.1)
    assert fit.sigmas["depth_scale"] == pytest.approx(0.002, rel=0.1)
    assert fit.correlation_factor == pytest.approx(2.0, rel=0.15)
    assert fit.config_values()["timing_sigma_s"] == fit.sigmas["timing"]
    with pytest.raises(InputError, match="basis 'timing'"):
        fit_sensor_terms(e, P, bases={"timing": bases["timing"][:5]})


@pytest.mark.slow
def test_a_term_the_errors_do_not_have_is_fitted_to_exactly_zero():
    """Errors drawn with the depth-scale term alone (no timing error): the fit reports the timing
    term as exactly 0, not as the 1e-60 s where Nelder-Mead stops on the log scale, and keeps the
    depth-scale term; its log-likelihood is that of the reported terms."""
    from covo_gtsam.calibration import log_likelihood, timing_covariance

    rng = np.random.default_rng(8)
    n = 1500
    P = _random_spd(rng, n) * rng.uniform(0.2, 3.0, size=(n, 1, 1)) * 0.02
    b = rng.normal(size=(n, 6)) * np.array([0.1] * 3 + [2.0] * 3)
    bases = {"timing": timing_covariance(rng.normal(size=(n, 2, 6)) * np.array([1.0] * 3 + [0.3] * 3)),
             "depth_scale": np.einsum("ni,nj->nij", b, b)}
    C = sensor_covariance(P, 1.0, 0.0, 0.0, 1, bases, {"timing": 0.0, "depth_scale": 0.002})
    e = np.einsum("nij,nj->ni", np.linalg.cholesky(C), rng.normal(size=(n, 6)))
    fit = fit_sensor_terms(e, P, False, bases=bases)
    assert fit.sigmas["timing"] == 0.0
    assert fit.sigmas["depth_scale"] == pytest.approx(0.002, rel=0.1)
    assert fit.log_likelihood == pytest.approx(log_likelihood(e, fit.covariances(P, bases)), abs=1e-9)


def test_fit_without_the_rotation_frame_term_holds_it_at_zero():
    """Errors drawn without a rotation frame term but with a timing term: the fit that holds ``s_r``
    at 0 gives back the timing term and kappa 1; errors drawn with a frame term are then less likely
    under that fit than under the full one, which finds the frame term."""
    from covo_gtsam.calibration import timing_covariance

    rng = np.random.default_rng(7)
    n = 2000
    P = _random_spd(rng, n) * rng.uniform(0.2, 3.0, size=(n, 1, 1)) * 0.02
    bases = {"timing": timing_covariance(rng.normal(size=(n, 2, 6)) * np.array([1.0] * 3 + [0.3] * 3))}
    for s_r in (0.0, np.deg2rad(0.3)):
        C = sensor_covariance(P, 1.0, s_r, 0.0005, 1, bases, {"timing": 0.003})
        e = np.einsum("nij,nj->ni", np.linalg.cholesky(C), rng.normal(size=(n, 6)))
        held = fit_sensor_terms(e, P, False, bases=bases, frame_rotation=False)
        full = fit_sensor_terms(e, P, False, bases=bases)
        assert held.frame_sigma_rot_deg == 0.0 and held.correlation_factor == 1.0
        if s_r == 0.0:
            assert held.sigmas["timing"] == pytest.approx(0.003, rel=0.1)
            assert full.log_likelihood - held.log_likelihood < 0.01
        else:
            assert full.frame_sigma_rot_deg == pytest.approx(0.3, rel=0.1)
            assert full.log_likelihood - held.log_likelihood > 0.1


def test_twist_changes_learn_how_much_of_the_direction_carries_over():
    """Changes about one fixed axis keep the basis's direction (share 0); changes whose axis is new
    each time spread it over all axes (share at least 0.75), the basis's size (trace) kept."""
    from covo_gtsam.calibration import ISOTROPIC_SHARES, TwistChanges

    rng = np.random.default_rng(4)
    T = np.eye(4)
    noise = np.diag([1e-4] * 3 + [1e-6] * 3)
    axis = np.array([0.0, 0.0, 1.0])
    fixed, wandering = TwistChanges(), TwistChanges()
    twist_f, twist_w = np.zeros(6), np.zeros(6)
    for _ in range(60):
        step_f = np.concatenate([axis * rng.normal(scale=0.3), np.zeros(3)])
        d = rng.normal(size=3)
        step_w = np.concatenate([0.3 * d / np.linalg.norm(d), np.zeros(3)])
        fixed.add(T, twist_f, twist_f + step_f, noise, noise)
        wandering.add(T, twist_w, twist_w + step_w, noise, noise)
        twist_f, twist_w = twist_f + step_f, twist_w + step_w
    assert fixed.share == ISOTROPIC_SHARES[0]
    assert wandering.share >= 0.75
    assert np.trace(wandering.basis()) == pytest.approx(np.trace(wandering._mean), rel=1e-12)
    assert np.all(wandering.basis()[3:] == 0) and np.all(wandering.basis()[:, 3:] == 0)


def test_twist_changes_spread_what_a_window_not_yet_full_cannot_tell():
    """Changes about one axis fed into a window of 10 one by one: a first change says little about
    the next one's direction, so the basis it gives also covers turns about the other axes, and
    less so as the window fills, down to the learnt share (0 here: the direction carries over) when
    it is full; its size (trace) is the changes' mean square throughout. A basis thin across from
    the first change on left the pairs after a run's start overconfident (docs/derivation.md, "The
    history's length")."""
    from covo_gtsam.calibration import TwistChanges

    tc = TwistChanges(window=10)
    twist, across = np.zeros(6), []
    for n in range(14):
        step = np.array([0.0, 0.0, 0.3 if n % 2 else -0.3, 0.0, 0.0, 0.0])
        tc.add(np.eye(4), twist, twist + step, np.zeros((6, 6)), np.zeros((6, 6)))
        twist = twist + step
        B = tc.basis()
        assert np.trace(B) == pytest.approx(0.09, rel=1e-9)
        across.append((B[0, 0] + B[1, 1]) / np.trace(B))
    assert tc.share == 0.0
    assert across[0] > 0.5  # 9/10 of the size spread evenly: 0.6 across
    assert all(a > b for a, b in zip(across[:9], across[1:10]))
    assert across[9:] == [0.0] * 5


def test_twist_changes_clear_forgets_the_window():
    """After clear() the basis is that of a fresh history fed the same later changes."""
    from covo_gtsam.calibration import TwistChanges

    rng = np.random.default_rng(7)
    noise = np.eye(6) * 1e-4
    early = [rng.normal(size=(2, 6)) for _ in range(8)]
    late = [rng.normal(size=(2, 6)) for _ in range(4)]
    used, fresh = TwistChanges(), TwistChanges()
    for a, b in early:
        used.add(np.eye(4), a, b, noise, noise)
    used.clear()
    for a, b in late:
        used.add(np.eye(4), a, b, noise, noise)
        fresh.add(np.eye(4), a, b, noise, noise)
    used.share = fresh.share  # the share's scores are kept on purpose: they describe the motion
    np.testing.assert_allclose(used.basis(), fresh.basis(), rtol=1e-12, atol=1e-15)


def test_twist_changes_share_waits_then_follows_a_change_of_motion():
    """The share stays 0 for the first changes, and scores fade: after turns about one axis, turns
    about new axes each time move the share off 0 (scores that never faded would keep it)."""
    from covo_gtsam.calibration import SHARE_MIN_CHANGES, TwistChanges

    rng = np.random.default_rng(5)
    noise = np.diag([1e-4] * 3 + [1e-6] * 3)
    tc = TwistChanges()
    twist = np.zeros(6)
    shares = []
    for n in range(400):
        if n < 150:
            step = np.concatenate([[0.0, 0.0, rng.normal(scale=0.3)], np.zeros(3)])
        else:
            d = rng.normal(size=3)
            step = np.concatenate([0.3 * d / np.linalg.norm(d), np.zeros(3)])
        tc.add(np.eye(4), twist, twist + step, noise, noise)
        twist = twist + step
        shares.append(tc.share)
    assert max(shares[:150]) == 0.0
    assert shares[-1] >= 0.75
    # from the start, wandering turns: 0 until SHARE_MIN_CHANGES changes are scored, then more
    fresh, twist, early = TwistChanges(), np.zeros(6), []
    for _ in range(30):
        d = rng.normal(size=3)
        step = np.concatenate([0.3 * d / np.linalg.norm(d), np.zeros(3)])
        fresh.add(np.eye(4), twist, twist + step, noise, noise)
        twist = twist + step
        early.append(fresh.share)
    # a share chosen from one or two scored changes would be noise: the first three keep 0
    assert early[:3] == [0.0] * 3
    assert all(s == 0.0 for s in early[:SHARE_MIN_CHANGES]) and max(early) > 0.0


@pytest.mark.slow
def test_fit_reaches_the_maximum_another_optimiser_finds():
    """Five rank-one terms of random sizes: a single Nelder-Mead search stops short here (by 0.05 per
    pair); the fit restarts it, and Powell's method started from the fit's terms gains nothing."""
    from scipy.optimize import minimize

    rng = np.random.default_rng(2)
    n = 600
    P = _random_spd(rng, n) * rng.uniform(0.2, 3.0, size=(n, 1, 1)) * 0.02
    bases = {}
    for k in range(5):
        b = rng.normal(size=(n, 6)) * rng.uniform(0.05, 2, 6)
        bases[f"term{k}"] = np.einsum("ni,nj->nij", b, b)
    sigmas = {k: 10 ** rng.uniform(-3.5, -2) for k in bases}
    C = sensor_covariance(P, 1.0, np.deg2rad(0.1), 0.0005, 1, bases, sigmas)
    e = np.einsum("nij,nj->ni", np.linalg.cholesky(C), rng.normal(size=(n, 6)))
    fit = fit_sensor_terms(e, P, False, bases=bases)

    def cost(x):
        p = np.exp(x)
        return -log_likelihood(e, sensor_covariance(P, 1.0, p[0], p[1], 1, bases, dict(zip(bases, p[2:]))))

    x = np.log([np.deg2rad(fit.frame_sigma_rot_deg), fit.frame_sigma_trans_m, *(fit.sigmas[k] for k in bases)])
    assert -cost(x) == pytest.approx(fit.log_likelihood, abs=1e-9)
    polished = minimize(cost, x, method="Powell", options={"xtol": 1e-8, "ftol": 1e-12})
    assert -polished.fun - fit.log_likelihood < 1e-5


def test_span_basis_is_the_growth_of_a_persisting_per_interval_translation_error():
    """Monte Carlo of the span term's meaning: a translation error u (s.d. d per axis) that
    persists over a pair's k intervals adds up to k u; the basis is what k intervals have beyond
    the first, Cov(k u) - Cov(u) = d^2 (k^2 - 1), zero for consecutive pairs, translation only."""
    from covo_gtsam.calibration import span_basis

    rng = np.random.default_rng(7)
    d = 0.003
    u = rng.normal(scale=d, size=(200_000, 3))
    for k in (1, 2, 3, 7):
        B = span_basis(d, k)
        extra = np.cov((k * u).T) - np.cov(u.T)
        np.testing.assert_allclose(B[3:, 3:], extra, atol=0.02 * d**2 * k**2)
        assert not np.any(B[:3]) and not np.any(B[:, :3])
    assert not np.any(span_basis(d, 1))
    batch = span_basis(np.array([0.001, 0.002]), np.array([2, 3]))
    np.testing.assert_allclose(batch[1], span_basis(0.002, 3))


def test_span_factor_fit_recovers_the_factor_errors_were_drawn_with():
    """Errors drawn from C + c^2 B (pairs over 2-5 intervals, each with its recent translation
    per interval) give back c; with c = 0 the fit says 0 or a small factor."""
    from covo_gtsam.calibration import fit_span_factor, span_basis

    rng = np.random.default_rng(3)
    n = 1500
    C = _random_spd(rng, n) * rng.uniform(0.2, 3.0, size=(n, 1, 1)) * 0.01
    B = span_basis(rng.uniform(0.001, 0.02, n), rng.integers(2, 6, n))
    for c in (0.2, 0.8):
        e = np.einsum("nij,nj->ni", np.linalg.cholesky(C + c**2 * B), rng.normal(size=(n, 6)))
        assert fit_span_factor(e, C, B) == pytest.approx(c, rel=0.1)
    e = np.einsum("nij,nj->ni", np.linalg.cholesky(C), rng.normal(size=(n, 6)))
    assert fit_span_factor(e, C, B) < 0.05
    with pytest.raises(InputError, match="at least 10 pairs over more than one interval"):
        fit_span_factor(e[:20], C[:20], span_basis(0.01, np.ones(20)))
    with pytest.raises(InputError, match="finite"):
        fit_span_factor(np.full_like(e, np.nan), C, B)
