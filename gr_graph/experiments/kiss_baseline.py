"""KISS-ICP 1.3.0 on the very scans of a SLAM cell: the baseline column of Table I.

KISS-ICP runs with its default configuration, one thread, deskewing off (the synthetic
frames carry no per-point timestamps; the ``kitti`` preset is motion-compensated up to a
residual, like KITTI's odometry scans). It reads the same sequence view the SLAM cell reads
(same world seed, frames, channel subsampling, sensor preset); its trajectory is scored like
gr_graph's rounds (:func:`gr_graph.metrics.trajectory_metrics`, camera frame, RPE over 300
frames).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from gr_graph.datasets.base import LidarSequence, velo_to_cam_poses

__all__ = ["kiss_icp_poses", "kiss_icp_metrics"]


def _kiss_icp() -> Any:
    from kiss_icp.config import load_config
    from kiss_icp.kiss_icp import KissICP

    cfg = load_config(None)
    cfg.data.deskew = False
    cfg.registration.max_num_threads = 1
    return KissICP(cfg)


def kiss_icp_poses(sequence: LidarSequence) -> np.ndarray:
    """KISS-ICP's ``(K, 4, 4)`` poses ``T_w_velo`` of every frame of ``sequence`` (first = identity)."""
    k = _kiss_icp()
    empty = np.zeros(0)
    poses = []
    for i in range(len(sequence)):
        pts = np.asarray(sequence[i].points, np.float64)
        k.register_frame(pts[np.isfinite(pts).all(axis=1)], empty)
        poses.append(np.array(k.last_pose, np.float64))
    return np.asarray(poses)


def kiss_icp_metrics(sequence: LidarSequence) -> dict[str, Any]:
    """Trajectory metrics of KISS-ICP on ``sequence`` against its ground truth, with timing.

    Raises
    ------
    ValueError
        If the sequence has no ground truth.
    """
    from importlib.metadata import version

    from gr_graph.metrics import trajectory_metrics

    if sequence.gt_poses is None:
        raise ValueError(f"{sequence.name}: KISS-ICP baseline needs ground-truth poses")
    t0, c0 = time.perf_counter(), time.process_time()
    poses = kiss_icp_poses(sequence)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    gt = np.asarray(sequence.gt_poses, np.float64)[: len(poses)]
    gt = np.linalg.inv(gt[0]) @ gt
    T = np.asarray(sequence.T_cam_velo, np.float64)
    m = trajectory_metrics(velo_to_cam_poses(poses, T), velo_to_cam_poses(gt, T), delta=300)
    return {"system": f"KISS-ICP {version('kiss-icp')} (default config, 1 thread, deskew off)",
            "metrics": m, "wall_s": wall, "cpu_s": cpu, "n_frames": int(len(poses)),
            "poses_T_w_velo": poses[:, :3, :].tolist()}
