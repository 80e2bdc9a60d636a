#!/usr/bin/env python
"""Three views of one relative-pose covariance: GTSAM Marginals, the thesis's Q_tq, Monte Carlo.

    python examples/compare_covariances.py [--runs N] [--seq SEQ_DIR] [--pair I] [--gap G] [--seed S] [--out DIR]

For the estimate ``T_0,1`` (maps points of camera 1 into camera 0) it prints, per axis:

``Marginals``
    the estimator's covariance: ``gtsam.Marginals`` of the point-transfer graph (``result.covariance``,
    the per-point model's alone; on real frames covo reports it with the sensor terms added);
``Q_tq -> tangent``
    the thesis's covariance (4.20) computed independently here: first-order propagation of the
    point covariances through the (whitened) residuals' Jacobian with respect to the thesis's
    parameters ``(t, q_v)`` -- by central finite differences, no GTSAM -- i.e.
    ``Q_tq = phi (J_tq^T J_tq)^-1``, then mapped to GTSAM's tangent with
    :func:`covo_gtsam.covariance.tq_to_tangent`; it agrees with ``Marginals`` to finite-difference
    precision (and ``result.covariance_tq`` = ``tangent_to_tq(Marginals)`` agrees with ``Q_tq``);
``MC empirical``
    the spread of the estimates over repeated noise draws.

Part 1, simulation (:mod:`covo_gtsam.simulation`, the thesis's scene of section 5.2): ``--runs``
noise draws around a known truth, for both weightings (``consistent`` and the thesis's ``thesis``,
also with its phi = 16). Errors are ``xi = Log(T_est^-1 T_true)``; the empirical covariance is taken
about zero. Run 0 of the Monte Carlo is the one whose Marginals / Q_tq are shown.

Part 2, a real frame pair of a TUM sequence (default: the 40-frame sample shipped in ``data/``):

* *parametric resampling*: the matched keypoints' undistorted pixels and depths are re-drawn
  around their measured values with the noise model (pixel sigma, Kinect depth sigma(z, theta)),
  back-projected, given covariances at the re-drawn values, and ``T_0,1`` re-estimated; the
  covariance of the re-estimates (about their mean) is what the noise model implies;
* *pair bootstrap*: the matched pairs are resampled with replacement and ``T_0,1`` re-estimated;
  this uses the real residual scatter, so it exposes a noise model that is too optimistic or too
  pessimistic for the data;
* the reduced chi-square ``2 * final_error / (3N - 6)`` of the fit (1 when the point
  covariances match the residual scatter) and, with ground truth, the error of this one pair.

Both the bootstrap and the chi-square only see the pairs the rigid RANSAC kept (a Mahalanobis
gate at the chi2(3) 99 % quantile), so they are slightly biased low; and neither can see errors
shared by all points of a frame (depth calibration, colour/depth time offset, rolling shutter),
which do not average out over the pairs but also do not show up as residual scatter.

Conventions: GTSAM tangent ``[rx ry rz tx ty tz]`` (rotation first, rad and m), right
perturbation ``T_true = T_est * Exp(xi)``. The thesis's ``(t, q_v)``: translation of ``T_0,1``
(m) and the vector part of its unit quaternion (``qw >= 0``). ``q_v = sin(theta/2) axis`` is a
*half-angle* quantity: to first order ``d q_v = 1/2 (qw I + [q_v]x) d omega``, so sigma(q_v) is
about half of sigma(rotation) in radians. The table shows rotations in mrad, q_v in 1e-3 and
translations in mm.

The last printed line is a JSON object of the key numbers.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import gtsam
import numpy as np

from covo_gtsam.covariance import tangent_to_tq, tq_to_tangent
from covo_gtsam.errors import CovoError
from covo_gtsam.estimator import RelativePoseResult, estimate_relative_pose
from covo_gtsam.geometry import invert_pose, matrix_to_quat
from covo_gtsam.simulation import SimulationConfig, make_scene, noisy_measurements, run_simulation
from covo_gtsam.transfer import whitened_system, whitening

DEFAULT_SEQ = Path(__file__).resolve().parents[1] / "data" / "rgbd_dataset_freiburg1_rpy_head40"
AXES = ["rx", "ry", "rz", "tx", "ty", "tz"]
TQ_AXES = ["tx", "ty", "tz", "qx", "qy", "qz"]
#: Display units: mrad for rotations, mm for translations (tangent); mm and 1e-3 for (t, q_v).
UNIT = np.array([1e3] * 6)
CONVENTIONS = """\
Conventions: GTSAM tangent xi = [rx ry rz tx ty tz] (rad, m), right perturbation T_true = T_est * Exp(xi);
  errors xi = Log(T_est^-1 T_true). Thesis (t, q_v): translation (m) and quaternion vector part (qw >= 0),
  a half-angle quantity: d q_v = 1/2 (qw I + [q_v]x) d omega, so sigma(q_v) ~ sigma(rot)/2.
  Units below: rotation mrad, translation mm, q_v 1e-3."""


# ------------------------------------------------------------------------------------------------
# the thesis's Q_tq by independent first-order propagation
# ------------------------------------------------------------------------------------------------
def pose_from_tq(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation and translation of the thesis's parameters ``p = (t, q_v)``, ``qw = sqrt(1 - |q_v|^2)``."""
    t, qv = p[:3], p[3:]
    qw = np.sqrt(max(1.0 - qv @ qv, 0.0))
    x, y, z = qv
    R = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * qw), 2 * (x * z + y * qw)],
        [2 * (x * y + z * qw), 1 - 2 * (x * x + z * z), 2 * (y * z - x * qw)],
        [2 * (x * z - y * qw), 2 * (y * z + x * qw), 1 - 2 * (x * x + y * y)],
    ])
    return R, t


