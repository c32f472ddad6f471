"""A folder of point-cloud files (``.bin``, ``.pcd``, ``.ply`` or ``.npy``) as a LiDAR sequence.

Which files are scans, and their order (:func:`point_files`):

- hidden files (names starting with ``.``, e.g. macOS AppleDouble ``._000003.pcd`` files) are
  skipped; a warning gives their count;
- when every file name (without its suffix) is a decimal number, e.g. timestamps written with
  ``str(float)`` (``1600000000.3.pcd``, ``1600000000.1002998.pcd``), the files are ordered by
  that number; otherwise they are sorted naturally (digit runs by value: ``frame2`` before
  ``frame10``, ``1`` before ``10``, ROS-style ``<sec>_<nsec>`` names by seconds then nanoseconds);
- a folder mixing types is refused.

A scan without points (an empty ``.bin``, ``POINTS 0`` PCD, 0-byte file, ...; see
:mod:`gr_graph.datasets.point_files`) becomes an empty frame, logged and counted in
:attr:`FolderSequence.empty_frames`; the pipeline marks it unusable. The field conventions
(per-point time, rings) are probed on the first scan that has points and four more spread over the
folder (:func:`gr_graph.datasets.frame_fields.probe_indices`).

Optional side files, given explicitly or found next to the scans (in the folder, then its parent):

- timestamps: ``times.txt`` or ``timestamps.txt``, one number a line, strictly increasing, in
  seconds, milliseconds, microseconds or nanoseconds, absolute (e.g. epoch) or relative. The
  unit is the one of s/ms/us/ns that makes the median spacing between frames a LiDAR frame
  spacing (:data:`PLAUSIBLE_FRAME_SPACING_S`, 0.005-10 s; of two that do, the one in which the
  first time is a Unix time, else the larger) and is logged; when none does, or when
  that unit puts the first time after :data:`MAX_ABSOLUTE_TIME_S` (the magnitude contradicts
  the spacing), the file is refused. Without a timestamps file, frames are one sweep apart
  (logged): ``sensor.scan_period``, else the span of a full revolution's per-point times when it
  is more than 10 % away from 0.1 s, else 0.1 s;
- poses: ``poses.txt`` (or ``poses_kitti.txt`` / ``poses_tum.txt``), KITTI (12 numbers a line,
  row-major 3x4) or TUM (``t x y z qx qy qz qw``), told apart by the column count, one pose a
  frame, of the LiDAR in a world frame; they are re-expressed relative to the first (the world
  is the LiDAR frame of scan 0, :mod:`gr_graph.datasets.base`). A TUM file's times serve as
  frame timestamps when there is no timestamps file. A pose file found beside the scans (not
  given) is not taken from a folder that holds a gr_graph run's output (:func:`is_run_output`:
  ``metrics.json`` or ``config.yaml`` with ``round_0/``), where ``poses_kitti.txt`` is the run's
  own estimate, not ground truth (logged); the file taken is logged.

Files with a per-point time field (PCD/PLY/npy ``t``/``time``/``timestamp``) make the sequence
``motion_compensated = False``, so the odometry's ``deskew: auto`` deskews them. When those times
are relative to the sweep (or ``sensor.frame_stamp`` says where the stamps lie), the timestamps
are moved to the sweeps' middles, where the deskewed poses refer, and the ground truth along itself
with them (:mod:`gr_graph.datasets.stamp_shift`); absolute per-point times keep the stamps.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from gr_graph.datasets.base import DatasetError, LidarFrame, check_index
from gr_graph.datasets.frame_fields import (
    DEFAULT_FRAME_PERIOD_S,
    PLAUSIBLE_SWEEP_S,
    FieldConventions,
    frame_period,
    no_time_field_note,
    probe_indices,
)
from gr_graph.datasets.point_files import POINT_FILE_SUFFIXES, read_point_file
from gr_graph.datasets.pointcloud2 import TIME_FIELDS, DecodedCloud
from gr_graph.datasets.stamp_shift import stamps_moved_by_conventions
from gr_graph.sensors import TIME_UNITS, SensorConfig

log = logging.getLogger(__name__)

TIMESTAMP_FILES = ("times.txt", "timestamps.txt")
#: scan files that can carry a per-point time field (a ``.bin`` holds x, y, z[, intensity] only)
FIELD_FORMATS = (".pcd", ".ply", ".npy")
POSE_FILES = ("poses.txt", "poses_kitti.txt", "poses_tum.txt")
RUN_POSE_FILES = ("poses_kitti.txt", "poses_tum.txt")
"""The pose files a gr_graph run writes at the top of ``--out`` (its estimate, not ground truth)."""
PLAUSIBLE_FRAME_SPACING_S = PLAUSIBLE_SWEEP_S
"""Median frame spacing (s) a LiDAR sequence can have (200 Hz down to one frame in 10 s, e.g.
subsampled recordings). Its ratio (2000) exceeds the 1000 between units, so up to two units fit a
spacing: the one whose first time is a Unix time (:data:`UNIX_TIME_RANGE_S`) wins, else the larger
(5 read as 5 s, not 5 ms)."""
UNIX_TIME_RANGE_S = (1e8, 1e10)
"""Unix times from 1973 to 2286 (s): a first timestamp in this range, in one of the fitting units,
is an absolute stamp in that unit (epoch seconds, milliseconds, microseconds or nanoseconds)."""
MAX_ABSOLUTE_TIME_S = 1e10
"""Times above this many seconds (year 2286 as a Unix time) are not plausible in any unit."""
_DECIMAL_NAME = re.compile(r"[+-]?(\d+(\.\d*)?|\.\d+)")
_DATE_TIME = re.compile(r"\d{4}-\d{2}-\d{2}[ T]\d{2}:\d{2}")


def natural_key(name: str) -> list:
    """Sort key that orders digit runs by value: ``frame2`` < ``frame10``."""
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


_SEC_NSEC_NAME = re.compile(r"(\d+)\.(\d{1,9})")


def _spacing_irregularity(times: list[float]) -> float:
    """Spread of the steps between sorted ``times`` over their median (0 for even spacing)."""
    steps = np.diff(np.sort(np.asarray(times, np.float64)))
    med = float(np.median(steps)) if len(steps) else 0.0
    return float(np.std(steps) / med) if med > 0 else float("inf")


def sort_point_files(files: list[Path]) -> list[Path]:
    """``files`` in frame order.

    When every name without its suffix is a decimal number (``1600000000.1002998``,
    ``1600000000.3``, ``000012``), by that number (exactly, as a ``Decimal``; ties naturally);
    otherwise naturally (:func:`natural_key`), where ``1600000000.3`` would wrongly come before
    ``1600000000.1002998`` (3 < 1002998). Names such as ``100.5000000`` are ambiguous: a
    ``str(float)`` stamp (100.5 s) or seconds and unpadded nanoseconds (100.005 s, which the
    natural order gets right). When the two orders differ, the reading whose times are the more
    evenly spaced is taken, with a warning naming it.
    """
    natural = sorted(files, key=lambda p: natural_key(p.name))
    if not files or not all(_DECIMAL_NAME.fullmatch(p.stem) for p in files):
        return natural
    from decimal import Decimal

    decimal = sorted(files, key=lambda p: (Decimal(p.stem), natural_key(p.name)))
    if decimal == natural:
        return decimal
    if not all(_SEC_NSEC_NAME.fullmatch(p.stem) for p in files):
        log.info("%s: the file names are decimal numbers: ordered by their value (%s)", files[0].parent,
                 ", ".join(p.name for p in decimal[:3]) + (", ..." if len(decimal) > 3 else ""))
        return decimal
    as_decimal = [float(Decimal(p.stem)) for p in files]
    as_sec_nsec = [int(m.group(1)) + int(m.group(2)) * 1e-9 for m in (_SEC_NSEC_NAME.fullmatch(p.stem) for p in files)]
    nsec = _spacing_irregularity(as_sec_nsec) < _spacing_irregularity(as_decimal)
    log.warning("%s: file names such as %s read as %s (the order differs from the other reading; chosen because "
                "it spaces the frames more evenly); zero-padded names avoid the ambiguity", files[0].parent,
                natural[1].name if len(natural) > 1 else natural[0].name,
                "seconds.nanoseconds (natural order)" if nsec else "decimal seconds")
    return natural if nsec else decimal


def point_files(folder: Path) -> list[Path]:
    """The point files of ``folder`` in frame order (:func:`sort_point_files`), hidden files
    (``.*``, e.g. AppleDouble ``._x.pcd``) skipped with a warning; refuses an empty folder or mixed types."""
    if not folder.is_dir():
        raise DatasetError(f"{folder}: no such folder")
    candidates = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in POINT_FILE_SUFFIXES]
    hidden = sorted(p.name for p in candidates if p.name.startswith("."))
    if hidden:
        log.warning("%s: skipped %d hidden file%s named like scans (%s%s; e.g. macOS AppleDouble '._' files)",
                    folder, len(hidden), "s" if len(hidden) > 1 else "", ", ".join(hidden[:3]),
                    ", ..." if len(hidden) > 3 else "")
    files = [p for p in candidates if not p.name.startswith(".")]
    if not files:
        raise DatasetError(f"{folder}: no point files ({', '.join(POINT_FILE_SUFFIXES)})"
                           + (f"; {len(hidden)} hidden files skipped" if hidden else ""))
    kinds: dict[str, int] = {}
    for p in files:
        kinds[p.suffix.lower()] = kinds.get(p.suffix.lower(), 0) + 1
    if len(kinds) > 1:
        listing = ", ".join(f"{n} {k}" for k, n in sorted(kinds.items()))
        raise DatasetError(f"{folder}: mixed file types ({listing}); keep one type of point file in the folder")
    return sort_point_files(files)


def find_side_file(folder: Path, names: tuple[str, ...], skip_run_outputs: bool = False) -> Path | None:
    """The first of ``names`` in ``folder`` or its parent (with ``skip_run_outputs``, not a file a
    run writes, :data:`RUN_POSE_FILES`, in a folder that holds a gr_graph run's output,
    :func:`is_run_output`; logged)."""
    for where in (folder, folder.parent):
        for name in names:
            if (where / name).is_file():
                if skip_run_outputs and name in RUN_POSE_FILES and is_run_output(where):
                    log.warning("%s: not taken as ground truth: %s holds a gr_graph run's output (its poses are "
                                "that run's estimate); pass the ground truth's file with --poses", where / name, where)
                    continue
                return where / name
    return None


def is_run_output(folder: Path) -> bool:
    """``folder`` holds a gr_graph run's output (``round_0/`` beside ``metrics.json`` or ``config.yaml``)."""
    return (folder / "round_0").is_dir() and ((folder / "metrics.json").is_file() or (folder / "config.yaml").is_file())


