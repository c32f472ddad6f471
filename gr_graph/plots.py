"""Figures of a SLAM run (matplotlib, Agg backend; imported lazily by gr_graph.round_output).

* :func:`plot_trajectory`: top-down trajectory against ground truth, with the marginal
  position covariances as 3-sigma ellipses. A 0.05 m ellipse is invisible on a 600 m plot, so
  the ellipses are drawn magnified by a round factor (:func:`ellipse_scale`: the median
  ellipse's major axis becomes about 1.5 % of the plot's extent) and the legend says by how
  much ("x 1" when they are visible at true size).
* :func:`plot_rounds`: per learning round, RPE and ATE of the optimised and the odometry-only
  trajectories against ground truth (``metrics.json``).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from gr_graph.atomic import atomic_savefig

__all__ = ["plot_trajectory", "plot_rounds", "pyplot", "save_figure", "ellipse_axes", "ellipse_layout", "ellipse_scale",
           "ELLIPSE_SIGMA", "ELLIPSE_TARGET_FRACTION", "MAX_ELLIPSES"]

ELLIPSE_SIGMA = 3.0
#: Drawn major axis of the median ellipse as a fraction of the plot's extent.
ELLIPSE_TARGET_FRACTION = 0.015
#: At most this many ellipses (every n-th pose).
MAX_ELLIPSES = 60


def pyplot() -> Any:
    """matplotlib.pyplot, on the Agg backend unless one is chosen (imported on first use).

    A backend is taken as chosen when ``MPLBACKEND`` is set or pyplot is imported already (a notebook's
    inline backend, an interactive session): switching it would break that session's figures."""
    import sys

    if "matplotlib.pyplot" not in sys.modules and not os.environ.get("MPLBACKEND"):
        import matplotlib

        matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig: Any, path: str | os.PathLike[str], dpi: int = 120) -> Path:
    """Save ``fig`` atomically to ``path`` (tight bounding box) and close it, also on failure."""
    try:
        return atomic_savefig(fig, path, dpi=dpi, bbox_inches="tight")
    finally:
        pyplot().close(fig)


