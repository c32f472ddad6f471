"""One learning round with the same trained network and other densification settings (not a test).

Where does a learning round lose frame-to-frame accuracy? The paper's densification (Algorithm 2)
keeps the anisotropic points (``training.tau_ani``), replaces each by ``samples_per_point``
samples ~ N(s, C), and drops the rest. This study runs round 1 of a finished run again with the
same round 0 and the same round-1 network under other settings, e.g. ``tau_ani=0`` (every point
kept: the samples' noise alone) or ``keep_original=true keep_dropped=true`` (every point kept, the
samples added), and compares the rounds' accuracy at every scale: the mean translational RPE over
1, 10, 100 and 300 frames (all pairs), ATE and the GT-free test's verdict.

``run`` copies ``round_0`` (with its memory: the acceptance test reads the raw scans there) from
``BASE_RUN`` and the network's training folder (``checkpoint.pt``, trained with the settings of
``BASE_RUN/config.yaml`` plus the ``--set`` options, so it resumes as finished: no retraining)
into ``OUT``, and runs round 1 there with the ``--set`` options. Without ``--training-dir`` the
network is a finished ``model.pt`` used as it is (``--set weights=PATH --set fine_tune=false``:
the harness's cells keep ``model.pt`` but prune ``checkpoint.pt``)::

    python benchmarks/densify_variants_study.py run BASE_RUN OUT --training-dir DIR \\
        [--set tau_ani=0] [--set keep_original=true ...]
    python benchmarks/densify_variants_study.py run BASE_RUN OUT --set weights=MODEL_PT --set fine_tune=false \\
        [--set keep_original=true ...]
    python benchmarks/densify_variants_study.py report LABEL=RUN [LABEL=RUN ...] [--write]

``report`` takes runs labelled ``LABEL`` (several runs of one label: one per seed; the label
``round0`` reads round 0 of its runs, every other label round 1) and gives each run's figures and,
per label, the change against round 0 of the same run as mean ± std over its runs. ``--write``
writes ``benchmarks/results/densify_variants.md`` and ``.json``.
"""

from __future__ import annotations

import argparse
import json
import logging
import shlex
import shutil
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from results_io import change_percent, print_and_write  # noqa: E402

DELTAS = (1, 10, 100, 300)
KEYS = tuple(f"rpe{d}" for d in DELTAS) + ("ate_rmse",)


def _parse_value(text: str) -> Any:
    import yaml

    return yaml.safe_load(text)


def run(base_run: Path, out: Path, training_dir: Path | None, settings: dict[str, Any]) -> None:
    """Round 1 of ``base_run``'s configuration with ``settings`` in its ``training`` section, in ``out``."""
    import yaml

    from gr_graph.config import load_config
    from gr_graph.pipeline import SlamPipeline
    from gr_graph.pretrained import resolve_weights

    if not (base_run / "round_0" / "memory").is_dir():
        raise FileNotFoundError(f"{base_run}: needs round_0/memory (a run whose memories are not pruned)")
    if training_dir is None:
        if settings.get("weights") is None or settings.get("fine_tune", True):
            raise ValueError("without --training-dir give the network as --set weights=MODEL_PT --set fine_tune=false")
        resolve_weights(settings["weights"])  # before round 0 is copied: a missing file is an error naming it
    elif not (training_dir / "checkpoint.pt").is_file():
        raise FileNotFoundError(f"{training_dir}: no checkpoint.pt (a finished training folder)")
    out.mkdir(parents=True, exist_ok=True)
    if not (out / "round_0").is_dir():
        shutil.copytree(base_run / "round_0", out / "round_0")
    if training_dir is not None and not (out / "round_1" / "training").is_dir():
        shutil.copytree(training_dir, out / "round_1" / "training")
    cfg = yaml.safe_load((base_run / "config.yaml").read_text())
    cfg["training"]["rounds"] = 1
    for key, value in settings.items():
        section = cfg["training"]
        *parents, leaf = key.split(".")
        for p in parents:
            section = section.setdefault(p, {})
        section[leaf] = value
    cfg["output"].update({"out_dir": str(out), "resume": True})
    SlamPipeline(load_config(None, cfg)).run()