def propagated_q_tq(res: RelativePoseResult, X_k: np.ndarray, X_k1: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """``Q_tq = phi (J_tq^T J_tq)^-1``: the point covariances (as the residual weights ``C_b, C_f``
    the estimator used) propagated through the whitened residuals' Jacobian w.r.t. ``(t, q_v)``."""
    C_b, C_f = res.residual_covariances
    W_b, W_f = whitening(C_b), whitening(C_f)
    M = res.pose.matrix()
    p0 = np.concatenate([M[:3, 3], matrix_to_quat(M[:3, :3])[:3]])

    def e(p):
        R, t = pose_from_tq(p)
        return whitened_system(R, t, X_k, X_k1, W_b, W_f)[0]

    J = np.empty((6 * X_k.shape[0], 6))
    for j in range(6):
        d = np.zeros(6)
        d[j] = h
        J[:, j] = (e(p0 + d) - e(p0 - d)) / (2 * h)
    Q = res.scale * np.linalg.inv(J.T @ J)
    return 0.5 * (Q + Q.T)


def rel_diff(A: np.ndarray, B: np.ndarray) -> float:
    """Largest entry-wise difference relative to the diagonal scale: max |A-B|_ij / sqrt(B_ii B_jj)."""
    d = np.sqrt(np.diag(B))
    return float(np.max(np.abs(A - B) / np.outer(d, d)))


def whitened_eigs(emp: np.ndarray, pred: np.ndarray) -> np.ndarray:
    """Eigenvalues of ``pred^-1/2 emp pred^-T/2``: all 1 when the two covariances agree."""
    Li = np.linalg.inv(np.linalg.cholesky(pred))
    return np.linalg.eigvalsh(Li @ emp @ Li.T)


def sig(C: np.ndarray) -> np.ndarray:
    return np.sqrt(np.diag(C)) * UNIT


def print_table(title: str, columns: dict[str, np.ndarray], axes=AXES, ratio: tuple[str, str] | None = None) -> None:
    names = list(columns)
    print(f"\n{title}" + (f" (ratio = {ratio[0]} / {ratio[1]})" if ratio else ""))
    head = f"  {'axis':<5}" + "".join(f"{n:>20}" for n in names)
    if ratio:
        head += f"{'ratio':>10}"
    print(head)
    for k, ax in enumerate(axes):
        unit = "mrad" if ax.startswith("r") else ("mm" if ax.startswith("t") else "1e-3")
        row = f"  {ax:<2} {unit:<4}" + "".join(f"{columns[n][k]:>20.4f}" for n in names)
        if ratio:
            row += f"{columns[ratio[0]][k] / columns[ratio[1]][k]:>10.3f}"
        print(row)


# ------------------------------------------------------------------------------------------------
# part 1: simulation
# ------------------------------------------------------------------------------------------------
def simulation_part(runs: int, seed: int) -> dict:
    out = {}
    for label, weighting, scale in (("consistent", "consistent", 1.0), ("thesis", "thesis", 1.0),
                                    ("thesis_phi16", "thesis", 16.0)):
        cfg = SimulationConfig(runs=runs, seed=seed, weighting=weighting, scale=scale)
        sim = run_simulation(cfg)
        # Run 0 again, with its inputs (same generator sequence as run_simulation).
        rng = np.random.default_rng(seed)
        scene = make_scene(cfg, rng)
        model = cfg_noise_model(cfg)
        X0, Q0 = noisy_measurements(scene.X0, scene.camera, model, rng)
        X1, Q1 = noisy_measurements(scene.X1, scene.camera, model, rng)
        res = estimate_relative_pose(X0, X1, Q0, Q1, weighting=weighting, scale=scale)
        assert np.allclose(res.covariance, sim.covariances[0], rtol=1e-6, atol=0), "run 0 not reproduced"
        Q_tq = propagated_q_tq(res, X0, X1)
        from_tq = tq_to_tangent(Q_tq, res.pose)
        emp = sim.empirical_covariance()
        pred = sim.mean_predicted_covariance()
        T_true = gtsam.Pose3(scene.T01)
        print(f"\n=== simulation, {weighting} weighting, phi = {scale:g}: {runs} runs, {cfg.num_points} points, "
              f"{cfg.pixel_sigma:g} px ===")
        print_table(
            "GTSAM tangent, standard deviations:",
            {"Marginals (run 0)": sig(res.covariance), "Q_tq->tangent": sig(from_tq),
             "mean Marginals": sig(pred), "MC empirical": sig(emp)},
            ratio=("MC empirical", "mean Marginals"),
        )
        print_table(
            "thesis (t, q_v), standard deviations:",
            {"Q_tq (4.20) run 0": sig(Q_tq), "covariance_tq": sig(res.covariance_tq),
             "MC emp. G S G^T": sig(tangent_to_tq(emp, T_true))},
            axes=TQ_AXES,
        )
        eig = whitened_eigs(emp, pred)
        d_tq = rel_diff(from_tq, res.covariance)
        d_tq2 = rel_diff(res.covariance_tq, Q_tq)
        print(f"  Q_tq->tangent vs Marginals: max relative difference {d_tq:.1e}; covariance_tq vs Q_tq: {d_tq2:.1e}")
        print(f"  ANEES translation {sim.anees_translation:.2f}, rotation {sim.anees_rotation:.2f} (consistent: 3); "
              f"eigenvalues of mean-Marginals-whitened empirical covariance {eig.min():.2f} .. {eig.max():.2f} "
              f"(consistent: 1)")
        out[label] = {
            "anees_translation": sim.anees_translation,
            "anees_rotation": sim.anees_rotation,
            "whitened_eig_min": float(eig.min()),
            "whitened_eig_max": float(eig.max()),
            "qtq_vs_marginals_rel_diff": d_tq,
            "covariance_tq_vs_qtq_rel_diff": d_tq2,
        }
    return out


def cfg_noise_model(cfg: SimulationConfig):
    from covo_gtsam.noise import PixelNoise, PointNoiseModel

    return PointNoiseModel(pixel=PixelNoise(cfg.pixel_sigma, cfg.pixel_sigma), depth=cfg.depth_model)


# ------------------------------------------------------------------------------------------------
# part 2: a real frame pair
# ------------------------------------------------------------------------------------------------
def real_part(seq_dir: Path, pair: int, gap: int, runs: int, seed: int) -> dict:
    from covo_gtsam.datasets.tum import TumSequence
    from covo_gtsam.frontend import associate_frames
    from covo_gtsam.odometry import OdometryConfig, VisualOdometry

    seq = TumSequence(seq_dir)
    j = pair + gap
    if j >= len(seq):
        raise CovoError(f"{seq_dir}: frame {j} does not exist ({len(seq)} frames)")
    config = OdometryConfig()
    vo = VisualOdometry(seq.camera, config)
    frames = [vo.prepare(*seq.load(i, depth_scale=config.sensor.depth_scale)) for i in (pair, j)]
    pairs = associate_frames(frames[0], frames[1], config.frontend)
    n = len(pairs)
    if n < config.frontend.min_pairs:
        raise CovoError(f"frames {pair} and {j}: only {n} point pairs")
    model = config.noise_model()
    cam = seq.camera
    meas = []
    for f, idx in ((frames[0], pairs.idx_ref), (frames[1], pairs.idx_cur)):
        theta = f.theta[idx] if config.noise.use_surface_angle else np.zeros(n)
        meas.append((f.uv_undistorted[idx], f.depths[idx], theta))
    init = None if pairs.T_init is None else gtsam.Pose3(pairs.T_init)
    gt = None
    if getattr(seq, "groundtruth", None) is not None and seq.gt_valid[pair] and seq.gt_valid[j]:
        gt = gtsam.Pose3(invert_pose(seq.groundtruth[pair]) @ seq.groundtruth[j])

    out = {"pair": [pair, j], "num_pairs": n}
    for weighting in ("consistent", "thesis"):
        res = estimate_relative_pose(pairs.X_ref, pairs.X_cur, pairs.Q_ref, pairs.Q_cur, weighting=weighting,
                                     initial=init)
        Q_tq = propagated_q_tq(res, pairs.X_ref, pairs.X_cur)
        rng = np.random.default_rng(seed)
        para, boot = [], []
        failed = 0
        for _ in range(runs):
            Xs, Qs = [], []
            for uv, z, theta in meas:
                uv_n = uv + rng.standard_normal((n, 2)) * [model.pixel.sigma_u, model.pixel.sigma_v]
                z_n = z + rng.standard_normal(n) * model.depth.sigma(z, theta)
                z_n = np.maximum(z_n, 0.05)
                Xs.append(cam.backproject(uv_n, z_n))
                Qs.append(model.point_covariances(cam, uv_n, z_n, theta))
            try:
                r = estimate_relative_pose(Xs[0], Xs[1], Qs[0], Qs[1], weighting=weighting, initial=res.pose)
                para.append(gtsam.Pose3.Logmap(r.pose.between(res.pose)))
            except CovoError:
                failed += 1
            k = rng.integers(0, n, n)
            try:
                r = estimate_relative_pose(pairs.X_ref[k], pairs.X_cur[k], pairs.Q_ref[k], pairs.Q_cur[k],
                                           weighting=weighting, initial=res.pose)
                boot.append(gtsam.Pose3.Logmap(r.pose.between(res.pose)))
            except CovoError:
                failed += 1
        para, boot = np.array(para), np.array(boot)
        C_para = np.cov(para.T)
        C_boot = np.cov(boot.T)
        red_chi2 = 2 * res.final_error / (3 * n - 6)
        print(f"\n=== real pair: {seq_dir.name} frames {pair} -> {j}, {n} point pairs, {weighting} weighting, "
              f"{runs} re-estimates each ({failed} failed) ===")
        print_table(
            "GTSAM tangent, standard deviations:",
            {"Marginals": sig(res.covariance), "Q_tq->tangent": sig(tq_to_tangent(Q_tq, res.pose)),
             "MC param. resample": sig(C_para), "pair bootstrap": sig(C_boot)},
            ratio=("pair bootstrap", "Marginals"),
        )
        eig_p = whitened_eigs(C_para, res.covariance)
        eig_b = whitened_eigs(C_boot, res.covariance)
        print(f"  Q_tq->tangent vs Marginals: max relative difference "
              f"{rel_diff(tq_to_tangent(Q_tq, res.pose), res.covariance):.1e}")
        print(f"  Marginals-whitened eigenvalues: parametric {eig_p.min():.2f} .. {eig_p.max():.2f}, "
              f"bootstrap {eig_b.min():.2f} .. {eig_b.max():.2f} (agreement: 1)")
        print(f"  reduced chi-square of the fit 2*error/(3N-6) = {red_chi2:.3f} (1 = point covariances match the "
              f"residual scatter)")
        w = {
            "reduced_chi2": float(red_chi2),
            "param_whitened_eig_min": float(eig_p.min()), "param_whitened_eig_max": float(eig_p.max()),
            "boot_whitened_eig_min": float(eig_b.min()), "boot_whitened_eig_max": float(eig_b.max()),
            "sigma_marginals": dict(zip(AXES, (np.sqrt(np.diag(res.covariance))).tolist())),
            "sigma_param": dict(zip(AXES, (np.sqrt(np.diag(C_para))).tolist())),
            "sigma_boot": dict(zip(AXES, (np.sqrt(np.diag(C_boot))).tolist())),
            "failed": failed,
        }
        if gt is not None:
            xi = gtsam.Pose3.Logmap(res.pose.between(gt))
            C = res.covariance
            nees_r = float(xi[:3] @ np.linalg.solve(C[:3, :3], xi[:3]))
            nees_t = float(xi[3:] @ np.linalg.solve(C[3:, 3:], xi[3:]))
            print(f"  error against ground truth: rotation {np.linalg.norm(xi[:3]) * 1e3:.2f} mrad "
                  f"(NEES {nees_r:.2f}), translation {np.linalg.norm(xi[3:]) * 1e3:.2f} mm (NEES {nees_t:.2f}); "
                  f"one pair, chi2(3): 95 % below 7.8")
            w |= {"gt_nees_rotation": nees_r, "gt_nees_translation": nees_t}
        out[weighting] = w
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", type=int, default=1000, metavar="N", help="Monte Carlo runs / re-estimates (default 1000)")
    p.add_argument("--seq", default=str(DEFAULT_SEQ), metavar="SEQ_DIR",
                   help="TUM sequence for the real frame pair (default: the sample in data/); 'none' to skip")
    p.add_argument("--pair", type=int, default=0, metavar="I", help="first frame of the real pair (default 0)")
    p.add_argument("--gap", type=int, default=1, metavar="G", help="second frame = I + G (default 1)")
    p.add_argument("--seed", type=int, default=0, metavar="S", help="random seed (default 0)")
    p.add_argument("--out", metavar="DIR", help="also write the summary to DIR/compare_covariances.json")
    args = p.parse_args(argv)
    if args.runs < 10 or args.gap < 1 or args.pair < 0:
        print("error: --runs >= 10, --gap >= 1 and --pair >= 0 are required", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    print(CONVENTIONS)
    summary: dict = {"runs": args.runs, "seed": args.seed}
    try:
        summary["simulation"] = simulation_part(args.runs, args.seed)
        if args.seq.lower() != "none":
            summary["real"] = real_part(Path(args.seq), args.pair, args.gap, args.runs, args.seed)
    except CovoError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    summary["elapsed_s"] = time.perf_counter() - t0
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "compare_covariances.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
