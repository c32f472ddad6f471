"""Long-baseline consistency of a trajectory with its own raw scans (no ground truth).

A learning round can drift slowly (a few millimetres or a hundredth of a degree a frame, mostly in
height) while every local map stays sharp: an 11-frame window does not show it, a 300-frame
window does. This module measures the drift at an intermediate scale that the scans themselves
can still check: pairs of frames ``min_distance`` metres apart along the path (about 30 frames at
KITTI's speed) are registered directly, raw scan to raw scan (small_gicp GICP, one thread, so
deterministic), and each trajectory's relative pose over the pair is compared with that
registration. A trajectory that drifts more between the two frames disagrees more with it.

Why it is not decided on by default (measured on the synthetic ``kitti`` world, 16, 32 and
64 channels: README, "Learning rounds that never make things worse"; ``benchmarks/long_baseline_study.py``):
the registrations are not accurate enough. Against the ground truth, the pairs' registrations
are off in pitch by −0.07 to −0.11° on average with the vertical-angle correction and +0.14 to
+0.20° without it, ±0.03-0.20° pair to pair: the size of the drift they should reveal (0.2° over
25 m is 9 cm of height). Without the correction a round that undoes the sensor's bias reads as
*less* consistent; with it the figure saw one large loss and missed others. Computed with the
ground truth's relative poses in place of the registrations (what perfect registrations would
give), the figure rises far more for the large 16-channel losses, and not at all for the small
ones (the 32-channel rounds' few per cent, one 16-channel round's +33 % RPE-300): a 25 m median
rotation cannot see every drift, however good the registrations.

Functions
---------
baseline_pairs
    Frame pairs ``(k, l)``: ``l`` the first frame at least ``min_distance`` along the path from ``k``.
register_pairs
    GICP registration of each pair's raw scans, from an initial trajectory.
pair_discrepancy
    Translation and rotation of ``T_reg⁻¹ · T_k⁻¹ T_l`` per pair, for a trajectory.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["baseline_pairs", "register_pairs", "pair_discrepancy"]


def baseline_pairs(positions: np.ndarray, min_distance: float, step: int, max_frames: int) -> np.ndarray:
    """Frame pairs about ``min_distance`` apart along the path.

    Parameters
    ----------
    positions : (K, 3) array
        Positions of the trajectory that sets the pairs (the reference round's).
    min_distance : float
        ``l`` is the first frame after ``k`` whose path length from ``k`` is at least this [m].
    step : int
        A pair starts at every ``step``-th frame.
    max_frames : int
        Pairs more than this many frames apart are dropped (a long stop between them).

    Returns
    -------
    (M, 2) int array
        ``(k, l)`` with ``k < l``, no two pairs sharing ``l`` (the starts during a stop all reach the
        same frame: only the first is kept); empty when the path is shorter than ``min_distance`` or
        a position is not finite.
    """
    from gr_graph.metrics import path_distances

    p = np.asarray(positions, np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"baseline_pairs: positions must be (K, 3), got {p.shape}")
    if len(p) < 2 or not np.all(np.isfinite(p)):
        return np.zeros((0, 2), np.int64)
    travelled = path_distances(p)
    starts = np.arange(0, len(p), max(1, int(step)))
    ends = np.searchsorted(travelled, travelled[starts] + min_distance, side="left")
    keep = (ends < len(p)) & (ends - starts <= max_frames) & (ends > starts)
    starts, ends = starts[keep], ends[keep]
    _, first = np.unique(ends, return_index=True)
    return np.stack([starts[first], ends[first]], axis=1).astype(np.int64)


def register_pairs(scans: Sequence[np.ndarray], poses: np.ndarray, pairs: np.ndarray, voxel_size: float,
                   max_correspondence_distance: float, min_inlier_fraction: float,
                   num_neighbors: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Register scan ``l`` to scan ``k`` for every pair, starting from ``poses``.

    Parameters
    ----------
    scans : sequence of (N_k, >=3) arrays
        Raw scans in their sensor frames (x, y, z first).
    poses : (K, 4, 4) array
        ``T_w_k``; the initial guess of pair ``(k, l)`` is ``T_k⁻¹ T_l``.
    pairs : (M, 2) int array
        :func:`baseline_pairs`.
    voxel_size, max_correspondence_distance : float
        small_gicp's downsampling resolution and correspondence distance [m].
    min_inlier_fraction : float
        A registration that did not converge, or matched fewer of the source's points, fails.
    num_neighbors : int
        Neighbours of each point's covariance.

    Returns
    -------
    T : (M, 4, 4) array
        ``T_k_l`` of each registration (NaN where it failed).
    ok : (M,) bool array
        Which registrations succeeded.
    """
    import small_gicp

    poses = np.asarray(poses, np.float64)
    T = np.full((len(pairs), 4, 4), np.nan)
    ok = np.zeros(len(pairs), bool)
    clouds: dict[int, tuple[object, object]] = {}

    def cloud(k: int) -> tuple[object, object]:
        if k not in clouds:
            pts = np.ascontiguousarray(np.asarray(scans[k], np.float64)[:, :3])
            clouds[k] = small_gicp.preprocess_points(pts, downsampling_resolution=voxel_size,
                                                     num_neighbors=num_neighbors, num_threads=1)
        return clouds[k]

    for m, (k, l) in enumerate(np.asarray(pairs, np.int64)):
        target, target_tree = cloud(int(k))
        source, _ = cloud(int(l))
        if target.size() < num_neighbors or source.size() < num_neighbors:
            continue
        init = np.linalg.inv(poses[k]) @ poses[l]
        res = small_gicp.align(target, source, target_tree, init_T_target_source=init, registration_type="GICP",
                               max_correspondence_distance=max_correspondence_distance, num_threads=1)
        if res.converged and res.num_inliers >= min_inlier_fraction * source.size():
            T[m], ok[m] = res.T_target_source, True
        for j in [j for j in clouds if j < k]:  # pairs come in frame order: free the scans behind
            del clouds[j]
    return T, ok


def pair_discrepancy(poses: np.ndarray, pairs: np.ndarray, T_pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How far a trajectory's relative poses are from the pairs' registrations.

    Returns
    -------
    translation : (M,) array
        ``|t|`` of ``E = T_reg⁻¹ · T_k⁻¹ T_l`` [m].
    rotation : (M,) array
        Rotation angle of ``E`` [rad].
    """
    poses = np.asarray(poses, np.float64)
    pairs = np.asarray(pairs, np.int64)
    rel = np.linalg.inv(poses[pairs[:, 0]]) @ poses[pairs[:, 1]]
    E = np.linalg.inv(np.asarray(T_pairs, np.float64)) @ rel
    cos = np.clip((np.trace(E[:, :3, :3], axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    return np.linalg.norm(E[:, :3, 3], axis=1), np.arccos(cos)

