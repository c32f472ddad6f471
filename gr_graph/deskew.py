"""Motion compensation ("deskewing") of a LiDAR sweep under constant velocity.

A spinning LiDAR measures each point from the sensor pose at the point's own time; a sweep
taken while driving is therefore distorted (a 10 m/s car moves 1 m during a 0.1 s sweep).
Deskewing moves every point into the sensor frame at one reference time of the sweep, here
its middle, assuming the sensor moved with constant velocity during the sweep.

Conventions
-----------
* ``times`` are per-point fractions of the sweep in ``[0, 1]`` (0 = the sweep's start).
* ``sweep_motion`` is the pose of the sensor at the end of the sweep in the frame of the
  sensor at its start (a 4x4 matrix); under constant velocity the pose at fraction ``t`` is
  ``Exp(t * xi)`` with ``xi = Log(sweep_motion)`` (gtsam tangent order ``[omega, v]``). The
  odometry predicts it from the previous frame-to-frame motion.
* A point ``p`` measured at fraction ``t`` is, in the sensor frame at fraction ``s``,
  ``Exp((t - s) * xi) p``.

When the data carries no per-point time, :func:`times_from_azimuth` derives it from the
azimuth, for a sensor that spins clockwise seen from above (Velodyne, Ouster) and whose
sweep starts and ends facing backward, so that it faces forward at mid-sweep (KITTI's
camera is triggered when the laser faces forward; its poses refer to that instant).
"""

from __future__ import annotations

import numpy as np

from factors.se3 import exp_se3_batch, hat, log_se3

__all__ = ["times_from_azimuth", "normalise_times", "sweep_middle_offset", "resolve_time_reference", "TIME_REFERENCES",
           "deskew", "distort", "sweep_motion_from_velocity"]


def times_from_azimuth(points: np.ndarray, clockwise: bool = True, start_azimuth_deg: float = 180.0) -> np.ndarray:
    """Per-point sweep fraction in ``[0, 1]`` from the azimuth.

    Parameters
    ----------
    points : (N, 3) array
        Points in the sensor frame (x forward, y left, z up).
    clockwise : bool
        Rotation seen from above; clockwise (Velodyne, Ouster) means the azimuth decreases
        with time (``sensor.rotation``).
    start_azimuth_deg : float
        Azimuth where the sweep starts and ends (``sensor.sweep_start_azimuth_deg``; 0 = straight
        ahead, 90 = left); by default facing backward, where 0.5 is straight ahead.

    Returns
    -------
    np.ndarray
        ``(N,)`` float64.
    """
    az = np.arctan2(points[:, 1], points[:, 0])
    if start_azimuth_deg == 180.0:  # facing backward (the formula before the option existed, bit for bit)
        t = 0.5 * (1.0 - az / np.pi) if clockwise else 0.5 * (1.0 + az / np.pi)
    else:
        start = np.radians(start_azimuth_deg)
        t = np.mod(start - az if clockwise else az - start, 2.0 * np.pi) / (2.0 * np.pi)
    return np.clip(t, 0.0, 1.0)


TIME_REFERENCES = ("auto", "sweep_start", "sweep_end", "absolute")
"""What per-point times count from (:func:`normalise_times`)."""
RELATIVE_SLACK = 0.05
"""``reference="auto"``: times within ``[-s, 1 + s]`` scan periods of 0 count as relative to the sweep."""
FULL_SWEEP = 0.9
"""A frame of absolute stamps spanning at least this many scan periods is a full sweep: it counts
from its earliest point, as before partial sweeps were told apart (a frame stamp a few milliseconds
off the first firing, a driver's latency, does not shift it). Times relative to the sweep are
taken as they are."""
START_SLACK = 0.01
"""A sweep whose earliest time lies within this many scan periods of its reference starts at its
earliest point (the first firing is a hair after the reference; full sweeps are mapped exactly as
by the former ``(t - t_min) / period``)."""


def resolve_time_reference(times: np.ndarray, scan_period: float) -> str:
    """What ``times`` (seconds) count from, judged from their values (``reference="auto"``).

    ``"sweep_end"`` when every time lies in ``[-scan_period, 0]`` and one is below 0 (also a
    sweep's last few milliseconds, which would fit the start's slack too), ``"sweep_start"`` when
    every time lies in ``[0, scan_period]`` (up to :data:`RELATIVE_SLACK` periods), else
    ``"absolute"`` (stamps on some clock). Empty times count as ``"sweep_start"``.
    """
    t = np.asarray(times, np.float64)
    if t.size == 0:
        return "sweep_start"
    slack = RELATIVE_SLACK * float(scan_period)
    lo, hi = float(t.min()), float(t.max())
    if lo < 0.0 and hi <= 0.0 and lo >= -scan_period - slack:  # all back from 0: the tail of a sweep-end sweep
        return "sweep_end"
    if lo >= -slack and hi <= scan_period + slack:
        return "sweep_start"
    if lo >= -scan_period - slack and hi <= slack:
        return "sweep_end"
    return "absolute"


