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
  Split into horizontal (ideal 2) and vertical (ideal 1) parts (:func:`position_nees_split`).

A mean NEES far above the ideal means over-confident information, far below conservative.
Ground truth is only read here; nothing in SLAM uses it.

Command line (prints a table, ``--json`` writes the figures)::

    python -m gr_graph.noise_consistency RUN_DIR [--round R] [--json FILE]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import gtsam
import numpy as np

from gr_graph.atomic import read_json_or_none

__all__ = ["edge_nees", "gt_relative_poses", "edge_errors", "axis_stats", "path_error_percent", "AXES",
           "position_nees", "position_nees_split", "poses_without_world_marginals", "round_noise_consistency",
           "run_noise_consistency", "main"]

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


def round_noise_consistency(round_dir: str | Path, marginals: dict[str, Any] | None = None) -> dict[str, Any]:
    """Edge NEES per kind and position NEES of the marginals of one finished round.

    ``marginals`` is the round's :class:`gr_graph.pose_graph.MarginalsReport` as a dict (default: read
    from its ``round.json`` when there is one): the position NEES leaves out the poses of
    :func:`poses_without_world_marginals`, counted in ``position["n_left_out"]``.

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

    lines = ["| round | odometry NEES mean (n) | loop NEES mean (n) | position NEES mean / median "
             "| position NEES horizontal / vertical | odometry / loop: worst axis (z^2) |", "|---|---|---|---|---|---|"]
    for r, res in result.items():
        o, lp, p = res["edges"]["odometry"], res["edges"]["loop"], res["position"]
        lines.append(f"| {r} | {f(o['mean'])} ({o['n']}) | {f(lp['mean'])} ({lp['n']}) | "
                     f"{f(p['mean'])} / {f(p['median'])} | {part(p, 'horizontal')} / {part(p, 'vertical')} | "
                     f"{worst(o)} / {worst(lp)} |")
    lines.append("ideal: edges 6 (chi2(6)), positions 3 (chi2(3)), horizontal 2, vertical 1; median of chi2(6) 5.35, "
                 "of chi2(3) 2.37; z^2 = error^2 / variance of one axis, ideal 1 (the JSON has every axis, error mean "
                 "and RMS, and the position error RMS per world axis)")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m gr_graph.noise_consistency", description=__doc__.split("\n")[0])
    ap.add_argument("run_dir", help="the --out folder of python -m gr_graph.slam")
    ap.add_argument("--round", type=int, action="append", dest="rounds", help="only this round (repeatable)")
    ap.add_argument("--json", type=Path, help="write the figures to this file")
    args = ap.parse_args(argv)
    try:
        result = run_noise_consistency(args.run_dir, args.rounds)
    except (FileNotFoundError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(format_table(result))
    if args.json is not None:
        from gr_graph.atomic import atomic_write_json

        atomic_write_json(args.json, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
