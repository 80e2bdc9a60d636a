"""Sensor-level terms of the relative-pose covariance, and their maximum-likelihood fit.

The per-point model (pixel and depth noise, propagated through the estimator) treats the points'
errors as independent. A real RGB-D sensor also has errors shared by the points of a frame pair,
which the post-fit residuals cannot show. covo reports, for a pair ``k`` frame intervals apart::

    C = kappa * C_points + diag(s_r^2 k, s_r^2 k, s_r^2 k, s_t^2 k^2, s_t^2 k^2, s_t^2 k^2)

in GTSAM's tangent ``[rx ry rz tx ty tz]`` (radians, metres; right perturbation). ``kappa``
inflates the per-point covariance for errors correlated between points; ``s_r`` (rad) is a
rotation error per interval that adds up like a random walk (timestamp jitter is independent from
frame to frame); ``s_t`` (m) is a translation error per interval that persists over the intervals
of a pair (it comes with the scene's depth errors), so its standard deviation grows with ``k``.
The growth laws were chosen on keyframe pairs spanning 1-15 intervals (docs/consistency.md).

A timing term adds, for each frame ``f`` of the pair, ``tau^2 xi_f xi_f^T``: ``xi_f`` is the
camera's body twist ``[omega, v]`` at that frame (rad/s, m/s) and ``tau`` (s) the standard deviation
of the error of a frame's timestamp as a time of capture (stamp jitter, the colour-depth offset,
the readout). A frame taken ``d`` seconds away from its stamp has its pose off by ``Exp(d xi_f)``,
so this error grows with the speed of the camera, and vanishes for a camera at rest.

:func:`fit_sensor_terms` estimates ``kappa, s_r, s_t`` from the errors of consecutive pairs
against ground truth, by maximising the Gaussian likelihood; it needs SciPy
(``pip install "covo-gtsam[calibrate]"``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InputError

__all__ = ["SensorTerms", "frame_covariance", "timing_covariance", "sensor_covariance", "log_likelihood",
           "fit_sensor_terms"]


@dataclass(frozen=True)
class SensorTerms:
    """Fitted sensor terms: ``correlation_factor`` (kappa), per-interval standard deviations
    ``frame_sigma_rot_deg`` (degrees per axis) and ``frame_sigma_trans_m`` (metres per axis), the
    mean log-likelihood per pair at the fit, the number of pairs it used, and the timing term's
    ``timing_sigma_s`` (seconds; 0 when not fitted)."""

    correlation_factor: float
    frame_sigma_rot_deg: float
    frame_sigma_trans_m: float
    log_likelihood: float
    pairs: int
    timing_sigma_s: float = 0.0


def frame_covariance(sigma_rot_rad: float, sigma_trans_m: float, intervals: np.ndarray | int = 1) -> np.ndarray:
    """Frame term(s) (..., 6, 6) of pairs ``intervals`` (...,) frame intervals apart:
    ``diag(s_r^2 k (x3), s_t^2 k^2 (x3))``, tangent ``[omega, v]``."""
    k = np.asarray(intervals, dtype=float)[..., None]
    diag = np.concatenate([np.broadcast_to(sigma_rot_rad**2 * k, k.shape[:-1] + (3,)),
                           np.broadcast_to(sigma_trans_m**2 * k**2, k.shape[:-1] + (3,))], axis=-1)
    return diag[..., :, None] * np.eye(6)


def timing_covariance(twists: np.ndarray, timing_sigma_s: float) -> np.ndarray:
    """Timing term(s) (..., 6, 6): ``tau^2 sum_f xi_f xi_f^T`` over the body twists (..., F, 6)
    ``[omega, v]`` (rad/s, m/s) of a pair's F frames; ``tau = timing_sigma_s`` (s)."""
    xi = np.asarray(twists, dtype=float)
    return timing_sigma_s**2 * np.einsum("...fi,...fj->...ij", xi, xi)


def sensor_covariance(point_cov: np.ndarray, correlation_factor: float, sigma_rot_rad: float,
                      sigma_trans_m: float, intervals: np.ndarray | int = 1, twists: np.ndarray | None = None,
                      timing_sigma_s: float = 0.0) -> np.ndarray:
    """Reported covariance(s) ``kappa * C_points + frame_covariance(s_r, s_t, k)``, plus
    ``timing_covariance(twists, timing_sigma_s)`` when ``twists`` (..., F, 6) are given.

    ``point_cov`` (..., 6, 6) and ``intervals`` (...,) broadcast; tangent ``[omega, v]``.
    """
    C = correlation_factor * np.asarray(point_cov, dtype=float) + frame_covariance(
        sigma_rot_rad, sigma_trans_m, intervals)
    if twists is not None and timing_sigma_s > 0:
        C = C + timing_covariance(twists, timing_sigma_s)
    return C


