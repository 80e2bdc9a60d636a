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

Errors shared by all points of a frame (:mod:`covo_gtsam.frame_errors`) add terms
``sigma_j^2 B_j``: each ``B_j`` (6x6) is the pair's covariance per unit of a frame-level error
source, built from the pair's geometry and the camera's motion, and ``sigma_j`` is that source's
physical size (:data:`ERROR_TERMS`):

* ``timing`` (s): a frame captured off its timestamp; ``B = sum_f xi_f xi_f^T`` over the body twists
  ``xi_f`` ``[omega, v]`` (rad/s, m/s) at the pair's frames, the reference's carried into the current
  frame, since the frame's pose is then off by ``Exp(d xi_f)`` (:func:`stamp_error_basis`);
* ``depth_scale`` (relative): a frame's depths all scaled by ``1 + e``;
* ``depth_time`` (dimensionless): the depth image's time off by ``c`` times the frame's stamped
  colour-depth offset (a depth image delivered with the neighbouring colour image), independently
  at the pair's two frames: ``B = h_ref h_ref^T + h_cur h_cur^T``, ``h_f`` the pair's response to
  frame ``f``'s depths read its stamped offset later (:func:`~covo_gtsam.frame_errors.depth_time_basis`);
* ``depth_time_coherent`` (dimensionless): the depths read at the stamped offsets themselves, not
  compensated, both frames' effects together: ``B = (h_ref + h_cur)(h_ref + h_cur)^T``; 1 where the
  stamps are the depth images' true capture times (the realistic simulation's), less where they
  tell the offsets only in part;
* ``rolling_shutter`` (dimensionless): the twist the rolling-shutter compensation uses at the
  current frame off by ``c`` times half the change of the pair twist since the previous pair;
* ``latency`` (s): the stamps all late (or early) by one unknown constant against the clock
  the poses are used on (a driver's capture-to-stamp delay). Both frames' poses are then off by
  the same time, so the pair is off by ``L (xi_cur - Ad(T^-1) xi_ref)``: the change of the twist
  between the frames, not the twist itself as with ``timing`` (:func:`latency_basis`). A pair's
  own twist carries its own estimation error, so the basis is the recent pairs' mean
  (:class:`TwistChanges`), not this pair's; against an older keyframe the change from the keyframe
  to the last posed frame was measured by their own pairs (:func:`known_change_basis`, carried on
  over the pair) and only a new change since comes from that mean;
* ``depth_jump`` (dimensionless): the depth images of the pair's frames taken a whole number ``n`` of
  depth-frame periods apart relative to their colour images (the nearest depth image switched to
  its neighbour: :func:`~covo_gtsam.frame_errors.depth_period_jump`), ``B = b b^T`` with ``b`` the
  pair's response to the current frame's depths read ``J/2 = n P / 2`` later and the reference's
  ``J/2`` earlier (each point's own depth change and the depth image's change at the fixed pixel,
  :func:`~covo_gtsam.frame_errors.depth_read_change`); a prior held at 1 (the change is a whole
  period, not a fitted share of one);
* ``stamp_jitter`` (s): like ``timing``, the jitter of the stamps around the camera's regular
  clock: in full for a frame the frame clock has not placed yet (the first frames of a run), and
  ``1/n`` of its variance for a frame placed by a clock fitted to ``n`` stamps (the uncertainty of
  the fitted phase); a prior, not fitted (1.9 ms is the scatter of the shared fr1 colour stamps
  around a regular clock);
* ``span`` (dimensionless): a translation error that persists from interval to interval, ``c``
  times the camera's recent translation per interval ``d`` per axis, so a pair ``k`` intervals
  long gets ``c^2 d^2 (k^2 - 1)`` beyond what its first interval has (:func:`span_basis`); zero
  for consecutive pairs, whose other terms hold the first interval's share. ``d`` comes from the
  frame before the pair's current one, not from the pair itself (whose own error would enter its
  covariance). Fitted on pairs over two and three intervals with the other terms held
  (:func:`fit_span_factor`).

