"""Laser-ring recovery for KITTI scans and channel subsampling 64 -> 32 -> 16.

KITTI ``.bin`` files carry no ring index, but their points are stored scan line by scan
line, each line one full turn of the sensor. Splitting where the azimuth wraps around
over-counts (the azimuth jitters across +-pi inside a line: about 69 breaks for 64 rings
in frame 0 of sequence 00). We instead *unwrap* the azimuth along the storage order, so
that jitter cancels and the unwrapped angle grows by one turn per line; a point's line is
the number of whole turns swept since azimuth 0, where every line starts (on the real
KITTI 00 frames the azimuth crosses 0 exactly where the elevation steps to the next beam;
the first point of a scan need not lie at 0 when the top beam has no return ahead).

The elevation angle then checks the result: the lines' median elevations must run from
top to bottom along the storage order (KITTI stores the beams top to bottom), up to
:data:`ORDER_TOLERANCE_DEG` between adjacent lines (interleaved lasers put some adjacent
lines a few hundredths of a degree apart, in either order); ring 0 is the highest beam.
Frames that fail this (a partial last sweep, lines out of order) are matched against a
reference of per-ring elevations from other frames (:class:`RingIndexer`). Per-point elevation
alone cannot classify rings: the HDL-64E's lasers sit off the sensor origin, so within one
line the elevation seen from the origin spreads by about 0.3 deg, as much as the spacing
between beams.

The paper makes its 32- and 16-channel scans by keeping every 2nd / 4th of the 64 rings.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from gr_graph.datasets.base import DatasetError, LidarFrame

SUPPORTED_CHANNELS = (64, 32, 16)
_TWO_PI = 2.0 * np.pi
_START_TOLERANCE = np.radians(1.0)  # a line may start this far short of azimuth 0
ORDER_TOLERANCE_DEG = 0.1
"""Adjacent lines out of elevation order by up to this much are accepted in storage order.
Real KITTI 00 frames: adjacent ring medians are >= 0.22 deg apart and move by <= 0.1 deg
between frames; on another drive adjacent lines were 0.01-0.05 deg apart or swapped."""
REFERENCE_MAX_RESIDUAL_DEG = 0.1
"""Strategy 2 accepts a block of reference rings whose median residual is at most this."""
REFERENCE_MIN_MARGIN = 2.0
"""... and whose residual is at least this many times smaller than the next best block's."""
REFERENCE_MIN_LINE_FRACTION = 0.5
"""... and only for a frame with more lines than this fraction of the reference rings: a block of a
few lines fits many places (a half-azimuth sweep, whose azimuth does not wrap, is one "line")."""
REFERENCE_FRAMES = 5
"""Probe frames indexed in storage order whose ring medians make the reference (their median)."""
PROBE_FRAMES = 12
"""Other frames a :class:`RingIndexer` reads at most to build a reference when it needs one."""


class RingRecoveryError(DatasetError):
    """The scan lines of a scan could not be told apart."""


def elevation_deg(points: np.ndarray) -> np.ndarray:
    """Elevation angle of each point in degrees (0 = horizontal, positive up)."""
    r = np.linalg.norm(points, axis=1)
    return np.degrees(np.arcsin(np.clip(points[:, 2] / np.maximum(r, 1e-12), -1.0, 1.0)))


def scan_lines(points: np.ndarray) -> tuple[np.ndarray, int, np.ndarray]:
    """Split a scan stored line by line into its lines by unwrapping the azimuth.

    Parameters
    ----------
    points : (N, 3) array
        Points in storage order, LiDAR frame.

    Returns
    -------
    line : np.ndarray
        ``(N,)`` int64 line of each point, 0 = first line in storage order.
    n_lines : int
        Number of lines found.
    turns : np.ndarray
        ``(N,)`` turns swept since azimuth 0 (for messages).
    """
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
    return line, int(line[-1]) + 1, turns


