"""Render the synthetic sequence to disk in KITTI layout.

Examples::

    python -m gr_graph.datasets.synthetic --out /tmp/synth --frames 0:200 --seed 0
    python -m gr_graph.datasets.synthetic --out /tmp/synth --route-seed 3
    python -m gr_graph.datasets.synthetic --out /tmp/synth --trajectory poses.txt
    python -m gr_graph.datasets.synthetic --out /tmp/synth --frames 0:100 --world residential

write ``/tmp/synth/sequences/00/{velodyne/%06d.bin, calib.txt, times.txt}`` and
``/tmp/synth/poses/00.txt`` (camera frame), readable by the KITTI loader. By default the
sensor drives the project's generated route (``--route-seed``); ``--trajectory`` renders
along a KITTI (12 floats a row, camera frame) or TUM pose file, or the poses of a KITTI root.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from gr_graph.datasets.synthetic.actors import ActorsConfig
from gr_graph.datasets.synthetic.sequence import SyntheticSequence
from gr_graph.datasets.synthetic.town import TownConfig
from gr_graph.datasets.synthetic.writer import parse_frames, write_kitti_layout


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m gr_graph.datasets.synthetic", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True, help="dataset root DIR")
    ap.add_argument("--frames", default=None, help="A:B, frames A..B-1 (default: all)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the town and the noise (default 0)")
    ap.add_argument("--route-seed", type=int, default=0, help="seed of the generated route (default 0)")
    ap.add_argument("--trajectory", default=None,
                    help="render along this KITTI/TUM pose file or KITTI root instead of the route")
    ap.add_argument("--n-rings", type=int, default=64, help="64, 32 or 16 (default 64)")
    ap.add_argument("--max-range", type=float, default=120.0, help="metres (default 120)")
    ap.add_argument("--n-azimuth", type=int, default=2000, help="azimuth steps (default 2000)")
    ap.add_argument("--threads", type=int, default=0, help="ray-casting threads (0 = all)")
    ap.add_argument("--world", choices=("clean", "residential"), default="clean",
                    help="world effects: clean (none, default) or residential (porous vegetation, facade "
                         "details, fences, hedges, gardens, curved cars, moving vehicles and pedestrians)")
    ap.add_argument("--overwrite", action="store_true", help="replace existing .bin files in DIR")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        world = {} if args.world == "clean" else {"town_config": TownConfig.residential(),
                                                  "actors": ActorsConfig()}
        seq = SyntheticSequence(seed=args.seed, n_rings=args.n_rings, max_range=args.max_range,
                                n_azimuth=args.n_azimuth, nthreads=args.threads,
                                route_seed=args.route_seed, trajectory=args.trajectory, **world)
        frames = parse_frames(args.frames, len(seq))
        out = write_kitti_layout(seq, args.out, frames, overwrite=args.overwrite)
    except (ValueError, FileExistsError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {len(frames)} frames to {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