:func:`fit_sensor_terms` estimates ``kappa, s_r, s_t`` from the errors of consecutive pairs
against ground truth, by maximising the Gaussian likelihood; it needs SciPy
(``pip install "covo-gtsam[calibrate]"``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from .errors import InputError

__all__ = ["ERROR_TERMS", "DEFAULT_TERMS", "PRIOR_TERMS", "SensorTerms", "frame_covariance", "timing_covariance",
           "stamp_error_basis", "twist_change", "known_change_basis", "central_change_basis", "latency_basis",
           "TwistChanges", "span_basis", "sensor_covariance", "sensor_terms",
           "log_likelihood", "fit_sensor_terms", "MIN_SPAN_PAIRS", "span_fit_pairs", "fit_span_factor"]

#: Frame-level error terms and the :class:`~covo_gtsam.config.SensorConfig` field holding each sigma.
ERROR_TERMS = {"timing": "timing_sigma_s", "depth_scale": "depth_scale_sigma", "depth_time": "depth_time_factor",
               "depth_time_coherent": "depth_time_coherent_factor",
               "rolling_shutter": "rolling_shutter_factor", "stamp_jitter": "stamp_jitter_s",
               "latency": "latency_sigma_s", "span": "span_factor", "depth_jump": "depth_jump_factor",
               "gyro": "gyro_sigma_rad_s"}
#: The terms of the default model fitted on consecutive pairs (``stamp_jitter`` is a prior and ``span``
#: needs longer pairs; docs/cross_validation.md).
DEFAULT_TERMS = ("timing", "rolling_shutter", "latency", "depth_scale", "depth_time", "depth_time_coherent")
#: With a gyroscope: its error in place of the rolling-shutter term, which only the pairs its samples do
#: not cover keep (held at its configured value).
GYRO_TERMS = tuple(t for t in DEFAULT_TERMS if t != "rolling_shutter") + ("gyro",)
#: Terms held at their configured value (a prior) when the others are fitted.
PRIOR_TERMS = ("stamp_jitter", "depth_jump")
#: Fewest pairs over more than one interval the ``span`` term is fitted on (:func:`fit_span_factor`).
MIN_SPAN_PAIRS = 10


@dataclass(frozen=True)
class SensorTerms:
    """Fitted sensor terms: ``correlation_factor`` (kappa), per-interval standard deviations
    ``frame_sigma_rot_deg`` (degrees per axis) and ``frame_sigma_trans_m`` (metres per axis), the
    mean log-likelihood per pair at the fit, the number of pairs it used, ``sigmas``: the fitted
    sigma of each frame-level term (names of :data:`ERROR_TERMS`), and ``span_pairs``: the pairs
    over more than one interval the ``span`` term was fitted on (0: not fitted)."""

    correlation_factor: float
    frame_sigma_rot_deg: float
    frame_sigma_trans_m: float
    log_likelihood: float
    pairs: int
    sigmas: dict = field(default_factory=dict)
    span_pairs: int = 0

    def config_values(self) -> dict:
        """The fit as :class:`~covo_gtsam.config.SensorConfig` settings (the ``sensor`` group)."""
        out = {"correlation_factor": self.correlation_factor, "frame_sigma_rot_deg": self.frame_sigma_rot_deg,
               "frame_sigma_trans_m": self.frame_sigma_trans_m}
        out.update({ERROR_TERMS[k]: v for k, v in self.sigmas.items()})
        return out

    def covariances(self, point_covs: np.ndarray, bases: Mapping[str, np.ndarray] | None = None,
                    intervals: np.ndarray | int = 1) -> np.ndarray:
        """The covariances (..., 6, 6) this fit reports for pairs with per-point covariances
        ``point_covs`` and frame-level bases ``bases`` (:func:`sensor_covariance`)."""
        return sensor_covariance(point_covs, self.correlation_factor, np.deg2rad(self.frame_sigma_rot_deg),
                                 self.frame_sigma_trans_m, intervals, bases, self.sigmas)


def frame_covariance(sigma_rot_rad: float, sigma_trans_m: float, intervals: np.ndarray | int = 1) -> np.ndarray:
    """Frame term(s) (..., 6, 6) of pairs ``intervals`` (...,) frame intervals apart:
    ``diag(s_r^2 k (x3), s_t^2 k^2 (x3))``, tangent ``[omega, v]``."""
    k = np.asarray(intervals, dtype=float)[..., None]
    diag = np.concatenate([np.broadcast_to(sigma_rot_rad**2 * k, k.shape[:-1] + (3,)),
                           np.broadcast_to(sigma_trans_m**2 * k**2, k.shape[:-1] + (3,))], axis=-1)
    return diag[..., :, None] * np.eye(6)


def timing_covariance(twists: np.ndarray, timing_sigma_s: float = 1.0) -> np.ndarray:
    """Timing term(s) (..., 6, 6): ``tau^2 sum_f xi_f xi_f^T`` over the body twists (..., F, 6)
    ``[omega, v]`` (rad/s, m/s) of a pair's F frames; ``tau = timing_sigma_s`` (s). With the
    default ``tau = 1`` it is the term's basis ``B``."""
    xi = np.asarray(twists, dtype=float)
    return timing_sigma_s**2 * np.einsum("...fi,...fj->...ij", xi, xi)


def stamp_error_basis(T_ref_cur: np.ndarray, twist_ref: np.ndarray, twist_cur: np.ndarray,
                      weights: tuple[float, float] = (1.0, 1.0)) -> np.ndarray:
    """Basis (6, 6) of the ``timing`` term (and, with ``weights`` per frame, of ``stamp_jitter``):
    each frame of the pair ``T_ref,cur`` (4x4) captured ``d_f`` s off its stamp (independent, variance
    ``weights[f]`` per unit) moves the pair by ``-d_ref Ad(T^-1) xi_ref + d_cur xi_cur`` (right
    perturbation, body twists ``[omega, v]``); :func:`timing_covariance` of the two in the current
    frame."""
    import gtsam

    ref_in_cur = gtsam.Pose3(np.asarray(T_ref_cur, dtype=float)).inverse().AdjointMap() @ np.asarray(twist_ref, float)
    twists = np.stack([ref_in_cur, np.asarray(twist_cur, dtype=float)]) * np.sqrt(np.asarray(weights, float))[:, None]
    return timing_covariance(twists)


def span_basis(step_m: np.ndarray | float, intervals: np.ndarray | int) -> np.ndarray:
    """Basis(es) (..., 6, 6) of the ``span`` term: ``d^2 (k^2 - 1)`` on each translation axis of a
    pair ``k`` (...,) intervals long, ``d`` (..., m) the camera's recent translation per interval;
    zero for ``k = 1``."""
    d = np.asarray(step_m, dtype=float)
    k = np.asarray(intervals, dtype=float)
    out = np.zeros(np.broadcast_shapes(d.shape, k.shape) + (6, 6))
    out[..., 3:, 3:] = (d**2 * (k**2 - 1.0))[..., None, None] * np.eye(3)
    return out


def twist_change(T_ref_cur: np.ndarray, twist_ref: np.ndarray, twist_cur: np.ndarray) -> np.ndarray:
    """``b = xi_cur - Ad(T^-1) xi_ref`` (6,): the change of the body twist (``[omega, v]``, rad/s and
    m/s) from the reference frame to the current frame of a pair ``T_ref,cur`` (4x4), in the
    current frame. Both stamps ``L`` seconds late move the pair to
    ``Exp(L xi_ref)^-1 T Exp(L xi_cur) = T Exp(L b)`` to first order (right perturbation)."""
    import gtsam

    T = gtsam.Pose3(np.asarray(T_ref_cur, dtype=float))
    return np.asarray(twist_cur, dtype=float) - T.inverse().AdjointMap() @ np.asarray(twist_ref, dtype=float)


def _change_and_noise(T_ref_cur: np.ndarray, twist_ref: np.ndarray, twist_cur: np.ndarray, noise_ref: np.ndarray,
                      noise_cur: np.ndarray, cross: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`twist_change` ``b`` (6,) and the covariance (6, 6) of its estimation noise, ``N_cur +
    A N_ref A^T - A X - X^T A^T`` (``A = Ad(T^-1)``) from the two twists' noise covariances
    ``noise_ref``/``noise_cur`` and their cross-covariance ``cross`` ``X = Cov(xi_ref, xi_cur)`` (6, 6;
    zero if None: independent twists)."""
    import gtsam

    Ad = gtsam.Pose3(np.asarray(T_ref_cur, dtype=float)).inverse().AdjointMap()
    noise = noise_cur + Ad @ noise_ref @ Ad.T
    if cross is not None:
        AX = Ad @ np.asarray(cross, dtype=float)
        noise = noise - AX - AX.T
    return twist_change(T_ref_cur, twist_ref, twist_cur), noise


def _positive_part(M: np.ndarray) -> np.ndarray:
    """The symmetric matrix ``M`` with its negative eigenvalues set to 0 (positive semidefinite)."""
    w, U = np.linalg.eigh(M)
    return (U * np.clip(w, 0.0, None)) @ U.T


def known_change_basis(T_ref_cur: np.ndarray, twist_ref: np.ndarray, twist_cur: np.ndarray, noise_ref: np.ndarray,
                       noise_cur: np.ndarray) -> np.ndarray:
    """Basis (6, 6) of the ``latency`` term for a change of the twist that was measured: ``b b^T - N``
    (:func:`twist_change`, ``N`` its estimation noise from the twists' noise covariances (6, 6)),
    rotation block, clipped to positive semidefinite; as one change of :class:`TwistChanges`."""
    b, noise = _change_and_noise(T_ref_cur, twist_ref, twist_cur, noise_ref, noise_cur)
    out = np.zeros((6, 6))
    out[:3, :3] = _positive_part(np.outer(b[:3], b[:3]) - noise[:3, :3])
    return out


def central_change_basis(T_ref_cur: np.ndarray, twist_before: np.ndarray, twist_after: np.ndarray,
                         noise_before: np.ndarray, noise_after: np.ndarray) -> np.ndarray:
    """Basis (6, 6) of the ``latency`` term of a pair ``T_ref,cur`` (4x4) from the change of the twist
    across it, known one frame later: the twist of the pair before (at the reference frame; noise
    ``noise_before``) and of the pair after (``twist_after``, at the current frame). A pair's mean
    twist lags its end frame by half an interval, so the twist's change from the pair's reference
    frame to its current frame is about half the change from the pair before to the pair after:
    ``(b b^T - N) / 4`` in the current frame's axes (:func:`twist_change`, ``N`` its estimation
    noise; the two twists share no frame), all six axes, clipped to positive semidefinite."""
    b, noise = _change_and_noise(T_ref_cur, twist_before, twist_after, noise_before, noise_after)
    return 0.25 * _positive_part(np.outer(b, b) - noise)


def latency_basis(T_ref_cur: np.ndarray, twist_ref: np.ndarray, twist_cur: np.ndarray) -> np.ndarray:
    """Basis (6, 6) ``b b^T`` of the ``latency`` term for known twists at the two frames
    (:func:`twist_change`)."""
    b = twist_change(T_ref_cur, twist_ref, twist_cur)
    return np.outer(b, b)


#: Shares of the latency basis's rotation block spread evenly over the three axes (its size kept)
#: among which :class:`TwistChanges` chooses by how well each predicted the changes seen.
ISOTROPIC_SHARES = (0.0, 0.25, 0.5, 0.75, 1.0)
#: Weight of the previous score per new change (a fading memory: 1 / (1 - 0.97), about 33 changes).
SHARE_MEMORY = 0.97
#: Changes scored before the share moves from 0.
SHARE_MIN_CHANGES = 5


def _isotropic_mix(R: np.ndarray, share) -> np.ndarray:
    """``R`` (3, 3) with ``share`` (a number, or (K, 1, 1) for K shares at once) of its trace spread
    evenly over the three axes."""
    return (1.0 - share) * R + share * (np.trace(R) / 3.0) * np.eye(3)


#: Restarts of the fit's Nelder-Mead search from its own best point, at most.
FIT_RESTARTS = 5


class TwistChanges:
    """Basis of the ``latency`` term from the recent changes of the camera's twist (no ground truth).

    A pair's twist ``Log(T)/dt`` contains the pair's own estimation error, so a basis built from
    it grows where that pair's error lies and would cover it by construction. The basis of a pair
    is therefore the mean over the last ``window`` pairs *before* it of ``b b^T - N``, with ``b``
    the change of the twist from one pair to the next (:func:`latency_basis`; each pair's mean
    twist lags its frame by half an interval, which cancels in the change) and ``N`` the part of
    ``b b^T`` the two pairs' estimation noise accounts for (their per-point covariances over
    ``dt^2``, and their cross-covariance through the middle frame's points, which enter the two
    twists with opposite signs); changes of consecutive pairs of equal length, per frame interval (a change between
    pairs ``m`` intervals long counts ``1/m^2``), and a pair ``k`` intervals long gets ``k^2`` times
    the basis (odometry; against an older keyframe the measured change to the last posed frame,
    :func:`known_change_basis`, carried on over the pair, plus ``m^2`` times the basis over the ``m``
    intervals since); rotation block only (a translation change of the twist is below its noise). The
    mean is clipped to positive semidefinite (clipping each term instead would leave most of the
    noise in). Until the window holds a change the basis is the caller's prior (the
    odometry's: ``sensor.angular_acceleration_prior`` over one frame interval, in any direction;
    docs/derivation.md, "The history's length").

    The mean gives the changes' size and their direction over the window. Where the motion keeps
    its axis (fr1_rpy turns about one axis for seconds) the direction carries over to the next
    pair; where the axis wanders within a few frames it does not, and a basis that is thin across
    the recent direction leaves the next change uncovered. :attr:`share` of the rotation block's
    trace is therefore spread evenly over the three axes, the share among
    :data:`ISOTROPIC_SHARES` under whose bases the changes seen so far were most likely (each
    change scored against the basis before it, with its noise; scores fade by
    :data:`SHARE_MEMORY` per change; 0 for the first :data:`SHARE_MIN_CHANGES` changes). The run
    learns it from its own twists: no ground truth. Until the window is full, the share of the
    places still empty is spread over the axes too (nine tenths after one change in a window of 10,
    none when full): a few changes tell the next one's size better than its direction. After a long
    stretch about one axis the scores are far apart, and a switch to wandering turns takes about
    100-150 changes to move the share (about 50 from the start). :meth:`clear` (tracking lost)
    empties the window but keeps the scores and the share: they describe the camera's motion, not
    the last pairs.
    """

    def __init__(self, window: int = 10) -> None:
        from collections import deque

        self._changes = deque(maxlen=window)
        self._sum = np.zeros((6, 6))  # of the changes in the window
        self._mean = np.zeros((6, 6))  # their mean, clipped to positive semidefinite
        self._scores = np.zeros(len(ISOTROPIC_SHARES))
        self._scored = 0
        self.share = 0.0

    def _update_mean(self) -> None:
        """The mean of the window's changes, clipped to positive semidefinite."""
        if not self._changes:
            self._mean = np.zeros((6, 6))
            return
        self._mean = _positive_part(self._sum / len(self._changes))

    def basis(self, prior: np.ndarray | None = None) -> np.ndarray:
        """6x6 basis (tangent ``[omega, v]``, (rad/s)^2 blocks) for the next pair; ``prior`` (6, 6;
        zeros if None) before any change has been seen."""
        out = np.zeros((6, 6))
        n = len(self._changes)
        if not n:
            return out if prior is None else np.asarray(prior, dtype=float)
        W = self._changes.maxlen
        out[:3, :3] = _isotropic_mix(self._mean[:3, :3], self.share + (1.0 - self.share) * (W - n) / W)
        return out

    def _score(self, b: np.ndarray, noise: np.ndarray) -> None:
        """Score each share of :data:`ISOTROPIC_SHARES` by the log-likelihood of the observed change
        ``b`` (3,) under the basis it gave before ``b`` was seen, plus the change's noise (3, 3)."""
        C = _isotropic_mix(self._mean[:3, :3], np.asarray(ISOTROPIC_SHARES)[:, None, None]) + noise
        # by eigenvalues, floored far below the largest: a basis thin across b scores very low
        # (not a singular-matrix error), however small the change's noise
        w, U = np.linalg.eigh(C)
        w = np.maximum(w, max(1e-12 * float(w.max()), 1e-200))
        proj = np.einsum("kij,i->kj", U, b)
        ll = -0.5 * np.sum(proj**2 / w, axis=1) - 0.5 * np.sum(np.log(w), axis=1)
        if not np.all(np.isfinite(ll)):  # a change no share can score: it says nothing about the shares
            return
        self._scores = SHARE_MEMORY * self._scores + ll
        self._scored += 1
        if self._scored >= SHARE_MIN_CHANGES:
            self.share = float(ISOTROPIC_SHARES[int(np.argmax(self._scores))])

    def add(self, T_ref_cur: np.ndarray, twist_ref: np.ndarray, twist_cur: np.ndarray, noise_ref: np.ndarray,
            noise_cur: np.ndarray, intervals: int = 1, cross: np.ndarray | None = None) -> None:
        """Record the change between two consecutive pairs' mean twists (6,) (rad/s, m/s), each pair
        ``intervals`` frame intervals long (so their twists that far apart), per interval;
        ``T_ref,cur`` (4x4) is the later pair, ``noise_ref``/``noise_cur`` (6, 6) the covariances of
        the two twists' estimation noise ((rad/s)^2 and (m/s)^2 blocks: a pair's per-point
        covariance over its interval squared) and ``cross`` their cross-covariance (the shared middle
        frame's, :func:`~covo_gtsam.frame_errors.shared_frame_covariance` over both intervals; None:
        independent)."""
        change, noise = _change_and_noise(T_ref_cur, twist_ref, twist_cur, noise_ref, noise_cur, cross)
        change, noise = change / intervals, noise / intervals**2
        if not (np.all(np.isfinite(change)) and np.all(np.isfinite(noise))):
            return
        if self._changes:
            self._score(change[:3], noise[:3, :3])
        X = np.zeros((6, 6))
        X[:3, :3] = np.outer(change[:3], change[:3]) - noise[:3, :3]
        if not np.all(np.isfinite(X)):
            return
        if len(self._changes) == self._changes.maxlen:
            self._sum -= self._changes[0]
        self._changes.append(X)
        self._sum += X
        self._update_mean()

    def clear(self) -> None:
        self._changes.clear()
        self._sum = np.zeros((6, 6))
        self._update_mean()


