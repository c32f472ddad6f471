"""SLAM benchmarks: odometry throughput vs KISS-ICP, odometry RPE-300 per channel count, and
the full synthetic run along the generated route (wall time, peak memory). Writes ``benchmarks/results/slam.md``.

Sections (each stores ``benchmarks/results/slam_<section>.json``; the markdown is rebuilt from
all stored sections, so they can be run separately)::

    python benchmarks/bench_slam.py throughput [--frames 1000:1200] [--preset clean|kitti] --write
    python benchmarks/bench_slam.py rpe        [--frames 0:1500] [--preset clean|kitti] --write
    python benchmarks/bench_slam.py full       [--frames 0:4541] [--preset clean|kitti] --write
    python benchmarks/bench_slam.py ingest --out RUN_DIR --command "..." --label "..."

- throughput: frames are rendered (synthetic sequence) or read once into RAM, then the
  gr_graph front end (preprocess + VGICP odometry, 1 thread) and KISS-ICP 1.3.0
  (``KissICP`` with its default config, deskew off because frames have no per-point time,
  1 thread) process the very same frames, at 64, 32 and 16 channels; frames/s and ratio.
- rpe: one rendering pass; every frame feeds six front ends (gr_graph and KISS-ICP at
  64/32/16 channels); translational RPE over 300 frames (evo, via gr_graph.metrics) against
  the renderer's ground truth, camera frame.
- full: ``python -m gr_graph.slam --seq 00 --out ...`` in a subprocess (rendering included);
  wall time, peak RSS of the process (getrusage), metrics.json figures.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"
sys.path.insert(0, str(REPO))

from gr_graph.atomic import atomic_write_json, atomic_write_text  # noqa: E402
from gr_graph.config import GraphConfig, OdometryConfig, PreprocessConfig  # noqa: E402
from gr_graph.datasets.base import velo_to_cam_poses  # noqa: E402
from gr_graph.datasets.channels import subsample_channels  # noqa: E402
from gr_graph.datasets.registry import parse_frames  # noqa: E402
from gr_graph.odometry import VgicpOdometry  # noqa: E402
from gr_graph.preprocess import preprocess_scan  # noqa: E402

CHANNELS = (64, 32, 16)


def kiss_icp(deskew: bool = False):
    """KISS-ICP 1.3.0 with its default config, 1 thread; deskew off by default (no per-point timestamps)."""
    from kiss_icp.config import load_config
    from kiss_icp.kiss_icp import KissICP

    cfg = load_config(None)
    cfg.data.deskew = deskew
    cfg.registration.max_num_threads = 1
    return KissICP(cfg)


class GrFrontEnd:
    """gr_graph's front end as the pipeline runs it: preprocess once, VGICP odometry.

    ``vertical_correction_deg`` (KITTI HDL-64E vertical-angle correction) is applied to the raw
    points first, as the KITTI loader does with ``--kitti-vertical-correction``.
    """

    def __init__(self, vertical_correction_deg: float = 0.0) -> None:
        self.pc = PreprocessConfig()
        self.odo = VgicpOdometry(OdometryConfig(), GraphConfig())
        self.vertical_correction_deg = vertical_correction_deg

    def __call__(self, points: np.ndarray) -> np.ndarray:
        if self.vertical_correction_deg:
            from gr_graph.datasets.kitti import correct_vertical_angle

            points = correct_vertical_angle(points, self.vertical_correction_deg)
        self.odo.step(preprocess_scan(points, self.pc, num_threads=1))
        return self.odo.poses[-1]


class KissFrontEnd:
    def __init__(self) -> None:
        self.k = kiss_icp()
        self.empty = np.zeros(0)

    def __call__(self, points: np.ndarray) -> np.ndarray:
        self.k.register_frame(points, self.empty)
        return self.k.last_pose.copy()


#: slam.md's text after this line was written by hand (measurements made outside this script): kept on rebuilds
HAND_WRITTEN_MARK = ("<!-- written by hand below this line: kept as it is by `bench_slam.py` when it rebuilds the "
                     "sections above -->")
#: the synthetic world the published slam.md was measured on (before the default became ``kitti``)
DEFAULT_PRESET = "clean"


def open_seq(frames: tuple[int, int], preset: str = DEFAULT_PRESET):
    """The synthetic world's route at ``frames`` (never a KITTI root found on the machine: the sections
    compare systems on the same rendered frames, and the report names the world)."""
    from gr_graph.datasets.registry import open_sequence

    return open_sequence("00", frames=frames, synthetic_preset=preset, dataset="synthetic")


def machine() -> str:
    return f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores (shared), Python {platform.python_version()}"


# ----------------------------------------------------------------------------- sections


def bench_throughput(frames: tuple[int, int], preset: str = DEFAULT_PRESET) -> dict:
    seq, desc = open_seq(frames, preset)
    raw = [seq[i] for i in range(len(seq))]
    out = {"source": desc, "n_frames": len(raw), "rows": []}
    for ch in CHANNELS:
        pts = [f.points if ch == 64 else subsample_channels(f, ch).points for f in raw]
        row = {"channels": ch, "mean_points": float(np.mean([len(p) for p in pts]))}
        for name, make in (("gr_graph", GrFrontEnd), ("kiss_icp", KissFrontEnd)):
            fe = make()
            t0 = time.perf_counter()
            for p in pts:
                fe(p)
            dt = time.perf_counter() - t0
            row[f"{name}_fps"] = len(pts) / dt
        row["ratio"] = row["gr_graph_fps"] / row["kiss_icp_fps"]
        out["rows"].append(row)
        print(row, flush=True)
    return out


def run_front_ends(seq, front_ends: dict, desc: str = "rpe") -> dict:
    """Feed every frame of ``seq`` once to each front end; RPE-300 etc. per front end.

    ``front_ends`` maps ``(system, channels)`` to a callable ``points -> 4x4 pose``; frames are
    read once at full resolution and subsampled per channel count (gr_graph.datasets.channels).
    Returns ``{"rows": [...]}`` with one row per front end (evo metrics, camera frame).
    """
    from tqdm import tqdm

    from gr_graph.metrics import trajectory_metrics

    poses = {k: [] for k in front_ends}
    secs = {k: 0.0 for k in front_ends}
    channels = sorted({k[1] for k in front_ends}, reverse=True)
    for i in tqdm(range(len(seq)), desc=desc, mininterval=5):
        f = seq[i]
        for ch in channels:
            p = f.points if ch == f.n_rings else subsample_channels(f, ch).points
            for key, fe in front_ends.items():
                if key[1] != ch:
                    continue
                t0 = time.perf_counter()
                poses[key].append(fe(p))
                secs[key] += time.perf_counter() - t0
    gt = np.asarray(seq.gt_poses)
    gt = np.linalg.inv(gt[0]) @ gt
    T = seq.T_cam_velo
    rows = []
    for (name, ch), P in poses.items():
        m = trajectory_metrics(velo_to_cam_poses(np.asarray(P), T), velo_to_cam_poses(gt, T), delta=300)
        rows.append({"system": name, "channels": ch, "fps": len(P) / secs[(name, ch)],
                     **{k: m[k] for k in ("rpe300_consecutive_mean", "rpe300_consecutive_rmse",
                                          "rpe300_all_pairs_mean", "rpe300_all_pairs_rmse", "ate_rmse",
                                          "kitti_t_err_percent")}})
        print(rows[-1], flush=True)
    return {"rows": rows}


def bench_rpe(frames: tuple[int, int], preset: str = DEFAULT_PRESET) -> dict:
    seq, desc = open_seq(frames, preset)
    fes = {(name, ch): make() for ch in CHANNELS for name, make in (("gr_graph", GrFrontEnd), ("kiss_icp", KissFrontEnd))}
    return {"source": desc, "n_frames": len(seq), **run_front_ends(seq, fes)}


def bench_full(frames: tuple[int, int] | None, out_dir: Path, preset: str = DEFAULT_PRESET) -> dict:
    cmd = [sys.executable, "-m", "gr_graph.slam", "--seq", "00", "--dataset", "synthetic", "--synthetic-preset", preset,
           "--out", str(out_dir), "--no-resume", "--quiet"]
    if frames is not None:
        cmd += ["--frames", f"{frames[0]}:{frames[1]}"]
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=REPO)
    wall = time.perf_counter() - t0
    load = f"1-minute load average {load0:.1f} at the start, {os.getloadavg()[0]:.1f} at the end (2 cores)"
    peak_kb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    m = json.loads((out_dir / "metrics.json").read_text())
    r0 = m["rounds"]["0"]
    return {"command": " ".join(["python", "-m", "gr_graph.slam"] + cmd[3:]), "source": m["source"],
            "wall_s": wall, "peak_rss_gb": peak_kb / 1024**2, "load": load, "round0": r0}


def ingest_run(out_dir: Path, command: str, label: str) -> dict:
    """Record an existing CLI run (its metrics.json) under ``label`` in slam_runs.json."""
    m = json.loads((out_dir / "metrics.json").read_text())
    r0 = m["rounds"]["0"]
    p = RESULTS / "slam_runs.json"
    runs = json.loads(p.read_text()) if p.exists() else {}
    runs[label] = {"command": command, "source": m["source"], "channels": m["channels"], "round0": r0}
    atomic_write_json(p, runs)
    return runs


# ----------------------------------------------------------------------------- report


def _f(x, fmt="{:.2f}"):
    return "n/a" if x is None else fmt.format(x)


def write_markdown() -> Path:
    lines = ["# SLAM benchmarks (gr_graph.slam)", "", f"Machine: {machine()}. Other jobs shared the 2 cores, "
             "so absolute times are pessimistic; ratios within one section are measured on the same frames "
             "in the same process.", "",
             "Caveat: each section names the synthetic world it rendered (its source line). The `clean` preset "
             "(a generated 3.7 km route through a clean ray-cast town, the sections below unless they say "
             "otherwise) is far easier than the real KITTI 00: the paper reports RPE300 = 3.68 m for raw VGICP at "
             "64 channels on real data. Compare systems and channel counts within a table, not with the paper; "
             "`--preset kitti` renders the harder default world.", ""]
    p = RESULTS / "slam_throughput.json"
    if p.exists():
        d = json.loads(p.read_text())
        lines += ["## Odometry throughput vs KISS-ICP", "",
                  f"`python benchmarks/bench_slam.py throughput --frames {d['frames']} --preset "
                  f"{d.get('preset', DEFAULT_PRESET)} --write` — {d['source']}; "
                  f"{d['n_frames']} frames held in RAM (rendering excluded), 1 thread each.", "",
                  *([f"Note: {d['note']}", ""] if d.get("note") else []),
                  "| channels | points/scan | gr_graph [frames/s] | KISS-ICP [frames/s] | ratio (target ≥ 1) |",
                  "|---|---|---|---|---|"]
        for r in d["rows"]:
            lines.append(f"| {r['channels']} | {r['mean_points']:.0f} | {r['gr_graph_fps']:.1f} | "
                         f"{r['kiss_icp_fps']:.1f} | {r['ratio']:.2f} |")
        lines.append("")
    p = RESULTS / "slam_rpe.json"
    if p.exists():
        d = json.loads(p.read_text())
        lines += ["## Odometry RPE over 300 frames (translation, m), per channel count", "",
                  f"`python benchmarks/bench_slam.py rpe --frames {d['frames']} --preset {d.get('preset', DEFAULT_PRESET)} "
                  f"--write` — {d['source']}; "
                  f"{d['n_frames']} frames rendered once at 64 rings, 32/16 by ring subsampling (gr_graph.datasets.channels), one pass feeding all six front ends. "
                  "gr_graph = its VGICP front end (odometry only, no loop closures). "
                  "Camera frame, evo, consecutive and all pairs.", "",
                  *([f"Note: {d['note']}", ""] if d.get("note") else []),
                  "| system | channels | RPE300 mean (consec.) | RMSE (consec.) | mean (all pairs) | RMSE (all pairs) | ATE RMSE | KITTI % | frames/s |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for r in sorted(d["rows"], key=lambda r: (-r["channels"], r["system"])):
            lines.append(f"| {r['system']} | {r['channels']} | {_f(r['rpe300_consecutive_mean'])} | "
                         f"{_f(r['rpe300_consecutive_rmse'])} | {_f(r['rpe300_all_pairs_mean'])} | "
                         f"{_f(r['rpe300_all_pairs_rmse'])} | {_f(r['ate_rmse'])} | {_f(r['kitti_t_err_percent'])} | "
                         f"{r['fps']:.1f} |")
        lines.append("")
    p = RESULTS / "slam_full.json"
    if p.exists():
        d = json.loads(p.read_text())
        r0 = d["round0"]
        s = r0.get("slam", {})
        o = r0.get("odometry", {})
        lc = r0.get("loop_closure", {})
        rt = r0["runtime_s"]
        lines += ["## Full synthetic sequence (4,541 frames, 3.7 km), 64 channels, --rounds 0", "",
                  f"`{d['command']}` — {d['source']}", "",
                  f"- wall time: **{d['wall_s'] / 60:.1f} min** (target < 10 min), of which waiting for the "
                  f"renderer {rt.get('read', 0) / 60:.1f} min; peak RSS **{d['peak_rss_gb']:.2f} GB** (target < 4 GB)",
                  "- runtime per stage [s]: " + ", ".join(f"{k} {v:.1f}" for k, v in rt.items()),
                  *([f"- load: {d['load']}"] if d.get("load") else []),
                  *([f"- note: {d['note']}"] if d.get("note") else []),
                  f"- frames: {r0['n_frames']}, flagged odometry edges: {r0['n_flagged_odometry_edges']}, "
                  f"points/scan: {r0['mean_points_per_scan']:.0f}",
                  f"- loop closures: {lc.get('n_loops')} accepted of {r0['n_loop_candidates']} verified candidates; "
                  f"precision {_f(lc.get('precision'))} (correct = within {lc.get('max_t_err')} m / "
                  f"{lc.get('max_r_err_deg')}° of GT), recall over revisit queries {_f(lc.get('recall'))}, "
                  f"revisit segments found {lc.get('segments_found')}/{lc.get('n_revisit_segments')}",
                  "", "| trajectory | RPE300 mean (consec.) | RMSE (consec.) | mean (all pairs) | ATE RMSE | KITTI % |",
                  "|---|---|---|---|---|---|"]
        for name, m in (("odometry only", o), ("SLAM (loops + graph)", s)):
            lines.append(f"| {name} | {_f(m.get('rpe300_consecutive_mean'))} | {_f(m.get('rpe300_consecutive_rmse'))} | "
                         f"{_f(m.get('rpe300_all_pairs_mean'))} | {_f(m.get('ate_rmse'))} | "
                         f"{_f(m.get('kitti_t_err_percent'))} |")
        lines.append("")
    p = RESULTS / "slam_runs.json"
    if p.exists():
        runs = json.loads(p.read_text())
        lines += ["## Other full synthetic runs (loop closure settings, channels)", "",
                  "Loop precision = accepted loops within 2 m / 10° of GT; recall = revisit queries (GT neighbour "
                  "≥ min_frame_gap older within 5 m) with an accepted loop; segments = contiguous revisit "
                  "stretches with at least one loop.", "",
                  "| run | command | loops (correct) | precision | recall | segments | RPE300 mean (consec.), odom / SLAM | ATE RMSE, odom / SLAM | wall [min] |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for label, d in runs.items():
            r0 = d["round0"]
            lc = r0.get("loop_closure", {})
            o, s_ = r0.get("odometry", {}), r0.get("slam", {})
            lines.append(f"| {label} | `{d['command']}` | {lc.get('n_loops')} ({lc.get('n_correct')}) | "
                         f"{_f(lc.get('precision'))} | {_f(lc.get('recall'))} | "
                         f"{lc.get('segments_found')}/{lc.get('n_revisit_segments')} | "
                         f"{_f(o.get('rpe300_consecutive_mean'))} / {_f(s_.get('rpe300_consecutive_mean'))} | "
                         f"{_f(o.get('ate_rmse'))} / {_f(s_.get('ate_rmse'))} | {r0['runtime_s']['total'] / 60:.1f} |")
        lines.append("")
    out = RESULTS / "slam.md"
    kept = out.read_text().split(HAND_WRITTEN_MARK, 1) if out.exists() else []
    tail = HAND_WRITTEN_MARK + kept[1] if len(kept) == 2 else ""
    return atomic_write_text(out, "\n".join(lines) + "\n" + tail)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("section", choices=("throughput", "rpe", "full", "ingest", "report"))
    ap.add_argument("--command", default="", help="ingest: the command that made --out")
    ap.add_argument("--label", default="", help="ingest: row label")
    ap.add_argument("--frames", default=None)
    ap.add_argument("--out", default="/tmp/gr_graph_bench_full")
    ap.add_argument("--preset", choices=("clean", "kitti", "raw"), default=DEFAULT_PRESET,
                    help=f"synthetic world rendered (default: {DEFAULT_PRESET}, as the published slam.md)")
    ap.add_argument("--write", action="store_true",
                    help="store the section's results (benchmarks/results/slam_<section>.json) and rebuild slam.md; "
                         "without it they are printed only, so a quick trial never replaces a published section")
    a = ap.parse_args()
    RESULTS.mkdir(parents=True, exist_ok=True)
    if a.section == "throughput":
        fr = parse_frames(a.frames or "1000:1200")
        d = bench_throughput(fr, a.preset)
    elif a.section == "rpe":
        fr = parse_frames(a.frames or "0:1500")
        d = bench_rpe(fr, a.preset)
    elif a.section == "full":
        fr = parse_frames(a.frames) if a.frames else None
        d = bench_full(fr, Path(a.out), a.preset)
    elif a.section == "ingest":
        ingest_run(Path(a.out), a.command, a.label)
    if a.section not in ("report", "ingest"):
        d["frames"] = a.frames or {"throughput": "1000:1200", "rpe": "0:1500", "full": "0:4541"}[a.section]
        d["preset"] = a.preset
        if not a.write:
            print(json.dumps(d, indent=2))
            print("not stored: add --write to store it and rebuild slam.md")
            return
        atomic_write_json(RESULTS / f"slam_{a.section}.json", d)
    print(write_markdown())


if __name__ == "__main__":
    main()
