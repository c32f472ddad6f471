"""The sensor path of a synthetic sequence: the project's generated route, or a given trajectory.

- :func:`route_path`: the route generated from a seed (:mod:`.route`), with the synthetic
  rig's own calibration (:mod:`.rig`). The default world.
- :func:`trajectory_path`: render along a real trajectory instead:

  * a KITTI pose file (12 floats a row, camera-0 frame). LiDAR poses are
    ``Tr⁻¹ · T_w_cam · Tr`` with ``Tr`` from a ``calib.txt`` beside the file, else the synthetic
    rig's ``T_cam_velo`` (so that exporting the rendering writes back the very same camera
    poses); timestamps from a ``times.txt`` beside the file, else 0.1 s steps;
  * a TUM file (``t x y z qx qy qz qw``): LiDAR poses (x forward, z up) with their timestamps;
  * a KITTI odometry root (a folder with ``poses/<seq>.txt``): its poses, the sequence's
    ``calib.txt`` (``Tr``) and ``times.txt``.

  Poses are re-based on the first one (world = LiDAR frame of frame 0).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gr_graph.datasets.base import DatasetError, cam_to_velo_poses
from gr_graph.datasets.synthetic import rig
from gr_graph.datasets.synthetic.route import Route, generate_route


@dataclass(frozen=True)
class SensorPath:
    """Where the synthetic sensor drives.

    Attributes
    ----------
    times : np.ndarray
        ``(K,)`` float64 timestamps (s).
    T_w_velo : np.ndarray
        ``(K, 4, 4)`` LiDAR poses, world = LiDAR frame of frame 0 (z up).
    T_cam_velo : np.ndarray
        ``(4, 4)`` LiDAR -> camera 0, used to write camera-frame poses.
    P0 : np.ndarray
        ``(3, 4)`` projection matrix written to ``calib.txt``.
    source : str
        One line: where the path comes from.
    route : Route or None
        The generated route (None for a given trajectory).
    """

    times: np.ndarray
    T_w_velo: np.ndarray
    T_cam_velo: np.ndarray
    P0: np.ndarray
    source: str
    route: Route | None = None

    def key(self) -> str:
        """A digest of the positions (identifies the town built around the path)."""
        return hashlib.sha1(np.ascontiguousarray(self.T_w_velo[:, :3, 3]).tobytes()).hexdigest()


def route_path(route_seed: int = 0) -> SensorPath:
    """The generated route of ``route_seed`` with the synthetic rig's calibration."""
    route = generate_route(int(route_seed))
    return SensorPath(route.times, route.T_w_velo, rig.T_cam_velo(), rig.P0(),
                      f"the project's generated route, route seed {int(route_seed)}", route)


def _rebase(T: np.ndarray) -> np.ndarray:
    out = np.linalg.inv(T[0]) @ T
    out[:, 3] = [0.0, 0.0, 0.0, 1.0]
    return out


def _kitti_file(poses_file: Path, calib_file: Path | None, times_file: Path | None) -> SensorPath:
    from gr_graph.datasets.kitti import calib_T_cam_velo, read_calib
    from gr_graph.trajectory import read_kitti_poses, read_kitti_times

    T_w_cam = read_kitti_poses(poses_file)
    P0 = rig.P0()
    if calib_file is not None and calib_file.is_file():
        calib = read_calib(calib_file)
        Tr = calib_T_cam_velo(calib)
        if "P0" in calib:
            P0 = calib["P0"].reshape(3, 4)
        calib_note = f"Tr from {calib_file}"
    else:
        Tr = rig.T_cam_velo()
        calib_note = "the synthetic rig's Tr"
    if times_file is not None and times_file.is_file():
        times = read_kitti_times(times_file)
        if len(times) != len(T_w_cam):
            raise DatasetError(f"{times_file}: {len(times)} timestamps for {len(T_w_cam)} poses in {poses_file}")
        times = times - times[0]
    else:
        times = np.arange(len(T_w_cam)) * 0.1
    T_w_velo = _rebase(cam_to_velo_poses(T_w_cam, Tr))
    return SensorPath(times, T_w_velo, Tr, P0, f"trajectory {poses_file} (KITTI format, {calib_note})")


def trajectory_path(path: str | Path, seq: str = "00") -> SensorPath:
    """A given trajectory as a sensor path (see the module docstring for the formats).

    Raises
    ------
    DatasetError
        A missing file, an unknown format or unreadable rows (the message names the file).
    """
    from gr_graph.trajectory import TrajectoryFormatError, read_tum_poses

    p = Path(path).expanduser()
    try:
        if p.is_dir():
            poses = p / "poses" / f"{seq}.txt"
            if not poses.is_file():
                raise DatasetError(f"{p}: no poses/{seq}.txt (a KITTI root given as the trajectory)")
            sdir = p / "sequences" / seq
            return _kitti_file(poses, sdir / "calib.txt", sdir / "times.txt")
        if not p.is_file():
            raise DatasetError(f"{p}: trajectory file not found")
        first = next((ln.split() for ln in p.read_text().splitlines()
                      if ln.strip() and not ln.lstrip().startswith("#")), None)
        if first is None:
            raise DatasetError(f"{p}: the trajectory file is empty")
        if len(first) == 12:
            return _kitti_file(p, p.parent / "calib.txt", p.parent / "times.txt")
        if len(first) == 8:
            ts, T = read_tum_poses(p)
            return SensorPath(ts - ts[0], _rebase(T), rig.T_cam_velo(), rig.P0(),
                              f"trajectory {p} (TUM format, LiDAR poses)")
        raise DatasetError(f"{p}: {len(first)} columns; a trajectory is KITTI (12 floats a row) or "
                           "TUM (t x y z qx qy qz qw)")
    except TrajectoryFormatError as exc:
        raise DatasetError(str(exc)) from exc
