"""Deskewing benchmarks: accuracy on motion-distorted synthetic stretches, throughput with
deskewing on vs off and vs KISS-ICP, and the KITTI vertical-angle correction on real frames.
Writes ``benchmarks/results/deskew.md`` (and one ``deskew_<section>.json`` per section).

Sections (each can be run alone; the markdown is rebuilt from all stored sections)::

    python benchmarks/bench_deskew.py accuracy   [--stretches 4200:4260,3950:4010,0:300]
    python benchmarks/bench_deskew.py throughput [--frames 1000:1200]
    python benchmarks/bench_deskew.py vertical   [--kitti ../shared/data/kitti]
    python benchmarks/bench_deskew.py report

- accuracy: synthetic KITTI 00 stretches (seed 0, 64 rings), each rendered once and held in
  RAM, then distorted by :class:`gr_graph.datasets.distortion.MotionDistortedSequence` (0.1 s
  sweeps, poses interpolated along the ground truth): the ``raw`` variant (full distortion,
  per-point times) and a ``compensated`` one (compensated with the true velocity plus
  0.1 m/s and 0.5 deg/s Gaussian errors per axis). gr_graph round 0, odometry only
  (``run_slam`` without loops), with ``odometry.deskew`` off / auto (data times) / on with
  the times removed (azimuth times); KISS-ICP 1.3.0 (default config, 1 thread) with its
  deskewing off / on (the same per-point times; KISS-ICP deskews to the sweep's end, so its
  poses are moved back by half its last increment to mid-sweep, where the ground truth is). RPE over 10 frames (mean, m), ATE RMSE (m),
  KITTI % where the stretch is long enough; camera frame.
- throughput: frames 1000:1200 rendered, distorted (raw variant) and held in RAM; per channel
  count (64/32/16 by ring subsampling) the front ends process the very same frames, one
  thread each: gr_graph (deskew + preprocess + VGICP odometry, the frame loop's code) with
  deskewing off, on with data times, on with azimuth times; KISS-ICP with deskewing off and
  on (per-point times given). Frames/s and ratios.
- vertical: the real KITTI 00 frames of ``../shared/data/kitti`` read with
  ``vertical_correction_deg`` 0 / 0.195 / 0.205 / 0.22: the realism statistics of
  :mod:`gr_graph.datasets.realism` (mean over the frames), its VGICP inlier RMSE between
  consecutive frames, and the error of that VGICP registration against the ground truth.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from bench_slam import kiss_icp, open_seq  # noqa: E402

from gr_graph.atomic import atomic_write_json, atomic_write_text  # noqa: E402
from gr_graph.config import GraphConfig, OdometryConfig, PreprocessConfig, load_config  # noqa: E402
from gr_graph.datasets.base import velo_to_cam_poses  # noqa: E402
from gr_graph.datasets.channels import subsample_channels  # noqa: E402
from gr_graph.datasets.distortion import MotionDistortedSequence  # noqa: E402
from gr_graph.datasets.registry import parse_frames  # noqa: E402
from gr_graph.frame_loop import FrameDeskewer  # noqa: E402
from gr_graph.odometry import VgicpOdometry  # noqa: E402
from gr_graph.preprocess import preprocess_scan  # noqa: E402

CHANNELS = (64, 32, 16)
SCAN_PERIOD = 0.1
COMP_VELOCITY_NOISE = 0.1  # m/s per axis (illustrative; the renderer's kitti preset owns the real model)
COMP_RATE_NOISE_DEG = 0.5  # deg/s per axis


def machine() -> str:
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return (f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores (shared; load {load:.1f} "
            f"at the end), Python {platform.python_version()}")


class Cached:
    """A sequence's frames held in RAM (rendering excluded from the timings); same attributes."""

    def __init__(self, seq, strip_time: bool = False) -> None:
        self.frames = [seq[i] for i in range(len(seq))]
        if strip_time:
            self.frames = [replace(f, time=None) for f in self.frames]
        self.name = seq.name + ("-notime" if strip_time else "")
        self.timestamps = np.asarray(seq.timestamps)
        self.gt_poses = np.asarray(seq.gt_poses)
        self.T_cam_velo = seq.T_cam_velo
        self.motion_compensated = bool(getattr(seq, "motion_compensated", True))
        if getattr(seq, "scan_period", None) is not None:
            self.scan_period = seq.scan_period

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i: int):
        return self.frames[i]

    def __iter__(self):
        return iter(self.frames)


