"""Frame times for the motion model, with displaced stamps put back on the sensor's beat.

A spinning LiDAR's sweeps follow one another at a steady period; frames missing from a recording
(a dropped message) leave gaps of a whole number of periods. Drivers that stamp a sweep when it is
received, and bags whose header stamps were replaced by log times, show something else now and
then: one stamp displaced by a CPU stall, so that the gap before it is far too short (2 ms after
its predecessor when the sweeps are 100 ms apart) and the gap after it too long, or the other way
round. The odometry's constant-velocity guess and the deskewing both scale motion by such gaps
(:func:`gr_graph.odometry.guess_time_ratio`, :func:`gr_graph.deskew.sweep_motion_from_velocity`):
one displaced stamp scales the next guess by 1/50 or by 10, and the deskewing of the next sweep by
50, which wrecks a trajectory (5.9 m of drift over 19 m measured on a generated 25-frame bag with
one stamp 2 ms after its predecessor, against 0.17 m with regular stamps), with no edge flagged.

:func:`motion_times` finds such stamps and gives the motion model times on the beat; the frames'
own stamps (the trajectory files' times) are left as the data hold them. Only sequences that keep
a beat are touched: at least :data:`MIN_GAPS` gaps, :data:`MIN_REGULAR_FRACTION` of them within
:data:`TOLERANCE` periods of a whole number of periods (the period is their median, or a half or a
third of it when that puts every gap on the beat: a throttled topic). Sensors without a steady rate
(frames cut at irregular times) are left alone, which is logged at debug level.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

__all__ = ["MAX_RUN", "MIN_GAPS", "MIN_REGULAR_FRACTION", "SUB_BEAT_TOLERANCE", "TOLERANCE", "MotionTimes",
           "motion_times"]

log = logging.getLogger(__name__)

#: a gap is on the beat when it is within this many periods of a whole number (>= 1) of periods
TOLERANCE = 0.3
#: fewer gaps than this: no beat is judged, the stamps are used as they are (one displaced stamp puts two
#: gaps off the beat, so a shorter sequence would rarely keep MIN_REGULAR_FRACTION of them on it)
MIN_GAPS = 10
#: the share of gaps on the beat a sequence needs for its off-beat stamps to be moved
MIN_REGULAR_FRACTION = 0.8
#: a half or a third of the median gap is the beat when every gap is within this many of its periods of a
#: whole number of them (tighter than TOLERANCE: a stamp displaced by 40 ms is no sweep of a 20 Hz beat)
SUB_BEAT_TOLERANCE = 0.1
#: the longest run of consecutive displaced stamps (a burst delivered after a stall) that is moved
MAX_RUN = 5


@dataclass
class MotionTimes:
    """Times [s] the motion model uses for a sequence's frames.

    Attributes
    ----------
    times : np.ndarray
        ``(K,)`` float64: the stamps, with the displaced ones moved onto the beat.
    period : float or None
        The beat (median gap) [s]; None when the sequence keeps none (too few frames, or too
        irregular).
    moved : list of int
        Frames (run positions) whose time was moved.
    unresolved : list of int
        Frames whose gap to the previous frame is off the beat and that no moved stamps explain
        (left as they are).
    """

    times: np.ndarray
    period: float | None
    moved: list[int] = field(default_factory=list)
    unresolved: list[int] = field(default_factory=list)

    def summary(self) -> dict[str, object]:
        """For the run summary: the beat, the moved frames and their count."""
        return {"period_s": self.period, "n_moved": len(self.moved), "moved": list(self.moved[:20]),
                "n_unresolved": len(self.unresolved), "unresolved": list(self.unresolved[:20])}


def _on_beat(gap: float, period: float, tolerance: float = TOLERANCE) -> bool:
    whole = max(1.0, float(np.round(gap / period)))
    return abs(gap / period - whole) <= tolerance


def _periods(gap: float, period: float) -> int:
    return int(np.round(gap / period))


def _displaced_run(t: np.ndarray, j: int, period: float) -> list[int] | None:
    """Move the fewest consecutive stamps (at most :data:`MAX_RUN`, one of them frame ``j - 1`` or ``j``)
    that put gap ``j`` (frames ``j - 1``, ``j``) back on the beat, in place; their indices, or None when
    no such run does. A run of ``k`` inner stamps is moved when its two neighbours are a whole number
    ``n >= k + 1`` of periods apart: each stamp goes to the whole period nearest its own time between
    them, in order, one period at least from the next. Failing that, a displaced first or last frame
    goes a whole number (at least one) of periods from its one neighbour."""
    for k in range(1, MAX_RUN + 1):
        for a in range(max(1, j - k), min(j, len(t) - 1 - k) + 1):  # stamps a .. a + k - 1, inner
            span = t[a + k] - t[a - 1]
            n = _periods(span, period)
            if n < k + 1 or not _on_beat(span, period):
                continue
            m_prev = 0
            places = []
            for i in range(k):
                m = int(np.clip(np.round((t[a + i] - t[a - 1]) / period), m_prev + 1, n - k + i))
                places.append(m)
                m_prev = m
            t[a:a + k] = t[a - 1] + span * np.asarray(places) / n
            return list(range(a, a + k))
    whole = max(1, _periods(t[j] - t[j - 1], period))
    if j == len(t) - 1:
        t[j] = t[j - 1] + whole * period
        return [j]
    if j == 1:
        t[0] = t[1] - whole * period
        return [0]
    return None


def _beat(gaps: np.ndarray) -> float | None:
    """The sensor's period: the median gap, or a half or third of it where every gap is a whole number of
    that within :data:`SUB_BEAT_TOLERANCE` (a topic throttled to every other sweep: gaps of mostly 0.2 s
    with some 0.1 and 0.3 s, every stamp true), so that such stamps are not taken for displaced ones;
    None without a steady beat."""
    period = float(np.median(gaps))
    on_beat = np.array([_on_beat(g, period) for g in gaps])
    if on_beat.all():
        return period
    for d in (2, 3):
        if all(_on_beat(g, period / d, SUB_BEAT_TOLERANCE) for g in gaps):
            return period / d
    return period if on_beat.mean() >= MIN_REGULAR_FRACTION else None


def motion_times(stamps: np.ndarray, source: str = "sequence", log_moves: bool = True) -> MotionTimes:
    """The frames' times for the motion model, with each stamp displaced off the sensor's beat moved
    back onto it.

    A gap off the beat (more than :data:`TOLERANCE` periods from a whole number of at least one
    period) is explained by the fewest consecutive displaced stamps (one, or a burst of up to
    :data:`MAX_RUN` delivered together after a stall) that, left out, leave their neighbours a whole
    number of periods apart with room for them (:func:`_displaced_run`); a gap nothing explains is
    counted in ``unresolved``. Moved stamps are logged with their count and first frames.

    Parameters
    ----------
    stamps : np.ndarray
        ``(K,)`` frame times [s], increasing (the loaders repair repeated and backward stamps).
    source : str
        Named in the log message (the sequence).
    log_moves : bool
        Log the moved stamps and the gaps left off the beat (a warning and an info line).

    Returns
    -------
    MotionTimes
    """
    t = np.asarray(stamps, np.float64).copy()
    gaps = np.diff(t)
    if len(gaps) < MIN_GAPS or not np.all(np.isfinite(gaps)) or not np.all(gaps > 0.0):
        return MotionTimes(t, None)
    period = _beat(gaps)
    if period is None:
        log.debug("%s: frame gaps keep no steady beat (under %.0f %% within %.1f periods of a whole number of the "
                  "median gap); stamps used as they are", source, 100 * MIN_REGULAR_FRACTION, TOLERANCE)
        return MotionTimes(t, None)
    moved: list[int] = []
    unresolved: list[int] = []
    for j in range(1, len(t)):  # gap j: between frames j - 1 and j
        if _on_beat(t[j] - t[j - 1], period):
            continue
        run = _displaced_run(t, j, period)
        if run is None:
            unresolved.append(j)
        else:  # a burst's first stamp may have been moved alone at the gap before: counted once
            moved.extend(k for k in run if k not in moved)
    if not log_moves:
        return MotionTimes(t, period, moved, unresolved)
    if moved:
        log.warning("%s: %d frame stamp%s off the sensor's %.4g s beat (frame%s %s): the odometry's guess and the "
                    "deskewing use %s on the beat; the trajectory keeps the stamps as they are",
                    source, len(moved), "s" if len(moved) > 1 else "", period, "s" if len(moved) > 1 else "",
                    ", ".join(str(k) for k in moved[:5]) + (", ..." if len(moved) > 5 else ""),
                    "times" if len(moved) > 1 else "a time")
    if unresolved:
        log.info("%s: %d frame gap%s off the %.4g s beat that no displaced stamps explain (before frame%s "
                 "%s); used as they are", source, len(unresolved), "s" if len(unresolved) > 1 else "", period,
                 "s" if len(unresolved) > 1 else "", ", ".join(str(k) for k in unresolved[:5])
                 + (", ..." if len(unresolved) > 5 else ""))
    return MotionTimes(t, period, moved, unresolved)
