"""Figures of a SLAM run (matplotlib, Agg backend; imported lazily by gr_graph.round_output)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from gr_graph.atomic import atomic_savefig


def plot_trajectory(
    path: str | os.PathLike[str],
    poses: np.ndarray,
    gt: np.ndarray | None = None,
    loops: np.ndarray | None = None,
    odometry: np.ndarray | None = None,
    title: str = "",
) -> Path:
    """Top-down (x-y, LiDAR/world frame of the first scan) trajectory against ground truth.

    Parameters
    ----------
    path : output PNG (written atomically)
    poses : (K, 4, 4) estimated T_w_velo
    gt : (K, 4, 4) ground truth in the same world frame, optional
    loops : (L, 2) run positions (i, j) of accepted loops, drawn as segments, optional
    odometry : (K, 4, 4) odometry-only poses, optional
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 7))
    p = poses[:, :3, 3]
    if gt is not None:
        g = gt[:, :3, 3]
        ax.plot(g[:, 0], g[:, 1], "k--", lw=1.2, label="ground truth")
    if odometry is not None:
        o = odometry[:, :3, 3]
        ax.plot(o[:, 0], o[:, 1], color="tab:orange", lw=0.8, label="odometry")
    ax.plot(p[:, 0], p[:, 1], color="tab:blue", lw=1.2, label="gr_graph")
    ax.plot(p[0, 0], p[0, 1], "go", ms=6, label="start")
    if loops is not None and len(loops):
        for i, j in np.asarray(loops):
            ax.plot([p[i, 0], p[j, 0]], [p[i, 1], p[j, 1]], color="tab:red", lw=0.6, alpha=0.6)
        ax.plot([], [], color="tab:red", lw=0.6, label=f"loop closures ({len(loops)})")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    if title:
        ax.set_title(title, fontsize=10)
    try:
        return atomic_savefig(fig, path, dpi=120, bbox_inches="tight")
    finally:
        plt.close(fig)
