"""What the loops' own variance factors do: a finished round's graph solved again without them.

``--loop-variance estimated`` / ``estimated_axes`` multiply every loop edge's information by a
factor from the graph's residuals (common, then per axis; :mod:`gr_graph.noise_calibration`), on top
of whatever calibration the edges had. This study takes round ``R`` of a run from its
``marginals.npz`` (every edge's measurement and information, the poses) and ``round.json`` (the
factors), divides the factors out of the loop edges, solves the graph again (the run's
``graph`` options, started from its poses) with marginals, and scores both graphs against the
ground truth (:func:`gr_graph.noise_consistency.round_noise_consistency`): the graph as run, solved
again (a check that the re-solve reproduces the run: its figures must equal the round's
``noise_consistency``), and the graph with the loops unscaled. The edge NEES depend only on the
informations; the positions and the ATE on the new solution.

Usage::

    python benchmarks/loop_factor_undone_study.py LABEL RUN@R [LABEL RUN@R ...] [--name N --title T --note N --write]
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from results_io import print_and_write  # noqa: E402

#: relative agreement required between the re-solved graph as run and the round's own figures
REPRODUCE_RTOL = 0.01


def solve_round(round_dir: Path, graph_cfg: Any, undo_loop_factors: bool,
                information_change: Callable[[dict[str, np.ndarray], np.ndarray], np.ndarray] | None = None
                ) -> dict[str, Any]:
    """NEES (odometry, loop, positions) and ATE RMSE of round ``round_dir``'s graph solved again,
    with the loops' variance factors divided out if ``undo_loop_factors``, then every edge's
    information passed through ``information_change(marginals, information)`` if given
    (``marginals``: the round's marginals.npz as a dict; ``information``: ``(E, 6, 6)``)."""
    from gr_graph.metrics import ate
    from gr_graph.noise_calibration import _axis_scaled
    from gr_graph.noise_consistency import round_noise_consistency
    from gr_graph.pose_graph import build_pose_graph, position_covariance_world

    with np.load(round_dir / "marginals.npz") as z:
        d = {k: np.array(z[k]) for k in z.files}
    summary = json.loads((round_dir / "round.json").read_text())
    lv = summary.get("loop_variance") or {}
    common = float(lv.get("scale") or 1.0)
    axes = np.asarray((lv.get("axes") or {}).get("axis_scale") or np.ones(6), float)
    information = d["edge_information"].copy()
    loops = d["edge_kind"] == 1
    if undo_loop_factors:
        for i in np.nonzero(loops)[0]:
            information[i] = _axis_scaled(information[i], 1.0 / axes) / common
    if information_change is not None:
        information = information_change(d, information)
    graph = build_pose_graph(graph_cfg, d["poses"], ((k, l, T, H, loop) for (k, l), T, H, loop
                                                     in zip(d["edges"], d["edge_T"], information, loops, strict=True)))
    res = graph.optimize(marginals=True)
    d.update(poses=res.poses, covariance=res.covariances, edge_information=information,
             position_cov_world=position_covariance_world(res.poses, res.covariances))
    with tempfile.TemporaryDirectory() as tmp:
        np.savez(Path(tmp) / "marginals.npz", **d)
        nc = round_noise_consistency(tmp, summary.get("marginals"))
    return {"odometry_nees": nc["edges"]["odometry"]["mean"], "loop_nees": nc["edges"]["loop"]["mean"],
            "position_nees": nc["position"]["mean"], "ate_rmse": float(ate(res.poses, d["gt_poses"]).rmse),
            "odometry_z2_axes": nc["edges"]["odometry"]["per_axis"]["z2_mean"],
            "loop_z2_axes": nc["edges"]["loop"]["per_axis"]["z2_mean"],
            "position_nees_vertical": nc["position"]["vertical"]["mean"],
            "loop_factor_common": common, "loop_factor_axes": axes.tolist(), "n_loops": int(loops.sum())}


def check_reproduced(as_run: dict[str, Any], round_dir: Path) -> None:
    """Raise when the re-solved graph as run does not give the round's own NEES and ATE."""
    summary = json.loads((round_dir / "round.json").read_text())
    nc, slam = summary["noise_consistency"], summary["slam"]
    own = {"odometry_nees": nc["edges"]["odometry"]["mean"], "loop_nees": nc["edges"]["loop"]["mean"],
           "position_nees": nc["position"]["mean"], "ate_rmse": slam["ate_rmse"]}
    off = {k: (as_run[k], v) for k, v in own.items() if not np.isclose(as_run[k], v, rtol=REPRODUCE_RTOL)}
    if off:
        raise RuntimeError(f"{round_dir}: the graph solved again does not reproduce the round ({off}: re-solved, "
                           "round); the study's figures would not describe this run")


def _fmt(x: float) -> str:
    return f"{x:.3g}"


def table(rows: list[tuple[str, dict[str, Any], dict[str, Any]]]) -> str:
    """Markdown: per run the graph as run and with the loops unscaled, then mean ± std over the runs."""
    keys = ("odometry_nees", "loop_nees", "position_nees", "ate_rmse")
    lines = ["| run | loops | loop factor (common; per axis ωx ωy ωz x y z) | as run: odometry / loop / position NEES, "
             "ATE [m] | loop factors undone: odometry / loop / position NEES, ATE [m] |", "|---|---|---|---|---|"]
    for label, a, b in rows:
        lines.append(f"| {label} | {a['n_loops']} | {a['loop_factor_common']:.2f}; "
                     + " ".join(f"{v:.2f}" for v in a["loop_factor_axes"])
                     + " | " + " / ".join(_fmt(a[k]) for k in keys) + " | " + " / ".join(_fmt(b[k]) for k in keys) + " |")
    if len(rows) > 1:
        def ms(which: int, k: str) -> str:
            v = np.array([r[which][k] for r in rows], float)
            return f"{_fmt(v.mean())} ± {_fmt(v.std(ddof=1))}"

        lines.append("| mean ± std | | | " + " / ".join(ms(1, k) for k in keys) + " | "
                     + " / ".join(ms(2, k) for k in keys) + " |")
    return "\n".join(lines)


def study_parser(doc: str, name: str, title: str) -> argparse.ArgumentParser:
    """The command line of a study of finished rounds: ``LABEL RUN@R`` pairs, ``--write``, ``--name``,
    ``--title``, ``--note``."""
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("pairs", nargs="+", help="LABEL RUN@R, repeated")
    ap.add_argument("--write", action="store_true", help="write benchmarks/results/NAME.md / .json")
    ap.add_argument("--name", default=name)
    ap.add_argument("--title", default=title)
    ap.add_argument("--note", default="", help="a paragraph written under the table (how the runs were made)")
    return ap


def rounds_given(ap: argparse.ArgumentParser, pairs: list[str]) -> Iterator[tuple[str, str, Path, Any]]:
    """``(label, RUN@R, round folder, the run's configuration)`` of each ``LABEL RUN@R`` pair (errors
    through ``ap``)."""
    if len(pairs) % 2:
        ap.error("give LABEL RUN@R pairs")
    import yaml

    from gr_graph.config import load_config

    for label, spec in zip(pairs[::2], pairs[1::2], strict=True):
        run, _, r = spec.rpartition("@")
        if not run or not r.isdigit():
            ap.error(f"{spec}: give RUN@R (a run folder and a round number)")
        yield label, spec, Path(run) / f"round_{r}", load_config(None, yaml.safe_load((Path(run) / "config.yaml").read_text()))


def main(argv: list[str] | None = None) -> int:
    ap = study_parser(__doc__, "loop_factor_undone", "The graph without the loops' own variance factors")
    args = ap.parse_args(argv)
    rows = []
    for label, _, round_dir, cfg in rounds_given(ap, args.pairs):
        as_run = solve_round(round_dir, cfg.graph, undo_loop_factors=False)
        check_reproduced(as_run, round_dir)
        rows.append((label, as_run, solve_round(round_dir, cfg.graph, undo_loop_factors=True)))
    command = shlex.join(["python", "benchmarks/loop_factor_undone_study.py", *(sys.argv[1:] if argv is None else argv)])
    text = (f"# {args.title}\n\nCommand: `{command}`. Each round's graph is solved again from its marginals.npz "
            "with the loops' factors from its round.json divided out; the graph as run, solved again, reproduces "
            f"the round's own NEES and ATE to {REPRODUCE_RTOL:.0%} (checked). Bands: edges 3-12, positions 1.5-6.\n\n"
            + table(rows) + "\n" + (f"\n{args.note}\n" if args.note else ""))
    print_and_write(args.name, text, {"runs": [{"label": label, "as_run": a, "loop_factors_undone": b}
                                              for label, a, b in rows]}, args.write)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
