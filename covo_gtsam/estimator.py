"""Relative pose and its covariance from matched 3D point pairs with per-point covariances.

:func:`estimate_relative_pose` solves the two-way point-transfer problem with GTSAM's
Levenberg-Marquardt on one ``Pose3`` key holding ``T_k,k1`` (maps points of frame k+1 into frame
k) and reads the 6x6 covariance from ``gtsam.Marginals`` (tangent ``[rx ry rz tx ty tz]``, right
perturbation ``T_true = T_est * Exp(xi)``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np

from .chi2 import SQRT_CHI2_3_95
from .covariance import tangent_to_tq
from .errors import (
    CovarianceError,
    DegenerateGeometryError,
    EstimationError,
    InputError,
    InsufficientPairsError,
)
from .factors import whitened_transfer_factor
from .geometry import rotation_angle
from .transfer import (
    WEIGHTINGS,
    is_positive_definite,
    residual_covariances,
    transfer_mahalanobis,
    weighted_rigid_fit,
    whitened_system,
    whitening,
)
from .validation import is_int, is_real

#: Key of the relative pose in the estimator's graph.
POSE_KEY = gtsam.symbol("T", 0)
#: Smallest eigenvalue ratio of the information matrix before the geometry counts as degenerate.
MIN_INFO_RATIO = 1e-12


@dataclass
class RelativePoseResult:
    """Estimated ``T_k,k1`` with its covariance.

    Attributes:
        pose: ``gtsam.Pose3`` T_k,k1, maps points of frame k+1 into frame k.
        covariance: 6x6, GTSAM tangent ``[rx ry rz tx ty tz]`` (rad, m), right perturbation,
            ``scale`` times the ``gtsam.Marginals`` covariance: the per-point model's alone. A real
            camera's pair errs more (errors shared by a frame's points); the odometry reports this
            plus the sensor terms (:meth:`~covo_gtsam.config.OdometryConfig.sensor_covariance`).
        information: 6x6 ``J^T W J`` at the solution (unscaled), same tangent.
        scale: the factor phi applied to the marginal covariance (thesis 5.2.2; 1 = none).
        weighting: ``"consistent"`` or ``"thesis"``.
        iterations: Levenberg-Marquardt iterations summed over re-weighting passes.
        final_error: GTSAM graph error ``0.5 * sum(e^2)`` of the whitened residuals at the solution.
        num_pairs: number of point pairs used.
        chi2_per_dof: ``sum(e^2) / (3N - 6)`` of the whitened residuals, the a-posteriori variance
            factor (about 1 when the point covariances are right).
    """

    pose: gtsam.Pose3
    covariance: np.ndarray
    information: np.ndarray
    scale: float
    weighting: str
    iterations: int
    final_error: float
    num_pairs: int
    residual_covariances: tuple[np.ndarray, np.ndarray] = field(repr=False)
    chi2_per_dof: float = float("nan")

    @property
    def matrix(self) -> np.ndarray:
        """4x4 homogeneous matrix of :attr:`pose`."""
        return self.pose.matrix()

    @property
    def covariance_tq(self) -> np.ndarray:
        """The thesis's ``Q_tq`` (4.20): covariance of ``(tx, ty, tz, qx, qy, qz)``, scaled by phi.

        First-order propagation of the point covariances through the residuals' Jacobian with
        respect to ``(t, q_v)``; equal to :func:`covo_gtsam.covariance.tangent_to_tq` of
        :attr:`covariance`.
        """
        return tangent_to_tq(self.covariance, self.pose)

    def noise_model(self) -> gtsam.noiseModel.Gaussian:
        """Gaussian noise model with exactly :attr:`covariance`."""
        return gtsam.noiseModel.Gaussian.Covariance(self.covariance)

    def between_factor(self, key_k: int, key_k1: int) -> gtsam.BetweenFactorPose3:
        """``BetweenFactorPose3(key_k, key_k1, T_k,k1)`` whose noise has exactly :attr:`covariance`."""
        return gtsam.BetweenFactorPose3(key_k, key_k1, self.pose, self.noise_model())


#: Largest accepted point coordinate and covariance entry magnitude (m, m^2): far beyond any camera
#: range, small enough that products of them stay finite in double precision.
MAX_COORDINATE = 1e6
MAX_COVARIANCE = 1e12


def validate_inputs(X_k, X_k1, Q_k, Q_k1) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Check shapes, finiteness, magnitudes (:data:`MAX_COORDINATE`, :data:`MAX_COVARIANCE`),
    symmetry and positive definiteness; return float64 arrays."""
    arrays = []
    for name, a, shape in (("X_k", X_k, (3,)), ("X_k1", X_k1, (3,)), ("Q_k", Q_k, (3, 3)), ("Q_k1", Q_k1, (3, 3))):
        try:
            a = np.asarray(a, dtype=float)
        except (TypeError, ValueError) as exc:
            raise InputError(f"{name} is not a numeric array") from exc
        if a.ndim != 1 + len(shape) or a.shape[1:] != shape:
            raise InputError(f"{name} must have shape (N, {', '.join(map(str, shape))}), got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise InputError(f"{name} contains NaN or inf")
        limit = MAX_COORDINATE if name.startswith("X") else MAX_COVARIANCE
        if np.abs(a).max(initial=0.0) > limit:
            raise InputError(f"{name} has entries above {limit:g} in magnitude (units are m and m^2)")
        arrays.append(a)
    X_k, X_k1, Q_k, Q_k1 = arrays
    n = X_k.shape[0]
    if not (X_k1.shape[0] == Q_k.shape[0] == Q_k1.shape[0] == n):
        raise InputError(
            f"inputs disagree on the number of pairs: X_k {n}, X_k1 {X_k1.shape[0]}, "
            f"Q_k {Q_k.shape[0]}, Q_k1 {Q_k1.shape[0]}"
        )
    for name, Q in (("Q_k", Q_k), ("Q_k1", Q_k1)):
        asym = np.abs(Q - np.swapaxes(Q, 1, 2)).max(initial=0.0)
        if asym > 1e-9 * max(np.abs(Q).max(initial=0.0), 1e-300):
            raise InputError(f"{name} is not symmetric (max asymmetry {asym:.3g})")
        pd = is_positive_definite(Q)
        if not np.all(pd):
            raise InputError(f"{name}[{int(np.argmin(pd))}] is not positive definite")
    return X_k, X_k1, Q_k, Q_k1


def initial_guess(X_k: np.ndarray, X_k1: np.ndarray, Q_k: np.ndarray, Q_k1: np.ndarray) -> gtsam.Pose3:
    """Closed-form rigid fit ``X_k ≈ R X_k1 + t`` weighted by ``1 / trace(Q_k + Q_k1)``."""
    R, t = weighted_rigid_fit(X_k, X_k1, Q_k, Q_k1)
    return gtsam.Pose3(gtsam.Rot3(R), t)


ROBUST_KERNELS = (None, "huber", "cauchy")
#: Default robust threshold: sqrt of the chi2(3) 95 % quantile, in Mahalanobis distance.
ROBUST_K = SQRT_CHI2_3_95


def robust_weights(d: np.ndarray, kernel: str, k: float = ROBUST_K) -> np.ndarray:
    """IRLS weights ``rho'(d) / d``: Huber ``min(1, k/d)``, Cauchy ``1 / (1 + (d/k)^2)``."""
    if kernel == "huber":
        return np.minimum(1.0, k / np.maximum(d, 1e-300))
    if kernel == "cauchy":
        return 1.0 / (1.0 + (d / k) ** 2)
    return np.ones_like(d)


def marginal_covariance(information: np.ndarray, pose: gtsam.Pose3, key: int = POSE_KEY) -> np.ndarray:
    """``gtsam.Marginals`` covariance of ``key`` from the graph linearised at ``pose``.

    The factor's whitened Jacobian ``J`` (6N x 6) at the solution enters GTSAM as the equivalent
    6x6 Jacobian factor ``R`` with ``R^T R = J^T J = information``: the same Gaussian density up to
    a constant, so the marginal is the same as ``gtsam.Marginals(graph, solution)`` on the
    nonlinear graph, without a second pass of the factor over all pairs.
    """
    R = np.linalg.cholesky(information).T
    linear = gtsam.GaussianFactorGraph()
    linear.add(gtsam.JacobianFactor(key, R, np.zeros(6), gtsam.noiseModel.Unit.Create(6)))
    values = gtsam.Values()
    values.insert(key, pose)
    return gtsam.Marginals(linear, values).marginalCovariance(key)


def one_line(exc: BaseException) -> str:
    """The first paragraph of an exception's text on one line (GTSAM's messages span many lines
    and end in a long explanation and links)."""
    text = str(exc).strip()
    return " ".join(text.split("\n\n")[0].split()) or type(exc).__name__


def as_pose3(pose, name: str = "pose") -> gtsam.Pose3:
    """A finite ``gtsam.Pose3`` from a ``Pose3`` or a 4x4 homogeneous matrix (rotation block
    orthonormal with determinant +1 to 1e-6, last row ``[0 0 0 1]``; the rotation is then
    re-orthonormalised); :class:`InputError` otherwise."""
    if isinstance(pose, gtsam.Pose3):
        T = pose.matrix()
    else:
        try:
            T = np.asarray(pose, dtype=float)
        except (TypeError, ValueError):
            raise InputError(f"{name} must be a gtsam.Pose3 or a 4x4 homogeneous matrix, got {pose!r}") from None
        if T.shape != (4, 4):
            raise InputError(f"{name} must be a gtsam.Pose3 or a 4x4 homogeneous matrix, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise InputError(f"{name} pose contains NaN or inf")
    if isinstance(pose, gtsam.Pose3):
        return pose
    R = T[:3, :3]
    if (np.abs(T[3] - [0.0, 0.0, 0.0, 1.0]).max() > 1e-6 or np.abs(R.T @ R - np.eye(3)).max() > 1e-6
            or np.linalg.det(R) <= 0):
        raise InputError(f"{name} is not a rigid transform: needs an orthonormal rotation block with "
                         "determinant +1 and the last row [0 0 0 1]")
    U, _, Vt = np.linalg.svd(R)
    return gtsam.Pose3(gtsam.Rot3(U @ Vt), T[:3, 3].copy())


def _degeneracy_message(n: int, eig: np.ndarray, X_k: np.ndarray, X_k1: np.ndarray, Q_k: np.ndarray,
                        Q_k1: np.ndarray) -> str:
    """Why the information matrix is (nearly) singular: the points' arrangement (collinear or
    coincident: the second singular value of the centred points of a frame is tiny) or, for
    well spread points, covariances so large or elongated that some pose direction is almost
    unconstrained (e.g. pixel noise far above the depth noise)."""
    ratio = eig[0] / max(eig[-1], 1e-300) if np.all(np.isfinite(eig)) else float("nan")
    head = f"the {n} point pairs do not constrain all 6 degrees of freedom (information eigenvalue ratio {ratio:.2e})"
    spreads = [np.linalg.svd(X - X.mean(axis=0), compute_uv=False) for X in (X_k, X_k1)]
    if any(sv[1] <= 1e-6 * max(sv[0], 1e-300) or sv[0] <= 1e-9 for sv in spreads):
        return head + ": the points are collinear or coincident"
    sd = np.sqrt(np.maximum(np.linalg.eigvalsh(np.concatenate([Q_k, Q_k1])), 0.0))
    return (head + ": the points are spread out, but their covariances are so large or elongated that the "
            f"problem is ill-conditioned (point standard deviations {sd.min():.2g} m to {sd.max():.2g} m; "
            "e.g. pixel noise far too large for the depth noise)")


def _lm_params(max_iterations: int) -> gtsam.LevenbergMarquardtParams:
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(1e-10)
    params.setAbsoluteErrorTol(1e-12)
    return params


def estimate_relative_pose(
    X_k: np.ndarray,
    X_k1: np.ndarray,
    Q_k: np.ndarray,
    Q_k1: np.ndarray,
    weighting: str = "consistent",
    scale: float = 1.0,
    initial: gtsam.Pose3 | None = None,
    max_iterations: int = 50,
    max_reweights: int = 4,
    reweight_tol: float = 2e-3,
    robust: str | None = None,
    robust_k: float = ROBUST_K,
    variance_factor: bool = False,
) -> RelativePoseResult:
    """Estimate ``T_k,k1`` and its covariance from N matched point pairs.

    Args:
        X_k, X_k1: (N, 3) matched points in camera frames k and k+1 (metres).
        Q_k, Q_k1: (N, 3, 3) their covariances (m^2), symmetric positive definite.
        weighting: ``"consistent"`` (default) or ``"thesis"`` (4.16); see :mod:`covo_gtsam.transfer`.
        scale: phi, multiplies the returned covariance (thesis uses 16; default 1).
        initial: initial guess of T_k,k1, a ``gtsam.Pose3`` or a 4x4 homogeneous matrix; a
            weighted closed-form rigid fit if None.
        max_iterations: Levenberg-Marquardt iterations per pass (an integer >= 1).
        max_reweights: (an integer >= 1) passes of the ``consistent`` weighting, each re-evaluating the residual
            covariances at the latest rotation until it changes by less than ``reweight_tol`` rad.
        robust: ``None``, ``"huber"`` or ``"cauchy"``: iteratively re-weighted least squares with
            per-pair weights ``w(d)`` of the pair's Mahalanobis distance ``d`` (3 dof) and threshold
            ``robust_k``; each pair's residual covariances are divided by its weight, so the
            returned covariance is ``(J^T W J)^-1`` with the robust weights.
        variance_factor: multiply the covariance by the a-posteriori variance factor
            ``max(1, chi2 / (3N - 6))`` of the fit (adaptive pixel noise; never shrinks it).

    Raises:
        InputError: wrong shapes, NaN/inf, non-symmetric or non-positive-definite covariances, an
            ``initial`` that is not a finite rigid transform, an unknown ``weighting`` or
            ``robust``, iteration counts that are not integers >= 1, ``reweight_tol`` or
            ``robust_k`` not positive and finite, ``variance_factor`` not a bool.
        InsufficientPairsError: fewer than 3 pairs.
        DegenerateGeometryError: the pairs do not constrain all 6 degrees of freedom.
        CovarianceError: GTSAM could not compute a valid marginal covariance.
    """
    if weighting not in WEIGHTINGS:
        raise InputError(f"unknown weighting {weighting!r}; choose one of {WEIGHTINGS}")
    if not (is_real(scale) and np.isfinite(scale) and scale > 0):
        raise InputError(f"scale must be a positive finite number, got {scale!r}")
    for name, value in (("max_iterations", max_iterations), ("max_reweights", max_reweights)):
        if not (is_int(value) and value >= 1):
            raise InputError(f"{name} must be an integer >= 1, got {value!r}")
    for name, value in (("reweight_tol", reweight_tol), ("robust_k", robust_k)):
        if not (is_real(value) and np.isfinite(value) and value > 0):
            raise InputError(f"{name} must be a positive finite number, got {value!r}")
    if not isinstance(variance_factor, (bool, np.bool_)):
        raise InputError(f"variance_factor must be True or False, got {variance_factor!r}")
    if robust not in ROBUST_KERNELS:
        raise InputError(f"unknown robust kernel {robust!r}; choose one of {ROBUST_KERNELS}")
    X_k, X_k1, Q_k, Q_k1 = validate_inputs(X_k, X_k1, Q_k, Q_k1)
    n = X_k.shape[0]
    if n < 3:
        raise InsufficientPairsError(f"need at least 3 point pairs, got {n}")

    if initial is None:
        try:
            pose = initial_guess(X_k, X_k1, Q_k, Q_k1)
        except np.linalg.LinAlgError as exc:
            raise DegenerateGeometryError(f"the closed-form initial fit failed ({exc})") from exc
        if not np.all(np.isfinite(pose.matrix())):
            raise DegenerateGeometryError("the closed-form initial fit is not finite")
    else:
        pose = as_pose3(initial, "initial")

    iterations = 0
    passes = max_reweights if (weighting == "consistent" or robust) else 1
    if robust:
        passes = max(passes, 8)
    w = np.ones(n)
    for _ in range(passes):
        R_w = pose.rotation().matrix()
        C_b, C_f = residual_covariances(Q_k, Q_k1, weighting, R_w)
        if robust:
            C_b, C_f = C_b / w[:, None, None], C_f / w[:, None, None]
        W_b, W_f = whitening(C_b), whitening(C_f)
        graph = gtsam.NonlinearFactorGraph()
        graph.add(whitened_transfer_factor(POSE_KEY, X_k, X_k1, W_b, W_f))
        values = gtsam.Values()
        values.insert(POSE_KEY, pose)
        try:
            optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, _lm_params(max_iterations))
            solution = optimizer.optimize()
        except RuntimeError as exc:
            raise DegenerateGeometryError(f"Levenberg-Marquardt failed: {one_line(exc)}") from exc
        iterations += optimizer.iterations()
        pose = solution.atPose3(POSE_KEY)
        if not np.all(np.isfinite(pose.matrix())):
            raise EstimationError("Levenberg-Marquardt returned a non-finite pose")
        converged = weighting == "thesis" or rotation_angle(R_w.T @ pose.rotation().matrix()) < reweight_tol
        if robust:
            R_p = pose.rotation().matrix()
            d = np.sqrt(transfer_mahalanobis(R_p, pose.translation(), X_k, X_k1, Q_k, Q_k1))
            w_new = robust_weights(d, robust, robust_k)
            converged = converged and np.max(np.abs(w_new - w)) < 1e-3
            w = w_new
        if converged:
            break

    e, J = whitened_system(pose.rotation().matrix(), pose.translation(), X_k, X_k1, W_b, W_f)
    information = J.T @ J
    eig = np.linalg.eigvalsh(information) if np.all(np.isfinite(information)) else np.full(6, np.nan)
    if not np.all(np.isfinite(eig)) or eig[0] <= MIN_INFO_RATIO * max(eig[-1], 1e-300):
        raise DegenerateGeometryError(_degeneracy_message(n, eig, X_k, X_k1, Q_k, Q_k1))
    try:
        marginal = marginal_covariance(information, pose)
    except (RuntimeError, np.linalg.LinAlgError) as exc:
        raise CovarianceError(f"GTSAM could not compute the marginal covariance: {one_line(exc)}") from exc
    cov = scale * 0.5 * (marginal + marginal.T)
    dof = 3 * n - 6
    chi2_per_dof = float(e @ e) / dof if dof > 0 else float("nan")
    if variance_factor and dof > 0:
        cov = cov * max(1.0, chi2_per_dof)
    if not np.all(np.isfinite(cov)) or np.linalg.eigvalsh(cov)[0] <= 0.0:  # eigvalsh only on finite input
        raise CovarianceError("the marginal covariance is not finite and positive definite")
    return RelativePoseResult(
        pose=pose,
        covariance=cov,
        information=information,
        scale=float(scale),
        weighting=weighting,
        iterations=int(iterations),
        final_error=float(0.5 * e @ e),
        num_pairs=n,
        residual_covariances=(C_b, C_f),
        chi2_per_dof=chi2_per_dof,
    )
