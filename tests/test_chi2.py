"""The named chi-square constants against scipy.stats.chi2, and the modules that use them."""

import math

import pytest

from covo_gtsam import chi2 as c


@pytest.mark.parametrize("name", sorted(c.SOURCES))
def test_constant_matches_scipy(name):
    from scipy.stats import chi2

    p, dof, root, decimals = c.SOURCES[name]
    expected = chi2.ppf(p, dof)
    if root:
        expected = math.sqrt(expected)
    value = getattr(c, name)
    if decimals is None:
        assert value == pytest.approx(expected, rel=1e-12)
    else:  # rounded to the digits written, correctly
        assert value == round(expected, decimals)
        assert abs(value - expected) <= 0.5 * 10.0**-decimals


def test_every_constant_has_a_source():
    names = {n for n in vars(c) if n.isupper() and n != "SOURCES"}
    assert names == set(c.SOURCES)
    assert set(c.SOURCES) <= set(c.__all__)


def test_modules_use_the_named_constants():
    from covo_gtsam import estimator, integrity
    from covo_gtsam.frontend import FrontendConfig

    assert estimator.ROBUST_K == c.SQRT_CHI2_3_95
    assert integrity.CHI2_6_MEDIAN is c.CHI2_6_MEDIAN
    assert FrontendConfig().ransac_chi2 == c.CHI2_3_99


def test_quantile_function_gives_the_reported_bound():
    # metrics.json's chi2_3_975 is this value
    assert c.chi2_quantile(0.975, 3) == c.CHI2_3_975


@pytest.mark.parametrize("pairs", [1, 8, 60, 1000])
def test_anees_band_is_scipys_chi_square_band_over_the_pairs(pairs):
    from scipy import stats

    from covo_gtsam.chi2 import anees_band
    from covo_gtsam.errors import InputError

    lo, hi = anees_band(pairs)
    assert lo == pytest.approx(stats.chi2.ppf(0.025, 3 * pairs) / pairs, rel=1e-9)
    assert hi == pytest.approx(stats.chi2.ppf(0.975, 3 * pairs) / pairs, rel=1e-9)
    with pytest.raises(InputError):
        anees_band(0)
