"""The report of a table: markdown + JSON in ``ROOT/<table>/`` (and, with ``publish``, in
``benchmarks/results/<table>.md`` with its figures in ``benchmarks/results/figures/``; another
budget than ``paper`` publishes ``<table>_<budget>.md``, figures prefixed likewise).

Every report states the exact command, the seeds, the budget (cells, frames, seeds, estimated
and measured time), the machine, which cells are missing, and the conventions of
:mod:`gr_graph.experiments.aggregate`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from gr_graph.atomic import atomic_write_bytes, atomic_write_json, atomic_write_text, read_json_or_none
from gr_graph.experiments import aggregate as agg
from gr_graph.experiments.cells import ABLATIONS, PAPER_REDUCTIONS, Budget, Cell
from gr_graph.experiments.records import RecordSet, read_records, write_records
from gr_graph.provenance import machine_line
from gr_graph.experiments.run_cell import (METRIC_KEYS, NEES_KEYS, SHORT_RANGE_KEYS, cell_dir, cell_wall_s,
                                          read_cell_result, reused_from_source, with_noise_consistency,
                                          with_short_range_rpe)

log = logging.getLogger(__name__)

__all__ = ["write_report", "published_name", "publish_records", "local_results", "RESULTS_DIR", "budget_lines", "machine_line"]

RESULTS_DIR = Path(__file__).resolve().parents[2] / "benchmarks" / "results"


def budget_lines(table: str, budget: Budget, cells: list[Cell], results: dict[str, dict[str, Any]]) -> list[str]:
    """The budget paragraph: cells, frames, seeds, estimated and measured time."""
    est = sum(c.est_minutes for c in cells)
    done = [results[c.key] for c in cells if c.key in results]
    cpu = sum(d.get("cpu_s", 0.0) for d in done) / 60.0
    wall = sum(cell_wall_s(d) for d in done) / 60.0
    frames = sorted({f"{c.frames[0]}:{c.frames[1]}" for c in cells})
    lines = [f"- budget `{budget.name}`: {len(cells)} cells ({len(done)} finished), frames {', '.join(frames)}, "
             f"seeds {', '.join(map(str, budget.seeds))} (world seed i paired with training seed i), "
             f"{budget.epochs} training epochs per round"
             + (f", {budget.n_pairs} pairs per registration cell" if table == "table2" else ""),
             f"- estimated time of all cells: {est:.0f} min ({est / 60:.1f} h) on 2 cores (rough: per-frame "
             f"costs measured on the Table I cells run alone); measured on the finished cells: wall {wall:.1f} min "
             f"(with the time of resumed rounds), CPU {cpu:.1f} min (of each cell's last call only: a resumed "
             "cell's earlier calls are not counted)"]
    missing = [f"{i} `{c.key}`" for i, c in enumerate(cells) if c.key not in results]
    if missing:
        lines.append(f"- **missing cells** (not finished): {', '.join(missing)}")
    return lines


def _header(table: str, title: str, budget: Budget, root: Path | str, cells: list[Cell],
            results: dict[str, dict[str, Any]], command: str) -> list[str]:
    return [f"# {title}", "",
            f"Command: `{command}` (one cell: add `--cell K`; `--list` shows the cells). Results in `{root}`.", "",
            *budget_lines(table, budget, cells, results),
            f"- machine: {machine_line()}",
            f"- written {datetime.now(timezone.utc).isoformat(timespec='minutes')}; data: synthetic sequence "
            "(generated route, `kitti` sensor preset), world and training seeds paired",
            "- mean ± std over seeds (sample std, ddof=1; `(n=1)`: one seed, no spread)"
            + ("; relative reductions are computed per seed against the same seed's raw round, then averaged"
               if table == "table1" else ""),
            *([f"- **smoke budget**: {budget.window[1] - budget.window[0]} frames, {budget.epochs} epoch(s), a tiny "
               "network: tests the machinery, the figures are no evidence for or against the method"]
              if budget.name == "smoke" else []), ""]


def _table1_md(summary: dict[str, Any], acceptance: bool) -> list[str]:
    lines: list[str] = []
    if not acceptance:
        lines += ["Note: no round carries an `accepted` flag (round acceptance not implemented in this "
                  "pipeline): every round counts as accepted, so \"2-step guarded\" equals \"2-step\".", ""]
    for g, s in summary.items():
        lines += [f"## {g}: {s['channels']} channels, frames {s['frames'][0]}:{s['frames'][1]}, "
                  f"seeds {', '.join(map(str, s['seeds']))}", "",
                  "| step | " + " | ".join(agg.METRIC_LABELS[k] for k in METRIC_KEYS) + " |",
                  "|---|" + "---|" * len(METRIC_KEYS)]
        for step, d in s["steps"].items():
            lines.append(f"| {step} | " + " | ".join(agg.fmt_ms(d[k]) for k in METRIC_KEYS) + " |")
        if s.get("kiss_icp"):
            lines.append("| KISS-ICP 1.3.0 | " + " | ".join(agg.fmt_ms(s["kiss_icp"][k]) for k in METRIC_KEYS) + " |")
        lines += ["", "Relative reduction vs raw (per seed, then mean ± std; positive = better):", "",
                  "| step | " + " | ".join(agg.METRIC_LABELS[k].split(" [")[0] for k in METRIC_KEYS)
                  + " | paper (RPE-300) |", "|---|" + "---|" * (len(METRIC_KEYS) + 1)]
        paper = s.get("paper_reduction") or {}
        for step, d in s["steps"].items():
            if step == "raw":
                continue
            nominal = {"1-step": 1, "2-step": 2, "2-step guarded": 2}[step]
            p = paper.get(nominal)
            lines.append(f"| {step} | " + " | ".join(agg.fmt_ms(d[f"reduction_{k}"], "{:.1f}", pct=True)
                                                     for k in METRIC_KEYS)
                         + f" | {'n/a' if p is None else f'{p} %'} |")
        notes = [n for d in s["steps"].values() for n in d["notes"]]
        if notes:
            lines += ["", "Notes: " + "; ".join(sorted(set(notes)))]
        a = s["acceptance_2x2"]
        if acceptance:
            lines += ["", "Round acceptance vs ground truth (RPE-300 all pairs vs the last accepted round, the one "
                      "the test judged against; equal counts as worse): accepted "
                      f"& better {a['accepted_better']}, accepted & worse {a['accepted_worse']}, rejected & "
                      f"better {a['rejected_better']}, rejected & worse {a['rejected_worse']}."]
        lines.append("")
        rows = [(g, step, d) for step, d in s["steps"].items()]
        lines += _short_range_md(rows, heading="###") + _nees_md(rows, heading="###")
    return lines


def _runtime_md(cells: list[Cell], results: dict[str, dict[str, Any]]) -> list[str]:
    """Where the wall time of each finished SLAM cell went (``runtime_s`` of its rounds), in minutes."""
    rows = []
    for c in cells:
        d = results.get(c.key)
        if c.kind != "slam" or d is None or not d.get("rounds"):
            continue
        rounds = {int(k): v.get("runtime_s") or {} for k, v in d["rounds"].items()}
        learning = [r for r in sorted(rounds) if r > 0]

        def minutes(r: int, key: str) -> str:
            v = rounds.get(r, {}).get(key)
            return "" if v is None else f"{v / 60:.1f}"

        kiss = (d.get("kiss_icp") or {}).get("wall_s")
        peak = d.get("peak_rss_mb")
        # ablations: work taken from the seed's default cell, timed there (what the cell recorded it took)
        reused = reused_from_source(d["reuse"] if "reuse" in d else {"what": c.params.get("reuse")})
        round0 = "reused" if "round_0" in reused else minutes(0, "total")
        training = ["reused" if r == 1 and "round_1/training" in reused else minutes(r, "training") for r in learning]
        rows.append(f"| {c.key} | {c.frames[1] - c.frames[0]} | {cell_wall_s(d) / 60:.1f} | "
                    f"{round0} | {', '.join(training)} | "
                    f"{', '.join(minutes(r, 'total') for r in learning)} | {'' if kiss is None else f'{kiss / 60:.1f}'} | "
                    f"{'' if peak is None else f'{peak / 1024:.1f}'} |")
    if not rows:
        return []
    return ["## Time per stage", "",
            "Wall minutes of each finished cell on its machine (records name it; for a cell resumed after an "
            "interruption, with the recorded time of the rounds finished in earlier calls): round 0 (rendering, SLAM, "
            "memory), each learning round's training and its SLAM (rendering again, the network on every frame, "
            "densification, SLAM; \"reused\": taken from another cell and timed there), the KISS-ICP "
            "baseline (rendering again); the process's peak resident memory in GiB (recorded since 2026-12-03; the "
            "peak of the whole process so far: with several cells run by one command, an upper bound that may be "
            "an earlier cell's; `--cell K` gives each cell its own). "
            "Cells run beside other work are slower.", "",
            "| cell | frames | wall | round 0 | training (rounds 1, 2, ...) | learning-round SLAM (rounds 1, 2, ...) "
            "| KISS-ICP | peak memory [GiB] |", "|---|---|---|---|---|---|---|---|", *rows, ""]


def _percent(value: float | None) -> str:
    """A success rate [%] of one seed, ``n/a`` when no pair was evaluated."""
    return "n/a" if value is None else f"{value:.0f}"


def _seed_percent(per_seed: dict[str, Any]) -> str:
    """One seed's success rate, labelled: ``s0 72``."""
    return f"s{per_seed['seed']} {_percent(per_seed['success_percent'])}"


