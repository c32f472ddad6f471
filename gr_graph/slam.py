"""The main command: ``python -m gr_graph.slam [PATH] [--seq 00] [options]``.

PATH is any supported dataset (a ROS bag or MCAP, a folder of scans, a KITTI raw drive or
odometry root; see :mod:`gr_graph.datasets.registry`).

Runs SLAM (round 0, raw scans) and, with ``--rounds N``, N learning rounds (Algorithm 3;
they need the trainer). Without a KITTI root it runs on the synthetic sequence (the
project's generated route through a procedural town) and says so.
Outputs (see :mod:`gr_graph.pipeline`) go to ``--out``; rerunning with the same ``--out``
skips finished rounds, unless the data changed since (replaced, added or deleted scans): then it
stops with an error (exit code 2) asking for a new ``--out`` or ``--no-resume``. A run in which
too few scans are usable for a trajectory (e.g. scans in millimetres, all cropped away by
``preprocess.max_range``) stops with an error too (exit code 2) instead of writing a trajectory of guesses. Each learning round is accepted or rejected by a test without ground
truth (:mod:`gr_graph.round_acceptance`); a rejection stops the rounds, and the final trajectory
(the last round of the unbroken run of accepted rounds) is written to ``--out``/poses_kitti.txt
and named in the one-line JSON summary printed at the end (``final_round``, ``final_poses``).

Examples: see ``EXAMPLES`` (shown by ``--help``).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from pathlib import Path
from typing import Any

from gr_graph.cli_common import (
    add_channels,
    add_config,
    add_data_root,
    add_device,
    add_frames,
    add_log_level,
    add_no_progress,
    add_out,
    add_point_format,
    add_seed,
    add_sensor,
    make_parser,
    setup_logging,
)
from gr_graph.config import (
    PAPER_TRAINING,
    DataConfig,
    GraphConfig,
    OdometryConfig,
    SlamConfig,
    TrainingConfig,
    config_to_yaml,
    load_config,
    merge_config,
    option_choices,
)
from gr_graph.datasets.registry import DATASETS, parse_frames

log = logging.getLogger(__name__)


EXAMPLES = (
    "python -m gr_graph.slam recording.bag --topic /velodyne_points --out runs/my_bag",
    "python -m gr_graph.slam --seq 00 --frames 0:300 --out runs/synth_0_300",
    "python -m gr_graph.slam --seq 00 --data-root ../shared/data/kitti --out runs/kitti_0_6",
    "python -m gr_graph.slam --seq 00 --frames 0:400 --channels 16 --rounds 1 --out runs/c16_r1 --no-progress",
    "python -m gr_graph.slam --seq 00 --sensor vlp16 --frames 0:300 --out runs/vlp16_0_300",
    "python -m gr_graph.slam --seq 00 --trajectory /path/to/kitti/poses/00.txt --frames 0:300 --out runs/along_kitti00",
)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``python -m gr_graph.slam``.

    Options left out keep the value of ``--config`` (or the default of :mod:`gr_graph.config`,
    quoted in the help).
    """
    d = SlamConfig()
    p = make_parser("python -m gr_graph.slam",
                    "gr_graph LiDAR SLAM: VGICP odometry, loop closures, gtsam pose graph, memory; "
                    "options override --config, which overrides the defaults of gr_graph/config.py.",
                    EXAMPLES)
    add_config(p, "YAML file with config sections (see gr_graph/config.py)")
    p.add_argument("path", nargs="?", default=None, metavar="PATH",
                   help="data to run on: a ROS1 .bag, ROS2 bag folder or .mcap; a folder of .bin/.pcd/.ply/.npy "
                        "scans; a KITTI raw drive; a KITTI odometry root (default: data.path, else --data-root, "
                        "else the synthetic sequence)")
    p.add_argument("--dataset", choices=DATASETS, default=None,
                   help=f"kind of data at PATH (default: {d.data.dataset}: guessed from the path)")
    p.add_argument("--topic", default=None, help="bags: the sensor_msgs/PointCloud2 topic (needed when the bag "
                                                 "has several; the error lists them)")
    p.add_argument("--timestamps", default=None, metavar="FILE",
                   help="folders of scans: one timestamp (s) a scan (default: times.txt/timestamps.txt next to "
                        "the scans, else 0.1 s apart)")
    p.add_argument("--poses", default=None, metavar="FILE",
                   help="folders of scans and bags: ground-truth LiDAR poses, KITTI or TUM format, one a scan")
    p.add_argument("--seq", default=None, help=f"KITTI odometry sequence (default: {d.data.seq})")
    add_data_root(p)
    add_point_format(p, default=None, help="layout of .bin scans (KITTI folders, raw drives, folders of .bin): float32 "
                                           "x,y,z,intensity (16 bytes a point) or x,y,z (12 bytes, no intensity) "
                                           f"(default: {d.data.point_format})")
    add_channels(p, default=None, help="laser rings kept of a 64-beam sensor: every 1st, 2nd or 4th "
                                       "(default: all the sensor's beams)")
    add_sensor(p, help="the sensor that took the scans (synthetic data: the beam model rendered); sets "
                       f"sensor.model and its beams, keeping the other sensor keys (default: {d.sensor.model})")
    add_frames(p, help="half-open frame range A:B (default: all frames)")
    p.add_argument("--route-seed", type=int, default=None, metavar="N",
                   help=f"synthetic: seed of the generated route (default: {d.data.route_seed})")
    p.add_argument("--trajectory", default=None, metavar="PATH",
                   help="synthetic: render along this KITTI/TUM pose file or KITTI root instead of the route")
    p.add_argument("--synthetic-preset", choices=option_choices(DataConfig, "synthetic_preset"), default=None,
                   help="synthetic data: the world and its sensor: clean (plain town, ideal sensor), kitti "
                        "(residential world, moving actors, KITTI-like sensor errors) or raw (kitti with the full "
                        "motion distortion) (default: kitti)")
    p.add_argument("--rounds", type=int, default=None, metavar="N",
                   help=f"learning rounds after round 0 (default: {d.training.rounds})")
    p.add_argument("--weights", default=None, metavar="pretrained|PATH",
                   help="learning round 1 starts from these weights: 'pretrained' (shipped with gr_graph, see the "
                        "README's model card) or a model.pt; a configuration with 0 rounds gets 1 "
                        "(default: random initial weights)")
    p.add_argument("--densify", action="store_true",
                   help="with --weights: exactly one learning round, which densifies with the weights as they "
                        "are, without training")
    p.add_argument("--paper-method", action="store_true",
                   help="learning rounds with the paper's Gaussian correspondence likelihood and densification "
                        "(samples replace the anisotropic points, the others are dropped) instead of the defaults "
                        "(a Student t; every point kept, the samples added); see the README's 'Defaults that are "
                        "not the paper's'")
    add_out(p, f"output directory (default: {d.output.out_dir})")
    add_seed(p, f"seed of the synthetic data and of the learning rounds: sets seed and training.seed "
                f"(default: {d.seed})", default=None)
    add_device(p, f"device of the learning rounds (default: {d.device})", default=None)
    p.add_argument("--no-loops", action="store_true", help="odometry only (no loop closures)")
    p.add_argument("--loop-min-path", type=float, default=None, metavar="M",
                   help="loop candidates lie at least M metres of path back along the estimate, not only "
                        "loops.min_frame_gap frames: a vehicle stopped longer than that closes no loops with itself; "
                        f"0: off (default: {d.loops.min_path_length})")
    p.add_argument("--deskew", choices=option_choices(OdometryConfig, "deskew"), default=None,
                   help="constant-velocity motion compensation of each scan to mid-sweep; auto: on for sequences "
                        f"that are not motion-compensated, off for KITTI odometry folders (default: {d.odometry.deskew})")
    p.add_argument("--kitti-vertical-correction", type=float, default=None, metavar="DEG",
                   help="raise every point's elevation by DEG degrees (KITTI folders and raw drives, the synthetic sequence; any data) "
                        "(KISS-ICP: 0.205) "
                        f"(default: {d.data.kitti_vertical_correction_deg})")
    p.add_argument("--loop-variance", choices=option_choices(GraphConfig, "loop_variance"), default=None,
                   help="loop edges' information: as registered, divided by the loops' variance factor estimated "
                        "from the graph's residuals, or that and then weakened per axis where an axis needs it "
                        f"(default: {d.graph.loop_variance})")
    p.add_argument("--ground-tilt-offset", action=argparse.BooleanOptionalAction, default=None,
                   help="widen every registered edge's roll and pitch by the disagreement of its rotation with the "
                        "ground planes of its two scans (gr_graph.ground_tilt) "
                        f"(default: {'on' if d.graph.ground_tilt_offset else 'off'})")
    p.add_argument("--registration-covariance", choices=option_choices(GraphConfig, "registration_covariance"), default=None,
                   help="information of registered edges: the scaled registration Hessian, or the cluster-robust "
                        f"covariance from the residuals (default: {d.graph.registration_covariance})")
    p.add_argument("--learned-noise-covariance", choices=option_choices(TrainingConfig, "learned_noise_covariance"),
                   default=None,
                   help="learning rounds: each edge's learned information is the network's H(C), or the inverse of "
                        "the cluster-robust covariance of the same learned cost (its shape over the six axes from the "
                        "residuals), or that with the offset of the edge's pose from the learned cost's minimum "
                        f"(default: {d.training.learned_noise_covariance})")
    p.add_argument("--map-keyframe", type=float, nargs=2, default=None, metavar=("M", "DEG"),
                   help="odometry map ('map' mode): a scan enters it only after moving M metres or turning DEG "
                        "degrees since the last one that entered, e.g. 0.1 1; 0 leaves that test out (default: "
                        f"{d.odometry.map_keyframe_translation} {d.odometry.map_keyframe_rotation_deg}: every scan)")
    p.add_argument("--long-baseline-guard", type=float, nargs="?", const=0.05, default=None, metavar="FRACTION",
                   help="learning rounds: also reject a round whose trajectory agrees worse with direct "
                        "registrations of scans 25 m apart (median rotation discrepancy up by more than FRACTION; "
                        "0.05 when given alone); for a well-calibrated sensor (with KITTI: together with "
                        "--kitti-vertical-correction): see the README's 'Learning rounds that never make things worse'; "
                        "put PATH before it, or write --long-baseline-guard=FRACTION (default: off)")
    p.add_argument("--no-resume", action="store_true",
                   help="recompute rounds even if finished (also when the data changed since they were made)")
    p.add_argument("--no-memory", action="store_true", help="do not write the memory")
    p.add_argument("--dump-config", action="store_true",
                   help="print the resolved configuration (defaults, --config, options) as YAML and exit")
    p.add_argument("--viz", action="store_true",
                   help="at the end, open an open3d window on the map of the final trajectory's round (the last "
                        "accepted one; needs a display)")
    add_no_progress(p, deprecated=("--quiet",))
    add_log_level(p)
    return p


