"""One wrong loop against the learned noise's one-scale calibration, on constructed pose graphs (not a test).

A 300-pose drive (two laps of a 150-pose circle, 1 m steps) with odometry edges whose information
is right, and ``n`` correct loops between the laps (``n`` = 15, or 3); every draw adds one wrong loop
(poses 280 -> 20, 2 m and 3 deg off) that passed verification. The information of every edge is
then calibrated as the learning rounds do (:func:`gr_graph.noise_calibration.variance_factor` on the
Gaussian graph) with the wrong loop in the estimate (the behaviour before 2026-12-06) and with the
loops that fail :func:`gr_graph.noise_calibration.outlying_loop` left out (opt-in since, with
``training.learned_noise_outlier_alpha``: on the full synthetic route it left out correct loops), and the
robust graph (Cauchy loops, as SLAM solves it) is scored by ATE against the constructed truth, beside
the same graph without the wrong loop. Also counted: false alarms of the test on the graphs without
a wrong loop.

Run::

    python benchmarks/calibration_wrong_loop.py [--draws 10] [--write]

``--write`` writes ``benchmarks/results/calibration_wrong_loop.md`` and ``.json``.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from factors.se3 import exp_se3
from gr_graph.config import GraphConfig
from gr_graph.noise_calibration import outlying_loop, variance_factor
from gr_graph.odometry import RegistrationEdge
from gr_graph.pose_graph import PoseGraph

from results_io import print_and_write

K = 300
SIGMAS = np.array([1e-3, 1e-3, 2e-3, 0.02, 0.02, 0.02])  # odometry: rad, rad, rad, m, m, m ([omega, v])
INFO = np.diag(1.0 / SIGMAS**2)
WRONG = np.array([0.0, 0.0, 0.05, 2.0, 1.0, 0.0])  # the wrong loop's error: 3 deg of yaw, 2.2 m
ALPHA = 1e-4


def truth() -> np.ndarray:
    """The constructed poses: 1 m a step, a full turn every 150 steps."""
    step = exp_se3(np.array([0.0, 0.0, 2 * np.pi / 150, 1.0, 0.0, 0.0]))
    poses = [np.eye(4)]
    for _ in range(K - 1):
        poses.append(poses[-1] @ step)
    return np.stack(poses)


def edge(gt: np.ndarray, rng: np.random.Generator, source: int, target: int, kind: str,
         error: np.ndarray | None = None) -> RegistrationEdge:
    """A measured edge: noise drawn from its information (loops 4x as precise), plus ``error``."""
    sd = SIGMAS if kind == "odometry" else 0.5 * SIGMAS
    T = np.linalg.inv(gt[target]) @ gt[source] @ exp_se3(rng.normal(size=6) * sd)
    if error is not None:
        T = T @ exp_se3(error)
    info = INFO if kind == "odometry" else 4.0 * INFO
    return RegistrationEdge(source, target, T, info, info.copy(), 1.0, 0.0, 1, True, "", kind)


def solve(edges: list[RegistrationEdge], scale: float, robust: bool) -> PoseGraph:
    """The graph of ``edges`` with every information x ``scale``, from the odometry's poses."""
    g = PoseGraph(GraphConfig(marginals=False, **({} if robust else {"loop_kernel": "none"})))
    poses = [np.eye(4)]
    for e in edges:
        if e.kind == "odometry":
            poses.append(poses[-1] @ e.T)
    for T in poses:
        g.add_pose(T)
    for e in edges:
        g.add_edge(e.source, e.target, e.T, scale * e.information, loop=e.kind == "loop")
    g.optimize(marginals=False)
    return g


def ate(g: PoseGraph, gt: np.ndarray) -> float:
    """Position RMSE against the truth (both anchored at pose 0, which the prior holds)."""
    p = g.current_poses()[:, :3, 3]
    return float(np.sqrt(np.mean(np.sum((p - gt[:, :3, 3]) ** 2, axis=1))))


def calibrated_scale(edges: list[RegistrationEdge], guard: bool) -> tuple[float, int]:
    """The calibration's scale with or without the loop test; and how many loops it left out."""
    kept = list(edges)
    left_out = 0
    while True:
        g = solve(kept, 1.0, robust=False)
        found = outlying_loop(g.graph, g.values, kept, ALPHA) if guard else None
        if found is None:
            return variance_factor(g.current_poses(), kept).scale, left_out
        kept.pop(found[0])
        left_out += 1


def draw(gt: np.ndarray, seed: int, n_loops: int) -> dict[str, float]:
    rng = np.random.default_rng(seed)
    edges = [edge(gt, rng, k + 1, k, "odometry") for k in range(K - 1)]
    edges += [edge(gt, rng, 150 + j * (140 // max(n_loops - 1, 1)), j * (140 // max(n_loops - 1, 1)), "loop")
              for j in range(n_loops)]
    wrong = edge(gt, rng, 280, 20, "loop", WRONG)
    clean_scale, false_alarms = calibrated_scale(edges, guard=True)
    before, _ = calibrated_scale(edges + [wrong], guard=False)
    after, left_out = calibrated_scale(edges + [wrong], guard=True)
    return {"seed": seed, "n_loops": n_loops, "false_alarms": false_alarms, "left_out": left_out,
            "scale_before": before, "scale_after": after, "scale_without_wrong": clean_scale,
            "ate_before": ate(solve(edges + [wrong], before, True), gt),
            "ate_after": ate(solve(edges + [wrong], after, True), gt),
            "ate_without_wrong": ate(solve(edges, clean_scale, True), gt)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--draws", type=int, default=10)
    ap.add_argument("--write", action="store_true")
    a = ap.parse_args(argv)
    gt = truth()
    rows = [draw(gt, seed, n) for n in (15, 3) for seed in range(a.draws)]
    lines = ["# One wrong loop against the learned noise's calibration (constructed graphs)", "",
             f"`python benchmarks/calibration_wrong_loop.py --draws {a.draws} --write`: {__doc__.split(chr(10) * 2)[1]}",
             "", "| correct loops | draws | wrong loop left out | false alarms (without it) | 1/σ₀² before → after "
             "(without the wrong loop) | ATE before | ATE after | ATE without the wrong loop |",
             "|---|---|---|---|---|---|---|---|"]
    for n in (15, 3):
        r = [x for x in rows if x["n_loops"] == n]

        def ms(key: str, fmt: str = ".3f") -> str:
            v = np.array([x[key] for x in r])
            return f"{v.mean():{fmt}} ± {v.std(ddof=1):{fmt}}"

        lines.append(f"| {n} | {len(r)} | {sum(x['left_out'] > 0 for x in r)} | {sum(x['false_alarms'] for x in r)} | "
                     f"{ms('scale_before')} → {ms('scale_after')} ({ms('scale_without_wrong')}) | {ms('ate_before')} m | "
                     f"{ms('ate_after')} m | {ms('ate_without_wrong')} m |")
    lines += ["", "Mean ± sample std over the draws; the true scale is 1 (the information is right)."]
    print_and_write("calibration_wrong_loop", "\n".join(lines), {"alpha": ALPHA, "rows": rows}, a.write)
    return 0


if __name__ == "__main__":
    sys.exit(main())
