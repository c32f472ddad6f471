"""The interface every LiDAR sequence implements (KITTI on disk, the synthetic renderer).

A sequence is a random-access, streaming collection of :class:`LidarFrame`. Frames are
produced on demand (read from disk or rendered); nothing holds a whole sequence of raw
scans in memory.

Frame conventions
-----------------
- ``points`` are in the LiDAR (velodyne) frame, ``float64`` of shape ``(N, 3)``, finite.
- ``intensity`` is ``float32`` of shape ``(N,)`` (reflectance in [0, 1] for KITTI).
- ``ring`` is the laser index ``0..n_rings-1`` ordered from the *highest* elevation beam
  (0) to the lowest, ``int16`` of shape ``(N,)``; ``None`` when unknown.
- ``time`` is each point's measurement time as a fraction of the sweep, ``float64`` in
  ``[0, 1]`` of shape ``(N,)`` (0 = the sweep's start, not the frame's earliest point: a
  partial sweep keeps its place in the sweep; loaders convert seconds or stamps with
  :func:`gr_graph.deskew.normalise_times`, see :mod:`gr_graph.datasets.frame_fields`); ``None``
  when the data has none or ``sensor.has_time`` is false (the odometry then derives it from
  the azimuth when it deskews).

Sequence attributes
-------------------
- ``motion_compensated`` (optional, default True when absent): whether the scans are
  already free of motion distortion (KITTI odometry scans were compensated with the
  vehicle's GPS/IMU). ``odometry.deskew: auto`` deskews exactly the sequences that say False.
- ``scan_period`` (optional): the sweep duration in seconds; without it the odometry takes
  the spacing of the frame timestamps.
- ``sensor`` (optional): a :class:`gr_graph.sensors.SensorConfig` naming the sensor that took
  the scans; SLAM refuses to run a configuration whose ``sensor`` section names another one.

Pose conventions
----------------
- ``gt_poses`` are ``T_w_velo`` (LiDAR frame to world), ``(K, 4, 4)`` float64, where the
  world is the LiDAR frame of scan 0. ``None`` when the sequence has no ground truth.
- ``T_cam_velo`` (KITTI's ``Tr``) maps LiDAR coordinates to camera-0 coordinates; camera-
  frame poses are ``T_w_cam = T_cam_velo @ T_w_velo @ inv(T_cam_velo)``.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from typing import Any, Protocol, runtime_checkable

import numpy as np

log = logging.getLogger(__name__)


class DatasetError(ValueError):
    """Raised for malformed or missing dataset files; the message names the file."""


@dataclass(frozen=True)
class LidarFrame:
    """One LiDAR scan.

    Attributes
    ----------
    index : int
        Frame index within its sequence.
    timestamp : float
        Seconds since the sequence's first stamp (folders and bags whose stamps were moved to the
        sweeps' middles start at that offset, e.g. +-0.05 s: :mod:`gr_graph.datasets.stamp_shift`).
    points : np.ndarray
        ``(N, 3)`` float64 points in the LiDAR frame.
    intensity : np.ndarray
        ``(N,)`` float32 reflectance.
    ring : np.ndarray or None
        ``(N,)`` int16 laser index (0 = highest beam), or None if unknown.
    n_rings : int
        Number of rings of the sensor this frame was taken (or subsampled) with.
    dropped_nonfinite : int
        Number of points removed when the frame was loaded: a non-finite coordinate, or exactly
        the origin, how organized clouds mark a beam without a return.
    time : np.ndarray or None
        ``(N,)`` float64 per-point sweep fraction in ``[0, 1]``, or None if the data has none.
    """

    index: int
    timestamp: float
    points: np.ndarray
    intensity: np.ndarray
    ring: np.ndarray | None = None
    n_rings: int = 64
    dropped_nonfinite: int = 0
    time: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = len(self.points)
        if self.points.ndim != 2 or self.points.shape[1] != 3:
            raise DatasetError(f"frame {self.index}: points must be (N, 3), got {self.points.shape}")
        if self.intensity.shape != (n,):
            raise DatasetError(f"frame {self.index}: intensity shape {self.intensity.shape} != ({n},)")
        if self.ring is not None and self.ring.shape != (n,):
            raise DatasetError(f"frame {self.index}: ring shape {self.ring.shape} != ({n},)")
        if self.time is not None:
            if self.time.shape != (n,):
                raise DatasetError(f"frame {self.index}: time shape {self.time.shape} != ({n},)")
            if n and not (np.all(np.isfinite(self.time)) and self.time.min() >= 0.0 and self.time.max() <= 1.0):
                raise DatasetError(f"frame {self.index}: per-point times must be finite sweep fractions in [0, 1] "
                                   "(convert seconds with gr_graph.deskew.normalise_times)")

    def __len__(self) -> int:
        return len(self.points)

    def select(self, mask: np.ndarray, n_rings: int | None = None) -> "LidarFrame":
        """Return a frame holding only the points where ``mask`` (bool or index array) selects."""
        return replace(
            self,
            points=self.points[mask],
            intensity=self.intensity[mask],
            ring=None if self.ring is None else self.ring[mask],
            time=None if self.time is None else self.time[mask],
            n_rings=self.n_rings if n_rings is None else n_rings,
        )


@runtime_checkable
class LidarSequence(Protocol):
    """A streaming, random-access LiDAR sequence (see the module docstring for frames)."""

    name: str
    timestamps: np.ndarray
    gt_poses: np.ndarray | None
    T_cam_velo: np.ndarray

    def __len__(self) -> int: ...

    def __getitem__(self, index: int) -> LidarFrame: ...

    def __iter__(self) -> Iterator[LidarFrame]: ...


def is_motion_compensated(sequence: Any) -> bool:
    """A sequence's ``motion_compensated`` attribute; True when it has none (see the module docstring)."""
    return bool(getattr(sequence, "motion_compensated", True))