def overrides_from_args(args: argparse.Namespace) -> dict[str, Any]:
    """Command-line options as a nested config override (only the options that were given)."""
    o: dict[str, Any] = {"data": {}, "output": {}, "training": {}, "loops": {}, "odometry": {}, "graph": {}}
    if args.seq is not None:
        o["data"]["seq"] = args.seq
    for key in ("path", "dataset", "topic", "timestamps", "poses"):
        if getattr(args, key) is not None:
            o["data"][key] = getattr(args, key)
    if args.data_root is not None:
        o["data"]["data_root"] = args.data_root
    if args.channels is not None:
        o["data"]["channels"] = args.channels
    if args.sensor is not None:  # a catalogue model: its beams replace those of --config
        o["sensor"] = {"model": args.sensor, "n_beams": None, "vertical_fov_deg": None, "elevations_deg": None}
    if args.point_format is not None:
        o["data"]["point_format"] = args.point_format
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
    if args.weights is not None:
        if args.rounds == 0:
            raise ValueError("--weights is for a learning round: it cannot go with --rounds 0")
        o["training"]["weights"] = args.weights
    if args.densify:  # the weights may come from --config (the configuration checks that there are some)
        o["training"]["fine_tune"] = False
        if args.rounds not in (None, 1):
            raise ValueError(f"--densify runs exactly one learning round (--rounds {args.rounds} given)")
        o["training"]["rounds"] = 1
    if args.paper_method:
        o["training"] = merge_config(o["training"], PAPER_TRAINING)
    if args.out is not None:
        o["output"]["out_dir"] = args.out
    if args.device is not None:
        o["device"] = args.device
    if args.seed is not None:
        o["seed"] = args.seed
        o["training"]["seed"] = args.seed
    if args.no_loops:
        o["loops"]["enabled"] = False
    if args.loop_min_path is not None:
        o["loops"]["min_path_length"] = args.loop_min_path
    if args.deskew is not None:
        o["odometry"]["deskew"] = args.deskew
    if args.kitti_vertical_correction is not None:
        o["data"]["kitti_vertical_correction_deg"] = args.kitti_vertical_correction
    if args.long_baseline_guard is not None:
        o["training"]["acceptance"] = {"max_long_baseline_rotation_increase": args.long_baseline_guard}
    if args.loop_variance is not None:
        o["graph"]["loop_variance"] = args.loop_variance
    if args.registration_covariance is not None:
        o["graph"]["registration_covariance"] = args.registration_covariance
    if args.ground_tilt_offset is not None:
        o["graph"]["ground_tilt_offset"] = args.ground_tilt_offset
    if args.learned_noise_covariance is not None:
        o["training"]["learned_noise_covariance"] = args.learned_noise_covariance
    if args.map_keyframe is not None:
        translation, rotation_deg = args.map_keyframe
        o["odometry"]["map_keyframe_translation"] = translation
        o["odometry"]["map_keyframe_rotation_deg"] = rotation_deg
    if args.no_resume:
        o["output"]["resume"] = False
    if args.no_memory:
        o["output"]["write_memory"] = False
    if args.no_progress:
        o["output"]["progress"] = False
    return {k: v for k, v in o.items() if v != {}}


