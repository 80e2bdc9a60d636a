"""estimate_relative_pose refuses iteration counts and thresholds it cannot use, naming them."""

from __future__ import annotations

import numpy as np
import pytest

from covo_gtsam.errors import InputError
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
