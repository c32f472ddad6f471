"""Seconds a training step, this checkout against another, and whether they train the same weights (not a test).

Runs ``--steps`` steps of the trainer (``training.trainer.Trainer``, the default configuration of
a 16-channel learning round: one pair a step, ``--threads`` torch threads, deterministic
algorithms) on a memory, in fresh processes, alternating between this checkout and the one given
by ``--compare`` (a ``git worktree`` of another commit) on every repeat. Reports each checkout's
median step time (the first five steps of a run warm up and are left out), the ratio of the
means, and a SHA-256 of the weights after the last step: equal digests mean the two checkouts
train bit-identical networks. Run::

    python benchmarks/bench_training_step.py --memory RUN/round_0/memory --compare OTHER_CHECKOUT
        [--steps 60] [--repeats 3] [--threads 2] [--write]

A memory comes from any SLAM run, e.g. ``python -m gr_graph.slam --frames 0:400 --channels 16
--synthetic-preset kitti --rounds 0 --out RUN``. Writes ``benchmarks/results/training_step.md``
and ``.json`` with ``--write``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
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


def _commit(tree: Path) -> str:
    """``tree``'s short commit, with ", uncommitted changes" when its tracked files differ from it."""
    res = subprocess.run(["git", "-C", str(tree), "rev-parse", "--short=7", "HEAD"], capture_output=True, text=True)
    dirty = subprocess.run(["git", "-C", str(tree), "status", "--porcelain", "--untracked-files=no"],
                           capture_output=True, text=True).stdout.strip()
    return (res.stdout.strip() or "?") + (", uncommitted changes" if dirty else "")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--memory", type=Path, required=True, help="a SLAM run's round_N/memory")
    ap.add_argument("--compare", type=Path, default=None, help="another checkout, measured in turn")
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2, help="torch threads")
    ap.add_argument("--write", action="store_true")
    ap.add_argument("--one", type=Path, default=None, help=argparse.SUPPRESS)  # child: output directory
    args = ap.parse_args(argv)
    if args.one is not None:
        print(json.dumps(run_steps(args.memory.resolve(), args.one, args.threads, args.steps)))
        return 0
    trees = {"this": HERE} | ({"other": args.compare.resolve()} if args.compare else {})
    runs: dict[str, list[dict[str, float | str]]] = {k: [] for k in trees}
    with tempfile.TemporaryDirectory() as tmp:
        for rep in range(args.repeats):
            for name, tree in trees.items():
                cmd = [sys.executable, str(Path(__file__).resolve()), "--one", f"{tmp}/{name}{rep}", "--memory",
                       str(args.memory.resolve()), "--steps", str(args.steps), "--threads", str(args.threads)]
                res = subprocess.run(cmd, cwd=tree, env={**os.environ, "PYTHONPATH": str(tree)}, capture_output=True,
                                     text=True)
                if res.returncode:
                    raise SystemExit(f"the {name} checkout ({tree}) failed:\n{res.stderr[-2000:]}")
                runs[name].append(json.loads(res.stdout.strip().splitlines()[-1]))
                print(f"repeat {rep}: {name} {runs[name][-1]['median_step_s'] * 1e3:.1f} ms a step", flush=True)
    lines = ["| checkout | median step [ms], mean ± std (runs) | weights after the steps (SHA-256, first 12) |",
             "|---|---|---|"]
    for name, rs in runs.items():
        ms = [r["median_step_s"] * 1e3 for r in rs]
        digests = sorted({str(r["weights_sha256"])[:12] for r in rs})
        lines.append(f"| {name} (commit {_commit(trees[name])}) | {np.mean(ms):.1f} ± "
                     f"{np.std(ms, ddof=1) if len(ms) > 1 else 0.0:.1f} ({len(ms)}) | {', '.join(digests)} |")
    if args.compare:
        ratio = np.mean([r["median_step_s"] for r in runs["this"]]) / np.mean([r["median_step_s"] for r in runs["other"]])
        same = {r["weights_sha256"] for r in runs["this"]} == {r["weights_sha256"] for r in runs["other"]}
        lines += ["", f"ratio this / other: {ratio:.3f}; bit-identical weights: {'yes' if same else 'NO'}"]
    print("\n".join(lines))
    if args.write:
        from gr_graph.atomic import atomic_write_json, atomic_write_text
        from gr_graph.provenance import machine_line

        atomic_write_json(RESULTS / "training_step.json", {"machine": machine_line(), "memory": str(args.memory),
                                                           "steps": args.steps, "threads": args.threads, "runs": runs})
        atomic_write_text(RESULTS / "training_step.md", "# Seconds a training step\n\n"
                          f"{args.steps} steps of the trainer (default 16-channel configuration, one pair a step, "
                          f"{args.threads} torch threads) on the {args.memory.parent.name} memory of "
                          f"`{args.memory.parent.parent.name}`; machine: {machine_line()}\n\n" + "\n".join(lines)
                          + "\n\nCommand: `python benchmarks/bench_training_step.py --memory RUN/round_0/memory "
                          f"--compare OTHER_CHECKOUT --steps {args.steps} --repeats {args.repeats} --threads "
                          f"{args.threads} --write`\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