def timestamp_unit(ts: np.ndarray, source: str) -> tuple[str, float]:
    """The unit ``(name, seconds per unit)`` of increasing frame times ``ts`` (see the module docstring).

    Raises
    ------
    DatasetError
        Naming ``source``, when no unit gives a plausible frame spacing, or the unit that does
        makes the times implausibly large.
    """
    if len(ts) < 2:
        return "s", 1.0  # one frame: its time is 0 whatever the unit
    spacing = float(np.median(np.diff(ts)))
    lo, hi = PLAUSIBLE_FRAME_SPACING_S
    fitting = [(name, unit) for name, unit in TIME_UNITS.items() if lo <= spacing * unit <= hi]
    if not fitting:
        tried = ", ".join(f"{spacing * unit:.3g} s in {name}" for name, unit in TIME_UNITS.items())
        raise DatasetError(f"{source}: the median spacing between timestamps is {spacing:.6g} (file units); no unit "
                           f"gives a LiDAR frame spacing of {lo:g}-{hi:g} s ({tried}): give one time a frame, "
                           "in s, ms, us or ns")
    # two units can fit (e.g. 5 s or 5 ms apart): Unix times say which; else the larger unit
    lo_epoch, hi_epoch = UNIX_TIME_RANGE_S
    epoch = [(name, unit) for name, unit in fitting if lo_epoch <= abs(float(ts[0])) * unit <= hi_epoch]
    name, unit = (epoch or fitting)[0]
    largest = float(np.max(np.abs(ts[[0, -1]]))) * unit
    if largest > MAX_ABSOLUTE_TIME_S:
        raise DatasetError(f"{source}: the frame spacing ({spacing:.6g}) says the times are in {name}, but then "
                           f"they reach {largest:.3g} s (more than {MAX_ABSOLUTE_TIME_S:g} s, year 2286 as a Unix "
                           "time): the values and their spacing contradict each other")
    return name, unit


