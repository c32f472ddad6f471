"""Pictures of the reports, like the paper's (matplotlib, Agg, atomic saves).

* :func:`plot_rpe_over_rounds`: RPE-300 per round, mean +- std over seeds (error bars), per
  channel count, with KISS-ICP as a dashed line;
* :func:`plot_round_trajectories`: each round's trajectory of one cell against ground truth
  (and KISS-ICP), top-down;
* :func:`plot_raw_vs_densified`: one scan, raw and densified with a round's model, top-down.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from gr_graph.plots import pyplot as _plt
from gr_graph.plots import save_figure

__all__ = ["needs_log_scale", "plot_rpe_over_rounds", "plot_round_trajectories", "plot_raw_vs_densified"]


def needs_log_scale(values: list[float], max_ratio: float = 30.0) -> bool:
    """True when positive ``values`` span more than ``max_ratio`` (a ruined round next to raw
    and KISS-ICP: on a linear axis the small values, the ones compared, would sit on the floor)."""
    v = np.asarray([x for x in values if x is not None and np.isfinite(x)], float)
    return bool(v.size and v.min() > 0 and v.max() / v.min() > max_ratio)


def plot_rpe_over_rounds(summary: dict[str, Any], path: str | Path,
                         metrics: tuple[str, ...] = ("rpe300_consecutive_mean", "rpe300_all_pairs_mean", "ate_rmse"),
                         ) -> Path | None:
    """Error-bar plot of Table I's ``summary`` (:func:`gr_graph.experiments.aggregate.table1_summary`),
    one panel per metric (RPE-300 consecutive, all pairs, ATE); None when no group has a value."""
    from gr_graph.experiments.aggregate import METRIC_LABELS

    plt = _plt()
    groups = [g for g in summary if any(summary[g]["steps"].get("raw", {}).get(m, {}).get("mean") is not None
                                        for m in metrics)]
    if not groups:
        return None
    fig, axes = plt.subplots(1, len(metrics), figsize=(5.5 * len(metrics), 4.2), squeeze=False)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, m in zip(axes[0], metrics):
        plotted: list[float] = []
        for i, g in enumerate(groups):
            s = summary[g]["steps"]
            xs, ys, es = [], [], []
            for r, step in enumerate(("raw", "1-step", "2-step")):
                d = s.get(step, {}).get(m)
                if d and d["mean"] is not None:
                    xs.append(r), ys.append(d["mean"]), es.append(d["std"] or 0.0)
            plotted += ys
            c = colors[i % len(colors)]
            ax.errorbar(xs, ys, yerr=es, marker="o", capsize=4, color=c,
                        label=f"{g} (seeds {','.join(map(str, summary[g]['seeds']))})")
            k = (summary[g].get("kiss_icp") or {}).get(m)
            if k and k["mean"] is not None:
                ax.axhline(k["mean"], color=c, ls="--", lw=0.8)
                plotted.append(k["mean"])
        ax.plot([], [], "k--", lw=0.8, label="KISS-ICP (same scans)")
        ax.set_xticks([0, 1, 2], ["raw (round 0)", "1-step", "2-step"])
        log = needs_log_scale(plotted)
        if log:
            ax.set_yscale("log")
        ax.set_ylabel(METRIC_LABELS[m] + (" (log scale)" if log else ""))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle("Trajectory error over learning rounds, mean ± std over seeds (unguarded rounds)", fontsize=10)
    return save_figure(fig, path, dpi=110)


def plot_round_trajectories(cell_dir: str | Path, path: str | Path, title: str = "") -> Path | None:
    """Every round's optimised trajectory of a SLAM cell against ground truth (and KISS-ICP);
    None when the cell has no finished round with ground truth."""
    slam = Path(cell_dir) / "slam"
    rounds = sorted((int(p.name.split("_")[1]), p) for p in slam.glob("round_*") if (p / "marginals.npz").is_file())
    if not rounds:
        return None
    plt = _plt()
    fig, axes = plt.subplots(1, len(rounds), figsize=(4.6 * len(rounds), 4.6), squeeze=False)
    kiss = None
    kp = Path(cell_dir) / "kiss_icp.json"
    if kp.is_file():
        kiss = np.asarray(json.loads(kp.read_text())["poses_T_w_velo"])[:, :, 3]
    for ax, (r, rd) in zip(axes[0], rounds):
        with np.load(rd / "marginals.npz") as z:
            p = np.array(z["poses"])[:, :3, 3]
            gt = np.array(z["gt_poses"])[:, :3, 3] if "gt_poses" in z.files else None
        if gt is not None:
            ax.plot(gt[:, 0], gt[:, 1], "k--", lw=1.0, label="ground truth")
        if kiss is not None:
            ax.plot(kiss[:, 0], kiss[:, 1], color="tab:gray", lw=0.8, label="KISS-ICP")
        ax.plot(p[:, 0], p[:, 1], color="tab:blue", lw=1.1, label=f"round {r}")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_title("raw (round 0)" if r == 0 else f"{r}-step (round {r})", fontsize=9)
        ax.grid(alpha=0.3)
        ax.set_xlabel("x [m]")
        ax.legend(fontsize=7)
    axes[0][0].set_ylabel("y [m]")
    if title:
        fig.suptitle(title, fontsize=10)
    return save_figure(fig, path, dpi=110)


def plot_raw_vs_densified(raw_points: np.ndarray, dense_points: np.ndarray, path: str | Path, title: str = "",
                          extent: float = 40.0) -> Path:
    """Top-down scatter of one scan, raw beside densified, within ``extent`` metres."""
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(11, 5.5), sharex=True, sharey=True)
    for ax, pts, name in ((axes[0], raw_points, "raw"), (axes[1], dense_points, "densified")):
        P = np.asarray(pts, np.float64)
        P = P[np.all(np.abs(P[:, :2]) < extent, axis=1)]
        ax.scatter(P[:, 0], P[:, 1], s=0.3, c=P[:, 2], cmap="viridis", vmin=-2.5, vmax=3.0, linewidths=0)
        ax.set_title(f"{name}: {len(pts):,} points", fontsize=9)
        ax.set_aspect("equal")
        ax.set_xlabel("x [m]")
        ax.grid(alpha=0.2)
    axes[0].set_ylabel("y [m]")
    if title:
        fig.suptitle(title, fontsize=10)
    return save_figure(fig, path, dpi=110)