def full_method_hint(argv: list[str]) -> str:
    """The one line printed after a run without learning rounds: the same command with one
    learning round, trained from random initial weights as in Table I (``--weights`` dropped).

    Not from the shipped weights: fine-tuning them gained less than training from scratch on
    every seed of Table I's 16-channel window after one round (all-pairs RPE-300 +2.1 ± 5.1 %
    against −32.5 ± 29.5 %; README, model card), at the same training time.
    """
    import shlex

    extra = ["--rounds", "1"]
    with_value = ("--rounds", "--weights")  # dropped with their values: extra sets --rounds, no --weights
    drop = ("--viz", "--densify", "--no-resume", "--no-memory")  # the hint reuses round 0 and its memory
    keep: list[str] = []
    skip = False
    for a in argv:
        if skip:
            skip = False
        elif a in with_value:
            skip = True
        elif a not in drop and not a.startswith(tuple(f"{w}=" for w in with_value)):
            keep.append(a)
    return ("this was round 0 (SLAM on the raw scans); the full method adds a learning round (the finished round 0 "
            "in the same --out is reused): " + " ".join(["python", "-m", "gr_graph.slam", *map(shlex.quote, keep),
                                                          *extra]))


def learning_flags_given(args: argparse.Namespace) -> list[str]:
    """The options given that only act on learning rounds (the training, the acceptance test, the network's
    device), spelled as on the command line."""
    given = []
    if args.paper_method:
        given.append("--paper-method")
    if args.long_baseline_guard is not None:
        given.append("--long-baseline-guard")
    if args.device is not None:
        given.append(f"--device {args.device}")
    if args.learned_noise_covariance is not None:
        given.append(f"--learned-noise-covariance {args.learned_noise_covariance}")
    return given


