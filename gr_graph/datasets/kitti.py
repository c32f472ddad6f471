"""KITTI odometry sequences on disk, streamed frame by frame.

Layout (the official odometry benchmark)::

    ROOT/sequences/XX/velodyne/000000.bin ...   float32 x, y, z, reflectance (or x, y, z: point_format="xyz")
    ROOT/sequences/XX/calib.txt                 P0..P3 and Tr (velodyne -> cam0), 12 floats
    ROOT/sequences/XX/times.txt                 one timestamp (s) per frame
    ROOT/poses/XX.txt                           optional ground truth, camera-0 frame

Ground truth is exposed in the LiDAR frame, ``T_w_velo = Tr⁻¹ · T_w_cam · Tr``, with the
world being the LiDAR frame of frame 0; estimates go back to the camera frame with
:meth:`KittiSequence.to_camera_frame`. Frames are read on demand; nothing but the file
list, timestamps and poses is held in memory.

Motion distortion: KITTI's odometry scans were motion-compensated with the vehicle's GPS/IMU
(its devkit readme), so a :class:`KittiSequence` says ``motion_compensated = True`` and the
odometry's ``deskew: auto`` leaves it alone.

Vertical-angle correction: the HDL-64E of KITTI measures elevations slightly too low; IMLS-SLAM
(Deschaud, ICRA 2018), CT-ICP (Dellenbach et al., ICRA 2022) and KISS-ICP (Vizzo et al., RA-L
2023; 0.205 in its 1.3.0 ``_correct_kitti_scan``) rotate every point up about the horizontal axis
perpendicular to its ray, by 0.195-0.22 degrees (:func:`correct_vertical_angle`). It is off by default (``vertical_correction_deg=0``):
the loader reads any KITTI-layout folder, including synthetic renders written in that layout
(:mod:`gr_graph.datasets.synthetic.writer`) and exports of other sensors, for which the
correction would be an error; pass the angle for real KITTI scans.

KITTI is licensed CC BY-NC-SA 3.0 (Geiger, Lenz, Urtasun, CVPR 2012).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from gr_graph.atomic import read_json_or_none
from gr_graph.datasets.base import (
    DatasetError,
    LidarFrame,
    cam_to_velo_poses,
    check_index,
    velo_to_cam_poses,
)
from gr_graph.datasets.channels import PROBE_FRAMES, RingIndexer
from gr_graph.datasets.point_layout import POINT_FORMATS, check_point_layout, float64_bin_problem, size_error
from gr_graph.datasets.pointcloud2 import finite_intensity, has_return

log = logging.getLogger(__name__)

KITTI_SCAN_PERIOD_S = 0.1037  # mean frame spacing of the odometry sequences (~10 Hz)


def correct_vertical_angle(points: np.ndarray, angle_deg: float) -> np.ndarray:
    """Raise every point's elevation by ``angle_deg``, keeping its range and azimuth.

    The point is rotated by ``angle_deg`` about the horizontal axis ``p x z`` (perpendicular
    to its ray); points on the vertical axis (no horizontal component) are unchanged. In closed
    form: with ``r = |p|``, ``rho = |(x, y)|``, elevation ``e = atan2(z, rho)``, the result has
    elevation ``e + angle`` and the same ``r`` and ``atan2(y, x)``.

    Parameters
    ----------
    points : (N, 3) array
    angle_deg : float
        Degrees; positive raises.

    Returns
    -------
    np.ndarray
        ``(N, 3)`` float64 (a copy; ``points`` itself when the angle is 0).
    """
    if angle_deg == 0.0:
        return points
    p = np.asarray(points, np.float64)
    rho = np.hypot(p[:, 0], p[:, 1])
    a = np.radians(angle_deg)
    ca, sa = np.cos(a), np.sin(a)
    new_rho = rho * ca - p[:, 2] * sa
    scale = np.divide(new_rho, rho, out=np.ones_like(rho), where=rho > 0)
    out = np.empty_like(p)
    out[:, 0] = p[:, 0] * scale
    out[:, 1] = p[:, 1] * scale
    out[:, 2] = np.where(rho > 0, rho * sa + p[:, 2] * ca, p[:, 2])
    return out


def read_calib(path: str | Path) -> dict[str, np.ndarray]:
    """Read a KITTI ``calib.txt`` into ``{key: (12,) float64}``.

    Raises
    ------
    DatasetError
        If the file is missing, a line is not ``KEY: 12 numbers``, or ``Tr`` is absent.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: calibration file not found")
    calib: dict[str, np.ndarray] = {}
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        key, sep, rest = line.partition(":")
        if not sep:
            raise DatasetError(f"{path}:{lineno}: expected 'KEY: values', got {line[:60]!r}")
        try:
            values = np.array([float(v) for v in rest.split()], np.float64)
        except ValueError as exc:
            raise DatasetError(f"{path}:{lineno}: non-numeric value in {key!r} ({exc})") from exc
        if len(values) != 12 or not np.all(np.isfinite(values)):
            raise DatasetError(f"{path}:{lineno}: {key!r} needs 12 finite numbers, got {len(values)}")
        calib[key.strip()] = values
    if "Tr" not in calib:
        raise DatasetError(f"{path}: no 'Tr' (velodyne -> cam0) line; keys are {sorted(calib)}")
    return calib