class GrFrontEnd:
    """The frame loop's odometry path: (deskew) + preprocess + VGICP odometry, one thread."""

    def __init__(self, deskew: bool, timestamps: np.ndarray) -> None:
        self.pc = PreprocessConfig()
        self.odo = VgicpOdometry(OdometryConfig(), GraphConfig())
        self.deskewer = FrameDeskewer(SCAN_PERIOD) if deskew else None
        self.ts = timestamps
        self.i = 0

    def __call__(self, frame) -> np.ndarray:
        if self.deskewer is not None:
            i = self.i
            period = float(self.ts[i - 1] - self.ts[i - 2]) if i >= 2 else None
            frame = self.deskewer(frame, self.odo.last_increment, period)
        self.i += 1
        self.odo.step(preprocess_scan(frame.points, self.pc, num_threads=1))
        return self.odo.poses[-1]


class KissFrontEnd:
    """KISS-ICP 1.3.0. With deskewing it moves every point to the END of the sweep (measured:
    a point at sweep fraction t gets ``Exp((t - 1) xi)``), so its poses refer to the sweep's
    end; ``mid_sweep_poses`` moves them back by half of its own last increment, to the
    mid-sweep instant the ground truth refers to."""

    def __init__(self, deskew: bool, mid_sweep_poses: bool = True) -> None:
        self.k = kiss_icp(deskew)
        self.deskew = deskew
        self.mid = deskew and mid_sweep_poses
        self.empty = np.zeros(0)

    def __call__(self, frame) -> np.ndarray:
        from factors.se3 import exp_se3, log_se3

        times = frame.time if (self.deskew and frame.time is not None) else self.empty
        self.k.register_frame(frame.points, times)
        pose = self.k.last_pose.copy()
        if self.mid and len(times):
            pose = pose @ exp_se3(-0.5 * log_se3(np.asarray(self.k.last_delta)))
        return pose


def _metrics(poses: np.ndarray, seq) -> dict:
    from gr_graph.metrics import ate, rpe_translation, trajectory_metrics

    gt = np.linalg.inv(seq.gt_poses[0]) @ seq.gt_poses
    T = seq.T_cam_velo
    e, g = velo_to_cam_poses(np.asarray(poses), T), velo_to_cam_poses(gt, T)
    out = {"rpe10_mean": rpe_translation(e, g, delta=10).mean, "ate_rmse": ate(e, g).rmse, "kitti_t_err_percent": None}
    if len(poses) >= 200:
        out["kitti_t_err_percent"] = trajectory_metrics(e, g, delta=100)["kitti_t_err_percent"]
    return out


# ----------------------------------------------------------------------------- sections


def bench_accuracy(stretches: list[tuple[int, int]]) -> dict:
    from gr_graph.frame_loop import run_slam

    cfg = load_config(overrides={"loops": {"enabled": False}, "graph": {"marginals": False},
                                 "output": {"progress": False}})
    rows = []
    for a, b in stretches:
        seq, desc = open_seq((a, b))
        clean = Cached(seq)
        gt = clean.gt_poses
        speed = float(np.mean(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1) / np.diff(clean.timestamps)))
        raw = Cached(MotionDistortedSequence(clean, SCAN_PERIOD))
        raw_notime = Cached(raw, strip_time=True)
        comp = Cached(MotionDistortedSequence(clean, SCAN_PERIOD, compensation_velocity_noise=COMP_VELOCITY_NOISE,
                                              compensation_rate_noise_deg=COMP_RATE_NOISE_DEG))
        runs = [("clean", clean, "auto"), ("raw", raw, "off"), ("raw", raw, "auto"), ("raw, no times", raw_notime, "on"),
                ("compensated", comp, "auto"), ("compensated", comp, "on")]
        for variant, s, mode in runs:
            res = run_slam(s, cfg.model_copy(update={"odometry": cfg.odometry.model_copy(update={"deskew": mode})}))
            d = res.info["deskew"]
            src = ",".join(k for k, v in d["time_source"].items() if v) or "-"
            rows.append({"stretch": f"{a}:{b}", "speed_mps": speed, "variant": variant, "system": "gr_graph",
                         "deskew": f"{mode} ({'on' if d['enabled'] else 'off'}; times: {src})",
                         **_metrics(res.odometry_poses, s)})
            print(rows[-1], flush=True)
        for variant, s, dks in (("clean", clean, (False,)), ("raw", raw, (False, True))):
            for dk in dks:
                fe = KissFrontEnd(dk)
                P = np.array([fe(f) for f in s])
                rows.append({"stretch": f"{a}:{b}", "speed_mps": speed, "variant": variant, "system": "kiss_icp",
                             "deskew": "on (data times; poses moved to mid-sweep)" if dk else "off", **_metrics(P, s)})
                print(rows[-1], flush=True)
    return {"source": "synthetic KITTI 00, seed 0, 64 rings", "scan_period": SCAN_PERIOD,
            "compensation_noise": [COMP_VELOCITY_NOISE, COMP_RATE_NOISE_DEG], "rows": rows}


