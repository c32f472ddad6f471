"""Table I's 16-channel window cells with fewer training epochs per round (not a test).

The speed target needs cheaper learning rounds; the cheapest lever is the number of epochs
(training is most of a round). This runs the Table I 16-channel window cell's configuration
(``gr_graph.experiments.cells``: frames 0:1500, the ``kitti`` preset, 2 rounds, every round
computed, world and training seed paired) with ``--epochs`` instead of the budget's 3, and
compares each seed with the published Table I record of the same seed
(``benchmarks/results/cells/paper/table1/16ch-sS.json``).

Run::

    python benchmarks/training_budget_study.py run --seed S --epochs 1 --root ROOT    # one cell, resumable
    python benchmarks/training_budget_study.py report --epochs 1 --root ROOT [--write]

``--write`` writes ``benchmarks/results/training_budget.md`` and ``training_budget.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"
RECORDS = RESULTS / "cells" / "paper" / "table1"
METRICS = ("rpe300_all_pairs_mean", "rpe300_consecutive_mean", "ate_rmse", "kitti_t_err_percent")


def run_dir(root: Path, epochs: int, seed: int) -> Path:
    return root / f"e{epochs}-s{seed}"


def run(seed: int, epochs: int, root: Path) -> None:
    """One Table I 16-channel window cell with ``epochs`` per round (resumes a finished round)."""
    from gr_graph.config import load_config
    from gr_graph.experiments.cells import BUDGETS, TABLE1_WINDOW, _slam_overrides
    from gr_graph.pipeline import SlamPipeline

    budget = dataclasses.replace(BUDGETS["paper"], epochs=epochs)
    out = {"out_dir": str(run_dir(root, epochs, seed)), "progress": False, "plot": False, "write_memory": True,
           "resume": True}
    cfg = load_config(None, {**_slam_overrides(budget, seed, 16, TABLE1_WINDOW, 2), "device": "cpu", "output": out})
    SlamPipeline(cfg).run()


def seed_rows(root: Path, epochs: int) -> list[dict]:
    """Per seed with a finished run: rounds 1 and 2 of both budgets, and the training steps."""
    rows = []
    for d in sorted(root.glob(f"e{epochs}-s*")):
        metrics = d / "metrics.json"
        seed = int(d.name.split("-s")[1])
        record = RECORDS / f"16ch-s{seed}.json"
        if not metrics.is_file() or not record.is_file():
            continue
        m, rec = json.loads(metrics.read_text())["rounds"], json.loads(record.read_text())["rounds"]
        if "2" not in m:
            continue
        row = {"seed": seed, "rounds": {}}
        for r in ("0", "1", "2"):
            row["rounds"][r] = {"fewer": {k: m[r]["slam"][k] for k in METRICS} | {"accepted": m[r]["accepted"]},
                                "published": {k: rec[r]["slam"][k] for k in METRICS} | {"accepted": rec[r]["accepted"]}}
        steps = []
        for r in ("1", "2"):
            s = json.loads((d / f"round_{r}" / "training" / "summary.json").read_text())
            steps.append(s["runtime_s"]["steps"])
        row["training_steps"] = steps
        rows.append(row)
    return rows


def report(rows: list[dict], epochs: int) -> str:
    lines = [f"| seed | round | RPE-300 all pairs [m], {epochs} epoch(s) / 3 | ATE RMSE [m], {epochs} / 3 "
             f"| KITTI [%], {epochs} / 3 | accepted, {epochs} / 3 |", "|---|---|---|---|---|---|"]
    for row in rows:
        for r in ("0", "1", "2"):
            a, b = row["rounds"][r]["fewer"], row["rounds"][r]["published"]
            lines.append(f"| {row['seed']} | {r} | {a['rpe300_all_pairs_mean']:.3f} / {b['rpe300_all_pairs_mean']:.3f} "
                         f"| {a['ate_rmse']:.3f} / {b['ate_rmse']:.3f} | {a['kitti_t_err_percent']:.3f} / "
                         f"{b['kitti_t_err_percent']:.3f} | {a['accepted']} / {b['accepted']} |")
    if len(rows) >= 2:
        lines += ["", f"Mean ± std over {len(rows)} seeds (sample std):", "",
                  f"| round | RPE-300 all pairs [m], {epochs} epoch(s) | 3 epochs | ATE [m], {epochs} | 3 |",
                  "|---|---|---|---|---|"]
        for r in ("1", "2"):
            def ms(which: str, key: str) -> str:
                v = np.array([row["rounds"][r][which][key] for row in rows])
                return f"{v.mean():.3f} ± {v.std(ddof=1):.3f}"
            lines.append(f"| {r} | {ms('fewer', 'rpe300_all_pairs_mean')} | {ms('published', 'rpe300_all_pairs_mean')} "
                         f"| {ms('fewer', 'ate_rmse')} | {ms('published', 'ate_rmse')} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run")
    r.add_argument("--seed", type=int, required=True)
    r.add_argument("--epochs", type=int, default=1)
    r.add_argument("--root", type=Path, required=True)
    p = sub.add_parser("report")
    p.add_argument("--epochs", type=int, default=1)
    p.add_argument("--root", type=Path, required=True)
    p.add_argument("--write", action="store_true")
    args = ap.parse_args(argv)
    if args.command == "run":
        logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
        run(args.seed, args.epochs, args.root)
        return 0
    rows = seed_rows(args.root, args.epochs)
    text = report(rows, args.epochs)
    print(text)
    if args.write:
        from gr_graph.atomic import atomic_write_json, atomic_write_text
        from gr_graph.provenance import machine_line

        atomic_write_json(RESULTS / "training_budget.json", {"machine": machine_line(), "epochs": args.epochs,
                                                             "seeds": rows})
        atomic_write_text(RESULTS / "training_budget.md", f"# Table I, 16 channels, frames 0:1500: {args.epochs} "
                          "training epoch(s) per round against the published 3\n\n"
                          f"Command: `python benchmarks/training_budget_study.py run --seed S --epochs {args.epochs} "
                          f"--root ROOT` for S in {' '.join(str(r['seed']) for r in rows)}, then `report`. "
                          f"Machine: {machine_line()}.\n\n"
                          + text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
