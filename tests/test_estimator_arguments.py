"""estimate_relative_pose's arguments and errors: iteration counts, thresholds, initial poses and scales
it cannot use are refused by name; GTSAM's and numpy's failures become one-line package errors."""

from __future__ import annotations

import numpy as np
import pytest

from covo_gtsam.errors import CovoError, DegenerateGeometryError, InputError
from covo_gtsam.estimator import estimate_relative_pose
from covo_gtsam.noise import PointNoiseModel
from covo_gtsam.simulation import SimulationConfig, make_scene, noisy_measurements


@pytest.fixture(scope="module")
def pairs():
    rng = np.random.default_rng(0)
    scene = make_scene(SimulationConfig(num_points=60), rng)
    X0, Q0 = noisy_measurements(scene.X0, scene.camera, PointNoiseModel(), rng)
    X1, Q1 = noisy_measurements(scene.X1, scene.camera, PointNoiseModel(), rng)
    return X0, X1, Q0, Q1


@pytest.mark.parametrize("kwargs, name", [
    ({"max_reweights": 0}, "max_reweights"),
    ({"max_reweights": -1}, "max_reweights"),
    ({"max_reweights": 2.0}, "max_reweights"),
    ({"max_iterations": 1.5}, "max_iterations"),
    ({"max_iterations": 0}, "max_iterations"),
    ({"max_iterations": True}, "max_iterations"),
    ({"robust": "huber", "robust_k": 0.0}, "robust_k"),
    ({"robust": "cauchy", "robust_k": -2.0}, "robust_k"),
    ({"robust_k": float("nan")}, "robust_k"),
    ({"reweight_tol": -1e-3}, "reweight_tol"),
    ({"reweight_tol": float("inf")}, "reweight_tol"),
    ({"variance_factor": "yes"}, "variance_factor"),
    ({"robust": "tukey"}, "robust kernel"),
])
def test_bad_argument_is_an_input_error_naming_it(pairs, kwargs, name):
    with pytest.raises(InputError, match=name):
        estimate_relative_pose(*pairs, **kwargs)


def test_smallest_valid_arguments_work(pairs):
    r = estimate_relative_pose(*pairs, max_reweights=1, max_iterations=np.int64(5), robust="huber", robust_k=0.5,
                               reweight_tol=1e-9)
    assert np.all(np.isfinite(r.covariance)) and r.iterations >= 1


# -- errors: GTSAM's failures and numpy's become one-line package errors --------------------------

def _sim_pairs(n: int = 60, pixel_sigma: float = 2.0):
    from covo_gtsam.noise import PixelNoise, PointNoiseModel
    from covo_gtsam.simulation import SimulationConfig, make_scene, noisy_measurements

    rng = np.random.default_rng(1)
    scene = make_scene(SimulationConfig(num_points=n), rng)
    model = PointNoiseModel(pixel=PixelNoise(pixel_sigma, pixel_sigma))
    X0, Q0 = noisy_measurements(scene.X0, scene.camera, model, rng)
    X1, Q1 = noisy_measurements(scene.X1, scene.camera, model, rng)
    return scene, X0, X1, Q0, Q1


def test_estimate_accepts_a_4x4_initial_pose():
    import gtsam

    from covo_gtsam.errors import InputError

    scene, X0, X1, Q0, Q1 = _sim_pairs()
    a = estimate_relative_pose(X0, X1, Q0, Q1, initial=gtsam.Pose3(scene.T01))
    b = estimate_relative_pose(X0, X1, Q0, Q1, initial=scene.T01)
    np.testing.assert_allclose(b.matrix, a.matrix, atol=1e-9)
    np.testing.assert_allclose(b.covariance, a.covariance, rtol=1e-6)
    c = estimate_relative_pose(X0, X1, Q0, Q1, initial=np.eye(4))
    np.testing.assert_allclose(c.matrix, a.matrix, atol=1e-6)
    for bad, needle in ((np.eye(3), "4x4"), (2 * np.eye(4), "rigid"), ("x", "4x4"), (np.full((4, 4), np.nan), "NaN")):
        with pytest.raises(InputError, match=needle) as info:
            estimate_relative_pose(X0, X1, Q0, Q1, initial=bad)
        assert "initial" in str(info.value)


