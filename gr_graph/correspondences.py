"""Nearest-neighbour correspondences of an edge under its relative pose T̂.

The one search used by the memory (correspondences stored per edge, :mod:`gr_graph.
memory_builder`) and by the learned edge noise (:mod:`gr_graph.edge_noise`): each source
point ``p``, mapped by ``T`` (source into target frame), is paired with its nearest target
point ``q`` when ``|T p - q| <= max_distance``. The search is small_gicp's KdTree (the
library the odometry already uses), in double precision.
"""

from __future__ import annotations

import numpy as np
import small_gicp

__all__ = ["target_tree", "nearest_correspondences"]


def target_tree(points: np.ndarray, num_threads: int = 1) -> small_gicp.KdTree | None:
    """A KdTree over ``points`` ``(M, 3)`` (None for an empty scan: it has no neighbours)."""
    pts = np.asarray(points, np.float64)
    if len(pts) == 0:
        return None
    return small_gicp.KdTree(pts, num_threads=num_threads)


def nearest_correspondences(
    source: np.ndarray,
    tree: small_gicp.KdTree | None,
    T_st: np.ndarray,
    max_distance: float,
    num_threads: int = 1,
) -> np.ndarray:
    """Index pairs ``(i, j)``: source point i and its nearest target point j within ``max_distance``.

    Parameters
    ----------
    source : (N, 3) array
        Points of the source scan, in its own frame.
    tree : small_gicp.KdTree or None
        :func:`target_tree` of the target's points (None: empty target, no pairs).
    T_st : (4, 4) array
        Maps source points into the target frame.
    max_distance : float
        Pairs farther apart than this (after mapping) are dropped [m].
    num_threads : int
        Threads of the search.

    Returns
    -------
    (P, 2) int32 array
        Ascending in ``i``; each source point appears at most once.
    """
    if len(source) == 0 or tree is None:
        return np.zeros((0, 2), np.int32)
    T_st = np.asarray(T_st, np.float64)
    p = np.asarray(source, np.float64) @ T_st[:3, :3].T + T_st[:3, 3]
    idx, d2 = tree.batch_nearest_neighbor_search(p, num_threads=num_threads)
    idx = np.asarray(idx, np.int64)
    ok = (idx >= 0) & (np.asarray(d2) <= max_distance**2)
    i = np.flatnonzero(ok)
    return np.column_stack([i, idx[ok]]).astype(np.int32)
