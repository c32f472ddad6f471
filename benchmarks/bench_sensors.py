"""SLAM with each beam model of the renderer: the HDL-64E (64 and 16 channels), the VLP-16, the OS1-64.

    python benchmarks/bench_sensors.py [--windows 0:100 street] [--out benchmarks/results/sensors.md]

For every sensor, the same windows of the generated route (route seed 0, town seed 0, clean
preset) go through ``gr_graph.frame_loop.run_slam`` with the default configuration and
``sensor.model`` set (loops on; a 100-frame window has no revisit, so none are found).
``street`` is the 100 frames starting where the route's longest same-direction revisit begins
its earlier pass (the street of the tests' revisit run). Reported per run: points per raw
scan and per preprocessed scan, the loop threshold the sensor gives, ATE (SE(3)-aligned RMSE,
evo via gr_graph.metrics), the end-point error of the odometry in the sensor frame of the
last ground-truth pose (x forward, y left, z up) and its share of the path, and wall time
(rendering included). Writes the markdown table and ``sensors.json`` next to it (atomic).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

SENSORS = (("hdl64e", None), ("hdl64e", 16), ("vlp16", None), ("os1-64", None))


def street_window(length: int = 100) -> tuple[int, int]:
    """The earlier pass of the street the tests' revisit run drives twice (route seed 0): the
    longest same-direction revisit whose later pass turned onto the street (as
    ``tests/slam_support.revisit_ranges``)."""
    from gr_graph.datasets.synthetic.route import generate_route

    route = generate_route(0)
    yaw = np.unwrap(np.arctan2(route.T_w_velo[:, 1, 0], route.T_w_velo[:, 0, 0]))
    turned_in = [r for r in route.revisits if r.direction == "same" and r.frames[0] >= 25
                 and abs(yaw[r.frames[0]] - yaw[r.frames[0] - 25]) > np.radians(45)]
    r = max(turned_in, key=lambda r: r.length_m)
    return int(r.earlier[0]), int(r.earlier[0]) + length


def run_one(sensor: str, channels: int | None, start: int, stop: int) -> dict:
    from gr_graph.config import load_config
    from gr_graph.datasets.registry import open_configured_sequence
    from gr_graph.frame_loop import run_slam
    from gr_graph.metrics import ate

    cfg = load_config(None, {"sensor": {"model": sensor}, "output": {"progress": False},
                             "data": {"channels": channels, "frames": (start, stop)}})
    seq, _ = open_configured_sequence(cfg.data, sensor=cfg.sensor)
    raw_points = [len(seq[k]) for k in (0, len(seq) // 2, len(seq) - 1)]
    t0 = time.perf_counter()
    res = run_slam(seq, cfg)
    wall = time.perf_counter() - t0
    gt = np.linalg.inv(seq.gt_poses[0]) @ seq.gt_poses
    d = res.odometry_poses[-1, :3, 3] - gt[-1, :3, 3]
    local = gt[-1, :3, :3].T @ d
    path = float(np.sum(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1)))
    return {"sensor": sensor, "channels": cfg.channels, "frames": f"{start}:{stop}", "path_m": path,
            "raw_points": float(np.mean(raw_points)), "scan_points": float(np.mean([len(s) for s in res.scans])),
            "loop_max_rmse": res.info["sensor"]["loop_max_rmse"], "n_loops": len(res.loops),
            "n_flagged": res.info["n_flagged_odometry"],
            "ate_slam_m": float(ate(res.poses, gt).rmse), "ate_odometry_m": float(ate(res.odometry_poses, gt).rmse),
            "end_error_xyz_m": [float(v) for v in local], "end_error_percent": 100.0 * float(np.linalg.norm(d)) / path,
            "wall_s": wall}


def main(argv: list[str] | None = None) -> int:
    from gr_graph.atomic import atomic_write_json, atomic_write_text

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--windows", nargs="+", default=["0:100", "street"],
                    help="frame windows A:B, or 'street' (see the module docstring)")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "sensors.md"))
    args = ap.parse_args(argv)
    windows = [street_window() if w == "street" else tuple(int(x) for x in w.split(":")) for w in args.windows]
    rows = []
    for start, stop in windows:
        for sensor, channels in SENSORS:
            r = run_one(sensor, channels, start, stop)
            print(r, flush=True)
            rows.append(r)
    out = Path(args.out)
    atomic_write_json(out.with_name("sensors.json"), rows)
    lines = [
        "# SLAM per sensor (beam model) on the synthetic sequence",
        "",
        f"`python benchmarks/bench_sensors.py --windows {' '.join(args.windows)}`; route seed 0, town seed 0, clean "
        "preset, default configuration with `sensor.model` set; `street` = frames "
        f"{street_window()[0]}:{street_window()[1]}. End error: odometry end point minus ground truth in the "
        "last ground-truth sensor frame (x forward, y left, z up).",
        "",
        "| frames | sensor | channels | path [m] | raw points | scan points | loop RMSE thr. [m] | ATE odometry [m] | "
        "ATE SLAM [m] | end error x / y / z [m] | end error [% of path] | wall [s] |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        x, y, z = r["end_error_xyz_m"]
        lines.append(f"| {r['frames']} | {r['sensor']} | {r['channels']} | {r['path_m']:.0f} | {r['raw_points']:.0f} | "
                     f"{r['scan_points']:.0f} | {r['loop_max_rmse']:.3f} | {r['ate_odometry_m']:.3f} | "
                     f"{r['ate_slam_m']:.3f} | {x:+.3f} / {y:+.3f} / {z:+.3f} | {r['end_error_percent']:.2f} | "
                     f"{r['wall_s']:.0f} |")
    atomic_write_text(out, "\n".join(lines) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