def figures(run_dir: Path, r: str) -> dict[str, Any]:
    """RPE over :data:`DELTAS` frames (all pairs, mean translation [m]), ATE and the verdict of round ``r``."""
    from gr_graph.metrics import rpe_translation
    from gr_graph.trajectory import read_kitti_poses

    gt = read_kitti_poses(run_dir / "gt_poses_kitti.txt")
    poses = read_kitti_poses(run_dir / f"round_{r}" / "poses_kitti.txt")
    rnd = json.loads((run_dir / "metrics.json").read_text())["rounds"][r]
    out: dict[str, Any] = {f"rpe{d}": rpe_translation(poses, gt, delta=d, all_pairs=True).mean for d in DELTAS}
    dens = rnd.get("densify") or {}
    out.update(ate_rmse=rnd["slam"]["ate_rmse"], accepted=rnd.get("accepted"), kept_fraction=dens.get("kept_fraction"),
               mean_output_points=dens.get("mean_output_points"),
               mean_input_points=dens.get("mean_preprocessed_points"))
    return out


def _f(v: float | None, fmt: str) -> str:
    return "n/a" if v is None or not np.isfinite(v) else format(v, fmt)


def table(rows: list[dict[str, Any]]) -> str:
    lines = ["| label | run | round | " + " | ".join(f"RPE-{d} [m]" for d in DELTAS)
             + " | ATE RMSE [m] | points kept | output points a scan | accepted |", "|" + "---|" * (len(KEYS) + 6)]
    for row in rows:
        f = row["figures"]
        lines.append(f"| {row['label']} | {row['run']} | {row['round']} | "
                     + " | ".join(_f(f[k], ".4f") for k in KEYS)
                     + f" | {_f(f['kept_fraction'], '.2f')} | {_f(f['mean_output_points'], '.0f')} | {f['accepted']} |")
    labels = [lb for lb in dict.fromkeys(r["label"] for r in rows) if lb != "round0"]
    if labels:
        lines += ["", "Change against round 0 of the same run (negative = better), mean ± std over the label's runs "
                  "(sample std; one run: no spread):", "",
                  "| label | runs | " + " | ".join(f"RPE-{d}" for d in DELTAS) + " | ATE RMSE |",
                  "|" + "---|" * (len(KEYS) + 2)]
        for lb in labels:
            mine = [r for r in rows if r["label"] == lb]
            cells = [change_percent([r["figures"][k] for r in mine], [r["round0"][k] for r in mine]) for k in KEYS]
            lines.append(f"| {lb} | {len(mine)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run")
    r.add_argument("base_run", type=Path)
    r.add_argument("out", type=Path)
    r.add_argument("--training-dir", type=Path, default=None,
                   help="a finished training folder (checkpoint.pt); without it --set weights=MODEL_PT fine_tune=false")
    r.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="a training option (dots for nested keys: trainer.corr_likelihood=student_t)")
    p = sub.add_parser("report")
    p.add_argument("runs", nargs="+", metavar="LABEL=RUN")
    p.add_argument("--write", action="store_true")
    args = ap.parse_args(argv)
    if args.command == "run":
        bad = [s for s in args.set if "=" not in s]
        if bad:
            ap.error(f"--set needs KEY=VALUE, got {bad}")
        logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
        run(args.base_run, args.out, args.training_dir,
            {k: _parse_value(v) for k, v in (s.split("=", 1) for s in args.set)})
        return 0
    rows = []
    for item in args.runs:
        if "=" not in item:
            ap.error(f"give LABEL=RUN, got {item!r}")
        label, path = item.split("=", 1)
        run_dir = Path(path)
        r = "0" if label == "round0" else "1"
        rows.append({"label": label, "run": str(run_dir), "round": int(r), "figures": figures(run_dir, r),
                     "round0": figures(run_dir, "0")})
    from gr_graph.provenance import machine_line

    command = shlex.join(["python", "benchmarks/densify_variants_study.py", *(sys.argv[1:] if argv is None else argv)])
    text = ("# One learning round, the same network, other densification settings\n\n"
            f"Command: `{command}`. Machine: {machine_line()}.\n\n" + table(rows))
    print_and_write("densify_variants", text, {"command": command, "machine": machine_line(), "rows": rows},
                    args.write)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
