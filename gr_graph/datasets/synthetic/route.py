"""The project's own driving route: a drive through a street grid, generated from a seed.

The embedded synthetic sequence follows this route (no third-party trajectory is shipped).
It has the character of KITTI odometry 00 without copying it: 4,541 frames at 10 Hz, 3.7 km,
0-13 m/s, 90-degree turns on a street grid, several stretches driven again (one of them in
the opposite direction), stops at intersections and gentle height changes.

How a route is built (deterministic for ``(seed, config)``):

1. **Grid.** ``grid_nodes`` intersections whose streets are spaced 80-150 m apart.
2. **Walk.** A random walk over the grid without U-turns, preferring streets not yet driven
   (a driven street is taken again with weight ``revisit_weight``; never a third time).
3. **Geometry.** Straight streets joined by circular arcs of ``turn_radius`` at the turns,
   driven ``lane_offset`` right of the street's centre line (right-hand traffic: a street
   driven in the other direction is 2 x ``lane_offset`` away), smoothed with a Gaussian of
   ``smoothing`` metres so that curvature ramps in and out instead of jumping.
4. **Speed.** Per street a cruise speed; at most ``sqrt(lateral_accel / curvature)`` in
   turns; zero at ``n_stops`` stop lines 15 m before intersection centres, held 12-18 s; limited
   acceleration and braking (forward/backward passes), then a Gaussian of ``speed_smoothing``
   seconds over time for smooth jerk (less 5 cm/s around stops, so that they are exact
   standstills). The cruise speeds are scaled (bisection) so that the 4,541 frames cover
   ``length_m``.
5. **Height and attitude.** The height is a function of place (three long sinusoids, grades
   of a few percent), so revisits pass at the same height; pitch follows the grade along the
   heading plus squat/dive under acceleration, roll the cross slope plus body roll in turns.
6. **Acceptance.** The walk is redrawn (attempt 0, 1, ...) until the route has at least
   ``min_revisits`` revisit stretches (at least one in the opposite direction, the first after
   ``first_revisit_after`` frames), ``n_stops`` stops of 10 s or more and a top speed of at
   most ``max_speed``; the attempt used is recorded.

The route reports what it built (:class:`Route`: revisit stretches with frame ranges and
direction, stops, turns), measured on the final frames, not taken from the plan.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.spatial import cKDTree

log = logging.getLogger(__name__)

N_FRAMES = 4541
FRAME_DT = 0.1


class RouteGenerationError(RuntimeError):
    """No walk satisfying the acceptance criteria was found within ``max_attempts``."""


@dataclass(frozen=True)
class RouteConfig:
    """Parameters of the generated route (metres, seconds, m/s, m/s²)."""

    n_frames: int = N_FRAMES
    frame_dt: float = FRAME_DT
    time_jitter: float = 0.0005
    """Uniform jitter (s) of each timestamp around ``k * frame_dt`` (frame 0 is at 0); timestamps
    are rounded to microseconds, so that they survive a text round trip exactly."""
    length_m: float = 3700.0
    grid_nodes: tuple[int, int] = (6, 5)
    block_min: float = 80.0
    block_max: float = 150.0
    revisit_weight: float = 0.2
    turn_radius: float = 10.0
    lane_offset: float = 1.75
    smoothing: float = 2.0
    cruise_min: float = 8.5
    cruise_max: float = 12.5
    max_speed: float = 13.0
    lateral_accel: float = 2.0
    accel: float = 1.2
    brake: float = 1.6
    speed_smoothing: float = 0.6
    n_stops: int = 2
    stop_min_s: float = 12.0
    stop_max_s: float = 18.0
    height_amplitude: float = 3.0
    pitch_per_accel: float = 0.005
    """Squat/dive (rad per m/s² of longitudinal acceleration; nose up when accelerating)."""
    roll_per_accel: float = 0.006
    """Body roll (rad per m/s² of lateral acceleration; outwards in a turn)."""
    min_revisits: int = 4
    revisit_radius: float = 6.0
    revisit_min_length: float = 40.0
    revisit_min_separation: float = 200.0
    """A frame revisits an earlier one only if the route drove this far in between (m)."""
    first_revisit_after: int = 1000
    max_attempts: int = 400
    step: float = 0.2
    """Arc-length sampling of the geometry (m)."""


@dataclass(frozen=True)
class RevisitStretch:
    """Frames ``frames[0]:frames[1]`` drive again where frames ``earlier[0]:earlier[1]`` drove."""

    frames: tuple[int, int]
    earlier: tuple[int, int]
    direction: str
    """``"same"`` or ``"opposite"`` (driven the other way, on the other lane)."""
    length_m: float


@dataclass(frozen=True)
class Stop:
    """The vehicle stands still (speed < 1 mm/s) for frames ``frames[0]:frames[1]``."""

    frames: tuple[int, int]
    duration_s: float


@dataclass(frozen=True)
class Turn:
    """A 90-degree turn at an intersection: ``frame`` nearest its apex, signed angle (left > 0)."""

    frame: int
    angle_deg: float


@dataclass(frozen=True)
class Route:
    """A generated route.

    Attributes
    ----------
    seed : int
        The route seed.
    attempt : int
        The walk drawn for this seed that passed the acceptance criteria.
    times : np.ndarray
        ``(K,)`` float64 timestamps (s), frame 0 at 0.
    T_w_velo : np.ndarray
        ``(K, 4, 4)`` LiDAR poses (x forward, y left, z up), world = LiDAR frame of frame 0.
    speed : np.ndarray
        ``(K,)`` speed (m/s).
    length_m : float
        Distance driven over the K frames (m).
    revisits, stops, turns : tuple
        What the route contains, measured on the frames.
    config : RouteConfig
    """

    seed: int
    attempt: int
    times: np.ndarray
    T_w_velo: np.ndarray
    speed: np.ndarray
    length_m: float
    revisits: tuple[RevisitStretch, ...]
    stops: tuple[Stop, ...]
    turns: tuple[Turn, ...]
    config: RouteConfig = field(repr=False)

    def describe(self) -> str:
        """One line: length, duration, speeds, revisits, stops, turns."""
        opp = sum(r.direction == "opposite" for r in self.revisits)
        return (f"route seed {self.seed}: {len(self.times)} frames, {self.length_m / 1000:.2f} km in "
                f"{self.times[-1]:.0f} s, speed 0-{self.speed.max():.1f} m/s, {len(self.turns)} turns, "
                f"{len(self.revisits)} revisit stretches ({opp} opposite), "
                f"{len(self.stops)} stops ({', '.join(f'{s.duration_s:.0f} s' for s in self.stops)})")


# ------------------------------------------------------------------------------ the walk
_DIRS = np.array([[1, 0], [0, 1], [-1, 0], [0, -1]])  # E, N, W, S


def _draw_walk(rng: np.random.Generator, cfg: RouteConfig, xs: np.ndarray, ys: np.ndarray,
               min_length: float) -> list[tuple[int, int]]:
    """Intersections visited by a walk without U-turns, at least ``min_length`` long."""
    nx, ny = len(xs), len(ys)
    node = (int(rng.integers(1, nx - 1)), int(rng.integers(1, ny - 1)))
    heading = int(rng.integers(4))
    nodes = [node]
    used: dict[frozenset, int] = {}
    length = 0.0
    while length < min_length:
        options, weights = [], []
        for turn, base in ((0, 1.0), (1, 0.8), (-1, 0.8)):
            h = (heading + turn) % 4
            nxt = (node[0] + _DIRS[h][0], node[1] + _DIRS[h][1])
            if not (0 <= nxt[0] < nx and 0 <= nxt[1] < ny):
                continue
            n_used = used.get(frozenset((node, nxt)), 0)
            if n_used >= 2:
                continue
            options.append((h, nxt))
            weights.append(base * (cfg.revisit_weight if n_used else 1.0))
        if not options:
            break
        w = np.asarray(weights)
        h, nxt = options[int(rng.choice(len(options), p=w / w.sum()))]
        edge = frozenset((node, nxt))
        used[edge] = used.get(edge, 0) + 1
        length += abs(xs[nxt[0]] - xs[node[0]]) + abs(ys[nxt[1]] - ys[node[1]])
        node, heading = nxt, h
        nodes.append(node)
    return nodes


def _centre_line(corners: np.ndarray, radius: float, step: float) -> tuple[np.ndarray, list[int], list[int]]:
    """Sample the polyline through ``corners`` with arcs at the turns, every ~``step`` m.

    Returns the samples ``(N, 2)``, the sample index of each turn apex, and the sample index
    at each intermediate corner (where the walk passes an intersection).
    """
    pts: list[np.ndarray] = []
    apex: list[int] = []
    passes: list[int] = []
    cur = corners[0].astype(float)

    def line(a: np.ndarray, b: np.ndarray) -> None:
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / step)))
        pts.append(a + (b - a) * (np.arange(n) / n)[:, None])

    for k in range(1, len(corners) - 1):
        d_in = corners[k] - corners[k - 1]
        d_out = corners[k + 1] - corners[k]
        d_in, d_out = d_in / np.linalg.norm(d_in), d_out / np.linalg.norm(d_out)
        cross = d_in[0] * d_out[1] - d_in[1] * d_out[0]
        if abs(cross) < 1e-9:  # straight through the intersection
            line(cur, corners[k])
            passes.append(sum(len(p) for p in pts))
            cur = corners[k].astype(float)
            continue
        entry = corners[k] - d_in * radius
        line(cur, entry)
        left = np.array([-d_in[1], d_in[0]]) * np.sign(cross)
        centre = entry + left * radius
        a0 = np.arctan2(*(entry - centre)[::-1])
        n = max(2, int(np.ceil(radius * np.pi / 2 / step)))
        ang = a0 + np.sign(cross) * (np.pi / 2) * np.arange(n) / n
        start = sum(len(p) for p in pts)
        pts.append(centre + radius * np.c_[np.cos(ang), np.sin(ang)])
        apex.append(start + n // 2)
        passes.append(start + n // 2)
        cur = corners[k] + d_out * radius
    line(cur, corners[-1])
    pts.append(corners[-1][None].astype(float))
    return np.concatenate(pts), apex, passes


def _resample(xy: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Resample a dense polyline every ``step`` m of arc length; also return the old arc length."""
    s_old = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    s = np.arange(0.0, s_old[-1], step)
    return np.c_[np.interp(s, s_old, xy[:, 0]), np.interp(s, s_old, xy[:, 1])], s_old


