"""From decoded point fields to a :class:`~gr_graph.datasets.base.LidarFrame`: the conventions
a sequence fixes once, from its probe frames and the ``sensor`` section (:class:`FieldConventions`).

- **Per-point time**: drivers store it in seconds (Velodyne ``time``, Hesai ``timestamp``),
  nanoseconds (Ouster ``t``, Livox) or microseconds, relative to the sweep or absolute. The
  unit is ``sensor.time_unit`` when given, else the power of 1000 that makes the time span
  closest to the frame spacing (a sweep lasts about one frame period), taken on the probe frame
  (below) of the median time span (the upper one of an even count: a short first message, the
  tail of a sweep, does not set it, nor does one overlong frame among five).
  Times become
  sweep fractions with :func:`gr_graph.deskew.normalise_times` over ``sensor.scan_period``
  (else the frame spacing), counted from ``sensor.time_reference`` when given, else from what
  the values say: times within one sweep of 0 count from the sweep's start (or back from its
  end), so a partial sweep keeps its place in the sweep; absolute stamps count from the
  frame's earliest point. With ``time_unit`` or ``time_reference`` given, times that do not
  fit one sweep are an error naming the file. With the unit guessed, a probe frame whose times
  span more than :data:`GUESSED_UNIT_SLACK` sweeps past one is an error when the sequence is
  opened (the guess is wrong; name the unit); a later frame's are clipped, logged once a frame
  and counted (:attr:`FieldConventions.n_overlong_frames`). ``sensor.has_time: false`` drops the time field
  (logged; the sequence still counts as not motion-compensated, so deskewing takes the times
  from the azimuth).
- **Sweep duration** (``scan_period``, what maps times to fractions and the odometry's motion to
  one sweep): ``sensor.scan_period`` when given; else the frame spacing, unless the first probe
  frame that is a full revolution (points in at least :data:`FULL_REVOLUTION_COVERAGE` of the
  azimuth sectors; a driver's start-up fragment is passed over, since 2026-12-07) has per-point
  times that span more than :data:`SWEEP_SPACING_MISMATCH` away from it and a plausible sweep
  duration (:data:`PLAUSIBLE_SWEEP_S`): then the span (logged). Where the first frame with points
  is a full revolution, that is the frame judged, as before the probe frames (the same frame
  times, so a resume of an earlier run's output sees the same data). That is a 20 Hz
  sensor without a timestamps file (spacing assumed 0.1 s, sweeps of 0.05 s: the folder then
  takes its frames 0.05 s apart; before, they were deskewed with half the motion) or a folder
  that keeps every other frame (spacing 0.2 s, sweeps of 0.1 s: deskewed to the sweep's middle
  instead of its end; the relative poses were right before too).
- **Frame stamps**: a deskewed sweep's pose is that of the sweep's middle, while drivers stamp a
  sweep's first point (Ouster, ROS2 Velodyne), its last (ROS1 Velodyne) or some instant between.
  :attr:`FieldConventions.stamp_to_sweep_middle` is the time from a frame's stamp to its sweep's
  middle: ``sensor.frame_stamp`` when given (``(0.5 - f) * scan_period`` for a stamp at sweep
  fraction ``f``), else the median over the probe frames of what their per-point times show
  (:func:`gr_graph.deskew.sweep_middle_offset`; times relative to the sweep count from the stamp,
  absolute times from a bag's header stamp). A bag whose header stamps do not increase is stamped
  with its log times, when each message arrived, after its sweep: with times relative to the
  sweep, the middle is then taken half a sweep before the stamp (``"log times"``, logged). Unknown
  (None) without per-point times, for absolute times without a stamp on their clock (folders), and
  for offsets beyond one sweep (logged). The loaders move the stamps by it
  (:func:`gr_graph.datasets.stamp_shift.stamps_at_sweep_middle`).
- **Rings**: the project numbers rings from the highest beam (0) down. Drivers differ (the
  Velodyne driver's ``ring`` 0 is the lowest beam, Ouster's the highest): when the median
  elevation of the first probe frame's rings rises with the ring number, rings are flipped
  (``n_rings - 1 - ring``). ``n_rings`` is the named sensor's beam count (``--sensor``,
  ``sensor.model`` / ``n_beams``; a larger ring index is an error), else the highest ring of the
  probe frames + 1 rounded up to 16, 32, 64 or 128 when one of those is at most 25 % above;
  a later frame with a higher ring is an error that says to name the sensor (renumbering on the
  fly would change the ``--channels`` stride and flipped rings between frames). ``sensor.has_ring: false`` drops
  the ring field (logged).
- **Probe frames**: the first frame with points and up to :data:`PROBE_FRAMES` - 1 more spread
  evenly over the sequence (:func:`probe_indices`), read by the loader when it opens the
  sequence: a first frame that misses the top beams (open sky) or holds a few milliseconds of
  a sweep does not fix the conventions alone.
- **Frames without points** (a warm-up message, a dropped sweep) become empty frames with the
  sequence's fields, whatever fields their file or message declares.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from gr_graph.datasets.base import DatasetError, LidarFrame
from gr_graph.datasets.pointcloud2 import DecodedCloud
from gr_graph.deskew import RELATIVE_SLACK, normalise_times, resolve_time_reference, sweep_middle_offset
from gr_graph.sensors import TIME_UNITS, SensorConfig

log = logging.getLogger(__name__)

TIME_UNITS_S = tuple(TIME_UNITS.values())
"""Candidate units of a per-point time field, in seconds (s, ms, us, ns)."""
COMMON_RING_COUNTS = (16, 32, 64, 128)
DEFAULT_FRAME_PERIOD_S = 0.1
"""Frame spacing assumed (10 Hz, the usual spinning-LiDAR rate) when no timestamps are known."""
AZIMUTH_SECTORS = 72
"""5-degree sectors of the azimuth, counted to tell a full revolution from a partial sweep."""
FULL_REVOLUTION_COVERAGE = 0.9
"""A frame with points in at least this share of :data:`AZIMUTH_SECTORS` is a full revolution."""
PLAUSIBLE_SWEEP_S = (0.005, 10.0)
"""Sweep durations (s) a time span may be taken for (as the frame spacings a timestamps file may
have): a span outside, e.g. nanoseconds declared as seconds, is not a sweep duration."""
SWEEP_SPACING_MISMATCH = 0.1
"""A full revolution's time span more than this (relative) away from the frame spacing is its
sweep duration; closer, the spacing stays (unchanged results for data that agree)."""
FRAME_STAMP_FRACTIONS = {"sweep_start": 0.0, "sweep_middle": 0.5, "sweep_end": 1.0}
"""``sensor.frame_stamp``: the sweep fraction where the frame stamps lie."""
STAMP_DISAGREEMENT = 0.1
"""``sensor.frame_stamp`` further than this many sweeps from what the per-point times show is logged."""
PROBE_FRAMES = 5
"""Frames that fix a sequence's conventions: its first frame with points and up to this many
minus one more spread over the sequence (:func:`probe_indices`)."""
GUESSED_UNIT_SLACK = 1.0
"""With a guessed time unit, sweep fractions further than this outside ``[0, 1]`` (times spanning
more than two sweeps) mean a wrong guess at a probe frame (an error) and an overlong frame later
(clipped, logged, counted)."""


def no_time_field_note(what: str) -> str:
    """The warning for scans without a per-point time field (``what``: the folder, or the bag's topic):
    taken as motion-compensated, since a driver's raw sweeps look the same."""
    return (f"{what} has no per-point time field: its scans are taken as motion-compensated (odometry.deskew: auto "
            "leaves them as they are); for raw sweeps set odometry.deskew: on (times from the azimuth)")


def probe_indices(n_frames: int, first: int, count: int = PROBE_FRAMES) -> list[int]:
    """``first`` and up to ``count - 1`` more frame indices spread evenly from it to the last frame."""
    if n_frames <= first:
        return [first]
    return sorted({int(round(x)) for x in np.linspace(first, n_frames - 1, count)})


def guess_time_unit(times: np.ndarray, frame_period: float) -> float:
    """The unit (seconds per stored unit) that makes the time span closest to ``frame_period``."""
    span = float(np.max(times) - np.min(times))
    if not span > 0.0:
        return 1.0
    errors = [abs(np.log(span * u / frame_period)) for u in TIME_UNITS_S]
    return TIME_UNITS_S[int(np.argmin(errors))]


def median_span(clouds: list[tuple[DecodedCloud, str]]) -> tuple[DecodedCloud, str]:
    """The cloud (and source) whose per-point time span is the median of ``clouds``': the upper one
    of an even count (of a short first message and a full sweep, the sweep); equal spans in their
    order in ``clouds``."""
    spans = [float(np.ptp(c.time)) for c, _ in clouds]
    order = sorted(range(len(spans)), key=lambda k: (spans[k], k))
    return clouds[order[len(order) // 2]]


def azimuth_coverage(points: np.ndarray, sectors: int = AZIMUTH_SECTORS) -> float:
    """Share of ``sectors`` equal azimuth sectors that hold at least one point (0 for no points)."""
    pts = np.asarray(points, np.float64)
    if not len(pts):
        return 0.0
    azimuth = np.arctan2(pts[:, 1], pts[:, 0])
    sector = np.clip(np.floor((azimuth + np.pi) / (2.0 * np.pi) * sectors), 0, sectors - 1).astype(np.int64)
    return float(len(np.unique(sector))) / sectors


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


#: after the flip, a ring whose median elevation lies more than this above the ring before it (by number)
#: means the numbers are not in elevation order (e.g. a driver's firing-order laser ids): renumbered
RING_ORDER_TOLERANCE_DEG = 0.1


def ring_renumbering(clouds: list[DecodedCloud], n_rings: int, flip: bool) -> np.ndarray | None:
    """A lookup table ``stored ring -> ring numbered from the highest beam`` when the stored numbers are
    not in elevation order (beyond :data:`RING_ORDER_TOLERANCE_DEG` between neighbours), else None.

    The rings seen in ``clouds`` (the probe frames) are numbered by their median elevation, highest
    first; rings not seen there take the numbers left, in their stored order (they are named in the
    log). Rings in order, or in reverse order (``flip``), need no table.
    """
    elevation = np.concatenate([np.arctan2(c.points[:, 2], np.hypot(c.points[:, 0], c.points[:, 1]))
                                for c in clouds])
    ring = np.concatenate([np.asarray(c.ring, np.int64) for c in clouds])
    ids = np.unique(ring)
    if len(ids) < 3:
        return None
    medians = np.degrees(np.array([np.median(elevation[ring == r]) for r in ids]))
    in_storage_order = medians[::-1] if flip else medians  # by the number the frames will carry
    if not (np.diff(in_storage_order) > RING_ORDER_TOLERANCE_DEG).any():
        return None
    table = np.full(n_rings, -1, np.int16)
    table[ids[np.argsort(-medians, kind="stable")]] = np.arange(len(ids))
    unseen = np.flatnonzero(table < 0)
    table[unseen] = np.arange(len(ids), n_rings)
    return table


@dataclass
class FieldConventions:
    """How a sequence turns decoded fields into frames (fixed by :meth:`probe` on the probe frames).

    Attributes
    ----------
    has_time : bool
        A probe frame has a per-point time field that spans more than 0: the scans are raw sweeps,
        not motion-compensated (also when ``use_time`` is False).
    time_unit_s : float
        Seconds per unit of the time field.
    scan_period : float
        Sweep duration (s) that maps times to fractions.
    scan_period_source : str
        Where ``scan_period`` comes from: ``"sensor.scan_period"``, ``"frame spacing"`` or
        ``"per-point times"`` (the span of a full revolution's times; see the module docstring).
    has_ring : bool
        The first probe frame has a ring field.
    n_rings : int
        Rings of the sensor: the named sensor's (``fixed_rings``), else the probe frames'; a
        later frame with a higher ring is an error naming the fix (name the sensor).
    flip_rings : bool
        Rings are numbered from the lowest beam and get flipped.
    ring_table : np.ndarray or None
        Rings whose stored numbers are not in elevation order (:func:`ring_renumbering`): stored
        number -> number from the highest beam (replaces the flip).
    time_reference : str
        What times count from (:data:`gr_graph.deskew.TIME_REFERENCES`; ``auto``: judged per
        frame from the values).
    time_tolerance : float or None
        Sweep fractions further than this outside ``[0, 1]`` are an error (None: clipped);
        set when the sensor section gives the time unit or reference.
    use_time, use_ring : bool
        False when the sensor section says to ignore the field (``has_time`` / ``has_ring``
        false): frames get no times / rings.
    fixed_rings : bool
        ``n_rings`` is the named sensor's beam count.
    stamp_to_sweep_middle : float or None
        Seconds from a frame's stamp to its sweep's middle (see the module docstring); None: unknown.
    stamp_to_sweep_middle_source : str
        ``"sensor.frame_stamp"``, ``"per-point times"``, ``"log times"`` or ``""`` (unknown).
    overlong_frames : set of str
        Sources of the frames read so far whose times spanned more than :data:`GUESSED_UNIT_SLACK`
        sweeps past one under a guessed unit (clipped to the sweep; each logged once);
        :attr:`n_overlong_frames` counts them.
    """

    has_time: bool = False
    time_unit_s: float = 1.0
    scan_period: float = DEFAULT_FRAME_PERIOD_S
    scan_period_source: str = "frame spacing"
    has_ring: bool = False
    n_rings: int = 64
    flip_rings: bool = False
    ring_table: np.ndarray | None = None
    time_reference: str = "auto"
    time_tolerance: float | None = None
    use_time: bool = True
    use_ring: bool = True
    fixed_rings: bool = False
    stamp_to_sweep_middle: float | None = None
    stamp_to_sweep_middle_source: str = ""
    overlong_frames: set[str] = field(default_factory=set)

    @property
    def n_overlong_frames(self) -> int:
        """Frames clipped to one sweep so far (:attr:`overlong_frames`)."""
        return len(self.overlong_frames)

    @property
    def motion_compensated(self) -> bool:
        """False when the data carries per-point times (raw sweeps), used or not."""
        return not self.has_time

    @classmethod
    def probe(cls, cloud: DecodedCloud, frame_period: float, source: str,
              sensor: SensorConfig | None = None,
              more: Sequence[tuple[DecodedCloud, str]] = (),
              sweep_starts: Sequence[float | None] = (),
              stamps_are_log_times: bool = False) -> FieldConventions:
        """Conventions of a sequence whose first frame is ``cloud`` and frames ``frame_period`` s apart.

        Parameters
        ----------
        cloud : DecodedCloud
            The first frame's fields.
        frame_period : float
            Spacing of the frame timestamps (s).
        source : str
            Named in messages and errors.
        sensor : SensorConfig, optional
            The ``sensor`` section. ``time_unit`` and ``time_reference``, when set (not None), replace the
            guesses (and make times that do not fit one sweep an error), ``scan_period``
            the frame spacing, ``model`` / ``n_beams`` given (:attr:`SensorConfig.named_beams`)
            fix ``n_rings``; ``has_time`` /
            ``has_ring`` false drop the field, true require it.
        more : sequence of (DecodedCloud, str)
            Further probe frames (:func:`probe_indices`) and their sources: the time unit is guessed
            on the frame of the median time span (the sweep duration on the first of ``cloud`` and
            them that covers a full revolution, else on ``cloud``), the ring count is their highest
            ring.
        sweep_starts : sequence of float or None
            The stamps (s) of ``cloud`` and of each of ``more`` on the clock of absolute per-point
            times (a bag's header stamps), for :attr:`stamp_to_sweep_middle`; empty: not known.
        stamps_are_log_times : bool
            The frames' stamps are a bag's log times (its header stamps did not increase): when a
            message arrived, after its sweep ended. Per-point times relative to the sweep then say
            nothing of where the stamp lies, and the sweep's middle is taken half a sweep before it
            (:attr:`stamp_to_sweep_middle` ``-scan_period / 2``, logged; ``sensor.frame_stamp`` and
            absolute per-point times, which carry their own clock, still decide when there).

        Raises
        ------
        DatasetError
            A field the sensor section requires is missing, a probe frame's times do not fit one
            sweep in the given unit (or span more than two under the guessed one), or its rings
            exceed the named sensor's beams.
        """
        period, period_source = float(frame_period), "frame spacing"
        if sensor is not None and sensor.scan_period is not None:
            period, period_source = float(sensor.scan_period), "sensor.scan_period"
        conv = cls(scan_period=period, scan_period_source=period_source)
        starts = list(sweep_starts) or [None] * (1 + len(more))
        if len(starts) != 1 + len(more):
            raise ValueError(f"sweep_starts holds {len(starts)} stamps for {1 + len(more)} probe frames")
        kept = [0, *[k + 1 for k, (c, _) in enumerate(more) if len(c.points)]]
        probes = [(cloud, source), *[more[k - 1] for k in kept[1:]]]
        conv._probe_time(probes, frame_period, sensor)
        conv._probe_ring(probes, sensor)
        conv._probe_stamp([(*probes[j], starts[k]) for j, k in enumerate(kept)], sensor, stamps_are_log_times)
        return conv

    def _probe_time(self, probes: list[tuple[DecodedCloud, str]], frame_period: float,
                    sensor: SensorConfig | None) -> None:
        want = None if sensor is None else sensor.has_time
        # the first probe frame whose times vary: a first message with a constant (e.g. zero) time field
        # does not make a sequence of raw sweeps look motion-compensated
        varying = [(c, src) for c, src in probes if c.time is not None and len(c.time) and np.ptp(c.time) > 0]
        cloud, source = varying[0] if varying else probes[0]
        if varying:
            self.has_time = True
            if want is False:
                self.use_time = False
                log.warning("%s: per-point time field %r ignored (sensor.has_time: false); deskewing, when on, "
                            "takes the times from the azimuth", source, cloud.time_field)
                return
            unit_given = sensor is not None and sensor.time_unit is not None
            reference_given = sensor is not None and sensor.time_reference is not None
            timed = [(c, src) for c, src in probes if c.time is not None and len(c.time)]
            # the probe of the median time span (neither a short first message nor an overlong frame) sets
            # the guessed unit; the sweep duration is judged on the first frame that covers a full revolution
            # (the first varying one when none does: a driver's first message after start-up is often a
            # fragment, whose span says nothing of a sweep's)
            median, median_source = median_span(timed)
            if unit_given:
                self.time_unit_s = TIME_UNITS[sensor.time_unit]  # type: ignore[union-attr]
            else:
                self.time_unit_s = guess_time_unit(median.time, self.scan_period)
            if reference_given:
                self.time_reference = sensor.time_reference  # type: ignore[union-attr]
            if unit_given or reference_given:
                self.time_tolerance = RELATIVE_SLACK
            if self.scan_period_source == "frame spacing":
                full = next(((c, src) for c, src in varying
                             if azimuth_coverage(c.points) >= FULL_REVOLUTION_COVERAGE), (cloud, source))
                self._sweep_duration_from_times(*full)
            log.info("%s: per-point time field %r read in units of %g s (%s; span %.4g s, scan period %.4g s, "
                     "frame period %.4g s), counted from %s", median_source, median.time_field, self.time_unit_s,
                     "sensor.time_unit" if unit_given else "guessed", np.ptp(median.time) * self.time_unit_s,
                     self.scan_period, frame_period,
                     self.time_reference if reference_given else "the reference the values show")
            for c, src in timed:  # every probe frame must fit one sweep (two under a guessed unit)
                self._fit(c.time, src)
        elif cloud.time is not None:
            log.warning("%s: per-point time field %r is constant: ignored", source, cloud.time_field)
        if want and not self.has_time:
            raise DatasetError(f"{source}: no per-point time field that varies (sensor.has_time is true)")

    def _sweep_duration_from_times(self, cloud: DecodedCloud, source: str) -> None:
        """Take a full revolution's time span as the sweep duration when the frame spacing disagrees."""
        span = float(np.ptp(cloud.time)) * self.time_unit_s
        lo, hi = PLAUSIBLE_SWEEP_S
        if abs(span / self.scan_period - 1.0) <= SWEEP_SPACING_MISMATCH or not lo <= span <= hi:
            return
        coverage = azimuth_coverage(cloud.points)
        if coverage < FULL_REVOLUTION_COVERAGE:
            log.info("%s: per-point times span %.4g s against a frame spacing of %.4g s, but the frame covers "
                     "%.0f %% of the azimuth (a partial sweep): the sweep duration stays the frame spacing",
                     source, span, self.scan_period, 100.0 * coverage)
            return
        log.warning("%s: the per-point times of a full revolution span %.4g s, the frames are %.4g s apart: "
                    "sweep duration %.4g s taken from the times (set sensor.scan_period to say otherwise)",
                    source, span, self.scan_period, span)
        self.scan_period, self.scan_period_source = span, "per-point times"

    def _probe_stamp(self, probes: list[tuple[DecodedCloud, str, float | None]], sensor: SensorConfig | None,
                     stamps_are_log_times: bool = False) -> None:
        """:attr:`stamp_to_sweep_middle`: ``sensor.frame_stamp``, else what the probe frames' times show
        (for log times, see :meth:`probe`)."""
        measured: list[float] = []
        relative = False  # the times count from the sweep, not on a clock of their own
        if self.has_time and self.use_time:
            for c, _, start in probes:
                if c.time is None or not len(c.time):
                    continue
                times = np.asarray(c.time, np.float64) * self.time_unit_s
                offset = sweep_middle_offset(times, self.scan_period, self.time_reference, start)
                if offset is not None:
                    measured.append(offset)
                    ref = (resolve_time_reference(times, self.scan_period) if self.time_reference == "auto"
                           else self.time_reference)
                    relative = relative or ref != "absolute"
        source = probes[0][1]
        median = float(np.median(measured)) if measured else None
        given = None if sensor is None else sensor.frame_stamp
        if given is not None:
            self.stamp_to_sweep_middle = (0.5 - FRAME_STAMP_FRACTIONS[given]) * self.scan_period
            self.stamp_to_sweep_middle_source = "sensor.frame_stamp"
            if median is not None and abs(median - self.stamp_to_sweep_middle) > STAMP_DISAGREEMENT * self.scan_period:
                log.warning("%s: sensor.frame_stamp %s puts the sweep's middle %+.4g s from the stamps; the "
                            "per-point times show %+.4g s (median of %d probe frames): the sensor section is "
                            "followed", source, given, self.stamp_to_sweep_middle, median, len(measured))
            return
        if median is None:
            return
        if stamps_are_log_times and relative:
            self.stamp_to_sweep_middle = -0.5 * self.scan_period
            self.stamp_to_sweep_middle_source = "log times"
            log.warning("%s: the frames are stamped with the bag's log times, when each message arrived, and the "
                        "per-point times count from the sweep: the sweep's middle is taken half a sweep (%.4g s) "
                        "before the log time, as if the message arrived when its sweep ended (set "
                        "sensor.frame_stamp to say otherwise)", source, 0.5 * self.scan_period)
            return
        if abs(median) > self.scan_period:
            log.warning("%s: the per-point times put the sweep's middle %+.4g s from the frame stamps, more than "
                        "one sweep (%.4g s): the stamps are kept (set sensor.frame_stamp to move them)", source,
                        median, self.scan_period)
            return
        self.stamp_to_sweep_middle, self.stamp_to_sweep_middle_source = median, "per-point times"

    def _probe_ring(self, probes: list[tuple[DecodedCloud, str]], sensor: SensorConfig | None) -> None:
        want = None if sensor is None else sensor.has_ring
        named = None if sensor is None else sensor.named_beams
        if named is not None:
            self.n_rings, self.fixed_rings = int(named), True
        cloud, source = probes[0]
        if cloud.ring is None or not len(cloud.ring):
            if want:
                raise DatasetError(f"{source}: no ring field (sensor.has_ring is true)")
            return
        self.has_ring = True
        if want is False:
            self.use_ring = False
            log.warning("%s: ring field ignored (sensor.has_ring: false)", source)
            return
        ringed = [(c, src) for c, src in probes if c.ring is not None and len(c.ring)]
        highest, source_highest = max((int(c.ring.max()), src) for c, src in ringed)
        if self.fixed_rings:
            self._check_named_rings(highest, source_highest)
        else:
            self.n_rings = ring_count(highest)
        self.flip_rings = rings_rise_with_elevation(cloud.points, cloud.ring)
        self.ring_table = ring_renumbering([c for c, _ in ringed], self.n_rings, self.flip_rings)
        if self.ring_table is not None:
            self.flip_rings = False
            seen = np.unique(np.concatenate([np.asarray(c.ring) for c, _ in ringed]))
            unseen = sorted(set(range(self.n_rings)) - set(seen.tolist()))
            log.warning("%s: the ring numbers are not in elevation order (e.g. a driver's firing-order laser "
                        "ids): rings renumbered by their median elevation over the %d probe frames, highest "
                        "first%s", source, len(ringed),
                        f"; rings {unseen} not seen there take the numbers {len(seen)}-{self.n_rings - 1}"
                        if unseen else "")
        elif self.flip_rings:
            log.info("%s: ring 0 is the lowest beam: rings flipped to number from the highest", source)

    def _check_named_rings(self, highest: int, source: str) -> None:
        if highest >= self.n_rings:
            raise DatasetError(f"{source}: ring {highest} >= {self.n_rings} rings of the sensor (sensor.model / "
                               "sensor.n_beams, --sensor): name the sensor that took the scans")

    def _fit(self, times: np.ndarray, source: str, sweep_start: float | None = None) -> np.ndarray:
        """Sweep fractions of times that fit one sweep (within the given units' slack, or
        :data:`GUESSED_UNIT_SLACK` under a guessed unit); else a :class:`DatasetError` naming the fix."""
        given = self.time_tolerance is not None
        try:
            return normalise_times(np.asarray(times, np.float64) * self.time_unit_s, self.scan_period,
                                   self.time_reference, sweep_start,
                                   self.time_tolerance if given else GUESSED_UNIT_SLACK)
        except ValueError as exc:
            hint = ("check sensor.time_unit, sensor.time_reference and sensor.scan_period" if given else
                    "the unit was guessed from the span of the probe frames' times: give sensor.time_unit "
                    "(and sensor.scan_period when a frame holds more than one sweep)")
            raise DatasetError(f"{source}: {exc} (read in units of {self.time_unit_s:g} s); {hint}") from None

    def fractions(self, times: np.ndarray, source: str, sweep_start: float | None = None) -> np.ndarray:
        """Sweep fractions of one frame's stored times (:func:`gr_graph.deskew.normalise_times`).

        Under a guessed unit, a frame whose times span more than :data:`GUESSED_UNIT_SLACK` sweeps
        past one is clipped to the sweep, logged and counted (:attr:`n_overlong_frames`)."""
        try:
            return self._fit(times, source, sweep_start)
        except DatasetError as exc:
            if self.time_tolerance is not None:
                raise
            if source not in self.overlong_frames:  # frames are read again in later rounds: logged once
                self.overlong_frames.add(source)
                log.warning("%s: clipped to one sweep (%d such frame%s so far)", exc, self.n_overlong_frames,
                            "s" if self.n_overlong_frames > 1 else "")
            return normalise_times(np.asarray(times, np.float64) * self.time_unit_s, self.scan_period,
                                   self.time_reference, sweep_start, None)

    def _rings(self, cloud: DecodedCloud, source: str) -> np.ndarray:
        highest = int(cloud.ring.max()) if len(cloud.ring) else -1  # type: ignore[union-attr]
        if highest >= self.n_rings:
            if self.fixed_rings:
                self._check_named_rings(highest, source)
            # not grown on the fly: the ring count sets the stride of --channels and the numbering of
            # flipped rings, and frames read earlier (other threads, the frame cache) would disagree
            raise DatasetError(f"{source}: ring {highest} >= {self.n_rings} rings counted in the probe frames (which "
                               "misses some beams, e.g. the sky): name the sensor so the count does not come from "
                               "the data (--sensor NAME, or sensor: {model: custom, n_beams: N, ...})")
        if self.ring_table is not None:
            return self.ring_table[np.asarray(cloud.ring, np.int64)]
        r = (self.n_rings - 1 - cloud.ring) if self.flip_rings else cloud.ring
        return np.asarray(r).astype(np.int16)

    def frame(self, cloud: DecodedCloud, index: int, timestamp: float, source: str,
              sweep_start: float | None = None) -> LidarFrame:
        """The frame of ``cloud`` under these conventions.

        ``sweep_start`` is the frame's stamp on the clock of absolute per-point times (s), when
        the loader knows it; absolute times that fall in the sweep starting there count from it.
        """
        n = len(cloud.points)
        time = None
        if self.has_time and self.use_time:
            if cloud.time is not None:
                time = self.fractions(cloud.time, source, sweep_start)
            elif n == 0:  # an empty message declaring no fields: an empty frame like the others
                time = np.zeros(0)
            else:
                raise DatasetError(f"{source}: no per-point time field, but the sequence's probe frames have one")
        ring = None
        if self.has_ring and self.use_ring:
            if cloud.ring is not None:
                ring = self._rings(cloud, source)
            elif n == 0:
                ring = np.zeros(0, np.int16)
            else:
                raise DatasetError(f"{source}: no ring field, but the sequence's first frame has one")
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