def log_likelihood(errors: np.ndarray, covs: np.ndarray) -> float:
    """Mean Gaussian log-likelihood per pair of errors (N, d) under covariances (N, d, d), without
    the constant ``-d/2 log(2 pi)``: ``mean(-1/2 e^T C^-1 e - 1/2 log det C)``."""
    errors = np.asarray(errors, dtype=float)
    covs = np.asarray(covs, dtype=float)
    if errors.ndim != 2 or covs.shape != errors.shape + (errors.shape[1],):
        raise InputError(f"need errors (N, d) and covariances (N, d, d), got {errors.shape} and {covs.shape}")
    sign, logdet = np.linalg.slogdet(covs)
    if np.any(sign <= 0):
        return -np.inf
    q = np.einsum("ni,ni->n", errors, np.linalg.solve(covs, errors[..., None])[..., 0])
    return float(np.mean(-0.5 * q - 0.5 * logdet))


def fit_sensor_terms(errors: np.ndarray, point_covs: np.ndarray, fit_correlation_factor: bool = True,
                     twists: np.ndarray | None = None) -> SensorTerms:
    """Maximum-likelihood ``kappa, s_r, s_t`` from consecutive pairs (one interval each); with
    ``fit_correlation_factor=False`` kappa stays 1 and only the frame term is fitted. With
    ``twists`` (N, F, 6), the body twists at each pair's frames, the timing term's ``tau`` is
    fitted too (:func:`timing_covariance`).

    ``errors`` (N, 6): ``Log(T_est^-1 T_true)`` of each pair
    (:func:`covo_gtsam.metrics.relative_pose_tangent_errors`; right perturbation, ``[omega, v]``);
    ``point_covs`` (N, 6, 6): the estimator's per-point covariance of the same pairs (run with
    ``correlation_factor = 1`` and zero frame sigmas). Needs at least 10 pairs.
    """
    errors = np.asarray(errors, dtype=float)
    point_covs = np.asarray(point_covs, dtype=float)
    if errors.ndim != 2 or errors.shape[1] != 6 or point_covs.shape != errors.shape + (6,):
        raise InputError(f"need errors (N, 6) and covariances (N, 6, 6), got {errors.shape} and {point_covs.shape}")
    if len(errors) < 10:
        raise InputError(f"need at least 10 pairs to fit the sensor terms, got {len(errors)}")
    if not (np.all(np.isfinite(errors)) and np.all(np.isfinite(point_covs))):
        raise InputError("errors and covariances must be finite")
    if twists is not None:
        twists = np.asarray(twists, dtype=float)
        if twists.ndim != 3 or twists.shape[0] != len(errors) or twists.shape[2] != 6 or not np.all(np.isfinite(twists)):
            raise InputError(f"twists must be finite (N, F, 6) for N = {len(errors)} pairs, got {twists.shape}")
    try:
        from scipy.optimize import minimize
    except ImportError as exc:  # pragma: no cover - depends on the installation
        raise ImportError('fitting the sensor terms needs SciPy: pip install "covo-gtsam[calibrate]"') from exc

    timing = twists is not None

    def params(x: np.ndarray) -> tuple[float, float, float, float]:
        p = tuple(np.exp(x)) if fit_correlation_factor else (1.0, *np.exp(x))
        return p if timing else (*p, 0.0)

    def cost(x: np.ndarray) -> float:
        kappa, s_r, s_t, tau = params(x)
        return -log_likelihood(errors, sensor_covariance(point_covs, kappa, s_r, s_t, 1, twists, tau))

    # start from moment matching: kappa 1, frame variances = mean squared error per axis, then
    # from larger kappa and smaller frame terms (the likelihood can have more than one maximum)
    start = np.log([1.0, np.sqrt(np.mean(errors[:, :3] ** 2)) + 1e-9, np.sqrt(np.mean(errors[:, 3:] ** 2)) + 1e-9])
    best = None
    for shift in (0.0, 1.0, 2.0, 3.0) if fit_correlation_factor else (0.0,):
        x0 = start + np.array([shift, -0.3 * shift, -0.3 * shift])
        x0 = x0 if fit_correlation_factor else x0[1:]
        if timing:  # from 2 ms, a typical stamp jitter
            x0 = np.append(x0, np.log(0.002))
        res = minimize(cost, x0, method="Nelder-Mead", options={"maxiter": 4000, "xatol": 1e-6, "fatol": 1e-10})
        if best is None or res.fun < best.fun:
            best = res
    kappa, s_r, s_t, tau = params(best.x)
    return SensorTerms(float(kappa), float(np.rad2deg(s_r)), float(s_t), float(-best.fun), len(errors), float(tau))
