"""Odometry steps as GTSAM pose-graph factors, and ROS ``PoseWithCovariance`` export.

Pose graph
----------
:func:`between_factors` turns the steps of a :class:`covo_gtsam.odometry.VisualOdometry` run
(``RunResult.steps``, or the steps a caller keeps from ``register_frame``, e.g. in a
:class:`~covo_gtsam.steps.StepHistory`) into one ``gtsam.BetweenFactorPose3`` per tracked frame
pair plus initial values::

    factors, initial = between_factors(result.steps)
    graph = gtsam.NonlinearFactorGraph()
    for f in factors:
        graph.add(f)
    graph.add(gtsam.PriorFactorPose3(gtsam.symbol("x", 0), gtsam.Pose3(), prior_noise))

Keys: every step that has a pose (status ``"first"``, ``"tracked"`` or ``"restart"``) gets the key
``gtsam.symbol(prefix, i)`` where ``i`` is its position in ``steps``. For a
:class:`~covo_gtsam.steps.StepHistory` and ``RunResult.steps`` -- one step per frame, lost frames
included -- ``i`` is therefore the frame index in the sequence, so keys stay tied to frames and
lost frames simply have no key (gaps in ``i``). A custom ``key(i)`` may replace the symbol, or
``key(timestamp)`` with ``key_by="timestamp"``.

Factors: for each ``"tracked"`` step, ``BetweenFactorPose3(key(ref), key(cur), T_ref,cur,
noise)`` where ``ref`` is the step whose timestamp is ``step.ref_timestamp``. GTSAM's
``BetweenFactor`` error is ``Log(T_meas^-1 x_ref^-1 x_cur)`` -- the right-perturbation tangent
``[omega, v]`` of ``T_ref,cur`` -- exactly the tangent in which ``step.covariance`` is expressed,
so the noise is ``gtsam.noiseModel.Gaussian.Covariance(step.covariance)`` with no conversion.

A ``"restart"`` step (a new segment after a run of lost frames) gets no factor: the motion
across the gap is unknown, so a back end needs another source (a prior, GNSS, loop closure) to
tie the segments together.

Initial values: ``T_world,cur`` of each keyed step (``step.pose``, world = first tracked camera
frame); where a step carries no pose, the composition of its reference's value with
``step.relative``.

:func:`unit_between_factors` is the same graph with one constant noise model on every factor (for
comparison studies); both go through the ``noise`` override of :func:`between_factors`.

ROS export
----------
:func:`to_pose_with_covariance` gives the fields of ``geometry_msgs/PoseWithCovariance`` as a plain
dict (no ROS dependency). ROS orders the covariance ``[x y z rot_x rot_y rot_z]`` (translation
first): the covariance of the position error ``dt = t_true - t`` and of the small rotation
``dtheta`` about the parent frame's fixed axes (``R_true = Exp(dtheta) R``). With the package's
right perturbation ``T_true = T * Exp([omega, v])``, to first order ``dt = R v`` and
``dtheta = R omega``::

    Sigma_ros = B Sigma B^T,      B = [[0, R], [R, 0]]  (rows dt, dtheta; columns omega, v)

(:func:`covo_gtsam.covariance.tangent_to_ros`). It is not the SE(3) adjoint: the left tangent
``Log(T_true T^-1)`` has the translation part ``dt - dtheta x t``, the position error only at the
origin: 3.7 m from it (``tests/test_graph.py``) the adjoint's position variances are 14 to 18
times the sampled ones.
:func:`from_pose_with_covariance` inverts the conversion exactly (up to floating point).
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

import gtsam
import numpy as np

from .covariance import check_covariance, check_matrix, ros_to_tangent, tangent_to_ros
from .errors import InputError
from .geometry import matrix_to_quat, quat_to_matrix
from .steps import POSED_STATUSES


NoiseSpec = Any  # gtsam noise model, 6x6 covariance, or callable(step) -> one of those


def _as_noise_model(spec: Any, what: str = "covariance") -> gtsam.noiseModel.Base:
    """A gtsam noise model as it is, or the Gaussian of a 6x6 covariance checked by
    :func:`~covo_gtsam.covariance.check_covariance` (symmetric positive definite, finite)."""
    if isinstance(spec, gtsam.noiseModel.Base):
        return spec
    return gtsam.noiseModel.Gaussian.Covariance(check_covariance(spec, what))


def step_keys(
    steps: Sequence,
    key: Callable[[Any], int] | None = None,
    prefix: str = "x",
    key_by: str = "index",
) -> dict[int, int]:
    """Map position ``i`` in ``steps`` -> GTSAM key for every step with a pose (first/tracked/restart).

    ``key`` receives ``i`` (``key_by="index"``, default) or the step's timestamp
    (``key_by="timestamp"``); without it the key is ``gtsam.symbol(prefix, i)``.
    """
    if key_by not in ("index", "timestamp"):
        raise InputError(f"key_by must be 'index' or 'timestamp', got {key_by!r}")
    keys: dict[int, int] = {}
    for i, s in enumerate(steps):
        if s.status not in POSED_STATUSES:
            continue
        if key is None:
            keys[i] = gtsam.symbol(prefix, i)
        else:
            keys[i] = int(key(i if key_by == "index" else s.timestamp))
    if len(set(keys.values())) != len(keys):
        raise InputError("the key function gives the same key to two steps")
    return keys


def between_factors(
    steps: Sequence,
    key: Callable[[Any], int] | None = None,
    prefix: str = "x",
    key_by: str = "index",
    noise: NoiseSpec | None = None,
) -> tuple[list[gtsam.BetweenFactorPose3], gtsam.Values]:
    """Between factors of the tracked steps and the composed absolute poses as initial values.

    Args:
        steps: :class:`~covo_gtsam.steps.OdometryStep` sequence in time order (``RunResult.steps``,
            a :class:`~covo_gtsam.steps.StepHistory`).
        key: optional ``key(i)`` (or ``key(timestamp)``, see ``key_by``) -> GTSAM key.
        prefix: symbol character of the default keys ``gtsam.symbol(prefix, i)``.
        key_by: ``"index"`` (position in ``steps``) or ``"timestamp"``: what ``key`` receives.
        noise: override of the factors' noise: a gtsam noise model or 6x6 covariance used for
            every factor, or a callable ``noise(step)`` returning either. Default: each step's own
            covariance, ``gtsam.noiseModel.Gaussian.Covariance(step.covariance)``.

    Returns:
        ``(factors, initial)``: one ``BetweenFactorPose3(key_ref, key_cur, T_ref,cur, noise)`` per
        ``"tracked"`` step, in order, and ``gtsam.Values`` with ``T_world,cur`` of every keyed step.

    Raises:
        InputError: a tracked step lacks its relative pose/covariance, its reference frame is not
            among the earlier keyed steps, two steps share a key, or a covariance (the steps' own
            or ``noise``) is not a finite, symmetric, positive definite 6x6 matrix.
    """
    keys = step_keys(steps, key, prefix, key_by)
    fixed_model = None
    if isinstance(noise, gtsam.noiseModel.Base) or (noise is not None and not callable(noise)):
        fixed_model = _as_noise_model(noise, "noise")
    by_stamp: dict[float, int] = {}
    factors: list[gtsam.BetweenFactorPose3] = []
    initial = gtsam.Values()
    for i, s in enumerate(steps):
        if i not in keys:
            continue
        k = keys[i]
        if s.status == "tracked":
            if s.relative is None:
                raise InputError(f"tracked step {i} (t={s.timestamp}) has no relative pose")
            ref = by_stamp.get(None if s.ref_timestamp is None else float(s.ref_timestamp))
            if ref is None:
                raise InputError(
                    f"tracked step {i} (t={s.timestamp}): its reference frame t={s.ref_timestamp} "
                    "is not an earlier first/tracked step")
            if fixed_model is not None:
                model = fixed_model
            elif noise is not None:
                model = _as_noise_model(noise(s), f"noise of tracked step {i} (t={s.timestamp})")
            else:
                if s.covariance is None:
                    raise InputError(f"tracked step {i} (t={s.timestamp}) has no covariance")
                model = _as_noise_model(s.covariance, f"covariance of tracked step {i} (t={s.timestamp})")
            factors.append(gtsam.BetweenFactorPose3(keys[ref], k, s.relative, model))
            pose = s.pose if s.pose is not None else initial.atPose3(keys[ref]).compose(s.relative)
        else:  # "first" or "restart"
            pose = s.pose if s.pose is not None else gtsam.Pose3()
        initial.insert(k, pose)
        by_stamp[float(s.timestamp)] = i
    return factors, initial


def unit_between_factors(
    steps: Sequence,
    sigma: float | Sequence[float] | None = None,
    covariance: np.ndarray | None = None,
    key: Callable[[Any], int] | None = None,
    prefix: str = "x",
    key_by: str = "index",
) -> tuple[list[gtsam.BetweenFactorPose3], gtsam.Values]:
    """:func:`between_factors` with one constant noise on every factor (comparison baseline).

    Give either ``sigma`` -- a scalar (isotropic, rad and m alike) or 6 standard deviations in
    GTSAM's tangent order ``[rx ry rz tx ty tz]`` -- or a 6x6 ``covariance``; default
    ``sigma=1.0`` (unit noise).
    """
    if sigma is not None and covariance is not None:
        raise InputError("give sigma or covariance, not both")
    if covariance is not None:
        model = _as_noise_model(covariance, "covariance")
    else:
        try:
            s = np.broadcast_to(np.asarray(1.0 if sigma is None else sigma, dtype=float), (6,))
        except (TypeError, ValueError):
            raise InputError(f"sigma must be one number or 6 numbers, got {sigma!r}") from None
        if not np.all(np.isfinite(s) & (s > 0)):
            raise InputError(f"sigma must be positive and finite, got {sigma!r}")
        model = gtsam.noiseModel.Diagonal.Sigmas(np.array(s))
    return between_factors(steps, key=key, prefix=prefix, key_by=key_by, noise=model)


# ------------------------------------------------------------------------------------------------
# ROS geometry_msgs/PoseWithCovariance
# ------------------------------------------------------------------------------------------------
def to_pose_with_covariance(T: gtsam.Pose3, cov: np.ndarray) -> dict:
    """``geometry_msgs/PoseWithCovariance`` fields of a pose and its GTSAM tangent covariance.

    Args:
        T: the pose (e.g. ``T_world,cam``); ``position`` is its translation and ``orientation`` its
            unit quaternion ``[qx, qy, qz, qw]`` (``qw >= 0``).
        cov: 6x6 in GTSAM's tangent ``[rx ry rz tx ty tz]``, right perturbation
            ``T_true = T * Exp(xi)``.

    Returns:
        ``{"position": [x, y, z], "orientation": [qx, qy, qz, qw], "covariance": [36 floats]}``
        with the covariance row-major in ROS order ``[x y z rot_x rot_y rot_z]``: position error and
        small rotations about the parent's fixed axes (see the module docstring).
    """
    cov = check_matrix(cov)  # may be singular: the first pose's covariance is zero
    if not isinstance(T, gtsam.Pose3):
        raise InputError(f"T must be a gtsam.Pose3, got {type(T).__name__}")
    M = T.matrix()
    ros = tangent_to_ros(cov, T)
    ros = 0.5 * (ros + ros.T)
    return {
        "position": [float(x) for x in M[:3, 3]],
        "orientation": [float(x) for x in matrix_to_quat(M[:3, :3])],
        "covariance": [float(x) for x in ros.reshape(-1)],
    }


def from_pose_with_covariance(d: dict) -> tuple[gtsam.Pose3, np.ndarray]:
    """Inverse of :func:`to_pose_with_covariance`: ``(gtsam.Pose3, 6x6 GTSAM tangent covariance)``.

    Accepts ``orientation`` as ``[qx, qy, qz, qw]`` (normalised here) and ``covariance`` as 36
    row-major values in ROS order.
    """
    try:
        p = np.asarray(d["position"], dtype=float).reshape(3)
        q = np.asarray(d["orientation"], dtype=float).reshape(4)
        c = np.asarray(d["covariance"], dtype=float).reshape(6, 6)
    except (KeyError, ValueError, TypeError) as exc:
        raise InputError(f"not a PoseWithCovariance dict (position[3], orientation[4], covariance[36]): {exc}") from exc
    nq = np.linalg.norm(q)
    if not (np.isfinite(nq) and nq > 0):
        raise InputError(f"orientation quaternion {q.tolist()} is not a valid rotation")
    T = gtsam.Pose3(gtsam.Rot3(quat_to_matrix(q)), p)
    cov = ros_to_tangent(c, T)
    return T, 0.5 * (cov + cov.T)
