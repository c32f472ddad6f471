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


def read_calib(path: Path) -> dict[str, np.ndarray]:
    """Read a KITTI ``calib.txt`` into ``{key: float64 array}``; raises DatasetError naming the file."""
    out: dict[str, np.ndarray] = {}
    try:
        lines = Path(path).read_text().splitlines()
    except OSError as exc:
        raise DatasetError(f"cannot read calibration file {path}: {exc}") from exc
    for n, line in enumerate(lines, 1):
        if not line.strip():
            continue
        key, sep, rest = line.partition(":")
        if not sep:
            raise DatasetError(f"{path}:{n}: expected 'KEY: values', got {line[:40]!r}")
        try:
            out[key.strip()] = np.array(rest.split(), dtype=np.float64)
        except ValueError as exc:
            raise DatasetError(f"{path}:{n}: non-numeric value in {key!r}") from exc
    return out


def read_kitti_poses(path: Path) -> np.ndarray:
    """Read KITTI poses (12 floats a row) as ``(K, 4, 4)`` float64."""
    try:
        rows = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except (OSError, ValueError) as exc:
        raise DatasetError(f"cannot read poses file {path}: {exc}") from exc
    if rows.shape[1] != 12:
        raise DatasetError(f"{path}: expected 12 floats a row, got {rows.shape[1]}")
    T = np.tile(np.eye(4), (len(rows), 1, 1))
    T[:, :3, :] = rows.reshape(-1, 3, 4)
    return T


@lru_cache(maxsize=1)
def load_kitti00_path(data_dir: Path = DATA_DIR) -> Kitti00Path:
    """Load (once per process) the shipped KITTI 00 poses, times and calibration."""
    calib = read_calib(data_dir / "calib.txt")
    for key, size in (("Tr", 12), ("P0", 12)):
        if key not in calib or calib[key].size != size:
            raise DatasetError(f"{data_dir / 'calib.txt'}: missing or malformed {key!r} line")
    Tr = np.eye(4)
    Tr[:3, :] = calib["Tr"].reshape(3, 4)
    T_w_cam = read_kitti_poses(data_dir / "poses.txt")
    try:
        times = np.loadtxt(data_dir / "times.txt", dtype=np.float64, ndmin=1)
    except (OSError, ValueError) as exc:
        raise DatasetError(f"cannot read {data_dir / 'times.txt'}: {exc}") from exc
    if len(times) != len(T_w_cam):
        raise DatasetError(
            f"{data_dir}: times.txt has {len(times)} rows but poses.txt has {len(T_w_cam)}"
        )
    T_w_velo = cam_to_velo_poses(T_w_cam, Tr)
    for arr in (times, T_w_cam, Tr, T_w_velo):
        arr.setflags(write=False)
    return Kitti00Path(times, T_w_cam, Tr, calib["P0"].reshape(3, 4), T_w_velo)
