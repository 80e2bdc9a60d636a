"""Time of estimate_relative_pose (LM solve + Marginals) per frame pair vs number of pairs.

    python benchmarks/bench_estimator.py [--repeats 50]

Prints median and 90th percentile in milliseconds for 100/300/500/1000 simulated pairs and both
weightings, and a breakdown for 1000 pairs.
"""

from __future__ import annotations

import argparse
import time

import gtsam
import numpy as np

from covo_gtsam.estimator import (
    POSE_KEY,
    _lm_params,
    estimate_relative_pose,
    initial_guess,
    marginal_covariance,
    validate_inputs,
)
from covo_gtsam.factors import transfer_factor
from covo_gtsam.noise import PixelNoise, PointNoiseModel
from covo_gtsam.simulation import SimulationConfig, make_scene, noisy_measurements
from covo_gtsam.transfer import residual_covariances, whitened_system, whitening


def pairs(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    scene = make_scene(SimulationConfig(num_points=n), rng)
    model = PointNoiseModel(pixel=PixelNoise(2.0, 2.0))
    X0, Q0 = noisy_measurements(scene.X0, scene.camera, model, rng)
    X1, Q1 = noisy_measurements(scene.X1, scene.camera, model, rng)
    return X0, X1, Q0, Q1


def timed(fn, repeats: int) -> np.ndarray:
    fn()  # warm-up
    out = np.empty(repeats)
    for i in range(repeats):
        t = time.perf_counter()
        fn()
        out[i] = (time.perf_counter() - t) * 1000
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=50)
    ap.add_argument("--pairs", type=int, nargs="+", default=[100, 300, 500, 1000])
    ap.add_argument("--no-breakdown", action="store_true", help="only the table")
    args = ap.parse_args()
    print(f"{'pairs':>6} {'weighting':>11} {'median ms':>10} {'p90 ms':>8} {'iterations':>10}")
    for n in args.pairs:
        data = pairs(n)
        for w in ("consistent", "thesis"):
            res = estimate_relative_pose(*data, weighting=w)
            t = timed(lambda data=data, w=w: estimate_relative_pose(*data, weighting=w), args.repeats)
            print(f"{n:>6} {w:>11} {np.median(t):>10.2f} {np.percentile(t, 90):>8.2f} {res.iterations:>10}")
    if args.no_breakdown:
        return

    X0, X1, Q0, Q1 = pairs(1000)
    init = initial_guess(X0, X1, Q0, Q1)
    C_b, C_f = residual_covariances(Q0, Q1, "consistent", init.rotation().matrix())
    graph = gtsam.NonlinearFactorGraph()
    graph.add(transfer_factor(POSE_KEY, X0, X1, C_b, C_f))
    values = gtsam.Values()
    values.insert(POSE_KEY, init)
    sol = gtsam.LevenbergMarquardtOptimizer(graph, values, _lm_params(50)).optimize()
    pose = sol.atPose3(POSE_KEY)
    W_b, W_f = whitening(C_b), whitening(C_f)
    R_sol, t_sol = pose.rotation().matrix(), pose.translation()

    def linearised_marginals():
        _, J = whitened_system(R_sol, t_sol, X0, X1, W_b, W_f)
        return marginal_covariance(J.T @ J, pose)

    parts = {
        "input checks": lambda: validate_inputs(X0, X1, Q0, Q1),
        "initial guess (closed form)": lambda: initial_guess(X0, X1, Q0, Q1),
        "residual covariances + factor": lambda: transfer_factor(POSE_KEY, X0, X1, *residual_covariances(
            Q0, Q1, "consistent", init.rotation().matrix())),
        "one LM solve": lambda: gtsam.LevenbergMarquardtOptimizer(graph, values, _lm_params(50)).optimize(),
        "Jacobian at the solution + Marginals": linearised_marginals,
        "(Marginals on the nonlinear graph)": lambda: gtsam.Marginals(graph, sol).marginalCovariance(POSE_KEY),
    }
    print("\nbreakdown at 1000 pairs (consistent weighting runs LM once per re-weighting pass)")
    for name, fn in parts.items():
        t = timed(fn, args.repeats)
        print(f"  {name:<38} {np.median(t):7.2f} ms")


if __name__ == "__main__":
    main()