def normalise_times(times: np.ndarray, scan_period: float | None = None, reference: str = "auto",
                    sweep_start: float | None = None, tolerance: float | None = None) -> np.ndarray:
    """Per-point times (seconds, or any unit without ``scan_period``) -> sweep fractions in ``[0, 1]``.

    Parameters
    ----------
    times : (N,) array
        Per-point times.
    scan_period : float, optional
        Sweep duration in the unit of ``times``. Without it the times are stretched to
        ``[0, 1]`` by their own range, ``(t - t_min) / (t_max - t_min)`` (``reference`` and
        ``sweep_start`` unused).
    reference : {"auto", "sweep_start", "sweep_end", "absolute"}
        What the times count from. ``sweep_start``: the sweep's start, fraction ``t / period``
        (a partial sweep keeps its place in the sweep); ``sweep_end``: back from its end
        (``t <= 0``), ``(t + period) / period``; ``absolute``: stamps, counted from
        ``sweep_start`` when given, else from the frame's earliest point (the only reference
        a frame of absolute stamps has; a partial sweep is then stretched from its first
        point). ``auto`` (default) picks one from the values (:func:`resolve_time_reference`);
        for absolute stamps it uses ``sweep_start`` only when the times fall in the sweep
        that starts there.
    sweep_start : float, optional
        Absolute times: the sweep's start on the same clock (e.g. the frame's stamp).
    tolerance : float, optional
        None (default): fractions outside ``[0, 1]`` are clipped. A number: fractions further
        than this outside ``[0, 1]`` raise ``ValueError`` (times that do not fit one sweep, e.g.
        a wrong unit); closer ones are clipped.

    Returns
    -------
    np.ndarray
        ``(N,)`` float64 fractions. A full sweep of absolute stamps (spanning at least
        :data:`FULL_SWEEP` periods) or a sweep whose earliest time lies within :data:`START_SLACK` periods of its
        reference maps to ``(t - t_min) / period`` exactly as before; only partial sweeps that
        start later (e.g. the front half only) keep their offset, ``(t - reference) / period``.
        Absolute stamps with a ``sweep_start``: the stamp is the sweep's start, or its end when
        the times lie in the period before it (drivers that stamp the last point).

    Raises
    ------
    ValueError
        Non-finite times, an unknown ``reference``, or (with ``tolerance``) times that do not
        fit one sweep.
    """
    t = np.asarray(times, np.float64)
    if t.size == 0:
        return t
    if not np.all(np.isfinite(t)):
        raise ValueError("per-point times contain non-finite values")
    if reference not in TIME_REFERENCES:
        raise ValueError(f"time reference must be one of {TIME_REFERENCES}, got {reference!r}")
    if scan_period is None:
        span = float(t.max() - t.min())
        if span <= 0.0:
            return np.full_like(t, 0.5)
        return np.clip((t - t.min()) / span, 0.0, 1.0)
    period = float(scan_period)
    if period <= 0.0:
        return np.full_like(t, 0.5)
    origin, ref = _sweep_origin(t, period, reference, sweep_start)
    rel = t - origin
    frac = rel / period
    if tolerance is not None:
        lo, hi = float(frac.min()), float(frac.max())
        if lo < -tolerance or hi > 1.0 + tolerance:
            raise ValueError(f"per-point times (from {ref}) span {float(rel.min()):.6g}..{float(rel.max()):.6g} s, "
                             f"i.e. sweep fractions {lo:.3g}..{hi:.3g} with a scan period of {period:.6g} s")
    return np.clip(frac, 0.0, 1.0)