def out_dir_problem(out: Path) -> str | None:
    """Why results cannot be written to ``out`` (a file, or a folder that cannot be written or
    created: the first existing one of it and its parents must be a writable folder), or None.
    Nothing is created."""
    existing = out
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        return f"--out {out}: {existing} is a file, not a folder"
    if not os.access(existing, os.W_OK | os.X_OK):
        return f"--out {out}: {existing} is not writable"
    return None


def _is_training_error(exc: BaseException) -> bool:
    """Whether ``exc`` is a :class:`training.trainer.TrainingError` (the trainer's module, which imports
    torch, is only looked up: a run that raised one has imported it)."""
    trainer = sys.modules.get("training.trainer")
    return trainer is not None and isinstance(exc, trainer.TrainingError)


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    args = build_parser().parse_args(argv)
    setup_logging(args.log_level)
    try:
        cfg = load_config(args.config, overrides_from_args(args))
        if cfg.training.weights is not None and cfg.training.rounds == 0 and args.rounds is None:
            cfg.training.rounds = 1  # weights are for a learning round
        if cfg.training.rounds > 0 and not args.dump_config:
            from gr_graph.pipeline import check_learning_config

            check_learning_config(cfg)  # before the data are opened: a bad --weights fails at once
    except (ValueError, FileNotFoundError, RuntimeError) as exc:  # TrainingError is a RuntimeError
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.dump_config:
        print(config_to_yaml(cfg), end="")
        return 0
    idle = learning_flags_given(args)
    if idle and cfg.training.rounds == 0:
        log.warning("%s only act on learning rounds, and this run has none (--rounds 0): ignored", ", ".join(idle))
    from gr_graph.datasets.base import DatasetError
    from gr_graph.memory import MemoryFormatError
    from gr_graph.pipeline import OutBusyError, ResumeDataError, SlamPipeline

    problem = out_dir_problem(Path(cfg.output.out_dir))
    if problem:  # before the data are opened (a bag is read through once when opened)
        print(f"error: {problem}", file=sys.stderr)
        return 2
    try:
        pipe = SlamPipeline(cfg)
        metrics = pipe.run()
    except (DatasetError, ResumeDataError, OutBusyError) as exc:  # DatasetError: also too few usable scans
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # a full disk, a folder that became unwritable: the message names the path
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except Exception as exc:  # a damaged memory or checkpoint, a training that failed: one line, not a traceback
        if not (isinstance(exc, MemoryFormatError) or _is_training_error(exc)):
            raise
        print(f"error: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1
    final_round = metrics["final_round"]
    final = metrics["rounds"][str(final_round)]
    brief = {"out": cfg.output.out_dir, "final_round": final_round,
             "final_poses": str(Path(cfg.output.out_dir) / "poses_kitti.txt"),
             "accepted_rounds": metrics["accepted_rounds"], "rejected_rounds": metrics["rejected_rounds"],
             "frames": final["n_frames"], "loops": final["n_loops"],
             "flagged_odometry_edges": final["n_flagged_odometry_edges"],
             "runtime_s": round(sum(s["runtime_s"]["total"] for s in metrics["rounds"].values()), 1),
             "resumed_rounds": pipe.resumed_rounds}
    if "slam" in final:
        s = final["slam"]
        brief.update({k: s.get(k) for k in ("rpe300_consecutive_mean", "ate_rmse", "kitti_t_err_percent")})
    print(json.dumps(brief))
    if cfg.training.rounds == 0:
        print(full_method_hint(sys.argv[1:] if argv is None else argv), file=sys.stderr)
    if args.viz:
        from gr_graph.map_export import map_path
        from gr_graph.round_output import round_dir
        from gr_graph.viewer import show_map

        show_map(map_path(round_dir(cfg.output.out_dir, int(metrics["final_round"]))),
                 title=f"gr_graph map: {cfg.output.out_dir}, round {metrics['final_round']} (the final trajectory)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