def ellipse_axes(cov_xy: np.ndarray, n_sigma: float = ELLIPSE_SIGMA) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Full width, full height and angle [deg] of the ``n_sigma`` ellipses of ``(K, 2, 2)`` covariances
    (width along the major axis)."""
    S = 0.5 * (np.asarray(cov_xy, np.float64) + np.swapaxes(cov_xy, -1, -2))
    w, V = np.linalg.eigh(S)
    w = np.maximum(w, 0.0)
    angle = np.degrees(np.arctan2(V[:, 1, 1], V[:, 0, 1]))
    return 2 * n_sigma * np.sqrt(w[:, 1]), 2 * n_sigma * np.sqrt(w[:, 0]), angle


def ellipse_scale(major_axes: np.ndarray, extent: float, target_fraction: float = ELLIPSE_TARGET_FRACTION) -> float:
    """Magnification (1, 2 or 5 x 10^k, at least 1) that makes the median ellipse's major axis
    about ``target_fraction`` of ``extent``."""
    positive = np.asarray(major_axes, np.float64)
    positive = positive[np.isfinite(positive) & (positive > 0)]
    if not len(positive) or not np.isfinite(extent) or extent <= 0:
        return 1.0
    want = target_fraction * extent / float(np.median(positive))
    if want <= 1.0:
        return 1.0
    exponent = np.floor(np.log10(want))
    mantissa = want / 10**exponent
    nice = max(m for m in (1.0, 2.0, 5.0) if m <= mantissa)
    return float(nice * 10**exponent)


def ellipse_layout(positions: np.ndarray, position_cov: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """The x-y position ellipses as ``trajectory.png`` draws them (the notebook too).

    Parameters
    ----------
    positions : (K, 2+) array
        Positions [m] (x, y first); non-finite ones get no ellipse.
    position_cov : (K, 3, 3) or (K, 2, 2) array
        World-frame position covariances; non-finite ones (failed marginals) get no ellipse.

    Returns
    -------
    width, height, angle : (K,) arrays
        :func:`ellipse_axes` (NaN where there is no covariance).
    drawn : (K,) bool array
        Poses with a finite position and ellipse.
    scale : float
        :func:`ellipse_scale` of the drawn ellipses on the extent of the finite positions (at least 1 m).
    """
    p = np.asarray(positions, np.float64)[:, :2]
    cov_xy = np.asarray(position_cov, np.float64)[:, :2, :2]
    placed = np.isfinite(p).all(axis=1)
    has_cov = np.isfinite(cov_xy).all(axis=(1, 2))
    width, height, angle = (np.full(len(p), np.nan) for _ in range(3))
    if has_cov.any():
        width[has_cov], height[has_cov], angle[has_cov] = ellipse_axes(cov_xy[has_cov])
    drawn = placed & np.isfinite(width) & np.isfinite(height) & np.isfinite(angle)
    extent = float(np.ptp(p[placed], axis=0).max()) if placed.sum() > 1 else 0.0
    return width, height, angle, drawn, ellipse_scale(width[drawn], max(extent, 1.0))


def plot_trajectory(
    path: str | os.PathLike[str],
    poses: np.ndarray,
    gt: np.ndarray | None = None,
    loops: np.ndarray | None = None,
    odometry: np.ndarray | None = None,
    title: str = "",
    position_cov: np.ndarray | None = None,
) -> Path:
    """Top-down (x-y, LiDAR/world frame of the first scan) trajectory against ground truth.

    Parameters
    ----------
    path : output PNG (written atomically)
    poses : (K, 4, 4) estimated T_w_velo
    gt : (K, 4, 4) ground truth in the same world frame, optional
    loops : (L, 2) run positions (i, j) of accepted loops, drawn as segments, optional
    odometry : (K, 4, 4) odometry-only poses, optional
    position_cov : (K, 3, 3) world-frame position covariances (``marginals.npz``
        ``position_cov_world``), drawn as 3-sigma x-y ellipses magnified by
        :func:`ellipse_scale` (said in the legend), optional
    """
    poses = np.asarray(poses)
    if poses.ndim != 3 or len(poses) == 0:
        raise ValueError(f"{path}: no poses to plot (got an array of shape {poses.shape})")
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 7))
    try:
        _draw_trajectory(ax, poses[:, :3, 3], gt, loops, odometry, position_cov)
    except BaseException:
        plt.close(fig)
        raise
    if title:
        ax.set_title(title, fontsize=10)
    return save_figure(fig, path, dpi=120)


def _draw_trajectory(ax: Any, p: np.ndarray, gt: np.ndarray | None, loops: np.ndarray | None,
                     odometry: np.ndarray | None, position_cov: np.ndarray | None) -> None:
    """:func:`plot_trajectory`'s drawing on ``ax``; ``p``: (K, 3) estimated positions."""
    from matplotlib.patches import Ellipse

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
    if position_cov is not None and len(position_cov):
        width, height, angle, drawn, scale = ellipse_layout(p, position_cov)
        if drawn.any():
            step = max(1, int(np.ceil(len(p) / MAX_ELLIPSES)))
            for k in range(0, len(p), step):
                if drawn[k]:
                    ax.add_patch(Ellipse(tuple(p[k, :2]), scale * width[k], scale * height[k], angle=angle[k],
                                         fill=False, color="tab:purple", lw=0.8))
            size = "true size" if scale == 1.0 else f"magnified x{scale:g}"
            missing = "" if drawn.all() else f"; {int((~drawn).sum())} poses without a finite pose or covariance"
            ax.plot([], [], color="tab:purple", lw=0.8,
                    label=f"{ELLIPSE_SIGMA:g}σ position ellipses, {size} (median major axis "
                          f"{np.median(width[drawn]):.3g} m; one every {step} poses{missing})")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)


def _round_values(metrics: dict[str, Any], part: str, key: str) -> tuple[list[int], list[float]]:
    rounds, values = [], []
    for r in sorted(metrics["rounds"], key=int):
        v = (metrics["rounds"][r].get(part) or {}).get(key)
        if v is not None:
            rounds.append(int(r))
            values.append(float(v))
    return rounds, values


def plot_rounds(path: str | os.PathLike[str], metrics: dict[str, Any], title: str = "") -> Path:
    """RPE (over 300 frames, consecutive pairs, mean) and ATE RMSE per round, optimised and
    odometry-only, from a run's ``metrics.json`` dict; a panel without values (no ground
    truth, or a run shorter than the RPE distance) says so."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    panels = (("rpe300_consecutive_mean", "RPE over 300 frames [m]"), ("ate_rmse", "ATE RMSE [m]"))
    all_rounds = sorted(int(r) for r in metrics["rounds"])
    for ax, (key, label) in zip(axes, panels):
        drawn = False
        for part, style, name in (("slam", "o-", "gr_graph (optimised)"), ("odometry", "s--", "odometry only")):
            rounds, values = _round_values(metrics, part, key)
            if values:
                ax.plot(rounds, values, style, label=name)
                drawn = True
        if drawn:
            ax.legend(fontsize=8)
        else:
            ax.text(0.5, 0.5, "not available\n(no ground truth, or the run is too short)", ha="center",
                    va="center", transform=ax.transAxes)
        ax.set_xticks(all_rounds)
        ax.set_xlabel("round (0: raw scans)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path, dpi=120)
