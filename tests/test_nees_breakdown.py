"""The NEES breakdown of metrics.json: motion taken from the ground truth, bins, tails and windows,
each against a direct computation or scipy's chi-square distribution."""

import numpy as np
import pytest
from scipy import stats
from scipy.spatial.transform import Rotation

from covo_gtsam.nees_breakdown import (
    SPEED_EDGES,
    by_bins,
    nees_breakdown,
    tail_statistics,
    true_motion,
    window_statistics,
)


def turning_pairs(omegas: np.ndarray, axes: np.ndarray, dt: float) -> np.ndarray:
    """T_ref,cur (K, 4, 4): rotation by omegas[k] dt about axes[k], and a small translation."""
    T = np.tile(np.eye(4), (len(omegas), 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(axes * (omegas * dt)[:, None]).as_matrix()
    T[:, :3, 3] = [0.01, -0.02, 0.005]
    return T


def test_speed_and_acceleration_of_a_turn_speeding_up():
    dt, a = 1 / 30, 6.0  # rad/s^2
    omegas = 0.5 + a * dt * np.arange(12)
    axes = np.tile([0.0, 0.6, 0.8], (12, 1))
    stamps = 100.0 + dt * np.arange(13)
    speed, accel = true_motion(turning_pairs(omegas, axes, dt), stamps[:-1], stamps[1:])
    np.testing.assert_allclose(speed, omegas, rtol=1e-9)
    assert np.isnan(accel[0])  # no pair before the first
    np.testing.assert_allclose(accel[1:], a, rtol=1e-9)


def test_acceleration_needs_the_pair_before_to_end_where_this_one_starts():
    dt = 1 / 30
    axes = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 1.0, 0], [0, 0, 1.0]])
    omegas = np.array([1.0, 1.0, 2.0, 1.0])
    ref = np.array([0.0, dt, 3 * dt, 4 * dt])  # a frame lost between the second and third pair
    cur = ref + dt
    _, accel = true_motion(turning_pairs(omegas, axes, dt), ref, cur)
    assert np.isnan(accel[0]) and np.isnan(accel[2])
    assert accel[1] == pytest.approx(np.sqrt(2.0) / dt, rel=1e-9)  # x-turn to y-turn at 1 rad/s
    assert accel[3] == pytest.approx(np.sqrt(5.0) / dt, rel=1e-9)  # 2 rad/s about y to 1 about z


def test_bins_count_each_value_once_and_leave_nan_out():
    rng = np.random.default_rng(3)
    values = rng.uniform(0, 4, 300)
    values[::17] = np.nan
    values[5] = 1.5  # on an edge: the upper bin
    nr, nt = rng.chisquare(3, 300), rng.chisquare(3, 300)
    bins = by_bins(values, SPEED_EDGES, nr, nt)
    assert sum(b["pairs"] for b in bins) == np.sum(~np.isnan(values))
    for b in bins:
        lo, hi = b["range"][0], np.inf if b["range"][1] is None else b["range"][1]
        inside = [i for i, v in enumerate(values) if lo <= v < hi]
        assert b["pairs"] == len(inside)
        if inside:
            assert b["anees_translation"] == pytest.approx(np.mean(nt[inside]))
            assert b["anees_rotation"] == pytest.approx(np.mean(nr[inside]))
        else:
            assert b["anees_translation"] is None
    assert bins[3]["range"] == [1.5, 2.0] and bins[-1]["range"] == [3.0, None]
    assert bins[-1]["pairs"] == sum(1 for v in values if v >= 3.0)


def test_tails_of_consistent_values_match_the_chi_square_distribution():
    x = np.random.default_rng(0).chisquare(3, 400_000)
    tails = tail_statistics(x)
    q98 = stats.chi2.ppf(0.98, 3)
    # E[X; X > q] = 3 P(chi2(5) > q) for X ~ chi2(3): the share of the sum in the top 2 %
    assert tails["share_of_sum_in_top_2_percent"] == pytest.approx(stats.chi2.sf(q98, 5), abs=0.002)
    assert tails["percentile_95"] == pytest.approx(stats.chi2.ppf(0.95, 3), rel=0.01)
    assert tails["largest"] == x.max()
    # a few gross pairs carry most of the sum
    y = np.r_[np.ones(98), 500.0, 500.0]
    assert tail_statistics(y)["share_of_sum_in_top_2_percent"] == pytest.approx(1000 / 1098)


def test_windows_and_their_band():
    w = window_statistics(np.full(150, 2.0), np.r_[np.full(60, 1.0), np.full(60, 5.0), np.full(30, 9.0)])
    assert w["windows"] == 2  # the last 30 pairs make no full window
    assert w["anees_upper_95"] == pytest.approx(stats.chi2.ppf(0.975, 180) / 60, rel=1e-9)
    assert (w["anees_translation"]["lowest"], w["anees_translation"]["highest"]) == (1.0, 5.0)
    assert w["anees_translation"]["share_above_upper_95"] == 0.5
    assert w["anees_rotation"]["share_above_upper_95"] == 0.0
    assert window_statistics(np.ones(59), np.ones(59)) is None
    # consistent values: about 2.5 % of the windows above the band
    x = np.random.default_rng(1).chisquare(3, (2, 60 * 4000))
    share = window_statistics(x[0], x[1])["anees_translation"]["share_above_upper_95"]
    assert share == pytest.approx(0.025, abs=0.008)


def test_breakdown_is_json_ready():
    import json

    dt = 1 / 30
    omegas = np.linspace(0.2, 2.5, 70)
    stamps = dt * np.arange(71)
    nr = nt = np.random.default_rng(2).chisquare(3, 70)
    bd = nees_breakdown(turning_pairs(omegas, np.tile([1.0, 0, 0], (70, 1)), dt), stamps[:-1], stamps[1:], nr, nt)
    text = json.dumps(bd, allow_nan=False)
    assert json.loads(text)["windows"]["windows"] == 1
