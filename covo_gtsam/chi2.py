"""Chi-square distribution without scipy, and the chi-square constants the package uses.

Every chi-square number the package relies on is named here, with the probability and degrees of
freedom it comes from (:data:`SOURCES`); ``tests/test_chi2.py`` checks each against
``scipy.stats.chi2``. A constant given with few digits is kept at those digits: the results
(inlier sets, robust weights, the integrity scale) depend on its exact value.
"""

from __future__ import annotations

import math

import numpy as np

from .errors import InputError

__all__ = [
    "CHI2_2_99",
    "CHI2_3_99",
    "CHI2_3_975",
    "anees_band",
    "CHI2_6_MEDIAN",
    "SOURCES",
    "SQRT_CHI2_3_95",
    "chi2_cdf",
    "chi2_pdf",
    "chi2_quantile",
]


def _gamma_pq(a: float, x: float) -> tuple[float, float]:
    """Regularised incomplete gamma ``(P(a, x), Q(a, x) = 1 - P)``, each accurate in its own tail.

    Series for ``x < a + 1``, Lentz continued fraction otherwise (Numerical Recipes 6.2).
    """
    if x <= 0.0:
        return 0.0, 1.0
    if math.isinf(x):
        return 1.0, 0.0
    log_pref = -x + a * math.log(x) - math.lgamma(a)
    if x < a + 1.0:
        ap, term, total = a, 1.0 / a, 1.0 / a
        for _ in range(10000):
            ap += 1.0
            term *= x / ap
            total += term
            if abs(term) < abs(total) * 1e-16:
                break
        p = total * math.exp(log_pref)
        return p, 1.0 - p
    tiny = 1e-300
    b = x + 1.0 - a
    c = 1.0 / tiny
    d = 1.0 / b
    h = d
    for i in range(1, 10000):
        an = -i * (i - a)
        b += 2.0
        d = an * d + b
        d = tiny if abs(d) < tiny else d
        c = b + an / c
        c = tiny if abs(c) < tiny else c
        d = 1.0 / d
        step = d * c
        h *= step
        if abs(step - 1.0) < 1e-16:
            break
    q = math.exp(log_pref) * h
    return 1.0 - q, q


def _check_dof(dof: float) -> float:
    dof = float(dof)
    if not dof > 0 or not math.isfinite(dof):
        raise InputError(f"degrees of freedom must be > 0, got {dof}")
    return dof


def chi2_cdf(x: float, dof: float) -> float:
    """Chi-square CDF ``P(dof/2, x/2)`` (scalar)."""
    return _gamma_pq(_check_dof(dof) / 2.0, float(x) / 2.0)[0]


def chi2_quantile(p: float, dof: float) -> float:
    """Chi-square quantile: ``x`` with ``CDF(x; dof) = p``, for ``0 < p < 1``.

    Bisection on the regularised incomplete gamma (lower tail for p <= 0.5, upper tail above),
    to ~1e-13 relative; e.g. ``chi2_quantile(0.975, 3) = 9.3484``.
    """
    dof = _check_dof(dof)
    p = float(p)
    if not 0.0 < p < 1.0:
        raise InputError(f"p must be in (0, 1), got {p}")
    a = dof / 2.0
    upper = p > 0.5
    target = 1.0 - p if upper else p

    def below(x: float) -> bool:  # True when the quantile is above x
        P, Q = _gamma_pq(a, x / 2.0)
        return Q > target if upper else P < target

    lo, hi = 0.0, max(1.0, dof + 10.0 * math.sqrt(2.0 * dof))
    while below(hi):
        lo, hi = hi, 2.0 * hi
    for _ in range(2000):
        mid = 0.5 * (lo + hi)
        if mid <= lo or mid >= hi:
            break
        if below(mid):
            lo = mid
        else:
            hi = mid
        if hi - lo <= 1e-14 * hi:
            break
    return 0.5 * (lo + hi)


def chi2_pdf(x: np.ndarray, dof: float) -> np.ndarray:
    """Chi-square density at ``x`` (any shape); 0 for x < 0."""
    dof = _check_dof(dof)
    x = np.asarray(x, dtype=float)
    k = dof / 2.0
    pos = x > 0
    xs = np.where(pos, x, 1.0)
    dens = np.exp((k - 1.0) * np.log(xs) - xs / 2.0 - k * math.log(2.0) - math.lgamma(k))
    at0 = 0.5 if dof == 2 else (np.inf if dof < 2 else 0.0)
    return np.where(pos, dens, np.where(x == 0, at0, 0.0))


def anees_band(pairs: int, dof: int = 3) -> tuple[float, float]:
    """Two-sided 95 % band of the ANEES of ``pairs`` independent ``dof``-dimensional NEES values of
    a consistent covariance: ``chi2_quantile(p, dof pairs) / pairs`` at p = 0.025 and 0.975
    (1.55-4.92 for 8 pairs of 3 dof, 2.41-3.65 for 60)."""
    n = int(pairs)
    if n < 1:
        raise InputError(f"the ANEES band needs at least one pair, got {pairs!r}")
    return chi2_quantile(0.025, dof * n) / n, chi2_quantile(0.975, dof * n) / n


#: chi2(3) 97.5 % quantile (9.3484): upper bound of a consistent 3-dof NEES; ``covo run`` reports
#: the share of NEES above it (``chi2_3_975`` in ``metrics.json``).
CHI2_3_975 = chi2_quantile(0.975, 3)
#: chi2(2) 99 % quantile (-2 ln 0.01 = 9.21034), rounded to 9.2103: the gate of a reprojection
#: residual (:func:`covo_gtsam.integrity.depth_free_consensus`).
CHI2_2_99 = 9.2103
#: chi2(3) 99 % quantile (11.34487), rounded to 11.345: default gate of the rigid RANSAC's
#: Mahalanobis inlier test.
CHI2_3_99 = 11.345
#: Square root of the chi2(3) 95 % quantile (sqrt(7.81473) = 2.79548), rounded to 2.7955: default
#: threshold of the robust kernels, a Mahalanobis distance.
SQRT_CHI2_3_95 = 2.7955
#: chi2(6) median (50 % quantile, 5.34812), rounded to 5.3481: the integrity statistic's scale.
CHI2_6_MEDIAN = 5.3481

#: Where each constant comes from: name -> (probability, degrees of freedom, square root taken,
#: decimals kept; None for full precision).
SOURCES = {
    "CHI2_3_975": (0.975, 3, False, None),
    "CHI2_2_99": (0.99, 2, False, 4),
    "CHI2_3_99": (0.99, 3, False, 3),
    "SQRT_CHI2_3_95": (0.95, 3, True, 4),
    "CHI2_6_MEDIAN": (0.5, 6, False, 4),
}
