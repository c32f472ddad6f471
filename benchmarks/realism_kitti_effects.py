"""How much each change of the kitti world moves the realism statistics (not a test).

Each row turns one group of :meth:`TownConfig.kitti` back to the value of
:meth:`TownConfig.residential` (the world before), everything else as in the kitti preset
(sensor effects and moving actors included), and reports the statistics of
:mod:`gr_graph.datasets.realism` over ``--frames`` frame pairs spread along the route; the
change is ``kitti`` minus ``kitti without <group>`` (what the group contributes).

Run::

    python benchmarks/realism_kitti_effects.py [--frames 12] [--out benchmarks/results/realism_kitti_effects.md]
"""

from __future__ import annotations

import argparse
import datetime as dt
import os
from pathlib import Path

import numpy as np

from gr_graph.atomic import atomic_write_text
from gr_graph.datasets.realism import HELD_OUT, STATISTICS, pair_statistics
from gr_graph.datasets.synthetic import SyntheticSequence
from gr_graph.datasets.synthetic.town import TownConfig

KEYS = list(STATISTICS) + list(HELD_OUT)
SHORT = {"thickness_cm": "thickness [cm]", "a90": "a90", "a99": "a99", "points_per_frame": "points/frame",
         "median_range_m": "median range [m]", "frac_beyond_40m": "frac > 40 m",
         "vgicp_inlier_rmse_cm": "VGICP inlier RMSE [cm] (held out)"}
_BEFORE = TownConfig.residential()
GROUPS = {
    "recessed windows": ("window_recesses", "window_recess"),
    "property-line hedges (fraction, height, gaps; no plain low walls)": (
        "hedge_fraction", "hedge_height", "property_gap", "low_walls"),
    "front-garden shrubs (spacing, size, tree fraction)": (
        "garden_spacing", "garden_tree_fraction", "garden_shrub_radii", "garden_shrub_width"),
    "street trees every 5-12 m": ("street_tree_spacing",),
    "houses up to 25 m back": ("building_setback_max",),
    "kerbside parking 0.8": ("parking_stay", "parking_start"),
    "tree leaf area density 1.5": ("leaf_area_density",),
}


def statistics(town: TownConfig, frames: np.ndarray) -> dict[str, float]:
    seq = SyntheticSequence(seed=0, nthreads=1, preset="kitti", town_config=town)
    rows = [pair_statistics(seq[int(i)].points, seq[int(i) + 1].points) for i in frames]
    return {k: float(np.nanmean([r[k] for r in rows])) for k in KEYS}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results" / "realism_kitti_effects.md")
    args = ap.parse_args()
    n = len(SyntheticSequence(seed=0, preset="clean"))
    frames = np.unique(np.round(np.linspace(0, n - 2, args.frames)).astype(int))
    load0 = os.getloadavg()
    kitti = statistics(TownConfig.kitti(), frames)
    print("kitti", kitti, flush=True)
    rows = {"residential (the world before)": statistics(_BEFORE, frames)}
    print(rows, flush=True)
    for name, fields in GROUPS.items():
        rows[name] = statistics(TownConfig.kitti(**{f: getattr(_BEFORE, f) for f in fields}), frames)
        print(name, rows[name], flush=True)

    def fmt(k: str, v: float) -> str:
        return f"{v:,.0f}" if k == "points_per_frame" else f"{v:.3f}" if k in ("a90", "a99", "frac_beyond_40m") \
            else f"{v:.2f}"

    lines = [
        "# What each change of the kitti world moves (leave one group out)",
        "",
        f"Reproduce: `python benchmarks/realism_kitti_effects.py --frames {args.frames}`",
        "",
        f"- date (UTC): {dt.datetime.now(dt.timezone.utc):%Y-%m-%d %H:%M}; load average {load0[0]:.1f}",
        f"- {len(frames)} frame pairs (i, i+1) spread along the route (frames {frames[0]}..{frames[-1]}), seed 0, "
        "64 rings, the kitti preset (sensor effects and moving actors); each row: the kitti world with one group "
        "set back to `TownConfig.residential()` (the world before this change). Few frames: differences below "
        "~0.5 cm thickness / 0.01 in a90, a99 are within the frame-to-frame spread.",
        "",
        "## kitti minus kitti without the group (what the group contributes)",
        "",
        "| group | " + " | ".join(SHORT[k] for k in KEYS) + " |",
        "|---|" + "---:|" * len(KEYS),
    ]
    for name, r in rows.items():
        lines.append(f"| {name} | " + " | ".join(f"{kitti[k] - r[k]:+.3g}" for k in KEYS) + " |")
    lines += ["", "## Absolute values", "", "| world | " + " | ".join(SHORT[k] for k in KEYS) + " |",
              "|---|" + "---:|" * len(KEYS), "| kitti | " + " | ".join(fmt(k, kitti[k]) for k in KEYS) + " |"]
    lines += [f"| kitti without {name} | " + " | ".join(fmt(k, r[k]) for k in KEYS) + " |"
              if not name.startswith("residential") else f"| {name} | " + " | ".join(fmt(k, r[k]) for k in KEYS) + " |"
              for name, r in rows.items()]
    atomic_write_text(args.out, "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
