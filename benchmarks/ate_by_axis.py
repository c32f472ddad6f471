"""Where a run's trajectory error lies: height or the horizontal plane, round by round (a study).

For every finished run (a ``gr_graph.slam`` output folder with ``gt_poses_kitti.txt`` and
``round_<r>/poses_kitti.txt``) and every round in it, the SE(3)-aligned ATE (evo's Umeyama, the
run's own ``ate_rmse``) is split into its height part (the camera frame's y axis of the KITTI-form
poses) and its horizontal part (x and z): :func:`gr_graph.metrics.ate_by_axis`. A learning round
can lower the ATE by undoing a height drift (the `kitti` preset's 0.22 deg vertical-angle error
tilts the odometry) while the horizontal trajectory gets worse; this table shows which.

Run::

    python benchmarks/ate_by_axis.py RUN [RUN ...] [--labels A B ...] [--write NAME]

(from the repository's top folder, or with the script's path in the repository).

``--write NAME`` writes ``benchmarks/results/NAME.md`` and ``.json``. Runs of the experiment
harness are ``ROOT/table1/<cell>/slam``.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path
from typing import Any

from gr_graph.metrics import ate_by_axis
from gr_graph.provenance import machine_line
from gr_graph.trajectory import read_kitti_poses
from results_io import last_change, print_and_write


def run_rounds(run: Path) -> list[int]:
    """The rounds of ``run`` that have poses (folders ``round_<r>``, r an integer), in order."""
    rounds = sorted(int(p.name[len("round_"):]) for p in run.glob("round_*")
                    if p.name[len("round_"):].isdigit() and (p / "poses_kitti.txt").is_file())
    if not rounds:
        raise SystemExit(f"{run}: no round_<r>/poses_kitti.txt: not a finished gr_graph.slam run")
    return rounds


def study_run(run: Path) -> dict[str, dict[str, Any]]:
    """Per round of ``run`` (str keys): ``rmse``, ``vertical_rmse``, ``horizontal_rmse`` [m] and
    ``accepted`` (the GT-free test's verdict from ``metrics.json``; None when not recorded)."""
    gt_file = run / "gt_poses_kitti.txt"
    if not gt_file.is_file():
        raise SystemExit(f"{run}: no gt_poses_kitti.txt (a run without ground truth cannot be split)")
    gt = read_kitti_poses(gt_file)
    summaries = json.loads((run / "metrics.json").read_text())["rounds"] if (run / "metrics.json").is_file() else {}
    return {str(r): {**ate_by_axis(read_kitti_poses(run / f"round_{r}" / "poses_kitti.txt"), gt),
                     "accepted": summaries.get(str(r), {}).get("accepted")} for r in run_rounds(run)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--labels", nargs="+", help="one label a run (default: the run folder's name, or the cell's "
                                                "name for a harness run ending in /slam)")
    ap.add_argument("--write", metavar="NAME", help="also write benchmarks/results/NAME.md and .json")
    args = ap.parse_args(argv)
    if args.labels and len(args.labels) != len(args.runs):
        ap.error(f"{len(args.labels)} labels for {len(args.runs)} runs")
    labels = args.labels or [r.parent.name if r.name == "slam" else r.name for r in args.runs]
    if len(set(labels)) != len(labels):
        ap.error(f"two runs share a label ({labels}): give --labels")
    results = {label: study_run(run) for label, run in zip(labels, args.runs, strict=True)}
    lines = ["# The trajectory error split into height and the horizontal plane, round by round", "",
             f"`python benchmarks/ate_by_axis.py {shlex.join(sys.argv[1:] if argv is None else argv)}`; "
             f"{machine_line()}. SE(3)-aligned ATE RMSE (evo's Umeyama) split along the camera frame's y axis "
             "(height) and x, z (plane), metres, round 0 → 1 → ...; the change is the last round against round 0 "
             "(a round the GT-free test rejected is marked ✗ in the last column).",
             "", "| run | ATE RMSE | height RMSE | horizontal RMSE | height change | horizontal change | rejected |",
             "|---|---|---|---|---|---|---|"]
    for label, per_round in results.items():
        rounds = sorted(per_round, key=int)
        col = {k: [per_round[r][k] for r in rounds] for k in ("rmse", "vertical_rmse", "horizontal_rmse")}
        lines.append(f"| {label} | " + " | ".join(" → ".join(f"{v:.3f}" for v in col[k]) for k in col)
                     + f" | {last_change(col['vertical_rmse'])} | {last_change(col['horizontal_rmse'])} | "
                     + (", ".join(f"{r} ✗" for r in rounds if per_round[r]["accepted"] is False) or "none") + " |")
    print_and_write(args.write or "ate_by_axis", "\n".join(lines),
                    {"command": ["python", "benchmarks/ate_by_axis.py", *(sys.argv[1:] if argv is None else argv)],
                     "runs": {label: str(run) for label, run in zip(labels, args.runs, strict=True)},
                     "rounds": results, "units": "m"}, bool(args.write))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