def test_string_scale_is_a_clear_error():
    from covo_gtsam.config import EstimatorConfig
    from covo_gtsam.errors import ConfigError
    from covo_gtsam.simulation import SimulationConfig

    for cls in (EstimatorConfig, SimulationConfig):
        with pytest.raises(ConfigError, match="scale must be a positive number.*, got '2'"):
            cls(scale="2")
        with pytest.raises(ConfigError, match="scale"):
            cls(scale=True)
    X = np.random.default_rng(0).uniform(-1, 1, (10, 3)) + [0, 0, 3]
    Q = np.tile(np.eye(3) * 1e-4, (10, 1, 1))
    for bad in ("2", True, float("nan")):
        with pytest.raises(InputError, match="scale must be a positive finite number"):
            estimate_relative_pose(X, X, Q, Q, scale=bad)


def test_gtsam_exceptions_never_leak_for_coincident_points():
    X = np.tile([0.0, 0.0, 2.0], (5, 1))
    Q = np.tile(np.eye(3) * 1e-4, (5, 1, 1))
    with pytest.raises(CovoError) as info:
        estimate_relative_pose(X, X, Q, Q)
    assert isinstance(info.value, DegenerateGeometryError)


def test_huge_inputs_are_input_errors_not_numpy_errors():
    _, X0, X1, Q0, Q1 = _sim_pairs()
    for args in ((X0 * 1e160, X1 * 1e160, Q0, Q1), (X0, X1, Q0 * 1e200, Q1)):
        with pytest.raises(InputError, match="in magnitude"):
            estimate_relative_pose(*args)


def test_degeneracy_message_tells_collinear_from_ill_conditioned():
    _, X0, X1, Q0, Q1 = _sim_pairs(pixel_sigma=1e6)
    with pytest.raises(DegenerateGeometryError) as info:
        estimate_relative_pose(X0, X1, Q0, Q1)
    msg = str(info.value)
    assert "ill-conditioned" in msg and "collinear" not in msg and "\n" not in msg
    X = np.stack([np.linspace(-1, 1, 10), np.zeros(10), np.full(10, 2.0)], 1)
    Q = np.tile(np.eye(3) * 1e-4, (10, 1, 1))
    with pytest.raises(DegenerateGeometryError, match="collinear"):
        estimate_relative_pose(X + [0.05, 0.0, 0.0], X, Q, Q)


def test_covariance_error_is_one_line(monkeypatch):
    import gtsam

    from covo_gtsam import estimator
    from covo_gtsam.errors import CovarianceError

    def singular_marginals(information, pose, key=estimator.POSE_KEY):
        R = np.zeros((6, 6))
        R[:5, :5] = np.eye(5)
        graph = gtsam.GaussianFactorGraph()
        graph.add(gtsam.JacobianFactor(key, R, np.zeros(6), gtsam.noiseModel.Unit.Create(6)))
        values = gtsam.Values()
        values.insert(key, pose)
        return gtsam.Marginals(graph, values).marginalCovariance(key)  # GTSAM's multi-line error

    monkeypatch.setattr(estimator, "marginal_covariance", singular_marginals)
    _, X0, X1, Q0, Q1 = _sim_pairs()
    with pytest.raises(CovarianceError) as info:
        estimate_relative_pose(X0, X1, Q0, Q1)
    msg = str(info.value)
    assert "\n" not in msg and "GTSAM could not compute the marginal covariance" in msg
    assert "ndetermina" in msg and "https://" not in msg  # GTSAM 4.2 says "Indeterminant"
