"""What the frame cache (:mod:`gr_graph.datasets.frame_cache`) saves a learning round (not a test).

A learning round reads every frame again: without the cache it renders it again (and builds the
synthetic town again, which the previous round freed); with it, it reads the frame back from
``<out>/frames``. Measured on the same frames, the two ways interleaved (so load from other jobs
falls on both alike):

- ``make``: rendering a frame (the town already built), the cost a learning round pays per frame
  without the cache;
- ``store``: writing a made frame to the cache (round 0 pays it once per frame);
- ``load``: reading a frame back (what a learning round pays with the cache);
- the town's build (paid once per learning round without the cache).

Run::

    python benchmarks/bench_frame_cache.py [--frames 0:120] [--channels 16] [--repeats 3]

Writes ``benchmarks/results/frame_cache.md`` and ``frame_cache.json``.
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import time
from pathlib import Path

import numpy as np

from gr_graph.atomic import atomic_write_json, atomic_write_text
from gr_graph.config import load_config
from gr_graph.datasets.base import release_render_cache
from gr_graph.datasets.frame_cache import CachedFrames
from gr_graph.datasets.registry import open_configured_sequence, parse_frames
from gr_graph.provenance import machine_line

RESULTS = Path(__file__).resolve().parent / "results"


def measure(frames: tuple[int, int], channels: int, repeats: int, preset: str) -> dict:
    cfg = load_config(overrides={"data": {"frames": list(frames), "channels": channels, "synthetic_preset": preset}})
    seq, desc = open_configured_sequence(cfg.data, synthetic_seed=cfg.seed, sensor=cfg.sensor)
    t0 = time.perf_counter()
    seq[0]  # builds the town
    town_s = time.perf_counter() - t0
    n = len(seq)
    make, store, load = [], [], []
    sizes, points = [], []
    with tempfile.TemporaryDirectory() as tmp:
        cache = CachedFrames(seq, Path(tmp) / "frames", key="bench")
        for rep in range(repeats):
            for i in range(n):  # interleaved per frame: make, store, load
                t0 = time.perf_counter()
                frame = seq[i]
                make.append(time.perf_counter() - t0)
                p = cache.path(i)
                p.unlink(missing_ok=True)
                t0 = time.perf_counter()
                cache._store(p, i, frame)
                store.append(time.perf_counter() - t0)
                t0 = time.perf_counter()
                back = cache[i]
                load.append(time.perf_counter() - t0)
                if rep == 0:
                    sizes.append(p.stat().st_size)
                    points.append(len(frame.points))
                    if not np.array_equal(back.points, frame.points):
                        raise AssertionError(f"frame {i}: points read back differ")
    release_render_cache(seq)
    t0 = time.perf_counter()
    seq[0]  # the build a learning round pays after the previous round freed the town
    rebuild_s = time.perf_counter() - t0
    med = {k: float(np.median(v)) for k, v in (("make", make), ("store", store), ("load", load))}
    return {"source": desc, "frames": list(frames), "channels": channels, "preset": preset, "repeats": repeats,
            "mean_points": int(np.mean(points)), "mean_file_mb": float(np.mean(sizes)) / 1e6,
            "median_s": med, "mean_s": {k: float(np.mean(v)) for k, v in (("make", make), ("store", store),
                                                                            ("load", load))},
            "town_build_s": town_s, "town_rebuild_s": rebuild_s,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
            "machine": machine_line()}


def report(r: dict, note: str) -> str:
    m, mean = r["median_s"], r["mean_s"]
    full = 4541
    saved_round = full * (mean["make"] - mean["load"]) + r["town_rebuild_s"]
    return "\n".join([
        "# Frame cache: what a learning round saves",
        "",
        f"Reproduce: `python benchmarks/bench_frame_cache.py --frames {r['frames'][0]}:{r['frames'][1]} "
        f"--channels {r['channels']} --repeats {r['repeats']}`" + (f" ({note})" if note else ""),
        "",
        f"Machine: {r['machine']}. Data: {r['source']}; {r['mean_points']:,} points a frame, "
        f"{r['mean_file_mb']:.2f} MB a cached frame. Each frame made, stored and loaded in turn, "
        f"{r['repeats']} passes (load from other jobs falls on all three alike).",
        "",
        "| per frame | median [ms] | mean [ms] | ratio to make (median) |",
        "|---|---|---|---|",
        *(f"| {k} | {1e3 * m[k]:.1f} | {1e3 * mean[k]:.1f} | {m[k] / m['make']:.3f} |" for k in ("make", "store", "load")),
        "",
        f"Town: built in {r['town_build_s']:.1f} s at the first frame, {r['town_rebuild_s']:.1f} s again after "
        "it was freed (what every learning round paid before the cache).",
        "",
        f"Scaled to the full sequence ({full:,} frames) by the means: a learning round saves "
        f"{full * (mean['make'] - mean['load']) / 60:.1f} min of rendering plus the town's rebuild "
        f"({saved_round / 60:.1f} min in all); round 0 pays {full * mean['store'] / 60:.1f} min of writing and "
        f"{full * r['mean_file_mb'] / 1e3:.1f} GB of disk. Peak RSS of this process: {r['peak_rss_mb']:.0f} MiB.",
        "",
    ])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", default="0:120")
    ap.add_argument("--channels", type=int, default=16, choices=(16, 32, 64))
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--preset", default="kitti")
    ap.add_argument("--note", default="", help="conditions to state in the report")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    r = measure(parse_frames(args.frames), args.channels, args.repeats, args.preset)
    atomic_write_json(args.out / "frame_cache.json", r)
    atomic_write_text(args.out / "frame_cache.md", report(r, args.note))
    print(report(r, args.note))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