def sensor_covariance(point_cov: np.ndarray, correlation_factor: float, sigma_rot_rad: float,
                      sigma_trans_m: float, intervals: np.ndarray | int = 1,
                      bases: Mapping[str, np.ndarray] | None = None,
                      sigmas: Mapping[str, float] | None = None) -> np.ndarray:
    """Reported covariance(s) ``kappa * C_points + frame_covariance(s_r, s_t, k) + sum_j sigma_j^2 B_j``.

    ``point_cov`` (..., 6, 6), ``intervals`` (...,) and each basis ``bases[j]`` (..., 6, 6)
    broadcast; ``sigmas[j]`` is the sigma of term ``j`` (0 if absent); tangent ``[omega, v]``.
    """
    C = correlation_factor * np.asarray(point_cov, dtype=float)
    for term in sensor_terms(sigma_rot_rad, sigma_trans_m, intervals, bases, sigmas).values():
        C = C + term
    return C


def sensor_terms(sigma_rot_rad: float, sigma_trans_m: float, intervals: np.ndarray | int = 1,
                 bases: Mapping[str, np.ndarray] | None = None,
                 sigmas: Mapping[str, float] | None = None) -> dict[str, np.ndarray]:
    """The sensor terms of :func:`sensor_covariance`, each on its own: ``"frame_term"``
    (:func:`frame_covariance`) and, by name, each frame-level term with ``sigmas[j] > 0``,
    ``sigma_j^2 B_j`` (..., 6, 6)."""
    terms = {"frame_term": frame_covariance(sigma_rot_rad, sigma_trans_m, intervals)}
    for name, B in (bases or {}).items():
        sigma = (sigmas or {}).get(name, 0.0)
        if sigma > 0:
            terms[name] = sigma**2 * np.asarray(B, dtype=float)
    return terms


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
                     bases: Mapping[str, np.ndarray] | None = None, fixed: np.ndarray | None = None,
                     intervals: np.ndarray | int = 1, frame_rotation: bool = True) -> SensorTerms:
    """Maximum-likelihood ``kappa, s_r, s_t`` and the sigma of each frame-level term in ``bases``
    from pairs ``intervals`` frame intervals apart (1: consecutive pairs; or one count per pair; the
    library's own calibration, :func:`covo_gtsam.pipeline.calibrate_sequence`, fits consecutive pairs);
    with ``fit_correlation_factor=False`` kappa stays 1, with ``frame_rotation=False`` ``s_r`` stays 0.

    ``errors`` (N, 6): ``Log(T_est^-1 T_true)`` of each pair
    (:func:`covo_gtsam.metrics.relative_pose_tangent_errors`; right perturbation, ``[omega, v]``);
    ``point_covs`` (N, 6, 6): the estimator's per-point covariance of the same pairs (run with
    ``correlation_factor = 1`` and no other term); ``bases``: term name -> (N, 6, 6) basis of
    each pair (:attr:`~covo_gtsam.steps.OdometryStep.error_bases`); ``fixed`` (N, 6, 6): known
    terms added as they are (e.g. a prior's). Needs at least 10 pairs.
    """
    errors = np.asarray(errors, dtype=float)
    point_covs = np.asarray(point_covs, dtype=float)
    if errors.ndim != 2 or errors.shape[1] != 6 or point_covs.shape != errors.shape + (6,):
        raise InputError(f"need errors (N, 6) and covariances (N, 6, 6), got {errors.shape} and {point_covs.shape}")
    if len(errors) < 10:
        raise InputError(f"need at least 10 pairs to fit the sensor terms, got {len(errors)}")
    if not (np.all(np.isfinite(errors)) and np.all(np.isfinite(point_covs))):
        raise InputError("errors and covariances must be finite")
    try:
        intervals = np.broadcast_to(np.asarray(intervals, dtype=float), (len(errors),))
    except ValueError:
        raise InputError(f"intervals must be one count or one per pair ({len(errors)}), got shape "
                         f"{np.shape(intervals)}") from None
    if not np.all(np.isfinite(intervals) & (intervals >= 1)):
        raise InputError("intervals must be frame interval counts of at least 1")
    bases = {k: np.asarray(v, dtype=float) for k, v in (bases or {}).items()}
    fixed = np.zeros_like(point_covs) if fixed is None else np.asarray(fixed, dtype=float)
    if fixed.shape != point_covs.shape or not np.all(np.isfinite(fixed)):
        raise InputError(f"fixed terms must be finite (N, 6, 6) for N = {len(errors)} pairs, got {fixed.shape}")
    for name, B in bases.items():
        if B.shape != point_covs.shape or not np.all(np.isfinite(B)):
            raise InputError(f"basis {name!r} must be finite (N, 6, 6) for N = {len(errors)} pairs, got {B.shape}")
    try:
        from scipy.optimize import minimize
    except ImportError as exc:  # pragma: no cover - depends on the installation
        raise ImportError('fitting the sensor terms needs SciPy: pip install "covo-gtsam[calibrate]"') from exc
    # a term whose basis is zero on every pair (e.g. the rolling shutter without a readout) leaves
    # the likelihood flat: it is not fitted and reported as 0
    dead = [k for k, B in bases.items() if not np.any(B)]
    bases = {k: B for k, B in bases.items() if k not in dead}
    names = list(bases)

    free = np.array([fit_correlation_factor, frame_rotation, True])  # of kappa, s_r, s_t

    def params(x: np.ndarray) -> tuple[float, float, float, dict]:
        head = np.array([1.0, 0.0, 0.0])
        head[free] = np.exp(x[:free.sum()])
        return head[0], head[1], head[2], dict(zip(names, np.exp(x[free.sum():])))

    def cost(x: np.ndarray) -> float:
        kappa, s_r, s_t, sig = params(x)
        return -log_likelihood(errors, sensor_covariance(point_covs, kappa, s_r, s_t, intervals, bases, sig) + fixed)

    # start from moment matching: kappa 1, frame variances = mean squared error per axis, then
    # from larger kappa and smaller frame terms (the likelihood can have more than one maximum);
    # each frame-level term starts where it explains a tenth of the mean squared error
    start = np.log([1.0, np.sqrt(np.mean(errors[:, :3] ** 2)) + 1e-9, np.sqrt(np.mean(errors[:, 3:] ** 2)) + 1e-9])
    msq = np.mean(np.einsum("ni,ni->n", errors, errors))
    term_start = [np.log(np.sqrt(0.1 * msq / max(np.mean(np.trace(bases[k], axis1=1, axis2=2)), 1e-30)))
                  for k in names]
    search = {"maxiter": 4000 * (1 + len(names)), "xatol": 1e-6, "fatol": 1e-10}
    best = None
    for shift in (0.0, 1.0, 2.0, 3.0) if fit_correlation_factor else (0.0,):
        x0 = start + np.array([shift, -0.3 * shift, -0.3 * shift])
        x0 = np.concatenate([x0[free], term_start])
        res = minimize(cost, x0, method="Nelder-Mead", options=search)
        if best is None or res.fun < best.fun:
            best = res
    # Nelder-Mead's simplex can collapse short of the maximum: restart it from its own best point
    # (a fresh simplex) while that still gains
    for _ in range(FIT_RESTARTS):
        res = minimize(cost, best.x, method="Nelder-Mead", options=search)
        if not res.fun < best.fun - 1e-9:
            break
        best = res
    x = _zero_where_flat(cost, best.x, first=int(fit_correlation_factor))
    kappa, s_r, s_t, sig = params(x)
    return SensorTerms(float(kappa), float(np.rad2deg(s_r)), float(s_t), float(-cost(x)), len(errors),
                       {**{k: float(v) for k, v in sig.items()}, **{k: 0.0 for k in dead}})


