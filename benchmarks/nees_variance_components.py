"""Offline study (not a test): one variance factor per edge kind instead of one shared scale.

The learned edge noise is calibrated by one a-posteriori variance factor for all edges
(:mod:`gr_graph.noise_calibration`). Loop edges stay over-confident on the full route, so the
natural alternative is a variance component estimation (Förstner 1979) with two groups, odometry
and loops, from the graph's residuals alone::

    r_g      = 6 n_g - tr(N^-1 N_g)            redundancy of group g (N: normal matrix at the optimum)
    sigma_g^2 = sum_{e in g} chi2_e / r_g       its variance factor; Lambda_e /= sigma_g^2; repeat

This script applies it to a finished round (``round_<r>/marginals.npz`` holds every edge's
measurement and information and the ground truth), solves the Gaussian graph again, and prints
the NEES against ground truth before and after (edge NEES per kind, position NEES of the new
marginals, horizontal / vertical). Nothing in SLAM uses ground truth; this only evaluates.

Run::

    python benchmarks/nees_variance_components.py RUN_DIR/round_2 [--iterations 15]
"""

from __future__ import annotations

import argparse
from pathlib import Path
from types import SimpleNamespace

import gtsam
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spl
from gtsam.symbol_shorthand import X

from gr_graph.noise_calibration import between_residuals
from gr_graph.noise_consistency import edge_nees, position_nees, position_nees_split
from gr_graph.pose_graph import position_covariance_world


def pose_values(poses: np.ndarray) -> gtsam.Values:
    values = gtsam.Values()
    for i, T in enumerate(poses):
        values.insert(X(i), gtsam.Pose3(T))
    return values


def gaussian_graph(edges: np.ndarray, edge_T: np.ndarray, info: np.ndarray, first_pose: np.ndarray,
                   prior_sigma: float) -> gtsam.NonlinearFactorGraph:
    """The round's graph without robust kernels: prior on pose 0, then one factor per edge in order."""
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(first_pose), gtsam.noiseModel.Isotropic.Sigma(6, prior_sigma)))
    for (k, l), T, L in zip(edges, edge_T, info):
        graph.add(gtsam.BetweenFactorPose3(X(int(l)), X(int(k)), gtsam.Pose3(T),
                                           gtsam.noiseModel.Gaussian.Information(0.5 * (L + L.T))))
    return graph


def solve(graph: gtsam.NonlinearFactorGraph, poses: np.ndarray) -> np.ndarray:
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(100)
    params.setRelativeErrorTol(1e-10)
    result = gtsam.LevenbergMarquardtOptimizer(graph, pose_values(poses), params).optimize()
    return np.stack([result.atPose3(X(i)).matrix() for i in range(len(poses))])


def redundancies(graph: gtsam.NonlinearFactorGraph, poses: np.ndarray, row_groups: list[np.ndarray]) -> list[float]:
    """``len(rows) - tr(N^-1 J_rows^T J_rows)`` of each group of rows, ``J`` the whitened Jacobian
    at ``poses`` and ``N = J^T J`` (linearised and factorised once)."""
    ijs = graph.linearize(pose_values(poses)).sparseJacobian_()  # 1-based (row, column, value); last column = rhs
    r, c, v = ijs[0].astype(int) - 1, ijs[1].astype(int) - 1, ijs[2]
    n = 6 * len(poses)
    keep = c < n
    J = sp.csr_matrix((v[keep], (r[keep], c[keep])), shape=(int(r.max()) + 1, n))
    lu = spl.splu((J.T @ J).tocsc())
    out = []
    for rows in row_groups:
        Jg = J[rows].toarray()
        out.append(float(len(rows) - np.trace(Jg @ lu.solve(Jg.T.copy()))))
    return out


