"""Wall time of a learning round with one or two reader threads (``data.read_threads``; not a test).

Runs ``python -m gr_graph.slam --frames A:B --channels C --synthetic-preset kitti --weights
pretrained --densify`` (round 0 on the raw frames, then one learning round that densifies every
frame with the shipped weights, without training) once per thread count and repeat, the thread
counts interleaved, each in a fresh process, and compares: round 1's wall time and its ``read``
stage (waiting for densified frames), and whether rounds 0 and 1 are bit-identical between
thread counts (poses, marginal covariances, edge information in ``marginals.npz``).

Run::

    python benchmarks/bench_reader_threads.py --work DIR [--frames 0:600] [--repeats 2] [--write]

Finished runs in ``DIR`` (``t<threads>_<repeat>/metrics.json``) are not run again. Writes
``benchmarks/results/reader_threads.md`` and ``.json`` with ``--write``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"
HERE = Path(__file__).resolve().parents[1]
THREADS = (2, 1)


def run_one(work: Path, threads: int, rep: int, frames: str, channels: int) -> Path:
    """The run with ``threads`` reader threads, repeat ``rep`` (skipped when finished)."""
    out = work / f"t{threads}_{rep}"
    if (out / "metrics.json").is_file():
        return out
    cfg = work / f"t{threads}.yaml"
    cfg.write_text(f"data:\n  read_threads: {threads}\noutput:\n  plot: false\n")
    cmd = [sys.executable, "-m", "gr_graph.slam", "--frames", frames, "--channels", str(channels),
           "--synthetic-preset", "kitti", "--weights", "pretrained", "--densify", "--config", str(cfg),
           "--out", str(out), "--no-progress"]
    subprocess.run(cmd, cwd=HERE, check=True)
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
    ap.add_argument("--frames", default="0:600")
    ap.add_argument("--channels", type=int, default=16, choices=(16, 32, 64))
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--write", action="store_true")
    args = ap.parse_args(argv)
    args.work.mkdir(parents=True, exist_ok=True)
    runs: dict[int, list[Path]] = {t: [] for t in THREADS}
    for rep in range(args.repeats):
        for t in THREADS:
            runs[t].append(run_one(args.work, t, rep, args.frames, args.channels))
            print(f"repeat {rep}: {t} thread(s) done", flush=True)
    stats: dict[str, dict[str, list[float]]] = {}
    for t, outs in runs.items():
        rounds = [json.loads((o / "metrics.json").read_text())["rounds"] for o in outs]
        stats[str(t)] = {"round1_total_s": [r["1"]["runtime_s"]["total"] for r in rounds],
                         "round1_read_s": [r["1"]["runtime_s"]["read"] for r in rounds],
                         "round0_total_s": [r["0"]["runtime_s"]["total"] for r in rounds]}
    identical = all(same_rounds(runs[THREADS[0]][0], o) for outs in runs.values() for o in outs)

    def cell(vals: list[float]) -> str:
        return f"{np.mean(vals):.1f} ± {np.std(vals, ddof=1) if len(vals) > 1 else 0.0:.1f}"

    lines = ["| reader threads | round 1 wall [s] | waiting for densified frames [s] | round 0 wall [s] | runs |",
             "|---|---|---|---|---|"]
    for t in THREADS:
        s = stats[str(t)]
        lines.append(f"| {t} | {cell(s['round1_total_s'])} | {cell(s['round1_read_s'])} | {cell(s['round0_total_s'])} "
                     f"| {len(s['round1_total_s'])} |")
    ratio = np.mean(stats["2"]["round1_total_s"]) / np.mean(stats["1"]["round1_total_s"])
    lines += ["", f"ratio of round 1's wall time, 2 threads / 1: {ratio:.3f}",
              f"rounds 0 and 1 bit-identical across all runs (poses, covariances, edge information): {identical}"]
    print("\n".join(lines))
    if args.write:
        from gr_graph.atomic import atomic_write_json, atomic_write_text
        from gr_graph.provenance import machine_line

        atomic_write_json(RESULTS / "reader_threads.json", {"machine": machine_line(), "frames": args.frames,
                                                            "channels": args.channels, "runs": stats,
                                                            "identical": identical})
        atomic_write_text(RESULTS / "reader_threads.md", "# Reader threads of a learning round (`data.read_threads`)\n\n"
                          f"Frames {args.frames} of the `kitti` preset at {args.channels} channels; round 1 densifies "
                          "every frame with the shipped weights (no training); machine: " + machine_line() + "\n\n"
                          + "\n".join(lines) + "\n\nCommand: `python benchmarks/bench_reader_threads.py --work DIR "
                          f"--frames {args.frames} --repeats {args.repeats} --write`\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
