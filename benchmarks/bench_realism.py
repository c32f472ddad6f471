"""How much each sensor effect moves the realism statistics (not a test).

Renders ``--frames`` frame pairs ``(i, i + 1)`` spread evenly along the generated route for
each configuration — the presets ``clean``, ``kitti``, ``raw``, every effect of ``kitti`` on
alone (from ``clean``) and off alone (from ``kitti``) — and computes the statistics of
:mod:`gr_graph.datasets.realism` (issue 9's definitions) on frame ``i``, plus the held-out
VGICP inlier RMSE of ``i`` onto ``i + 1``; the same on the real KITTI 00 frames of
``../shared/data/kitti``. Nothing is tuned to the held-out column.

Run::

    python benchmarks/bench_realism.py [--frames 50] [--real ../shared/data/kitti]

Writes ``benchmarks/results/realism.md`` (and ``realism.json`` beside it).
``--export DIR --preset kitti`` instead writes those frame pairs in KITTI layout, for the
realism CLI: ``python -m gr_graph.datasets.realism ../shared/data/kitti DIR --max-frames 50``
(it picks frames 0, 2, 4, ... of the 100, i.e. the first frame of every pair).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import time
from pathlib import Path

import numpy as np

from gr_graph.atomic import atomic_write_bytes
from gr_graph.datasets.realism import HELD_OUT, STATISTICS, pair_statistics
from gr_graph.datasets.synthetic import SyntheticSequence
from gr_graph.datasets.synthetic.effects import EFFECT_NAMES, SensorEffects, preset

RESULTS = Path(__file__).resolve().parent / "results" / "realism.md"
KEYS = list(STATISTICS) + list(HELD_OUT)
SHORT = {"thickness_cm": "thickness [cm]", "a90": "a90", "a99": "a99", "points_per_frame": "points/frame",
         "median_range_m": "median range [m]", "frac_beyond_40m": "frac > 40 m",
         "vgicp_inlier_rmse_cm": "VGICP inlier RMSE [cm] (held out)"}


def real_statistics(root: Path) -> dict[str, float]:
    files = sorted((root / "sequences" / "00" / "velodyne").glob("*.bin"))
    pts = [np.fromfile(f, dtype=np.float32).reshape(-1, 4)[:, :3].astype(np.float64) for f in files]
    rows = [pair_statistics(pts[k], pts[k + 1]) for k in range(len(pts) - 1)]
    return {k: float(np.nanmean([r[k] for r in rows])) for k in KEYS} | {"frames": len(rows)}


def world_of(world: str, configuration: str) -> str:
    """The world of a configuration: ``world`` unless it is ``preset``, then the world of the
    preset the configuration starts from (``clean`` and ``only <effect>``: the plain town;
    ``kitti``, ``raw`` and ``kitti without <effect>``: the kitti world)."""
    if world != "preset":
        return world
    return "clean" if configuration == "clean" or configuration.startswith("only ") else "kitti"


def synthetic_statistics(effects: SensorEffects, frames: np.ndarray, n_rings: int = 64,
                         world: str = "clean") -> dict[str, float]:
    seq = SyntheticSequence(seed=0, n_rings=n_rings, nthreads=1, effects=effects, world=world)
    rows = [pair_statistics(seq[int(i)].points, seq[int(i) + 1].points) for i in frames]
    return {k: float(np.nanmean([r[k] for r in rows])) for k in KEYS} | {"frames": len(rows)}


class FramePairs:
    """Frames ``(i, i + 1)`` for ``i`` in ``starts`` of a sequence, as one contiguous sequence (so the
    exporter can write them and ``python -m gr_graph.datasets.realism`` reads pairs). Timestamps and
    poses are the selected frames'; every other attribute is the sequence's."""

    def __init__(self, seq: SyntheticSequence, starts: np.ndarray):
        self._seq = seq
        self._idx = np.stack([np.asarray(starts), np.asarray(starts) + 1], axis=1).ravel()
        self.timestamps = seq.timestamps[self._idx]
        self.gt_poses = seq.gt_poses[self._idx]

    def __getattr__(self, name: str):
        return getattr(self._seq, name)

    def __len__(self) -> int:
        return len(self._idx)

    def __getitem__(self, k: int):
        return self._seq[int(self._idx[k])]

    def __repr__(self) -> str:
        return f"FramePairs({self._seq!r}, frames {self._idx[::2].tolist()} and their successors)"


def configurations() -> list[tuple[str, SensorEffects]]:
    kitti = preset("kitti")
    out = [("clean", preset("clean")), ("kitti", kitti), ("raw", preset("raw"))]
    out += [(f"only {n}", preset("clean").with_effect(n, True)) for n in EFFECT_NAMES]
    out += [(f"kitti without {n}", kitti.with_effect(n, False)) for n in EFFECT_NAMES]
    return out


def _fmt(k: str, v: float) -> str:
    if k == "points_per_frame":
        return f"{v:,.0f}"
    if k in ("a90", "a99", "frac_beyond_40m"):
        return f"{v:.3f}"
    return f"{v:.2f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=50, help="frame pairs along the route per configuration")
    ap.add_argument("--real", type=Path, default=Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "kitti")
    ap.add_argument("--only", default=None, help="comma-separated configuration names (default: all)")
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--export", type=Path, default=None,
                    help="only write the frame pairs of --preset to this KITTI-layout folder and exit")
    ap.add_argument("--preset", default="kitti", help="preset of --export")
    ap.add_argument("--world", choices=("preset", "clean", "residential", "kitti"), default="preset",
                    help="world of every configuration (and of --export): preset (that of the preset: clean for "
                         "clean, kitti for the others), clean (the plain town), kitti (the kitti world) or "
                         "residential (every world "
                         "effect and the moving actors)")
    args = ap.parse_args()
    if args.export is not None:
        from gr_graph.datasets.synthetic.writer import write_kitti_layout

        seq = SyntheticSequence(seed=0, nthreads=1, preset=args.preset, world=world_of(args.world, args.preset))
        frames = np.unique(np.round(np.linspace(0, len(seq) - 2, args.frames)).astype(int))
        write_kitti_layout(FramePairs(seq, frames), args.export, overwrite=True)
        return
    load0 = os.getloadavg()
    n_route = len(SyntheticSequence(seed=0))
    frames = np.unique(np.round(np.linspace(0, n_route - 2, args.frames)).astype(int))
    real = real_statistics(args.real)
    print("real", real)
    results: dict[str, dict[str, float]] = {}
    configs = configurations()
    if args.only:
        wanted = set(args.only.split(","))
        configs = [c for c in configs if c[0] in wanted]
    for name, fx in configs:
        t0 = time.perf_counter()
        results[name] = synthetic_statistics(fx, frames, world=world_of(args.world, name))
        print(name, f"{time.perf_counter() - t0:.0f} s", results[name], flush=True)

    def within(k: str, v: float) -> str:
        rel = v / real[k] - 1.0
        return f"{_fmt(k, v)} ({100 * rel:+.0f} %)"

    lines = [
        "# Realism of the synthetic world: statistics against real KITTI 00, and what each sensor effect moves",
        "",
        f"Reproduce: `python benchmarks/bench_realism.py --frames {args.frames} --world {args.world}"
        + (f" --only {args.only}" if args.only else "") + "`",
        "",
        f"- date (UTC): {dt.datetime.now(dt.timezone.utc):%Y-%m-%d %H:%M}; load average {load0[0]:.1f}",
        f"- real: the {real['frames']} consecutive pairs of the 6 real KITTI 00 frames in `../shared/data/kitti`",
        f"- synthetic: seed 0, route seed 0, 64 rings, {len(frames)} frame pairs (i, i+1) spread evenly along "
        f"the route (frames {frames[0]}..{frames[-1]}, every ~{int(np.median(np.diff(frames)))} frames)",
        "- statistics: `gr_graph.datasets.realism` (issue 9: crop 2.5-100 m, 0.5 m voxels, PCA of 10 neighbours; "
        "mean over frames); the VGICP inlier RMSE is a held-out check, nothing was tuned to it",
        "- effects: `gr_graph/datasets/synthetic/effects.py` (parameters and their sources in its docstring); "
        + ("the world of each row follows its preset: `clean` and `only <effect>` the plain town, `kitti`, `raw` "
           "and `kitti without <effect>` the kitti world (`TownConfig.kitti()` + moving actors)"
           if args.world == "preset" else f"every row in the {args.world} world"),
        "",
        "## Against real KITTI 00 (relative difference to real; target +-25 %)",
        "",
        "| | " + " | ".join(SHORT[k] for k in KEYS) + " |",
        "|---|" + "---:|" * len(KEYS),
        "| real KITTI 00 | " + " | ".join(_fmt(k, real[k]) for k in KEYS) + " |",
    ]
    for name in ("clean", "kitti", "raw"):
        if name in results:
            lines.append(f"| {name} | " + " | ".join(within(k, results[name][k]) for k in KEYS) + " |")
    base = results.get("clean")
    kit = results.get("kitti")
    has_effect_rows = any(n.startswith(("only ", "kitti without ")) for n in results)
    if base is not None and kit is not None and has_effect_rows:
        lines += ["", "## What each effect moves", "",
                  "Change of each statistic when the effect is turned on alone (from `clean`) and when it is "
                  "turned off alone (from `kitti`: the change is `kitti` minus `kitti without`, i.e. what the "
                  "effect contributes inside the preset).", "",
                  "| effect | " + " | ".join(SHORT[k] for k in KEYS) + " |",
                  "|---|" + "---:|" * len(KEYS)]
        for n in EFFECT_NAMES:
            on, off = results.get(f"only {n}"), results.get(f"kitti without {n}")
            if on is not None:
                lines.append(f"| {n} on alone | " + " | ".join(
                    f"{on[k] - base[k]:+.3g}" for k in KEYS) + " |")
            if off is not None:
                lines.append(f"| {n} (kitti minus kitti without) | " + " | ".join(
                    f"{kit[k] - off[k]:+.3g}" for k in KEYS) + " |")
        lines += ["", "Absolute values:", "", "| configuration | " + " | ".join(SHORT[k] for k in KEYS) + " |",
                  "|---|" + "---:|" * len(KEYS)]
        lines += [f"| {name} | " + " | ".join(_fmt(k, r[k]) for k in KEYS) + " |" for name, r in results.items()]
    text = "\n".join(lines) + "\n"
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(args.out, text.encode())
    atomic_write_bytes(args.out.with_suffix(".json"),
                       (json.dumps({"real": real, "synthetic": results, "frames": frames.tolist()}, indent=2)
                        + "\n").encode())
    print(text)


if __name__ == "__main__":
    main()
