"""One learning round with densification that only adds, against the paper's (not a test).

The paper's Algorithm 2 replaces a scan by samples around its anisotropic points and drops the
rest; ``training.keep_original`` + ``training.keep_dropped`` keep every point and add the
samples. This pairs the two on the same round 0 and the same trained round-1 network: ``run``
copies ``round_0`` and ``round_1/training`` of a finished default run (e.g. an ablation cell's
``ROOT/ablations/default-sS/slam``) into a new folder and runs round 1 there with both options
(the training resumes as finished: no retraining; round 0 is reused); ``report`` compares round
1 of both against round 0, per seed and as mean ± std.

Run::

    python -m gr_graph.experiments ablations --root ROOT --cell default-sS --no-records
    python benchmarks/densify_adds_study.py run ROOT/ablations/default-sS/slam OUT_S
    python benchmarks/densify_adds_study.py report DEFAULT_RUN ADDS_RUN [DEFAULT_RUN ADDS_RUN ...] [--write]

``--write`` writes ``benchmarks/results/densify_adds.md`` and ``.json``.
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import shlex
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from results_io import change_percent  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
METRICS = ("ate_rmse", "rpe300_all_pairs_mean", "rpe300_consecutive_mean", "kitti_t_err_percent")


def run(default_run: Path, out: Path) -> None:
    """Round 1 of ``default_run``'s configuration with densification that only adds, in ``out``."""
    import yaml

    from gr_graph.config import load_config
    from gr_graph.pipeline import SlamPipeline

    model = default_run / "round_1" / "training" / "checkpoint.pt"
    if not (default_run / "round_0" / "memory").is_dir() or not model.is_file():
        raise FileNotFoundError(f"{default_run}: needs round_0/memory and round_1/training/checkpoint.pt "
                                "(a default run whose memories are not pruned)")
    out.mkdir(parents=True, exist_ok=True)
    if not (out / "round_0").is_dir():
        shutil.copytree(default_run / "round_0", out / "round_0")
    if not (out / "round_1" / "training").is_dir():
        shutil.copytree(default_run / "round_1" / "training", out / "round_1" / "training")
    cfg = yaml.safe_load((default_run / "config.yaml").read_text())
    cfg["training"].update({"rounds": 1, "keep_original": True, "keep_dropped": True})
    cfg["output"].update({"out_dir": str(out), "resume": True})
    SlamPipeline(load_config(None, cfg)).run()


def _round(run_dir: Path, r: str) -> dict:
    rnd = json.loads((run_dir / "metrics.json").read_text())["rounds"][r]
    nc = rnd.get("noise_consistency") or {}
    return {**{k: rnd["slam"][k] for k in METRICS}, "accepted": rnd.get("accepted"),
            "odometry_nees": (nc.get("edges") or {}).get("odometry", {}).get("mean"),
            "position_nees": (nc.get("position") or {}).get("mean"),
            "kept_fraction": (rnd.get("densify") or {}).get("kept_fraction"),
            "path_error_percent": (nc.get("edges") or {}).get("odometry", {}).get("path_error_percent")}


def rows_of(pairs: list[tuple[Path, Path]]) -> list[dict]:
    import yaml

    rows = []
    for default_run, adds_run in pairs:
        seed = yaml.safe_load((default_run / "config.yaml").read_text()).get("seed")
        rows.append({"default_run": str(default_run), "adds_run": str(adds_run), "seed": seed,
                     "round0": _round(default_run, "0"), "default": _round(default_run, "1"),
                     "adds": _round(adds_run, "1"), "adds_round0": _round(adds_run, "0")})
    return rows


def _f(v: float | None, fmt: str = ".3f") -> str:
    return "n/a" if v is None or not np.isfinite(v) else format(v, fmt)


def table(rows: list[dict]) -> str:
    lines = ["| seed | step | ATE RMSE [m] | RPE-300 all pairs [m] | RPE-300 consec. [m] | KITTI [%] | odometry NEES "
             "| position NEES | odometry path error [%] | accepted |", "|" + "---|" * 10]
    for row in rows:
        for step, f in (("round 0", row["round0"]), ("1-step, paper (replace)", row["default"]),
                        ("1-step, only adds", row["adds"])):
            lines.append(f"| {row['seed']} | {step} | {_f(f['ate_rmse'])} | "
                         f"{_f(f['rpe300_all_pairs_mean'])} | {_f(f['rpe300_consecutive_mean'])} | "
                         f"{_f(f['kitti_t_err_percent'])} | {_f(f['odometry_nees'], '.3g')} | "
                         f"{_f(f['position_nees'], '.3g')} | {_f(f['path_error_percent'], '+.2f')} | {f['accepted']} |")
    if len(rows) >= 2:
        lines += ["", f"Change against round 0 (negative = better), mean ± std over {len(rows)} seeds (sample std):", "",
                  "| step | ATE RMSE | RPE-300 all pairs | RPE-300 consec. | KITTI |", "|---|---|---|---|---|"]
        for name, key in (("1-step, paper (replace)", "default"), ("1-step, only adds", "adds")):
            cells = [change_percent([row[key][m] for row in rows], [row["round0"][m] for row in rows]) for m in METRICS]
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run")
    r.add_argument("default_run", type=Path)
    r.add_argument("out", type=Path)
    p = sub.add_parser("report")
    p.add_argument("runs", nargs="+", type=Path, help="DEFAULT_RUN ADDS_RUN pairs")
    p.add_argument("--write", action="store_true")
    args = ap.parse_args(argv)
    if args.command == "run":
        logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
        run(args.default_run, args.out)
        return 0
    if len(args.runs) % 2:
        ap.error("give DEFAULT_RUN ADDS_RUN pairs")
    rows = rows_of(list(zip(args.runs[::2], args.runs[1::2])))
    for row in rows:  # the pairing is only fair on the same round 0
        if any(row["round0"][k] != row["adds_round0"][k] for k in METRICS):
            raise SystemExit(f"{row['adds_run']}: its round 0 differs from {row['default_run']}'s")
    text = table(rows)
    print(text)
    if args.write:
        from gr_graph.atomic import atomic_write_json, atomic_write_text
        from gr_graph.provenance import machine_line

        command = shlex.join(["python", "benchmarks/densify_adds_study.py", *(sys.argv[1:] if argv is None else argv)])
        atomic_write_json(RESULTS / "densify_adds.json", {"machine": machine_line(), "rows": rows})
        atomic_write_text(RESULTS / "densify_adds.md", "# One learning round: densification that only adds against "
                          "the paper's (same round 0, same trained network)\n\n"
                          f"Command: `{command}`. Machine: {machine_line()}.\n\n" + text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
