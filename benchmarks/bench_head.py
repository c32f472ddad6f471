"""Benchmark of the covariance head's share of a training step: the geometric head's 3x3 form
against its former k x k form and against the paper's Cholesky head.

    python benchmarks/bench_head.py [--frames 9] [--rings 16] [--threads 1] [--repeats 12]

Writes ``benchmarks/results/head_speed.md`` and ``head_speed.json``.

One training step of Algorithm 1 (sampling, forward, both losses with the pose layer, backward;
no optimiser step) on odometry pairs of the synthetic sequence preprocessed as the SLAM stores
them (``bench_training.build_synthetic_memory``), with the default ``TrainConfig``. The three
variants run interleaved, pair by pair, so that load from other jobs falls on all of them alike;
the result is the median time per step and its ratio to the 3x3 geometric head.
"""

from __future__ import annotations

import argparse
import shlex
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench_training import build_synthetic_memory  # noqa: E402

import training.network as network  # noqa: E402
from gr_graph.atomic import atomic_write_json, atomic_write_text  # noqa: E402
from gr_graph.provenance import machine_line  # noqa: E402
from training.dataset import SkipSample  # noqa: E402
from training.trainer import TrainConfig, Trainer  # noqa: E402

VARIANTS = {
    "geometric, 3x3 form (default)": ("geometric", network.geometric_covariance),
    "geometric, former k x k form": ("geometric", network.geometric_covariance_kxk),
    "cholesky (paper's literal head)": ("cholesky", network.geometric_covariance),
}


def step_seconds(trainer: Trainer, edge: int) -> float | None:
    """Wall seconds of one step without the optimiser: sample, forward, losses, backward (None
    when the trainer would skip the pair)."""
    t0 = time.perf_counter()
    s = trainer.dataset.sample(edge, 99)
    C = trainer.forward(s)
    try:
        loss, _ = trainer.pair_loss(s, C)
    except SkipSample:
        return None
    loss.backward()
    trainer.model.zero_grad()
    return time.perf_counter() - t0


def measure(args: argparse.Namespace) -> dict:
    torch.set_num_threads(args.threads)
    mem, _ = build_synthetic_memory(args.start, args.frames, args.rings)
    times: dict[str, list[float]] = {k: [] for k in VARIANTS}
    with tempfile.TemporaryDirectory() as tmp:
        trainers = {}
        for name, (head, _) in VARIANTS.items():
            cfg = TrainConfig.from_dict({"epochs": 1, "progress": False, "num_threads": args.threads,
                                         "net": {"head": head}})
            trainers[name] = Trainer(mem, Path(tmp) / str(len(trainers)), cfg)
        for rep in range(args.repeats + 1):  # the first pass warms up
            for name, (_, head_fn) in VARIANTS.items():
                network.geometric_covariance = head_fn
                try:
                    dt = step_seconds(trainers[name], rep % mem.n_edges)
                finally:
                    network.geometric_covariance = VARIANTS["geometric, 3x3 form (default)"][1]
                if rep and dt is not None:
                    times[name].append(dt)
    base = statistics.median(times["geometric, 3x3 form (default)"])
    return {"frames": args.frames, "start": args.start, "rings": args.rings, "threads": args.threads,
            "repeats": args.repeats, "pairs": mem.n_edges,
            "variants": {k: {"median_s": statistics.median(v), "min_s": min(v),
                             "ratio_to_default": statistics.median(v) / base} for k, v in times.items()}}


def write_report(res: dict, argv: list[str]) -> Path:
    out = REPO / "benchmarks" / "results"
    atomic_write_json(out / "head_speed.json", res)
    lines = ["# Covariance head: time of a training step", "",
             f"Reproduce: `{shlex.join(['python', 'benchmarks/bench_head.py', *argv])}`", "",
             f"Machine: {machine_line()}, torch {torch.__version__}, "
             f"{res['threads']} torch thread(s). {res['rings']}-channel synthetic scans, frames {res['start']}.."
             f"{res['start'] + res['frames'] - 1} ({res['pairs']} odometry pairs), default network and trainer "
             f"settings; {res['repeats']} steps a variant, interleaved (load from other jobs falls on all alike).", "",
             "| head | median step [ms] | fastest step [ms] | ratio to the default |", "|---|---|---|---|"]
    for name, v in res["variants"].items():
        lines.append(f"| {name} | {v['median_s'] * 1000:.0f} | {v['min_s'] * 1000:.0f} | {v['ratio_to_default']:.2f} |")
    if res.get("note"):
        lines += ["", f"Conditions: {res['note']}"]
    lines += ["", "A step: sampling, forward, correspondence and pose likelihoods (pose layer), backward; no "
              "optimiser step. Both geometric forms compute the same covariances and gradients (to rounding: "
              "`tests/training/test_network.py`)."]
    return atomic_write_text(out / "head_speed.md", "\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=9)
    ap.add_argument("--start", type=int, default=100)
    ap.add_argument("--rings", type=int, default=16)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=12)
    ap.add_argument("--note", default="", help="a sentence on the conditions (e.g. other jobs running), added to the report")
    argv = sys.argv[1:] if argv is None else argv
    args = ap.parse_args(argv)
    res = measure(args)
    res["note"] = args.note
    print(write_report(res, argv).read_text())


if __name__ == "__main__":
    main()
