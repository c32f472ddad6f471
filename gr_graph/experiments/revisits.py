"""Frame windows of the generated route that contain a revisit (found from its ground truth).

A revisit is a pair of frames at least ``min_gap`` frames apart whose ground-truth positions
are within ``radius`` metres, with at least ``min_path`` metres driven between them: the vehicle
left the place and came back, the situation where a loop closure can be found. Table I is meant
to run on a window that contains at least one, so that the loop closures (and what densification
does to them) take part in the result.

Until 2026-12-06 there was no ``min_path``: a stop counted as a revisit. The 111-frame stop at
frame 346 of route seed 0 gives 3,159 pairs of frames 100+ frames apart within 5 m, all within
5 m of path, and so the published Table I window (frames 0:1500) and the ablations' (0:600) were
chosen as windows "with a revisit" while they hold none: their loop closures close the stop. On
the whole route every pair lies either under 5 m or over 200 m of path apart, so any ``min_path``
from 5 to 200 m finds the same revisits; the first 1,500-frame window holding one is 400:1900
(frames 949-1001 driven again at 1873-1899, 816-826 m of path later); no 600-frame window holds one.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["revisit_pairs", "count_revisits", "first_revisit_window", "route_positions"]


def revisit_pairs(positions: np.ndarray, min_gap: int = 100, radius: float = 5.0,
                  min_path: float = 50.0) -> np.ndarray:
    """``(M, 2)`` int64 rows ``(i, j)``, ``i < j``, ``j - i >= min_gap``, ``|p_i - p_j| <= radius``,
    and at least ``min_path`` metres of path between frames ``i`` and ``j`` (a stop is not a revisit)."""
    from gr_graph.metrics import path_distances

    P = np.asarray(positions, np.float64).reshape(-1, 3)
    travelled = path_distances(P)
    pairs = cKDTree(P).query_pairs(float(radius), output_type="ndarray").reshape(-1, 2)
    lo, hi = pairs.min(axis=1), pairs.max(axis=1)
    keep = ((hi - lo) >= min_gap) & (travelled[hi] - travelled[lo] >= min_path)
    out = np.stack([lo[keep], hi[keep]], axis=1).astype(np.int64)
    return out[np.lexsort((out[:, 1], out[:, 0]))] if len(out) else out.reshape(0, 2)


def count_revisits(positions: np.ndarray, window: tuple[int, int], min_gap: int = 100, radius: float = 5.0,
                   min_path: float = 50.0) -> int:
    """Number of revisit pairs with both frames in the half-open ``window``."""
    a, b = window
    return int(len(revisit_pairs(np.asarray(positions)[a:b], min_gap, radius, min_path)))


def first_revisit_window(positions: np.ndarray, length: int, step: int = 100, min_gap: int = 100,
                         radius: float = 5.0, min_path: float = 50.0) -> tuple[int, int]:
    """The first window ``[a, a + length)`` (``a`` a multiple of ``step``) holding a revisit.

    Raises
    ------
    ValueError
        If no window of that length holds one (or the route is shorter than ``length``).
    """
    P = np.asarray(positions, np.float64).reshape(-1, 3)
    pairs = revisit_pairs(P, min_gap, radius, min_path)
    for a in range(0, len(P) - length + 1, step):
        if np.any((pairs[:, 0] >= a) & (pairs[:, 1] < a + length)):
            return a, a + length
    raise ValueError(f"no {length}-frame window of the {len(P)}-frame route has frames >= {min_gap} apart "
                     f"within {radius} m with >= {min_path} m of path between them")


def route_positions(route_seed: int = 0) -> np.ndarray:
    """Ground-truth positions ``(K, 3)`` of the synthetic sequence's generated route (no rendering)."""
    from gr_graph.datasets.synthetic.sequence import route_path

    return np.asarray(route_path(route_seed).T_w_velo, np.float64)[:, :3, 3]
