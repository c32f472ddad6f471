"""Does the long-baseline consistency see what a learning round did to the drift? (a study)

For every finished run and every learning round, the GT-free acceptance test
(:mod:`gr_graph.round_acceptance`, the package's defaults or ``--set KEY=VALUE``) is redone with
the long-baseline figure (:func:`gr_graph.round_acceptance.long_baseline_comparison`: frame pairs
25 m apart registered raw scan to raw scan; the median rotation discrepancy of each trajectory
with them), and the rounds are judged in order as a run judges them: against the last accepted
round, stopping at the first rejection. Each threshold of ``--thresholds`` on the median rotation
discrepancy's increase is applied on top of the test's other rules; the 2x2 count
(accepted/rejected x worse/not worse by ground truth: all-pairs RPE-300 and ATE more than 5 %
above the reference round's) is given for each.

Run::

    python benchmarks/long_baseline_study.py RUN[@SCANS] [RUN[@SCANS] ...] [--labels ...]
        [--thresholds none 0.05 0.1 0.2] [--set KEY=VALUE] [--write NAME]

``@SCANS``: a run whose ``round_0/memory`` holds the same raw scans (the harness prunes its
cells' memories; a rerun of round 0 with the cell's config, ``python -m gr_graph.slam --config
CELL/slam/config.yaml --rounds 0 --out SCANS``, rebuilds them). Round 0's poses of the two must
agree to a millimetre. ``--write NAME`` writes ``benchmarks/results/NAME.md`` and ``.json``.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path
from typing import Any

import numpy as np

from bench_round_acceptance import acceptance_settings, worse
from gr_graph.provenance import machine_line
from results_io import last_change, print_and_write


def run_and_scans(spec: str) -> tuple[Path, Path]:
    """``RUN[@SCANS]`` -> (run, the run whose round 0 memory holds the raw scans)."""
    run, _, scans = spec.partition("@")
    return Path(run), Path(scans or run)


def load_scans(run: Path, scans_run: Path) -> list[np.ndarray]:
    """Round 0's raw scans of ``scans_run``, checked to be ``run``'s (round 0 poses within 1 mm)."""
    from gr_graph.round_acceptance import _raw_scans
    from gr_graph.round_output import read_round_poses, round_dir

    if not (scans_run / "round_0" / "memory").is_dir():
        raise SystemExit(f"{scans_run}: no round_0/memory (pruned?): give RUN@SCANS with a run that has it")
    a, b = read_round_poses(round_dir(run, 0)), read_round_poses(round_dir(scans_run, 0))
    if a.shape != b.shape or np.abs(a[:, :3, 3] - b[:, :3, 3]).max() > 1e-3:
        raise SystemExit(f"{scans_run}: its round 0 is not {run}'s (poses differ): not the same scans")
    return _raw_scans(scans_run)


def study_run(run: Path, scans: list[np.ndarray], cfg: Any, thresholds: list[float | None],
              gt: np.ndarray | None) -> dict[str, Any]:
    """Verdicts of ``run``'s learning rounds under each threshold (module docstring); ``gt``:
    :func:`lidar_truth`."""
    from gr_graph.round_acceptance import evaluate_round

    m = json.loads((run / "metrics.json").read_text())
    summaries = m["rounds"]
    rounds = sorted(int(k) for k, s in summaries.items() if "slam" in s and (run / f"round_{k}" / "marginals.npz").is_file())
    cache: dict[tuple[int, int], dict[str, Any]] = {}

    def verdict(r: int, ref: int) -> dict[str, Any]:
        if (r, ref) not in cache:
            v = evaluate_round(run, r, ref, summaries, cfg, scans=scans)
            s, s0 = summaries[str(r)]["slam"], summaries[str(ref)]["slam"]
            lb = v["long_baseline"] or {}
            cache[(r, ref)] = {
                "round": r, "reference": ref, "other_rules_accept": v["accepted"], "reasons": v["reasons"],
                "mean_entropy_increase": v["mean_entropy_increase"], "long_baseline": lb,
                "rotation_increase_with_truth": truth_figure(run, gt, r, ref, cfg),
                "rpe300": [s0["rpe300_all_pairs_mean"], s["rpe300_all_pairs_mean"]],
                "ate": [s0["ate_rmse"], s["ate_rmse"]]}
        return cache[(r, ref)]

    by_threshold = {}
    for thr in thresholds:
        ref, judged = 0, []
        for r in rounds[1:]:
            v = dict(verdict(r, ref))
            inc = v["long_baseline"].get("rotation_increase")
            v["accepted"] = bool(v["other_rules_accept"] and (thr is None or inc is None or inc <= thr))
            judged.append(v)
            if not v["accepted"]:
                break
            ref = r
        by_threshold[str(thr)] = {"judged": judged, "final_round": ref}
    return {"rounds": rounds, "by_threshold": by_threshold, "verdicts": list(cache.values())}


def synthetic_lidar_poses(path: Path) -> np.ndarray:
    """A synthetic run's KITTI-form pose file (camera frame) in the LiDAR's frame (the rig's
    ``T_cam_velo`` takes it there)."""
    from gr_graph.datasets.base import cam_to_velo_poses
    from gr_graph.datasets.synthetic.rig import T_cam_velo
    from gr_graph.trajectory import read_kitti_poses

    return cam_to_velo_poses(read_kitti_poses(path), T_cam_velo())


def lidar_truth(run: Path) -> np.ndarray | None:
    """The synthetic run's ground-truth poses in the LiDAR's frame (:func:`synthetic_lidar_poses`);
    None for other runs."""
    source = json.loads((run / "metrics.json").read_text()).get("source", "")
    if "synthetic world" not in source or not (run / "gt_poses_kitti.txt").is_file():
        return None
    return synthetic_lidar_poses(run / "gt_poses_kitti.txt")


def truth_figure(run: Path, gt: np.ndarray | None, r: int, ref: int, cfg: Any) -> float | None:
    """The rotation figure with perfect registrations: the check's pairs (from the reference round's
    path; all of them, where the check keeps the registered ones), the ground truth's relative poses
    in place of the registrations; the round's median
    rotation discrepancy over the reference's, minus 1. It tells a blind figure (this does not rise
    either) from registrations that mislead it (this rises, the registered one does not). ``gt``:
    :func:`lidar_truth` (None: no ground truth, and None is returned)."""
    from gr_graph.long_baseline import baseline_pairs, pair_discrepancy
    from gr_graph.round_output import read_round_poses, round_dir

    if gt is None:
        return None
    poses, ref_poses = read_round_poses(round_dir(run, r)), read_round_poses(round_dir(run, ref))
    pairs = baseline_pairs(ref_poses[:, :3, 3], cfg.long_baseline_distance, cfg.long_baseline_step,
                           cfg.long_baseline_max_frames)
    if len(pairs) == 0:
        return None
    T_true = np.linalg.inv(gt[pairs[:, 0]]) @ gt[pairs[:, 1]]
    a, a_ref = (float(np.median(pair_discrepancy(p, pairs, T_true)[1])) for p in (poses, ref_poses))
    return a / a_ref - 1.0 if a_ref > 0 else None


def registration_truth(run: Path, scans: list[np.ndarray], cfg: Any, gt: np.ndarray | None) -> dict[str, Any] | None:
    """The pairs' registrations (from round 0's poses) against the ground truth: mean and standard
    deviation of the pitch and height of ``T_gt⁻¹ T_reg`` over the pairs. ``gt``: :func:`lidar_truth`
    (synthetic runs only; None otherwise, and None is returned)."""
    from scipy.spatial.transform import Rotation

    from gr_graph.long_baseline import baseline_pairs, register_pairs
    from gr_graph.round_output import read_round_poses, round_dir

    if gt is None:
        return None
    poses = read_round_poses(round_dir(run, 0))
    pairs = baseline_pairs(poses[:, :3, 3], cfg.long_baseline_distance, cfg.long_baseline_step,
                           cfg.long_baseline_max_frames)
    T, ok = register_pairs(scans, poses, pairs, cfg.long_baseline_voxel_size, cfg.long_baseline_max_correspondence,
                           cfg.long_baseline_min_inliers)
    E = np.linalg.inv(np.linalg.inv(gt[pairs[ok, 0]]) @ gt[pairs[ok, 1]]) @ T[ok]
    pitch = np.degrees(Rotation.from_matrix(E[:, :3, :3]).as_rotvec()[:, 1])  # about the LiDAR's y axis
    return {"n": int(ok.sum()), "pitch_mean_deg": float(pitch.mean()), "pitch_std_deg": float(pitch.std()),
            "height_mean_m": float(E[:, 2, 3].mean()), "height_std_m": float(E[:, 2, 3].std())}


def report(results: dict[str, dict[str, Any]], thresholds: list[float | None], command: str, cfg: Any) -> str:
    lines = ["# Long-baseline consistency as an acceptance rule, against ground truth", "",
             f"`{command}`; {machine_line()}. Pairs {cfg.long_baseline_distance:g} m apart along the reference's path, "
             f"one every {cfg.long_baseline_step} frames, registered raw scan to raw scan (GICP, voxel "
             f"{cfg.long_baseline_voxel_size:g} m); per trajectory the median rotation angle of T_reg⁻¹ · T_k⁻¹ T_l. "
             "\"rot.\" is the round's median over the reference round's, minus 1; \"other rules\" is the test's "
             "verdict without this figure (map entropy, standstill creep, failures). Changes by ground truth are "
             "against the reference round (all-pairs RPE-300 mean, ATE RMSE).", "",
             "\"rot., GT\" is the same figure with the ground truth's relative poses in place of the registrations "
             "(perfect registrations): where it does not rise either, the figure itself is blind to the round's change.",
             "", "| run | round | ref | pairs | rot. median ref → round [deg] | rot. | rot., GT | transl. | pairs worse | "
             "other rules | RPE-300 | ATE |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for label, res in results.items():
        for v in sorted(res["verdicts"], key=lambda v: (v["round"], v["reference"])):
            lb = v["long_baseline"]
            rot = "-" if lb.get("rotation_increase") is None else f"{100 * lb['rotation_increase']:+.0f} %"
            tr = "-" if lb.get("translation_increase") is None else f"{100 * lb['translation_increase']:+.0f} %"
            med = ("-" if lb.get("rotation_deg") is None
                   else f"{lb['reference_rotation_deg']:.4f} → {lb['rotation_deg']:.4f}")
            fw = "-" if lb.get("fraction_rotation_worse") is None else f"{lb['fraction_rotation_worse']:.2f}"
            gt_inc = v.get("rotation_increase_with_truth")
            rot_gt = "-" if gt_inc is None else f"{100 * gt_inc:+.0f} %"
            lines.append(f"| {label} | {v['round']} | {v['reference']} | {lb.get('n_registered', 0)}/{lb.get('n_pairs', 0)} "
                         f"| {med} | {rot} | {rot_gt} | {tr} | {fw} | {'accept' if v['other_rules_accept'] else 'reject'} | "
                         f"{last_change(v['rpe300'])} | {last_change(v['ate'])} |")
    lines += ["", "Rounds judged in order (stopping at the first rejection), per threshold on \"rot.\" (none: the "
              "other rules alone). Counts: accepted/rejected x worse (> 5 %) / not worse, by all-pairs RPE-300 and by "
              "ATE; final: the final round of each run.", "",
              "| threshold | acc., RPE-300 not worse | acc., worse | rej., not worse | rej., worse | acc., ATE not worse "
              "| acc., worse | rej., not worse | rej., worse | final rounds |", "|---|---|---|---|---|---|---|---|---|---|"]
    for thr in thresholds:
        c = {(k, a, w): 0 for k in ("rpe300", "ate") for a in (True, False) for w in (False, True)}
        finals = []
        for label, res in results.items():
            bt = res["by_threshold"][str(thr)]
            finals.append(f"{label}: {bt['final_round']}")
            for v in bt["judged"]:
                for k in ("rpe300", "ate"):
                    c[(k, v["accepted"], worse(*v[k]))] += 1
        cells = [str(c[(k, a, w)]) for k in ("rpe300", "ate") for a in (True, False) for w in (False, True)]
        lines.append(f"| {'none' if thr is None else f'+{100 * thr:g} %'} | " + " | ".join(cells)
                     + " | " + ", ".join(finals) + " |")
    truth = {label: res["registration_truth"] for label, res in results.items() if res.get("registration_truth")}
    if truth:
        lines += ["", "The registrations themselves against the ground truth (pairs from round 0's poses; T_gt⁻¹ T_reg, "
                  "pitch about the LiDAR's y axis, height along its z axis): a bias here is one the test would read "
                  "as the trajectories' drift.", "", "| run | pairs | pitch mean ± std [deg] | height mean ± std [mm] |",
                  "|---|---|---|---|"]
        lines += [f"| {label} | {t['n']} | {t['pitch_mean_deg']:+.3f} ± {t['pitch_std_deg']:.3f} | "
                  f"{1e3 * t['height_mean_m']:+.1f} ± {1e3 * t['height_std_m']:.1f} |" for label, t in truth.items()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="RUN or RUN@SCANS")
    ap.add_argument("--labels", nargs="+")
    ap.add_argument("--thresholds", nargs="+", default=["none", "0.05", "0.1", "0.2"],
                    help="thresholds on the rotation figure's increase ('none': the other rules alone)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override an acceptance setting")
    ap.add_argument("--write", metavar="NAME", help="also write benchmarks/results/NAME.md and .json")
    args = ap.parse_args(argv)
    cfg = acceptance_settings(None, [*args.set, "long_baseline=true", "max_long_baseline_rotation_increase=null"])
    thresholds = [None if t.lower() == "none" else float(t) for t in args.thresholds]
    specs = [run_and_scans(s) for s in args.runs]
    if args.labels and len(args.labels) != len(specs):
        ap.error(f"{len(args.labels)} labels for {len(specs)} runs")
    labels = args.labels or [str(r.parent.name if r.name == "slam" else r.name) for r, _ in specs]
    if len(set(labels)) != len(labels):
        ap.error(f"two runs share a label ({labels}): give --labels")
    results = {}
    for label, (run, scans_run) in zip(labels, specs, strict=True):
        scans = load_scans(run, scans_run)
        gt = lidar_truth(run)
        results[label] = {**study_run(run, scans, cfg, thresholds, gt),
                          "registration_truth": registration_truth(run, scans, cfg, gt)}
        print(f"{label}: done", file=sys.stderr, flush=True)
    command = "python benchmarks/long_baseline_study.py " + shlex.join(sys.argv[1:] if argv is None else argv)
    print_and_write(args.write or "long_baseline_study", report(results, thresholds, command, cfg),
                    {"command": command, "runs": {lb: a for lb, a in zip(labels, args.runs, strict=True)},
                     "settings": cfg.model_dump(mode="json"), "results": results}, bool(args.write))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
