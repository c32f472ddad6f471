"""Loop edges with a fixed weight against the loops' estimated variance component (not a test).

Compares finished round-0 runs made with ``graph.loop_variance: fixed`` (the default) and
``estimated`` on the same data (``--loop-variance estimated``; :mod:`gr_graph.noise_calibration`):
NEES against ground truth per edge kind and of the marginal positions (horizontal / vertical),
the trajectory's accuracy (ATE, RPE-300 over all pairs, KITTI %), and the factor the loops got.
The runs themselves use no ground truth; this only evaluates them.

Run::

    python -m gr_graph.slam --frames 0:1500 --channels 16 --synthetic-preset kitti --seed S --out FIXED
    python -m gr_graph.slam --frames 0:1500 --channels 16 --synthetic-preset kitti --seed S --out EST \\
        --loop-variance estimated
    python benchmarks/loop_variance_study.py LABEL FIXED EST [LABEL FIXED EST ...] [--write]

``FIXED`` may also be a published cell record (``benchmarks/results/cells/paper/table1/KEY.json``)
whose round 0 was made with the same data and the default.

``--write`` writes ``benchmarks/results/loop_variance.md`` and ``loop_variance.json``.

A run may name its round as ``RUN@R`` (default ``@0``), e.g. round 0 against round 1 of one run
(``LABEL RUN@0 RUN@1``) or the learning rounds of two runs (``LABEL RUN_A@1 RUN_B@1``).

Any two round-0 runs of the same data compare the same way, e.g. without and with the
vertical-angle correction (both ``--loop-variance estimated``)::

    python benchmarks/loop_variance_study.py LABEL RUN_A RUN_B ... --labels "no correction" "0.22 deg" \
        --name vertical_correction_nees --title "..." --write
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

import numpy as np

from gr_graph.atomic import atomic_write_json, atomic_write_text
from gr_graph.noise_consistency import round_noise_consistency
from gr_graph.provenance import machine_line

RESULTS = Path(__file__).resolve().parent / "results"


def record_figures(record: Path, r: int = 0) -> dict:
    """The same figures from a published cell record (``benchmarks/results/cells/...json``: no
    horizontal / vertical split, no loop factor), for runs whose folders are gone."""
    rnd = json.loads(record.read_text())["rounds"][str(r)]
    nees, slam = rnd["nees"], rnd["slam"]
    return {"odometry_nees": nees["nees_odometry_mean"], "odometry_nees_median": None, "odometry_z2": None,
            "loop_nees": nees["nees_loop_mean"], "n_loops": rnd["n_loops"],
            "position_nees": nees["nees_position_mean"], "horizontal_nees": None, "vertical_nees": None,
            "ate_rmse": slam["ate_rmse"], "rpe300_all_pairs_mean": slam["rpe300_all_pairs_mean"],
            "kitti_t_err_percent": slam["kitti_t_err_percent"], "loop_scale": None, "loop_redundancy": None,
            "accepted": rnd.get("accepted"), "round": r}


def round_figures(run: Path, r: int = 0) -> dict:
    """NEES, accuracy and the loop factor of round ``r`` of ``run`` (a run folder, or a cell
    record: :func:`record_figures`)."""
    if run.suffix == ".json":
        return record_figures(run, r)
    rd = run / f"round_{r}"
    nc = round_noise_consistency(rd)
    summary = json.loads((rd / "round.json").read_text())
    slam = summary.get("slam") or json.loads((run / "metrics.json").read_text())["rounds"][str(r)]["slam"]
    lv = summary.get("loop_variance") or {}
    return {"odometry_nees": nc["edges"]["odometry"]["mean"], "odometry_nees_median": nc["edges"]["odometry"]["median"],
            "odometry_z2": nc["edges"]["odometry"]["per_axis"]["z2_mean"], "loop_nees": nc["edges"]["loop"]["mean"],
            "n_loops": nc["edges"]["loop"]["n"], "position_nees": nc["position"]["mean"],
            "horizontal_nees": nc["position"]["horizontal"]["mean"], "vertical_nees": nc["position"]["vertical"]["mean"],
            "ate_rmse": slam["ate_rmse"], "rpe300_all_pairs_mean": slam["rpe300_all_pairs_mean"],
            "kitti_t_err_percent": slam["kitti_t_err_percent"], "loop_scale": _loop_scale(lv),
            "loop_z2": (nc["edges"]["loop"].get("per_axis") or {}).get("z2_mean"),
            "loop_redundancy": lv.get("redundancy"), "accepted": summary.get("accepted"), "round": r}


def run_round(arg: str) -> tuple[Path, int]:
    """``RUN`` or ``RUN@R`` -> (run folder or cell record, round); an existing path is taken whole."""
    path, sep, r = arg.rpartition("@")
    if not sep or not r.isdigit() or Path(arg).exists():
        return Path(arg), 0
    return Path(path), int(r)


def _loop_scale(lv: dict) -> float | list[float] | None:
    """The factor the loops' information got (``round.json``'s ``loop_variance``): one number, or
    six (one per axis) when the per-axis stage of ``estimated_axes`` scaled them further."""
    axes = lv.get("axes") or {}
    if axes.get("reason") is None and axes.get("axis_scale") is not None:
        return [lv["scale"] * a for a in axes["axis_scale"]]
    return lv.get("scale")


def _fmt(v: float | None) -> str:
    """Three significant digits (NEES, factors)."""
    return "n/a" if v is None or not np.isfinite(v) else f"{v:.3g}"


def _axes(z2: list[float] | None) -> str:
    return "n/a" if z2 is None else " / ".join(f"{v:.2g}" for v in z2)


def table(rows: list[tuple[str, dict, dict]], labels: tuple[str, str] = ("fixed", "estimated"),
          axes: bool = False, summary: bool = True) -> str:
    """Markdown table of the run pairs; ``axes`` adds the odometry edges' NEES median and per-axis z^2;
    ``summary`` the mean ± std rows over the pairs (off when the pairs are not seeds of one setting)."""
    extra = (" odometry NEES median | odometry z² (ωx / ωy / ωz / x / y / z) | loop z² (ωx / ωy / ωz / x / y / z) |"
             if axes else "")
    head = ("| run | loops | odometry NEES | loop NEES | position NEES (horizontal / vertical) | ATE RMSE [m] "
            "| RPE-300 all pairs [m] | KITTI [%] | loop information x |" + extra)
    lines = [head, "|" + "---|" * (12 if axes else 9)]
    for label, fixed, est in rows:
        for what, f in zip(labels, (fixed, est)):
            scale = ("1" if f["loop_scale"] is None else _axes(f["loop_scale"]) if isinstance(f["loop_scale"], list)
                     else _fmt(f["loop_scale"]))  # no factor: the loops as registered; a list: one per axis
            more = (f" {_fmt(f.get('odometry_nees_median'))} | {_axes(f.get('odometry_z2'))} | "
                    f"{_axes(f.get('loop_z2'))} |" if axes else "")
            flag = " (rejected)" if f.get("accepted") is False else ""  # a learning round the acceptance test rejected
            lines.append(f"| {label}, {what}{flag} | {f['n_loops']} | {_fmt(f['odometry_nees'])} | {_fmt(f['loop_nees'])} "
                         f"| {_fmt(f['position_nees'])} ({_fmt(f['horizontal_nees'])} / {_fmt(f['vertical_nees'])}) "
                         f"| {f['ate_rmse']:.3f} | {f['rpe300_all_pairs_mean']:.3f} | {f['kitti_t_err_percent']:.3f} "
                         f"| {scale} |" + more)
    if summary and len(rows) >= 2:  # mean ± sample std over the triples, per run kind
        keys = ("odometry_nees", "loop_nees", "position_nees", "ate_rmse", "rpe300_all_pairs_mean",
                "kitti_t_err_percent") + (("odometry_nees_median",) if axes else ())
        for i, what in enumerate(labels):
            v = {k: np.array([r[1 + i][k] for r in rows], float) for k in keys}
            ms = {k: "n/a" if np.isnan(x).any() else f"{x.mean():.3g} ± {x.std(ddof=1):.2g}" for k, x in v.items()}
            more = ""
            if axes:
                means = []
                for kind in ("odometry_z2", "loop_z2"):
                    z2 = [r[1 + i].get(kind) for r in rows]
                    means.append(None if any(z is None for z in z2) else list(np.mean(z2, axis=0)))
                more = f" {ms['odometry_nees_median']} | {_axes(means[0])} (mean) | {_axes(means[1])} (mean) |"
            lines.append(f"| mean ± std, {what} | | {ms['odometry_nees']} | {ms['loop_nees']} | {ms['position_nees']} "
                         f"| {ms['ate_rmse']} | {ms['rpe300_all_pairs_mean']} | {ms['kitti_t_err_percent']} | |" + more)
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("triples", nargs="+", help="LABEL FIXED_RUN ESTIMATED_RUN, repeated")
    ap.add_argument("--write", action="store_true", help="write benchmarks/results/NAME.md / .json")
    ap.add_argument("--labels", nargs=2, default=["fixed", "estimated"], metavar=("A", "B"),
                    help="names of the two runs of a triple (default: fixed estimated)")
    ap.add_argument("--name", default="loop_variance", help="results file name (default: loop_variance)")
    ap.add_argument("--title", default="Loop edges: fixed weight against the estimated loop variance component "
                    "(round 0)", help="the results file's heading (name the rounds when comparing others)")
    ap.add_argument("--axes", action="store_true",
                    help="add the odometry edges' NEES median and the odometry and loop edges' per-axis z^2")
    ap.add_argument("--no-summary", action="store_true",
                    help="no mean ± std rows (the triples are not seeds of one setting, e.g. a parameter sweep)")
    ap.add_argument("--note", default="", help="a paragraph written under the table (how the runs were made)")
    args = ap.parse_args(argv)
    if len(args.triples) % 3:
        ap.error("give LABEL FIXED_RUN ESTIMATED_RUN triples")
    rows = []
    for i in range(0, len(args.triples), 3):
        label, fixed, est = args.triples[i], run_round(args.triples[i + 1]), run_round(args.triples[i + 2])
        rows.append((label, round_figures(*fixed), round_figures(*est)))
    a, b = args.labels
    text = table(rows, (a, b), args.axes, not args.no_summary)
    print(text)
    if args.write:
        RESULTS.mkdir(parents=True, exist_ok=True)
        atomic_write_json(RESULTS / f"{args.name}.json", {"machine": machine_line(), "labels": [a, b], "runs": [
            {"label": label, a: fixed, b: est} for label, fixed, est in rows]})
        command = shlex.join(["python", "benchmarks/loop_variance_study.py", *(sys.argv[1:] if argv is None else argv)])
        atomic_write_text(RESULTS / f"{args.name}.md", f"# {args.title}\n\nCommand: `{command}` (each run's "
                          f"options in its `config.yaml`). Machine: {machine_line()}.\n\n" + text + "\n"
                          + (f"\n{args.note}\n" if args.note else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
