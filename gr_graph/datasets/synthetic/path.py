"""The KITTI odometry 00 trajectory shipped with gr_graph (the path of the synthetic sequence).

The files live in ``gr_graph/data/kitti00/`` (see its README): ``poses.txt`` (official ground
truth, camera-0 frame, 12 floats a row), ``times.txt`` and ``calib.txt`` (``P0`` and ``Tr``).
Source: the KITTI Vision Benchmark Suite (Geiger, Lenz, Urtasun, CVPR 2012), CC BY-NC-SA 3.0.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from gr_graph.datasets.base import DatasetError, cam_to_velo_poses
from gr_graph.datasets.kitti import calib_T_cam_velo, read_calib, read_times
from gr_graph.trajectory import read_kitti_poses

DATA_DIR = Path(__file__).resolve().parents[2] / "data" / "kitti00"
N_FRAMES = 4541


@dataclass(frozen=True)
class Kitti00Path:
    """The shipped KITTI 00 trajectory.

    Attributes
    ----------
    times : np.ndarray
        ``(K,)`` float64 timestamps in seconds.
    T_w_cam : np.ndarray
        ``(K, 4, 4)`` float64 camera-0 poses (KITTI's ground-truth convention).
    T_cam_velo : np.ndarray
        ``(4, 4)`` KITTI ``Tr`` (velodyne -> camera 0).
    P0 : np.ndarray
        ``(3, 4)`` projection matrix of camera 0.
    T_w_velo : np.ndarray
        ``(K, 4, 4)`` LiDAR poses ``Tr⁻¹ · T_w_cam · Tr`` (world = LiDAR frame of scan 0).
    """

    times: np.ndarray
    T_w_cam: np.ndarray
    T_cam_velo: np.ndarray
    P0: np.ndarray
    T_w_velo: np.ndarray


@lru_cache(maxsize=1)
def load_kitti00_path(data_dir: Path = DATA_DIR) -> Kitti00Path:
    """Load (once per process) the shipped KITTI 00 poses, times and calibration."""
    calib = read_calib(data_dir / "calib.txt")
    if "P0" not in calib:
        raise DatasetError(f"{data_dir / 'calib.txt'}: no 'P0' line")
    Tr = calib_T_cam_velo(calib)
    try:
        T_w_cam = read_kitti_poses(data_dir / "poses.txt")
    except ValueError as exc:
        raise DatasetError(str(exc)) from exc
    times = read_times(data_dir / "times.txt")
    if len(times) != len(T_w_cam):
        raise DatasetError(
            f"{data_dir}: times.txt has {len(times)} rows but poses.txt has {len(T_w_cam)}"
        )
    T_w_velo = cam_to_velo_poses(T_w_cam, Tr)
    for arr in (times, T_w_cam, Tr, T_w_velo):
        arr.setflags(write=False)
    return Kitti00Path(times, T_w_cam, Tr, calib["P0"].reshape(3, 4), T_w_velo)