def line_elevations(points: np.ndarray, line: np.ndarray, n_lines: int) -> np.ndarray:
    """Median elevation (degrees) of each of ``n_lines`` contiguous lines."""
    bounds = np.concatenate([np.searchsorted(line, np.arange(n_lines)), [len(line)]])
    elev = elevation_deg(points)
    return np.array([np.median(elev[bounds[k] : bounds[k + 1]]) if bounds[k + 1] > bounds[k] else np.nan
                     for k in range(n_lines)])


def recover_rings(points: np.ndarray, n_rings: int = 64, order_tolerance_deg: float = ORDER_TOLERANCE_DEG,
                  reference_elevations: np.ndarray | None = None) -> np.ndarray:
    """Recover the laser ring of every point of a KITTI-ordered scan.

    Two strategies, tried in turn:

    1. *storage order*: the scan holds exactly ``n_rings`` lines whose median elevations
       run from top to bottom along the storage order. Adjacent lines may be out of order
       by up to ``order_tolerance_deg`` (the HDL-64E's interleaved lasers put neighbouring
       lines 0.01-0.05 deg apart, and per-laser offsets can swap them): the storage order,
       not the elevation, then numbers the lines.
    2. *reference*: given the sensor's per-ring median elevations (e.g. from earlier
       frames of the sequence, :class:`RingIndexer`), a scan with fewer lines (a partial
       sweep: the last frame of a recording) or with lines out of order beyond the
       tolerance is matched to a contiguous block of reference rings; accepted when the
       frame has more than :data:`REFERENCE_MIN_LINE_FRACTION` of the reference's lines,
       the best block fits to :data:`REFERENCE_MAX_RESIDUAL_DEG` (median) and clearly beats
       the next best. (A frame cut in azimuth, e.g. the front half only, has no azimuth
       wrap between its lines and shows as one or a few "lines": refused here,
       :class:`RingIndexer` then takes rings from per-point elevation.)

    Parameters
    ----------
    points : (N, 3) array
        Points in storage order (as read from a KITTI ``.bin``), LiDAR frame.
    n_rings : int
        Number of laser rings of the sensor (64 for KITTI's HDL-64E).
    order_tolerance_deg : float
        Largest elevation inversion between adjacent lines that strategy 1 accepts.
    reference_elevations : (n_rings,) array, optional
        Median elevation of each ring, ring 0 highest; enables strategy 2.

    Returns
    -------
    np.ndarray
        ``(N,)`` int16 ring index, 0 = highest elevation.

    Raises
    ------
    RingRecoveryError
        If neither strategy gives an honest ring index (e.g. the points were shuffled, or
        a scan is cropped and no reference is given).
    """
    return recover_rings_with_method(points, n_rings, order_tolerance_deg, reference_elevations)[0]


def recover_rings_with_method(points: np.ndarray, n_rings: int = 64,
                              order_tolerance_deg: float = ORDER_TOLERANCE_DEG,
                              reference_elevations: np.ndarray | None = None) -> tuple[np.ndarray, str]:
    """:func:`recover_rings`, also naming the strategy that worked (``"storage_order"`` or ``"reference"``)."""
    n = len(points)
    if n < 2 * n_rings:
        raise RingRecoveryError(f"{n} points are too few to hold {n_rings} scan lines")
    line, n_lines, turns = scan_lines(points)
    if n_lines > n_rings:
        raise RingRecoveryError(
            f"found {n_lines} scan lines where {n_rings} were expected "
            f"(total sweep {turns[-1]:.2f} turns); are the points in sensor order?"
        )
    medians = line_elevations(points, line, n_lines)
    problem = ""
    if n_lines == n_rings:
        steps = np.diff(medians)
        descending = medians[-1] < medians[0]
        inversions = steps if descending else -steps  # > 0: a line above the one before it
        worst = int(np.argmax(inversions))
        if inversions[worst] <= order_tolerance_deg:
            ring = line if descending else (n_rings - 1) - line
            return ring.astype(np.int16), "storage_order"
        problem = (f"scan lines {worst} and {worst + 1} are not ordered by elevation "
                   f"({medians[worst]:.2f} vs {medians[worst + 1]:.2f} deg)")
    else:
        problem = (f"found {n_lines} scan lines where {n_rings} were expected "
                   f"(total sweep {turns[-1]:.2f} turns)")
    if reference_elevations is None:
        raise RingRecoveryError(f"{problem}; are the points in sensor order?")
    offset = _match_reference(medians, np.asarray(reference_elevations, np.float64), problem)
    descending = n_lines < 2 or medians[-1] < medians[0]
    ring = offset + (line if descending else (n_lines - 1) - line)
    return ring.astype(np.int16), "reference"