# ------------------------------------------------------------------------------ the speed
def _speed_limits(kappa: np.ndarray, seg_id: np.ndarray, seg_speed: np.ndarray, scale: float,
                  cfg: RouteConfig) -> np.ndarray:
    v = np.minimum(seg_speed[seg_id] * scale, cfg.max_speed)
    return np.minimum(v, np.sqrt(cfg.lateral_accel / np.maximum(np.abs(kappa), 1e-9)))


def _passes(vlim: np.ndarray, stops: np.ndarray, cfg: RouteConfig) -> np.ndarray:
    """Speed over arc length under the limits, zero at ``stops``, with accel/brake limits."""
    v = vlim.copy()
    v[stops] = 0.0
    a2, b2 = 2 * cfg.accel * cfg.step, 2 * cfg.brake * cfg.step
    out = np.empty_like(v)
    out[0] = v[0]
    for i in range(1, len(v)):
        out[i] = min(v[i], np.sqrt(out[i - 1] ** 2 + a2))
    for i in range(len(v) - 2, -1, -1):
        out[i] = min(out[i], np.sqrt(out[i + 1] ** 2 + b2))
    return out


def _drive(v: np.ndarray, stops: np.ndarray, holds: np.ndarray, cfg: RouteConfig,
           duration: float) -> tuple[np.ndarray, np.ndarray]:
    """Distance travelled on a fine time grid (``dt = 0.02 s``) for the speed-over-distance profile.

    Returns ``(tau, s(tau))`` with the speed smoothed over time (Gaussian of
    ``speed_smoothing`` s). Stops hold their position for their hold time.
    """
    ds = cfg.step
    vm = 0.5 * (v[1:] + v[:-1])
    dt = ds / np.maximum(vm, 1e-3)
    t = np.concatenate([[0.0], np.cumsum(dt)])
    s = np.arange(len(v)) * ds
    # insert the holds: time shifts by the hold after each stop sample
    shift = np.zeros(len(v))
    for i, h in zip(stops, holds):
        shift[i + 1:] += h
    t_knots = np.concatenate([t + shift, t[stops] + shift[stops] + holds])
    s_knots = np.concatenate([s, s[stops]])
    order = np.argsort(t_knots, kind="stable")
    t_knots, s_knots = t_knots[order], s_knots[order]
    tau = np.arange(0.0, duration + 1.0, 0.02)
    s_tau = np.interp(tau, t_knots, s_knots)
    vel = np.gradient(s_tau, tau)
    # smooth over time; around the holds shift down by 5 cm/s (clipped at 0) so that the car
    # stands exactly still instead of creeping on the Gaussian's tails (elsewhere no shift:
    # the distance must stay where the speed limits were computed)
    holding = np.zeros(len(tau))
    for i, h in zip(stops, holds):
        t_stop = t[i] + shift[i]
        holding[(tau >= t_stop) & (tau <= t_stop + h)] = 1.0
    near = np.clip(3.0 * gaussian_filter1d(holding, 1.0 / 0.02, mode="nearest"), 0.0, 1.0)
    vel = np.maximum(gaussian_filter1d(vel, cfg.speed_smoothing / 0.02, mode="nearest") - 0.05 * near, 0.0)
    s_smooth = np.concatenate([[0.0], np.cumsum(0.5 * (vel[1:] + vel[:-1]) * 0.02)])
    return tau, s_smooth


