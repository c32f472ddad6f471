"""Does the odometry's drift between revisits see the small losses of a learning round? (a study)

The GT-free checks tried so far compare a round's *optimised* trajectory with its raw scans: in
11-frame local maps (the acceptance test), at revisits (``revisit_consistency.py``) and over 25 m of
path (``long_baseline_study.py``). None saw the losses of a few per cent that the 32- and 64-channel
rounds made. At revisits the optimised trajectory is held by the very loops that closed them, and
25 m is too short to accumulate such a drift. This study measures the **odometry alone** (each
round's ``odometry_kitti.txt``: the chain of its registrations, before any loop) between the two
visits of a place, hundreds of frames and a few hundred metres of path apart:

* pairs ``(k, l)`` of frames at least ``--min-gap`` frames and ``--min-path`` metres of path apart
  whose positions in the reference round (round 0, optimised) lie within ``--max-distance`` of each
  other, at most ``--pairs`` drawn at random;
* each pair's raw scans registered once, scan to scan (:func:`gr_graph.long_baseline.register_pairs`,
  the long-baseline check's settings), from the reference round's relative pose; the same
  registrations judge every round;
* for each round, the rotation and translation of ``T_reg⁻¹ · O_k⁻¹ O_l`` with ``O`` the round's
  odometry-only poses (:func:`gr_graph.long_baseline.pair_discrepancy`): the odometry's drift over
  the cycle; its median, and its change against the reference round;
* beside it, the same figure with the ground truth's relative poses in place of the registrations
  (what perfect registrations would give), and the ground truth's judgement of the round's final
  trajectory (all-pairs RPE-300 and ATE) and of its odometry.

No ground truth is used by the figure itself. Over cycles of hundreds of metres the odometry drifts
by metres and degrees, so the registrations' own errors (centimetres, hundredths of a degree)
hardly matter; what is asked is whether the odometry's drift follows the final trajectory's.

Run (finished runs with ``round_0/memory``, ``odometry_kitti.txt`` in every round and
``gt_poses_kitti.txt``)::

    python benchmarks/revisit_odometry_study.py RUN [RUN ...] [--labels A B ...] [--write NAME]

``--write NAME`` writes ``benchmarks/results/NAME.md`` and ``.json``.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path
from typing import Any

import numpy as np

from gr_graph.config import AcceptanceConfig
from gr_graph.experiments.revisits import revisit_pairs
from gr_graph.long_baseline import pair_discrepancy, register_pairs
from gr_graph.provenance import machine_line
from gr_graph.round_output import read_round_poses, round_dir
from long_baseline_study import lidar_truth, synthetic_lidar_poses
from results_io import last_change, print_and_write


def cycle_pairs(positions: np.ndarray, min_gap: int, min_path: float, max_distance: float, n_pairs: int,
                seed: int) -> np.ndarray:
    """(M, 2) revisit pairs ``(k, l)``, ``k < l``, sorted by ``k``
    (:func:`gr_graph.experiments.revisits.revisit_pairs`: ``min_gap`` frames and ``min_path`` metres of
    path apart, within ``max_distance``); at most ``n_pairs``, drawn at random with ``seed``."""
    pairs = revisit_pairs(positions, min_gap, max_distance, min_path)
    if len(pairs) > n_pairs:
        pairs = pairs[np.sort(np.random.default_rng(seed).choice(len(pairs), n_pairs, replace=False))]
    return pairs


def _medians(poses: np.ndarray, pairs: np.ndarray, T: np.ndarray) -> tuple[float, float]:
    t, a = pair_discrepancy(poses, pairs, T)
    return float(np.median(t)), float(np.degrees(np.median(a)))


def study_run(run: Path, args: argparse.Namespace) -> dict[str, Any]:
    """The figures of every round of ``run`` against its round 0."""
    from gr_graph.round_acceptance import _raw_scans

    metrics = json.loads((run / "metrics.json").read_text())["rounds"]
    rounds = sorted(int(k) for k, s in metrics.items()
                    if "slam" in s and (round_dir(run, int(k)) / "odometry_kitti.txt").is_file())
    gt = lidar_truth(run)
    if gt is None:
        raise SystemExit(f"{run}: no ground truth of the synthetic world (gt_poses_kitti.txt)")
    ref_poses = read_round_poses(round_dir(run, 0))
    pairs = cycle_pairs(ref_poses[:, :3, 3], args.min_gap, args.min_path, args.max_distance, args.pairs, args.seed)
    if not len(pairs):
        raise SystemExit(f"{run}: no revisits ({args.min_gap}+ frames and {args.min_path}+ m of path apart, "
                         f"within {args.max_distance} m)")
    lb = AcceptanceConfig()
    T, ok = register_pairs(_raw_scans(run), ref_poses, pairs, lb.long_baseline_voxel_size,
                           lb.long_baseline_max_correspondence, lb.long_baseline_min_inliers)
    pairs, T = pairs[ok], T[ok]
    T_gt = np.linalg.inv(gt[pairs[:, 0]]) @ gt[pairs[:, 1]]
    reg_t, reg_a = pair_discrepancy(gt, pairs, T)  # the registrations against the truth
    out: dict[str, Any] = {"run": str(run), "n_pairs": int(len(ok)), "n_registered": int(ok.sum()),
                           "registration_error_median": [float(np.median(reg_t)), float(np.degrees(np.median(reg_a)))],
                           "frames_apart_median": float(np.median(pairs[:, 1] - pairs[:, 0])), "rounds": {}}
    for r in rounds:
        odo = synthetic_lidar_poses(round_dir(run, r) / "odometry_kitti.txt")  # the odometry-only poses
        s = metrics[str(r)]
        fig = {"odometry_reg": _medians(odo, pairs, T), "odometry_gt": _medians(odo, pairs, T_gt),
               "rpe300": s["slam"]["rpe300_all_pairs_mean"], "ate": s["slam"]["ate_rmse"],
               "odometry_rpe300": (s.get("odometry") or {}).get("rpe300_all_pairs_mean"),
               "accepted": s.get("accepted")}
        out["rounds"][str(r)] = fig
        print(f"{run.name} round {r}: odometry drift at revisits (registered) {fig['odometry_reg'][0]:.3f} m "
              f"{fig['odometry_reg'][1]:.3f} deg, (truth) {fig['odometry_gt'][0]:.3f} m "
              f"{fig['odometry_gt'][1]:.3f} deg; "
              f"RPE-300 {fig['rpe300']:.3f} ATE {fig['ate']:.3f}", flush=True)
    return out


def _pct(new: float | None, old: float | None) -> str:
    return "" if new is None or not old else last_change([old, new])


def table(results: list[tuple[str, dict[str, Any]]]) -> str:
    """Markdown: one row per round; a learning round's figures as changes against the run's round 0."""
    rows = ["| run | round | pairs (median frames apart; registrations against the truth) | odometry drift at "
            "revisits, registered: translation / rotation | the same with the truth | odometry all-pairs RPE-300 | "
            "final all-pairs RPE-300 | final ATE | accepted |", "|---|---|---|---|---|---|---|---|---|"]
    for label, res in results:
        f0 = res["rounds"]["0"]
        reg = res["registration_error_median"]
        for r, f in res["rounds"].items():
            if r == "0":
                cells = [f"{res['n_registered']} ({res['frames_apart_median']:.0f}; "
                         f"{100 * reg[0]:.0f} cm, {reg[1]:.2f}°)",
                         f"{f['odometry_reg'][0]:.2f} m / {f['odometry_reg'][1]:.2f}°",
                         f"{f['odometry_gt'][0]:.2f} m / {f['odometry_gt'][1]:.2f}°",
                         "" if f["odometry_rpe300"] is None else f"{f['odometry_rpe300']:.3f} m",
                         f"{f['rpe300']:.3f} m", f"{f['ate']:.3f} m", ""]
            else:
                reg_change = [_pct(f["odometry_reg"][i], f0["odometry_reg"][i]) for i in (0, 1)]
                gt_change = [_pct(f["odometry_gt"][i], f0["odometry_gt"][i]) for i in (0, 1)]
                cells = ["", " / ".join(reg_change), " / ".join(gt_change),
                         _pct(f["odometry_rpe300"], f0["odometry_rpe300"]), _pct(f["rpe300"], f0["rpe300"]),
                         _pct(f["ate"], f0["ate"]), "" if f["accepted"] is None else ("yes" if f["accepted"] else "no")]
            rows.append(" | ".join([f"| {label}", r, *cells]) + " |")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--labels", nargs="+", help="one label a run (default: the folder's name)")
    ap.add_argument("--pairs", type=int, default=150)
    ap.add_argument("--min-gap", type=int, default=100, help="frames between the two scans of a pair")
    ap.add_argument("--min-path", type=float, default=100.0, help="metres of path between them")
    ap.add_argument("--max-distance", type=float, default=10.0, help="metres between them in round 0")
    ap.add_argument("--seed", type=int, default=0, help="draw of the pairs")
    ap.add_argument("--write", metavar="NAME", help="write benchmarks/results/NAME.md and .json")
    args = ap.parse_args(argv)
    labels = args.labels or [r.name for r in args.runs]
    if len(labels) != len(args.runs):
        ap.error("--labels needs one label a run")
    results = [(lab, study_run(run, args)) for lab, run in zip(labels, args.runs)]
    command = "python benchmarks/revisit_odometry_study.py " + shlex.join(sys.argv[1:] if argv is None else argv)
    text = (f"# Does the odometry's drift between revisits see the small losses of a learning round?\n\n"
            f"Command: `{command}`. Machine: {machine_line()}. Round 0 in absolute figures, the learning rounds as "
            "changes against it; the figures are medians over the pairs.\n\n" + table(results))
    print_and_write(args.write or "revisit_odometry_study", text,
                    {"command": command, "settings": vars(args) | {"runs": [str(r) for r in args.runs]},
                     "results": dict(results)}, bool(args.write))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