def read_timestamps_file(path: Path, n_frames: int) -> np.ndarray:
    """Seconds since the first frame, one a frame (the unit is guessed and logged, see the module docstring)."""
    from gr_graph.trajectory import TrajectoryFormatError, read_kitti_times

    try:
        ts = read_kitti_times(path)
    except (TrajectoryFormatError, ValueError) as exc:
        message = str(exc) if str(path) in str(exc) else f"{path}: {exc}"
        if _DATE_TIME.match(path.read_text(errors="replace").lstrip()):
            message += (" (date-time stamps, as in a KITTI raw drive's velodyne_points/timestamps.txt: open the "
                        "drive folder, the one holding velodyne_points/, which the kitti_raw loader reads, or give "
                        "--timestamps with one number a frame)")
        raise DatasetError(message) from exc
    if len(ts) != n_frames:
        raise DatasetError(f"{path}: {len(ts)} timestamps for {n_frames} frames")
    name, unit = timestamp_unit(ts, str(path))
    rel = (ts - ts[0]) * unit
    if len(ts) > 1:
        log.info("%s: timestamps read in %s (median frame spacing %.4g s)", path, name,
                 float(np.median(np.diff(rel))))
    return rel


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


def check_pose_times(pose_times: np.ndarray, frame_times: np.ndarray, pose_path: Path, times_path: Path) -> None:
    """Ground-truth poses are paired with the scans row by row: their own times (a TUM file's) must then
    follow the scans' (``times_path``: a timestamps file, or a bag's messages), up to a constant offset
    (another clock's origin).

    Raises
    ------
    DatasetError
        Naming both files, when the two disagree by more than half a frame spacing after the offset.
    """
    if len(pose_times) < 2:
        return
    gap = (np.asarray(pose_times, np.float64) - pose_times[0]) - (np.asarray(frame_times, np.float64) - frame_times[0])
    tolerance = 0.5 * float(np.median(np.diff(frame_times)))
    k = int(np.argmax(np.abs(gap)))
    if abs(gap[k]) > tolerance:
        raise DatasetError(
            f"{pose_path}: its poses are paired with the scans row by row, but their times do not follow the "
            f"scans' ({times_path}): row {k} is {gap[k]:+.4g} s off after the first row's offset (tolerance "
            f"{tolerance:.3g} s, half a frame spacing); give one pose a scan, at the scan's time")