def _sweep_origin(t: np.ndarray, period: float, reference: str, sweep_start: float | None) -> tuple[float, str]:
    """The time (on the clock of ``t``, non-empty and finite) that :func:`normalise_times` maps to
    fraction 0, and the reference it resolved ``reference`` to."""
    ref = resolve_time_reference(t, period) if reference == "auto" else reference
    if ref == "sweep_start":
        start: float | None = 0.0
    elif ref == "sweep_end":
        start = -period
    elif sweep_start is not None:
        # the stamp marks the sweep's start, or its end (drivers that stamp the last point)
        on_stamp = resolve_time_reference(t - float(sweep_start), period)
        start = (float(sweep_start) if on_stamp == "sweep_start" or reference == "absolute" and on_stamp != "sweep_end"
                 else float(sweep_start) - period if on_stamp == "sweep_end" else None)
    else:
        start = None
    t_min = float(t.min())
    stamped_full_sweep = ref == "absolute" and float(t.max()) - t_min >= FULL_SWEEP * period
    if start is None or abs(t_min - start) <= START_SLACK * period or stamped_full_sweep:
        # absolute stamps without a start, or a full sweep of absolute stamps (whatever the stamp's
        # latency): from its first point
        return t_min, ref
    return start, ref


def sweep_middle_offset(times: np.ndarray, scan_period: float, reference: str = "auto",
                        sweep_start: float | None = None) -> float | None:
    """Seconds from a frame's stamp to the middle of its sweep (fraction 0.5, where deskewing moves the
    points and the frame's pose refers), read from the frame's per-point times (seconds).

    The fractions are those of :func:`normalise_times` (same ``reference`` and ``sweep_start``): times
    relative to the sweep count from the stamp (a driver stamping the sweep's start gives about
    ``+scan_period / 2``, one stamping its end ``-scan_period / 2``); absolute times count from
    ``sweep_start``, the stamp on their clock.

    Returns
    -------
    float or None
        None when the times cannot say: no times, absolute times without ``sweep_start``, or no
        ``scan_period``.
    """
    t = np.asarray(times, np.float64)
    if t.size == 0 or not np.all(np.isfinite(t)) or not scan_period or scan_period <= 0.0:
        return None
    if reference not in TIME_REFERENCES:
        raise ValueError(f"time reference must be one of {TIME_REFERENCES}, got {reference!r}")
    period = float(scan_period)
    origin, ref = _sweep_origin(t, period, reference, sweep_start)
    if ref == "absolute":
        if sweep_start is None:
            return None
        origin -= float(sweep_start)
    return origin + 0.5 * period


def sweep_motion_from_velocity(frame_motion: np.ndarray, frame_period: float = 0.1,
                               scan_period: float = 0.1) -> np.ndarray:
    """The sweep motion (start -> end pose) from the motion between two frames (constant velocity).

    ``frame_motion`` is the pose of frame k in frame k-1 (the odometry's last increment);
    the sweep lasts ``scan_period`` of the ``frame_period`` between frames.
    """
    from factors.se3 import exp_se3

    return exp_se3(log_se3(np.asarray(frame_motion, np.float64)) * (scan_period / frame_period))