# ------------------------------------------------------------------------------ attitude
def _rotations(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """``Rz(yaw) Ry(pitch) Rx(roll)`` for arrays of angles."""
    cy, sy, cp, sp, cr, sr = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    R = np.empty((len(yaw), 3, 3))
    R[:, 0, 0] = cy * cp
    R[:, 0, 1] = cy * sp * sr - sy * cr
    R[:, 0, 2] = cy * sp * cr + sy * sr
    R[:, 1, 0] = sy * cp
    R[:, 1, 1] = sy * sp * sr + cy * cr
    R[:, 1, 2] = sy * sp * cr - cy * sr
    R[:, 2, 0] = -sp
    R[:, 2, 1] = cp * sr
    R[:, 2, 2] = cp * cr
    return R


class _Height:
    """Height of the road at a place: three long sinusoids (wavelengths 400-900 m)."""

    def __init__(self, rng: np.random.Generator, amplitude: float):
        ang = rng.uniform(0, 2 * np.pi, 3)
        self.k = (2 * np.pi / rng.uniform(400.0, 900.0, 3))[:, None] * np.c_[np.cos(ang), np.sin(ang)]
        self.phase = rng.uniform(0, 2 * np.pi, 3)
        self.amp = amplitude * rng.uniform(0.5, 1.0, 3) / 3

    def __call__(self, xy: np.ndarray) -> np.ndarray:
        return (self.amp * np.sin(xy @ self.k.T + self.phase)).sum(axis=1)

    def gradient(self, xy: np.ndarray) -> np.ndarray:
        return (self.amp * np.cos(xy @ self.k.T + self.phase)) @ self.k


# ------------------------------------------------------------------------------ analysis
def find_revisits(positions: np.ndarray, yaw: np.ndarray, travelled: np.ndarray, radius: float = 6.0,
                  min_separation: float = 200.0, min_length: float = 40.0) -> tuple[RevisitStretch, ...]:
    """Stretches of frames that pass within ``radius`` of an earlier frame, heading (anti)parallel.

    A frame ``i`` revisits an earlier frame ``j`` if the route drove at least
    ``min_separation`` m from ``j`` to ``i``, the two are within ``radius`` m (xy) and their
    headings differ by less than 25° (same direction) or more than 155° (opposite). Runs of
    consecutive revisiting frames with the same direction and a continuous earlier pass form
    a stretch; stretches shorter than ``min_length`` m (crossings, turns onto a driven
    street) are dropped.
    """
    xy = positions[:, :2]
    tree = cKDTree(xy)
    cos_tol = np.cos(np.radians(25.0))
    match = np.full(len(xy), -1)
    direction = np.zeros(len(xy), dtype=int)
    for i, nb in enumerate(tree.query_ball_point(xy, radius)):
        nb = np.asarray(nb, dtype=int)
        nb = nb[travelled[nb] <= travelled[i] - min_separation]
        if len(nb) == 0:
            continue
        c = np.cos(yaw[nb] - yaw[i])
        ok = np.abs(c) >= cos_tol
        if not ok.any():
            continue
        nb, c = nb[ok], c[ok]
        k = int(np.argmin(np.linalg.norm(xy[nb] - xy[i], axis=1)))
        match[i], direction[i] = nb[k], 1 if c[k] > 0 else -1
    out: list[RevisitStretch] = []
    i = 0
    while i < len(xy):
        if match[i] < 0:
            i += 1
            continue
        j = i
        while (j + 1 < len(xy) and match[j + 1] >= 0 and direction[j + 1] == direction[i]
               and abs(travelled[match[j + 1]] - travelled[match[j]]) < 20.0):
            j += 1
        length = travelled[j] - travelled[i]
        if length >= min_length:
            e = match[i:j + 1]
            out.append(RevisitStretch((i, j + 1), (int(e.min()), int(e.max()) + 1),
                                      "same" if direction[i] > 0 else "opposite", float(length)))
        i = j + 1
    return tuple(out)


def find_stops(speed: np.ndarray, times: np.ndarray, threshold: float = 0.001,
               min_duration: float = 10.0) -> tuple[Stop, ...]:
    """Runs of frames with ``speed < threshold`` lasting at least ``min_duration`` s."""
    still = np.r_[False, speed < threshold, False]
    edges = np.flatnonzero(np.diff(still.astype(int)))
    out = []
    for a, b in zip(edges[::2], edges[1::2]):
        dur = float(times[b - 1] - times[a]) if b - 1 > a else 0.0
        if dur >= min_duration:
            out.append(Stop((int(a), int(b)), dur))
    return tuple(out)


# ------------------------------------------------------------------------------ building
def _build(seed: int, attempt: int, cfg: RouteConfig) -> Route | None:
    rng = np.random.default_rng([int(seed), int(attempt), 0x2017E])
    nx, ny = cfg.grid_nodes
    xs = np.concatenate([[0.0], np.cumsum(rng.uniform(cfg.block_min, cfg.block_max, nx - 1))])
    ys = np.concatenate([[0.0], np.cumsum(rng.uniform(cfg.block_min, cfg.block_max, ny - 1))])
    nodes = _draw_walk(rng, cfg, xs, ys, cfg.length_m * 1.3)
    corners = np.array([[xs[i], ys[j]] for i, j in nodes])
    if len(corners) < 4 or np.sum(np.linalg.norm(np.diff(corners, axis=0), axis=1)) < cfg.length_m * 1.2:
        return None
    corners[0] = 0.5 * (corners[0] + corners[1])  # start mid-block
    centre, apex_idx, pass_idx = _centre_line(corners, cfg.turn_radius, cfg.step / 2)
    # lane offset to the right of the direction of travel, then Gaussian smoothing
    d = np.gradient(centre, axis=0)
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    lane = centre + cfg.lane_offset * np.c_[d[:, 1], -d[:, 0]]
    sig = cfg.smoothing / (cfg.step / 2)
    lane = np.c_[gaussian_filter1d(lane[:, 0], sig, mode="nearest"),
                 gaussian_filter1d(lane[:, 1], sig, mode="nearest")]
    xy, s_dense = _resample(lane, cfg.step)
    n = len(xy)
    dxy = np.gradient(xy, axis=0)
    yaw = np.unwrap(np.arctan2(dxy[:, 1], dxy[:, 0]))
    kappa = gaussian_filter1d(np.gradient(yaw) / cfg.step, 2.0, mode="nearest")

    def at(i_dense: int) -> int:  # dense centre-line sample -> resampled index
        return int(min(n - 1, np.searchsorted(np.arange(n) * cfg.step, s_dense[i_dense])))

    apex = np.array([at(i) for i in apex_idx], dtype=int)
    passes = np.array([at(i) for i in pass_idx], dtype=int)
    # per street (between turns) a cruise speed
    seg_id = np.searchsorted(apex, np.arange(n))
    seg_speed = rng.uniform(cfg.cruise_min, cfg.cruise_max, len(apex) + 1)
    # stops: stop lines 15 m before intersection centres, spread over the first ~85 % of the drive
    stop_len = int(round(15.0 / cfg.step))
    cand = passes[(passes * cfg.step > 300.0) & (passes * cfg.step < 0.85 * cfg.length_m)]
    stops: list[int] = []
    for c in rng.permutation(cand):
        if all(abs(c - s) * cfg.step > 700.0 for s in stops):
            stops.append(int(c) - stop_len)
        if len(stops) == cfg.n_stops:
            break
    if len(stops) < cfg.n_stops:
        return None
    stops_arr = np.array(sorted(stops), dtype=int)
    holds = rng.uniform(cfg.stop_min_s, cfg.stop_max_s, len(stops_arr))
    duration = (cfg.n_frames - 1) * cfg.frame_dt + 0.01
    jitter = rng.uniform(-cfg.time_jitter, cfg.time_jitter, cfg.n_frames)
    height = _Height(rng, cfg.height_amplitude)

    def travelled(scale: float) -> tuple[np.ndarray, np.ndarray]:
        v = _passes(_speed_limits(kappa, seg_id, seg_speed, scale, cfg), stops_arr, cfg)
        return _drive(v, stops_arr, holds, cfg, duration)

    lo, hi = 0.5, cfg.max_speed / cfg.cruise_min
    tau, s_tau = travelled(hi)
    if np.interp(duration, tau, s_tau) < cfg.length_m:
        return None  # cannot cover the length within the speed limit
    for _ in range(24):
        mid = 0.5 * (lo + hi)
        tau, s_tau = travelled(mid)
        if np.interp(duration - 0.01, tau, s_tau) < cfg.length_m:
            lo = mid
        else:
            hi = mid
    tau, s_tau = travelled(hi)
    if s_tau[-1] > (n - 1) * cfg.step:
        return None

    times = np.round(np.arange(cfg.n_frames) * cfg.frame_dt + jitter, 6)  # microseconds, as logged
    times[0] = 0.0
    s_k = np.interp(times, tau, s_tau)
    vel_tau = np.gradient(s_tau, tau)
    speed = np.interp(times, tau, vel_tau)
    acc = np.interp(times, tau, np.gradient(vel_tau, tau))
    grid = np.arange(n) * cfg.step
    p = np.c_[np.interp(s_k, grid, xy[:, 0]), np.interp(s_k, grid, xy[:, 1])]
    psi = np.interp(s_k, grid, yaw)
    kap = np.interp(s_k, grid, kappa)
    g = height.gradient(p)
    fwd = np.c_[np.cos(psi), np.sin(psi)]
    left = np.c_[-np.sin(psi), np.cos(psi)]
    pitch = -np.arctan((g * fwd).sum(1)) - cfg.pitch_per_accel * acc
    roll = np.arctan((g * left).sum(1)) + cfg.roll_per_accel * speed**2 * kap
    T = np.tile(np.eye(4), (cfg.n_frames, 1, 1))
    T[:, :3, :3] = _rotations(psi, pitch, roll)
    T[:, :2, 3] = p
    T[:, 2, 3] = height(p)
    T0_inv = np.linalg.inv(T[0])
    T = T0_inv @ T
    T[0] = np.eye(4)
    T[:, 3] = [0.0, 0.0, 0.0, 1.0]

    revisits = find_revisits(T[:, :3, 3], psi - psi[0], s_k, cfg.revisit_radius,
                             cfg.revisit_min_separation, cfg.revisit_min_length)
    found_stops = find_stops(speed, times)
    apex_s = apex * cfg.step
    turns = []
    for a in apex_s[apex_s < s_k[-1] - 30.0]:
        k = int(np.searchsorted(s_k, a))
        before = np.interp(a - 30.0, grid, yaw)
        after = np.interp(a + 30.0, grid, yaw)
        turns.append(Turn(k, float(np.degrees(after - before))))
    route = Route(int(seed), int(attempt), times, T, speed, float(s_k[-1]), revisits, found_stops,
                  tuple(turns), cfg)
    opposite = [r for r in revisits if r.direction == "opposite"]
    if (len(revisits) < cfg.min_revisits or not opposite
            or revisits[0].frames[0] < cfg.first_revisit_after
            or len(found_stops) < cfg.n_stops or speed.max() > cfg.max_speed + 1e-6):
        return None
    return route


@lru_cache(maxsize=4)
def generate_route(seed: int = 0, config: RouteConfig | None = None) -> Route:
    """The route of ``seed`` (cached per process; deterministic for ``(seed, config)``).

    Raises
    ------
    ValueError
        A negative seed.
    RouteGenerationError
        No acceptable walk within ``config.max_attempts`` attempts.
    """
    if int(seed) < 0:
        raise ValueError(f"route seed must be >= 0, got {seed}")
    cfg = config or RouteConfig()
    for attempt in range(cfg.max_attempts):
        route = _build(int(seed), attempt, cfg)
        if route is not None:
            for arr in (route.times, route.T_w_velo, route.speed):
                arr.setflags(write=False)
            log.info("%s (walk attempt %d)", route.describe(), attempt)
            return route
    raise RouteGenerationError(f"route seed {seed}: no walk met the acceptance criteria in "
                               f"{cfg.max_attempts} attempts")