def _match_reference(medians: np.ndarray, reference: np.ndarray, problem: str) -> int:
    """Offset o such that the lines (top to bottom) are rings o, o+1, ...; raise if unclear
    (too few lines to place, :data:`REFERENCE_MIN_LINE_FRACTION`, or no clear best block)."""
    n_lines, n_rings = len(medians), len(reference)
    if n_lines <= REFERENCE_MIN_LINE_FRACTION * n_rings:
        raise RingRecoveryError(
            f"{problem}; too few lines to match to the {n_rings} reference rings (need more than "
            f"{int(REFERENCE_MIN_LINE_FRACTION * n_rings)}: is the scan cut in azimuth?)"
        )
    top_down = medians if n_lines < 2 or medians[-1] < medians[0] else medians[::-1]
    fits = np.array([np.nanmedian(np.abs(top_down - reference[o : o + n_lines]))
                     for o in range(n_rings - n_lines + 1)])
    order = np.argsort(fits, kind="stable")
    best = int(order[0])
    second = float(fits[order[1]]) if len(order) > 1 else np.inf
    if not fits[best] <= REFERENCE_MAX_RESIDUAL_DEG or not second >= REFERENCE_MIN_MARGIN * fits[best]:
        raise RingRecoveryError(
            f"{problem}, and the lines match no block of the reference rings (best fit rings "
            f"{best}..{best + n_lines - 1}, median residual {fits[best]:.3f} deg, next {second:.3f} deg)"
        )
    return best


