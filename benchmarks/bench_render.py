"""Benchmark of the synthetic renderer along the generated route (not a test).

Measures the scene build time (procedural town + open3d BVH), frames rendered per second
at 64/32/16 rings with 1 ray-casting thread and with all threads, and, as a check that the
town is a realistic odometry problem, small_gicp VGICP frame-to-frame odometry over a
stretch of frames against the ground truth.

Run::

    python benchmarks/bench_render.py [--frames 60] [--odometry 100] [--presets clean,kitti,raw]

Writes ``benchmarks/results/render.md``.
"""

from __future__ import annotations

import argparse
import datetime as dt
import os
import platform
import resource
import time
from pathlib import Path

import numpy as np

from factors.se3 import rotation_angle
from gr_graph.atomic import atomic_write_text
from gr_graph.datasets.synthetic import SyntheticSequence
from gr_graph.datasets.synthetic.path import route_path
from gr_graph.datasets.synthetic.sequence import clear_scene_cache, get_town_and_scene

RESULTS = Path(__file__).resolve().parent / "results" / "render.md"


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def bench_build() -> tuple[float, float, int]:
    """Town build seconds, BVH build seconds (first cast), triangles."""
    import open3d as o3d

    path = route_path(0)  # generate the route first: only the town is timed
    clear_scene_cache()
    t0 = time.perf_counter()
    town, scene = get_town_and_scene(0, path)
    t_town = time.perf_counter() - t0
    ray = np.array([[0, 0, 1.73, 1, 0, 0]], dtype=np.float32)
    t0 = time.perf_counter()
    scene.cast_rays(o3d.core.Tensor(ray))  # embree builds its BVH lazily on the first query
    t_bvh = time.perf_counter() - t0
    return t_town, t_bvh, len(town.triangles)


def bench_fps(n_rings: int, nthreads: int, frames: np.ndarray, preset: str = "clean", town_config=None,
              actors=None) -> tuple[float, float]:
    """Frames/s and points/frame; without ``town_config`` the world (town and actors) of ``preset``."""
    world = {} if town_config is None else {"town_config": town_config, "actors": actors}
    seq = SyntheticSequence(seed=0, n_rings=n_rings, nthreads=nthreads, preset=preset, **world)
    seq[int(frames[0])]  # warm up
    n_pts = 0
    t0 = time.perf_counter()
    for i in frames:
        n_pts += len(seq[int(i)])
    dt_ = time.perf_counter() - t0
    return len(frames) / dt_, n_pts / len(frames)


def bench_odometry(n_rings: int, start: int, n: int) -> dict[str, float]:
    """Frame-to-frame VGICP (small_gicp) from a constant-velocity guess, vs GT."""
    import small_gicp

    seq = SyntheticSequence(seed=0, n_rings=n_rings, preset="clean")
    gt = seq.gt_poses[start:start + n + 1]
    T = np.eye(4)
    est = [T.copy()]
    prev = None
    guess = np.eye(4)
    errs_t, errs_r = [], []
    for k in range(n):
        if prev is None:
            prev = seq[start]
        cur = seq[start + k + 1]
        res = small_gicp.align(prev.points, cur.points, init_T_target_source=guess,
                               registration_type="VGICP", voxel_resolution=1.0,
                               downsampling_resolution=0.25, num_threads=1)
        rel = res.T_target_source
        rel_gt = np.linalg.inv(gt[k]) @ gt[k + 1]
        E = np.linalg.inv(rel_gt) @ rel
        errs_t.append(np.linalg.norm(E[:3, 3]))
        errs_r.append(np.degrees(rotation_angle(E[:3, :3])))
        T = T @ rel
        est.append(T.copy())
        guess, prev = rel, cur
    gt_rel = np.linalg.inv(gt[0]) @ gt
    length = np.sum(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1))
    end_err = np.linalg.norm(est[-1][:3, 3] - gt_rel[-1][:3, 3])
    return {"frames": n, "length_m": length, "end_drift_pct": 100 * end_err / length,
            "mean_t_cm": 100 * float(np.mean(errs_t)), "max_t_cm": 100 * float(np.max(errs_t)),
            "mean_r_deg": float(np.mean(errs_r)), "max_r_deg": float(np.max(errs_r))}


