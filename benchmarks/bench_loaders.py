"""Dataloaders: reading speed per format, and SLAM on a generated bag against the same frames rendered directly.

Writes ``benchmarks/results/loaders.md``::

    python benchmarks/bench_loaders.py [--frames 40]

A short motion-distorted drive (16 rings, the ``raw`` preset: per-point times, 8 m/s along a
gentle S-curve; the helpers of ``tests/loader_support.py``) is written as a ROS2 bag (sqlite3
and MCAP), a ROS1 bag, a folder of binary PCD (open3d) and a folder of ``.npy``; each is opened
(the bags index every message once) and read frame by frame. SLAM then runs (round 0, no loops,
no memory) on the ROS2 bag with ``deskew: auto`` and ``off``, and on the synthetic sequence
itself along the same trajectory (``--channels 16``, the same frames up to float32); the ATE is
the pipeline's (evo, aligned) against the rendered poses.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))

from gr_graph.atomic import atomic_write_text  # noqa: E402
from gr_graph.datasets.folder import FolderSequence  # noqa: E402
from gr_graph.datasets.rosbag import RosbagSequence  # noqa: E402
from gr_graph.datasets.synthetic.effects import interpolate_poses  # noqa: E402
from gr_graph.trajectory import write_kitti_poses  # noqa: E402
from loader_support import CloudLayout, cloud_array, drive, write_bag  # noqa: E402


def read_all(open_fn) -> tuple[float, float, int]:
    """(open seconds, read seconds, points) of opening a sequence and reading every frame."""
    t0 = time.perf_counter()
    seq = open_fn()
    t1 = time.perf_counter()
    n = sum(len(f) for f in seq)
    return t1 - t0, time.perf_counter() - t1, n


def run_slam(args: list[str], out: Path) -> dict:
    from gr_graph.slam import main

    t0 = time.perf_counter()
    code = main(args + ["--out", str(out), "--no-loops", "--no-memory", "--no-progress", "--log-level", "WARNING"])
    if code != 0:
        raise RuntimeError(f"slam {args} exited {code}")
    r = json.loads((out / "metrics.json").read_text())["rounds"]["0"]
    return {"ate": r["slam"]["ate_rmse"], "deskew": r["deskew"]["enabled"], "wall": time.perf_counter() - t0}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "loaders.md")
    args = ap.parse_args(argv)
    load0 = os.getloadavg()[0]
    n = args.frames
    with tempfile.TemporaryDirectory(prefix="bench_loaders-") as tmp:
        root = Path(tmp)
        seq = drive("raw", n, str(root / "drive"))
        t0 = time.perf_counter()
        frames = [seq[i] for i in range(n)]
        render_s = time.perf_counter() - t0
        arrays = [cloud_array(f, CloudLayout(with_time=True)) for f in frames]
        bags = {kind: write_bag(root / f"bag_{kind}" if kind != "ros1" else root / "drive.bag",
                                {"/points": arrays}, kind=kind) for kind in ("ros2", "mcap", "ros1")}
        import open3d as o3d

        (root / "pcd").mkdir()
        (root / "npy").mkdir()
        for k, (f, a) in enumerate(zip(frames, arrays)):
            pc = o3d.t.geometry.PointCloud(o3d.core.Tensor(f.points.astype(np.float32)))
            pc.point.intensity = o3d.core.Tensor(f.intensity[:, None])
            pc.point.t = o3d.core.Tensor((f.time * 0.1).astype(np.float32)[:, None])
            o3d.t.io.write_point_cloud(str(root / "pcd" / f"{k}.pcd"), pc)
            np.save(root / "npy" / f"{k}.npy", a)
        rows = ["| format | open (index) s | read s | frames/s | points/frame |", "|---|---|---|---|---|"]
        rows.append(f"| rendering (reference) | - | {render_s:.2f} | {n / render_s:.0f} | "
                    f"{np.mean([len(f) for f in frames]):.0f} |")
        for label, fn in (("ROS2 bag (sqlite3)", lambda: RosbagSequence(bags["ros2"])),
                          ("ROS2 bag (MCAP)", lambda: RosbagSequence(bags["mcap"])),
                          ("ROS1 bag", lambda: RosbagSequence(bags["ros1"])),
                          ("folder of binary PCD", lambda: FolderSequence(root / "pcd")),
                          ("folder of structured .npy", lambda: FolderSequence(root / "npy"))):
            open_s, read_s, pts = read_all(fn)
            rows.append(f"| {label} | {open_s:.3f} | {read_s:.3f} | {n / read_s:.0f} | {pts / n:.0f} |")
        gt = np.linalg.inv(seq.gt_poses[0]) @ seq.gt_poses  # mid-sweep, where the deskewed poses refer
        # the ground truth a user gives, one pose a scan at its stamp: the bag's times count from the stamps,
        # which mark the sweeps' starts, half a sweep before the rendered poses (the loader moves it back)
        at_stamps = np.array([interpolate_poses(seq.timestamps, gt, np.array([t - 0.5 * seq.scan_period]), k)[0]
                              for k, t in enumerate(seq.timestamps)])
        write_kitti_poses(root / "gt.txt", np.linalg.inv(at_stamps[0]) @ at_stamps)
        runs = {
            "ROS2 bag, deskew auto (on: per-point times)": run_slam([str(bags["ros2"]), "--poses", str(root / "gt.txt")],
                                                                    root / "run_auto"),
            "ROS2 bag, deskew off": run_slam([str(bags["ros2"]), "--poses", str(root / "gt.txt"), "--deskew", "off"],
                                             root / "run_off"),
            "synthetic sequence directly, same trajectory, --channels 16": run_slam(
                ["--trajectory", str(root / "drive" / f"trajectory_{n}.tum"), "--synthetic-preset", "raw",
                 "--channels", "16"], root / "run_synth"),
        }
        travelled = float(np.sum(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1)))
    slam_rows = ["| input | deskew | ATE (m) | wall s |", "|---|---|---|---|"]
    slam_rows += [f"| {k} | {'on' if v['deskew'] else 'off'} | {v['ate']:.4f} | {v['wall']:.1f} |"
                  for k, v in runs.items()]
    load1 = os.getloadavg()[0]
    text = "\n".join([
        "# Dataloaders", "",
        f"`python benchmarks/bench_loaders.py --frames {n}`: {n} frames, 16 rings, preset `raw`, "
        f"{travelled:.1f} m driven. Load average {load0:.1f} -> {load1:.1f} (2 shared cores).", "",
        "## Reading", "", *rows, "",
        "## SLAM on the bag (round 0, no loops)", "", *slam_rows, "",
        "The bag's per-point times count from each message's stamp, the sweep's start; its ground truth is "
        "given as a user would, one pose a scan at the stamp, and the loader moves stamps and ground truth to "
        "the sweeps' middles, where the deskewed poses refer (`gr_graph.datasets.stamp_shift`). The direct "
        "run is evaluated against the rendered mid-sweep poses.", "",
    ])
    atomic_write_text(args.out, text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