def _table2_md(summary: dict[str, Any]) -> list[str]:
    lines = ["Success = rotation error < 10° and translation error < 2 m, pairs within 10 m (ground truth), "
             "sampled with the world seed; the same pairs for every step of a seed.", "",
             "| channels | step | solver | success [%] | per seed | paper |", "|---|---|---|---|---|---|"]
    unpaired = []
    for ch, s in summary.items():
        paper = s.get("paper") or {}
        seeds = {}
        for step, solvers in s["steps"].items():
            for solver, row in solvers.items():
                pap = paper.get("raw") if step == "raw" else None
                seeds[f"{step} ({solver})"] = sorted({q["seed"] for q in row["per_seed"]
                                                      if q["success_percent"] is not None})
                lines.append(f"| {ch} | {step} | {solver} | {agg.fmt_ms(row, '{:.1f}')} | "
                             f"{', '.join(_seed_percent(q) for q in row['per_seed'])} | "
                             f"{'' if pap is None else f'raw {pap:.0f}'} |")
        for solver, b in s["best_step"].items():
            lines.append(f"| {ch} | best densified step | {solver} | {b['mean']:.1f} ({b['step']}) | | "
                         f"{'best step %.0f' % paper['best_step'] if paper else ''} |")
        if len({tuple(v) for v in seeds.values()}) > 1:
            unpaired.append(f"{ch} channels: " + "; ".join(f"{row} seeds {', '.join(map(str, v)) or 'none'}"
                                                          for row, v in seeds.items()))
    lines.append("")
    if unpaired:  # a step's mean over other seeds than another's: its difference is not the densification's alone
        lines += ["Steps measured on different seeds (cells missing): " + " / ".join(unpaired) + ".", ""]
    return lines