def inherit_sweep_attributes(view: Any, parent: Any) -> None:
    """Give a view of ``parent`` (a frame subset, densified scans) the parent's sweep attributes:
    ``motion_compensated`` and, when the parent has them, ``scan_period``, ``sensor`` and
    ``stamps_moved_by_s`` (:mod:`gr_graph.datasets.stamp_shift`)."""
    view.motion_compensated = is_motion_compensated(parent)
    if getattr(parent, "stamps_moved_by_s", None) is not None:
        view.stamps_moved_by_s = float(parent.stamps_moved_by_s)
    if getattr(parent, "scan_period", None) is not None:
        view.scan_period = float(parent.scan_period)
    if getattr(parent, "sensor", None) is not None:
        view.sensor = parent.sensor


def find_in_chain(sequence: Any, attribute: str, accept: Callable[[Any], bool] = callable) -> Any:
    """The first of ``sequence``, its ``parent``, the parent's parent, ... whose ``attribute``
    passes ``accept`` (default: is callable), or None."""
    seen: set[int] = set()
    while sequence is not None and id(sequence) not in seen:
        seen.add(id(sequence))
        if accept(getattr(sequence, attribute, None)):
            return sequence
        sequence = getattr(sequence, "parent", None)
    return None


def release_render_cache(sequence: Any) -> bool:
    """Free what ``sequence`` (or the sequence it is a view of, through ``parent``) keeps in
    memory to make frames, e.g. the synthetic town and its ray-casting scene: the optional
    method ``release_cache()``. Frames read later are made again, identical. Returns whether
    anything was freed."""
    owner = find_in_chain(sequence, "release_cache")
    return False if owner is None else bool(owner.release_cache())


def increasing_stamps(stamps_ns: np.ndarray, source: str) -> np.ndarray:
    """``stamps_ns`` (int64 ns) with every stamp not after its predecessor moved to the
    predecessor plus the median forward spacing (a repeated or backward line of a driver's
    timestamps file): the trajectory files need increasing times, and a run must not fail over
    them after SLAM. Logged with the count and the first lines (1-based); unchanged when they
    increase."""
    t = np.asarray(stamps_ns, np.int64).copy()
    step = np.diff(t)
    if len(t) < 2 or np.all(step > 0):
        return t
    forward = step[step > 0]
    spacing = int(np.median(forward)) if len(forward) else 100_000_000  # 0.1 s when no two increase
    fixed = []
    for k in range(1, len(t)):
        if t[k] <= t[k - 1]:
            t[k] = t[k - 1] + spacing
            fixed.append(k)
    log.warning("%s: %d timestamp%s not after the one before (line%s %s): set to the previous one + %.4g s",
                source, len(fixed), "s" if len(fixed) > 1 else "", "s" if len(fixed) > 1 else "",
                ", ".join(str(k + 1) for k in fixed[:5]) + (", ..." if len(fixed) > 5 else ""), spacing * 1e-9)
    return t


def check_index(index: int, length: int, name: str) -> int:
    """Normalise a (possibly negative) frame index, raising ``IndexError`` when out of range."""
    i = int(index)
    if i < 0:
        i += length
    if not 0 <= i < length:
        raise IndexError(f"{name}: frame {index} out of range for {length} frames")
    return i


def velo_to_cam_poses(T_w_velo: np.ndarray, T_cam_velo: np.ndarray) -> np.ndarray:
    """Express LiDAR-frame poses ``(K, 4, 4)`` in the camera-0 frame (KITTI's convention)."""
    return T_cam_velo @ T_w_velo @ np.linalg.inv(T_cam_velo)


def cam_to_velo_poses(T_w_cam: np.ndarray, T_cam_velo: np.ndarray) -> np.ndarray:
    """Express camera-0-frame poses ``(K, 4, 4)`` in the LiDAR frame: ``Tr⁻¹ · T_w_cam · Tr``."""
    return np.linalg.inv(T_cam_velo) @ T_w_cam @ T_cam_velo
