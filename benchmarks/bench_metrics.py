"""Benchmark of the metrics area: trajectory I/O, trajectory metrics, global registration.

Writes ``benchmarks/results/metrics.md`` (and the global-registration pairs/results JSON
under ``benchmarks/results/global_registration/``).

    python benchmarks/bench_metrics.py [--n-pairs 100] [--channels 64 32 16] [--skip-registration]

Global registration runs on the sequence :func:`gr_graph.datasets.registry.open_sequence`
gives (KITTI 00 if a root is configured, otherwise the synthetic sequence along the
generated route), on the raw
scans (no learned reasoning), with the paper's protocol: pairs within 10 m, success =
rotation error < 10 deg and translation error < 2 m.
"""

from __future__ import annotations

import argparse
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from gr_graph import global_registration as greg  # noqa: E402
from gr_graph.metrics import trajectory_metrics  # noqa: E402
from gr_graph.trajectory import (  # noqa: E402
    atomic_write_text,
    read_kitti_poses,
    read_tum_poses,
    write_kitti_poses,
    write_tum_poses,
)



def route_gt_camera() -> np.ndarray:
    """The generated route (route seed 0) as camera-frame poses, as a KITTI GT file holds them."""
    from gr_graph.datasets.base import velo_to_cam_poses
    from gr_graph.datasets.synthetic import rig
    from gr_graph.datasets.synthetic.route import generate_route

    return velo_to_cam_poses(np.asarray(generate_route(0).T_w_velo), rig.T_cam_velo())


def best_of(fn, repeat: int = 3) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def bench_trajectory() -> list[str]:
    gt = route_gt_camera()
    rng = np.random.default_rng(0)
    est = gt.copy()
    est[:, :3, 3] += np.cumsum(rng.normal(scale=0.02, size=(len(gt), 3)), axis=0)
    ts = np.arange(len(gt)) * 0.1
    rows = ["| operation (generated route, 4541 poses) | best of 3 (s) |", "|---|---|"]
    with tempfile.TemporaryDirectory() as d:
        k, t = Path(d) / "a.txt", Path(d) / "a.tum"
        gt_file = write_kitti_poses(Path(d) / "gt.txt", gt)
        rows.append(f"| read_kitti_poses | {best_of(lambda: read_kitti_poses(gt_file)):.3f} |")
        rows.append(f"| write_kitti_poses | {best_of(lambda: write_kitti_poses(k, gt)):.3f} |")
        write_tum_poses(t, ts, est)
        rows.append(f"| write_tum_poses | {best_of(lambda: write_tum_poses(t, ts, est)):.3f} |")
        rows.append(f"| read_tum_poses | {best_of(lambda: read_tum_poses(t)):.3f} |")
    rows.append(f"| trajectory_metrics (RPE x2, ATE x2, KITTI devkit) | {best_of(lambda: trajectory_metrics(est, gt)):.3f} |")
    m = trajectory_metrics(est, gt)
    rows += ["", "Example values (GT + random-walk drift, sigma 2 cm / frame, seed 0):", ""]
    rows += [f"- `{k}`: {v:.4g}" if isinstance(v, float) else f"- `{k}`: {v}" for k, v in m.items()]
    return rows


def bench_registration(n_pairs: int, channels: list[int], seed: int) -> list[str]:
    from gr_graph.datasets.registry import open_sequence

    out_root = REPO / "benchmarks" / "results" / "global_registration"
    rows = [
        "| channels | solver | success | median rot err (deg) | median trans err (m) | median time (s) |",
        "|---|---|---|---|---|---|",
    ]
    desc = ""
    pairs = None
    for ch in channels:
        seq, desc = open_sequence("00", None, ch)
        poses = np.asarray(seq.gt_poses)
        if pairs is None:
            pairs = greg.sample_pairs(poses, n_pairs, 10.0, seed, min_frame=14)
        out = out_root / f"{ch}ch"
        greg.save_pairs(out / "pairs.json", pairs, {"sequence": desc, "seed": seed, "max_distance_m": 10.0, "min_frame": 14})
        res = greg.evaluate_pairs(seq, poses, pairs, seed=seed)
        res["settings"]["sequence"] = desc
        greg.write_results(out / "results.json", res)
        for s, v in res["summary"].items():
            rows.append(
                f"| {ch} | {s} | {v['n_success']}/{v['n_pairs']} ({100 * v['success_rate']:.0f}%) | "
                f"{v['median_rot_err_deg']:.2f} | {v['median_trans_err_m']:.2f} | {v['median_seconds']:.2f} |"
            )
    return [f"Data: {desc.split(', frames')[0]}; {n_pairs} pairs (seed {seed}, within 10 m, frames >= 14), "
            f"voxel {greg.DEFAULT_VOXEL} m, raw scans.", ""] + rows + [
        "", "Pairs and per-pair results: `benchmarks/results/global_registration/<channels>ch/`."]


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n-pairs", type=int, default=100)
    ap.add_argument("--channels", type=int, nargs="+", default=[64, 32, 16])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--skip-registration", action="store_true")
    args = ap.parse_args()
    cmd = "python benchmarks/bench_metrics.py " + " ".join(sys.argv[1:])
    lines = [
        "# Benchmark: metrics area (trajectory I/O, metrics, global registration)",
        "",
        f"Command: `{cmd.strip()}` (from the repository root)",
        f"Machine: {platform.processor() or platform.machine()}, Python {platform.python_version()}, "
        f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}",
        "",
        "## Trajectory I/O and metrics",
        "",
    ]
    lines += bench_trajectory()
    if not args.skip_registration:
        lines += ["", "## Global registration (raw scans)", ""]
        lines += bench_registration(args.n_pairs, args.channels, args.seed)
    out = REPO / "benchmarks" / "results" / "metrics.md"
    atomic_write_text(out, "\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