def bench_world(n_frames: int, out: Path) -> None:
    """Render speed with the world effects (64 rings, one ray-casting thread), written to ``out``."""
    from gr_graph.datasets.synthetic.actors import ActorsConfig
    from gr_graph.datasets.synthetic.town import TownConfig, build_town

    load0 = os.getloadavg()
    positions = route_path(0).T_w_velo[:, :3, 3]
    frames = np.arange(1000, 1000 + n_frames)
    variants = [("clean (every effect off)", TownConfig(), None),
                ("world effects of the town (`TownConfig.residential()`)", TownConfig.residential(), None),
                ("moving actors only (`ActorsConfig()`)", TownConfig(), ActorsConfig()),
                ("every world effect (town + actors)", TownConfig.residential(), ActorsConfig())]
    rows = []
    for name, tc, ac in variants:
        t0 = time.perf_counter()
        town = build_town(positions, seed=0, config=tc)
        t_build = time.perf_counter() - t0
        clear_scene_cache()
        fps, pts = bench_fps(64, 1, frames, town_config=tc, actors=ac)
        clear_scene_cache()
        rows.append((name, t_build, len(town.triangles), fps, pts))
        print(rows[-1], flush=True)
    load1 = os.getloadavg()
    lines = [
        "# Synthetic renderer: speed with the world effects",
        "",
        f"Reproduce: `python benchmarks/bench_render.py --world-effects --frames {n_frames}`",
        "",
        f"- date (UTC): {dt.datetime.now(dt.timezone.utc):%Y-%m-%d %H:%M}",
        f"- machine: {_cpu_model()}, {os.cpu_count()} logical CPUs; load average "
        f"{load0[0]:.1f} before / {load1[0]:.1f} after (shared machine: lower bounds)",
        f"- 64 rings, 1 ray-casting thread, frames 1000..{1000 + n_frames} of the generated route, "
        "seed 0, today's sensor model; target >= 10 frames/s with every effect on",
        "",
        "| world | town build [s] | triangles | frames/s | points/frame |",
        "|---|---:|---:|---:|---:|",
    ]
    lines += [f"| {n} | {b:.1f} | {t / 1e6:.2f} M | {f:.1f} | {p:,.0f} |" for n, b, t, f, p in rows]
    text = "\n".join(lines) + "\n"
    atomic_write_text(out, text)
    print(text)