def calib_T_cam_velo(calib: dict[str, np.ndarray]) -> np.ndarray:
    """The 4x4 ``Tr`` (velodyne -> cam0) of a calibration read by :func:`read_calib`."""
    T = np.eye(4)
    T[:3, :4] = calib["Tr"].reshape(3, 4)
    return T


def read_times(path: str | Path) -> np.ndarray:
    """Read ``times.txt`` (one float per line, strictly increasing) with errors naming the file and
    line (a repeated or earlier time would stop the run only after SLAM, when the TUM trajectory is
    written)."""
    path = Path(path)
    rows = []
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            value = float(line.split()[0])
        except ValueError as exc:
            raise DatasetError(f"{path}:{lineno}: non-numeric timestamp {line[:40]!r}") from exc
        if not np.isfinite(value):
            raise DatasetError(f"{path}:{lineno}: non-finite timestamp")
        if rows and value <= rows[-1]:
            raise DatasetError(f"{path}:{lineno}: timestamp {value:.9g} s is not after the one before ({rows[-1]:.9g} "
                               "s): the times must increase")
        rows.append(value)
    return np.asarray(rows, np.float64)


def read_velodyne_bin(path: str | Path, point_format: str = "xyzi") -> np.ndarray:
    """Read one KITTI-style ``.bin`` as an ``(N, 4)`` float32 array (x, y, z, intensity).

    Parameters
    ----------
    path : path
    point_format : {"xyzi", "xyz"}
        ``"xyzi"``: 16 bytes a point (KITTI); ``"xyz"``: 12 bytes a point, no intensity (the
        intensity column of the result is 0).

    Raises
    ------
    DatasetError
        If the file is missing, its size is not a multiple of the point size (the message
        suggests the other format when the size fits it), or its contents do not look like
        ``point_format`` points (e.g. a 12-byte x,y,z file read as x,y,z,intensity; see
        :mod:`gr_graph.datasets.point_layout`), or were written as float64
        (:func:`~gr_graph.datasets.point_layout.float64_bin_problem`).
    """
    if point_format not in POINT_FORMATS:
        raise ValueError(f"point_format must be one of {sorted(POINT_FORMATS)}, got {point_format!r}")
    path = Path(path)
    try:
        size = path.stat().st_size
    except FileNotFoundError as exc:
        raise DatasetError(f"{path}: scan file not found") from exc
    stride = POINT_FORMATS[point_format]
    if size % (4 * stride):
        values = np.fromfile(path, dtype=np.float32) if size % 4 == 0 else None
        raise size_error(path, size, point_format, values)
    values = np.fromfile(path, dtype=np.float32)
    problem = float64_bin_problem(path, values)
    if problem is not None:
        raise DatasetError(problem)
    check_point_layout(values, point_format, path)
    if stride == 4:
        return values.reshape(-1, 4)
    out = np.zeros((len(values) // 3, 4), dtype=np.float32)
    out[:, :3] = values.reshape(-1, 3)
    return out



def read_velodyne_scan(path: str | Path, point_format: str = "xyzi", ring_indexer: RingIndexer | None = None
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]:
    """One Velodyne ``.bin`` scan as ``(points (N, 3) float64, intensity (N,), ring or None, kept)``;
    ``kept`` is the mask of the file's points that were kept.

    Points without a return (a non-finite coordinate, or exactly the origin) are dropped (logged
    with the file name and counted); a non-finite intensity at a point with a return is set to 0
    and the point kept (logged): the rules of the other readers
    (:func:`gr_graph.datasets.pointcloud2.decode_structured`), so a ``.bin`` gives the same points
    in a KITTI layout as in a folder. With a ``ring_indexer`` every point gets its ring, and a frame
    not indexed by storage order is logged. Shared by the KITTI odometry and raw-drive loaders.
    """
    raw = read_velodyne_bin(path, point_format)
    keep = has_return(raw[:, :3])
    dropped = int(len(raw) - keep.sum())
    if dropped:
        log.warning("%s: dropped %d points without a return (non-finite or exactly at the origin)", path, dropped)
        raw = raw[keep]
    points = raw[:, :3].astype(np.float64)
    ring = None
    if ring_indexer is not None and not len(points):
        ring = np.zeros(0, np.int16)  # an empty scan has its (no) rings: --channels keeps it as an empty frame
    elif ring_indexer is not None:
        ring, method, problem = ring_indexer(points)
        if method != "storage_order":
            log.warning("%s: rings by %s (%s)%s", path, method, problem,
                        "; approximate: per-point elevation" if method == "elevation" else "")
    return points, finite_intensity(raw[:, 3].copy(), str(path)), ring, keep


def probe_points(files: list[Path], k: int, point_format: str = "xyzi") -> np.ndarray | None:
    """Points with a return of the k-th of ``PROBE_FRAMES`` frames spread evenly over ``files`` (the ring
    reference probes of :class:`~gr_graph.datasets.channels.RingIndexer`); None past the last."""
    n = len(files)
    if k >= min(PROBE_FRAMES, n):
        return None
    raw = read_velodyne_bin(files[(k * n) // min(PROBE_FRAMES, n)], point_format)
    return raw[has_return(raw[:, :3])][:, :3].astype(np.float64)


class KittiSequence:
    """A KITTI odometry sequence read from disk, one frame at a time.

    Parameters
    ----------
    root : path
        Dataset root holding ``sequences/`` (and optionally ``poses/``).
    seq : str
        Sequence name, e.g. ``"00"``.
    recover_ring_index : bool
        Recover each point's laser ring (needed for channel subsampling) with a
        :class:`gr_graph.datasets.channels.RingIndexer`: frames whose lines are not found in
        order are matched to per-ring elevations of probe frames, and as a last resort get
        approximate rings from per-point elevation; every fallback is logged and counted
        (:attr:`ring_recovery_counts`), every frame has a ring index.
    n_rings : int
        Rings of the sensor (64 for KITTI's HDL-64E; 32 or 16 for subsampled exports).
    point_format : {"xyzi", "xyz"}
        ``"xyzi"``: float32 x, y, z, intensity a point (KITTI); ``"xyz"``: float32 x, y, z
        (12 bytes a point; frames get intensity 0). Every file is checked against it when
        read: a file that looks like the other layout is refused, naming the file.
    vertical_correction_deg : float
        Raise every point's elevation by this angle (:func:`correct_vertical_angle`) after
        ring recovery; 0 (default, see the module docstring) reads the scans unchanged.
        KISS-ICP 1.3.0 uses 0.205 for KITTI (its ``_correct_kitti_scan``).
    per_point_times : bool
        Read ``sequences/XX/times/NNNNNN.npy`` when every scan has one (the synthetic exporter's raw
        sweeps): frames get ``time`` and the sequence is not motion-compensated. False
        (``sensor.has_time: false``) ignores them.

    Attributes
    ----------
    timestamps : (K,) array
    gt_poses : (K, 4, 4) array or None
        Ground truth in the LiDAR frame (``T_w_velo``), None without ``poses/XX.txt``.
    T_cam_velo : (4, 4) array
        KITTI's ``Tr``.
    """

    def __init__(
        self, root: str | Path, seq: str = "00", recover_ring_index: bool = True, n_rings: int = 64,
        point_format: str = "xyzi", vertical_correction_deg: float = 0.0, per_point_times: bool = True,
    ) -> None:
        if point_format not in POINT_FORMATS:
            raise ValueError(f"point_format must be one of {sorted(POINT_FORMATS)}, got {point_format!r}")
        self.point_format = point_format
        if not (np.isfinite(vertical_correction_deg) and abs(vertical_correction_deg) <= 2.0):
            raise ValueError(f"vertical_correction_deg must be within +-2 degrees, got {vertical_correction_deg}")
        self.vertical_correction_deg = float(vertical_correction_deg)
        self.motion_compensated = True  # KITTI odometry scans: compensated with the GPS/IMU
        self.root = Path(root)
        self.n_rings = n_rings
        self.seq = f"{int(seq):02d}" if str(seq).isdigit() else str(seq)
        self.name = f"kitti-{self.seq}"
        self.recover_ring_index = recover_ring_index
        self.ring_indexer = RingIndexer(n_rings, reference_source=self._probe_points)
        seq_dir = self.root / "sequences" / self.seq
        velo_dir = seq_dir / "velodyne"
        if not velo_dir.is_dir():
            raise DatasetError(f"{velo_dir}: no such folder (is {self.root} a KITTI odometry root?)")
        self.files = sorted(p for p in velo_dir.glob("*.bin") if not p.name.startswith("."))  # not macOS ._ files
        if not self.files:
            raise DatasetError(f"{velo_dir}: no .bin scans")
        expected = [f"{i:06d}.bin" for i in range(len(self.files))]
        if [f.name for f in self.files] != expected:
            first_bad = next(a.name for a, b in zip(self.files, expected) if a.name != b)
            raise DatasetError(f"{velo_dir}: scans are not numbered 000000.bin.. consecutively (at {first_bad})")
        self.calib = read_calib(seq_dir / "calib.txt")
        self.T_cam_velo = calib_T_cam_velo(self.calib)

        times_path = seq_dir / "times.txt"
        if times_path.is_file():
            self.timestamps = read_times(times_path)
            if len(self.timestamps) != len(self.files):
                raise DatasetError(
                    f"{times_path}: {len(self.timestamps)} timestamps for {len(self.files)} scans"
                )
        else:
            log.warning("%s missing: assuming %.4f s between frames", times_path, KITTI_SCAN_PERIOD_S)
            self.timestamps = np.arange(len(self.files)) * KITTI_SCAN_PERIOD_S

        exported = read_json_or_none(seq_dir / "synthetic.json")  # the synthetic exporter's record
        if isinstance(exported, dict) and isinstance(exported.get("n_rings"), int) and exported["n_rings"] != n_rings:
            log.warning("%s: exported with %d of the sensor's rings, read here as a %d-ring sensor: the rings are "
                        "recovered approximately, and --channels would subsample them again (read it without)",
                        seq_dir / "synthetic.json", exported["n_rings"], n_rings)
        self.time_files = self._per_point_time_files(seq_dir / "times") if per_point_times else None
        if self.time_files is not None:  # a raw sweep (e.g. the synthetic `raw` preset's export): deskewed with them
            self.motion_compensated = False

        self.gt_poses: np.ndarray | None = None
        pose_path = self.root / "poses" / f"{self.seq}.txt"
        if pose_path.is_file():
            from gr_graph.trajectory import read_kitti_poses

            try:
                cam_poses = read_kitti_poses(pose_path)
            except ValueError as exc:
                raise DatasetError(str(exc)) from exc
            if len(cam_poses) != len(self.files):
                raise DatasetError(f"{pose_path}: {len(cam_poses)} poses for {len(self.files)} scans")
            self.gt_poses = self.to_lidar_frame(cam_poses)

    def __len__(self) -> int:
        return len(self.files)

    def _per_point_time_files(self, times_dir: Path) -> list[Path] | None:
        """``sequences/XX/times/NNNNNN.npy``, one a scan (sweep fractions of its points, in its point
        order: what the synthetic exporter writes for sweeps that are not motion-compensated), or None."""
        if not times_dir.is_dir():
            return None
        files = [times_dir / f"{i:06d}.npy" for i in range(len(self.files))]
        n_found = sum(p.is_file() for p in files)
        if n_found < len(files):
            log.warning("%s: per-point times of %d of the %d scans; ignored (scans read as motion-compensated)",
                        times_dir, n_found, len(files))
            return None
        log.info("%s: per-point times of every scan: raw sweeps, deskewed with them", times_dir)
        return files

    def _probe_points(self, k: int) -> np.ndarray | None:
        return probe_points(self.files, k, self.point_format)

    @property
    def ring_recovery_counts(self) -> dict[str, int]:
        """Frames indexed per method so far: ``storage_order``, ``reference``, ``line_rank``, ``elevation``."""
        return dict(self.ring_indexer.counts)

    def __getitem__(self, index: int) -> LidarFrame:
        i = check_index(index, len(self), self.name)
        points, intensity, ring, kept = read_velodyne_scan(
            self.files[i], self.point_format, self.ring_indexer if self.recover_ring_index else None)
        points = correct_vertical_angle(points, self.vertical_correction_deg)
        dropped = int(len(kept) - len(points))
        time = None
        if self.time_files is not None:
            try:
                time = np.asarray(np.load(self.time_files[i], allow_pickle=False), np.float64).reshape(-1)
            except (OSError, ValueError, EOFError) as exc:
                raise DatasetError(f"{self.time_files[i]}: unreadable per-point times ({exc})") from None
            if len(time) != len(kept):
                raise DatasetError(f"{self.time_files[i]}: {len(time)} per-point times for the {len(kept)} "
                                   f"points of {self.files[i].name}")
            time = time[kept]  # the times of the points with a return
        return LidarFrame(
            index=i,
            timestamp=float(self.timestamps[i]),
            points=points,
            intensity=intensity,
            ring=ring,
            n_rings=self.n_rings,
            dropped_nonfinite=dropped,
            time=time,
        )

    def __iter__(self) -> Iterator[LidarFrame]:
        for i in range(len(self)):
            yield self[i]

    def to_lidar_frame(self, T_w_cam: np.ndarray) -> np.ndarray:
        """Camera-0-frame poses ``(K, 4, 4)`` -> LiDAR-frame poses (``Tr⁻¹ · T · Tr``)."""
        return cam_to_velo_poses(T_w_cam, self.T_cam_velo)

    def to_camera_frame(self, T_w_velo: np.ndarray) -> np.ndarray:
        """LiDAR-frame poses ``(K, 4, 4)`` -> camera-0 frame, comparable to KITTI's ground truth."""
        return velo_to_cam_poses(T_w_velo, self.T_cam_velo)
