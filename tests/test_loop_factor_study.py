"""benchmarks/loop_factor_undone_study.py on a constructed round: the loops' factors divided out
exactly, and a round the re-solve does not reproduce refused."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from benchmark_support import benchmark_script
from factors.se3 import exp_se3
from gr_graph.config import GraphConfig
from gr_graph.noise_consistency import edge_nees, round_noise_consistency
from gr_graph.pose_graph import PoseGraph, position_covariance_world


def _round(tmp_path: Path, common: float, axes: np.ndarray) -> tuple[Path, np.ndarray, np.ndarray]:
    """A 30-pose loop drive with noisy odometry and 3 loops whose information carries the factors."""
    rng = np.random.default_rng(0)
    n = 30
    gt = [np.eye(4)]
    for i in range(1, n):
        gt.append(gt[-1] @ exp_se3(np.r_[0, 0, 2 * np.pi / n, 1.0, 0, 0]))
    gt = np.stack(gt)
    sigma = np.r_[0.004, 0.004, 0.01, 0.05, 0.05, 0.02]
    base = np.diag(1 / sigma**2)
    edges, measured, info, kind = [], [], [], []
    for k, l, loop in [(i + 1, i, False) for i in range(n - 1)] + [(29, 0, True), (25, 3, True), (20, 8, True)]:
        T = np.linalg.inv(gt[l]) @ gt[k] @ exp_se3(rng.normal(size=6) * sigma)
        edges.append((k, l))
        measured.append(T)
        root = np.sqrt(axes)
        info.append(common * root[:, None] * base * root[None, :] if loop else base)
        kind.append(1 if loop else 0)
    graph = PoseGraph(GraphConfig())
    odo = [np.eye(4)]
    for T in measured[:n - 1]:
        odo.append(odo[-1] @ T)
    for T in odo:
        graph.add_pose(T)
    for (k, l), T, H, c in zip(edges, measured, info, kind):
        graph.add_edge(k, l, T, H, loop=bool(c))
    res = graph.optimize(marginals=True)
    rd = tmp_path / "round_1"
    rd.mkdir()
    np.savez(rd / "marginals.npz", poses=res.poses, covariance=res.covariances,
             position_cov_world=position_covariance_world(res.poses, res.covariances), edges=np.array(edges),
             edge_T=np.stack(measured), edge_information=np.stack(info), edge_kind=np.array(kind, np.uint8),
             edge_ok=np.ones(len(edges), bool), gt_poses=gt)
    from gr_graph.metrics import ate

    summary = {"loop_variance": {"scale": common, "axes": {"axis_scale": axes.tolist()}},
               "noise_consistency": round_noise_consistency(rd), "slam": {"ate_rmse": float(ate(res.poses, gt).rmse)},
               "marginals": None}
    (rd / "round.json").write_text(json.dumps(summary))
    return rd, np.stack(info), base


def test_the_loop_factors_are_divided_out_and_the_run_reproduced(tmp_path: Path) -> None:
    study = benchmark_script("loop_factor_undone_study")
    axes = np.array([1.0, 0.3, 1.0, 1.0, 1.0, 1.0])
    rd, info, base = _round(tmp_path, 0.5, axes)
    with np.load(rd / "marginals.npz") as z:
        edges, edge_T, kind, gt = z["edges"], z["edge_T"], z["edge_kind"], z["gt_poses"]
    as_run = study.solve_round(rd, GraphConfig(), undo_loop_factors=False)
    study.check_reproduced(as_run, rd)  # no error: the re-solve gives the round's figures
    undone = study.solve_round(rd, GraphConfig(), undo_loop_factors=True)
    loops = kind == 1
    expected = edge_nees(edges[loops], edge_T[loops], np.repeat(base[None], loops.sum(), 0), gt).mean()
    scaled = edge_nees(edges[loops], edge_T[loops], info[loops], gt).mean()
    assert undone["loop_nees"] == pytest.approx(expected, rel=1e-9)
    assert as_run["loop_nees"] == pytest.approx(scaled, rel=1e-9)
    assert abs(expected - scaled) > 0.1 * expected  # the factors matter here
    assert undone["odometry_nees"] == pytest.approx(as_run["odometry_nees"], rel=1e-12)


def test_a_round_the_resolve_does_not_reproduce_is_refused(tmp_path: Path) -> None:
    study = benchmark_script("loop_factor_undone_study")
    rd, _, _ = _round(tmp_path, 0.5, np.ones(6))
    summary = json.loads((rd / "round.json").read_text())
    summary["slam"]["ate_rmse"] *= 1.5  # as if the round had been solved with other edges
    (rd / "round.json").write_text(json.dumps(summary))
    as_run = study.solve_round(rd, GraphConfig(), undo_loop_factors=False)
    with pytest.raises(RuntimeError, match="does not reproduce the round"):
        study.check_reproduced(as_run, rd)
