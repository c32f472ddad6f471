"""The GT-free acceptance test of learning rounds (:mod:`gr_graph.round_acceptance`) against ground truth.

    # the 2x2 count (accepted/rejected x better/worse by ground truth) over finished runs
    python benchmarks/bench_round_acceptance.py table RUN_DIR [RUN_DIR ...]
    # a trajectory that creeps 3 cm/frame while the vehicle stands still (ground-truth speed
    # below 1 cm/frame), evaluated against the run's round 0
    python benchmarks/bench_round_acceptance.py creep RUN_DIR [--step 0.03]
    # every learning round of finished runs judged again by the current test (the package's
    # defaults, changed with --set KEY=VALUE), beside the verdict stored in the run
    python benchmarks/bench_round_acceptance.py rescore RUN_DIR [RUN_DIR ...] [--set thickness_floor=0]
    # round 1 of RUN_DIR redone with a corrupted copy of its model (weights + noise of
    # --noise x each tensor's standard deviation), into OUT (round 0 copied from RUN_DIR)
    python benchmarks/bench_round_acceptance.py corrupt RUN_DIR OUT [--noise 1.0]

"Worse by ground truth", counted separately for ATE RMSE (SE(3)-aligned) and RPE over 100
frames (RMSE): more than 5 % above the reference round's (the round it was tested against).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path
from typing import Any

import numpy as np

from gr_graph.round_acceptance import _signed


def gt_errors(out: Path, r: int) -> tuple[float, float]:
    """(ATE RMSE, RPE-100 RMSE) [m] of round ``r`` of the run in ``out``."""
    from gr_graph.metrics import ate, rpe_translation
    from gr_graph.trajectory import read_kitti_poses

    gt = read_kitti_poses(out / "gt_poses_kitti.txt")
    est = read_kitti_poses(out / f"round_{r}" / "poses_kitti.txt")
    delta = min(100, len(gt) - 1)
    return float(ate(est, gt).rmse), float(rpe_translation(est, gt, delta=delta).rmse)


def worse(before: float, after: float) -> bool:
    """"Worse by ground truth": more than 5 % above the reference round's figure."""
    return after > 1.05 * before


def count_rows(count: dict[tuple[str, bool, bool], int], metrics: tuple[str, ...]) -> list[str]:
    """The 2x2 count (accepted/rejected x not worse/worse) of each metric, as markdown rows."""
    rows = ["| | " + " | ".join(f"{m} {w}" for m in metrics for w in ("not worse", "worse")) + " |",
            "|---|" + "---|" * (2 * len(metrics))]
    for acc in (True, False):
        rows.append(f"| {'accepted' if acc else 'rejected'} | " + " | ".join(
            str(count[(m, acc, w)]) for m in metrics for w in (False, True)) + " |")
    return rows


