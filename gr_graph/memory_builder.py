"""The memory of a SLAM run (format: :mod:`gr_graph.memory`) from its result.

Edges: odometry edges (k+1, k) (source P = S_{k+1}, target Q = S_k) and loop edges (i, j)
with i the newer scan, in the run's order. For each edge

- ``edge_T`` is T̂ = T_target⁻¹ T_source from the *optimised* trajectory;
- ``edge_H`` is the registration Hessian (small_gicp, unscaled); a flagged edge (failed
  registration, listed in ``info.flagged_edges``) stores its fallback information, times the
  round's variance factor when the learned edge noise was calibrated
  (:func:`gr_graph.frame_loop.scale_learned_information` scales it in place before the memory is built);
- ``corr`` are the nearest stored target points within ``odometry.corr_max_distance`` under
  that T̂ (:func:`gr_graph.correspondences.nearest_correspondences`).

``info`` holds ``frame_index`` (sequence index of each scan), ``flagged_edges`` and what the
caller adds (round, channels, source...).
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from gr_graph.config import SlamConfig
from gr_graph.correspondences import nearest_correspondences, target_tree
from gr_graph.frame_loop import SlamResult
from gr_graph.memory import EDGE_LOOP, EDGE_ODOMETRY, Memory, save_memory_from_scans

__all__ = ["EDGE_H_DESCRIPTION", "build_memory"]

EDGE_H_DESCRIPTION = ("registration Hessian (small_gicp, unscaled); flagged edges (info.flagged_edges, failed "
                      "registrations): the fallback information")


def build_memory(result: SlamResult, cfg: SlamConfig, info: dict[str, Any] | None = None,
                 scans: Sequence[np.ndarray] | None = None, directory: str | Path | None = None) -> Memory:
    """The memory of a SLAM run (see the module docstring).

    Parameters
    ----------
    result : SlamResult
        Poses, edges and frame indices of the run.
    cfg : SlamConfig
        ``odometry.corr_max_distance`` and ``odometry.num_threads`` are used.
    info : dict, optional
        Added to the memory's ``info``.
    scans : list of (N_k, 3) arrays, optional
        The scans to store (default: ``result.scans``); learning rounds store round 0's raw
        downsampled scans. Correspondences are searched among these.
    directory : path, optional
        Write the memory there (atomically) while assembling it, with no concatenated copy of
        the points and correspondences in RAM, and return it memory-mapped
        (:func:`gr_graph.memory.save_memory_from_scans`). Without it the memory is assembled in
        RAM (:meth:`Memory.from_scans`).
    """
    scans = result.scans if scans is None else scans
    if len(scans) != len(result.poses):
        raise ValueError(f"build_memory: {len(scans)} scans for {len(result.poses)} poses")
    poses = result.poses
    by_target: dict[int, list[int]] = defaultdict(list)
    for e, edge in enumerate(result.edges):
        by_target[edge.target].append(e)
    E = len(result.edges)
    Ts: list[np.ndarray] = [np.eye(4)] * E
    corr: list[np.ndarray] = [np.zeros((0, 2), np.int32)] * E
    threads = cfg.odometry.num_threads
    for l in tqdm(sorted(by_target), desc="memory", unit="scan", disable=not cfg.output.progress, mininterval=1.0):
        tree = target_tree(scans[l], threads)
        for e in by_target[l]:
            edge = result.edges[e]
            T = np.linalg.inv(poses[edge.target]) @ poses[edge.source]
            Ts[e] = T
            corr[e] = nearest_correspondences(scans[edge.source], tree, T, cfg.odometry.corr_max_distance, threads)
    H = [edge.H_raw if edge.ok else edge.information for edge in result.edges]
    assemble = Memory.from_scans if directory is None else partial(save_memory_from_scans, directory)
    return assemble(
        scans=scans,
        poses=poses,
        edges=[(e.source, e.target) for e in result.edges],
        edge_kind=[EDGE_LOOP if e.kind == "loop" else EDGE_ODOMETRY for e in result.edges],
        edge_T=Ts,
        edge_H=H,
        corr=corr,
        info={"frame_index": result.frame_index.tolist(),
              "flagged_edges": [e for e, edge in enumerate(result.edges) if not edge.ok],
              **(info or {})},
    )