def _short_range_md(rows: list[tuple[str, str, dict[str, Any]]], heading: str = "##") -> list[str]:
    """The short-range accuracy table: per (name, step, step summary) the mean translational RPE over
    1 and 10 frames ± std over seeds, and its reduction against round 0."""
    if not any(d.get(k, {}).get("n") for _, _, d in rows for k in SHORT_RANGE_KEYS):
        return []
    lines = [f"{heading} Short-range accuracy (RPE over 1 and 10 frames)", "",
             "Mean translational RPE of the SLAM trajectory over every pair of frames 1 and 10 apart (frame-to-frame "
             "registration, local maps), then mean ± std over seeds; reduction against the same seed's round 0 "
             "(positive = better). RPE-300 measures drift; a round can reduce drift and still register "
             "consecutive frames worse.", "",
             "| run | step | " + " | ".join(agg.SHORT_RANGE_LABELS[k] for k in SHORT_RANGE_KEYS) + " | "
             + " | ".join(f"reduction {agg.SHORT_RANGE_LABELS[k].split(' [')[0]}" for k in SHORT_RANGE_KEYS) + " |",
             "|---|---|" + "---|" * (2 * len(SHORT_RANGE_KEYS))]
    for name, step, d in rows:
        reductions = [("" if step == "raw" else agg.fmt_ms(d.get(f"reduction_{k}"), "{:.1f}", pct=True))
                      for k in SHORT_RANGE_KEYS]
        lines.append(f"| {name} | {step} | " + " | ".join(agg.fmt_ms(d.get(k), "{:.4f}") for k in SHORT_RANGE_KEYS)
                     + " | " + " | ".join(reductions) + " |")
    return lines + [""]


