"""Does a ground-truth-free figure see the slow drift a learning round adds? (a study, not a test)

The acceptance test (:mod:`gr_graph.round_acceptance`) rates a round by the sharpness of local maps
of the raw scans (11 consecutive frames). A round can pass it and still drift more over kilometres:
seed 2 of the full-route learning round on raw scans (ATE 0.177 -> 0.240 m) had a slightly *sharper*
local map. This study asks whether two other GT-free figures would have seen it, and then measures,
with ground truth, where the drift lies:

* **Revisit consistency**: for pairs of frames (i, j) at least ``--min-gap`` frames apart whose
  positions in the reference round (round 0) lie within ``--max-distance``, the raw scan i is
  registered (small_gicp GICP) against the raw scans j-2..j+2, placed by the round's poses, starting
  from the round's relative pose; the correction GICP applies (translation, rotation) is how far
  the round's trajectory disagrees with the scans where the vehicle came back. Loop edges tie some
  of those pairs; the others (most of them) are free to show drift. Paired over the same pairs for
  every round: median and mean correction, and the Wilcoxon signed-rank p of round r against 0.
* **Significance of the local sharpness change**: the per-window entropy differences the
  acceptance test recorded (``metrics.json``), their mean, the one-sample t statistic and its
  two-sided p, and the Wilcoxon p: would "accept only a significant sharpening" have helped?
* **With ground truth**: the ATE (SE(3)-aligned, evo, the run's own figure) and the share of
  500-frame blocks whose mean aligned position error rose (a drift spread over the route raises
  most blocks; a local failure, a few).

Run (finished runs with ``--rounds 1`` or more and ``gt_poses_kitti.txt``)::

    python benchmarks/revisit_consistency.py RUN [RUN ...] [--labels A B ...] [--write]

``--write`` writes ``benchmarks/results/revisit_consistency.md`` and ``.json``.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

import numpy as np
import small_gicp
from scipy import stats
from scipy.spatial import cKDTree

from gr_graph.atomic import atomic_write_json, atomic_write_text
from gr_graph.memory import load_memory
from gr_graph.provenance import machine_line
from gr_graph.round_output import read_round_poses
from gr_graph.trajectory import read_kitti_poses, to_evo_path

RESULTS = Path(__file__).resolve().parent / "results"


def revisit_pairs(positions: np.ndarray, min_gap: int, max_distance: float, n_pairs: int, seed: int) -> np.ndarray:
    """(M, 2) frame pairs (i > j) at least ``min_gap`` frames apart within ``max_distance`` metres,
    at most ``n_pairs`` of them drawn at random (sorted)."""
    found = np.array(sorted((max(a, b), min(a, b)) for a, b in cKDTree(positions).query_pairs(max_distance)
                            if abs(a - b) >= min_gap), np.int64).reshape(-1, 2)
    if len(found) <= n_pairs:
        return found
    return found[np.sort(np.random.default_rng(seed).choice(len(found), n_pairs, replace=False))]


def _submap(scans: list[np.ndarray], poses: np.ndarray, centre: int, half: int) -> np.ndarray:
    to_centre = np.linalg.inv(poses[centre])
    parts = []
    for k in range(max(0, centre - half), min(len(scans), centre + half + 1)):
        T = to_centre @ poses[k]
        parts.append(scans[k] @ T[:3, :3].T + T[:3, 3])
    return np.concatenate(parts)


def revisit_corrections(scans: list[np.ndarray], poses: np.ndarray, pairs: np.ndarray, half: int = 2) -> np.ndarray:
    """(M, 2) translation [m] and rotation [deg] of the correction GICP applies to each pair's
    relative pose under ``poses``."""
    out = np.zeros((len(pairs), 2))
    for n, (i, j) in enumerate(pairs):
        start = np.linalg.inv(poses[j]) @ poses[i]
        res = small_gicp.align(_submap(scans, poses, j, half), scans[i], start, registration_type="GICP",
                               downsampling_resolution=0.25, max_correspondence_distance=1.0, num_threads=2,
                               max_iterations=30)
        D = np.linalg.inv(start) @ res.T_target_source
        out[n] = np.linalg.norm(D[:3, 3]), np.degrees(np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1)))
    return out


def aligned_errors(est: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Per-frame position error [m] after evo's SE(3) Umeyama alignment of ``est`` to ``gt``."""
    est_path, gt_path = to_evo_path(est), to_evo_path(gt)
    est_path.align(gt_path)
    return np.linalg.norm(est_path.positions_xyz - gt_path.positions_xyz, axis=1)


def entropy_significance(acceptance: dict) -> dict:
    """Mean, t statistic and p values of the per-window entropy change a verdict recorded."""
    new = np.array([np.nan if v is None else v for v in acceptance["window_entropy"]], np.float64)
    ref = np.array([np.nan if v is None else v for v in acceptance["reference_window_entropy"]], np.float64)
    d = (new - ref)[np.isfinite(new - ref)]
    t = stats.ttest_1samp(d, 0.0)
    nonzero = d[d != 0]
    return {"n_windows": int(d.size), "mean": float(d.mean()), "t": float(t.statistic), "p_t": float(t.pvalue),
            "p_wilcoxon": float(stats.wilcoxon(nonzero).pvalue) if nonzero.size else 1.0,
            "share_sharper": float(np.mean(d < 0))}


