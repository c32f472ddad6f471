"""Frame stamps moved to the middle of their sweeps, the instant a deskewed sweep's pose refers to.

Deskewing (:mod:`gr_graph.deskew`) moves every point of a raw sweep into the sensor frame at the
sweep's middle, so the pose the odometry estimates for the frame is that of the middle. Drivers
stamp a sweep's first point (Ouster, ROS2 Velodyne) or its last (ROS1 Velodyne): written with
those stamps, every pose would lie half a sweep (0.05 s at 10 Hz, 0.5 m at 10 m/s) from its time,
and evo's association by time (``evo_ape tum``) would pair it with the wrong ground truth.

The folder and bag loaders therefore add the offset from stamp to sweep middle
(:attr:`gr_graph.datasets.frame_fields.FieldConventions.stamp_to_sweep_middle`) to the frames'
timestamps, and move the ground-truth poses, given one per scan at the scan's stamp, to the new
times along the ground truth itself (:func:`poses_at_times`). Relative times between frames are
unchanged, so the odometry's velocity and the deskewing are too.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np

from factors.se3 import exp_se3_batch, log_se3

if TYPE_CHECKING:
    from gr_graph.datasets.frame_fields import FieldConventions

__all__ = ["poses_at_times", "stamps_at_sweep_middle", "stamps_moved_by_conventions"]

log = logging.getLogger(__name__)


def poses_at_times(times: np.ndarray, poses: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Poses at ``query`` times along a path of ``poses`` at ``times``, on SE(3).

    Each query time moves along the constant-twist segment between the two path poses around it;
    before the first and after the last, the end segment is extrapolated.

    Parameters
    ----------
    times : (K,) array
        Strictly increasing times of ``poses``.
    poses : (K, 4, 4) array
    query : (M,) array

    Returns
    -------
    np.ndarray
        ``(M, 4, 4)``; with one path pose, that pose for every query time.

    Raises
    ------
    ValueError
        Shapes that do not match, or times that do not strictly increase.
    """
    t = np.asarray(times, np.float64)
    P = np.asarray(poses, np.float64)
    q = np.asarray(query, np.float64)
    if t.ndim != 1 or P.shape != (len(t), 4, 4) or q.ndim != 1:
        raise ValueError(f"times (K,) and poses (K, 4, 4) expected, got {t.shape} and {P.shape}; query {q.shape}")
    if len(t) > 1 and not np.all(np.diff(t) > 0):
        raise ValueError("the path's times must strictly increase")
    if len(t) == 1:
        return np.repeat(P, len(q), axis=0)
    a = np.clip(np.searchsorted(t, q, side="right") - 1, 0, len(t) - 2)
    u = (q - t[a]) / (t[a + 1] - t[a])
    segments, which = np.unique(a, return_inverse=True)
    twists = np.array([log_se3(np.linalg.inv(P[k]) @ P[k + 1]) for k in segments]).reshape(-1, 6)
    return P[a] @ exp_se3_batch(u[:, None] * twists[which])


def stamps_at_sweep_middle(timestamps: np.ndarray, gt_poses: np.ndarray | None, shift: float | None, source: str,
                           why: str = "") -> tuple[np.ndarray, np.ndarray | None]:
    """``timestamps + shift`` and the ground truth moved to those times (see the module docstring).

    Parameters
    ----------
    timestamps : (K,) array
        The frames' stamps (s).
    gt_poses : (K, 4, 4) array or None
        Ground truth, one pose a frame at its stamp (anchored at the first frame).
    shift : float or None
        Seconds from a stamp to its sweep's middle; None or 0: nothing moves.
    source : str
        Named in the log.
    why : str
        Where the shift comes from, for the log.

    Returns
    -------
    tuple
        The new timestamps and ground truth, anchored at the first frame again (the given arrays
        when nothing moves).
    """
    if shift is None or shift == 0.0:
        return timestamps, gt_poses
    ts = np.asarray(timestamps, np.float64)
    moved = ts + float(shift)
    log.info("%s: the poses refer to the sweeps' middles: stamps moved by %+.4g s (%s)%s", source, shift,
             why or "the offset from stamp to sweep middle",
             "; the ground truth moved along itself to the new times" if gt_poses is not None else "")
    if gt_poses is None:
        return moved, None
    gt = poses_at_times(ts, gt_poses, moved)
    return moved, np.linalg.inv(gt[0]) @ gt  # anchored at the first frame, as the loaders read it


def stamps_moved_by_conventions(timestamps: np.ndarray, gt_poses: np.ndarray | None, conventions: FieldConventions,
                                source: str) -> tuple[np.ndarray, np.ndarray | None, float]:
    """:func:`stamps_at_sweep_middle` with the offset the loader's field conventions found or were given.

    Parameters
    ----------
    timestamps, gt_poses, source
        As for :func:`stamps_at_sweep_middle`.
    conventions : FieldConventions
        Its ``stamp_to_sweep_middle`` (None: nothing moves) and ``stamp_to_sweep_middle_source``.

    Returns
    -------
    tuple
        The new timestamps, the moved ground truth and the seconds the stamps moved by (the
        loaders' ``stamps_moved_by_s``; 0.0 when nothing moved).
    """
    shift = conventions.stamp_to_sweep_middle
    moved, gt = stamps_at_sweep_middle(timestamps, gt_poses, shift, source, conventions.stamp_to_sweep_middle_source)
    return moved, gt, float(shift or 0.0)
