"""Property tests: well-posed random scenes give a valid covariance that covers the truth; garbage
gives the package's exception and nothing else."""

from __future__ import annotations

import gtsam
import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from covo_gtsam.errors import CovoError
from covo_gtsam.estimator import estimate_relative_pose
from covo_gtsam.metrics import chi2_quantile

# "within 5 sigma" for a 6-dof error: the Mahalanobis distance^2 below the chi2(6) quantile whose tail
# probability equals the two-sided 5-sigma tail of a Gaussian (5.7e-7).
BOUND_6DOF = chi2_quantile(1 - 5.7e-7, 6)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(20, 300), weighting=st.sampled_from(["consistent", "thesis"]))
def test_random_well_posed_scenes(seed, n, weighting):
    rng = np.random.default_rng(seed)
    T = gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3) * np.deg2rad(20)), rng.uniform(-0.5, 0.5, 3))
    X1 = rng.uniform([-1.5, -1.0, 0.5], [1.5, 1.0, 4.0], size=(n, 3))
    X0_true = X1 @ T.rotation().matrix().T + T.translation()

    def covs():
        A = rng.normal(scale=rng.uniform(0.002, 0.02), size=(n, 3, 3))
        return A @ A.transpose(0, 2, 1) + 1e-6 * np.eye(3)

    Q0, Q1 = covs(), covs()
    X0 = X0_true + np.einsum("nij,nj->ni", np.linalg.cholesky(Q0), rng.standard_normal((n, 3)))
    X1n = X1 + np.einsum("nij,nj->ni", np.linalg.cholesky(Q1), rng.standard_normal((n, 3)))
    res = estimate_relative_pose(X0, X1n, Q0, Q1, weighting="consistent")
    C = res.covariance
    assert np.all(np.isfinite(C)) and np.allclose(C, C.T) and np.linalg.eigvalsh(C)[0] > 0
    xi = gtsam.Pose3.Logmap(res.pose.between(T))
    assert xi @ np.linalg.solve(C, xi) < BOUND_6DOF
    # the thesis weighting still returns a valid covariance (it is only overconfident)
    res_t = estimate_relative_pose(X0, X1n, Q0, Q1, weighting=weighting)
    assert np.all(np.isfinite(res_t.covariance)) and np.linalg.eigvalsh(res_t.covariance)[0] > 0


garbage_arrays = st.one_of(
    st.just(np.zeros((0, 3))),
    st.builds(lambda n: np.full((n, 3), np.nan), st.integers(1, 10)),
    st.builds(lambda n: np.ones((n, 2)), st.integers(1, 10)),
    st.builds(lambda n: np.ones((n, 3, 1)), st.integers(1, 10)),
    st.builds(lambda n, s: np.random.default_rng(s).normal(size=(n, 3)), st.integers(0, 6), st.integers(0, 100)),
    st.builds(lambda n: np.full((n, 3), np.inf), st.integers(1, 5)),
    st.just("not an array"),
)
garbage_covs = st.one_of(
    st.builds(lambda n: -np.tile(np.eye(3), (n, 1, 1)), st.integers(1, 10)),
    st.builds(lambda n: np.zeros((n, 3, 3)), st.integers(1, 10)),
    st.builds(lambda n, s: np.random.default_rng(s).normal(size=(n, 3, 3)), st.integers(1, 10), st.integers(0, 100)),
    st.builds(lambda n: np.tile(np.eye(3), (n, 1, 1)) * 1e-4, st.integers(0, 10)),
    st.just(np.full((4, 3, 3), np.nan)),
)


@settings(max_examples=60, deadline=None)
@given(X0=garbage_arrays, X1=garbage_arrays, Q0=garbage_covs, Q1=garbage_covs)
def test_garbage_raises_package_error(X0, X1, Q0, Q1):
    try:
        res = estimate_relative_pose(X0, X1, Q0, Q1)
    except CovoError:
        return
    # if it was accepted after all, the result must be valid
    assert np.all(np.isfinite(res.covariance)) and np.linalg.eigvalsh(res.covariance)[0] > 0
    assert np.all(np.isfinite(res.matrix))
