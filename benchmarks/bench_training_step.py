"""Seconds a training step, this checkout against another, and whether they train the same weights (not a test).

Runs ``--steps`` steps of the trainer (``training.trainer.Trainer``, the default configuration of
a 16-channel learning round: one pair a step, ``--threads`` torch threads, deterministic
algorithms) on a memory, in fresh processes, alternating between this checkout and the one given
by ``--compare`` (a ``git worktree`` of another commit) on every repeat. Reports each checkout's
median step time (the first five steps of a run warm up and are left out), the ratio of the
means, and a SHA-256 of the weights after the last step: equal digests mean the two checkouts
train bit-identical networks (every run of a checkout must give the same digest, and the two
checkouts the same one). ``--parts`` adds where this checkout's step goes: the median
milliseconds of sampling the pair, the network's forward pass, the losses (pose layer
included), the backward pass and the Adam step with the trainer's checks, timed one by one
under deterministic algorithms as the trainer runs them. Run::

    python benchmarks/bench_training_step.py --memory RUN/round_0/memory --compare OTHER_CHECKOUT
        [--steps 60] [--repeats 3] [--threads 2] [--parts] [--write]

A memory comes from any SLAM run, e.g. ``python -m gr_graph.slam --frames 0:400 --channels 16
--synthetic-preset kitti --rounds 0 --out RUN``. Writes ``benchmarks/results/training_step.md``
and ``.json`` with ``--write``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"
HERE = Path(__file__).resolve().parents[1]


def weights_digest(model) -> str:
    """SHA-256 of a module's parameters and buffers, in ``state_dict`` order."""
    h = hashlib.sha256()
    for name, tensor in model.state_dict().items():
        h.update(name.encode())
        h.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def run_steps(memory: Path, out: Path, threads: int, steps: int) -> dict[str, float | str]:
    """Median seconds a step over ``steps`` steps in this process and the weights' digest after them."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_training_layout import time_steps

    trained: list = []
    result: dict[str, float | str] = dict(time_steps(memory, out, threads, steps, keep=trained))
    result["weights_sha256"] = weights_digest(trained[0].model)
    return result


def step_parts(memory: Path, out: Path, threads: int, steps: int) -> dict[str, float]:
    """Median milliseconds of each part of a training step over ``steps`` steps (the first five left out)."""
    import torch

    from training.trainer import SkipSample, deterministic_algorithms

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_training_layout import make_trainer

    trainer = make_trainer(memory, out, threads)
    torch.set_num_threads(threads)
    order = trainer.epoch_order(0)
    parts: dict[str, list[float]] = {"sample": [], "forward": [], "losses": [], "backward": [], "adam and checks": []}
    with deterministic_algorithms():
        for k in range(min(steps, len(order))):
            t = [time.perf_counter()]
            sample = trainer.dataset.sample(int(order[k]), 0)
            t.append(time.perf_counter())
            C = trainer.forward(sample)
            t.append(time.perf_counter())
            try:
                loss, _ = trainer.pair_loss(sample, C)
            except SkipSample:  # a pair the trainer would skip: not a step
                trainer.optimizer.zero_grad(set_to_none=False)
                continue
            t.append(time.perf_counter())
            loss.backward()
            t.append(time.perf_counter())
            trainer.apply_gradients()
            trainer.optimizer.zero_grad(set_to_none=False)
            t.append(time.perf_counter())
            for name, a, b in zip(parts, t[:-1], t[1:]):
                parts[name].append(b - a)
    return {name: float(np.median(v[5:]) * 1e3) for name, v in parts.items()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--memory", type=Path, required=True, help="a SLAM run's round_N/memory")
    ap.add_argument("--compare", type=Path, default=None, help="another checkout, measured in turn")
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2, help="torch threads")
    ap.add_argument("--parts", action="store_true", help="also time the parts of this checkout's step")
    ap.add_argument("--write", action="store_true")
    ap.add_argument("--parts-only", action="store_true", help=argparse.SUPPRESS)  # child: time the parts
    ap.add_argument("--one", type=Path, default=None, help=argparse.SUPPRESS)  # child: output directory
    args = ap.parse_args(argv)
    if args.one is not None:
        if args.parts_only:
            print(json.dumps(step_parts(args.memory.resolve(), args.one, args.threads, args.steps)))
        else:
            print(json.dumps(run_steps(args.memory.resolve(), args.one, args.threads, args.steps)))
        return 0
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from checkouts import checkout_label, run_alternating

    trees = {"this": HERE} | ({"other": args.compare.resolve()} if args.compare else {})
    labels = {name: checkout_label(tree) for name, tree in trees.items()}  # the code as measured
    script = Path(__file__).resolve()
    with tempfile.TemporaryDirectory() as tmp:
        def child(name: str, rep: int, parts: bool = False) -> list[str]:
            return (["--one", f"{tmp}/{name}{rep}{'p' if parts else ''}", "--memory", str(args.memory.resolve()),
                     "--steps", str(args.steps), "--threads", str(args.threads)] + (["--parts-only"] if parts else []))

        lines_out = run_alternating(script, trees, args.repeats, child, lambda name, rep, line: print(
            f"repeat {rep}: {name} {json.loads(line)['median_step_s'] * 1e3:.1f} ms a step", flush=True))
        parts = (json.loads(run_alternating(script, {"this": HERE}, 1, lambda n, r: child(n, r, True))["this"][0])
                 if args.parts else None)
    runs = {name: [json.loads(line) for line in rs] for name, rs in lines_out.items()}
    lines = ["| checkout | median step [ms], mean ± std (runs) | weights after the steps (SHA-256, first 12) |",
             "|---|---|---|"]
    for name, rs in runs.items():
        ms = [r["median_step_s"] * 1e3 for r in rs]
        digests = sorted({str(r["weights_sha256"])[:12] for r in rs})
        lines.append(f"| {name} (commit {labels[name]}) | {np.mean(ms):.1f} ± "
                     f"{np.std(ms, ddof=1) if len(ms) > 1 else 0.0:.1f} ({len(ms)}) | {', '.join(digests)} |")
    if args.compare:
        ratio = np.mean([r["median_step_s"] for r in runs["this"]]) / np.mean([r["median_step_s"] for r in runs["other"]])
        digests = [{r["weights_sha256"] for r in runs[name]} for name in ("this", "other")]
        same = len(digests[0]) == 1 and digests[0] == digests[1]  # every run alike, and both checkouts
        lines += ["", f"ratio this / other: {ratio:.3f}; bit-identical weights: {'yes' if same else 'NO'}"]
    if parts is not None:
        lines += ["", "Where a step of this checkout goes (one run, median ms):", "",
                  "| " + " | ".join(parts) + " | sum |", "|" + "---|" * (len(parts) + 1),
                  "| " + " | ".join(f"{v:.1f}" for v in parts.values()) + f" | {sum(parts.values()):.1f} |"]
    print("\n".join(lines))
    if args.write:
        from gr_graph.atomic import atomic_write_json, atomic_write_text
        from gr_graph.provenance import machine_line

        atomic_write_json(RESULTS / "training_step.json", {"machine": machine_line(), "memory": str(args.memory),
                                                           "steps": args.steps, "threads": args.threads, "runs": runs,
                                                           "labels": labels, "parts_ms": parts})
        atomic_write_text(RESULTS / "training_step.md", "# Seconds a training step\n\n"
                          f"{args.steps} steps of the trainer (default 16-channel configuration, one pair a step, "
                          f"{args.threads} torch threads) on the {args.memory.parent.name} memory of "
                          f"`{args.memory.parent.parent.name}`; machine: {machine_line()}\n\n" + "\n".join(lines)
                          + "\n\nCommand: `python benchmarks/bench_training_step.py --memory RUN/round_0/memory "
                          f"--compare OTHER_CHECKOUT --steps {args.steps} --repeats {args.repeats} --threads "
                          f"{args.threads}{' --parts' if parts else ''} --write`\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