def bench_kitti_preset(n_frames: int, out: Path) -> None:
    """Render speed of the ``kitti`` preset (its world, actors and every sensor effect), 64 rings,
    one ray-casting thread, written to ``out``: wall-clock and CPU-time frames/s (the machine is
    shared; the CPU time of this process is the figure less disturbed by other jobs)."""
    load0 = os.getloadavg()
    seq = SyntheticSequence(seed=0, n_rings=64, nthreads=1, preset="kitti")
    t0 = time.perf_counter()
    n_tri = len(seq.town.triangles)
    t_build = time.perf_counter() - t0
    seq[999]  # warm up: BVH and actors
    frames = np.arange(1000, 1000 + n_frames)
    n_pts = 0
    t0, c0 = time.perf_counter(), time.process_time()
    for i in frames:
        n_pts += len(seq[int(i)])
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    load1 = os.getloadavg()
    lines = [
        "# Synthetic renderer: speed of the kitti preset (every world and sensor effect)",
        "",
        f"Reproduce: `python benchmarks/bench_render.py --kitti-preset --frames {n_frames}`",
        "",
        f"- date (UTC): {dt.datetime.now(dt.timezone.utc):%Y-%m-%d %H:%M}",
        f"- machine: {_cpu_model()}, {os.cpu_count()} logical CPUs; load average {load0[0]:.1f} before / "
        f"{load1[0]:.1f} after (shared machine)",
        f"- 64 rings, 1 ray-casting thread, frames {frames[0]}..{frames[-1]} of the generated route, seed 0; "
        "target >= 10 frames/s",
        "",
        "| town build [s] | triangles | frames/s (wall clock) | frames/s (CPU time of the process) | points/frame |",
        "|---:|---:|---:|---:|---:|",
        f"| {t_build:.1f} | {n_tri / 1e6:.2f} M | {n_frames / wall:.1f} | {n_frames / cpu:.1f} | "
        f"{n_pts / n_frames:,.0f} |",
    ]
    atomic_write_text(out, "\n".join(lines) + "\n")
    print("\n".join(lines))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=60, help="frames timed per configuration")
    ap.add_argument("--odometry", type=int, default=100, help="frames of the odometry check (0: skip)")
    ap.add_argument("--presets", default="clean",
                    help="comma-separated sensor presets to time (clean, kitti, raw; default clean)")
    ap.add_argument("--out", type=Path, default=None,
                    help=f"default {RESULTS} (with --world-effects: render_world.md beside it)")
    ap.add_argument("--world-effects", action="store_true",
                    help="only time the world effects (town effects, actors) at 64 rings, 1 thread")
    ap.add_argument("--kitti-preset", action="store_true",
                    help="only time the kitti preset (its world and every sensor effect) at 64 rings, 1 thread")
    args = ap.parse_args()
    if args.kitti_preset:
        bench_kitti_preset(args.frames, args.out or RESULTS.with_name("render_kitti.md"))
        return
    if args.world_effects:
        bench_world(args.frames, args.out or RESULTS.with_name("render_world.md"))
        return
    args.out = args.out or RESULTS
    load0 = os.getloadavg()
    t_town, t_bvh, n_tri = bench_build()
    rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    rng = np.random.default_rng(0)
    seq_frames = np.arange(1000, 1000 + args.frames)
    rand_frames = np.sort(rng.choice(4541, args.frames, replace=False))
    rows = []
    presets = args.presets.split(",")
    for preset in presets:
        for n_rings in (64, 32, 16):
            for nthreads in (1, 0):
                fps, pts = bench_fps(n_rings, nthreads, seq_frames, preset)
                fps_r, _ = bench_fps(n_rings, nthreads, rand_frames, preset)
                rows.append((preset, n_rings, "1" if nthreads == 1 else f"all ({os.cpu_count()})", fps, fps_r, pts))
                print(rows[-1])
    odo = []
    if args.odometry:
        for n_rings in (64, 16):
            for start in (1000, 3000):
                odo.append((n_rings, start, bench_odometry(n_rings, start, args.odometry)))
                print(odo[-1])
    load1 = os.getloadavg()

    lines = [
        "# Synthetic renderer (generated route): speed",
        "",
        f"Reproduce: `python benchmarks/bench_render.py --frames {args.frames} --odometry {args.odometry} "
        f"--presets {args.presets}`",
        "",
        f"- date (UTC): {dt.datetime.now(dt.timezone.utc):%Y-%m-%d %H:%M}",
        f"- machine: {_cpu_model()}, {os.cpu_count()} logical CPUs; load average "
        f"{load0[0]:.1f} before / {load1[0]:.1f} after (the machine is shared: other jobs run "
        "at the same time, so these are lower bounds)",
        "- open3d RaycastingScene (Embree), seed 0, 2000 azimuth steps, max range 120 m",
        "",
        "## Scene build (once per process and seed)",
        "",
        f"- procedural town: **{t_town:.1f} s** ({n_tri / 1e6:.2f} M triangles)",
        f"- BVH build on the first ray cast: **{t_bvh:.1f} s**",
        f"- peak RSS after the build: {rss_mb:.0f} MB",
        "",
        "## Frames rendered per second (target: >= 10 at 64 rings)",
        "",
        "Sensor presets (`gr_graph/datasets/synthetic/effects.py`): `clean` = no effect; `kitti` and `raw` = "
        "every effect on (motion distortion, per-laser calibration, range noise, mixed pixels, roughness).",
        "",
        "| preset | rings | ray-cast threads | frames/s, sequential (1000..) | frames/s, random frames | points/frame |",
        "|---|---:|---|---:|---:|---:|",
    ]
    lines += [f"| {pr} | {r} | {t} | {f:.1f} | {fr:.1f} | {p:,.0f} |" for pr, r, t, f, fr, p in rows]
    if odo:
        lines += [
            "",
            "## Is it a realistic odometry problem? small_gicp VGICP frame to frame vs GT",
            "",
            "VGICP (voxel 1 m, downsampling 0.25 m), each pair started from the previous relative "
            "motion (constant velocity), chained; errors of each relative pose vs the ground truth.",
            "",
            "| rings | frames | length [m] | end drift [% of length] | rel. trans. error mean / max [cm] "
            "| rel. rot. error mean / max [deg] |",
            "|---:|---|---:|---:|---:|---:|",
        ]
        lines += [f"| {r} | {s}..{s + o['frames']} | {o['length_m']:.0f} | {o['end_drift_pct']:.2f} | "
                  f"{o['mean_t_cm']:.1f} / {o['max_t_cm']:.1f} | {o['mean_r_deg']:.3f} / {o['max_r_deg']:.3f} |"
                  for r, s, o in odo]
    text = "\n".join(lines) + "\n"
    atomic_write_text(args.out, text)
    print(text)


if __name__ == "__main__":
    main()
