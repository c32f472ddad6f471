"""A folder of point-cloud files (``.bin``, ``.pcd``, ``.ply`` or ``.npy``) as a LiDAR sequence.

The files are sorted naturally (``frame2`` before ``frame10``); a folder mixing types is refused.
Optional side files, given explicitly or found next to the scans (in the folder, then its parent):

- timestamps: ``times.txt`` or ``timestamps.txt``, one number a line, seconds (values above
  1e12 are taken as nanoseconds); without one, frames are 0.1 s apart (logged);
- poses: ``poses.txt`` (or ``poses_kitti.txt`` / ``poses_tum.txt``), KITTI (12 numbers a line,
  row-major 3x4) or TUM (``t x y z qx qy qz qw``), told apart by the column count, one pose a
  frame, of the LiDAR in a world frame; they are re-expressed relative to the first (the world
  is the LiDAR frame of scan 0, :mod:`gr_graph.datasets.base`). A TUM file's times serve as
  frame timestamps when there is no timestamps file.

Files with a per-point time field (PCD/PLY/npy ``t``/``time``/``timestamp``) make the sequence
``motion_compensated = False``, so the odometry's ``deskew: auto`` deskews them.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from gr_graph.datasets.base import DatasetError, LidarFrame, check_index
from gr_graph.datasets.frame_fields import DEFAULT_FRAME_PERIOD_S, FieldConventions, frame_period
from gr_graph.datasets.point_files import POINT_FILE_SUFFIXES, read_point_file

log = logging.getLogger(__name__)

TIMESTAMP_FILES = ("times.txt", "timestamps.txt")
POSE_FILES = ("poses.txt", "poses_kitti.txt", "poses_tum.txt")
_NS_THRESHOLD = 1e12


def natural_key(name: str) -> list:
    """Sort key that orders digit runs by value: ``frame2`` < ``frame10``."""
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


def point_files(folder: Path) -> list[Path]:
    """The point files of ``folder``, naturally sorted; refuses an empty folder or mixed types."""
    if not folder.is_dir():
        raise DatasetError(f"{folder}: no such folder")
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in POINT_FILE_SUFFIXES]
    if not files:
        raise DatasetError(f"{folder}: no point files ({', '.join(POINT_FILE_SUFFIXES)})")
    kinds: dict[str, int] = {}
    for p in files:
        kinds[p.suffix.lower()] = kinds.get(p.suffix.lower(), 0) + 1
    if len(kinds) > 1:
        listing = ", ".join(f"{n} {k}" for k, n in sorted(kinds.items()))
        raise DatasetError(f"{folder}: mixed file types ({listing}); keep one type of point file in the folder")
    return sorted(files, key=lambda p: natural_key(p.name))


def find_side_file(folder: Path, names: tuple[str, ...]) -> Path | None:
    """The first of ``names`` in ``folder`` or its parent."""
    for where in (folder, folder.parent):
        for name in names:
            if (where / name).is_file():
                return where / name
    return None


def read_timestamps_file(path: Path, n_frames: int) -> np.ndarray:
    """Seconds since the first frame, one a frame (see the module docstring for units)."""
    from gr_graph.trajectory import TrajectoryFormatError, read_kitti_times

    try:
        ts = read_kitti_times(path)
    except (TrajectoryFormatError, ValueError) as exc:
        raise DatasetError(str(exc) if str(path) in str(exc) else f"{path}: {exc}") from exc
    if len(ts) != n_frames:
        raise DatasetError(f"{path}: {len(ts)} timestamps for {n_frames} frames")
    if ts[0] > _NS_THRESHOLD:
        ts = (ts - ts[0]) * 1e-9
        log.info("%s: timestamps above 1e12 read as nanoseconds", path)
    return ts - ts[0]


def read_pose_file(path: Path, n_frames: int) -> tuple[np.ndarray, np.ndarray | None]:
    """LiDAR poses relative to the first ``(K, 4, 4)`` and, for TUM files, their times (s, from 0)."""
    from gr_graph.trajectory import TrajectoryFormatError, read_kitti_poses, read_tum_poses

    first = next((ln.split() for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")),
                 None)
    if first is None:
        raise DatasetError(f"{path}: empty pose file")
    try:
        if len(first) == 12:
            poses, times = read_kitti_poses(path), None
        elif len(first) == 8:
            times, poses = read_tum_poses(path)
            times = times - times[0]
        else:
            raise DatasetError(f"{path}: {len(first)} columns a line; expected 12 (KITTI) or 8 (TUM)")
    except (TrajectoryFormatError, ValueError) as exc:
        if isinstance(exc, DatasetError):
            raise
        raise DatasetError(str(exc) if str(path) in str(exc) else f"{path}: {exc}") from exc
    if len(poses) != n_frames:
        raise DatasetError(f"{path}: {len(poses)} poses for {n_frames} frames")
    return np.linalg.inv(poses[0]) @ poses, times


class FolderSequence:
    """A folder of point files, streamed one file per frame (LidarSequence protocol).

    Parameters
    ----------
    folder : path
    point_format : {"xyzi", "xyz"}
        Layout of ``.bin`` files.
    timestamps, poses : path, optional
        Side files (see the module docstring); None: look next to the scans.

    Attributes
    ----------
    files : list of Path
    timestamps : (K,) array
    gt_poses : (K, 4, 4) array or None
    motion_compensated : bool
        False when the files carry per-point times.
    scan_period : float
        The frame spacing (s), used as the sweep duration.
    """

    def __init__(self, folder: str | Path, point_format: str = "xyzi", timestamps: str | Path | None = None,
                 poses: str | Path | None = None) -> None:
        self.folder = Path(folder)
        self.point_format = point_format
        self.files = point_files(self.folder)
        self.name = f"folder-{self.folder.name}"
        self.T_cam_velo = np.eye(4)
        n = len(self.files)
        pose_path = Path(poses) if poses is not None else find_side_file(self.folder, POSE_FILES)
        times_path = Path(timestamps) if timestamps is not None else find_side_file(self.folder, TIMESTAMP_FILES)
        for given, what in ((poses, "poses"), (timestamps, "timestamps")):
            if given is not None and not Path(given).is_file():
                raise DatasetError(f"{given}: {what} file not found")
        self.gt_poses: np.ndarray | None = None
        pose_times = None
        if pose_path is not None:
            self.gt_poses, pose_times = read_pose_file(pose_path, n)
        if times_path is not None:
            self.timestamps = read_timestamps_file(times_path, n)
        elif pose_times is not None:
            self.timestamps = pose_times
        else:
            log.warning("%s: no timestamps file (%s): frames taken %.2f s apart", self.folder,
                        " / ".join(TIMESTAMP_FILES), DEFAULT_FRAME_PERIOD_S)
            self.timestamps = np.arange(n) * DEFAULT_FRAME_PERIOD_S
        self.scan_period = frame_period(self.timestamps)
        first = read_point_file(self.files[0], point_format)
        self.conventions = FieldConventions.probe(first, self.scan_period, str(self.files[0]))
        self.motion_compensated = not self.conventions.has_time
        self.n_rings = self.conventions.n_rings

    def __len__(self) -> int:
        return len(self.files)

    def __getitem__(self, index: int) -> LidarFrame:
        i = check_index(index, len(self), self.name)
        path = self.files[i]
        cloud = read_point_file(path, self.point_format)
        if cloud.dropped_nonfinite:
            log.warning("%s: dropped %d non-finite points", path, cloud.dropped_nonfinite)
        return self.conventions.frame(cloud, i, float(self.timestamps[i]), str(path))

    def __iter__(self) -> Iterator[LidarFrame]:
        for i in range(len(self)):
            yield self[i]
