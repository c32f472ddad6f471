"""Re-judge the learning rounds of finished Table I cells with today's acceptance test (not a test).

The harness prunes each cell's memories, so round 0's raw downsampled scans (what the test places
with each round's trajectory) are made again: ``python -m gr_graph.slam --config CELL/config.yaml
--rounds 0`` into a scratch folder, checked byte for byte against the cell's published round-0 poses.
Each learning round is then judged against its recorded reference round from its published poses
and summary (:func:`gr_graph.round_acceptance.round_figures`, :func:`decide`), and set beside its
recorded verdict: whether the recomputed window entropies reproduce the recorded ones, the verdict,
the smallest share of the reference's measurable points a window kept and the worst creep against
round 0's standstills (the two rules added on 2026-12-06), and the mean entropy rise against round 0
(tested since 2026-12-07). ``--full-coverage`` places the windows side by side over the whole run instead of the
default 60.

Run::

    python benchmarks/rejudge_acceptance.py --root ROOT --scratch DIR [--cells 16ch-s0 ...] [--full-coverage] [--write]

``ROOT`` is a harness root (``ROOT/table1/<cell>/slam``); ``--write`` writes
``benchmarks/results/acceptance_rejudge[_full].md`` and ``.json``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from gr_graph.config import AcceptanceConfig
from gr_graph.memory import load_memory
from gr_graph.round_acceptance import decide, round_figures
from gr_graph.round_output import read_round_poses

from results_io import print_and_write


def remake_round0(cell_dir: Path, scratch: Path) -> Path:
    """Round 0 of the cell again (its memory holds the raw scans); its folder."""
    out = scratch / cell_dir.parent.name
    if not (out / "round_0" / "memory").is_dir():
        subprocess.run([sys.executable, "-m", "gr_graph.slam", "--config", str(cell_dir / "config.yaml"),
                        "--rounds", "0", "--out", str(out), "--no-progress", "--log-level", "WARNING"], check=True)
    published = (cell_dir / "round_0" / "poses_kitti.txt").read_bytes()
    if (out / "round_0" / "poses_kitti.txt").read_bytes() != published:
        raise SystemExit(f"{out}: round 0 differs from the published {cell_dir / 'round_0'}: not the same scans")
    return out


def rejudge(cell_dir: Path, scans: list[np.ndarray], cfg: AcceptanceConfig, full: bool) -> list[dict]:
    """One row per learning round of the cell."""
    figures: dict[int, dict] = {}

    def figure(r: int) -> dict:
        if r not in figures:
            rd = cell_dir / f"round_{r}"
            figures[r] = round_figures(scans, read_round_poses(rd), rd, json.loads((rd / "round.json").read_text()), cfg)
        return figures[r]

    rows = []
    for rd in sorted(cell_dir.glob("round_*"), key=lambda p: int(p.name.split("_")[1])):
        r = int(rd.name.split("_")[1])
        summary = json.loads((rd / "round.json").read_text()) if (rd / "round.json").is_file() else {}
        recorded = summary.get("acceptance")
        if r == 0 or not recorded:
            continue
        reference = recorded["reference_round"]
        v = decide(figure(r), figure(reference), cfg, round0=figure(0) if reference != 0 else None)
        creep0 = (v["standstill_round_0"] or v["standstill"] or {}).get("worst_creep_per_frame_m")
        same = None if full else bool(np.allclose(np.asarray(figure(r)["entropy"], float),
                                                  np.asarray(recorded["window_entropy"], float),
                                                  atol=1e-4, equal_nan=True))
        rows.append({"cell": cell_dir.parent.name, "round": r, "reference": recorded["reference_round"],
                     "recorded_accepted": summary.get("accepted"), "accepted": v["accepted"], "reasons": v["reasons"],
                     "windows": cfg.n_windows, "entropies_reproduced": same,
                     "mean_entropy_increase": v["mean_entropy_increase"],
                     "window_entropy_increase": v["window_entropy_increase"],
                     "worst_window_measurable_fraction": v["worst_window_measurable_fraction"],
                     "worst_creep_vs_round_0_m": creep0,
                     "mean_entropy_increase_vs_round_0": (v["map_sharpness_round_0"] or v)["mean_entropy_increase"]})
    return rows


def _nats(value: float | None) -> str:
    return "n/a" if value is None else f"{value:+.4f}"


def _mm(metres: float | None) -> str:
    return "-" if metres is None else f"{1e3 * metres:.3f}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", type=Path, required=True, help="harness root (ROOT/table1/<cell>/slam)")
    ap.add_argument("--scratch", type=Path, required=True, help="where round 0 of each cell is made again")
    ap.add_argument("--cells", nargs="+", default=None, help="cells (default: every table1 cell of the root)")
    ap.add_argument("--full-coverage", action="store_true", help="windows side by side over the whole run")
    ap.add_argument("--write", action="store_true")
    args = ap.parse_args(argv)
    if not (args.root / "table1").is_dir():
        raise SystemExit(f"{args.root}: no table1/ folder (not a harness root of `python -m gr_graph.experiments table1`)")
    all_cells = sorted(p.name for p in (args.root / "table1").iterdir() if (p / "slam").is_dir())
    cells = args.cells or all_cells
    rows = []
    for cell in cells:
        cell_dir = args.root / "table1" / cell / "slam"
        scans = load_memory(remake_round0(cell_dir, args.scratch) / "round_0" / "memory").scans()
        cfg = AcceptanceConfig()
        if args.full_coverage:
            cfg = cfg.model_copy(update={"n_windows": int(np.ceil(len(scans) / (2 * cfg.half_window + 1)))})
        rows += rejudge(cell_dir, scans, cfg, args.full_coverage)
    changed = sum(r["accepted"] != r["recorded_accepted"] for r in rows)
    windows = "windows over the whole run" if args.full_coverage else "default windows"
    lines = [f"# Published learning rounds re-judged ({windows})",
             "", f"`python benchmarks/rejudge_acceptance.py --root ROOT --scratch DIR"
             f"{' --full-coverage' if args.full_coverage else ''}"
             f"{' --cells ' + ' '.join(cells) if cells != all_cells else ''}` on {args.root.name} ({len(cells)} cells); "
             f"{changed} of {len(rows)} verdicts differ from the recorded ones.", "",
             "| cell | round (reference) | windows | recorded | now | entropies reproduced | mean / q0.9 entropy rise "
             "(nats) | mean entropy rise vs round 0 | worst window measurable share | worst creep vs round 0 (mm/frame) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['cell']} | {r['round']} ({r['reference']}) | {r['windows']} | {r['recorded_accepted']} | "
                     f"{r['accepted']}{' (' + '; '.join(r['reasons']) + ')' if r['reasons'] else ''} | "
                     f"{'-' if r['entropies_reproduced'] is None else r['entropies_reproduced']} | "
                     f"{_nats(r['mean_entropy_increase'])} / {_nats(r['window_entropy_increase'])} | "
                     f"{_nats(r['mean_entropy_increase_vs_round_0'])} | "
                     f"{r['worst_window_measurable_fraction']:.3f} | {_mm(r['worst_creep_vs_round_0_m'])} |")
    name = "acceptance_rejudge_full" if args.full_coverage else "acceptance_rejudge"
    settings = AcceptanceConfig().model_dump(mode="json")
    if args.full_coverage:
        settings["n_windows"] = "enough to cover each run (per cell)"
    print_and_write(name, "\n".join(lines), {"root": args.root.name, "cells": cells, "full_coverage": args.full_coverage,
                                              "acceptance_settings": settings, "rows": rows}, args.write)
    return 0


if __name__ == "__main__":
    sys.exit(main())