def bench_throughput(frames: tuple[int, int]) -> dict:
    seq, desc = open_seq(frames)
    raw = Cached(MotionDistortedSequence(Cached(seq), SCAN_PERIOD))
    out = {"source": desc + ", raw variant (MotionDistortedSequence, 0.1 s sweeps)", "n_frames": len(raw), "rows": []}
    for ch in CHANNELS:
        fr = [f if ch == 64 else subsample_channels(f, ch) for f in raw.frames]
        fr_notime = [replace(f, time=None) for f in fr]
        row = {"channels": ch, "mean_points": float(np.mean([len(f) for f in fr]))}
        systems = (("gr_off", lambda: GrFrontEnd(False, raw.timestamps), fr),
                   ("gr_on_data", lambda: GrFrontEnd(True, raw.timestamps), fr),
                   ("gr_on_azimuth", lambda: GrFrontEnd(True, raw.timestamps), fr_notime),
                   ("kiss_off", lambda: KissFrontEnd(False), fr),
                   ("kiss_on", lambda: KissFrontEnd(True), fr))
        for name, make, frames_ in systems:
            fe = make()
            t0 = time.perf_counter()
            for f in frames_:
                fe(f)
            row[f"{name}_fps"] = len(frames_) / (time.perf_counter() - t0)
        row["gr_on_over_off"] = row["gr_on_data_fps"] / row["gr_off_fps"]
        row["gr_on_over_kiss_on"] = row["gr_on_data_fps"] / row["kiss_on_fps"]
        row["gr_on_azimuth_over_kiss_on"] = row["gr_on_azimuth_fps"] / row["kiss_on_fps"]
        row["gr_off_over_kiss_off"] = row["gr_off_fps"] / row["kiss_off_fps"]
        out["rows"].append(row)
        print(row, flush=True)
    return out


def bench_vertical(root: Path) -> dict:
    import small_gicp

    from gr_graph.datasets.kitti import KittiSequence
    from gr_graph.datasets.realism import STATISTICS, downsample, frame_statistics, vgicp_inlier_rmse
    from factors.se3 import rotation_angle

    rows = []
    for angle in (0.0, 0.195, 0.205, 0.22):
        seq = KittiSequence(root, "00", recover_ring_index=False, vertical_correction_deg=angle)
        pts = [seq[i].points for i in range(len(seq))]
        stats = [frame_statistics(p) for p in pts]
        row = {"angle_deg": angle, **{k: float(np.mean([getattr(s, k) for s in stats])) for k in STATISTICS}}
        rmse, terr, rerr = [], [], []
        for i in range(len(pts) - 1):
            rmse.append(100.0 * vgicp_inlier_rmse(pts[i], pts[i + 1]))
            src, tgt = downsample(pts[i + 1]), downsample(pts[i])
            res = small_gicp.align(tgt, src, registration_type="VGICP", voxel_resolution=1.0,
                                   max_correspondence_distance=1.0, num_threads=1)
            gt_rel = np.linalg.inv(seq.gt_poses[i]) @ seq.gt_poses[i + 1]
            dev = np.linalg.inv(gt_rel) @ np.asarray(res.T_target_source)
            terr.append(100.0 * float(np.linalg.norm(dev[:3, 3])))
            rerr.append(float(np.degrees(rotation_angle(dev[:3, :3]))))
        row.update(vgicp_inlier_rmse_cm=float(np.mean(rmse)), registration_t_err_cm=float(np.mean(terr)),
                   registration_r_err_deg=float(np.mean(rerr)), n_frames=len(pts))
        rows.append(row)
        print(row, flush=True)
    return {"source": f"real KITTI 00 frames in {root}", "rows": rows}


# ----------------------------------------------------------------------------- report


def _f(x, fmt="{:.3f}"):
    return "-" if x is None else fmt.format(x)