class FolderSequence:
    """A folder of point files, streamed one file per frame (LidarSequence protocol).

    Parameters
    ----------
    folder : path
    point_format : {"xyzi", "xyz"}
        Layout of ``.bin`` files.
    timestamps, poses : path, optional
        Side files (see the module docstring); None: look next to the scans.
    sensor : SensorConfig, optional
        The ``sensor`` section: its time unit and reference when set, its ``scan_period`` (else the
        frame spacing), ``has_time`` / ``has_ring``, and the ring count of a named sensor
        (:meth:`gr_graph.datasets.frame_fields.FieldConventions.probe`).

    Attributes
    ----------
    files : list of Path
    timestamps : (K,) array
    gt_poses : (K, 4, 4) array or None
    motion_compensated : bool
        False when the files carry per-point times.
    scan_period : float
        The sweep duration (s): ``sensor.scan_period`` when given, else the frame spacing or a full
        revolution's per-point time span (:attr:`FieldConventions.scan_period_source`). Without a
        timestamps file the frames are taken this far apart.
    empty_frames : set of int
        Indices of the frames read so far whose file held no points (each logged once).
    """

    def __init__(self, folder: str | Path, point_format: str = "xyzi", timestamps: str | Path | None = None,
                 poses: str | Path | None = None, sensor: SensorConfig | None = None) -> None:
        self.folder = Path(folder)
        self.point_format = point_format
        self.files = point_files(self.folder)
        self.name = f"folder-{self.folder.name}"
        self._said_dropped = False  # points without a return were logged once
        self.T_cam_velo = np.eye(4)
        n = len(self.files)
        pose_path = Path(poses) if poses is not None else find_side_file(self.folder, POSE_FILES, skip_run_outputs=True)
        times_path = Path(timestamps) if timestamps is not None else find_side_file(self.folder, TIMESTAMP_FILES)
        for given, what in ((poses, "poses"), (timestamps, "timestamps")):
            if given is not None and not Path(given).is_file():
                raise DatasetError(f"{given}: {what} file not found")
        self.gt_poses: np.ndarray | None = None
        pose_times = None
        if pose_path is not None:
            self.gt_poses, pose_times = read_pose_file(pose_path, n)
            log.info("%s: ground-truth poses from %s%s", self.folder, pose_path, "" if poses is not None else " (found)")
        stamps = read_timestamps_file(times_path, n) if times_path is not None else pose_times
        if times_path is not None and pose_times is not None:
            check_pose_times(pose_times, stamps, pose_path, times_path)
        at_10hz = np.arange(n) * DEFAULT_FRAME_PERIOD_S  # the frames' times when neither they nor the sweep are known
        self.empty_frames: set[int] = set()
        self._read_ahead: dict[int, DecodedCloud] = {}
        probe_index = 0
        for probe_index, path in enumerate(self.files):  # the first scan with points fixes the conventions
            first = read_point_file(path, point_format)
            self._read_ahead = {probe_index: first}
            if len(first.points):
                break
        more = [(read_point_file(self.files[k], point_format), str(self.files[k]))
                for k in probe_indices(n, probe_index)[1:]]  # spread over the folder (not kept: read again)
        self.conventions = FieldConventions.probe(first, frame_period(at_10hz if stamps is None else stamps),
                                                  str(self.files[probe_index]), sensor, more)
        self.scan_period = self.conventions.scan_period
        if stamps is None:
            # frames one sweep apart when sensor.scan_period or a full revolution's times say how long one
            # lasts; else exactly 0.1 s (not the median spacing's rounding: the same times, and data
            # fingerprint, as before the sweep was known)
            source = self.conventions.scan_period_source
            stamps = at_10hz if source == "frame spacing" else np.arange(n) * self.scan_period
            log.warning("%s: no timestamps file (%s): frames taken %.4g s apart (%s)", self.folder,
                        " / ".join(TIMESTAMP_FILES), float(stamps[1] - stamps[0]) if n > 1 else DEFAULT_FRAME_PERIOD_S,
                        "the usual 10 Hz" if source == "frame spacing" else source)
        self.timestamps, self.gt_poses, self.stamps_moved_by_s = stamps_moved_by_conventions(
            stamps, self.gt_poses, self.conventions, str(self.folder))
        self.motion_compensated = self.conventions.motion_compensated
        if self.motion_compensated and self.files[0].suffix.lower() in FIELD_FORMATS:
            # files that could hold a time field and do not: raw sweeps look the same, say what is assumed
            log.warning(no_time_field_note(f"{self.folder} ({' / '.join(TIME_FIELDS)}, in any case)"))

    @property
    def n_rings(self) -> int:
        """Rings of the scans (:attr:`gr_graph.datasets.frame_fields.FieldConventions.n_rings`)."""
        return self.conventions.n_rings

    def __len__(self) -> int:
        return len(self.files)

    def __getitem__(self, index: int) -> LidarFrame:
        i = check_index(index, len(self), self.name)
        path = self.files[i]
        cloud = self._read_ahead.pop(i, None)
        if cloud is None:
            cloud = read_point_file(path, self.point_format)
        if cloud.dropped_nonfinite:  # organized clouds have them in every frame: said once, then at debug level
            log.log(logging.DEBUG if self._said_dropped else logging.WARNING,
                    "%s: dropped %d points without a return (non-finite, or exactly at the origin)%s", path,
                    cloud.dropped_nonfinite, "" if self._said_dropped else
                    "; counted in each frame's dropped_nonfinite, not logged again")
            self._said_dropped = True
        if len(cloud.points) == 0:
            return self._empty_frame(i, path, cloud)
        return self.conventions.frame(cloud, i, float(self.timestamps[i]), str(path))

    def _empty_frame(self, i: int, path: Path, cloud: DecodedCloud) -> LidarFrame:
        """The frame of a scan without points (unusable for registration; logged once a frame)."""
        if i not in self.empty_frames:
            self.empty_frames.add(i)
            what = ("a 0-byte file" if path.stat().st_size == 0 else
                    f"all {cloud.dropped_nonfinite} points without a return" if cloud.dropped_nonfinite else "no points")
            log.warning("%s: empty scan (%s): frame %d is empty (%d empty frame%s so far)", path, what, i,
                        len(self.empty_frames), "s" if len(self.empty_frames) > 1 else "")
        conv = self.conventions  # the fields the sequence's other frames have, empty
        has_time = conv.has_time and conv.use_time
        has_ring = conv.has_ring and conv.use_ring
        return LidarFrame(index=i, timestamp=float(self.timestamps[i]), points=np.zeros((0, 3)),
                          intensity=np.zeros(0, np.float32), ring=np.zeros(0, np.int16) if has_ring else None,
                          n_rings=conv.n_rings, dropped_nonfinite=cloud.dropped_nonfinite,
                          time=np.zeros(0) if has_time else None)

    def __iter__(self) -> Iterator[LidarFrame]:
        for i in range(len(self)):
            yield self[i]
