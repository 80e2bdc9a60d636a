"""Graph helpers and covariance conversions refuse matrices that are no covariance, by name."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from covo_gtsam import covariance as cv
from covo_gtsam.errors import InputError
from covo_gtsam.graph import between_factors, to_pose_with_covariance, unit_between_factors
from covo_gtsam.odometry import OdometryStep


def steps_with(cov) -> list[OdometryStep]:
    """A first step and one tracked step whose covariance is ``cov``."""
    rel = gtsam.Pose3(gtsam.Rot3.Rz(0.1), np.array([0.1, 0.0, 0.0]))
    return [OdometryStep(0.0, "first", pose=gtsam.Pose3(), pose_covariance=np.zeros((6, 6))),
            OdometryStep(0.033, "tracked", ref_timestamp=0.0, relative=rel, covariance=cov, pose=rel)]


def _asymmetric():
    c = 1e-4 * np.eye(6)
    c[0, 1] = 1e-5
    return c


def _indefinite():
    c = 1e-4 * np.eye(6)
    c[2, 2] = -1e-4
    return c


BAD = {
    "negative": (-1e-4 * np.eye(6), "positive definite"),
    "zero": (np.zeros((6, 6)), "positive definite"),
    "singular": (np.diag([1e-4] * 5 + [0.0]), "positive definite"),
    "indefinite": (_indefinite(), "positive definite"),
    "asymmetric": (_asymmetric(), "symmetric"),
    "nan": (np.full((6, 6), np.nan), "NaN"),
    "shape": (np.eye(3), "6x6"),
    "text": ("1e-4", "6x6"),
}


@pytest.mark.parametrize("name", BAD)
def test_between_factors_refuse_a_step_covariance_that_is_no_covariance(name):
    cov, needle = BAD[name]
    with pytest.raises(InputError, match=needle):
        between_factors(steps_with(cov))


@pytest.mark.parametrize("name", BAD)
def test_noise_override_and_unit_factors_refuse_it_too(name):
    cov, needle = BAD[name]
    good = steps_with(1e-4 * np.eye(6))
    with pytest.raises(InputError, match=needle):
        between_factors(good, noise=cov)
    with pytest.raises(InputError, match=needle):
        between_factors(good, noise=lambda step: cov)
    with pytest.raises(InputError, match=needle):
        unit_between_factors(good, covariance=cov)


def test_valid_covariance_is_used_exactly():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(6, 6))
    cov = 1e-4 * (A @ A.T + np.eye(6))
    factors, _ = between_factors(steps_with(cov))
    model = factors[0].noiseModel()
    R = model.R()
    np.testing.assert_allclose(np.linalg.inv(R.T @ R), cov, rtol=1e-9)


@pytest.mark.parametrize("sigma", [[0.1, 0.2, 0.3], "abc", [[1.0] * 6] * 2])
def test_unit_factors_refuse_sigmas_of_the_wrong_shape(sigma):
    with pytest.raises(InputError, match="sigma"):
        unit_between_factors(steps_with(1e-4 * np.eye(6)), sigma=sigma)


POSE = gtsam.Pose3(gtsam.Rot3.Rx(0.3), np.array([1.0, 2.0, 3.0]))
CONVERSIONS = {
    "tangent_to_tq": lambda c: cv.tangent_to_tq(c, POSE),
    "tq_to_tangent": lambda c: cv.tq_to_tangent(c, POSE),
    "tangent_to_ros": lambda c: cv.tangent_to_ros(c, POSE),
    "ros_to_tangent": lambda c: cv.ros_to_tangent(c, POSE),
    "compose_a": lambda c: cv.compose_covariance(POSE, c, POSE, np.eye(6)),
    "compose_b": lambda c: cv.compose_covariance(POSE, np.eye(6), POSE, c),
    "to_pose_with_covariance": lambda c: to_pose_with_covariance(POSE, c),
}


@pytest.mark.parametrize("conversion", CONVERSIONS)
@pytest.mark.parametrize("bad, needle", [(np.full((6, 6), np.nan), "NaN"), (np.eye(6)[:, :5], "6x6"),
                                         (np.eye(5), "6x6"), (np.where(np.eye(6) > 0, np.inf, 0.0), "NaN or inf")])
def test_conversions_refuse_non_finite_or_wrongly_shaped_matrices(conversion, bad, needle):
    with pytest.raises(InputError, match=needle):
        CONVERSIONS[conversion](bad)


@pytest.mark.parametrize("conversion", ["tangent_to_tq", "tangent_to_ros", "ros_to_tangent"])
def test_conversions_refuse_a_pose_that_is_no_pose3(conversion):
    fn = getattr(cv, conversion)
    with pytest.raises(InputError, match="gtsam.Pose3"):
        fn(np.eye(6), np.eye(4))


def test_tq_to_tangent_at_half_a_turn_is_an_input_error():
    half_turn = gtsam.Pose3(gtsam.Rot3.Rx(np.pi), np.zeros(3))
    with pytest.raises(InputError, match="180 degrees"):
        cv.tq_to_tangent(np.eye(6), half_turn)


def test_conversions_still_round_trip():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(6, 6))
    cov = A @ A.T
    np.testing.assert_allclose(cv.tq_to_tangent(cv.tangent_to_tq(cov, POSE), POSE), cov, atol=1e-12)
    np.testing.assert_allclose(cv.ros_to_tangent(cv.tangent_to_ros(cov, POSE), POSE), cov, atol=1e-12)