def _nees_md(rows: list[tuple[str, str, dict[str, Any]]], heading: str = "##") -> list[str]:
    """The noise-consistency table: per (name, step, step summary) the mean NEES ± std over seeds."""
    if not any(d.get(k, {}).get("n") for _, _, d in rows for k in NEES_KEYS):
        return []
    ideal = ", ".join(f"{agg.NEES_LABELS[k].split(' [')[0]} {agg.NEES_IDEAL[k]}" for k in NEES_KEYS)
    lines = [f"{heading} Noise consistency (NEES against ground truth)", "",
             "Mean NEES of a run (`python -m gr_graph.noise_consistency RUN`: edges `xi^T Lambda xi` with the "
             "information the graph used, flagged registrations left out; positions against the marginals), "
             "then mean ± std over seeds; the NEES target is within a factor 2 of the ideal (above: over-confident, "
             "below: conservative). Odometry path error: the length of the path the odometry edges measure "
             f"against ground truth (negative: motion under-estimated). Ideal: {ideal}.", "",
             "| run | step | " + " | ".join(agg.NEES_LABELS[k] for k in NEES_KEYS) + " |",
             "|---|---|" + "---|" * len(NEES_KEYS)]
    for name, step, d in rows:
        lines.append(f"| {name} | {step} | " + " | ".join(agg.fmt_ms(d.get(k), "{:.3g}") for k in NEES_KEYS) + " |")
    return lines + [""]


