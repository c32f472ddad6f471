"""Margin of the point-layout test (12-byte x,y,z vs 16-byte x,y,z,intensity) on real and synthetic frames.

Writes ``benchmarks/results/point_layout.md``::

    python benchmarks/bench_point_layout.py [--kitti-root ../shared/data/kitti] [--synthetic-frames 0 500 1000 2000]

Every frame (real KITTI 00 frames from ``--kitti-root`` when it exists, synthetic frames
rendered at 64 and 16 channels) is written in these variants and judged by
:func:`gr_graph.datasets.point_layout.check_point_layout`:

- ``xyzi``: as is (KITTI intensity 0-1); ``xyzi255``: intensity x 255, rounded;
- ``xyz``: 12 bytes a point, truncated to a multiple of 4 points so that the size is a
  multiple of 16 too (the case the size check cannot catch);
- ``... shuffled``: the points in random order (scan-order test blind, column test alone);
- ``xyzir``: 20 bytes a point (a 5th float column), truncated to a multiple of 4 points.

The table gives the two statistics at 12- and 16-byte reading and what the loader decides
for each declared format; the summary gives the margins to the thresholds.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from gr_graph.atomic import atomic_write_text  # noqa: E402
from gr_graph.datasets.base import DatasetError  # noqa: E402
from gr_graph.datasets.point_layout import (  # noqa: E402
    MIXED_KS,
    ORDERED_LOCALITY,
    POINT_FORMATS,
    check_point_layout,
    stride_evidence,
)

TRUE_STRIDE = {"xyzi": 4, "xyzi255": 4, "xyz": 3, "xyzir": 5}


def variants(xyzi: np.ndarray, rng: np.random.Generator) -> Iterator[tuple[str, np.ndarray]]:
    """The file contents (flat float32) of every variant of one ``(N, 4)`` frame."""
    n4 = len(xyzi) // 4 * 4
    i255 = xyzi.copy()
    i255[:, 3] = np.round(i255[:, 3] * 255.0)
    five = np.concatenate([xyzi[:n4], np.arange(n4, dtype=np.float32)[:, None] % 64], axis=1)
    perm = rng.permutation(len(xyzi))
    for name, arr in (("xyzi", xyzi), ("xyzi255", i255), ("xyz", xyzi[:n4, :3]), ("xyzir", five)):
        yield name, np.ascontiguousarray(arr, np.float32).ravel()
        yield name + " shuffled", np.ascontiguousarray(arr[perm[perm < len(arr)]], np.float32).ravel()


def decide(values: np.ndarray, fmt: str) -> str:
    if len(values) % POINT_FORMATS[fmt]:
        return "size"
    try:
        check_point_layout(values, fmt, "f")
    except DatasetError as exc:
        return "refused (" + str(exc).split(": ", 1)[1].split(" points", 1)[0].replace("looks like ", "~") + ")"
    return "accepted"


def small_excerpts(arrays: list[np.ndarray], sizes: tuple[int, ...] = (400, 600, 1000), trials: int = 30,
                   seed: int = 1) -> list[str]:
    """Rows of a table: decisions on short excerpts (contiguous and random subsets) of the frames."""
    rng = np.random.default_rng(seed)
    rows = ["| points | valid xyzi refused | 12-byte (contiguous) missed | 12-byte (shuffled) missed | "
            "valid xyz refused as xyz | xyzi read as xyz missed |", "|---|---|---|---|---|---|"]
    for n in sizes:
        counts = np.zeros(5, int)
        total = 0
        for a in arrays:
            for _ in range(trials):
                total += 1
                m = n // 12 * 12  # a multiple of 4 and 3 points: every size check passes
                start = int(rng.integers(0, len(a) - m))
                cont, sub = a[start:start + m], a[np.sort(rng.choice(len(a), m, replace=False))]
                sub = sub[rng.permutation(m)]
                cases = ((cont, "xyzi", True), (cont[:, :3], "xyzi", False), (sub[:, :3], "xyzi", False),
                         (cont[:, :3], "xyz", True), (cont, "xyz", False))
                for k, (arr, fmt, valid) in enumerate(cases):
                    accepted = decide(np.ascontiguousarray(arr, np.float32).ravel(), fmt) == "accepted"
                    counts[k] += accepted != valid
        rows.append(f"| {n} | " + " | ".join(f"{c}/{total}" for c in counts) + " |")
    return rows


def frames(kitti_root: Path | None, synthetic_frames: list[int]) -> Iterator[tuple[str, np.ndarray]]:
    if kitti_root is not None:
        for f in sorted((kitti_root / "sequences" / "00" / "velodyne").glob("*.bin")):
            yield f"KITTI 00 {f.stem}", np.fromfile(f, np.float32).reshape(-1, 4)
    from gr_graph.datasets.synthetic import SyntheticSequence

    for rings in (64, 16):
        seq = SyntheticSequence(seed=0, n_rings=rings)
        for i in synthetic_frames:
            fr = seq[i]
            arr = np.empty((len(fr), 4), np.float32)
            arr[:, :3] = fr.points
            arr[:, 3] = fr.intensity
            yield f"synthetic {rings}ch {i}", arr


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kitti-root", type=Path, default=REPO.parent / "shared" / "data" / "kitti")
    ap.add_argument("--synthetic-frames", type=int, nargs="*", default=[0, 500, 1000, 2000])
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "point_layout.md")
    args = ap.parse_args(argv)
    root = args.kitti_root if (args.kitti_root / "sequences" / "00" / "velodyne").is_dir() else None
    rng = np.random.default_rng(0)
    rows = ["| frame | variant | 12 B: locality | 12 B: KS | 16 B: locality | 16 B: KS | read as xyzi | read as xyz |",
            "|---|---|---|---|---|---|---|---|"]
    right_ks, wrong_ks, right_loc, wrong_loc, errors, times = [], [], [], [], [], []
    arrays = []
    for label, arr in frames(root, args.synthetic_frames):
        arrays.append(arr)
        for name, values in variants(arr, rng):
            ev = {s: stride_evidence(values, s) for s in (3, 4)}
            truth = TRUE_STRIDE[name.split()[0]]
            for s, e in ev.items():
                (right_ks if s == truth else wrong_ks).append(e.column_ks)
                if "shuffled" not in name:
                    (right_loc if s == truth else wrong_loc).append(e.locality)
            got = {fmt: decide(values, fmt) for fmt in ("xyzi", "xyz")}
            for fmt, verdict in got.items():
                should_accept = POINT_FORMATS[fmt] == truth
                if (verdict == "accepted") != should_accept and verdict != "size":
                    errors.append(f"{label} {name} as {fmt}: {verdict}")
            if name == "xyzi":
                t0 = time.perf_counter()
                check_point_layout(values, "xyzi", "f")
                times.append(time.perf_counter() - t0)
            rows.append(f"| {label} | {name} | {ev[3].locality:.4f} | {ev[3].column_ks:.3f} | "
                        f"{ev[4].locality:.4f} | {ev[4].column_ks:.3f} | {got['xyzi']} | {got['xyz']} |")
    summary = [
        f"Thresholds: columns alike if the largest KS distance < {MIXED_KS}; rows in scan order if "
        f"locality < {ORDERED_LOCALITY}.",
        "",
        "| statistic | at the right layout | at a wrong layout |",
        "|---|---|---|",
        f"| largest KS distance between columns (all variants) | min {min(right_ks):.3f} | max {max(wrong_ks):.3f} |",
        f"| locality (scan-ordered variants) | max {max(right_loc):.4f} | min {min(wrong_loc):.4f} |",
        "",
        f"Margins: KS {min(right_ks) / MIXED_KS:.1f}x above / {MIXED_KS / max(wrong_ks):.1f}x below the threshold; "
        f"locality {ORDERED_LOCALITY / max(right_loc):.0f}x below / {min(wrong_loc) / ORDERED_LOCALITY:.1f}x above.",
        f"Wrong decisions: {len(errors)}" + ("" if not errors else ": " + "; ".join(errors)),
        f"Cost of the check on a valid xyzi frame: median {1e3 * np.median(times):.1f} ms.",
    ]
    shown = os.path.relpath(root, REPO) if root else ""
    source = (f"real KITTI 00 frames from `{shown}` and synthetic frames" if root
              else "synthetic frames only (no KITTI root)")
    text = "\n".join([
        "# Point-layout test: 12-byte x,y,z vs 16-byte x,y,z,intensity",
        "",
        f"`python benchmarks/bench_point_layout.py` on {source}. "
        "`size` = the file size does not fit the declared format (caught before the data test).",
        "",
        *summary, "",
        "## Short excerpts",
        "",
        "Files this short are judged once they hold 256 rows (`MIN_ROWS`); counts are over "
        f"{len(arrays)} frames x 30 random excerpts.",
        "",
        *small_excerpts(arrays), "",
        "## Every frame and variant",
        "",
        *rows, "",
    ])
    atomic_write_text(args.out, text)
    print("\n".join(summary))
    print(f"wrote {args.out}")
    return 1 if errors else 0


if __name__ == "__main__":
    raise SystemExit(main())
