"""The thesis's simulation: reproducible by seed; a quick consistency smoke test."""

from __future__ import annotations

import numpy as np

from covo_gtsam.simulation import SimulationConfig, run_simulation


def test_reproducible_by_seed():
    a = run_simulation(SimulationConfig(runs=5, seed=3, num_points=100))
    b = run_simulation(SimulationConfig(runs=5, seed=3, num_points=100))
    c = run_simulation(SimulationConfig(runs=5, seed=4, num_points=100))
    np.testing.assert_array_equal(a.errors, b.errors)
    np.testing.assert_array_equal(a.covariances, b.covariances)
    assert not np.array_equal(a.errors, c.errors)


def test_consistent_weighting_smoke():
    # 60 runs only: a loose bound for a fast test; the acceptance figures come from `covo simulate`
    r = run_simulation(SimulationConfig(runs=60, seed=0, pixel_sigma=1.0))
    assert 1.8 < r.anees_translation < 4.5
    assert 1.8 < r.anees_rotation < 4.5
    s = r.summary()
    assert s["runs"] == 60 and set(s["sigma_empirical"]) == {"rx", "ry", "rz", "tx", "ty", "tz"}


def test_thesis_weighting_is_overconfident():
    r = run_simulation(SimulationConfig(runs=40, seed=0, weighting="thesis"))
    assert r.anees_translation > 8 and r.anees_rotation > 8