def _ablations_md(summary: dict[str, Any]) -> list[str]:
    keys = ("rpe300_all_pairs_mean", "rpe300_consecutive_mean", "ate_rmse", "kitti_t_err_percent")
    lines = ["\"2-step guarded\": the last round whose learning rounds were all accepted by the GT-free test "
             "(round 0 when round 1 was rejected); \"2-step\": round 2 as computed. Every cell of a seed shares "
             "round 0 (raw scans, registration-Hessian edge noise).", "",
             "## Against round 0: what the learning rounds bring", "",
             "Reduction against the same seed's round 0, per seed, then mean ± std over seeds (positive = the "
             "rounds helped); acceptance: the learning rounds' 2x2 count (accepted/rejected x better/worse than "
             "the last accepted round, the one the test judged against, by all-pairs RPE-300; equal counts as worse).", "",
             "| ablation | step | " + " | ".join(agg.METRIC_LABELS[k].split(" [")[0] for k in keys)
             + " | accepted better / worse | rejected better / worse |", "|---|---|" + "---|" * (len(keys) + 2)]
    if summary:
        first = next(iter(summary.values()))["steps"].get("raw")
        if first is not None:
            lines.append("| round 0 (all) | raw | " + " | ".join(agg.fmt_ms(first[k]) for k in keys) + " | | |")
    for name, s in summary.items():
        a = s.get("acceptance_2x2") or {}
        for step in ("1-step", "2-step", "2-step guarded"):
            d = s["steps"].get(step)
            if d is None or f"reduction_{keys[0]}" not in d:
                continue
            acc = (f"{a.get('accepted_better', 0)} / {a.get('accepted_worse', 0)} | "
                   f"{a.get('rejected_better', 0)} / {a.get('rejected_worse', 0)}") if step == "1-step" else " | "
            lines.append(f"| {name} | {step} | "
                         + " | ".join(agg.fmt_ms(d[f"reduction_{k}"], "{:.1f}", pct=True) for k in keys)
                         + f" | {acc} |")
    lines += ["", "Difference to the default cell of the same seed (ablation − default; negative = the ablation "
              "is better), mean ± std over seeds; **bold**: all seeds agree in sign, |mean| > std and |mean| > "
              f"{agg.MIN_RELATIVE_GAP:.1%} of the default's value (the rule for changing a default; smaller gaps are "
              "float noise).", ""]
    for step in ("1-step", "2-step", "2-step guarded"):
        lines += [f"## {step}", "", "| ablation | " + " | ".join(agg.METRIC_LABELS[k] for k in keys) + " | "
                  + " | ".join(f"Δ {agg.METRIC_LABELS[k].split(' [')[0]}" for k in keys) + " |",
                  "|---|" + "---|" * (2 * len(keys))]
        for name, s in summary.items():
            d = s["steps"].get(step)
            if d is None:
                continue
            diffs = []
            for k in keys:
                t = agg.fmt_ms(d[f"diff_{k}"]) if name != "default" else "—"
                diffs.append(f"**{t}**" if d[f"diff_{k}"].get("consistent") else t)
            lines.append(f"| {name}: {ABLATIONS.get(name, (s['what'],))[0]} | "
                         + " | ".join(agg.fmt_ms(d[k]) for k in keys) + " | " + " | ".join(diffs) + " |")
        lines.append("")
    first = next(iter(summary), None)  # every cell of a seed shares round 0: its row once
    rows = [("round 0 (all)" if step == "raw" else name, step, d) for name, s in summary.items()
            for step, d in s["steps"].items() if step != "raw" or name == first]
    lines += _short_range_md(rows)
    lines += _nees_md(rows)
    reuse = {n: s["reuse"] for n, s in summary.items() if any(v for v in s["reuse"].values())}
    if reuse:
        lines += ["Reuse: " + "; ".join(f"{n} seed {seed}: {r.get('copied') or r.get('note')}"
                                        for n, rs in reuse.items() for seed, r in rs.items() if r), ""]
    notes = sorted({f"{n} seed {p['seed']}: {p['note']}" for n, s in summary.items() for st in s["steps"].values()
                    for p in st["per_seed"] if p.get("note")})
    if notes:
        lines += ["Notes: " + "; ".join(notes), ""]
    return lines


def _figures(table: str, root: Path, cells: list[Cell], results: dict[str, dict[str, Any]],
             summary: dict[str, Any], device: str, stem: str) -> dict[str, Path]:
    from gr_graph.experiments import figures as fig

    out: dict[str, Path] = {}
    fdir = root / table / "figures"

    def add(name: str, draw: Callable[[], Path | None]) -> None:
        """A picture that cannot be drawn (a damaged file of one cell) is logged and left out, not the report."""
        try:
            p = draw()
        except Exception as exc:  # noqa: BLE001 (any reader or plotting error)
            log.warning("%s: figure %r left out of the report: %s: %s", table, name, type(exc).__name__, exc)
            return
        if p is not None:
            out[name] = p

    if table == "table1":
        add("error over rounds (RPE-300, ATE)", lambda: fig.plot_rpe_over_rounds(summary, fdir / f"{stem}_rpe_over_rounds.png"))
        for c in cells:
            if c.key in results and c.seed == cells[0].seed:
                add(f"trajectories {c.key}", lambda c=c: fig.plot_round_trajectories(
                    cell_dir(root, c), fdir / f"{stem}_trajectories_{c.key}.png",
                    title=f"{c.what}: each round against ground truth"))
        c32 = next((c for c in cells if c.channels == 32 and c.key in results), None)
        if c32 is not None:
            add("raw vs densified 32-channel scan",
                lambda: _raw_vs_densified(root, c32, fdir / f"{stem}_raw_vs_densified_32ch.png", device))
    return out


