"""Are a run's edge informations and marginals consistent with ground truth? (NEES per edge kind)

Two checks of the noise models of a finished round (``round_<r>/marginals.npz``, which holds
every edge's measurement ``edge_T``, kind and information, the optimised poses, the marginal
position covariances and the re-anchored ground truth):

- **edge NEES**: for each edge ``(k, l)`` with measurement ``T̂_kl`` and information
  ``Lambda`` (the one given to the graph, before its factors raise eigenvalues under
  ``graph.min_information_eigenvalue``, 1e-2: along an unconstrained axis the NEES is lower than
  the factor's), the ground-truth relative pose
  ``T_kl = G_l^-1 G_k`` gives the error ``xi = Log(T̂_kl^-1 T_kl)`` ([omega, v], right
  perturbation, as gtsam's ``BetweenFactorPose3``) and ``NEES = xi^T Lambda xi``. If
  ``Lambda^-1`` is the covariance of the measurement error, NEES ~ chi2(6): mean 6. Reported
  per kind (odometry, loop) over edges whose registration was not flagged, with a breakdown per
  axis (:func:`axis_stats`: error mean and RMS, ``xi_a^2 / Sigma_aa``) that shows which axis
  is over-confident or biased, and the odometry's path length against ground truth
  (:func:`path_error_percent`, a scale error);
- **position NEES of the marginals**: ``e = p_k - p_k^GT`` (world = first scan, both
  anchored there) and ``NEES = e^T Sigma_k^-1 e`` with the world-frame position marginal
  ``Sigma_k`` (``position_cov_world``): mean 3 if consistent (the first pose, fixed by the
  prior, is left out, and so are poses whose marginals failed or whose graph component was
  marginalised anchored on its own first pose: :func:`poses_without_world_marginals`). The same
  definition as the notebook ``marginal_covariances.ipynb``.
  Split into horizontal (ideal 2) and vertical (ideal 1) parts (:func:`position_nees_split`);
- **chain NEES of the odometry** (:func:`chain_nees`, chains of 10 and 100 consecutive edges):
  the error of the relative pose a chain adds up to, against the covariance the graph's
  independent edges give it (their informations floored as the run's graph did:
  :func:`run_min_eigenvalue`). The positions accumulate chains, so where the per-edge NEES is
  right and the chains' is not (errors that cancel or persist from one edge to the next), the
  marginals' positions are off in the same direction.

A mean NEES far above the ideal means over-confident information, far below conservative.
Ground truth is only read here; nothing in SLAM uses it.

Command line (prints a table, ``--json`` writes the figures)::

    python -m gr_graph.noise_consistency RUN_DIR [--round R] [--json FILE] [--draws N [--draws-seed S]]

``--draws``: :func:`position_nees_draws`, the spread of one run's mean position NEES under an
exact noise model (Monte Carlo), which says how far an observed figure may stray by chance.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import gtsam
import numpy as np

from gr_graph.atomic import read_json_or_none
from gr_graph.config import GraphConfig

__all__ = ["edge_nees", "gt_relative_poses", "edge_errors", "axis_stats", "path_error_percent", "AXES",
           "position_nees", "position_nees_split", "odometry_chains", "chain_nees", "chain_nees_of",
           "CHAIN_LENGTHS", "MIN_EIGENVALUE", "POSITION_BAND", "position_nees_draws", "run_min_eigenvalue",
           "poses_without_world_marginals", "round_noise_consistency", "run_noise_consistency", "main"]

EDGE_KINDS = {0: "odometry", 1: "loop"}


def edge_nees(edges: np.ndarray, edge_T: np.ndarray, information: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """``(E,)`` NEES ``xi^T Lambda xi`` of each edge's measurement against ground truth.

    Parameters
    ----------
    edges : (E, 2) int array
        ``(k, l)`` run positions of each edge.
    edge_T : (E, 4, 4) array
        Measurements ``T̂_kl`` (scan k into the frame of scan l).
    information : (E, 6, 6) array
        Information of each edge, gtsam order ``[omega, v]``.
    gt : (K, 4, 4) array
        Ground-truth poses (any common world frame).
    """
    return _nees(edge_errors(edge_T, gt_relative_poses(edges, gt)), _symmetric(information))


def _symmetric(information: np.ndarray) -> np.ndarray:
    return 0.5 * (information + np.transpose(information, (0, 2, 1)))


def _nees(xi: np.ndarray, information: np.ndarray) -> np.ndarray:
    return np.einsum("ei,eij,ej->e", xi, information, xi)


def gt_relative_poses(edges: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """``(E, 4, 4)`` ground-truth relative poses ``T_kl = G_l^-1 G_k`` of the edges ``(k, l)``
    (arguments as :func:`edge_nees`)."""
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    gt = np.asarray(gt, np.float64)
    return np.linalg.inv(gt[edges[:, 1]]) @ gt[edges[:, 0]]


def edge_errors(edge_T: np.ndarray, T_gt: np.ndarray) -> np.ndarray:
    """``(E, 6)`` errors ``xi = Log(T̂_kl^-1 T_kl)`` ([omega, v], gtsam order) of each edge's
    measurement ``edge_T`` against its ground-truth relative pose (:func:`gt_relative_poses`)."""
    out = np.empty((len(T_gt), 6))
    for i, (T, T_ref) in enumerate(zip(edge_T, T_gt)):
        out[i] = gtsam.Pose3.Logmap(gtsam.Pose3(np.asarray(T, np.float64)).between(gtsam.Pose3(T_ref)))
    return out


def path_error_percent(edge_T: np.ndarray, T_gt: np.ndarray) -> float | None:
    """``100 (sum |t̂_kl| / sum |t_kl| - 1)``: the length of the path the measurements ``edge_T``
    add up to against their ground truth ``T_gt`` (:func:`gt_relative_poses`); negative: motion
    under-estimated, e.g. a scan pattern that moves with the sensor holding registrations back.
    None without edges or motion. :func:`round_noise_consistency` uses the odometry edges whose
    registration was not flagged."""
    if len(T_gt) == 0:
        return None
    measured = float(np.linalg.norm(np.asarray(edge_T)[:, :3, 3], axis=1).sum())
    true = float(np.linalg.norm(np.asarray(T_gt)[:, :3, 3], axis=1).sum())
    return None if true <= 0 else 100.0 * (measured / true - 1.0)


AXES = ("rot_x", "rot_y", "rot_z", "x", "y", "z")

#: chain lengths of :func:`chain_nees` in :func:`round_noise_consistency` (odometry edges per chain)
CHAIN_LENGTHS = (10, 100)
#: the pose graph's default eigenvalue floor (``graph.min_information_eigenvalue``), for :func:`chain_nees`
MIN_EIGENVALUE = GraphConfig().min_information_eigenvalue


def odometry_chains(edges: np.ndarray, m: int) -> list[np.ndarray]:
    """Non-overlapping chains of ``m`` consecutive edges: index arrays into ``edges``.

    Edge ``(k, l)`` maps scan ``k`` into the frame of scan ``l``; a chain follows edges whose target is
    the previous edge's source (``(1, 0), (2, 1), ...``), in order of the targets, and breaks where the
    next edge is missing (a flagged registration left out, a skipped frame). The remainder of a
    contiguous run shorter than ``m`` is not used.
    """
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    if m < 1:
        raise ValueError(f"odometry_chains: m must be >= 1, got {m}")
    by_target = {int(t): i for i, (_, t) in enumerate(edges)}
    chains: list[np.ndarray] = []
    current: list[int] = []
    expected_target: int | None = None
    for i in sorted(range(len(edges)), key=lambda j: int(edges[j, 1])):
        target = int(edges[i, 1])
        if target != expected_target or by_target.get(target) != i:
            current = []
        current.append(i)
        expected_target = int(edges[i, 0])
        if len(current) == m:
            chains.append(np.array(current))
            current = []
    return chains


def chain_nees(edges: np.ndarray, edge_T: np.ndarray, information: np.ndarray, gt: np.ndarray,
               m: int, min_eigenvalue: float | None = MIN_EIGENVALUE) -> dict[str, Any]:
    """NEES of the relative poses that chains of ``m`` consecutive edges add up to.

    For a chain of measurements ``T̂_1 ... T̂_m`` (scan ``a + m`` into the frame of scan ``a``)
    the error is ``xi = Log((T̂_1 ... T̂_m)^-1 T_GT)`` (as :func:`edge_errors`) and its covariance,
    if the edges' errors are independent with covariances ``Lambda_i^-1``, is
    ``sum_i A_i Lambda_i^-1 A_i^T`` with ``A_i = Ad((T̂_{i+1} ... T̂_m)^-1)`` (first order; each
    edge's right perturbation carried into the chain's last frame), the informations floored as
    the pose graph floors them (``min_eigenvalue``, ``graph.min_information_eigenvalue``; the
    per-edge NEES uses them unfloored, the same wherever no eigenvalue is below the floor). This
    is the independence the pose graph assumes: mean NEES 6 over chains when it holds, whatever
    ``m``. Edges whose errors are correlated along the chain show here and not in the per-edge
    NEES: errors that
    partly cancel from one edge to the next (a scan's own error enters the edges on both of its
    sides with opposite signs) give chain NEES below the per-edge one, so the marginals' positions,
    which accumulate the chain, turn conservative; errors that persist (a bias) give it above.

    Returns
    -------
    dict
        ``m``, ``n`` chains, ``mean`` and ``median`` NEES (ideal 6), ``z2_mean`` per axis of the
        chain's error (ideal 1), and ``edge_z2_mean``: the per-axis ``z²`` of the same edges one by
        one, to set beside it.
    """
    return chain_nees_of(odometry_chains(edges, m), edge_T, information, gt_relative_poses(edges, gt), m,
                         min_eigenvalue)


def chain_nees_of(chains: list[np.ndarray], edge_T: np.ndarray, information: np.ndarray, T_gt: np.ndarray,
                  m: int, min_eigenvalue: float | None = MIN_EIGENVALUE) -> dict[str, Any]:
    """:func:`chain_nees` of given chains (index arrays into the edges, each in the order of composition)
    with the edges' ground-truth relative poses ``T_gt`` (:func:`gt_relative_poses`): e.g. the same edges
    chained in a random order, which keeps their covariances and removes any correlation between neighbours."""
    from factors.noise import floored_information

    out: dict[str, Any] = {"m": int(m), "n": len(chains), "mean": None, "median": None, "z2_mean": None,
                           "edge_z2_mean": None}
    if not chains:
        return out
    edge_T = np.asarray(edge_T, np.float64)
    used = np.unique(np.concatenate(chains))
    cov = {int(i): np.linalg.inv(floored_information(information[i], min_eigenvalue=min_eigenvalue)[0])
           for i in used}
    nees, z2, edge_z2 = [], [], []
    for chain in chains:
        measured = gtsam.Pose3()
        chain_cov = np.zeros((6, 6))
        for i in chain:  # the chain so far carried into the new last frame, plus the new edge's own
            step = gtsam.Pose3(edge_T[i])
            A = step.inverse().AdjointMap()
            chain_cov = A @ chain_cov @ A.T + cov[int(i)]
            measured = measured.compose(step)
        true = np.linalg.multi_dot([T_gt[i] for i in chain]) if len(chain) > 1 else T_gt[chain[0]]
        xi = gtsam.Pose3.Logmap(measured.between(gtsam.Pose3(true)))
        nees.append(float(xi @ np.linalg.solve(chain_cov, xi)))
        z2.append(xi**2 / np.diag(chain_cov))
        edge_z2.append(edge_errors(edge_T[chain], T_gt[chain]) ** 2
                       / np.array([np.diag(cov[int(i)]) for i in chain]))
    out.update(mean=float(np.mean(nees)), median=float(np.median(nees)), z2_mean=np.mean(z2, axis=0).tolist(),
               edge_z2_mean=np.concatenate(edge_z2).mean(axis=0).tolist())
    return out


def axis_stats(xi: np.ndarray, information: np.ndarray) -> dict[str, Any]:
    """Per axis of the edge errors ``xi`` ``(E, 6)``: mean (a bias), RMS, and the mean of
    ``xi_a^2 / Sigma_aa`` with ``Sigma = information^-1`` (ideal 1; which axis is over-confident).

    ``xi`` is the right perturbation of :func:`edge_errors`, so each edge's error is expressed
    in the frame of its source scan ``k``; rotations in radians, the translation part is
    Logmap's ``v`` (metres; the translation error itself for small rotations). A singular
    information (stored before the graph's eigenvalue floor) counts as infinite variance along
    its null space (pseudo-inverse; those axes contribute 0)."""
    if len(xi) == 0:
        return {"axes": list(AXES), "error_mean": None, "error_rms": None, "z2_mean": None}
    var = np.diagonal(np.linalg.pinv(information, hermitian=True), axis1=1, axis2=2)
    with np.errstate(divide="ignore", invalid="ignore"):
        z2 = np.where(var > 0, xi**2 / np.where(var > 0, var, 1.0), 0.0)
    return {"axes": list(AXES), "error_mean": xi.mean(0).tolist(), "error_rms": np.sqrt((xi**2).mean(0)).tolist(),
            "z2_mean": z2.mean(0).tolist()}


def position_nees(poses: np.ndarray, position_cov_world: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """``(K - 1,)`` position NEES ``e^T Sigma^-1 e`` of poses 1..K-1 (``e = p - p_GT``, world frame)."""
    e, S = _position_errors(poses, position_cov_world, gt)
    return np.einsum("ki,kij,kj->k", e, np.linalg.inv(S), e)


def _position_errors(poses: np.ndarray, position_cov_world: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Errors ``p - p_GT`` ``(K - 1, 3)`` and covariances ``(K - 1, 3, 3)`` of poses 1..K-1 (the
    first is fixed by the prior), with a tiny diagonal so a degenerate marginal stays invertible."""
    return poses[1:, :3, 3] - gt[1:, :3, 3], position_cov_world[1:] + 1e-12 * np.eye(3)


def position_nees_split(poses: np.ndarray, position_cov_world: np.ndarray, gt: np.ndarray) -> dict[str, Any]:
    """Position NEES of poses 1..K-1 split into horizontal (world x, y: ideal mean 2) and
    vertical (world z: ideal mean 1), with the RMS position error per world axis [m].

    The world is the first scan's frame (z up at the start). A SLAM whose height drifts (e.g.
    a sensor's vertical-angle error bending the trajectory) shows it here, where the 3-D
    position NEES mixes both.
    """
    e, S = _position_errors(poses, position_cov_world, gt)
    horizontal = np.einsum("ki,kij,kj->k", e[:, :2], np.linalg.inv(S[:, :2, :2]), e[:, :2])
    vertical = e[:, 2] ** 2 / S[:, 2, 2]
    return {"horizontal": _stats(horizontal, 2), "vertical": _stats(vertical, 1),
            "error_rms_xyz": np.sqrt(np.mean(e ** 2, axis=0)).tolist() if len(e) else None}


def _stats(x: np.ndarray, dof: int) -> dict[str, Any]:
    from scipy.stats import chi2

    if len(x) == 0:
        return {"n": 0, "mean": None, "median": None, "frac_below_95": None, "ideal_mean": dof}
    return {"n": len(x), "mean": float(np.mean(x)), "median": float(np.median(x)),
            "frac_below_95": float(np.mean(x < chi2.ppf(0.95, dof))), "ideal_mean": dof,
            "ideal_median": float(chi2.median(dof))}


#: band of the issue's target for the mean position NEES (a factor 2 of the ideal 3)
POSITION_BAND = (1.5, 6.0)


def position_nees_draws(round_dir: str | Path, graph_cfg: Any, n_draws: int = 100, seed: int = 0,
                        progress: bool = False) -> dict[str, Any]:
    """How far one run's mean position NEES strays when every edge's information is exactly right.

    The mean over a run's poses is no average of independent figures: neighbouring poses share
    their errors, so one run's mean position NEES scatters widely around 3 even when the noise
    model is exact. Monte Carlo, without ground truth: around the round's own solution (the
    reference), each draw gives every edge the measurement ``T_ref Exp(-xi)``, ``xi`` drawn from
    the covariance the graph gives that edge (its information after the graph's eigenvalue
    floor), solves the graph as the run did (``graph_cfg``: robust loops, the prior on the first
    pose; started from the reference), and scores the solution against the reference with the
    round's own position marginals; the poses :func:`round_noise_consistency` leaves out are left
    out. Where the round has ground truth, its observed mean position NEES is placed among the
    draws (``observed_percentile``: the percentage of draws below it).

    Parameters
    ----------
    round_dir : path
        A finished round (``marginals.npz``; ``round.json`` for the marginals' report).
    graph_cfg : GraphConfig
        The run's ``graph`` section (its ``config.yaml``).
    n_draws : int
        Monte Carlo draws (0.8 s each on the full 4,541-pose route, 0.2 s on 1,500 poses; measured
        on one core of the 2-core Xeon beside another job).
    seed : int
        Of the draws: the result is a function of the round and ``(n_draws, seed)``.
    progress : bool
        A progress bar on stderr.

    Returns
    -------
    dict
        ``n_draws``, ``seed``, per part (``position``, ``horizontal``, ``vertical``) each draw's mean
        NEES (``draws``), their ``mean`` and ``percentiles`` 5 / 50 / 95, and for ``position``
        ``frac_in_band`` (:data:`POSITION_BAND`), ``observed`` and ``observed_percentile`` (None
        without ground truth).
    """
    from factors.noise import floored_information
    from gr_graph.pose_graph import build_pose_graph

    if n_draws < 1:
        raise ValueError(f"position_nees_draws: n_draws must be >= 1, got {n_draws}")
    path = Path(round_dir) / "marginals.npz"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file (not a finished round)")
    with np.load(path) as z:
        missing = [k for k in ("poses", "position_cov_world", "edges", "edge_information", "edge_kind")
                   if k not in z.files]
        if missing:
            raise ValueError(f"{path}: lacks {missing}")
        d = {k: np.array(z[k]) for k in z.files}
    reference = d["poses"]
    edges = np.asarray(d["edges"], np.int64)
    loops = d["edge_kind"] == 1
    T_ref = np.linalg.inv(reference[edges[:, 1]]) @ reference[edges[:, 0]]
    info = np.array([floored_information(H, min_eigenvalue=graph_cfg.min_information_eigenvalue)[0]
                     for H in d["edge_information"]])
    chol = np.linalg.cholesky(np.linalg.inv(info))
    marginals = (read_json_or_none(Path(round_dir) / "round.json") or {}).get("marginals")
    keep = ~poses_without_world_marginals(d["position_cov_world"], marginals)
    keep[0] = True  # _position_errors drops the first pose itself
    if keep.sum() < 2:
        raise ValueError(f"{path}: no pose besides the first has a world-frame position marginal")
    cov = d["position_cov_world"][keep]
    rng = np.random.default_rng(seed)
    draws = np.empty((n_draws, 3))
    bar = range(n_draws)
    if progress:
        from tqdm import tqdm

        bar = tqdm(bar, desc="position NEES draws", unit="draw")
    for j in bar:
        xi = np.einsum("eij,ej->ei", chol, rng.standard_normal((len(edges), 6)))
        graph = build_pose_graph(graph_cfg, reference, ((k, l, T @ gtsam.Pose3.Expmap(-x).matrix(), H, loop) for
                                                        (k, l), T, x, H, loop in zip(edges, T_ref, xi, info, loops,
                                                                                     strict=True)))
        solved = graph.optimize(marginals=False).poses[keep]
        split = position_nees_split(solved, cov, reference[keep])
        draws[j] = (position_nees(solved, cov, reference[keep]).mean(), split["horizontal"]["mean"],
                    split["vertical"]["mean"])
    out: dict[str, Any] = {"n_draws": int(n_draws), "seed": int(seed)}
    for i, part in enumerate(("position", "horizontal", "vertical")):
        out[part] = {"mean": float(draws[:, i].mean()), "percentiles": {str(q): float(np.percentile(draws[:, i], q))
                                                                         for q in (5, 50, 95)},
                     "draws": draws[:, i].tolist()}
    lo, hi = POSITION_BAND
    out["position"]["frac_in_band"] = float(np.mean((draws[:, 0] >= lo) & (draws[:, 0] <= hi)))
    observed = None
    if "gt_poses" in d:
        observed = float(position_nees(d["poses"][keep], cov, d["gt_poses"][keep]).mean())
    out["position"]["observed"] = observed
    out["position"]["observed_percentile"] = (None if observed is None
                                              else float(100.0 * np.mean(draws[:, 0] < observed)))
    return out


def poses_without_world_marginals(covariance_world: np.ndarray, marginals: dict[str, Any] | None) -> np.ndarray:
    """Boolean ``(K,)``: poses whose position covariance cannot be compared with world-frame errors.

    Those are the poses with non-finite covariances (marginals that ``status`` "failed") and the poses of
    graph components gtsam could only marginalise anchored on their own first pose (``marginals``:
    a :class:`gr_graph.pose_graph.MarginalsReport` as a dict; each ``unanchored_components`` entry
    ``[first, last, n]`` leaves out poses first..last).
    """
    out = ~np.isfinite(covariance_world).reshape(len(covariance_world), -1).all(axis=1)
    for first, last, _n in (marginals or {}).get("unanchored_components") or []:
        out[int(first): int(last) + 1] = True
    return out


def run_min_eigenvalue(round_dir: str | Path) -> float:
    """The eigenvalue floor the round's graph used: ``graph.min_information_eigenvalue`` of the run's
    ``config.yaml`` (the folder above ``round_dir``, read with :func:`gr_graph.config.load_config`),
    else :data:`MIN_EIGENVALUE` (no config).

    Raises
    ------
    ValueError
        When the config is not a valid configuration (e.g. a floor that is not a positive number),
        naming the file and the key.
    """
    from gr_graph.config import load_config

    path = Path(round_dir).parent / "config.yaml"
    if not path.is_file():
        return MIN_EIGENVALUE
    return float(load_config(path).graph.min_information_eigenvalue)


def round_noise_consistency(round_dir: str | Path, marginals: dict[str, Any] | None = None,
                            min_eigenvalue: float | None = None) -> dict[str, Any]:
    """Edge NEES per kind and position NEES of the marginals of one finished round.

    ``marginals`` is the round's :class:`gr_graph.pose_graph.MarginalsReport` as a dict (default: read
    from its ``round.json`` when there is one): the position NEES leaves out the poses of
    :func:`poses_without_world_marginals`, counted in ``position["n_left_out"]``. The chains of
    odometry edges floor each edge's information as the round's graph did: at ``min_eigenvalue``
    (default: :func:`run_min_eigenvalue`, the run's ``graph.min_information_eigenvalue``), recorded
    in ``edges["odometry"]["chain_min_eigenvalue"]``.

    Raises
    ------
    FileNotFoundError
        Without ``marginals.npz``.
    ValueError
        When the file lacks ground truth, marginals or the edge measurements (``edge_T``,
        written since this module exists), naming the file.
    """
    path = Path(round_dir) / "marginals.npz"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file (not a finished round)")
    with np.load(path) as z:
        missing = [k for k in ("gt_poses", "edge_T", "covariance", "position_cov_world", "poses", "edges",
                               "edge_information", "edge_kind", "edge_ok") if k not in z.files]
        if missing:
            raise ValueError(f"{path}: lacks {missing} (a run without ground truth or marginals, or written "
                             "before edge_T was stored)")
        d = {k: np.array(z[k]) for k in z.files}
    gt = d["gt_poses"]
    T_gt = gt_relative_poses(d["edges"], gt)
    xi = edge_errors(d["edge_T"], T_gt)
    info = _symmetric(d["edge_information"])
    nees = _nees(xi, info)
    ok = d["edge_ok"].astype(bool)
    out: dict[str, Any] = {"edges": {}}
    for code, kind in EDGE_KINDS.items():
        sel = (d["edge_kind"] == code) & ok
        out["edges"][kind] = {**_stats(nees[sel], 6), "per_axis": axis_stats(xi[sel], info[sel])}
    odometry = (d["edge_kind"] == 0) & ok  # the same edges as the NEES: flagged registrations left out
    out["edges"]["odometry"]["path_error_percent"] = path_error_percent(d["edge_T"][odometry], T_gt[odometry])
    floor = run_min_eigenvalue(round_dir) if min_eigenvalue is None else float(min_eigenvalue)
    out["edges"]["odometry"]["chains"] = {str(m): chain_nees(d["edges"][odometry], d["edge_T"][odometry],
                                                             info[odometry], gt, m, floor) for m in CHAIN_LENGTHS}
    out["edges"]["odometry"]["chain_min_eigenvalue"] = floor
    out["edges"]["n_flagged_left_out"] = int((~ok).sum())
    if marginals is None:
        marginals = (read_json_or_none(Path(round_dir) / "round.json") or {}).get("marginals")
    left_out = poses_without_world_marginals(d["position_cov_world"], marginals)
    left_out[0] = False  # the first pose is never compared (fixed by the prior)
    keep = ~left_out
    poses, cov, gt_kept = d["poses"][keep], d["position_cov_world"][keep], gt[keep]
    out["position"] = _stats(position_nees(poses, cov, gt_kept), 3)
    out["position"].update(position_nees_split(poses, cov, gt_kept))
    out["position"]["n_left_out"] = int(left_out.sum())
    return out


def run_noise_consistency(run_dir: str | Path, rounds: list[int] | None = None) -> dict[str, Any]:
    """:func:`round_noise_consistency` of every finished round of a run (or of ``rounds``)."""
    run = Path(run_dir)
    found = sorted(int(p.name.split("_")[1]) for p in run.glob("round_*") if (p / "marginals.npz").is_file())
    if rounds is not None:
        absent = sorted(set(rounds) - set(found))
        if absent:
            raise FileNotFoundError(f"{run}: rounds {absent} have no marginals.npz")
        found = sorted(rounds)
    if not found:
        raise FileNotFoundError(f"{run}: no finished round (round_<r>/marginals.npz)")
    return {str(r): round_noise_consistency(run / f"round_{r}") for r in found}


def format_table(result: dict[str, Any]) -> str:
    """Markdown table of :func:`run_noise_consistency`'s result."""
    def f(x: float | None) -> str:
        return "-" if x is None else f"{x:.3g}"

    def worst(e: dict[str, Any]) -> str:
        z2 = (e.get("per_axis") or {}).get("z2_mean")
        if not z2:
            return "-"
        a = int(np.argmax(z2))
        return f"{AXES[a]} {z2[a]:.3g}"

    def part(p: dict[str, Any], key: str) -> str:
        return f(((p.get(key) or {}).get("mean")))

    def chains(o: dict[str, Any]) -> str:
        return " / ".join(f((c or {}).get("mean")) for c in (o.get("chains") or {}).values()) or "-"

    lines = ["| round | odometry NEES mean (n) | odometry chains of " + " / ".join(map(str, CHAIN_LENGTHS))
             + ": NEES mean | loop NEES mean (n) | position NEES mean / median "
             "| position NEES horizontal / vertical | odometry / loop: worst axis (z^2) |",
             "|---|---|---|---|---|---|---|"]
    for r, res in result.items():
        o, lp, p = res["edges"]["odometry"], res["edges"]["loop"], res["position"]
        lines.append(f"| {r} | {f(o['mean'])} ({o['n']}) | {chains(o)} | {f(lp['mean'])} ({lp['n']}) | "
                     f"{f(p['mean'])} / {f(p['median'])} | {part(p, 'horizontal')} / {part(p, 'vertical')} | "
                     f"{worst(o)} / {worst(lp)} |")
    lines.append("ideal: edges and chains of edges 6 (chi2(6)), positions 3 (chi2(3)), horizontal 2, vertical 1; "
                 "median of chi2(6) 5.35, of chi2(3) 2.37; z^2 = error^2 / variance of one axis, ideal 1 (the JSON "
                 "has every axis, error mean and RMS, and the position error RMS per world axis)")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m gr_graph.noise_consistency", description=__doc__.split("\n")[0])
    ap.add_argument("run_dir", help="the --out folder of python -m gr_graph.slam")
    ap.add_argument("--round", type=int, action="append", dest="rounds", help="only this round (repeatable)")
    ap.add_argument("--json", type=Path, help="write the figures to this file")
    ap.add_argument("--draws", type=int, default=0, metavar="N",
                    help="also N Monte Carlo draws per round: the spread of the mean position NEES if every edge's "
                         "information were exactly right, and where the observed one falls in it (position_nees_draws)")
    ap.add_argument("--draws-seed", type=int, default=0, help="seed of the draws (default 0)")
    args = ap.parse_args(argv)
    if args.draws < 0:
        ap.error(f"--draws must be >= 0, got {args.draws}")
    try:
        result = run_noise_consistency(args.run_dir, args.rounds)
        if args.draws:
            from gr_graph.config import load_config

            cfg = load_config(Path(args.run_dir) / "config.yaml")
            for r, res in result.items():
                res["position"]["draws"] = position_nees_draws(Path(args.run_dir) / f"round_{r}", cfg.graph,
                                                               args.draws, args.draws_seed, progress=True)
    except (FileNotFoundError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(format_table(result))
    for r, res in result.items():
        draws = res["position"].get("draws")
        if draws:
            p = draws["position"]
            q = p["percentiles"]
            seen = "" if p["observed"] is None else (f"; observed {p['observed']:.3g}, above "
                                                     f"{p['observed_percentile']:.0f} % of the draws")
            print(f"round {r}: mean position NEES if the edges' information were exact ({draws['n_draws']} draws): "
                  f"5 / 50 / 95 % {q['5']:.3g} / {q['50']:.3g} / {q['95']:.3g}, in {POSITION_BAND[0]:g}-"
                  f"{POSITION_BAND[1]:g} in {100 * p['frac_in_band']:.0f} % of the draws{seen}")
    if args.json is not None:
        from gr_graph.atomic import atomic_write_json

        atomic_write_json(args.json, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
