"""Wall time of a learning round under two thread settings (not a test).

``--setting reader_threads`` (default) compares one and two reader threads (``data.read_threads``);
``--setting blas_threads`` compares numpy's BLAS held to one thread during SLAM
(``gr_graph.frame_loop.SLAM_BLAS_THREADS``, the default) with OpenBLAS's own team (the limit
lifted in the benchmark's process). Each run is ``python -m gr_graph.slam --frames A:B --channels
C --synthetic-preset kitti --weights pretrained --densify`` (round 0 on the raw frames, then one
learning round that densifies every frame with the shipped weights, without training), the
settings interleaved, each run in a fresh process. Compared: round 1's wall time and its ``read``
stage (waiting for densified frames), and whether rounds 0 and 1 are bit-identical between the
settings (poses, marginal covariances, edge information in ``marginals.npz``).

Run::

    python benchmarks/bench_reader_threads.py --work DIR [--setting blas_threads] [--frames 0:600] [--repeats 2] [--write]

Finished runs in ``DIR`` (``<variant>_<repeat>/metrics.json``) are not run again: use a new
``DIR`` after a code change (``t2``, two readers, runs with the BLAS limit since it landed, as
shipped; the published ``reader_threads.md`` predates it). Writes ``benchmarks/results/<setting>.md``
and ``.json`` with ``--write`` (notes added below the table by hand are overwritten).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gr_graph.atomic import read_json_or_none

RESULTS = Path(__file__).resolve().parent / "results"
HERE = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Variant:
    """One setting of a comparison: its label (also its run directories' prefix), how the table
    names it, its ``data.read_threads`` and numpy's BLAS threads during SLAM (None: OpenBLAS's own
    team)."""

    label: str
    shown: str
    read_threads: int = 2
    blas_threads: int | None = 1


SETTINGS: dict[str, tuple[str, str, tuple[Variant, Variant]]] = {
    "reader_threads": ("Reader threads of a learning round (`data.read_threads`)", "reader threads",
                       (Variant("t2", "2", read_threads=2), Variant("t1", "1", read_threads=1))),
    "blas_threads": ("numpy's BLAS threads during SLAM (`gr_graph.frame_loop.SLAM_BLAS_THREADS`)",
                     "numpy BLAS threads during SLAM",
                     (Variant("blas1", "1", blas_threads=1), Variant("blasteam", "OpenBLAS's team", blas_threads=None))),
}


def run_one(work: Path, variant: Variant, rep: int, frames: str, channels: int) -> Path:
    """The run of ``variant``, repeat ``rep`` (skipped when finished)."""
    out = work / f"{variant.label}_{rep}"
    if "final_round" in (read_json_or_none(out / "metrics.json") or {}):  # finished (written after each round)
        return out
    cfg = work / f"{variant.label}.yaml"
    cfg.write_text(f"data:\n  read_threads: {variant.read_threads}\noutput:\n  plot: false\n")
    argv = ["--frames", frames, "--channels", str(channels), "--synthetic-preset", "kitti", "--weights", "pretrained",
            "--densify", "--config", str(cfg), "--out", str(out), "--no-progress"]
    code = ("import sys, gr_graph.frame_loop as f; from gr_graph.slam import main; "
            f"f.SLAM_BLAS_THREADS = {variant.blas_threads!r}; raise SystemExit(main(sys.argv[1:]))")
    subprocess.run([sys.executable, "-c", code, *argv], cwd=HERE, check=True)
    return out


def same_rounds(a: Path, b: Path) -> bool:
    """Rounds 0 and 1 of two runs hold bit-identical poses, covariances and edge information."""
    for r in ("round_0", "round_1"):
        with np.load(a / r / "marginals.npz") as za, np.load(b / r / "marginals.npz") as zb:
            if not all(np.array_equal(za[k], zb[k]) for k in ("poses", "covariance", "edge_information")):
                return False
    return True


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=Path, required=True, help="directory of the runs (kept; reruns skip finished ones)")
    ap.add_argument("--setting", choices=sorted(SETTINGS), default="reader_threads")
    ap.add_argument("--frames", default="0:600")
    ap.add_argument("--channels", type=int, default=16, choices=(16, 32, 64))
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--write", action="store_true")
    args = ap.parse_args(argv)
    from gr_graph.experiments.aggregate import fmt_ms, mean_std

    title, column, variants = SETTINGS[args.setting]
    args.work.mkdir(parents=True, exist_ok=True)
    runs: dict[str, list[Path]] = {v.label: [] for v in variants}
    for rep in range(args.repeats):
        for v in variants:
            runs[v.label].append(run_one(args.work, v, rep, args.frames, args.channels))
            print(f"repeat {rep}: {v.label} done", flush=True)
    stats: dict[str, dict[str, list[float]]] = {}
    for label, outs in runs.items():
        rounds = [json.loads((o / "metrics.json").read_text())["rounds"] for o in outs]
        stats[label] = {"round1_total_s": [r["1"]["runtime_s"]["total"] for r in rounds],
                        "round1_read_s": [r["1"]["runtime_s"]["read"] for r in rounds],
                        "round0_total_s": [r["0"]["runtime_s"]["total"] for r in rounds]}
    first = variants[0].label
    identical = all(same_rounds(runs[first][0], o) for outs in runs.values() for o in outs)

    def cell(vals: list[float]) -> str:
        return fmt_ms(mean_std(vals), "{:.1f}")

    lines = [f"| {column} | round 1 wall [s] | waiting for densified frames [s] | round 0 wall [s] | runs |",
             "|---|---|---|---|---|"]
    for v in variants:
        s = stats[v.label]
        lines.append(f"| {v.shown} | {cell(s['round1_total_s'])} | {cell(s['round1_read_s'])} "
                     f"| {cell(s['round0_total_s'])} | {len(s['round1_total_s'])} |")
    a, b = (np.mean(stats[v.label]["round1_total_s"]) for v in variants)
    lines += ["", f"ratio of round 1's wall time, {variants[0].label} / {variants[1].label}: {a / b:.3f}",
              f"rounds 0 and 1 bit-identical across all runs (poses, covariances, edge information): {identical}"]
    print("\n".join(lines))
    if args.write:
        from gr_graph.atomic import atomic_write_json, atomic_write_text
        from gr_graph.provenance import machine_line

        atomic_write_json(RESULTS / f"{args.setting}.json", {"machine": machine_line(), "frames": args.frames,
                                                             "channels": args.channels, "runs": stats,
                                                             "identical": identical})
        atomic_write_text(RESULTS / f"{args.setting}.md", f"# {title}\n\n"
                          f"Frames {args.frames} of the `kitti` preset at {args.channels} channels; round 1 densifies "
                          "every frame with the shipped weights (no training); machine: " + machine_line() + "\n\n"
                          + "\n".join(lines) + "\n\nCommand: `python benchmarks/bench_reader_threads.py --work DIR "
                          f"--setting {args.setting} --frames {args.frames} --repeats {args.repeats} --write`\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