def _raw_vs_densified(root: Path, cell: Cell, path: Path, device: str) -> Path | None:
    """One scan of a 32-channel cell (middle of the window), raw and densified with round 1's model."""
    from gr_graph.config import load_config
    from gr_graph.densify import densified_sequence
    from gr_graph.experiments.figures import plot_raw_vs_densified
    from gr_graph.experiments.run_cell import open_cell_sequence

    slam = cell_dir(root, cell) / "slam"
    model = slam / "round_1" / "training" / "model.pt"
    if not model.is_file():
        return None
    if path.is_file() and path.stat().st_mtime > model.stat().st_mtime:
        return path  # rendering a frame again is not free: keep a picture newer than the model
    cfg = load_config(slam / "config.yaml", {"device": device})
    seq, _ = open_cell_sequence(cfg)
    k = len(seq) // 2
    dense = densified_sequence(seq, model, cfg.training, device=device, preprocess=cfg.preprocess)
    return plot_raw_vs_densified(seq[k].points, dense[k].points, path,
                                 title=f"32 channels, frame {cell.frames[0] + k}, seed {cell.seed}: raw vs densified "
                                       f"(round-1 model, tau_ani {cfg.training.tau_ani}, "
                                       f"M = {cfg.training.samples_per_point})")


TITLES = {"table1": "Table I: trajectory error over learning rounds, gr_graph vs KISS-ICP",
          "table2": "Table II: global registration on raw and densified scans",
          "ablations": "Ablations: what the self-supervised learning contributes (16 channels)"}


def published_name(table: str, budget: Budget) -> str:
    """File stem of a published table: ``table1`` for the paper budget, ``table1_student-t`` for another."""
    return table if budget.name == "paper" else f"{table}_{budget.name}"


def write_report(table: str, root: str | Path, budget: Budget, cells: list[Cell], command: str,
                 publish: bool = False, device: str = "cpu", records_dir: str | Path | None = None) -> Path:
    """Aggregate the finished cells of ``table``; write ``ROOT/<table>/report.md`` and
    ``report.json`` (and publish them); return the markdown path.

    ``records_dir`` (e.g. :data:`gr_graph.experiments.records.RECORDS_DIR`): cells not finished
    in ``root`` are taken from the published records there whose definition is current (the
    report names them and their commits); None: only ``root``. ``publish`` also writes a record
    of every cell finished in ``root`` to ``RESULTS_DIR/cells``.
    """
    root = Path(root)
    local = local_results(root, cells)
    recs = read_records(records_dir, budget.name, cells) if records_dir is not None else None
    recorded = {k: v for k, v in (recs.results if recs else {}).items() if k not in local}
    results = {c.key: local.get(c.key, recorded.get(c.key)) for c in cells if c.key in local or c.key in recorded}
    res_list = [results[c.key] for c in cells if c.key in results]
    lines: list[str] = []
    if table == "table1":
        summary = agg.table1_summary(res_list)
        lines += _table1_md(summary, agg.acceptance_recorded(res_list))
        lines += ["Paper (Table I, relative RPE-300 reduction vs raw): "
                  + "; ".join(f"{ch} ch: 1-step {v[1]} %, 2-step {v[2]} %" for ch, v in PAPER_REDUCTIONS.items()), ""]
    elif table == "table2":
        summary = agg.table2_summary(res_list)
        lines += _table2_md(summary)
    else:
        summary = agg.ablation_summary(res_list)
        lines += _ablations_md(summary)
    lines += _runtime_md(cells, results)
    name = published_name(table, budget)
    figs = _figures(table, root, cells, local, summary, device, name)  # pictures need the cells' files
    md_dir = root / table
    pub_dir = RESULTS_DIR
    fig_lines = list(figs.items())
    fig_md = ["## Figures", ""] + [f"![{n}](figures/{p.name})" for n, p in fig_lines] + [""] if fig_lines else []

    def document(shown_command: str, fig_paths: dict[str, str]) -> dict[str, Any]:
        return {"table": table, "command": shown_command, "budget": budget.name, "seeds": list(budget.seeds),
                "machine": machine_line(), "cells": {c.key: {"index": i, "done": c.key in results, "what": c.what,
                                                             "est_minutes": c.est_minutes,
                                                             "from_record": c.key in recorded}
                                                     for i, c in enumerate(cells)},
                "summary": summary, "figures": fig_paths}

    provenance_md = _provenance_lines(cells, local, recorded, recs)
    header = _header(table, TITLES[table], budget, root, cells, results, command)[:-1] + provenance_md + [""]
    atomic_write_json(md_dir / "report.json", document(command, {k: str(v) for k, v in figs.items()}))
    md = atomic_write_text(md_dir / "report.md", "\n".join(header + lines + fig_md) + "\n")
    if publish:
        # The published copy names no path of this machine: the root reads ROOT, figures are relative.
        pub_command = command.replace(f"--root {root}", "--root ROOT")
        pub_header = _header(table, TITLES[table], budget, "ROOT", cells, results, pub_command)[:-1] + provenance_md + [""]
        (pub_dir / "figures").mkdir(parents=True, exist_ok=True)
        for _, p in fig_lines:
            atomic_write_bytes(pub_dir / "figures" / p.name, p.read_bytes())
        atomic_write_text(pub_dir / f"{name}.md", "\n".join(pub_header + lines + fig_md) + "\n")
        atomic_write_json(pub_dir / f"{name}.json",
                          document(pub_command, {k: f"figures/{v.name}" for k, v in figs.items()}))
        publish_records(root, budget, cells, local)
    return md


