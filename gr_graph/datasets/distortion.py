"""Motion-distorted views of an undistorted sequence (what a moving spinning LiDAR measures).

:class:`MotionDistortedSequence` takes a sequence whose frames are undistorted (every point in
the sensor frame at mid-sweep, e.g. the synthetic renderer, which casts every ray from the
frame's pose) and ground-truth poses that refer to the middle of the sweep, and returns the
frames a sensor sweeping for ``scan_period`` seconds would have measured: a point at sweep
fraction ``t`` is expressed in the sensor frame at time ``t_k + (t - 0.5) * scan_period``,
the pose being interpolated along the ground-truth trajectory (geodesically between frame k
and its neighbour on that side; extrapolated at the ends of the sequence).

Per-point times come from the azimuth of the *measured* point (a sensor fires by its own
azimuth), found by a fixed-point iteration started from the undistorted azimuth.

Two variants:

- ``compensation_velocity_noise=None`` (``raw``): the full distortion, per-point times in
  ``LidarFrame.time``, ``motion_compensated = False`` (the odometry's ``deskew: auto``
  deskews it), like KITTI raw drives or bags with per-point time;
- a number (``compensated``): the distorted frame is then compensated to mid-sweep with
  the true constant velocity (central difference of the ground truth) plus Gaussian errors
  of ``compensation_velocity_noise`` m/s and ``compensation_rate_noise_deg`` deg/s per axis,
  leaving the residual distortion of an imperfect GPS/IMU compensation, no per-point times,
  ``motion_compensated = True``, like KITTI odometry folders.

A true per-point-time render (rays cast from the interpolated poses) can replace this
wrapper; it keeps the interface of a :class:`~gr_graph.datasets.base.LidarSequence`.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace

import numpy as np

from factors.se3 import exp_se3, log_se3
from gr_graph.datasets.base import DatasetError, LidarFrame, LidarSequence, check_index
from gr_graph.deskew import deskew, distort, sweep_motion_from_velocity, times_from_azimuth

__all__ = ["MotionDistortedSequence", "distort_with_trajectory"]

_AZIMUTH_ITERATIONS = 5


def _segment_motion(poses: np.ndarray, stamps: np.ndarray, a: int, b: int, scan_period: float) -> np.ndarray:
    """The sweep motion (start -> end, ``scan_period`` long) of the constant velocity from pose a to b."""
    return sweep_motion_from_velocity(np.linalg.inv(poses[a]) @ poses[b], float(stamps[b] - stamps[a]),
                                      scan_period)


def distort_with_trajectory(points: np.ndarray, times: np.ndarray, poses: np.ndarray, stamps: np.ndarray,
                            k: int, scan_period: float) -> np.ndarray:
    """Points of frame ``k`` (sensor frame at mid-sweep) as measured at their own times.

    Points with ``t >= 0.5`` move along the geodesic from pose k to pose k+1, the others
    along the one from k-1 to k (extrapolated past the first and last frames).

    Parameters
    ----------
    points : (N, 3) array
        Undistorted points of frame k.
    times : (N,) array
        Sweep fractions in ``[0, 1]``.
    poses : (K, 4, 4) array
        Mid-sweep sensor poses (any world frame).
    stamps : (K,) array
        Their times [s].
    k : int
    scan_period : float
        Sweep duration [s].
    """
    K = len(poses)
    if K < 2:
        raise DatasetError("motion distortion needs at least two poses")
    after = (k, k + 1) if k + 1 < K else (k - 1, k)
    before = (k - 1, k) if k >= 1 else (k, k + 1)
    out = np.empty_like(np.asarray(points, np.float64))
    late = times >= 0.5
    for mask, (a, b) in ((late, after), (~late, before)):
        if np.any(mask):
            out[mask] = distort(points[mask], times[mask], _segment_motion(poses, stamps, a, b, scan_period))
    return out


class MotionDistortedSequence:
    """``sequence`` as a moving LiDAR sweeping for ``scan_period`` seconds measures it (module docstring).

    Parameters
    ----------
    sequence : LidarSequence
        Undistorted frames with ground truth (``gt_poses``, mid-sweep) and ``timestamps``.
    scan_period : float
        Sweep duration [s] (KITTI's HDL-64E: 0.1).
    compensation_velocity_noise : float, optional
        None: the ``raw`` variant (full distortion, per-point times). A number: compensate
        with the true velocity plus this Gaussian error per axis [m/s].
    compensation_rate_noise_deg : float
        Gaussian error per axis of the compensating angular rate [deg/s] (compensated variant).
    seed : int
        Seeds the compensation errors (per frame from ``(seed, index)``).
    clockwise : bool
        Spin direction (Velodyne: clockwise seen from above).
    """

    def __init__(self, sequence: LidarSequence, scan_period: float = 0.1,
                 compensation_velocity_noise: float | None = None, compensation_rate_noise_deg: float = 0.0,
                 seed: int = 0, clockwise: bool = True) -> None:
        if sequence.gt_poses is None:
            raise DatasetError(f"{sequence.name}: motion distortion needs ground-truth poses")
        if not scan_period > 0.0:
            raise ValueError(f"scan_period must be > 0, got {scan_period}")
        if compensation_velocity_noise is not None and compensation_velocity_noise < 0.0:
            raise ValueError(f"compensation_velocity_noise must be >= 0, got {compensation_velocity_noise}")
        if compensation_rate_noise_deg < 0.0:
            raise ValueError(f"compensation_rate_noise_deg must be >= 0, got {compensation_rate_noise_deg}")
        self.parent = sequence
        self.scan_period = float(scan_period)
        self.compensation_velocity_noise = compensation_velocity_noise
        self.compensation_rate_noise_deg = float(compensation_rate_noise_deg)
        self.seed = int(seed)
        self.clockwise = clockwise
        self.raw = compensation_velocity_noise is None
        self.motion_compensated = not self.raw
        self.name = f"{sequence.name}-{'raw' if self.raw else 'compensated'}"
        self.timestamps = np.asarray(sequence.timestamps, np.float64)
        self.gt_poses = np.asarray(sequence.gt_poses, np.float64)
        self.T_cam_velo = sequence.T_cam_velo

    def __len__(self) -> int:
        return len(self.parent)

    def measure(self, frame: LidarFrame, k: int) -> tuple[np.ndarray, np.ndarray]:
        """The distorted points of undistorted frame ``k`` and their sweep fractions."""
        p = frame.points
        times = times_from_azimuth(p, self.clockwise)
        for _ in range(_AZIMUTH_ITERATIONS):  # the sensor fires by the azimuth it measures
            measured = distort_with_trajectory(p, times, self.gt_poses, self.timestamps, k, self.scan_period)
            times = times_from_azimuth(measured, self.clockwise)
        measured = distort_with_trajectory(p, times, self.gt_poses, self.timestamps, k, self.scan_period)
        return measured, times

    def compensation_motion(self, k: int) -> np.ndarray:
        """The (noisy) sweep motion an imperfect compensation of frame ``k`` uses."""
        K = len(self)
        a, b = max(k - 1, 0), min(k + 1, K - 1)
        xi = log_se3(_segment_motion(self.gt_poses, self.timestamps, a, b, self.scan_period))
        rng = np.random.default_rng([self.seed, int(k), 0xDE5C])
        xi[:3] += np.radians(self.compensation_rate_noise_deg) * self.scan_period * rng.standard_normal(3)
        xi[3:] += float(self.compensation_velocity_noise or 0.0) * self.scan_period * rng.standard_normal(3)
        return exp_se3(xi)

    def __getitem__(self, index: int) -> LidarFrame:
        k = check_index(index, len(self), self.name)
        frame = self.parent[k]
        measured, times = self.measure(frame, k)
        if self.raw:
            return replace(frame, points=measured, time=times)
        return replace(frame, points=deskew(measured, times, self.compensation_motion(k)), time=None)

    def __iter__(self) -> Iterator[LidarFrame]:
        for i in range(len(self)):
            yield self[i]