def table(runs: list[Path]) -> int:
    rows = ["| run | round | ref | accepted | mean ΔH [nats] | q0.9 window ΔH | ΔMPV [mm²] | failures | loop rej. | "
            "rel. pose d² median / >χ² | ATE ref→round [m] | RPE100 ref→round [m] | by GT | reasons |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    count = {(m, a, w): 0 for m in ("ATE", "RPE100") for a in (True, False) for w in (True, False)}
    for out in runs:
        m = json.loads((out / "metrics.json").read_text())
        for k, s in sorted(m["rounds"].items(), key=lambda kv: int(kv[0])):
            if "acceptance" not in s:
                continue
            a = s["acceptance"]
            ref = a["reference_round"]
            (ate0, rpe0), (ate1, rpe1) = gt_errors(out, ref), gt_errors(out, int(k))
            worse_ate, worse_rpe = worse(ate0, ate1), worse(rpe0, rpe1)
            count[("ATE", s["accepted"], worse_ate)] += 1
            count[("RPE100", s["accepted"], worse_rpe)] += 1
            rp = a.get("relative_pose_agreement", {})
            mpv = a.get("mean_plane_variance_change")
            rows.append(f"| {out.name} | {k} | {ref} | {s['accepted']} | {_signed(a['mean_entropy_increase'])} | "
                        f"{_signed(a['window_entropy_increase'])} | {'-' if mpv is None else f'{1e6 * mpv:+.1f}'} | "
                        f"{a['registration_failure_rate']:.3f} | "
                        f"{a['reference_loop_rejection_rate']:.2f}→{a['loop_rejection_rate']:.2f} | "
                        f"{rp.get('median_mahalanobis2', float('nan')):.3g} / "
                        f"{rp.get('fraction_beyond_chi2_999', float('nan')):.2f} | "
                        f"{ate0:.3f} → {ate1:.3f} | {rpe0:.3f} → {rpe1:.3f} | ATE {'worse' if worse_ate else 'ok'}, RPE {'worse' if worse_rpe else 'ok'} | "
                        f"{'; '.join(a['reasons'])} |")
    rows += ["", *count_rows(count, ("ATE", "RPE100"))]
    print("\n".join(rows))
    return 0


def acceptance_settings(out: Path | None, settings: list[str]) -> Any:
    """The acceptance settings: the run's own (``out``'s config.yaml) or, with ``out`` None, the
    package's defaults; each ``KEY=VALUE`` of ``settings`` overrides one (validated)."""
    import yaml

    from gr_graph.config import AcceptanceConfig, load_config

    base = load_config(out / "config.yaml").training.acceptance if out is not None else AcceptanceConfig()
    update = {}
    for kv in settings:
        key, sep, value = kv.partition("=")
        if not sep or key not in AcceptanceConfig.model_fields:
            raise SystemExit(f"--set {kv!r}: expected KEY=VALUE with KEY one of {sorted(AcceptanceConfig.model_fields)}")
        update[key] = yaml.safe_load(value)
    try:
        return AcceptanceConfig.model_validate({**base.model_dump(), **update})
    except ValueError as exc:  # pydantic's ValidationError
        raise SystemExit(f"--set {' '.join(settings)}: {exc}") from None


def rescore(runs: list[Path], settings: list[str]) -> int:
    """Every learning round of ``runs`` judged by the current test (module docstring)."""
    from gr_graph.round_acceptance import _raw_scans, evaluate_round

    cfg = acceptance_settings(None, settings)
    print(f"Settings: `{json.dumps(cfg.model_dump(mode='json'))}`\n")
    rows = ["| run | round | ref | stored verdict | verdict now | mean ΔH [nats] | q0.9 window ΔH | worst standstill "
            "creep [mm/frame] | ATE ref→round [m] | RPE100 ref→round [m] | all-pairs RPE-300 ref→round [m] | reasons now |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    count = {(m, a, w): 0 for m in ("ATE", "RPE100", "RPE-300") for a in (True, False) for w in (True, False)}
    for out in runs:
        missing = [f for f in ("metrics.json", "gt_poses_kitti.txt", "round_0/memory") if not (out / f).exists()]
        if missing:
            print(f"{out}: skipped, no {', '.join(missing)} (a pruned or unfinished run?)", file=sys.stderr)
            continue
        m = json.loads((out / "metrics.json").read_text())
        scans = None
        for k, s in sorted(m["rounds"].items(), key=lambda kv: int(kv[0])):
            if "acceptance" not in s:
                continue
            ref = s["acceptance"]["reference_round"]
            need = [f"round_{r}/{f}" for r in (int(k), ref) for f in ("poses_kitti.txt", "round.json", "marginals.npz")]
            if any(not (out / f).is_file() for f in need):
                print(f"{out}: round {k} skipped, needs {', '.join(f for f in need if not (out / f).is_file())}",
                      file=sys.stderr)
                continue
            scans = _raw_scans(out) if scans is None else scans
            v = evaluate_round(out, int(k), ref, m["rounds"], cfg, scans=scans)
            (ate0, rpe0), (ate1, rpe1) = gt_errors(out, ref), gt_errors(out, int(k))
            # the run's own all-pairs RPE-300 (metrics.json; None on runs of 300 frames or fewer)
            r300 = tuple(m["rounds"][str(r)]["slam"].get("rpe300_all_pairs_mean") for r in (ref, int(k)))
            by_gt = {"ATE": worse(ate0, ate1), "RPE100": worse(rpe0, rpe1)}
            if r300[0] is not None:
                by_gt["RPE-300"] = worse(*r300)
            for metric, w in by_gt.items():
                count[(metric, v["accepted"], w)] += 1
            st = v.get("standstill") or {}
            creep_mm = "-" if not st.get("stretches") else f"{1e3 * st['worst_creep_per_frame_m']:+.2f}"
            rpe300 = "-" if r300[0] is None else f"{r300[0]:.3f} → {r300[1]:.3f}"
            rows.append(f"| {out} | {k} | {ref} | {'accepted' if s['accepted'] else 'rejected'} | "
                        f"{'accepted' if v['accepted'] else 'rejected'} | {_signed(v['mean_entropy_increase'])} | "
                        f"{_signed(v['window_entropy_increase'])} | {creep_mm} | {ate0:.3f} → {ate1:.3f} | "
                        f"{rpe0:.3f} → {rpe1:.3f} | {rpe300} | {'; '.join(v['reasons'])} |")
    rows += ["", "Verdict now against ground truth (worse: more than 5 % above the reference round):", "",
             *count_rows(count, ("ATE", "RPE100", "RPE-300"))]
    print("\n".join(rows))
    return 0


def creep(out: Path, step: float, r: int = 0, settings: list[str] | None = None) -> int:
    """Round ``r``'s trajectory with a creep of ``step`` m/frame (along the vehicle's x axis) added
    while the ground truth stands still, judged against round ``r`` itself (the run's own
    acceptance settings, ``settings`` overriding them)."""
    from gr_graph.round_acceptance import decide, round_figures
    from gr_graph.round_output import read_round_poses, round_dir
    from gr_graph.trajectory import read_kitti_poses

    cfg = acceptance_settings(out, settings or [])
    gt = read_kitti_poses(out / "gt_poses_kitti.txt")
    still = np.r_[False, np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1) < 0.01]
    if not still.any():
        print(f"{out}: the ground truth never stands still", file=sys.stderr)
        return 1
    from gr_graph.round_acceptance import _raw_scans

    scans = _raw_scans(out)
    rd = round_dir(out, r)
    poses = read_round_poses(rd)
    summary = json.loads((rd / "round.json").read_text())
    crept = poses.copy()
    offset = np.cumsum(still) * step  # grows by `step` every frame the vehicle stands still
    crept[:, :3, 3] += offset[:, None] * poses[:, :3, 0]
    ref = round_figures(scans, poses, rd, summary, cfg)
    fig = round_figures(scans, crept, rd, summary, cfg)
    v = decide(fig, ref, cfg)
    print(json.dumps({"run": str(out), "still_frames": int(still.sum()), "step_m": step,
                      "accepted": v["accepted"], "reasons": v["reasons"],
                      "mean_entropy_increase": v["mean_entropy_increase"],
                      "window_entropy_increase": v["window_entropy_increase"],
                      "standstill": v["standstill"], "settings": cfg.model_dump(mode="json")}, indent=1))
    return 0


def corrupt(run: Path, out: Path, noise: float, seed: int = 0) -> int:
    """Round 1 of ``run`` redone into ``out`` with its model's weights perturbed."""
    import torch

    from gr_graph.config import load_config
    from gr_graph.densify import densified_sequence
    from gr_graph.pipeline import SlamPipeline

    model = run / "round_1" / "training" / "model.pt"
    if out.resolve() == run.resolve():
        raise SystemExit(f"{out}: OUT must not be RUN (its round 1 is redone with the corrupted model)")
    out.mkdir(parents=True, exist_ok=True)
    if not (out / "round_0").exists():
        shutil.copytree(run / "round_0", out / "round_0")
    state = torch.load(model, map_location="cpu", weights_only=False)
    gen = torch.Generator().manual_seed(seed)
    for name, t in state["model_state"].items():
        if t.is_floating_point() and t.numel() > 1:
            t.add_(torch.randn(t.shape, generator=gen, dtype=t.dtype) * noise * float(t.std()))
    bad = out / "corrupted_model.pt"
    torch.save(state, bad)
    cfg = load_config(run / "config.yaml", {"output": {"out_dir": str(out), "progress": False},
                                            "training": {"rounds": 1}})

    class CorruptedModelPipeline(SlamPipeline):
        def densified_scans(self, r, resume_training):  # noqa: ANN001, ANN201 - the parent's signature
            tc = self.cfg.training
            return densified_sequence(self.sequence, bad, tc, device=self.cfg.device, preprocess=self.cfg.preprocess,
                                      keep_predictions=max(16, self.cfg.data.prefetch + 8))

    # the corrupted model is not in the round's fingerprint: a round 1 left in OUT by another --noise or
    # --seed would be resumed and its verdict printed for this one
    shutil.rmtree(out / "round_1", ignore_errors=True)
    m = CorruptedModelPipeline(cfg).run()
    print(json.dumps({"run": str(run), "noise": noise, "seed": seed, "final_round": m["final_round"],
                      "round_1_accepted": m["rounds"]["1"]["accepted"],
                      "reasons": m["rounds"]["1"]["acceptance"]["reasons"]}))
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("table")
    t.add_argument("runs", nargs="+", type=Path)
    c = sub.add_parser("creep")
    c.add_argument("run", type=Path)
    c.add_argument("--step", type=float, default=0.03)
    c.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override an acceptance setting")
    q = sub.add_parser("rescore")
    q.add_argument("runs", nargs="+", type=Path)
    q.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override an acceptance setting")
    k = sub.add_parser("corrupt")
    k.add_argument("run", type=Path)
    k.add_argument("out", type=Path)
    k.add_argument("--noise", type=float, default=1.0)
    args = p.parse_args(argv)
    if args.cmd == "table":
        return table(args.runs)
    if args.cmd == "creep":
        return creep(args.run, args.step, settings=args.set)
    if args.cmd == "rescore":
        return rescore(args.runs, args.set)
    return corrupt(args.run, args.out, args.noise)


if __name__ == "__main__":
    sys.exit(main())