def local_results(root: str | Path, cells: list[Cell]) -> dict[str, dict[str, Any]]:
    """The cells finished in ``root`` (key -> ``cell.json`` with the noise consistency and the short-range
    RPE of every round)."""
    return {c.key: with_short_range_rpe(root, c, with_noise_consistency(root, c, r))
            for c in cells if (r := read_cell_result(root, c)) is not None}


def publish_records(root: str | Path, budget: Budget, cells: list[Cell],
                    local: dict[str, dict[str, Any]] | None = None) -> list[Path]:
    """Write a record of every cell finished in ``root`` to ``RESULTS_DIR/cells`` (no table);
    ``local``: :func:`local_results` when already computed. Returns the written paths."""
    local = local_results(root, cells) if local is None else local
    slam_metrics = {c.key: read_json_or_none(cell_dir(root, c) / "slam" / "metrics.json") for c in cells
                    if c.key in local}
    return write_records(RESULTS_DIR / "cells", budget.name, cells, local, slam_metrics)


def _provenance_lines(cells: list[Cell], local: dict[str, Any], recorded: dict[str, Any],
                      recs: RecordSet | None) -> list[str]:
    """Which cells come from published records (and their commits), and the stale records."""
    if recs is None:
        return []
    lines = []
    if recorded:
        by_origin: dict[str, list[str]] = {}
        for c in cells:
            if c.key in recorded:
                by_origin.setdefault(recs.provenance_of(c.key), []).append(f"`{c.key}`")
        lines.append("- cells from published records (`benchmarks/results/cells/`, run on other machines or "
                     "sessions; no figures drawn for them; the measured times above add up all machines): "
                     + "; ".join(f"{', '.join(keys)} ({origin})" for origin, keys in by_origin.items()))
        lines.append(f"- cells run in this report's root: {', '.join(f'`{k}`' for k in local) or 'none'}")
    if recs.stale:
        lines.append(f"- records ignored because the cell's definition changed since: {', '.join(recs.stale)}")
    if recs.unreadable:
        lines.append(f"- unreadable records ignored: {', '.join(recs.unreadable)}")
    if recs.orphans:
        lines.append(f"- records of cells that no longer exist, ignored: {', '.join(recs.orphans)}")
    return lines
