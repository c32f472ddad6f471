"""CPU time per frame of a learning round's network pass (not a test), optionally against another checkout.

A learning round runs, for every frame: preprocessing, the network's covariances
(neighbourhoods + forward), the positive-definiteness check, the anisotropy filter and the
sampling, and the densified points' intensity (:class:`gr_graph.densify.DensifiedSequence`).
Measured on ``--frames`` rendered frames of the ``kitti`` preset (rendering excluded), with the
shipped weights, 1 torch thread, as the CPU time of the measuring thread (so other jobs on the
machine inflate it less than wall time). With ``--compare DIR`` (a checkout of another commit)
each repeat runs this checkout and that one in turn, in fresh processes.

Run::

    python benchmarks/bench_network_pass.py [--frames 40] [--repeats 6] [--compare /path/to/other/checkout]

Writes ``benchmarks/results/network_pass.md`` and ``network_pass.json`` with ``--write``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"
HERE = Path(__file__).resolve().parents[1]


class _Rendered:
    """``sequence`` with its first frames served from memory (every other attribute its own)."""

    def __init__(self, sequence, frames: list) -> None:
        self._sequence, self._frames = sequence, frames

    def __len__(self) -> int:
        return len(self._frames)

    def __getitem__(self, i: int):
        return self._frames[i]

    def __getattr__(self, name: str):
        return getattr(self._sequence, name)


def measure(n_frames: int, channels: int) -> float:
    """Mean CPU milliseconds per frame of the network pass in this process."""
    import torch

    torch.set_num_threads(1)
    from gr_graph.config import load_config
    from gr_graph.datasets.registry import open_configured_sequence
    from gr_graph.densify import densified_sequence
    from gr_graph.pretrained import resolve_weights

    cfg = load_config(overrides={"data": {"frames": [300, 300 + n_frames], "channels": channels,
                                          "synthetic_preset": "kitti"}})
    seq, _ = open_configured_sequence(cfg.data, synthetic_seed=cfg.seed, sensor=cfg.sensor)
    frames = [seq[i] for i in range(n_frames)]  # rendered once, outside the measurement
    ds = densified_sequence(_Rendered(seq, frames), resolve_weights("pretrained"), cfg.training, device="cpu",
                            preprocess=cfg.preprocess)
    ds[0]  # warm-up
    t0 = time.thread_time()
    for i in range(1, n_frames):
        ds[i]
    return (time.thread_time() - t0) / (n_frames - 1) * 1e3


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--channels", type=int, default=16, choices=(16, 32, 64))
    ap.add_argument("--repeats", type=int, default=6)
    ap.add_argument("--compare", type=Path, default=None, help="another checkout, measured in turn")
    ap.add_argument("--write", action="store_true")
    ap.add_argument("--one", action="store_true", help=argparse.SUPPRESS)  # child process: print one figure
    args = ap.parse_args(argv)
    if args.one:
        print(f"{measure(args.frames, args.channels):.2f}")
        return 0
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from checkouts import checkout_label, run_alternating

    trees = {"this": HERE} | ({"other": args.compare.resolve()} if args.compare else {})
    labels = {name: checkout_label(tree) for name, tree in trees.items()}  # the code as measured
    runs = run_alternating(Path(__file__).resolve(), trees, args.repeats,
                           lambda name, rep: ["--one", "--frames", str(args.frames), "--channels", str(args.channels)],
                           lambda name, rep, line: print(f"repeat {rep}: {name} {float(line):.1f} ms/frame", flush=True))
    out = {name: [float(v) for v in lines] for name, lines in runs.items()}
    import numpy as np

    lines = ["| checkout | CPU ms per frame, mean ± std (n) |", "|---|---|"]
    for name, vals in out.items():
        lines.append(f"| {name} (commit {labels[name]}) | {np.mean(vals):.1f} ± {np.std(vals, ddof=1) if len(vals) > 1 else 0:.1f}"
                     f" ({len(vals)}) |")
    if args.compare:
        lines.append(f"\nratio this / other: {np.mean(out['this']) / np.mean(out['other']):.3f}")
    print("\n".join(lines))
    if args.write:
        from gr_graph.atomic import atomic_write_json, atomic_write_text
        from gr_graph.provenance import machine_line

        atomic_write_json(RESULTS / "network_pass.json", {"machine": machine_line(), "frames": args.frames,
                                                          "channels": args.channels, "ms_per_frame": out})
        atomic_write_text(RESULTS / "network_pass.md", "# Network pass of a learning round, CPU time per frame\n\n"
                          f"{args.frames} frames of the `kitti` preset at {args.channels} channels (frames "
                          f"300:{300 + args.frames}), shipped weights, 1 torch thread; machine: {machine_line()}\n\n"
                          + "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
