"""Benchmark of the trainer: time per training pair, time per epoch of synthetic KITTI 00, memory,
and what the self-supervised covariances learn compared with PCA on 16-channel scans.

    python benchmarks/bench_training.py [--frames 41] [--rings 64] [--threads 1] [--no-learning] --write

With ``--write``, writes ``benchmarks/results/training.md`` (without it, prints the figures only). The
published file was measured on 2026-11-22, before the library's defaults changed: this script pins
what it measured then (the ``clean`` synthetic world, the Gaussian correspondence likelihood), so a
rerun measures the same configuration.

Part 1 (speed). Frames ``start .. start+frames`` of the synthetic KITTI 00 sequence
(``gr_graph.datasets.synthetic``) are preprocessed exactly like the SLAM stores them
(``gr_graph.preprocess.preprocess_scan``, 0.5 m voxels), paired as odometry edges (k, k+1)
with the ground-truth T̂ and nearest-neighbour correspondences within 1 m (as
``gr_graph.memory_builder.build_memory`` does), and one epoch of Algorithm 1 is run with the default
TrainConfig. The time of one epoch over all 4540 odometry pairs of KITTI 00 is extrapolated
from the measured mean time per pair (rendering all 4541 frames is not part of training).

Part 2 (what is learned). A 16-channel street scene with known normals and known normal noise
(``training.toy_scenes``) is trained self-supervised; the predicted covariances of a held-out
scan are compared with the true normals / noise and with PCA covariances of the raw k-NN
neighbourhood (k = 10, 16, 30) on the same points.
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from gr_graph.atomic import atomic_write_text  # noqa: E402
from gr_graph.correspondences import nearest_correspondences, target_tree  # noqa: E402
from gr_graph.memory import Memory  # noqa: E402
from training.trainer import TrainConfig, Trainer  # noqa: E402

N_KITTI00_PAIRS = 4540
#: what the published training.md measured (2026-11-22), pinned: the defaults have changed since (the
#: synthetic world's preset is ``kitti``, the correspondence likelihood a Student t, whose C is a scale
#: matrix: the λ_min/σ² column's "1 is right" holds for the Gaussian only)
SYNTHETIC_PRESET = "clean"
CORR_LIKELIHOOD = "gaussian"
NOTES = """
Findings (written by hand after the 2026-11-22 run; a rerun prints them unchanged: check them against its tables):
- Ground, the majority of the points of a 16-channel scan, where a k-NN neighbourhood collapses onto one scan
  line: the learned covariances get the normal right (median ~1°, 98-99 % within 10°) and the noise level within
  the factor-2 bound (λ_min/σ² ≈ 0.75), where PCA with k = 10/16 is wrong (~88°, λ_min/σ² ≈ 0.01-0.04).
- Walls and cylinders: PCA with k ≥ 10 is better on this scene at these budgets; the learned covariances improve
  with training (walls 6.4° → 4.4°, cylinders 25.6° → 17.6° median from 20 to 60 epochs). A verified cause on the
  walls: with nearest-neighbour correspondences, the scan lines of two scans hit a vertical wall at nearly the
  same heights, so the residuals are small vertically as well as along the normal (and mixed-surface outliers
  make the normal-direction residual variance 3-4x 2σ² there); the correspondence likelihood then does not single
  out the normal. The paper's Theorem 1 assumes correspondences of the same underlying point.
