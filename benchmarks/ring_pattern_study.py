"""How much of a small roll or pitch the VGICP odometry finds on sparse scans (not a test).

A scan of ``R`` rings is rendered twice from the same place: once from the route's pose ``P`` and
once from ``P`` turned by ``delta`` about the sensor's x (roll) or y (pitch) axis. The second
scan is then registered the way the odometry registers (``gr_graph.preprocess.preprocess_scan``
with the default ``preprocess`` settings, small_gicp VGICP with the default ``odometry`` voxel
and correspondence distance, the initial guess ``P``), onto

- ``scan``: a voxel map of the first scan alone (a standstill: one ring pattern), and
- ``map``: a voxel map of the ``--map-scans`` scans before it at their true poses (driving: the
  odometry's sliding map),

and the fraction of ``delta`` it finds is reported (1: all of it; 0: none). A control registers
the first scan's own points turned by ``delta`` onto the first map (the same samples: the
surfaces alone decide, so it must find all of ``delta``). The ``clean`` preset (no sensor errors)
isolates the sampling: the rings of a turned sensor hit the surfaces elsewhere, and a registration
that follows the ring pattern instead of the surfaces finds less than ``delta``.

With ``--runs RUN ...`` it also reads finished ``gr_graph.slam`` runs of a synthetic world
(``RUN/round_0/marginals.npz``, which holds the ground truth) and fits, over their registered
odometry edges and their loops, each edge's roll and pitch error ``xi = Log(T_measured^-1 T_true)``
against the true roll and pitch change of the edge (least squares with an intercept): the slope is
the share of the true change the registration missed (0: none missed, 1: all of it).

Run::

    python benchmarks/ring_pattern_study.py [--rings 16 32 64] [--frames 200 1000 2000 3000 4000]
        [--delta-mrad 4] [--map-scans 20] [--seed 0] [--num-neighbors K] [--runs RUN ...]
        [--write] [--name ring_pattern] [--note TEXT]

``--write`` writes ``benchmarks/results/NAME.md`` and ``.json``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"
AXES = {"roll": 0, "pitch": 1}


def turned(axis: int, angle: float) -> np.ndarray:
    """``(4, 4)`` rotation by ``angle`` [rad] about the sensor axis ``axis`` (0 x, 1 y)."""
    import gtsam

    T = np.eye(4)
    T[:3, :3] = gtsam.Rot3.Expmap(np.eye(3)[axis] * angle).matrix()
    return T


def render_from(seq, index: int, T_w_s: np.ndarray) -> np.ndarray:
    """Scan ``index`` of ``seq`` (same noise draws) rendered from the pose ``T_w_s`` instead of its own."""
    own = seq.gt_poses[index].copy()
    seq.gt_poses[index] = T_w_s
    try:
        return seq[index].points
    finally:
        seq.gt_poses[index] = own


def found_fraction(target, source_points: np.ndarray, init: np.ndarray, axis: int, delta: float, cfg) -> float:
    """Register ``source_points`` onto the voxel map ``target`` from ``init``; the share of ``delta``
    found about ``axis`` (the registered pose relative to ``init``)."""
    import gtsam
    import small_gicp

    from gr_graph.preprocess import preprocess_scan

    source = preprocess_scan(source_points, cfg.preprocess)
    res = small_gicp.align(target, source.cloud, init_T_target_source=init,
                           max_correspondence_distance=cfg.odometry.max_correspondence_distance,
                           max_iterations=cfg.odometry.max_iterations)
    xi = gtsam.Pose3.Logmap(gtsam.Pose3(np.linalg.inv(init) @ np.asarray(res.T_target_source)))
    return float(xi[axis] / delta)


def study(rings: int, frames: list[int], delta: float, map_scans: int, seed: int,
          num_neighbors: int | None = None) -> dict:
    """Fractions found per frame and axis: ``scan``, ``map`` and the ``control``."""
    import small_gicp

    from gr_graph.config import SlamConfig
    from gr_graph.datasets.synthetic import SyntheticSequence
    from gr_graph.preprocess import preprocess_scan

    cfg = SlamConfig()
    if num_neighbors is not None:
        cfg.preprocess.num_neighbors = num_neighbors
    seq = SyntheticSequence(seed=seed, n_rings=rings, preset="clean")
    gt = seq.gt_poses.copy()

    def voxel_map(indices: list[int]):
        vm = small_gicp.GaussianVoxelMap(cfg.odometry.voxel_resolution)
        for k in indices:
            vm.insert(preprocess_scan(seq[k].points, cfg.preprocess).cloud, gt[k])
        return vm

    rows = []
    for i in frames:
        if i < map_scans:
            raise ValueError(f"frame {i}: needs {map_scans} scans before it (--map-scans)")
        single, sliding = voxel_map([i]), voxel_map(list(range(i - map_scans, i)))
        own = seq[i].points
        row = {"frame": i, "map_span_m": float(np.linalg.norm(gt[i, :3, 3] - gt[i - map_scans, :3, 3]))}
        for name, axis in AXES.items():
            T = turned(axis, delta)
            rendered = render_from(seq, i, gt[i] @ T)
            same_points = own @ T[:3, :3]  # the first scan's points seen from the turned sensor
            row[name] = {"scan": found_fraction(single, rendered, gt[i], axis, delta, cfg),
                         "map": found_fraction(sliding, rendered, gt[i], axis, delta, cfg),
                         "control": found_fraction(single, same_points, gt[i], axis, delta, cfg)}
        rows.append(row)
        print(f"{rings} rings, frame {i}: " + "; ".join(
            f"{a} scan {row[a]['scan']:.2f} map {row[a]['map']:.2f} control {row[a]['control']:.2f}" for a in AXES),
            flush=True)
    summary = {a: {case: {"mean": float(np.mean([r[a][case] for r in rows])),
                          "min": float(np.min([r[a][case] for r in rows])),
                          "max": float(np.max([r[a][case] for r in rows]))}
                   for case in ("scan", "map", "control")} for a in AXES}
    return {"rings": rings, "num_neighbors": cfg.preprocess.num_neighbors, "frames": rows, "summary": summary}


def missed_share(run: Path) -> list[dict]:
    """Per edge kind (odometry, loop) and axis (roll, pitch): the slope of the edges' error on
    their true change (module docstring)."""
    from scipy.spatial.transform import Rotation

    from gr_graph.noise_consistency import edge_errors, gt_relative_poses

    path = run / "round_0" / "marginals.npz"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: not a finished gr_graph.slam run (round 0's marginals.npz is missing)")
    with np.load(path) as d:
        if "gt_poses" not in d:
            raise ValueError(f"{path}: no ground truth (a synthetic world's run is needed)")
        arrays = {k: d[k] for k in ("edges", "edge_T", "edge_kind", "edge_ok", "gt_poses")}
    out = []
    for kind_name, kind in (("odometry", 0), ("loop", 1)):
        chosen = (arrays["edge_kind"] == kind) & arrays["edge_ok"].astype(bool)
        if chosen.sum() < 3:
            continue
        true_rel = gt_relative_poses(arrays["edges"][chosen], arrays["gt_poses"])
        xi = edge_errors(arrays["edge_T"][chosen], true_rel)
        true_change = Rotation.from_matrix(true_rel[:, :3, :3]).as_rotvec()
        row = {"run": str(run), "kind": kind_name, "edges": int(chosen.sum())}
        for name, axis in AXES.items():
            g = true_change[:, axis] - true_change[:, axis].mean()
            row[name] = float(g @ (xi[:, axis] - xi[:, axis].mean()) / (g @ g))
            row[f"{name}_true_change_rms_mrad"] = float(1e3 * np.sqrt(np.mean(true_change[:, axis] ** 2)))
            row[f"{name}_error_rms_mrad"] = float(1e3 * np.sqrt(np.mean(xi[:, axis] ** 2)))
        out.append(row)
    return out


def markdown(results: list[dict], runs: list[dict], command: str, delta_mrad: float, map_scans: int,
             seconds: float) -> str:
    from datetime import datetime, timezone

    from gr_graph.provenance import machine_line

    lines = ["# How much of a small roll or pitch the VGICP odometry finds on sparse scans (clean preset)", "",
             f"Command: `{command}` ({seconds:.0f} s). Machine: {machine_line()}; "
             f"written {datetime.now(timezone.utc).isoformat(timespec='minutes')}.", "",
             f"Share of a {delta_mrad:g} mrad roll or pitch found when the scan is rendered again from the turned "
             f"pose and registered with the odometry's defaults onto one scan from the same place (`scan`) or onto "
             f"the {map_scans} scans before it (`map`); `control`: the first scan's own points turned (1 = all of "
             "it). Mean [min, max] over the frames.", "",
             "| rings | neighbours | axis | scan | map | control |", "|---|---|---|---|---|---|"]
    for r in results:
        for a in AXES:
            s = r["summary"][a]
            lines.append(f"| {r['rings']} | {r['num_neighbors']} | {a} | " + " | ".join(
                f"{s[c]['mean']:.2f} [{s[c]['min']:.2f}, {s[c]['max']:.2f}]" for c in ("scan", "map", "control")) + " |")
    lines += ["", "Per frame:", "", "| rings | frame | map span [m] | roll: scan / map / control | "
              "pitch: scan / map / control |", "|---|---|---|---|---|"]
    for r in results:
        for f in r["frames"]:
            lines.append(f"| {r['rings']} | {f['frame']} | {f['map_span_m']:.1f} | " + " | ".join(
                " / ".join(f"{f[a][c]:.2f}" for c in ("scan", "map", "control")) for a in AXES) + " |")
    if runs:
        lines += ["", "In SLAM runs: share of each edge's true roll and pitch change its registration missed "
                  "(slope of the edge error on the true change; round 0 of finished runs; odometry edges: "
                  "consecutive scans onto the sliding map; loops: a revisit's scan pair):", "",
                  "| run | edges | roll: missed share | pitch: missed share | roll: true change / error rms [mrad] "
                  "| pitch: true change / error rms [mrad] |", "|---|---|---|---|---|---|"]
        for r in runs:
            lines.append(f"| {r['run']} | {r['edges']} {r['kind']} | {r['roll']:.2f} | {r['pitch']:.2f} | "
                         f"{r['roll_true_change_rms_mrad']:.3f} / {r['roll_error_rms_mrad']:.3f} | "
                         f"{r['pitch_true_change_rms_mrad']:.3f} / {r['pitch_error_rms_mrad']:.3f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rings", type=int, nargs="+", default=[16, 32, 64])
    ap.add_argument("--frames", type=int, nargs="+", default=[200, 1000, 2000, 3000, 4000])
    ap.add_argument("--delta-mrad", type=float, default=4.0, help="the roll or pitch applied [mrad] (default 4)")
    ap.add_argument("--map-scans", type=int, default=20, help="scans in the sliding map (default 20)")
    ap.add_argument("--seed", type=int, default=0, help="world seed (default 0)")
    ap.add_argument("--num-neighbors", type=int, default=None,
                    help="neighbours of the per-point covariances (default: preprocess.num_neighbors)")
    ap.add_argument("--runs", type=Path, nargs="*", default=[], help="finished synthetic-world runs to read")
    ap.add_argument("--write", action="store_true", help="write benchmarks/results/NAME.md and .json")
    ap.add_argument("--name", default="ring_pattern", help="results file name (default ring_pattern)")
    ap.add_argument("--note", default="", help="a paragraph appended to the results file (e.g. how the runs were made)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    runs = [row for r in args.runs for row in missed_share(r)]
    results = [study(r, args.frames, args.delta_mrad * 1e-3, args.map_scans, args.seed, args.num_neighbors)
               for r in args.rings]
    seconds = time.perf_counter() - t0
    command = (f"python benchmarks/ring_pattern_study.py --rings {' '.join(map(str, args.rings))} --frames "
               f"{' '.join(map(str, args.frames))} --delta-mrad {args.delta_mrad:g} --map-scans {args.map_scans} "
               f"--seed {args.seed}" + (f" --num-neighbors {args.num_neighbors}" if args.num_neighbors else "")
               + (f" --runs {' '.join(str(r) for r in args.runs)}" if args.runs else ""))
    text = markdown(results, runs, command, args.delta_mrad, args.map_scans, seconds)
    if args.note:
        text += "\n\n" + args.note
    print(text)
    if args.write:
        from gr_graph.atomic import atomic_write_json, atomic_write_text

        atomic_write_text(RESULTS / f"{args.name}.md", text + "\n")
        atomic_write_json(RESULTS / f"{args.name}.json", {"command": command, "delta_mrad": args.delta_mrad,
                                                           "map_scans": args.map_scans, "results": results,
                                                           "runs": runs})


if __name__ == "__main__":
    main()
