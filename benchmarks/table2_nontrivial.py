"""Table II against the pairs the identity already solves (a study of finished Table II cells).

The paper's protocol draws 100 scan pairs within 10 m of each other. On a route with stops and slow
driving, many of them are nearly the same scan twice: the identity (no registration at all) passes the
10° / 2 m test on them. This study reads the per-pair rows of a harness root's Table II cells
(``ROOT/table2/<cell>/registration.json``), finds the pairs the identity solves from the cell's own
ground truth (the Table I cell's ``slam/config.yaml`` opens the same sequence), and reports per
channel count, step and solver (mean ± sample std over seeds):

- the identity's success rate (the floor every solver gets for free);
- each solver's success on all pairs and on the pairs the identity does not solve;
- how many of the solver's answers were "no solution" (KISS-Matcher's ``valid`` false, FPFH with no
  accepted hypothesis) and how many of those the evaluation scored as successes (cells run before
  ``valid`` was recorded scored the identity they returned like any estimate).

Cells run since then carry these figures in ``registration.json`` (``identity``, ``n_invalid``,
``success_rate_nontrivial``); this script recomputes them the same way for older cells.

Run::

    python benchmarks/table2_nontrivial.py ROOT [--write NAME]
    python benchmarks/table2_nontrivial.py benchmarks/results/NAME.json --from-json [--write NAME]

``--write NAME`` writes ``benchmarks/results/NAME.md`` and ``.json``; ``--from-json`` rebuilds the tables
from such a JSON (the per-cell figures) when the harness root is gone.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from gr_graph.global_registration import is_success, relative_transform
from gr_graph.provenance import machine_line
from results_io import print_and_write

STEPS = {0: "raw", 1: "1-step", 2: "2-step"}


def cell_ground_truth(root: Path, definition: dict[str, Any]) -> np.ndarray:
    """LiDAR-frame ground truth of the sequence a Table II cell registered (its Table I cell's config)."""
    from gr_graph.config import load_config
    from gr_graph.datasets.registry import open_configured_sequence

    cfg = load_config(root / definition["source"] / "slam" / "config.yaml", {})
    seq, _ = open_configured_sequence(cfg.data, synthetic_seed=cfg.seed)
    return np.asarray(seq.gt_poses, np.float64)[: len(seq)]


def study_cell(root: Path, cell_dir: Path, gt_cache: dict[str, np.ndarray]) -> dict[str, Any]:
    """Identity and per-solver figures of one finished Table II cell."""
    definition = json.loads((cell_dir / "definition.json").read_text())["definition"]
    rows = json.loads((cell_dir / "registration.json").read_text())["pairs"]
    if definition["source"] not in gt_cache:
        gt_cache[definition["source"]] = cell_ground_truth(root, definition)
    gt = gt_cache[definition["source"]]
    pairs = sorted({(r["source"], r["target"]) for r in rows})
    trivial = {p: is_success(np.eye(4), relative_transform(gt, *p)) for p in pairs}
    out: dict[str, Any] = {"channels": definition["channels"], "seed": definition["seed"],
                           "round": definition["params"]["round"], "n_pairs": len(pairs),
                           "identity": float(np.mean(list(trivial.values()))), "solvers": {}}
    for solver in sorted({r["solver"] for r in rows}):
        mine = [r for r in rows if r["solver"] == solver]
        # before `valid` was recorded: a solver without a solution returned exactly the identity
        invalid = [not r["valid"] if "valid" in r else np.array_equal(np.asarray(r["T_est"]), np.eye(4))
                   for r in mine]
        hard = [r["success"] for r in mine if not trivial[(r["source"], r["target"])]]
        out["solvers"][solver] = {
            "success": float(np.mean([r["success"] for r in mine])),
            "success_nontrivial": float(np.mean(hard)) if hard else None, "n_nontrivial": len(hard),
            "n_invalid": int(sum(invalid)),
            "n_invalid_scored_success": int(sum(bool(r["success"]) and bad for r, bad in zip(mine, invalid))),
        }
    return out


def mean_std(values: list[float | None]) -> str:
    """``m ± s`` in percent (sample std; one value: no spread) of the values given (None: not measured)."""
    v = 100.0 * np.asarray([x for x in values if x is not None], float)
    if not len(v):
        return "n/a"
    return f"{v.mean():.1f} ± {v.std(ddof=1):.1f}" if len(v) > 1 else f"{v[0]:.1f}"


def paired_changes(cells: dict[str, dict[str, Any]], solvers: list[str]) -> list[str]:
    """Markdown rows: per channel count, densified step and solver, the change of the success on the
    non-trivial pairs against the same seed's raw scans [points], mean ± sample std over the seeds
    measured in both, and each seed's."""
    by_key = {(c["channels"], c["seed"], c["round"]): c for c in cells.values()}
    rows = []
    for channels, r in sorted({(c["channels"], c["round"]) for c in cells.values() if c["round"] > 0},
                              key=lambda k: (-k[0], k[1])):
        for solver in solvers:
            seeds, deltas = [], []
            for (ch, seed, rr), c in sorted(by_key.items()):
                raw = by_key.get((ch, seed, 0))
                if ch != channels or rr != r or raw is None:
                    continue
                a, b = (x["solvers"].get(solver, {}).get("success_nontrivial") for x in (raw, c))
                if a is not None and b is not None:
                    seeds.append(seed)
                    deltas.append(b - a)
            per_seed = ", ".join(f"s{s} {100 * d:+.1f}" for s, d in zip(seeds, deltas)) or "n/a"
            mean = mean_std(deltas)
            signed = mean if mean == "n/a" or mean.startswith("-") else "+" + mean
            rows.append(f"| {channels} | {STEPS.get(r, r)} | {solver} | {signed} | {per_seed} | "
                        f"{sum(d > 0 for d in deltas)} of {len(deltas)} |")
    return rows


def report(root: Path, cells: dict[str, dict[str, Any]], command: str, machine: str, rebuilt_with: str = "") -> str:
    """The markdown table: per channel count, step and solver, over seeds (``machine``: where the figures
    were computed; ``rebuilt_with``: the command that rebuilt the tables from their JSON, if one did)."""
    groups: dict[tuple[int, int], list[dict[str, Any]]] = defaultdict(list)
    for c in cells.values():
        groups[(c["channels"], c["round"])].append(c)
    solvers = sorted({s for c in cells.values() for s in c["solvers"]})
    lines = [
        "# Table II against the pairs the identity already solves",
        "",
        f"`{command}` ({machine}{f'; tables rebuilt from its JSON with `{rebuilt_with}`' if rebuilt_with else ''}): the per-pair rows of the Table II cells in `{root}`; success is "
        "rotation < 10° and translation < 2 m; mean ± std over seeds [%]. \"Non-trivial\": the pairs on which "
        "the identity (no registration) fails.",
        "",
        "| channels | step | seeds | identity | " + " | ".join(
            f"{s}: all | {s}: non-trivial (n) | {s}: no solution (scored success)" for s in solvers) + " |",
        "|---|---|---|---|" + "---|---|---|" * len(solvers),
    ]
    for (channels, r), cs in sorted(groups.items(), key=lambda kv: (-kv[0][0], kv[0][1])):
        cells_solvers = [[c["solvers"][s] for c in cs if s in c["solvers"]] for s in solvers]
        parts = []
        for per_seed in cells_solvers:
            n_hard = "/".join(str(x["n_nontrivial"]) for x in per_seed) or "none run"
            parts += [mean_std([x["success"] for x in per_seed]),
                      f"{mean_std([x['success_nontrivial'] for x in per_seed])} ({n_hard})",
                      f"{sum(x['n_invalid'] for x in per_seed)} ({sum(x['n_invalid_scored_success'] for x in per_seed)})"]
        lines.append(f"| {channels} | {STEPS.get(r, r)} | {len(cs)} | {mean_std([c['identity'] for c in cs])} | "
                     + " | ".join(parts) + " |")
    lines += ["", "Paired by seed: the change of the success on the non-trivial pairs against the same seed's raw "
              "scans [points], mean ± sample std over the seeds measured in both:", "",
              "| channels | step | solver | change | per seed | better in |", "|---|---|---|---|---|---|",
              *paired_changes(cells, solvers)]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("root", type=Path, help="an experiment harness root with finished Table II cells")
    ap.add_argument("--write", metavar="NAME", help="write benchmarks/results/NAME.md and .json")
    ap.add_argument("--from-json", action="store_true",
                    help="ROOT is a JSON this script wrote (its per-cell figures): rebuild the table from it")
    args = ap.parse_args(argv)
    command = "python benchmarks/table2_nontrivial.py " + " ".join(shlex.quote(a) for a in (argv or sys.argv[1:]))
    if args.from_json:
        stored = json.loads(args.root.read_text())
        root, cells = Path(stored["root"]), stored["cells"]
        machine = stored.get("machine", "machine not recorded")
        rebuilt_with = command  # the figures are the stored run's, the tables this call's
        command = stored.get("command", f"python benchmarks/table2_nontrivial.py {shlex.quote(stored['root'])}")
    else:
        cell_dirs = sorted(d for d in (args.root / "table2").glob("*") if (d / "registration.json").is_file())
        if not cell_dirs:
            print(f"error: {args.root / 'table2'}: no finished Table II cell (registration.json)", file=sys.stderr)
            return 2
        gt_cache: dict[str, np.ndarray] = {}
        root, cells = args.root, {d.name: study_cell(args.root, d, gt_cache) for d in cell_dirs}
        machine, rebuilt_with = machine_line(), ""
    print_and_write(args.write or "", report(root, cells, command, machine, rebuilt_with),
                    {"root": str(root), "command": command, "machine": machine, "cells": cells}, bool(args.write))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
