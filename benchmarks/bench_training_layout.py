"""Training throughput of two process layouts on this machine's cores (not a test).

Times ``--steps`` steps of the trainer (``training.trainer.Trainer``, the default configuration of a
16-channel learning round, one pair a step) on a memory, in two layouts, each in fresh processes,
the layouts interleaved per repeat:

- ``one process``: one trainer with ``--threads`` torch threads (the learning rounds' layout);
- ``processes side by side``: ``--threads`` trainers with one torch thread each, started together
  (what two data-parallel ranks would cost per step; their pairs are not averaged here).

Reports the median seconds a step of each process and the pairs a second of the layout. Run::

    python benchmarks/bench_training_layout.py --memory RUN/round_0/memory [--steps 150] [--repeats 2] [--write]

A memory comes from any SLAM run, e.g. ``python -m gr_graph.slam --frames 0:1500 --channels 16
--synthetic-preset kitti --out RUN`` (Table I's 16-channel window). Writes
``benchmarks/results/training_layout.md`` and ``.json`` with ``--write``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"
HERE = Path(__file__).resolve().parents[1]


class _Enough(Exception):
    """Raised from the trainer's step callback once the steps are done."""


def make_trainer(memory: Path, out: Path, threads: int):
    """A trainer of one epoch with a 16-channel learning round's default configuration and ``threads`` torch threads."""
    from gr_graph.config import load_config
    from gr_graph.memory import load_memory
    from training.trainer import TrainConfig, Trainer

    cfg = load_config(overrides={"data": {"channels": 16, "synthetic_preset": "kitti"}})
    options = cfg.training.trainer_config("cpu", False, None).model_dump()
    options.update(epochs=1, num_threads=threads)
    return Trainer(load_memory(memory), out, TrainConfig.from_dict(options))


def time_steps(memory: Path, out: Path, threads: int, steps: int, keep: list | None = None) -> dict[str, float]:
    """Seconds of ``steps`` trainer steps on ``memory`` with ``threads`` torch threads.

    ``keep``: if given, the trainer is appended to it (its weights after the steps).
    """
    trainer = make_trainer(memory, out, threads)
    done = [0]

    def stop_after(_record: dict) -> None:
        done[0] += 1
        if done[0] >= steps:
            raise _Enough

    t0 = time.perf_counter()
    try:
        trainer.fit(resume=False, callback=stop_after)
    except _Enough:
        pass
    if keep is not None:
        keep.append(trainer)
    step_s = np.asarray(trainer.step_seconds[5:], np.float64)  # the first steps warm up
    return {"threads": threads, "steps": len(trainer.step_seconds), "wall_s": time.perf_counter() - t0,
            "median_step_s": float(np.median(step_s))}


def run_layout(memory: Path, processes: int, threads: int, steps: int) -> list[dict[str, float]]:
    """Start ``processes`` workers with ``threads`` torch threads each, together; their results."""
    with tempfile.TemporaryDirectory() as tmp:
        cmds = [[sys.executable, __file__, "--worker", "--memory", str(memory), "--out", f"{tmp}/{k}",
                 "--threads", str(threads), "--steps", str(steps)] for k in range(processes)]
        procs = [subprocess.Popen(c, cwd=HERE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
                 for c in cmds]
        outs = [p.communicate()[0] for p in procs]
        if any(p.returncode for p in procs):
            raise RuntimeError(f"a training worker failed: {[p.returncode for p in procs]}")
    return [json.loads(o.strip().splitlines()[-1]) for o in outs]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--memory", type=Path, required=True, help="a SLAM run's round_N/memory")
    ap.add_argument("--steps", type=int, default=150)
    ap.add_argument("--threads", type=int, default=2, help="cores to share: torch threads of the one process, "
                    "number of the one-thread processes")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--write", action="store_true")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--out", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        print(json.dumps(time_steps(args.memory, args.out, args.threads, args.steps)))
        return 0
    from gr_graph.experiments.aggregate import fmt_ms, mean_std

    n = args.threads
    layouts = {"one process": (1, n), "processes side by side": (n, 1)}
    runs: dict[str, list[list[dict[str, float]]]] = {k: [] for k in layouts}
    for rep in range(args.repeats):
        for name, (procs, threads) in layouts.items():
            runs[name].append(run_layout(args.memory, procs, threads, args.steps))
            print(f"repeat {rep}: {name}: {[round(r['median_step_s'] * 1e3, 1) for r in runs[name][-1]]} ms a step",
                  flush=True)
    lines = ["| layout | processes x torch threads | median step [ms], per process and repeat | pairs a second |",
             "|---|---|---|---|"]
    rates = {}
    for name, (procs, threads) in layouts.items():
        steps_ms = [[r["median_step_s"] * 1e3 for r in rep] for rep in runs[name]]
        rates[name] = [sum(1e3 / s for s in rep) for rep in steps_ms]
        lines.append(f"| {name} | {procs} x {threads} | {'; '.join(', '.join(f'{s:.0f}' for s in rep) for rep in steps_ms)} "
                     f"| {fmt_ms(mean_std(rates[name]), '{:.1f}')} |")
    ratio = np.mean(rates["processes side by side"]) / np.mean(rates["one process"])
    lines += ["", f"pairs a second, processes side by side / one process: {ratio:.2f}"]
    print("\n".join(lines))
    if args.write:
        from gr_graph.atomic import atomic_write_json, atomic_write_text
        from gr_graph.provenance import machine_line

        atomic_write_json(RESULTS / "training_layout.json", {"machine": machine_line(), "memory": str(args.memory),
                                                             "steps": args.steps, "runs": runs})
        atomic_write_text(RESULTS / "training_layout.md", "# Training throughput of two process layouts\n\n"
                          f"{args.steps} steps of the trainer (default 16-channel configuration, one pair a step) on "
                          f"the {args.memory.parent.name} memory of `{args.memory.parent.parent.name}`; machine: "
                          + machine_line() + "\n\n" + "\n".join(lines) + "\n\nCommand: `python "
                          f"benchmarks/bench_training_layout.py --memory RUN/round_0/memory --steps {args.steps} "
                          f"--threads {n} --repeats {args.repeats} --write`\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