class RingIndexer:
    """Ring indices for every frame of a sequence, with a counted fallback (never an error).

    Frames whose lines are found in order are indexed by :func:`recover_rings` strategy 1.
    The first frame that strategy 1 cannot index makes the indexer build a reference of
    per-ring median elevations from fixed probe frames of the same sequence
    (``reference_source``; the per-ring median over up to :data:`REFERENCE_FRAMES` probes
    that strategy 1 indexes), so the reference, and every ring index, does not depend on
    the order in which frames are read. Such frames are matched against the reference
    (strategy 2) when they have most of the reference's lines. A frame with every line but
    stored out of elevation order (e.g. laser-id order) numbers its lines by their median
    elevation (``"line_rank"``). A frame none of these indexes (e.g. shuffled points, or a sweep
    cut in azimuth, whose lines cannot be split) gets rings from per-point elevation (``"elevation"``: nearest reference ring, or
    equal-count elevation bins without a reference): approximate, logged by the caller and
    counted in :attr:`counts`, so that a whole run is never refused for one odd frame.

    Parameters
    ----------
    n_rings : int
        Rings of the sensor.
    reference_source : callable, optional
        ``reference_source(k)`` returns the points of the k-th probe frame (k = 0, 1, ...,
        :data:`PROBE_FRAMES` - 1; None when the sequence has no more), e.g. frames spread
        evenly over the sequence.
    """

    def __init__(self, n_rings: int = 64, reference_source=None) -> None:
        self.n_rings = n_rings
        self.reference_source = reference_source
        self.counts: dict[str, int] = {"storage_order": 0, "reference": 0, "line_rank": 0, "elevation": 0}
        self.reference: np.ndarray | None = None
        """Per-ring median elevation (deg, ring 0 highest) of the probe frames; None until probed."""
        self._probed = False

    def _probe(self) -> None:
        """Build a reference from other frames of the sequence (once)."""
        if self._probed or self.reference_source is None:
            return
        self._probed = True
        samples: list[np.ndarray] = []
        for k in range(PROBE_FRAMES):
            pts = self.reference_source(k)
            if pts is None:
                break
            try:
                ring = recover_rings(pts, self.n_rings)
            except RingRecoveryError:
                continue
            elev = elevation_deg(pts)
            samples.append(np.array([np.median(elev[ring == r]) for r in range(self.n_rings)]))
            if len(samples) >= REFERENCE_FRAMES:
                break
        if samples:
            self.reference = np.median(np.stack(samples), axis=0)

    def __call__(self, points: np.ndarray) -> tuple[np.ndarray, str, str]:
        """``(ring, method, problem)`` for one frame; ``problem`` is "" unless a fallback was used."""
        try:
            ring, method = recover_rings_with_method(points, self.n_rings)
            self.counts[method] += 1
            return ring, method, ""
        except RingRecoveryError as exc:
            first = str(exc)
        if self.reference is None:
            self._probe()
        try:
            ring, method = recover_rings_with_method(points, self.n_rings, reference_elevations=self.reference)
            self.counts[method] += 1
            return ring, method, first
        except RingRecoveryError as exc:
            problem = str(exc)
        ring = line_rank_rings(points, self.n_rings)
        if ring is not None:
            self.counts["line_rank"] += 1
            return ring, "line_rank", problem
        self.counts["elevation"] += 1
        return elevation_rings(points, self.n_rings, self.reference), "elevation", problem


def line_rank_rings(points: np.ndarray, n_rings: int) -> np.ndarray | None:
    """Rings of a frame whose scan lines are all there but stored out of elevation order (e.g. in
    laser-id order): every line gets the rank of its median elevation, highest first; None unless
    :func:`scan_lines` finds exactly ``n_rings`` lines (a cut or shuffled scan)."""
    if len(points) < 2 * n_rings:
        return None
    line, n_lines, _ = scan_lines(points)
    if n_lines != n_rings:
        return None
    medians = line_elevations(points, line, n_lines)
    if not np.all(np.isfinite(medians)):
        return None
    rank = np.empty(n_lines, np.int64)
    rank[np.argsort(-medians, kind="stable")] = np.arange(n_lines)
    return rank[line].astype(np.int16)


def elevation_rings(points: np.ndarray, n_rings: int, reference: np.ndarray | None = None) -> np.ndarray:
    """Approximate rings from per-point elevation (last resort; see :class:`RingIndexer`).

    With ``reference`` (per-ring median elevations, ring 0 highest) each point takes the
    nearest ring; without, the points are split into ``n_rings`` equal-count elevation
    bins, highest first. Per-point elevation mixes neighbouring rings (the lasers sit off
    the origin): subsampled channels from it are approximate.
    """
    elev = elevation_deg(points)
    if reference is not None and len(reference) == n_rings and np.all(np.isfinite(reference)):
        ref = np.asarray(reference, np.float64)
        order = np.argsort(ref)  # ascending elevation
        pos = np.clip(np.searchsorted(ref[order], elev), 1, n_rings - 1)
        lo, hi = ref[order][pos - 1], ref[order][pos]
        nearest = np.where(np.abs(elev - lo) <= np.abs(elev - hi), pos - 1, pos)
        return order[nearest].astype(np.int16)
    rank = np.empty(len(elev), np.int64)
    rank[np.argsort(-elev, kind="stable")] = np.arange(len(elev))
    return np.minimum(rank * n_rings // max(len(elev), 1), n_rings - 1).astype(np.int16)


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
    return replace(sub, ring=(sub.ring // stride).astype(np.int16))
