"""Laser-ring recovery for KITTI scans and channel subsampling 64 -> 32 -> 16.

KITTI ``.bin`` files carry no ring index, but their points are stored scan line by scan
line, each line one full turn of the sensor. Splitting where the azimuth wraps around
over-counts (the azimuth jitters across +-pi inside a line: about 69 breaks for 64 rings
in frame 0 of sequence 00). We instead *unwrap* the azimuth along the storage order, so
that jitter cancels and the unwrapped angle grows by one turn per line; a point's line is
the number of whole turns swept since azimuth 0, where every line starts (on the real
KITTI 00 frames the azimuth crosses 0 exactly where the elevation steps to the next beam;
the first point of a scan need not lie at 0 when the top beam has no return ahead).

The elevation angle then checks the result and numbers the lines: the lines' median
elevations must be strictly ordered along the storage order (KITTI stores the beams top
to bottom), and the lines are numbered by elevation, 0 = highest beam. Per-point elevation
alone cannot classify rings: the HDL-64E's lasers sit off the sensor origin, so within one
line the elevation seen from the origin spreads by about 0.3 deg, as much as the spacing
between beams.

The paper makes its 32- and 16-channel scans by keeping every 2nd / 4th of the 64 rings.
"""

from __future__ import annotations

import numpy as np

from gr_graph.datasets.base import DatasetError, LidarFrame

SUPPORTED_CHANNELS = (64, 32, 16)
_TWO_PI = 2.0 * np.pi
_START_TOLERANCE = np.radians(1.0)  # a line may start this far short of azimuth 0


class RingRecoveryError(DatasetError):
    """The scan lines of a scan could not be told apart."""


def elevation_deg(points: np.ndarray) -> np.ndarray:
    """Elevation angle of each point in degrees (0 = horizontal, positive up)."""
    r = np.linalg.norm(points, axis=1)
    return np.degrees(np.arcsin(np.clip(points[:, 2] / np.maximum(r, 1e-12), -1.0, 1.0)))


def recover_rings(points: np.ndarray, n_rings: int = 64) -> np.ndarray:
    """Recover the laser ring of every point of a KITTI-ordered scan.

    Parameters
    ----------
    points : (N, 3) array
        Points in storage order (as read from a KITTI ``.bin``), LiDAR frame.
    n_rings : int
        Number of laser rings of the sensor (64 for KITTI's HDL-64E).

    Returns
    -------
    np.ndarray
        ``(N,)`` int16 ring index, 0 = highest elevation.

    Raises
    ------
    RingRecoveryError
        If the scan does not hold ``n_rings`` lines, or the lines' elevations are not
        ordered along the storage order (e.g. the points were shuffled or cropped), so
        that no honest ring index can be given.
    """
    n = len(points)
    if n < 2 * n_rings:
        raise RingRecoveryError(f"{n} points are too few to hold {n_rings} scan lines")
    azimuth = np.arctan2(points[:, 1], points[:, 0])
    unwrapped = np.unwrap(azimuth)
    direction = 1.0 if unwrapped[-1] >= unwrapped[0] else -1.0
    # Lines start facing forward (azimuth 0), as in KITTI. Count turns from there, not from
    # the first point: when the top beam has no return straight ahead, the first point lies
    # further round, and counting from it would push the next lines' first points into the
    # line above. A first point a hair short of 0 (jitter) belongs to line 0 as well.
    start = np.mod(direction * azimuth[0] + _START_TOLERANCE, _TWO_PI) - _START_TOLERANCE
    turns = (direction * (unwrapped - unwrapped[0]) + start) / _TWO_PI
    line = np.maximum.accumulate(np.maximum(np.floor(turns), 0).astype(np.int64))
    n_lines = int(line[-1]) + 1
    if n_lines != n_rings:
        raise RingRecoveryError(
            f"found {n_lines} scan lines where {n_rings} were expected "
            f"(total sweep {turns[-1]:.2f} turns); are the points in sensor order?"
        )
    bounds = np.concatenate([np.searchsorted(line, np.arange(n_rings)), [n]])
    elev = elevation_deg(points)
    medians = np.array([np.median(elev[bounds[k] : bounds[k + 1]]) for k in range(n_rings)])
    steps = np.diff(medians)
    if not (np.all(steps < 0) or np.all(steps > 0)):
        bad = int(np.argmax(np.sign(steps) != np.sign(steps[0])))
        raise RingRecoveryError(
            f"scan lines {bad} and {bad + 1} are not ordered by elevation "
            f"({medians[bad]:.2f} vs {medians[bad + 1]:.2f} deg); are the points in sensor order?"
        )
    order = np.argsort(-medians, kind="stable")  # highest beam first
    rank = np.empty(n_rings, np.int64)
    rank[order] = np.arange(n_rings)
    return rank[line].astype(np.int16)


def subsample_channels(frame: LidarFrame, channels: int) -> LidarFrame:
    """Keep every ``n_rings // channels``-th ring of a frame (the paper's 64 -> 32 -> 16).

    Parameters
    ----------
    frame : LidarFrame
        A frame with ring indices (``frame.ring`` not None).
    channels : int
        Number of rings to keep; must divide ``frame.n_rings``.

    Returns
    -------
    LidarFrame
        The frame with rings ``0, s, 2s, ...`` kept (``s = n_rings // channels``),
        renumbered ``0..channels-1``, and ``n_rings == channels``.
    """
    if channels == frame.n_rings:
        return frame
    if frame.ring is None:
        raise DatasetError(f"frame {frame.index}: no ring indices, cannot subsample to {channels} channels")
    if channels <= 0 or frame.n_rings % channels:
        raise DatasetError(f"cannot subsample {frame.n_rings} rings to {channels} channels")
    stride = frame.n_rings // channels
    keep = (frame.ring % stride) == 0
    sub = frame.select(keep, n_rings=channels)
    return LidarFrame(
        index=sub.index,
        timestamp=sub.timestamp,
        points=sub.points,
        intensity=sub.intensity,
        ring=(sub.ring // stride).astype(np.int16),
        n_rings=channels,
        dropped_nonfinite=sub.dropped_nonfinite,
        time=sub.time,
    )
