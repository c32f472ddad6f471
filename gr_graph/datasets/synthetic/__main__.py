"""Render the synthetic sequence to disk in KITTI layout.

By default the sensor drives the project's generated route (``--route-seed``); ``--trajectory``
renders along a KITTI (12 floats a row, camera frame) or TUM pose file, or the poses of a KITTI
root, instead.

Writes ``DIR/sequences/00/{velodyne/%06d.bin, calib.txt, times.txt, synthetic.json}`` and
``DIR/poses/00.txt`` (camera frame), readable by the KITTI loader (``--data-root DIR``).
``--point-format xyz`` writes 12-byte x,y,z points without intensity, as some public
datasets do (read them back with ``--point-format xyz``).
``--preset`` chooses the world and its sensor (``kitti`` by default: the residential world
with moving actors and KITTI-like sensor effects; ``clean``: the plain town and an ideal
sensor; ``raw``: ``kitti`` with the full motion distortion; see
``gr_graph.datasets.synthetic.effects``, ``.town`` and ``.actors``); ``raw`` scans also get
``sequences/00/times/%06d.npy``, each point's sweep fraction (float32, in file order).
``--world`` overrides the preset's world (``kitti``: the world of the ``kitti`` preset;
``residential``: every world effect at its first amounts (``TownConfig.residential()``) and the
moving actors; ``clean``: the plain town).
"""

from __future__ import annotations

import argparse
import sys

from gr_graph.cli_common import (
    add_channels,
    add_frames,
    add_log_level,
    add_no_progress,
    add_out,
    add_point_format,
    add_seed,
    add_sensor,
    add_threads,
    make_parser,
    setup_logging,
)
from gr_graph.datasets.synthetic.effects import PRESETS
from gr_graph.datasets.synthetic.sequence import DEFAULT_PRESET, WORLDS, SyntheticSequence
from gr_graph.datasets.registry import parse_frames
from gr_graph.datasets.synthetic.writer import write_kitti_layout

EXAMPLES = (
    "python -m gr_graph.datasets.synthetic --out /tmp/synth --frames 0:200 --seed 0",
    "python -m gr_graph.datasets.synthetic --out /tmp/synth16 --frames 0:200 --channels 16 --no-progress",
    "python -m gr_graph.datasets.synthetic --out /tmp/synth_r3 --frames 0:100 --route-seed 3",
    "python -m gr_graph.datasets.synthetic --out /tmp/synth_raw --frames 0:100 --preset raw",
    "python -m gr_graph.datasets.synthetic --out /tmp/synth_vlp16 --frames 0:100 --sensor vlp16",
    "python -m gr_graph.datasets.synthetic --out /tmp/synth_clean --frames 0:100 --preset clean",
)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``python -m gr_graph.datasets.synthetic``."""
    ap = make_parser("python -m gr_graph.datasets.synthetic", __doc__, EXAMPLES)
    add_out(ap, "dataset root to write", required=True)
    add_frames(ap, help="half-open frame range A:B of the sequence (default: all)")
    add_seed(ap, "seed of the town and the noise")
    ap.add_argument("--route-seed", type=int, default=0, metavar="N", help="seed of the generated route")
    ap.add_argument("--trajectory", default=None, metavar="PATH",
                    help="render along this KITTI/TUM pose file or KITTI root instead of the generated route")
    add_sensor(ap, help="beam model rendered (gr_graph.sensors)", default="hdl64e")
    add_channels(ap, help="laser rings rendered of a 64-beam sensor (default: all the sensor's beams)", default=None)
    add_point_format(ap, help="layout of the written .bin files: float32 x,y,z,intensity (KITTI, 16 bytes a point) "
                              "or x,y,z (12 bytes a point)")
    ap.add_argument("--max-range", type=float, default=None, metavar="M",
                    help="largest range [m] (default: the sensor's: 120 HDL-64E and OS1-64, 100 VLP-16)")
    ap.add_argument("--n-azimuth", type=int, default=None, metavar="N",
                    help="azimuth steps of a revolution (default: the sensor's: 2000, 1800, 1024)")
    ap.add_argument("--preset", choices=PRESETS, default=None,
                    help=f"the world and its sensor: clean (plain town, ideal sensor), kitti (residential world "
                         f"with moving actors, KITTI-like sensor effects) or raw (kitti with the full motion "
                         f"distortion) (default: {DEFAULT_PRESET})")
    ap.add_argument("--world", choices=WORLDS, default=None,
                    help="override the preset's world: clean (no world effect), residential (porous vegetation, "
                         "facade details, fences, hedges, gardens, curved cars, moving vehicles and pedestrians at "
                         "their first amounts) or kitti (residential with recessed windows and the composition of "
                         "KITTI 00's streets: the world of the kitti preset)")
    add_threads(ap, "ray-casting threads (0 = all)", default=0)
    ap.add_argument("--overwrite", action="store_true", help="replace existing .bin files in DIR")
    add_no_progress(ap)
    add_log_level(ap)
    return ap


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    args = build_parser().parse_args(argv)
    setup_logging(args.log_level)
    try:
        seq = SyntheticSequence(seed=args.seed, n_rings=args.channels, max_range=args.max_range,
                                n_azimuth=args.n_azimuth, nthreads=args.threads,
                                route_seed=args.route_seed, trajectory=args.trajectory,
                                preset=args.preset, world=args.world, sensor=args.sensor)
        frames = range(*parse_frames(args.frames, len(seq)))
        out = write_kitti_layout(seq, args.out, frames, overwrite=args.overwrite, progress=not args.no_progress,
                                 point_format=args.point_format)
    except (ValueError, FileExistsError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {len(frames)} frames to {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
