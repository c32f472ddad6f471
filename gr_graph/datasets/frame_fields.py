"""From decoded point fields to a :class:`~gr_graph.datasets.base.LidarFrame`: the conventions
a sequence fixes once, from its first frame (:class:`FieldConventions`).

- **Per-point time**: drivers store it in seconds (Velodyne ``time``, Hesai ``timestamp``),
  nanoseconds (Ouster ``t``, Livox) or microseconds, relative to the sweep or absolute. The
  unit is the power of 1000 that makes the first frame's time span closest to the frame
  spacing (a sweep lasts about one frame period); times become sweep fractions
  ``(t - t_min) / scan_period`` in ``[0, 1]`` (:func:`gr_graph.deskew.normalise_times`).
- **Rings**: the project numbers rings from the highest beam (0) down. Drivers differ (the
  Velodyne driver's ``ring`` 0 is the lowest beam, Ouster's the highest): when the median
  elevation of the first frame's rings rises with the ring number, rings are flipped
  (``n_rings - 1 - ring``). ``n_rings`` is the first frame's highest ring + 1 rounded up to
  16, 32, 64 or 128 when one of those is at most 25 % above; a later ring at or above it is an
  error naming the frame's source.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from gr_graph.datasets.base import DatasetError, LidarFrame
from gr_graph.datasets.pointcloud2 import DecodedCloud
from gr_graph.deskew import normalise_times

log = logging.getLogger(__name__)

TIME_UNITS_S = (1.0, 1e-3, 1e-6, 1e-9)
"""Candidate units of a per-point time field, in seconds (s, ms, us, ns)."""
COMMON_RING_COUNTS = (16, 32, 64, 128)
DEFAULT_FRAME_PERIOD_S = 0.1
"""Frame spacing assumed (10 Hz, the usual spinning-LiDAR rate) when no timestamps are known."""


def guess_time_unit(times: np.ndarray, frame_period: float) -> float:
    """The unit (seconds per stored unit) that makes the time span closest to ``frame_period``."""
    span = float(np.max(times) - np.min(times))
    if not span > 0.0:
        return 1.0
    errors = [abs(np.log(span * u / frame_period)) for u in TIME_UNITS_S]
    return TIME_UNITS_S[int(np.argmin(errors))]


def ring_count(max_ring: int) -> int:
    """``max_ring + 1`` rounded up to a common beam count when one is at most 25 % above."""
    n = int(max_ring) + 1
    for common in COMMON_RING_COUNTS:
        if n <= common <= 1.25 * n:
            return common
    return n


def rings_rise_with_elevation(points: np.ndarray, ring: np.ndarray) -> bool:
    """True when the median elevation of each ring grows with the ring number (ring 0 lowest)."""
    elevation = np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1]))
    ids = np.unique(ring)
    medians = np.array([np.median(elevation[ring == r]) for r in ids])
    if len(ids) < 2:
        return False
    return float(np.corrcoef(ids, medians)[0, 1]) > 0.0


@dataclass
class FieldConventions:
    """How a sequence turns decoded fields into frames (fixed by :meth:`probe` on the first frame).

    Attributes
    ----------
    has_time : bool
        The first frame has a per-point time field (and it spans more than 0).
    time_unit_s : float
        Seconds per unit of the time field.
    scan_period : float
        Sweep duration (s) that maps times to fractions.
    has_ring : bool
    n_rings : int
    flip_rings : bool
        Rings are numbered from the lowest beam and get flipped.
    """

    has_time: bool = False
    time_unit_s: float = 1.0
    scan_period: float = DEFAULT_FRAME_PERIOD_S
    has_ring: bool = False
    n_rings: int = 64
    flip_rings: bool = False

    @classmethod
    def probe(cls, cloud: DecodedCloud, frame_period: float, source: str) -> FieldConventions:
        """Conventions of a sequence whose first frame is ``cloud`` and frames ``frame_period`` s apart."""
        conv = cls(scan_period=float(frame_period))
        if cloud.time is not None and len(cloud.time) and np.ptp(cloud.time) > 0:
            conv.has_time = True
            conv.time_unit_s = guess_time_unit(cloud.time, frame_period)
            log.info("%s: per-point time field %r read in units of %g s (span %.4g s, frame period %.4g s)",
                     source, cloud.time_field, conv.time_unit_s, np.ptp(cloud.time) * conv.time_unit_s,
                     frame_period)
        elif cloud.time is not None:
            log.warning("%s: per-point time field %r is constant: ignored", source, cloud.time_field)
        if cloud.ring is not None and len(cloud.ring):
            conv.has_ring = True
            conv.n_rings = ring_count(int(cloud.ring.max()))
            conv.flip_rings = rings_rise_with_elevation(cloud.points, cloud.ring)
            if conv.flip_rings:
                log.info("%s: ring 0 is the lowest beam: rings flipped to number from the highest", source)
        return conv

    def frame(self, cloud: DecodedCloud, index: int, timestamp: float, source: str) -> LidarFrame:
        """The frame of ``cloud`` under these conventions."""
        n = len(cloud.points)
        time = None
        if self.has_time:
            if cloud.time is None:
                raise DatasetError(f"{source}: no per-point time field, but the sequence's first frame has one")
            time = normalise_times(cloud.time * self.time_unit_s, self.scan_period)
        ring = None
        if self.has_ring:
            if cloud.ring is None:
                raise DatasetError(f"{source}: no ring field, but the sequence's first frame has one")
            if n and int(cloud.ring.max()) >= self.n_rings:
                raise DatasetError(f"{source}: ring {int(cloud.ring.max())} >= {self.n_rings} rings "
                                   "(from the first frame)")
            r = (self.n_rings - 1 - cloud.ring) if self.flip_rings else cloud.ring
            ring = r.astype(np.int16)
        intensity = cloud.intensity if cloud.intensity is not None else np.zeros(n, np.float32)
        return LidarFrame(index=index, timestamp=float(timestamp), points=cloud.points,
                          intensity=intensity.astype(np.float32, copy=False), ring=ring,
                          n_rings=self.n_rings, dropped_nonfinite=cloud.dropped_nonfinite, time=time)


def frame_period(timestamps: np.ndarray) -> float:
    """Median spacing of increasing timestamps (s); :data:`DEFAULT_FRAME_PERIOD_S` for < 2 frames."""
    ts = np.asarray(timestamps, np.float64)
    if len(ts) < 2:
        return DEFAULT_FRAME_PERIOD_S
    period = float(np.median(np.diff(ts)))
    return period if period > 0 else DEFAULT_FRAME_PERIOD_S
