"""What rendering only the kept rings saves at 32 and 16 channels (not a test).

``open_sequence(channels=32|16)`` on the synthetic world casts only the rings it keeps (every 2nd /
4th of the 64 beams); before, it rendered all 64 and dropped the others
(:func:`gr_graph.datasets.channels.subsample_channels`). Each ray keeps its random draws from the full
beam grid, so the two give the same frames. Measured on frames spread along the route, the two ways
interleaved frame by frame (so load from other jobs falls on both alike), with every field of every
frame compared bit for bit:

- ``every ring``: render the 64 rings, then subsample (the former cost of a frame);
- ``kept rings``: the frame as ``open_sequence`` now makes it.

Run::

    python benchmarks/bench_render_channels.py [--frames 40] [--repeats 2] [--preset kitti] [--write]

Writes ``benchmarks/results/render_channels.md`` and ``render_channels.json`` with ``--write``.
"""

from __future__ import annotations

import argparse
import resource
import time

import numpy as np

from gr_graph.datasets.channels import subsample_channels
from gr_graph.datasets.registry import open_sequence
from gr_graph.datasets.synthetic import SyntheticSequence
from gr_graph.provenance import machine_line

FIELDS = ("points", "intensity", "ring", "time")


def same_frame(a, b) -> bool:
    """Whether two frames agree in every field, bit for bit (None only where both are None)."""
    for field in FIELDS:
        x, y = getattr(a, field), getattr(b, field)
        if (x is None) != (y is None):
            return False
        if x is not None and (x.dtype != y.dtype or not np.array_equal(x, y)):
            return False
    return (a.index, a.timestamp, a.n_rings) == (b.index, b.timestamp, b.n_rings)


def measure(channels: int, frames: np.ndarray, repeats: int, preset: str) -> dict:
    """Median and mean milliseconds a frame both ways, and how many frames differ."""
    every_ring = SyntheticSequence(seed=0, preset=preset)
    kept, _ = open_sequence(channels=channels, synthetic_preset=preset)
    every_ring[int(frames[0])]  # the town is built once, outside the timing
    times: dict[str, list[float]] = {"every ring": [], "kept rings": []}
    differing, points = 0, []
    for rep in range(repeats):
        for i in frames:
            t0 = time.perf_counter()
            old = subsample_channels(every_ring[int(i)], channels)
            t1 = time.perf_counter()
            new = kept[int(i)]
            t2 = time.perf_counter()
            times["every ring"].append(t1 - t0)
            times["kept rings"].append(t2 - t1)
            if rep == 0:
                differing += not same_frame(old, new)
                points.append(len(new.points))
    med = {k: float(np.median(v) * 1e3) for k, v in times.items()}
    return {"channels": channels, "preset": preset, "frames": [int(i) for i in frames], "repeats": repeats,
            "median_ms": med, "mean_ms": {k: float(np.mean(v) * 1e3) for k, v in times.items()},
            "ratio_median": med["kept rings"] / med["every ring"], "frames_differing": differing,
            "mean_points": float(np.mean(points))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=40, help="frames, evenly spread along the route")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--preset", default="kitti")
    ap.add_argument("--write", action="store_true")
    args = ap.parse_args(argv)
    n_route = len(SyntheticSequence(seed=0, preset=args.preset))
    frames = np.linspace(0, n_route - 1, args.frames).round().astype(int)
    rows = [measure(ch, frames, args.repeats, args.preset) for ch in (32, 16)]
    lines = ["# Rendering only the kept rings (32 and 16 channels)", "",
             f"Reproduce: `python benchmarks/bench_render_channels.py --frames {args.frames} --repeats "
             f"{args.repeats} --preset {args.preset} --write`", "",
             f"- machine: {machine_line()}",
             f"- `{args.preset}` preset, seed 0, {args.frames} frames evenly spread over the route's {n_route}, "
             f"{args.repeats} passes, the two ways interleaved frame by frame; the town built before timing",
             "", "| channels | every ring rendered, then subsampled [ms a frame, median] | kept rings only "
             "[ms] | ratio | frames differing (any field, bit for bit) | points a frame |",
             "|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['channels']} | {r['median_ms']['every ring']:.1f} | {r['median_ms']['kept rings']:.1f} | "
                     f"{r['ratio_median']:.2f} | {r['frames_differing']} of {args.frames} | {r['mean_points']:.0f} |")
    lines += ["", f"Peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0:.0f} MB."]
    from results_io import print_and_write

    print_and_write("render_channels", "\n".join(lines), {"machine": machine_line(), "rows": rows}, args.write)
    return 1 if any(r["frames_differing"] for r in rows) else 0


if __name__ == "__main__":
    raise SystemExit(main())