def write_markdown() -> Path:
    lines = ["# Deskewing (gr_graph.frame_loop, odometry.deskew) and the KITTI vertical-angle correction", "",
             f"Machine: {machine()}. Ratios are measured on the same frames in the same process.", ""]
    p = RESULTS / "deskew_accuracy.json"
    if p.exists():
        d = json.loads(p.read_text())
        lines += ["## Accuracy on motion-distorted synthetic stretches", "",
                  f"`python benchmarks/bench_deskew.py accuracy --stretches {d['stretches']}` — {d['source']}; "
                  f"{d['scan_period']} s sweeps, `raw` = full distortion with per-point times, `compensated` = "
                  f"compensated with velocity errors of {d['compensation_noise'][0]} m/s and "
                  f"{d['compensation_noise'][1]} deg/s per axis. Odometry only, camera frame; RPE over 10 frames "
                  "(mean, m), ATE RMSE (m), KITTI % on stretches of 200+ frames.", "",
                  "| stretch | speed [m/s] | data | system | deskew | RPE-10 [m] | ATE [m] | KITTI % |",
                  "|---|---|---|---|---|---|---|---|"]
        for r in d["rows"]:
            lines.append(f"| {r['stretch']} | {r['speed_mps']:.1f} | {r['variant']} | {r['system']} | {r['deskew']} | "
                         f"{_f(r['rpe10_mean'])} | {_f(r['ate_rmse'])} | {_f(r['kitti_t_err_percent'], '{:.2f}')} |")
        lines.append("")
    p = RESULTS / "deskew_throughput.json"
    if p.exists():
        d = json.loads(p.read_text())
        lines += ["## Throughput with deskewing (frames/s, one thread each)", "",
                  f"`python benchmarks/bench_deskew.py throughput --frames {d['frames']}` — {d['source']}; "
                  f"{d['n_frames']} frames held in RAM. gr_graph = deskew (the frame loop's `FrameDeskewer`) + "
                  "preprocess + VGICP odometry; KISS-ICP 1.3.0 with its default config, deskewing with the same "
                  "per-point times.", "",
                  "| channels | points | gr off | gr on (data t) | gr on (azimuth t) | KISS off | KISS on | "
                  "gr on / gr off | gr on / KISS on (target ≥ 2) | gr on (az.) / KISS on | gr off / KISS off |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in d["rows"]:
            lines.append(f"| {r['channels']} | {r['mean_points']:.0f} | {r['gr_off_fps']:.1f} | "
                         f"{r['gr_on_data_fps']:.1f} | {r['gr_on_azimuth_fps']:.1f} | {r['kiss_off_fps']:.1f} | "
                         f"{r['kiss_on_fps']:.1f} | {r['gr_on_over_off']:.2f} | {r['gr_on_over_kiss_on']:.2f} | "
                         f"{r['gr_on_azimuth_over_kiss_on']:.2f} | {r['gr_off_over_kiss_off']:.2f} |")
        lines.append("")
    p = RESULTS / "deskew_vertical.json"
    if p.exists():
        d = json.loads(p.read_text())
        lines += ["## KITTI vertical-angle correction on real frames", "",
                  f"`python benchmarks/bench_deskew.py vertical` — {d['source']} (mean over frames; registration "
                  "figures over consecutive pairs: VGICP of frame k+1 onto k from the identity, 1 m voxels, against "
                  "the ground-truth relative pose).", "",
                  "| angle [deg] | thickness [cm] | a90 | a99 | points/frame | VGICP inlier RMSE [cm] | "
                  "registration t err [cm] | registration r err [deg] |", "|---|---|---|---|---|---|---|---|"]
        for r in d["rows"]:
            lines.append(f"| {r['angle_deg']:g} | {r['thickness_cm']:.2f} | {r['a90']:.3f} | {r['a99']:.3f} | "
                         f"{r['points_per_frame']:.0f} | {r['vgicp_inlier_rmse_cm']:.2f} | "
                         f"{r['registration_t_err_cm']:.2f} | {r['registration_r_err_deg']:.3f} |")
        lines.append("")
    out = RESULTS / "deskew.md"
    atomic_write_text(out, "\n".join(lines) + "\n")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("section", choices=("accuracy", "throughput", "vertical", "report"))
    ap.add_argument("--stretches", default="4200:4260,3950:4010,0:300")
    ap.add_argument("--frames", default="1000:1200")
    ap.add_argument("--kitti", default=str(REPO.parent / "shared" / "data" / "kitti"))
    a = ap.parse_args()
    RESULTS.mkdir(parents=True, exist_ok=True)
    if a.section == "accuracy":
        d = bench_accuracy([parse_frames(s) for s in a.stretches.split(",")])
        d["stretches"] = a.stretches
    elif a.section == "throughput":
        d = bench_throughput(parse_frames(a.frames))
        d["frames"] = a.frames
    elif a.section == "vertical":
        d = bench_vertical(Path(a.kitti))
    if a.section != "report":
        d["machine"] = machine()
        atomic_write_json(RESULTS / f"deskew_{a.section}.json", d)
    print(write_markdown())


if __name__ == "__main__":
    main()
