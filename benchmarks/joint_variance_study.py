"""The odometry's and the loops' variance factors estimated together, offline, on finished rounds (not a test).

A learning round scales every edge's information by one factor from the graph's residuals
(``training.learned_noise_calibration: graph_residuals``) and then the loops by their own factors
(``graph.loop_variance``), the odometry held fixed. This study asks whether the odometry's factor
can be estimated as well, from the same residuals and without ground truth: starting from the
informations a finished round used (``marginals.npz``), each pass

1. solves the Gaussian graph (loops without their kernel) and divides every odometry edge's
   information by ``sigma_O^2 = chi2_odometry / r_odometry`` (its variance component, ``r`` the
   odometry edges' share of the redundancy: :func:`gr_graph.noise_calibration.factor_redundancies`);
2. estimates the loops' common factor and then their per-axis factors with the odometry held fixed
   (:func:`~gr_graph.noise_calibration.loop_variance_factor`,
   :func:`~gr_graph.noise_calibration.loop_axis_variance_factors`, as ``estimated_axes`` does);

and reports, after every pass, the NEES against ground truth of the odometry and loop edges and of
the marginal positions (the robust graph solved with the new informations). Iterated, the passes
are the classical alternating variance-component estimate of two groups. Run::

    python benchmarks/joint_variance_study.py RUN@R [RUN@R ...] [--passes 3] [--write]

(``RUN@R``: round ``R`` of a finished run folder; ``RUN`` alone is round 0.) Writes
``benchmarks/results/joint_variance_components.md`` and ``.json`` with ``--write``.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from gr_graph.atomic import atomic_write_json, atomic_write_text
from gr_graph.config import load_config
from gr_graph.noise_calibration import factor_redundancies, loop_axis_variance_factors, loop_variance_factor
from gr_graph.noise_consistency import edge_nees, position_nees, position_nees_split
from gr_graph.pose_graph import PoseGraph, position_covariance_world
from gr_graph.provenance import machine_line

RESULTS = Path(__file__).resolve().parent / "results"


class _RoundGraph:
    """The edges of a finished round (``marginals.npz``) as a pose graph with changeable informations."""

    def __init__(self, round_dir: Path) -> None:
        path = round_dir / "marginals.npz"
        with np.load(path) as z:
            d = {k: np.array(z[k]) for k in z.files}
        missing = [k for k in ("gt_poses", "edges", "edge_T", "edge_information", "edge_kind", "edge_ok", "poses")
                   if k not in d]
        if missing:
            raise SystemExit(f"{path}: lacks {missing} (a run without ground truth, or written before edge_T)")
        self.d = d
        self.graph_cfg = load_config().graph
        info = 0.5 * (d["edge_information"] + np.transpose(d["edge_information"], (0, 2, 1)))
        self.edges = [SimpleNamespace(source=int(a), target=int(b), T=T, information=H,
                                      kind="loop" if k == 1 else "odometry")
                      for (a, b), T, H, k in zip(d["edges"], d["edge_T"], info, d["edge_kind"], strict=True)]
        self.latest = d["poses"]

    def build(self, informations: list[np.ndarray], gaussian: bool) -> PoseGraph:
        cfg = self.graph_cfg.model_copy(update={"loop_kernel": "none"}) if gaussian else self.graph_cfg
        g = PoseGraph(cfg)
        for T in self.latest:
            g.add_pose(T)
        for e, H in zip(self.edges, informations, strict=True):
            g.add_edge(e.source, e.target, e.T, H, loop=e.kind == "loop")
        return g

    def solve(self, informations: list[np.ndarray]):
        """Gaussian graph with ``informations``, solved from the latest poses: ``(graph, values)``."""
        g = self.build(informations, gaussian=True)
        self.latest = g.optimize(marginals=False).poses
        return g.graph, g.values

    def nees(self) -> dict[str, float]:
        """Mean NEES of odometry edges, loop edges and marginal positions with the current informations."""
        d = self.d
        res = self.build([e.information for e in self.edges], gaussian=False).optimize(marginals=True)
        info = np.stack([e.information for e in self.edges])
        n = edge_nees(d["edges"], d["edge_T"], info, d["gt_poses"])
        ok = d["edge_ok"].astype(bool)
        pc = position_covariance_world(res.poses, res.covariances)
        split = position_nees_split(res.poses, pc, d["gt_poses"])
        return {"odometry": float(n[(d["edge_kind"] == 0) & ok].mean()), "loop": float(n[(d["edge_kind"] == 1) & ok].mean()),
                "position": float(position_nees(res.poses, pc, d["gt_poses"]).mean()),
                "horizontal": float(split["horizontal"]["mean"]), "vertical": float(split["vertical"]["mean"])}

    def one_pass(self) -> dict[str, float]:
        """Step 1 and 2 of the module docstring; the figures of the pass."""
        odo = [i for i, e in enumerate(self.edges) if e.kind == "odometry"]
        loops = [i for i, e in enumerate(self.edges) if e.kind == "loop"]
        graph, values = self.solve([e.information for e in self.edges])
        chi2_o = sum(2.0 * graph.at(1 + i).error(values) for i in odo)  # factor 0 is the prior
        chi2_l = sum(2.0 * graph.at(1 + i).error(values) for i in loops)
        r_o, r_l = factor_redundancies(graph, values, [[1 + i for i in odo], [1 + i for i in loops]])
        s_o = float(chi2_o / r_o)
        for i in odo:
            self.edges[i].information = self.edges[i].information / s_o
        common = loop_variance_factor(self.solve, self.edges)
        for i in loops:
            self.edges[i].information = common.scaled_information(self.edges[i].information)
        axes = loop_axis_variance_factors(self.solve, self.edges)
        for i in loops:
            self.edges[i].information = axes.scaled_information(self.edges[i].information)
        return {"odometry_sigma_sq": s_o, "odometry_redundancy": float(r_o), "loop_redundancy": float(r_l),
                "loop_sigma_sq": float(chi2_l / r_l), "loop_scale": common.scale,
                "loop_axis_scale": [float(a) for a in axes.axis_scale]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="RUN@R: round R of a finished run")
    ap.add_argument("--passes", type=int, default=3)
    ap.add_argument("--write", action="store_true")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from loop_variance_study import run_round

    results = []
    lines = ["| run | pass | odometry sigma_O² (redundancy) | loops sigma_L² (redundancy) | odometry NEES (3-12) "
             "| loop NEES (3-12) | position NEES (1.5-6) (horizontal / vertical) |", "|---|---|---|---|---|---|---|"]
    for arg in args.runs:
        run, r = run_round(arg)
        g = _RoundGraph(run / f"round_{r}")
        rows = [{"pass": 0, **g.nees()}]
        for k in range(1, args.passes + 1):
            est = g.one_pass()
            rows.append({"pass": k, **est, **g.nees()})
        results.append({"run": str(run), "round": r, "passes": rows})
        for row in rows:
            est = (f"{row['odometry_sigma_sq']:.3g} ({row['odometry_redundancy']:.1f}) | {row['loop_sigma_sq']:.3g} "
                   f"({row['loop_redundancy']:.1f})" if row["pass"] else "as run | as run")
            lines.append(f"| {run.name}@{r} | {row['pass']} | {est} | {row['odometry']:.3g} | {row['loop']:.3g} | "
                         f"{row['position']:.3g} ({row['horizontal']:.3g} / {row['vertical']:.3g}) |")
            print(lines[-1], flush=True)
    text = "\n".join(lines)
    if args.write:
        command = shlex.join(["python", "benchmarks/joint_variance_study.py", *(sys.argv[1:] if argv is None else argv)])
        atomic_write_json(RESULTS / "joint_variance_components.json", {"machine": machine_line(), "runs": results})
        atomic_write_text(RESULTS / "joint_variance_components.md", "# The odometry's and the loops' variance factors "
                          f"estimated together (offline)\n\nCommand: `{command}`. Machine: {machine_line()}.\n\n"
                          "Pass 0: the informations the round used (one scale for all edges from the graph's residuals, "
                          "then the loops' common and per-axis factors). Each pass k >= 1 divides the odometry edges' "
                          "information by their variance component sigma_O² (from the residuals of the pass's solution) "
                          "and then re-estimates the loops' factors with the odometry held fixed "
                          "(`benchmarks/joint_variance_study.py` docstring). NEES against ground truth after the pass.\n\n"
                          + text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
