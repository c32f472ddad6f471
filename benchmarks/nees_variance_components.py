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
marginals, horizontal / vertical) and the accuracy of the re-solved poses (ATE RMSE, mean RPE-300
over all pairs). Nothing in SLAM uses ground truth; this only evaluates. ``--loops-only``
estimates the loops' factor alone (the odometry edges keep the run's shared scale).
``--loop-axes`` alternates, for ``--iterations`` passes, the odometry's variance component with
the library's loop stage of ``graph.loop_variance: estimated_axes`` (the loops' common factor, then
their per-axis factors, the odometry held fixed), and prints the NEES after every pass.
``--odometry-of OTHER_ROUND_DIR`` asks which part of a round's graph moved its trajectory: the
round's graph re-solved with the odometry edges' information of another round of the same run
(same odometry measurements; the loops as they are), and with only that round's per-axis shape
(the median ratio of each axis' variance between the rounds, divided by its geometric mean; the
round's own scale kept).

Run::

    python benchmarks/nees_variance_components.py RUN_DIR/round_2 [--iterations 15] [--loops-only | --loop-axes]
    python benchmarks/nees_variance_components.py RUN_DIR/round_1 --odometry-of RUN_DIR/round_0
"""

from __future__ import annotations

import argparse
from pathlib import Path
from types import SimpleNamespace

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from gr_graph.metrics import ate, rpe_translation
from gr_graph.noise_calibration import (
    between_residuals,
    factor_redundancies,
    loop_axis_variance_factors,
    loop_variance_factor,
)
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


def chi2_per_edge(poses: np.ndarray, edges: np.ndarray, edge_T: np.ndarray, info: np.ndarray) -> np.ndarray:
    """``r^T Lambda r`` of every edge, ``r`` the pose graph's own residual (:func:`between_residuals`)."""
    res = between_residuals(poses, [SimpleNamespace(source=int(k), target=int(l), T=T)
                                    for (k, l), T in zip(edges, edge_T)])
    return np.einsum("ei,eij,ej->e", res, 0.5 * (info + np.swapaxes(info, 1, 2)), res)


def odometry_variance(z: dict[str, np.ndarray], info: np.ndarray, poses: np.ndarray,
                      prior_sigma: float) -> tuple[np.ndarray, dict[int, float], dict[int, float]]:
    """Solve the Gaussian graph with ``info`` from ``poses``; the solution, each group's redundancy
    (0: odometry, 1: loops) and its variance factor ``sigma_g^2 = chi2_g / r_g``."""
    edges, kind, edge_T = z["edges"], z["edge_kind"], z["edge_T"]
    graph = gaussian_graph(edges, edge_T, info, z["poses"][0], prior_sigma)
    poses = solve(graph, poses)
    total = 6 * len(edges) + 6 - 6 * len(poses)
    r_loop, r_prior = factor_redundancies(graph, pose_values(poses), [1 + np.flatnonzero(kind == 1), [0]])
    r = {0: total - r_loop - r_prior, 1: r_loop}  # factor 0 is the prior
    chi2 = chi2_per_edge(poses, edges, edge_T, info)
    return poses, r, {g: chi2[kind == g].sum() / r[g] for g in (0, 1)}


def variance_components(z: dict[str, np.ndarray], iterations: int, prior_sigma: float) -> dict:
    """Both groups (odometry, loops) estimated from the residuals, rescaled together until stable."""
    kind = z["edge_kind"]
    info = np.array(z["edge_information"], np.float64)
    poses = np.array(z["poses"])
    scale = {0: 1.0, 1: 1.0}
    for it in range(iterations):
        poses, r, s2 = odometry_variance(z, info, poses, prior_sigma)
        print(f"  iteration {it}: redundancy odometry {r[0]:.1f}, loops {r[1]:.1f}; "
              f"sigma^2 odometry {s2[0]:.4g}, loops {s2[1]:.4g}")
        for g in (0, 1):
            info[kind == g] /= s2[g]
            scale[g] *= s2[g]
        if max(abs(s2[0] - 1.0), abs(s2[1] - 1.0)) < 1e-3:
            break
    return _solved(z, info, poses, prior_sigma, {"variance": scale})


def _library_solver(z: dict[str, np.ndarray], prior_sigma: float, poses: np.ndarray):
    """``solve(informations) -> (graph, values)`` as the library's loop variance functions take it
    (each call solved from the previous solution, kept in ``latest[0]``), and ``latest``."""
    latest = [np.array(poses)]

    def solve_with(informations: list[np.ndarray]) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
        graph = gaussian_graph(z["edges"], z["edge_T"], np.array(informations), z["poses"][0], prior_sigma)
        latest[0] = solve(graph, latest[0])
        return graph, pose_values(latest[0])

    return solve_with, latest


def odometry_then_loop_axes(z: dict[str, np.ndarray], passes: int, prior_sigma: float) -> dict:
    """``passes`` times: the odometry edges divided by their variance factor, then the loops' common
    and per-axis factors with the odometry held fixed (the library's ``estimated_axes`` stage);
    the NEES row after every pass is printed."""
    kind = z["edge_kind"]
    info = np.array(z["edge_information"], np.float64)
    poses = np.array(z["poses"])
    res = None
    for it in range(passes):
        poses, r, s2 = odometry_variance(z, info, poses, prior_sigma)
        info[kind == 0] /= s2[0]
        edges = [SimpleNamespace(kind="loop" if k == 1 else "odometry", information=H) for k, H in zip(kind, info)]
        solve_with, latest = _library_solver(z, prior_sigma, poses)
        common = loop_variance_factor(solve_with, edges)
        for e in edges:
            if e.kind == "loop":
                e.information = common.scaled_information(e.information)
        axes = loop_axis_variance_factors(solve_with, edges)
        info = np.stack([axes.scaled_information(e.information) if e.kind == "loop" else e.information for e in edges])
        res = _solved(z, info, latest[0], prior_sigma, {"variance": {0: s2[0], 1: s2[1]}})
        poses = res["poses"]
        print(nees_row(f"pass {it + 1}: odometry sigma^2 {s2[0]:.3g} (redundancy {r[0]:.1f}), loops sigma^2 "
                       f"{s2[1]:.3g} ({r[1]:.1f}); loops x {common.scale:.3g}, per axis "
                       f"{' / '.join(f'{a:.2g}' for a in axes.axis_scale)}", z, poses,
                       position_covariance_world(poses, res["covariance"]), info), flush=True)
    return res


def loop_variance_only(z: dict[str, np.ndarray], iterations: int, prior_sigma: float) -> dict:
    """The library's loop variance component (:func:`gr_graph.noise_calibration.loop_variance_factor`)
    on the stored graph: loops rescaled, odometry held fixed."""
    kind = z["edge_kind"]
    edges = [SimpleNamespace(kind="loop" if k == 1 else "odometry", information=H)
             for k, H in zip(kind, z["edge_information"])]
    solve_with, latest = _library_solver(z, prior_sigma, z["poses"])
    lv = loop_variance_factor(solve_with, edges, max_iterations=iterations)
    print(f"  loop variance: sigma_L^2 {[round(v, 4) for v in lv.sigma_sq]}, redundancy {lv.redundancy}, "
          f"scale {lv.scale:.4g} ({lv.reason or 'estimated'})")
    info = np.array(z["edge_information"], np.float64)
    info[kind == 1] *= lv.scale
    return _solved(z, info, latest[0], prior_sigma, {"variance": {0: 1.0, 1: 1.0 / lv.scale}})


def _solved(z: dict[str, np.ndarray], info: np.ndarray, poses: np.ndarray, prior_sigma: float,
            extra: dict) -> dict:
    """Solve the graph with ``info`` from ``poses``; poses, marginal covariances, information."""
    graph = gaussian_graph(z["edges"], z["edge_T"], info, z["poses"][0], prior_sigma)
    poses = solve(graph, poses)
    marginals = gtsam.Marginals(graph, pose_values(poses))
    cov = np.stack([marginals.marginalCovariance(X(i)) for i in range(len(poses))])
    return {"poses": poses, "covariance": cov, "information": info, **extra}


def odometry_swapped(z: dict[str, np.ndarray], other: dict[str, np.ndarray],
                     prior_sigma: float) -> list[tuple[str, dict]]:
    """``z``'s graph re-solved with ``other``'s odometry information, then with only its per-axis shape."""
    odo, odo_other = z["edge_kind"] == 0, other["edge_kind"] == 0
    if not np.array_equal(z["edges"][odo], other["edges"][odo_other]) or not np.allclose(
            z["edge_T"][odo], other["edge_T"][odo_other]):
        raise SystemExit("--odometry-of: the two rounds' odometry edges differ (not rounds of one run on raw scans?)")
    own, theirs = z["edge_information"][odo], other["edge_information"][odo_other]
    ratio = np.median(np.einsum("eii->ei", np.linalg.inv(own)) / np.einsum("eii->ei", np.linalg.inv(theirs)), axis=0)
    root = np.sqrt(ratio / np.exp(np.mean(np.log(ratio))))
    out = []
    for tag, odometry_info in (("odometry information of the other round", theirs),
                               ("odometry per-axis shape of the other round (own scale; axis factors "
                                + " / ".join(f"{v:.2g}" for v in root ** 2) + ")",
                                root[None, :, None] * own * root[None, None, :])):
        info = np.array(z["edge_information"])
        info[odo] = odometry_info
        out.append((tag, _solved(z, info, z["poses"], prior_sigma, {})))
    return out


def nees_row(tag: str, z: dict[str, np.ndarray], poses: np.ndarray, cov_world: np.ndarray, info: np.ndarray) -> str:
    kind, ok, gt = z["edge_kind"], z["edge_ok"].astype(bool), z["gt_poses"]
    ne = edge_nees(z["edges"], z["edge_T"], info, gt)
    pos = position_nees(poses, cov_world, gt)
    split = position_nees_split(poses, cov_world, gt)
    if len(poses) > 300:
        rpe = f"{rpe_translation(poses, gt, delta=300, all_pairs=True).mean:.3f}"
    else:
        rpe = "n/a"
    return (f"| {tag} | {ne[(kind == 0) & ok].mean():.3g} | {ne[(kind == 1) & ok].mean():.3g} ({int((kind == 1).sum())}) "
            f"| {pos.mean():.3g} | {split['horizontal']['mean']:.3g} / {split['vertical']['mean']:.3g} "
            f"| {ate(poses, gt, align=True).rmse:.3f} | {rpe} |")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("round_dir", type=Path)
    ap.add_argument("--iterations", type=int, default=15)
    ap.add_argument("--prior-sigma", type=float, default=1e-4, help="graph.prior_sigma of the run")
    mode = ap.add_mutually_exclusive_group()
    mode.add_argument("--loops-only", action="store_true",
                      help="estimate the loops' variance factor only; the odometry edges keep the run's scale")
    mode.add_argument("--loop-axes", action="store_true",
                      help="alternate the odometry's variance factor with the loops' common and per-axis factors, "
                           "--iterations passes, the NEES printed after each")
    mode.add_argument("--odometry-of", type=Path, metavar="OTHER_ROUND_DIR",
                      help="re-solve with the odometry edges' information of another round of the same run, "
                           "then with only its per-axis shape")
    args = ap.parse_args(argv)
    with np.load(args.round_dir / "marginals.npz") as f:
        z = {k: np.array(f[k]) for k in f.files}
    if not (z["edge_kind"] == 1).any():
        print(f"{args.round_dir}: no loop edges, nothing to estimate")
        return 2
    header = ("| graph | odometry NEES | loop NEES (n) | position NEES | horizontal / vertical | ATE RMSE [m] "
              "| RPE-300 all pairs [m] |\n|---|---|---|---|---|---|---|")
    as_run = nees_row("as run (one shared scale)", z, z["poses"], z["position_cov_world"], z["edge_information"])
    if args.odometry_of:
        with np.load(args.odometry_of / "marginals.npz") as f:
            other = {k: np.array(f[k]) for k in f.files}
        print(header + "\n" + nees_row("other round as run", other, other["poses"], other["position_cov_world"],
                                       other["edge_information"]) + "\n" + as_run, flush=True)
        for tag, res in odometry_swapped(z, other, args.prior_sigma):
            print(nees_row(tag, z, res["poses"], position_covariance_world(res["poses"], res["covariance"]),
                           res["information"]), flush=True)
        return 0
    if args.loop_axes:
        print(header + "\n" + as_run, flush=True)
        odometry_then_loop_axes(z, args.iterations, args.prior_sigma)
        return 0
    estimate = loop_variance_only if args.loops_only else variance_components
    res = estimate(z, args.iterations, args.prior_sigma)
    print(header + "\n" + as_run)
    what = "loop variance component" if args.loops_only else "two variance components"
    print(nees_row(f"{what} (x{1 / res['variance'][0]:.3g} odometry, "
                   f"x{1 / res['variance'][1]:.3g} loops)", z, res["poses"],
                   position_covariance_world(res["poses"], res["covariance"]), res["information"]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