def study_run(run: Path, rounds: list[int], args: argparse.Namespace) -> dict:
    """The figures of one run's rounds (round ``rounds[0]`` is the reference)."""
    mem = load_memory(run / "round_0" / "memory")
    scans = [np.array(mem.scan(k), np.float64) for k in range(mem.n_scans)]
    metrics = json.loads((run / "metrics.json").read_text())
    gt = read_kitti_poses(run / "gt_poses_kitti.txt")
    ref_poses = read_round_poses(run / f"round_{rounds[0]}")
    pairs = revisit_pairs(ref_poses[:, :3, 3], args.min_gap, args.max_distance, args.pairs, args.seed)
    if not len(pairs):
        raise SystemExit(f"{run}: no frames {args.min_gap} or more apart lie within {args.max_distance} m of each "
                         "other in round 0 (lower --min-gap or raise --max-distance)")
    out: dict = {"run": str(run), "n_pairs": int(len(pairs)), "rounds": {}}
    ref_corr = ref_err = None
    for r in rounds:
        rd = run / f"round_{r}"
        corr = revisit_corrections(scans, read_round_poses(rd), pairs)
        err = aligned_errors(read_kitti_poses(rd / "poses_kitti.txt"), gt)
        summary = metrics["rounds"][str(r)]
        fig = {"revisit_median_mm": 1e3 * float(np.median(corr[:, 0])), "revisit_mean_mm": 1e3 * float(corr[:, 0].mean()),
               "revisit_median_rot_deg": float(np.median(corr[:, 1])), "ate_rmse": summary["slam"]["ate_rmse"],
               "rpe300_all_pairs_mean": summary["slam"]["rpe300_all_pairs_mean"]}
        if ref_corr is not None:
            diff = corr[:, 0] - ref_corr[:, 0]
            fig["revisit_share_closer"] = float(np.mean(diff < 0))
            fig["revisit_p_wilcoxon"] = float(stats.wilcoxon(diff).pvalue) if np.any(diff != 0) else 1.0
            blocks = [(err[k:k + 500].mean() > ref_err[k:k + 500].mean()) for k in range(0, len(err), 500)]
            fig["share_blocks_worse"] = float(np.mean(blocks))
            fig["accepted"] = summary.get("accepted")
            if summary.get("acceptance"):
                fig["entropy_change"] = entropy_significance(summary["acceptance"])
        else:
            ref_corr, ref_err = corr, err
        out["rounds"][str(r)] = fig
        print(f"{run.name} round {r}: " + ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}"
                                                    for k, v in fig.items() if not isinstance(v, dict)), flush=True)
    return out


def table(results: list[tuple[str, dict]]) -> str:
    head = ("| run | round | revisit correction, median / mean [mm] | closer than round 0 (Wilcoxon p) | "
            "local entropy change, mean [nats] (t, p; Wilcoxon p) | accepted | ATE RMSE [m] | RPE-300 all pairs [m] | "
            "500-frame blocks worse |\n|---|---|---|---|---|---|---|---|---|")
    rows = [head]
    for label, res in results:
        for r, f in res["rounds"].items():
            ent = f.get("entropy_change")
            rows.append(" | ".join([
                f"| {label}", r, f"{f['revisit_median_mm']:.1f} / {f['revisit_mean_mm']:.1f}",
                f"{100 * f['revisit_share_closer']:.0f} % ({f['revisit_p_wilcoxon']:.2g})" if "revisit_share_closer" in f else "",
                f"{ent['mean']:+.4f} ({ent['t']:.2f}, {ent['p_t']:.2g}; {ent['p_wilcoxon']:.2g})" if ent else "",
                "" if f.get("accepted") is None else ("yes" if f["accepted"] else "no"),
                f"{f['ate_rmse']:.3f}", f"{f['rpe300_all_pairs_mean']:.3f}",
                f"{100 * f['share_blocks_worse']:.0f} %" if "share_blocks_worse" in f else ""]) + " |")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--labels", nargs="+", help="one label a run (default: the folder's name)")
    ap.add_argument("--rounds", nargs="+", type=int, default=[0, 1], help="the first is the reference")
    ap.add_argument("--pairs", type=int, default=150)
    ap.add_argument("--min-gap", type=int, default=100, help="frames between the two scans of a pair")
    ap.add_argument("--max-distance", type=float, default=10.0, help="metres between them in round 0")
    ap.add_argument("--seed", type=int, default=0, help="draw of the pairs")
    ap.add_argument("--note", default="", help="a paragraph written under the table")
    ap.add_argument("--write", action="store_true")
    args = ap.parse_args(argv)
    labels = args.labels or [r.name for r in args.runs]
    if len(labels) != len(args.runs):
        ap.error("--labels needs one label a run")
    results = [(lab, study_run(run, args.rounds, args)) for lab, run in zip(labels, args.runs)]
    md = table(results)
    print(md)
    if args.write:
        given = list(sys.argv[1:] if argv is None else argv)
        if "--note" in given:  # the note is written under the table, not into the command
            at = given.index("--note")
            del given[at:at + 2]
        cmd = "python benchmarks/revisit_consistency.py " + shlex.join(given) + (" --note NOTE" if args.note else "")
        text = (f"# Does a GT-free figure see the slow drift of a learning round?\n\nCommand: `{cmd}`. "
                f"Machine: {machine_line()}.\n\n{md}\n\n{args.note}\n")
        atomic_write_text(RESULTS / "revisit_consistency.md", text)
        atomic_write_json(RESULTS / "revisit_consistency.json", {"command": cmd, "results": dict(results)})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