- PCA with k = 30 is competitive overall on this scene (median 1.7° vs 1.9°); the premise "learned beats PCA"
  holds against the usual small neighbourhoods (k = 10-20, GICP's choice) on sparse scan lines.
"""


def build_synthetic_memory(start: int, frames: int, rings: int) -> tuple[Memory, float]:
    from gr_graph.config import PreprocessConfig
    from gr_graph.datasets.synthetic import SyntheticSequence
    from gr_graph.preprocess import preprocess_scan

    seq = SyntheticSequence(seed=0, n_rings=rings, preset=SYNTHETIC_PRESET)
    pc = PreprocessConfig()
    t0 = time.perf_counter()
    scans, poses = [], []
    for i in range(start, start + frames):
        fr = seq[i]
        scans.append(preprocess_scan(fr.points, pc, index=i).points.astype(np.float32))
        poses.append(seq.gt_poses[i])
    t_render = time.perf_counter() - t0
    edges, eT, corr = [], [], []
    for k in range(frames - 1):
        T = np.linalg.inv(poses[k + 1]) @ poses[k]
        edges.append((k, k + 1))
        eT.append(T)
        corr.append(nearest_correspondences(scans[k], target_tree(scans[k + 1]), T, 1.0))
    mem = Memory.from_scans(scans, np.stack(poses), edges, [0] * len(edges), eT, [np.eye(6)] * len(edges), corr)
    return mem, t_render


def time_components(trainer: Trainer, n: int) -> dict[str, float]:
    """Mean seconds per pair of sampling, forward, losses (incl. pose layer) and backward."""
    acc = {"sample": 0.0, "forward": 0.0, "losses": 0.0, "backward": 0.0}
    for e in range(n):
        t0 = time.perf_counter()
        s = trainer.dataset.sample(e % len(trainer.dataset), 99)
        t1 = time.perf_counter()
        C = trainer.forward(s)
        t2 = time.perf_counter()
        loss, _ = trainer.pair_loss(s, C)
        t3 = time.perf_counter()
        loss.backward()
        trainer.model.zero_grad()
        t4 = time.perf_counter()
        for k, dt in zip(acc, (t1 - t0, t2 - t1, t3 - t2, t4 - t3)):
            acc[k] += dt / n
    return acc


def speed(args) -> dict:
    torch.set_num_threads(args.threads)
    mem, t_render = build_synthetic_memory(args.start, args.frames, args.rings)
    sizes = np.diff(mem.scan_offsets)
    ncorr = np.diff(mem.corr_offsets)
    presets = {}
    for n_points, max_corr in ((4096, 2048), (2048, 1024), (1024, 512)):
        with tempfile.TemporaryDirectory() as tmp:
            cfg = TrainConfig.from_dict({"epochs": 1, "progress": False, "num_threads": args.threads, "max_corr": max_corr,
                                         "corr_likelihood": CORR_LIKELIHOOD, "net": {"n_points": n_points}})
            tr = Trainer(mem, tmp, cfg)
            comp = time_components(tr, min(10, mem.n_edges))
            t0 = time.perf_counter()
            tr.fit(resume=False)
            t_epoch = time.perf_counter() - t0
            recs = [json.loads(x) for x in (Path(tmp) / "train_log.jsonl").read_text().splitlines()]
            step_median = json.loads((Path(tmp) / "summary.json").read_text())["runtime_s"]["step_median"]
        per_pair = t_epoch / mem.n_edges
        presets[f"{n_points}/{max_corr}"] = {
            "n_points": n_points, "max_corr": max_corr, "epoch_s": t_epoch, "per_pair_s": per_pair,
            "per_pair_step_median_s": step_median,  # pairs_per_step = 1
            "components_s": comp, "kitti00_epoch_min": per_pair * N_KITTI00_PAIRS / 60,
            "skipped": int(sum(1 for r in recs if r.get("skipped"))),
        }
    return {
        "frames": args.frames, "start": args.start, "rings": args.rings, "threads": args.threads,
        "points_per_scan_mean": float(sizes.mean()), "corr_per_edge_mean": float(ncorr.mean()),
        "render_preprocess_s": t_render, "pairs": mem.n_edges, "presets": presets,
    }


def geometry_metrics(C: np.ndarray, normals: np.ndarray, sigma: float) -> dict[str, float]:
    from training.toy_scenes import normal_angles_deg

    ang, w = normal_angles_deg(C, normals)
    return {"angle_median_deg": float(np.median(ang)), "angle_p75_deg": float(np.percentile(ang, 75)),
            "frac_below_10deg": float(np.mean(ang < 10)), "lambda_min_ratio_median": float(np.median(w[:, 0]) / sigma**2)}


def learning(args) -> dict:
    from training.predict import predict_covariances
    from training.toy_scenes import pca_covariances, street_learning_problem

    torch.set_num_threads(args.threads)
    sigma = 0.02
    # the same scene, memory and held-out scan as tests/training/test_learns_geometry.py
    prob = street_learning_problem(sigma=sigma)
    scene, mem, edges, pts, nrm, ids = prob.scene, prob.memory, prob.edges, prob.points, prob.normals, prob.ids
    groups = {"all": np.ones(len(pts), bool), "ground": ids == 0, "walls": (ids == 1) | (ids == 2),
              "cylinders": ids >= len(scene.planes)}
    out = {"sigma": sigma, "n_points_eval": len(pts), "train_s": {}, "epochs": args.learn_epochs}
    with tempfile.TemporaryDirectory() as tmp:
        cfg = TrainConfig.from_dict({"epochs": max(args.learn_epochs), "lr": 3e-3, "max_corr": 1024, "progress": False,
                                     "checkpoint_every": 10**6, "corr_likelihood": CORR_LIKELIHOOD,
                                     "net": {"n_points": 4096}})
        tr = Trainer(mem, tmp, cfg)
        snaps = {}

        def snap(rec):
            if rec["step"] == len(edges) - 1 and rec["epoch"] + 1 in args.learn_epochs:
                snaps[rec["epoch"] + 1] = ({k: v.clone() for k, v in tr.model.state_dict().items()}, time.perf_counter() - t0)

        t0 = time.perf_counter()
        tr.fit(resume=False, callback=snap)
        for ep, (state, t) in sorted(snaps.items()):
            tr.model.load_state_dict(state)
            C = predict_covariances(tr.model, pts, n_points=4096)
            out["train_s"][ep] = t
            for g, m in groups.items():
                out[f"net-{ep}ep/{g}"] = geometry_metrics(C[m], nrm[m], sigma)
    for k in (10, 16, 30):
        Cp = pca_covariances(pts, k)
        for g, m in groups.items():
            out[f"pca{k}/{g}"] = geometry_metrics(Cp[m], nrm[m], sigma)
    return out


def write_report(sp: dict, le: dict | None, path: Path, argv: list[str]) -> None:
    L = ["# Training benchmark", "",
         f"Reproduce: `python benchmarks/bench_training.py {' '.join(a for a in argv if a != '--write')} --write`", "",
         f"Machine: {platform.processor() or platform.machine()}, 2 cores shared with other jobs while measured, "
         f"torch {torch.__version__}, {sp['threads']} torch thread(s) (2 threads were slower under contention).", "",
         "## Speed (synthetic KITTI 00, preprocessed like the SLAM memory)", "",
         f"{sp['pairs']} odometry pairs from frames {sp['start']}..{sp['start'] + sp['frames'] - 1}, {sp['rings']} rings, "
         f"{sp['points_per_scan_mean']:.0f} stored points/scan (0.5 m voxels), {sp['corr_per_edge_mean']:.0f} "
         "correspondences/edge. Time per pair = sampling + neighbourhoods + forward + both losses with the pose "
         "layer + backward + Adam. The KITTI 00 epoch (4540 odometry pairs) is extrapolated from the measured mean.", "",
         "| network input / correspondences | time per pair | sample | forward | losses | backward | epoch, KITTI 00 (4540 pairs) |",
         "|---|---|---|---|---|---|---|"]
    for name, p in sp["presets"].items():
        c = p["components_s"]
        L.append(f"| {p['n_points']} pts / {p['max_corr']} corr | {p['per_pair_s'] * 1000:.0f} ms | {c['sample'] * 1000:.0f} ms | "
                 f"{c['forward'] * 1000:.0f} ms | {c['losses'] * 1000:.0f} ms | {c['backward'] * 1000:.0f} ms | "
                 f"**{p['kitti00_epoch_min']:.1f} min** |")
    L += ["", "Paper: ~15 min per epoch. Target here: < 5 min. Default: `NetConfig.n_points = 2048`, `TrainConfig.max_corr = 1024` (the second row; on the 16-channel scene below it learned about as well as 4096 points in a run outside this script on 2026-11-22: ground 1.1°, walls 5.2°, cylinders 27.7° median after 20 epochs, vs 1.1° / 6.4° / 25.6°), and the other "
          "presets above; `torchrun --nproc_per_node=2 -m training.ddp` splits each step's pairs over processes "
          "(~2x on 2 free cores, not measured here because the cores were shared).",
          f"Peak resident memory of the benchmark process: {sp['peak_rss_mb']:.0f} MB.", ""]
    if le:
        L += ["## What is learned: 16-channel street scene, known normals, normal noise σ = "
              f"{le['sigma'] * 100:.0f} cm", "",
              "Same scene as `tests/training/test_learns_geometry.py`: 16 rings (+2..-24.8°), 0.5° azimuth, ground + 2 walls "
              "+ cylinders (r 0.3-1 m); 6 training scans, 9 pairs with true T̂ and NN correspondences; held-out scan "
              f"of {le['n_points_eval']} points. Training time to each budget: "
              + ", ".join(f"{e} epochs {t:.0f} s" for e, t in le["train_s"].items()) + ". "
              "Angle = smallest eigenvector vs true normal; λ_min/σ² = smallest eigenvalue over the true noise "
              "variance (1 is right).", "",
              "| estimator | points | median angle (°) | 75th pct (°) | < 10° | median λ_min/σ² |",
              "|---|---|---|---|---|---|"]
        for key in [k for k in le if "/" in k]:
            est, g = key.split("/")
            m = le[key]
            L.append(f"| {est} | {g} | {m['angle_median_deg']:.1f} | {m['angle_p75_deg']:.1f} | "
                     f"{m['frac_below_10deg'] * 100:.0f}% | {m['lambda_min_ratio_median']:.2f} |")
        L.append(NOTES)
    atomic_write_text(path, "\n".join(L) + "\n")


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=41)
    ap.add_argument("--start", type=int, default=100)
    ap.add_argument("--rings", type=int, default=64)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--learn-epochs", type=int, nargs="+", default=[20, 60])
    ap.add_argument("--no-learning", action="store_true")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "training.md"))
    ap.add_argument("--write", action="store_true", help="write --out (without it the figures are printed only)")
    args = ap.parse_args(argv)
    sp = speed(args)
    le = None if args.no_learning else learning(args)
    sp["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps({"speed": sp, "learning": le, "synthetic_preset": SYNTHETIC_PRESET,
                      "corr_likelihood": CORR_LIKELIHOOD}, indent=1))
    if args.write:
        write_report(sp, le, Path(args.out), argv)
    else:
        print(f"not written: add --write to replace {args.out}")


if __name__ == "__main__":
    main()