def _zero_where_flat(cost, x: np.ndarray, first: int) -> np.ndarray:
    """``x`` (logs of the fitted sigmas) with each sigma from index ``first`` on set to exactly 0
    (log -inf) where the cost per pair cannot tell it from 0 (within 1e-9): a fit driven to the
    boundary stops at values such as 1e-60 s, which mean none."""
    x = np.array(x, dtype=float)
    base = cost(x)
    for i in range(first, len(x)):
        trial = x.copy()
        trial[i] = -np.inf
        if cost(trial) <= base + 1e-9:
            x = trial
    return x


def span_fit_pairs(span_bases: np.ndarray) -> np.ndarray:
    """Which pairs (N,) of span bases (N, 6, 6) the span term can be fitted on: those whose basis is
    not zero (over more than one interval, after a frame with a recent translation)."""
    return np.any(np.asarray(span_bases) != 0, axis=(1, 2))


def fit_span_factor(errors: np.ndarray, covs: np.ndarray, span_bases: np.ndarray) -> float:
    """Maximum-likelihood sigma of the ``span`` term (:func:`span_basis`) from pairs over more than
    one interval, the other terms held: ``errors`` (N, 6) against ground truth (tangent
    ``[omega, v]``), ``covs`` (N, 6, 6) the covariances without the span term, ``span_bases``
    (N, 6, 6). Needs at least :data:`MIN_SPAN_PAIRS` pairs whose basis is not zero
    (:func:`span_fit_pairs`); SciPy."""
    errors = np.asarray(errors, dtype=float)
    covs = np.asarray(covs, dtype=float)
    span_bases = np.asarray(span_bases, dtype=float)
    if errors.ndim != 2 or errors.shape[1] != 6 or covs.shape != errors.shape + (6,) or span_bases.shape != covs.shape:
        raise InputError(f"need errors (N, 6), covariances and bases (N, 6, 6), got {errors.shape}, {covs.shape} "
                         f"and {span_bases.shape}")
    if not (np.all(np.isfinite(errors)) and np.all(np.isfinite(covs)) and np.all(np.isfinite(span_bases))):
        raise InputError("errors, covariances and bases must be finite")
    used = span_fit_pairs(span_bases)
    if used.sum() < MIN_SPAN_PAIRS:
        raise InputError(f"need at least {MIN_SPAN_PAIRS} pairs over more than one interval with a recent translation "
                         f"to fit the span term, got {int(used.sum())}")
    try:
        from scipy.optimize import minimize_scalar
    except ImportError as exc:  # pragma: no cover - depends on the installation
        raise ImportError('fitting the sensor terms needs SciPy: pip install "covo-gtsam[calibrate]"') from exc
    e, C, B = errors[used], covs[used], span_bases[used]
    res = minimize_scalar(lambda x: -log_likelihood(e, C + np.exp(2 * x) * B), bounds=(np.log(1e-4), np.log(100.0)),
                          method="bounded", options={"xatol": 1e-6})
    # no factor the search found explains the pairs better than none: no growth beyond the other terms
    if not -res.fun > log_likelihood(e, C):
        return 0.0
    return float(np.exp(res.x))  # at most 100, the setting's largest value
