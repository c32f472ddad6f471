"""Loop closures against ground truth: true revisits, the error of a loop, precision and recall.

A checked scan is a *true revisit* when the ground truth has an older scan (at least
``min_frame_gap`` frames older) within ``revisit_radius``; an accepted loop is *correct*
when its pose error against the ground truth is below ``max_t_err`` and ``max_r_err_deg``.
Recall counts revisit queries with a correct loop, and contiguous revisit stretches
(segments) with at least one.
"""

from __future__ import annotations

import numpy as np

from factors.se3 import rotation_angle
from gr_graph.loop_closure import last_scan_path_back, path_lengths

__all__ = ["true_revisits", "loop_error", "loop_precision_recall"]


def true_revisits(gt_poses: np.ndarray, min_frame_gap: int, radius: float, min_path_length: float = 0.0) -> np.ndarray:
    """Boolean (K,): scan i has an older scan (gap ≥ ``min_frame_gap`` and at least ``min_path_length``
    of ground-truth path back: the loop candidates' limits) within ``radius`` in GT."""
    pos = np.asarray(gt_poses)[:, :3, 3]
    K = len(pos)
    path = path_lengths(pos)
    out = np.zeros(K, dtype=bool)
    for i in range(min_frame_gap, K):
        last = i - min_frame_gap
        if min_path_length > 0.0:
            last = min(last, last_scan_path_back(path, i, min_path_length))
        if last >= 0:
            d = np.linalg.norm(pos[: last + 1] - pos[i], axis=1)
            out[i] = bool(d.min() <= radius)
    return out


def loop_error(T_ij: np.ndarray, gt_poses: np.ndarray, i: int, j: int) -> tuple[float, float]:
    """Translation [m] and rotation [deg] error of a loop T̂_ij against GT (T_j⁻¹ T_i)."""
    T_gt = np.linalg.inv(gt_poses[j]) @ gt_poses[i]
    E = np.linalg.inv(T_gt) @ T_ij
    return float(np.linalg.norm(E[:3, 3])), float(np.degrees(rotation_angle(E[:3, :3])))


def loop_precision_recall(
    loops: list[tuple[int, int, np.ndarray]],
    gt_poses: np.ndarray,
    checked: np.ndarray,
    min_frame_gap: int,
    revisit_radius: float = 5.0,
    max_t_err: float = 2.0,
    max_r_err_deg: float = 10.0,
    min_path_length: float = 0.0,
) -> dict:
    """Precision and recall of accepted loops against ground truth.

    Parameters
    ----------
    loops : list of (i, j, T̂_ij)
        Accepted loops.
    gt_poses : (K, 4, 4)
        Ground-truth poses (any common world frame).
    checked : (K,) bool
        Which scans were queried for loops (recall is over those).
    revisit_radius : float
        A checked scan is a true revisit when GT has an older scan within this radius.
    min_path_length : float
        ... and that scan lies this much ground-truth path back (``loops.min_path_length``).

    Returns
    -------
    dict with ``n_loops``, ``n_correct`` (pose error < max_t_err / max_r_err_deg),
    ``precision``, ``n_revisit_queries``, ``n_revisit_found``, ``recall`` (revisit queries
    with an accepted loop), ``n_revisit_segments``, ``segments_found`` (contiguous revisit
    stretches with at least one loop) and ``segment_recall``; ``None`` where undefined. The
    segments are built from every true revisit, checked or not: a stretch shorter than the
    checking interval, or inside a cooldown, counts even though no query fell in it (so
    ``segment_recall`` is a lower bound of what the schedule allowed).
    """
    correct = []
    for i, j, T in loops:
        et, er = loop_error(T, gt_poses, i, j)
        correct.append(et <= max_t_err and er <= max_r_err_deg)
    revisit = true_revisits(gt_poses, min_frame_gap, revisit_radius, min_path_length)
    q = revisit & np.asarray(checked, bool)
    found = np.zeros_like(q)
    for (i, _j, _T), ok in zip(loops, correct):
        if ok:
            found[i] = True
    n_q = int(q.sum())
    n_found = int((found & q).sum())
    # contiguous revisit segments (gaps of < min_frame_gap / 2 frames merged)
    segs: list[tuple[int, int]] = []
    idx = np.flatnonzero(revisit)
    for i in idx:
        if segs and i - segs[-1][1] <= max(1, min_frame_gap // 2):
            segs[-1] = (segs[-1][0], int(i))
        else:
            segs.append((int(i), int(i)))
    seg_found = sum(1 for a, b in segs if found[a : b + 1].any())
    n = len(loops)
    return {
        "n_loops": n,
        "n_correct": int(sum(correct)),
        "precision": (sum(correct) / n) if n else None,
        "n_revisit_queries": n_q,
        "n_revisit_found": n_found,
        "recall": (n_found / n_q) if n_q else None,
        "n_revisit_segments": len(segs),
        "revisit_segments": segs,
        "segments_found": seg_found,
        "segment_recall": (seg_found / len(segs)) if segs else None,
        "revisit_radius": revisit_radius,
        "max_t_err": max_t_err,
        "max_r_err_deg": max_r_err_deg,
    }
