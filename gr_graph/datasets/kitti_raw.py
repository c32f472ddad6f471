"""KITTI raw drives (``YYYY_MM_DD_drive_XXXX_sync``) as LiDAR sequences.

Layout (the raw data recordings, Geiger et al., IJRR 2013)::

    DATE/calib_imu_to_velo.txt                        optional, R and T of the IMU in the LiDAR frame
    DATE/DRIVE/velodyne_points/data/0000000000.bin    float32 x, y, z, reflectance
    DATE/DRIVE/velodyne_points/timestamps.txt         "2011-09-26 13:02:25.964389445" a scan
    DATE/DRIVE/velodyne_points/timestamps_start.txt   optional sweep starts (same format)
    DATE/DRIVE/velodyne_points/timestamps_end.txt     optional sweep ends
    DATE/DRIVE/oxts/data/0000000000.txt               optional GPS/IMU: lat lon alt roll pitch yaw ...

Unlike the odometry benchmark, these scans are **not** motion-compensated
(``motion_compensated = False``: ``deskew: auto`` deskews them); the sweep duration is the
median of ``timestamps_end - timestamps_start`` when both files exist, else the frame spacing.

Ground truth from ``oxts/`` (the devkit's conversion): with Earth radius 6378137 m and the
Mercator scale ``s = cos(lat_0)`` of the first latitude, the IMU position is
``(s·R·lon·π/180, s·R·ln tan((90 + lat)·π/360), alt)`` and its rotation
``Rz(yaw)·Ry(pitch)·Rx(roll)``; the LiDAR pose is ``T_w_imu · T_imu_velo`` (``T_imu_velo`` the
inverse of ``calib_imu_to_velo.txt``; identity with a warning when that file is missing),
re-expressed relative to the first scan. Rings are recovered as for the odometry folders
(:class:`gr_graph.datasets.channels.RingIndexer`, HDL-64E storage order).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from datetime import datetime
from pathlib import Path

import numpy as np

from gr_graph.datasets.base import DatasetError, LidarFrame, check_index, increasing_stamps
from gr_graph.datasets.channels import RingIndexer
from gr_graph.datasets.folder import natural_key
from gr_graph.datasets.frame_fields import frame_period
from gr_graph.datasets.kitti import probe_points, read_velodyne_scan
from gr_graph.sensors import SensorConfig

log = logging.getLogger(__name__)

EARTH_RADIUS_M = 6378137.0
OXTS_MIN_VALUES = 6


def is_kitti_raw_drive(path: Path) -> bool:
    """A folder holding ``velodyne_points/data``."""
    return (path / "velodyne_points" / "data").is_dir()


def parse_kitti_datetime(text: str) -> int:
    """Nanoseconds since the epoch (UTC, naive) of ``"YYYY-MM-DD HH:MM:SS.fffffffff"`` (exact integers:
    a float64 of seconds since 1970 would keep only about 0.2 microseconds)."""
    date_part, _, frac = text.strip().partition(".")
    base = datetime.strptime(date_part, "%Y-%m-%d %H:%M:%S")
    if frac and (not frac.isdigit() or len(frac) > 9):
        raise ValueError(f"fraction of a second {frac!r}")
    seconds = int((base - datetime(1970, 1, 1)).total_seconds())
    return seconds * 1_000_000_000 + (int(frac.ljust(9, "0")) if frac else 0)


def read_raw_timestamps(path: Path) -> np.ndarray:
    """Nanoseconds since the epoch (int64) of each line of a raw-drive ``timestamps*.txt``."""
    out = []
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            out.append(parse_kitti_datetime(line))
        except ValueError as exc:
            raise DatasetError(f"{path}:{lineno}: not a 'YYYY-MM-DD HH:MM:SS.fff' date ({line[:40]!r})") from exc
    return np.asarray(out, np.int64)


def rotation_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """``Rz(yaw) · Ry(pitch) · Rx(roll)``."""
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def oxts_to_poses(oxts: np.ndarray) -> np.ndarray:
    """IMU poses ``(K, 4, 4)`` in the Mercator world of the first latitude from OXTS rows
    ``lat lon alt roll pitch yaw ...`` (degrees, metres, radians)."""
    scale = np.cos(np.radians(oxts[0, 0]))
    poses = np.tile(np.eye(4), (len(oxts), 1, 1))
    for k, (lat, lon, alt, roll, pitch, yaw) in enumerate(oxts[:, :6]):
        poses[k, 0, 3] = scale * EARTH_RADIUS_M * np.radians(lon)
        poses[k, 1, 3] = scale * EARTH_RADIUS_M * np.log(np.tan(np.radians(90.0 + lat) / 2.0))
        poses[k, 2, 3] = alt
        poses[k, :3, :3] = rotation_rpy(roll, pitch, yaw)
    return poses


def read_oxts_folder(folder: Path, n_frames: int) -> np.ndarray:
    """The ``(K, >=6)`` OXTS rows of ``oxts/data/*.txt``."""
    files = sorted(folder.glob("*.txt"), key=lambda p: natural_key(p.name))
    if len(files) != n_frames:
        raise DatasetError(f"{folder}: {len(files)} OXTS files for {n_frames} scans")
    rows = []
    for path in files:
        try:
            values = np.array([float(v) for v in path.read_text().split()], np.float64)
        except ValueError as exc:
            raise DatasetError(f"{path}: non-numeric OXTS value ({exc})") from exc
        if len(values) < OXTS_MIN_VALUES or not np.all(np.isfinite(values[:OXTS_MIN_VALUES])):
            raise DatasetError(f"{path}: needs at least {OXTS_MIN_VALUES} finite values "
                               "(lat lon alt roll pitch yaw), got " + str(len(values)))
        rows.append(values[:OXTS_MIN_VALUES])
    return np.asarray(rows)


def read_rigid_calib(path: Path) -> np.ndarray:
    """The 4x4 transform of a raw-data calibration file with ``R:`` (9 numbers) and ``T:`` (3)."""
    entries: dict[str, np.ndarray] = {}
    for line in path.read_text().splitlines():
        key, sep, rest = line.partition(":")
        if sep and key.strip() in ("R", "T"):
            try:
                entries[key.strip()] = np.array([float(v) for v in rest.split()])
            except ValueError as exc:
                raise DatasetError(f"{path}: non-numeric {key.strip()} ({exc})") from exc
    if entries.get("R", np.zeros(0)).size != 9 or entries.get("T", np.zeros(0)).size != 3:
        raise DatasetError(f"{path}: needs 'R:' with 9 numbers and 'T:' with 3")
    T = np.eye(4)
    T[:3, :3] = entries["R"].reshape(3, 3)
    T[:3, 3] = entries["T"]
    return T


class KittiRawSequence:
    """A KITTI raw drive, streamed scan by scan (LidarSequence protocol).

    Parameters
    ----------
    drive : path
        The drive folder (holding ``velodyne_points/``).
    point_format : {"xyzi", "xyz"}
    recover_ring_index : bool
        Recover rings as :class:`gr_graph.datasets.kitti.KittiSequence` does.
    sensor : SensorConfig, optional
        The ``sensor`` section: its ``scan_period``, when given, is the sweep duration the
        deskewer uses (else the median of ``timestamps_end - timestamps_start``, else the frame
        spacing). The drive's HDL-64E fixes everything else.

    Attributes
    ----------
    timestamps : (K,) array
        Seconds since the first scan.
    gt_poses : (K, 4, 4) array or None
        LiDAR poses from ``oxts/`` (None without it).
    motion_compensated : bool
        False.
    scan_period : float
        Sweep duration (s): ``sensor.scan_period``, the start/end stamps' median span or the frame spacing.
    """

    def __init__(self, drive: str | Path, point_format: str = "xyzi", recover_ring_index: bool = True,
                 sensor: SensorConfig | None = None) -> None:
        self.drive = Path(drive)
        velo = self.drive / "velodyne_points"
        data = velo / "data"
        if not data.is_dir():
            raise DatasetError(f"{data}: no such folder (is {self.drive} a KITTI raw drive?)")
        self.files = sorted((p for p in data.glob("*.bin") if not p.name.startswith(".")),  # not macOS ._ files
                            key=lambda p: natural_key(p.name))
        others = sorted({p.suffix for p in data.iterdir()  # hidden files (macOS .DS_Store, ._*) are not scans
                         if p.is_file() and p.suffix != ".bin" and not p.name.startswith(".")})
        if others:
            raise DatasetError(f"{data}: mixed file types (.bin and {', '.join(map(repr, others))})")
        if not self.files:
            raise DatasetError(f"{data}: no .bin scans")
        self.point_format = point_format
        self.name = f"kitti-raw-{self.drive.name}"
        self.T_cam_velo = np.eye(4)
        self.n_rings = 64
        self.motion_compensated = False
        self.recover_ring_index = recover_ring_index
        self.ring_indexer = RingIndexer(self.n_rings, reference_source=self._probe_points)
        n = len(self.files)
        times_path = velo / "timestamps.txt"
        if not times_path.is_file():
            raise DatasetError(f"{times_path}: missing (a raw drive has one date a scan)")
        absolute = read_raw_timestamps(times_path)
        if len(absolute) != n:
            raise DatasetError(f"{times_path}: {len(absolute)} timestamps for {n} scans")
        absolute = increasing_stamps(absolute, str(times_path))
        self.timestamps = (absolute - absolute[0]).astype(np.float64) * 1e-9
        self.scan_period = frame_period(self.timestamps)
        start_path, end_path = velo / "timestamps_start.txt", velo / "timestamps_end.txt"
        if start_path.is_file() and end_path.is_file():
            starts, ends = read_raw_timestamps(start_path), read_raw_timestamps(end_path)
            if len(starts) == len(ends) == n and np.all(ends > starts):
                self.scan_period = float(np.median(ends - starts)) * 1e-9
        if sensor is not None and sensor.scan_period is not None:
            log.info("%s: sweep duration %.4g s from sensor.scan_period (the drive's stamps say %.4g s)",
                     self.drive, sensor.scan_period, self.scan_period)
            self.scan_period = float(sensor.scan_period)
        self.gt_poses: np.ndarray | None = None
        oxts = self.drive / "oxts" / "data"
        if oxts.is_dir():
            T_w_imu = oxts_to_poses(read_oxts_folder(oxts, n))
            calib = self.drive.parent / "calib_imu_to_velo.txt"
            if calib.is_file():
                T_imu_velo = np.linalg.inv(read_rigid_calib(calib))
            else:
                log.warning("%s missing: ground truth takes the LiDAR at the IMU (identity extrinsics)", calib)
                T_imu_velo = np.eye(4)
            T_w_velo = T_w_imu @ T_imu_velo
            self.gt_poses = np.linalg.inv(T_w_velo[0]) @ T_w_velo

    def __len__(self) -> int:
        return len(self.files)

    def _probe_points(self, k: int) -> np.ndarray | None:
        return probe_points(self.files, k, self.point_format)

    def __getitem__(self, index: int) -> LidarFrame:
        i = check_index(index, len(self), self.name)
        points, intensity, ring, kept = read_velodyne_scan(
            self.files[i], self.point_format, self.ring_indexer if self.recover_ring_index else None)
        return LidarFrame(index=i, timestamp=float(self.timestamps[i]), points=points, intensity=intensity,
                          ring=ring, n_rings=self.n_rings, dropped_nonfinite=int(len(kept) - len(points)))

    def __iter__(self) -> Iterator[LidarFrame]:
        for i in range(len(self)):
            yield self[i]