def _check(points: np.ndarray, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    p = np.asarray(points, np.float64)
    t = np.asarray(times, np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or t.shape != (len(p),):
        raise ValueError(f"points must be (N, 3) and times (N,), got {p.shape} and {t.shape}")
    return p, t


_TAYLOR_BELOW = 0.05  # rad: below, 3-term Taylor series of A, B, C (error < theta^6/5040 < 4e-12)


def _apply_scaled_twist(p: np.ndarray, s: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """``Exp(s_i xi) p_i`` for every point, without forming a matrix per point.

    With ``W = [omega]x`` and ``theta_i = |s_i| |omega|``, ``Exp(s xi) p = p + s A W p + s^2 B W^2 p
    + s v + s^2 B W v + s^3 C W^2 v`` (``A = sin(theta)/theta``, ``B = (1 - cos theta)/theta^2``,
    ``C = (theta - sin theta)/theta^3``), so the per-point work is three scalar coefficients
    and two fixed 3x3 products, done coordinate by coordinate on contiguous rows (a
    120k-point sweep takes a few ms). When every ``theta_i`` is below 0.05 rad (a sweep
    turning less than ~6 degrees) A, B, C come from their Taylor series.
    """
    w, v = xi[:3], xi[3:]
    W = hat(w)
    W2 = W @ W
    norm_w = float(np.linalg.norm(w))
    if float(np.abs(s).max()) * norm_w < _TAYLOR_BELOW:
        t2 = (s * norm_w) ** 2
        A = 1.0 - t2 * (1.0 / 6.0 - t2 / 120.0)
        B = 0.5 - t2 * (1.0 / 24.0 - t2 / 720.0)
        C = 1.0 / 6.0 - t2 * (1.0 / 120.0 - t2 / 5040.0)
    else:
        theta = np.abs(s) * norm_w
        small = theta < 1e-4
        th = np.where(small, 1.0, theta)
        th2 = th * th
        t2 = theta * theta
        A = np.where(small, 1.0 - t2 / 6.0, np.sin(th) / th)
        B = np.where(small, 0.5 - t2 / 24.0, (1.0 - np.cos(th)) / th2)
        C = np.where(small, 1.0 / 6.0 - t2 / 120.0, (th - np.sin(th)) / (th2 * th))
    a = s * A
    b = s * s * B
    c = s * s * s * C
    Wv, W2v = W @ v, W2 @ v
    rows = np.ascontiguousarray(p.T)
    out = np.empty((3, len(p)))
    for r in range(3):
        wp = W[r, 0] * rows[0] + W[r, 1] * rows[1] + W[r, 2] * rows[2]
        w2p = W2[r, 0] * rows[0] + W2[r, 1] * rows[1] + W2[r, 2] * rows[2]
        out[r] = rows[r] + a * wp + b * (w2p + Wv[r]) + s * v[r] + c * W2v[r]
    return np.ascontiguousarray(out.T)


def deskew(points: np.ndarray, times: np.ndarray, sweep_motion: np.ndarray,
           reference_time: float = 0.5) -> np.ndarray:
    """Move every point into the sensor frame at ``reference_time`` (constant velocity).

    Parameters
    ----------
    points : (N, 3) array
        Points, each in the sensor frame at its own time.
    times : (N,) array
        Sweep fractions in ``[0, 1]`` (:func:`times_from_azimuth`, :func:`normalise_times`).
    sweep_motion : (4, 4) array
        Sensor pose at the end of the sweep in the frame at its start.
    reference_time : float
        Sweep fraction the points are moved to (0.5: the middle).

    Returns
    -------
    np.ndarray
        ``(N, 3)`` float64 deskewed points.
    """
    return _move(points, times, sweep_motion, reference_time, sign=1.0)


def deskew_covariances(covariances: np.ndarray, times: np.ndarray, sweep_motion: np.ndarray,
                       reference_time: float = 0.5) -> np.ndarray:
    """Covariances of points that :func:`deskew` moves, in their new frames: each ``C_i`` is turned
    by the rotation of the point's motion, ``R_i C_i R_iᵀ`` with ``R_i = Exp((t_i − reference_time) ω)``
    (``ω``: the rotation of ``Log(sweep_motion)``).

    Parameters
    ----------
    covariances : (N, 3, 3) array
    times : (N,) array
        Sweep fractions, as for :func:`deskew`.
    sweep_motion : (4, 4) array
    reference_time : float

    Returns
    -------
    np.ndarray
        ``(N, 3, 3)`` float64.
    """
    C = np.asarray(covariances, np.float64)
    t = np.asarray(times, np.float64)
    if C.ndim != 3 or C.shape[1:] != (3, 3) or t.shape != (len(C),):
        raise ValueError(f"covariances must be (N, 3, 3) and times (N,), got {C.shape} and {t.shape}")
    w = log_se3(np.asarray(sweep_motion, np.float64))[:3]
    if len(C) == 0 or not np.any(w):
        return C.copy()
    twists = np.zeros((len(C), 6))
    twists[:, :3] = (t - reference_time)[:, None] * w
    R = exp_se3_batch(twists)[:, :3, :3]
    return R @ C @ np.swapaxes(R, 1, 2)


def distort(points: np.ndarray, times: np.ndarray, sweep_motion: np.ndarray,
            reference_time: float = 0.5) -> np.ndarray:
    """The inverse of :func:`deskew`: what a sensor moving with ``sweep_motion`` measures.

    ``points`` are in the sensor frame at ``reference_time``; each is returned in the sensor
    frame at its own time, ``Exp(-(t - s) xi) p``. ``deskew(distort(p, t, M), t, M) == p``.
    """
    return _move(points, times, sweep_motion, reference_time, sign=-1.0)


def _move(points: np.ndarray, times: np.ndarray, sweep_motion: np.ndarray, reference_time: float,
          sign: float) -> np.ndarray:
    """``Exp(sign * (t - reference_time) * xi) p`` for every point (``xi = Log(sweep_motion)``)."""
    p, t = _check(points, times)
    if len(p) == 0:
        return p.copy()
    xi = log_se3(np.asarray(sweep_motion, np.float64))
    if not np.any(xi):
        return p.copy()
    return _apply_scaled_twist(p, sign * (t - reference_time), xi)