def chi2_per_edge(poses: np.ndarray, edges: np.ndarray, edge_T: np.ndarray, info: np.ndarray) -> np.ndarray:
    """``r^T Lambda r`` of every edge, ``r`` the pose graph's own residual (:func:`between_residuals`)."""
    res = between_residuals(poses, [SimpleNamespace(source=int(k), target=int(l), T=T)
                                    for (k, l), T in zip(edges, edge_T)])
    return np.einsum("ei,eij,ej->e", res, 0.5 * (info + np.swapaxes(info, 1, 2)), res)


def variance_components(z: dict[str, np.ndarray], iterations: int, prior_sigma: float) -> dict:
    edges, kind, edge_T = z["edges"], z["edge_kind"], z["edge_T"]
    info = np.array(z["edge_information"], np.float64)
    poses = np.array(z["poses"])
    scale = {0: 1.0, 1: 1.0}
    K = len(poses)
    loop_rows = np.concatenate([np.arange(6 * (e + 1), 6 * (e + 2)) for e in np.flatnonzero(kind == 1)])
    for it in range(iterations):
        graph = gaussian_graph(edges, edge_T, info, z["poses"][0], prior_sigma)
        poses = solve(graph, poses)
        total = 6 * len(edges) + 6 - 6 * K
        r_loop, r_prior = redundancies(graph, poses, [loop_rows, np.arange(6)])
        r_odo = total - r_loop - r_prior
        chi2 = chi2_per_edge(poses, edges, edge_T, info)
        s2 = {0: chi2[kind == 0].sum() / r_odo, 1: chi2[kind == 1].sum() / r_loop}
        print(f"  iteration {it}: redundancy odometry {r_odo:.1f}, loops {r_loop:.1f}; "
              f"sigma^2 odometry {s2[0]:.4g}, loops {s2[1]:.4g}")
        for g in (0, 1):
            info[kind == g] /= s2[g]
            scale[g] *= s2[g]
        if max(abs(s2[0] - 1.0), abs(s2[1] - 1.0)) < 1e-3:
            break
    graph = gaussian_graph(edges, edge_T, info, z["poses"][0], prior_sigma)
    poses = solve(graph, poses)
    marginals = gtsam.Marginals(graph, pose_values(poses))
    cov = np.stack([marginals.marginalCovariance(X(i)) for i in range(K)])
    return {"poses": poses, "covariance": cov, "information": info, "variance": scale}


def nees_row(tag: str, z: dict[str, np.ndarray], poses: np.ndarray, cov_world: np.ndarray, info: np.ndarray) -> str:
    kind, ok, gt = z["edge_kind"], z["edge_ok"].astype(bool), z["gt_poses"]
    ne = edge_nees(z["edges"], z["edge_T"], info, gt)
    pos = position_nees(poses, cov_world, gt)
    split = position_nees_split(poses, cov_world, gt)
    return (f"| {tag} | {ne[(kind == 0) & ok].mean():.3g} | {ne[(kind == 1) & ok].mean():.3g} ({int((kind == 1).sum())}) "
            f"| {pos.mean():.3g} | {split['horizontal']['mean']:.3g} / {split['vertical']['mean']:.3g} |")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("round_dir", type=Path)
    ap.add_argument("--iterations", type=int, default=15)
    ap.add_argument("--prior-sigma", type=float, default=1e-4, help="graph.prior_sigma of the run")
    args = ap.parse_args(argv)
    with np.load(args.round_dir / "marginals.npz") as f:
        z = {k: np.array(f[k]) for k in f.files}
    if not (z["edge_kind"] == 1).any():
        print(f"{args.round_dir}: no loop edges, nothing to estimate")
        return 2
    res = variance_components(z, args.iterations, args.prior_sigma)
    print("| graph | odometry NEES | loop NEES (n) | position NEES | horizontal / vertical |")
    print("|---|---|---|---|---|")
    print(nees_row("as run (one shared scale)", z, z["poses"], z["position_cov_world"], z["edge_information"]))
    print(nees_row(f"two variance components (x{1 / res['variance'][0]:.3g} odometry, "
                   f"x{1 / res['variance'][1]:.3g} loops)", z, res["poses"],
                   position_covariance_world(res["poses"], res["covariance"]), res["information"]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
