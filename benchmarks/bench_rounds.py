"""Reciprocal rounds (Algorithm 3) on an excerpt of the synthetic sequence: RPE/ATE and wall time per round.

    python benchmarks/bench_rounds.py --frames 0:300 --channels 16 --rounds 2 --net small \
        --out runs/bench_rounds_small [--results benchmarks/results/rounds.md]

Runs ``python -m gr_graph.slam`` (resuming whatever is finished in ``--out``), then appends a
markdown table to ``--results``: per round ATE (SE(3)-aligned RMSE), RPE over 100 frames (RMSE,
computed here from the written poses, since the 300-frame RPE needs > 300 frames), KITTI devkit
translation error, trajectory change, kept fraction of the anisotropy filter, and wall time of
training / SLAM (``read`` = rendering + densification).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import yaml

NETS = {
    "small": {"trainer": {"lr": 3e-3, "max_corr": 300, "num_threads": 1,
                          "net": {"n_points": 512, "k0": 8, "k1": 8, "k2": 8, "c0": 16, "c1": 32, "c2": 32, "kw": 8}}},
    "default": {"trainer": {"num_threads": 1}},
}


def summarize(out: Path) -> list[str]:
    from gr_graph.metrics import rpe_translation
    from gr_graph.trajectory import read_kitti_poses

    m = json.loads((out / "metrics.json").read_text())
    gt = read_kitti_poses(out / "gt_poses_kitti.txt")
    rows = ["| round | ATE RMSE [m] | RPE100 RMSE [m] | KITTI t_err [%] | change [m] | kept | training [s] | SLAM [s] (read) |",
            "|---|---|---|---|---|---|---|---|"]
    for r, s in sorted(m["rounds"].items(), key=lambda kv: int(kv[0])):
        rpe = rpe_translation(read_kitti_poses(out / f"round_{r}" / "poses_kitti.txt"), gt, delta=100).rmse
        rt = s["runtime_s"]
        kept = s.get("densify", {}).get("kept_fraction")
        t_err = s["slam"]["kitti_t_err_percent"]
        rows.append(
            f"| {r} | {s['slam']['ate_rmse']:.4f} | {rpe:.4f} | {t_err if t_err is None else round(t_err, 3)} | "
            f"{s.get('trajectory_change', float('nan')):.3f} | {'-' if kept is None else f'{kept:.2f}'} | "
            f"{rt.get('training', 0.0):.0f} | {rt['total']:.0f} ({rt['read']:.0f}) |"
        )
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", default="0:300")
    ap.add_argument("--channels", type=int, default=16)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--net", choices=sorted(NETS), default="small")
    ap.add_argument("--epochs", type=int, default=3)
    ap.add_argument("--out", required=True)
    ap.add_argument("--results", default=None, help="markdown file to append the table to")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cfg_path = out / "bench_config.yaml"
    cfg_path.write_text(yaml.safe_dump({"training": {"epochs": args.epochs, **NETS[args.net]}}))
    from gr_graph.slam import main as slam_main

    rc = slam_main(["--seq", "00", "--frames", args.frames, "--channels", str(args.channels), "--rounds",
                    str(args.rounds), "--out", str(out), "--config", str(cfg_path), "--quiet"])
    if rc:
        return rc
    rows = summarize(out)
    text = "\n".join([f"`python benchmarks/bench_rounds.py --frames {args.frames} --channels {args.channels} "
                      f"--rounds {args.rounds} --net {args.net} --epochs {args.epochs} --out {out}`", "", *rows, ""])
    print(text)
    if args.results:
        with open(args.results, "a") as fh:
            fh.write("\n" + text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
