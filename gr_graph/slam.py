"""The main command: ``python -m gr_graph.slam --seq 00 [options]``.

Runs SLAM (round 0, raw scans) and, with ``--rounds N``, N learning rounds (Algorithm 3;
they need the trainer). Without a KITTI root it runs on the synthetic sequence (the
project's generated route through a procedural town) and says so.
Outputs (see :mod:`gr_graph.pipeline`) go to ``--out``; rerunning with the same ``--out``
skips finished rounds.

Examples
--------
::

    python -m gr_graph.slam --seq 00 --frames 0:300 --out runs/synth_0_300
    python -m gr_graph.slam --seq 00 --data-root ../shared/data/kitti --out runs/kitti_0_6
    python -m gr_graph.slam --seq 00 --channels 16 --config my.yaml --out runs/c16
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from typing import Any

from gr_graph.config import load_config, parse_frames


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m gr_graph.slam",
        description="gr_graph LiDAR SLAM: VGICP odometry, loop closures, gtsam pose graph, memory.",
    )
    p.add_argument("--seq", default=None, help="KITTI sequence (default 00)")
    p.add_argument("--data-root", default=None, help="KITTI odometry root (default: $GR_GRAPH_KITTI_ROOT, else synthetic)")
    p.add_argument("--channels", type=int, choices=(64, 32, 16), default=None)
    p.add_argument("--frames", default=None, help="frame range A:B (half-open)")
    p.add_argument("--route-seed", type=int, default=None, help="synthetic: seed of the generated route (default 0)")
    p.add_argument("--trajectory", default=None,
                   help="synthetic: render along this KITTI/TUM pose file or KITTI root instead of the route")
    p.add_argument("--synthetic-preset", choices=("clean", "kitti", "raw"), default=None,
                   help="synthetic: sensor effects preset (default: the sequence's default)")
    p.add_argument("--rounds", type=int, default=None, help="learning rounds after round 0 (default 0)")
    p.add_argument("--out", default=None, help="output directory (default runs/slam)")
    p.add_argument("--config", default=None, help="YAML file with config sections (see gr_graph/config.py)")
    p.add_argument("--device", choices=("cpu", "cuda"), default=None, help="device of the learning rounds")
    p.add_argument("--no-loops", action="store_true", help="odometry only (no loop closures)")
    p.add_argument("--no-resume", action="store_true", help="recompute rounds even if finished")
    p.add_argument("--no-memory", action="store_true", help="do not write the memory")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--log-level", default="INFO")
    return p


def overrides_from_args(args: argparse.Namespace) -> dict[str, Any]:
    """Command-line options as a nested config override (only the options that were given)."""
    o: dict[str, Any] = {"data": {}, "output": {}, "training": {}, "loops": {}}
    if args.seq is not None:
        o["data"]["seq"] = args.seq
    if args.data_root is not None:
        o["data"]["data_root"] = args.data_root
    if args.channels is not None:
        o["data"]["channels"] = args.channels
    if args.frames is not None:
        o["data"]["frames"] = parse_frames(args.frames)
    if args.route_seed is not None:
        o["data"]["route_seed"] = args.route_seed
    if args.trajectory is not None:
        o["data"]["trajectory"] = args.trajectory
    if args.synthetic_preset is not None:
        o["data"]["synthetic_preset"] = args.synthetic_preset
    if args.rounds is not None:
        if args.rounds < 0:
            raise ValueError("--rounds must be >= 0")
        o["training"]["rounds"] = args.rounds
    if args.out is not None:
        o["output"]["out_dir"] = args.out
    if args.device is not None:
        o["device"] = args.device
    if args.no_loops:
        o["loops"]["enabled"] = False
    if args.no_resume:
        o["output"]["resume"] = False
    if args.no_memory:
        o["output"]["write_memory"] = False
    if args.quiet:
        o["output"]["progress"] = False
    return {k: v for k, v in o.items() if v != {}}


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=getattr(logging, str(args.log_level).upper(), logging.INFO),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        cfg = load_config(args.config, overrides_from_args(args))
    except (ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    from gr_graph.datasets.base import DatasetError
    from gr_graph.pipeline import LearningRoundsUnavailable, SlamPipeline

    try:
        pipe = SlamPipeline(cfg)
        metrics = pipe.run()
    except (DatasetError, LearningRoundsUnavailable) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    last = metrics["rounds"][max(metrics["rounds"], key=int)]
    brief = {"out": cfg.output.out_dir, "frames": last["n_frames"], "loops": last["n_loops"],
             "flagged_odometry_edges": last["n_flagged_odometry_edges"],
             "runtime_s": round(last["runtime_s"]["total"], 1)}
    if "slam" in last:
        s = last["slam"]
        brief.update({k: s.get(k) for k in ("rpe300_consecutive_mean", "ate_rmse", "kitti_t_err_percent")})
    print(json.dumps(brief))
    return 0


if __name__ == "__main__":
    sys.exit(main())
