"""``gr-densify IN OUT`` (``python -m gr_graph.densify_cli``): densify one point cloud with a trained network.

Reads ``IN`` (``.bin``/``.pcd``/``.ply``/``.npy``, :mod:`gr_graph.cloud_io`), densifies it with
:func:`gr_graph.densify.densify_cloud` (Algorithm 2 of the paper, the same code the learning
rounds use) and writes the densified cloud to ``OUT`` in the format of its extension; with
``--covariances FILE.npy`` also the ``(M, 3, 3)`` covariance of every output point (its source
point's), with ``--ply-covariances`` the same as PLY properties of ``OUT``. Prints one JSON
line with the counts.

Exit codes: 0 done, 2 bad input (the message names the file).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from gr_graph.cli_common import (
    add_device,
    add_log_level,
    add_point_format,
    add_seed,
    at_least,
    make_parser,
    number_in,
    setup_logging,
)
from gr_graph.config import PreprocessConfig, TrainingConfig

EXAMPLES = (
    "python -m gr_graph.densify_cli scan.pcd dense.ply",
    "python -m gr_graph.densify_cli scan.pcd dense.ply --weights runs/slam/round_1/training/model.pt",
    "python -m gr_graph.densify_cli 000000.bin dense.pcd --weights model.pt --tau-ani 0.8 --samples 8 "
    "--covariances dense_cov.npy",
    "python -m gr_graph.densify_cli scan.npy dense.ply --weights model.pt --ply-covariances --seed 1",
)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``gr-densify``."""
    t, pre = TrainingConfig(), PreprocessConfig()
    p = make_parser("gr-densify",
                    "Densify one point cloud (Algorithm 2): a trained network predicts a covariance per point; "
                    "points with anisotropy above --tau-ani each gain --samples samples of N(s, C) (by default every "
                    "point is kept too; --no-keep-original --no-keep-dropped: the paper's, the samples replace the "
                    "anisotropic points and the others are dropped). "
                    "The cloud is first preprocessed like a SLAM scan (range crop around the origin, voxel "
                    "downsampling), which is the network's training input.",
                    EXAMPLES)
    p.add_argument("input", metavar="IN", help="input cloud: .bin (KITTI float32), .pcd, .ply or .npy")
    p.add_argument("output", metavar="OUT", help="output cloud, format from the extension: .ply, .pcd, .bin or .npy")
    p.add_argument("--weights", default="pretrained", metavar="pretrained|PATH",
                   help="'pretrained' (the model shipped with gr_graph; see the README's model card) or a model.pt "
                        "written by `gr-train` or by a gr-slam --rounds run (round_<r>/training/model.pt) "
                        "(default: pretrained)")
    p.add_argument("--tau-ani", type=number_in(float, 0.0, 1.0), default=None, metavar="A",
                   help=f"anisotropy threshold: keep points with 1 - l_min/l_max > A (default: {t.tau_ani})")
    p.add_argument("--samples", type=at_least(1), default=None, metavar="M",
                   help=f"samples ~ N(s, C) per kept point (default: {t.samples_per_point})")
    p.add_argument("--keep-original", action=argparse.BooleanOptionalAction, default=None,
                   help=f"also write the kept points themselves (default: {t.keep_original}; the paper: no)")
    p.add_argument("--keep-dropped", action=argparse.BooleanOptionalAction, default=None,
                   help=f"also write the points the anisotropy filter drops, unchanged (default: {t.keep_dropped}; "
                        "the paper: no)")
    p.add_argument("--covariances", default=None, metavar="FILE.npy",
                   help="also write the (M, 3, 3) covariance of every output point [m^2]")
    p.add_argument("--ply-covariances", action="store_true",
                   help="OUT is .ply: store the covariances as properties cov_xx, cov_xy, cov_xz, cov_yy, cov_yz, cov_zz")
    p.add_argument("--voxel-size", type=number_in(float, 0.0, low_open=True), default=None, metavar="M",
                   help=f"voxel downsampling before the network; must match the network's training data "
                        f"(default: {pre.voxel_size})")
    p.add_argument("--min-range", type=number_in(float, 0.0), default=None, metavar="M",
                   help=f"drop points closer than this to the origin (default: {pre.min_range})")
    p.add_argument("--max-range", type=number_in(float, 0.0), default=None, metavar="M",
                   help=f"drop points farther than this from the origin (default: {pre.max_range})")
    add_point_format(p, help="layout of an IN .bin file: float32 x,y,z,intensity (16 bytes a point) or x,y,z (12 bytes)")
    add_seed(p, "seed of the network's input split and of the sampling")
    add_device(p)
    add_log_level(p)
    return p


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Densify ``args.input`` into ``args.output``; return the counts printed by :func:`main`."""
    import numpy as np

    from gr_graph.atomic import atomic_path
    from gr_graph.cloud_io import check_suffix, read_cloud_counted, write_cloud
    from gr_graph.densify import densify_cloud

    out = Path(args.output)
    check_suffix(out)  # before the network runs: an OUT of unknown format fails at once
    if args.ply_covariances and out.suffix.lower() != ".ply":
        raise ValueError(f"{out}: --ply-covariances needs a .ply OUT")
    if args.covariances is not None:
        if Path(args.covariances).suffix.lower() != ".npy":
            raise ValueError(f"{args.covariances}: --covariances writes a .npy file")
        for other, what in ((out, "OUT"), (Path(args.input), "IN")):
            if Path(args.covariances).resolve() == other.resolve():
                raise ValueError(f"{args.covariances}: --covariances is {what}; it would be overwritten")
    default = PreprocessConfig()
    lo = default.min_range if args.min_range is None else args.min_range
    hi = default.max_range if args.max_range is None else args.max_range
    if lo >= hi:  # said with the options' names, before the config's own check
        raise ValueError(f"--min-range {lo:g} m is not below --max-range {hi:g} m: no point would be left")
    pre = PreprocessConfig(**{k: v for k, v in (("voxel_size", args.voxel_size), ("min_range", args.min_range),
                                                 ("max_range", args.max_range)) if v is not None})
    points, intensity, dropped = read_cloud_counted(args.input, args.point_format)
    try:
        res = densify_cloud(points, args.weights, intensity=intensity, tau_ani=args.tau_ani,
                            samples_per_point=args.samples, keep_original=args.keep_original,
                            keep_dropped=args.keep_dropped, seed=args.seed, device=args.device, preprocess=pre)
    except (ValueError, FloatingPointError) as exc:
        raise ValueError(f"{args.input}: {exc}") from None
    C = res.covariances
    if args.covariances is not None:  # first, so that a finished OUT always has its covariances beside it
        with atomic_path(args.covariances) as tmp, open(tmp, "wb") as fh:  # a handle: np.save appends ".npy"
            np.save(fh, C)  # to a name that ends otherwise (".NPY")
    write_cloud(out, res.points, res.intensity, C if args.ply_covariances else None)
    return {"input": str(args.input), "output": str(out), "input_points": len(points), "dropped_points": dropped,
            "network_points": len(res.network_input), "kept_points": res.n_kept, "output_points": len(res.points),
            "fallback": res.fallback, "covariances": args.covariances}


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``gr-densify``; returns the exit code."""
    args = build_parser().parse_args(argv)
    setup_logging(args.log_level)
    from gr_graph.datasets.base import DatasetError

    try:
        summary = run(args)
    except (DatasetError, ValueError, OSError, RuntimeError) as exc:  # TrainingError is a RuntimeError
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except ImportError as exc:  # open3d for .pcd files
        print(f"error: {exc} (needed for {args.input} / {args.output})", file=sys.stderr)
        return 2
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
