"""Moving vehicles and pedestrians of the synthetic town, ray cast at each ray's own time.

Every actor follows the sensor path's own streets (the path resampled every 0.5 m, arc
length ``s``) at a lateral offset, with a deterministic arc-length law ``s(t)`` tabulated
every ``time_step`` seconds (linear in between, so the speed is piecewise constant and an
actor at ``t`` and ``t + dt`` is displaced by ``speed * dt`` along its lane):

- **lead vehicles** drive ahead of the ego vehicle in its lane: ``s(t) = s_ego(t + tau(t)) + g0``,
  a time headway ``tau`` that falls from ``headway_far`` (it appears far ahead) to 1.5-3.5 s and
  rises again (it pulls away), plus a standstill gap ``g0`` of 7-9 m, so a lead vehicle brakes,
  stops and starts like the ego vehicle did ``tau`` seconds later and never reaches it (urban
  time headways of 1-3 s: e.g. Vogel 2003; standstill gaps 2-3 m bumper to bumper);
- **oncoming vehicles** drive the other lane (``oncoming_offset`` = 3.3 m left of the ego lane,
  right-hand traffic) against the route at a constant 8-13 m/s (30-47 km/h, urban limits of 30-50 km/h),
  appearing 80-150 m ahead of the ego vehicle and vanishing 60 m behind it;
- **pedestrians** walk on the sidewalks (5.4-7.6 m off the ego lane) at 1.2-1.5 m/s (typical
  free walking speeds, Knoblauch et al. 1996; Fruin 1971), some standing still, each for a
  window of 30-90 s around the time the ego vehicle passes.

Every actor is checked against the ego vehicle's footprint (``ego_box``, inflated by
``clearance``) every ``time_step`` over its whole life, and redrawn (up to 20 times, then
dropped: counted in ``n_rejected``) if they would overlap, so no actor ever touches the ego
vehicle or stands where the sensor is. With ``obstacles`` (circles of the town's parked cars,
tree trunks, poles and bushes: :func:`town_obstacles`), draws that would run through one are
redrawn the same way.

Shapes: vehicles are curved car meshes (:func:`meshes.car_mesh`, 3.8-4.9 x 1.7-1.95 x
1.4-1.55 m), pedestrians lofted bodies of 1.55-1.90 m (:func:`meshes.pedestrian_mesh`); a few
templates of each, every template in its own open3d ``RaycastingScene`` in its own frame.
:meth:`Actors.cast` selects, per actor alive during the rays' time span, the rays whose
azimuth can reach it, moves them into the actor's frame at *each ray's own time* (exact
motion, no time bins) and casts them against the template.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from gr_graph.datasets.synthetic.meshes import MATERIAL, car_mesh, pedestrian_mesh
from gr_graph.datasets.synthetic.town import resample_path_with_arc_length

log = logging.getLogger(__name__)

KIND_LEAD, KIND_ONCOMING, KIND_PEDESTRIAN = 0, 1, 2
KIND_NAMES = ("lead vehicle", "oncoming vehicle", "pedestrian")


@dataclass(frozen=True)
class ActorsConfig:
    """How many actors, and their ranges (metres, seconds, m/s)."""

    n_lead: int = 25
    """Lead vehicles over the whole route (each alive 20-60 s)."""
    n_oncoming: int = 60
    """Oncoming vehicles over the whole route (each alive while it passes, ~15-25 s)."""
    n_pedestrians: int = 100
    """Pedestrians over the whole route (each alive 30-90 s around the time the ego vehicle passes)."""
    oncoming_offset: float = 3.3
    """Oncoming lane centre, m left of the ego lane (residential lanes are 2.75-3.5 m wide)."""
    sidewalk: tuple[float, float] = (5.4, 7.6)
    """Pedestrians walk this far left or right of the ego lane (the town's sidewalk is 5-8 m)."""
    walk_speed: tuple[float, float] = (1.2, 1.5)
    standing_fraction: float = 0.2
    oncoming_speed: tuple[float, float] = (8.0, 13.0)
    headway_near: tuple[float, float] = (1.5, 3.5)
    headway_far: float = 8.0
    standstill_gap: tuple[float, float] = (7.0, 9.0)
    """Sensor to lead-vehicle centre at standstill (ego front ~2.1 m + gap 2-3 m + half a car)."""
    ego_box: tuple[float, float, float] = (2.1, -2.7, 1.0)
    """Ego vehicle footprint around the sensor: front, rear (x) and half width (m)."""
    clearance: float = 0.7
    time_step: float = 0.05
    vehicle_templates: int = 8
    pedestrian_templates: int = 6

    def __post_init__(self) -> None:
        if min(self.n_lead, self.n_oncoming, self.n_pedestrians) < 0:
            raise ValueError(f"actor counts must be >= 0, got {self}")
        if self.time_step <= 0:
            raise ValueError(f"time_step must be > 0, got {self.time_step}")


def _rects_overlap(c1: np.ndarray, yaw1: np.ndarray, h1: np.ndarray,
                   c2: np.ndarray, yaw2: np.ndarray, h2: np.ndarray) -> np.ndarray:
    """Separating-axis test of oriented rectangles (centres ``(n, 2)``, yaws, half sizes ``(n, 2)``)."""
    axes1 = np.stack([np.c_[np.cos(yaw1), np.sin(yaw1)], np.c_[-np.sin(yaw1), np.cos(yaw1)]], 1)
    axes2 = np.stack([np.c_[np.cos(yaw2), np.sin(yaw2)], np.c_[-np.sin(yaw2), np.cos(yaw2)]], 1)
    d = c2 - c1
    overlap = np.ones(len(d), dtype=bool)
    for axes in (axes1, axes2):
        for k in range(2):
            a = axes[:, k]
            r1 = (np.abs(np.einsum("ij,ij->i", a, axes1[:, 0])) * h1[:, 0]
                  + np.abs(np.einsum("ij,ij->i", a, axes1[:, 1])) * h1[:, 1])
            r2 = (np.abs(np.einsum("ij,ij->i", a, axes2[:, 0])) * h2[:, 0]
                  + np.abs(np.einsum("ij,ij->i", a, axes2[:, 1])) * h2[:, 1])
            overlap &= np.abs(np.einsum("ij,ij->i", a, d)) <= r1 + r2
    return overlap


def town_obstacles(footprints: dict[str, np.ndarray]) -> np.ndarray:
    """Circles ``(M, 3)`` ``x, y, r`` covering the town's parked cars (3 circles of half their
    width along each), tree trunks (0.35 m), poles and bushes (their radius)."""
    out = []
    cars = np.asarray(footprints.get("car", np.zeros((0, 4, 2))))
    if len(cars):
        a, b = 0.5 * (cars[:, 0] + cars[:, 3]), 0.5 * (cars[:, 1] + cars[:, 2])  # end midpoints
        half_w = 0.5 * np.linalg.norm(cars[:, 3] - cars[:, 0], axis=1)
        for f in (0.2, 0.5, 0.8):
            q = a + f * (b - a)
            out.append(np.c_[q, half_w])
    for kind, r in (("tree", 0.35), ("pole", None), ("bush", None)):
        circ = np.asarray(footprints.get(kind, np.zeros((0, 3))))
        if len(circ):
            out.append(np.c_[circ[:, :2], np.full(len(circ), r) if r else circ[:, 2]])
    return np.concatenate(out) if out else np.zeros((0, 3))


def _wrapped_intervals(lo: float, hi: float) -> list[tuple[float, float]]:
    """``[lo, hi]`` (radians, ``hi - lo < 2 pi``) as intervals inside ``[-pi, pi]``."""
    if lo < -np.pi:
        return [(-np.pi, hi), (lo + 2 * np.pi, np.pi)]
    if hi > np.pi:
        return [(lo, np.pi), (-np.pi, hi - 2 * np.pi)]
    return [(lo, hi)]


@dataclass
class _Actor:
    kind: int
    template: int
    offset: float
    """Lateral offset from the ego lane (m, left positive)."""
    backwards: bool
    """Faces against the direction of the route (oncoming, pedestrians walking back)."""
    t0: float
    s_table: np.ndarray
    """Arc length at ``t0 + k * time_step``."""
    albedo: float
    half_size: tuple[float, float]
    radius: float
    z_table: np.ndarray | None = None
    """Ground height under the actor at lane samples ``k_lo + j`` (every 0.5 m of arc length)."""
    k_lo: int = 0


class Actors:
    """The moving actors along a sensor path (deterministic for ``(path, seed, config)``).

    Parameters
    ----------
    times : np.ndarray
        ``(K,)`` timestamps (s) of the sensor poses.
    positions : np.ndarray
        ``(K, 3)`` sensor positions (world).
    seed : int
        Seeds the actors' draws.
    config : ActorsConfig, optional
    ground : callable, optional
        ``ground(xy (n, 2)) -> z (n,)`` terrain height (the town's ``GroundModel``); by default
        the sensor height minus ``sensor_height`` along the path.
    sensor_height : float
        Height of the sensor above the road (m), used without ``ground``.
    obstacles : np.ndarray, optional
        ``(M, 3)`` circles ``x, y, r`` that no actor may overlap (see :func:`town_obstacles`).
    """

    def __init__(self, times: np.ndarray, positions: np.ndarray, seed: int = 0,
                 config: ActorsConfig | None = None, ground=None, sensor_height: float = 1.73,
                 obstacles: np.ndarray | None = None):
        self.config = c = config or ActorsConfig()
        times = np.asarray(times, np.float64)
        positions = np.asarray(positions, np.float64)
        if positions.ndim != 2 or positions.shape[1] != 3 or len(positions) != len(times) or len(times) < 2:
            raise ValueError(f"Actors: need times (K>=2,) and positions (K, 3), got {times.shape}, "
                             f"{positions.shape}")
        self.seed = int(seed)
        self.times = times
        self.line, self.s_ego_frames = resample_path_with_arc_length(positions, 0.5)
        self.step = 0.5
        xy = self.line[:, :2]
        w = 4
        n = len(xy)
        tang = xy[np.minimum(np.arange(n) + w, n - 1)] - xy[np.maximum(np.arange(n) - w, 0)]
        tang /= np.maximum(np.linalg.norm(tang, axis=1, keepdims=True), 1e-9)
        self.left = np.c_[-tang[:, 1], tang[:, 0]]
        self.heading = np.unwrap(np.arctan2(tang[:, 1], tang[:, 0]))
        self._lane = np.c_[self.line, self.left, self.heading]
        self.sensor_height = sensor_height
        self.ground = ground
        self.obstacles = None if obstacles is None or len(obstacles) == 0 else np.asarray(obstacles, np.float64)
        self._obstacle_kd = None if self.obstacles is None else cKDTree(self.obstacles[:, :2])
        self.s_end = (len(self.line) - 1) * self.step
        veh_rng, ped_rng, shape_rng = (np.random.default_rng(s) for s in
                                       np.random.SeedSequence([self.seed, 0xAC7026]).spawn(3))
        self._build_templates(shape_rng)
        self.actors: list[_Actor] = []
        self.n_rejected = 0
        for kind, count in ((KIND_LEAD, c.n_lead), (KIND_ONCOMING, c.n_oncoming),
                            (KIND_PEDESTRIAN, c.n_pedestrians)):
            r = ped_rng if kind == KIND_PEDESTRIAN else veh_rng
            for _ in range(count):
                for _attempt in range(20):
                    actor = self._draw(kind, r)
                    if actor is not None and not self._touches_ego(actor) and not self._touches_obstacle(actor):
                        self._fill_ground(actor)
                        self.actors.append(actor)
                        break
                else:
                    self.n_rejected += 1
        self._t_start = np.array([a.t0 for a in self.actors])
        self._t_stop = np.array([a.t0 + (len(a.s_table) - 1) * c.time_step for a in self.actors])
        self._scenes: dict[tuple[int, int], object] = {}
        counts = np.bincount([a.kind for a in self.actors], minlength=3)
        log.info("actors (seed %d): %d lead vehicles, %d oncoming vehicles, %d pedestrians (%d draws dropped)",
                 self.seed, counts[0], counts[1], counts[2], self.n_rejected)

    # ---- construction ---------------------------------------------------------------------
    def _build_templates(self, rng: np.random.Generator) -> None:
        c = self.config
        self.vehicle_meshes = []
        for _ in range(c.vehicle_templates):
            L, W, H = rng.uniform(3.8, 4.9), rng.uniform(1.7, 1.95), rng.uniform(1.4, 1.55)
            v, t, glass = car_mesh(L, W, H, clearance=rng.uniform(0.14, 0.2), rng=rng)
            self.vehicle_meshes.append((v.astype(np.float32), t.astype(np.uint32), glass, (L / 2, W / 2)))
        self.pedestrian_meshes = []
        for _ in range(c.pedestrian_templates):
            v, t = pedestrian_mesh(rng.uniform(1.55, 1.9), rng=rng)
            self.pedestrian_meshes.append((v.astype(np.float32), t.astype(np.uint32),
                                           np.zeros(len(t), bool), (0.3, 0.3)))

    def s_ego(self, t: np.ndarray) -> np.ndarray:
        """Arc length of the ego sensor along the path at times ``t`` (linear between poses)."""
        return np.interp(t, self.times, self.s_ego_frames)

    def _draw(self, kind: int, rng: np.random.Generator) -> _Actor | None:
        c = self.config
        dt = c.time_step
        t_lo, t_hi = self.times[0], self.times[-1]
        if kind == KIND_LEAD:
            dur = rng.uniform(20.0, 60.0)
            t0 = rng.uniform(t_lo - 10.0, t_hi - 10.0)
            tt = t0 + np.arange(int(dur / dt) + 1) * dt
            near = rng.uniform(*c.headway_near)
            bump = np.sin(np.pi * np.clip((tt - t0) / dur, 0, 1)) ** 2
            ramp = np.clip(np.minimum(tt - t0, t0 + dur - tt) / 6.0, 0.0, 1.0)  # |dtau/dt| <= ~1
            tau = c.headway_far - (c.headway_far - near) * np.minimum(bump, ramp)
            s = self.s_ego(tt + tau) + rng.uniform(*c.standstill_gap)
            offset, backwards = 0.0, False
            template = int(rng.integers(len(self.vehicle_meshes)))
        elif kind == KIND_ONCOMING:
            v = rng.uniform(*c.oncoming_speed)
            t0 = rng.uniform(t_lo - 5.0, t_hi)
            s0 = self.s_ego(t0) + rng.uniform(80.0, 150.0)
            # alive until it is 60 m behind the ego vehicle (or 60 s)
            tt = t0 + np.arange(int(60.0 / dt) + 1) * dt
            offset = c.oncoming_offset
            s = self._lane_walk(offset, s0, -v, tt - t0)
            behind = np.flatnonzero(s < self.s_ego(tt) - 60.0)
            if len(behind):
                tt, s = tt[:behind[0] + 1], s[:behind[0] + 1]
            backwards = True
            template = int(rng.integers(len(self.vehicle_meshes)))
        else:
            t_pass = rng.uniform(t_lo, t_hi)
            dur = rng.uniform(30.0, 90.0)
            t0 = t_pass - dur * rng.uniform(0.3, 0.7)
            v = 0.0 if rng.uniform() < c.standing_fraction else rng.uniform(*c.walk_speed)
            sign = 1.0 if rng.uniform() < 0.5 else -1.0
            tt = t0 + np.arange(int(dur / dt) + 1) * dt
            s_pass = self.s_ego(t_pass) + rng.uniform(-30.0, 30.0)
            offset = (1.0 if rng.uniform() < 0.5 else -1.0) * rng.uniform(*c.sidewalk)
            s = self._lane_walk(offset, s_pass, sign * v, tt - t_pass)
            backwards = sign < 0
            template = int(rng.integers(len(self.pedestrian_meshes)))
        inside = (s >= 0.0) & (s <= self.s_end)
        if inside.sum() < 20:
            return None
        first, last = np.flatnonzero(inside)[[0, -1]]
        if not inside[first:last + 1].all():
            return None
        tt, s = tt[first:last + 1], s[first:last + 1]
        meshes = self.pedestrian_meshes if kind == KIND_PEDESTRIAN else self.vehicle_meshes
        half = meshes[template][3]
        return _Actor(kind=kind, template=template, offset=float(offset), backwards=bool(backwards),
                      t0=float(tt[0]), s_table=s.astype(np.float64), albedo=float(rng.uniform(0.15, 0.85)),
                      half_size=half, radius=float(np.hypot(*half)) + 0.1)

    def _lane_walk(self, offset: float, s_ref: float, speed: float, dt: np.ndarray) -> np.ndarray:
        """Ego-lane arc length of an actor moving at a constant ``speed`` (signed, m/s) along the
        lane ``offset`` m left of the ego lane, at ``s_ref`` when ``dt = 0``: its own lane is
        longer on the outside of a turn and shorter inside, so it is walked by its own length."""
        lane = self.line[:, :2] + offset * self.left
        seg = np.maximum(np.linalg.norm(np.diff(lane, axis=0), axis=1), 1e-3 * self.step)
        own = np.concatenate([[0.0], np.cumsum(seg)])
        grid = np.arange(len(self.line)) * self.step
        ell = np.interp(s_ref, grid, own) + speed * np.asarray(dt, np.float64)
        s = np.interp(ell, own, grid)
        # beyond either end of the path: keep the distance (the actor is dropped there anyway)
        return np.where(ell < 0, ell, np.where(ell > own[-1], grid[-1] + ell - own[-1], s))

    def _fill_ground(self, actor: _Actor) -> None:
        """Tabulate the ground height along the actor's lane stretch (every 0.5 m)."""
        k_lo = max(int(np.floor(actor.s_table.min() / self.step)) - 1, 0)
        k_hi = min(int(np.ceil(actor.s_table.max() / self.step)) + 2, len(self.line))
        s = np.arange(k_lo, k_hi) * self.step
        pos, _, _ = self._pose_s(actor, s)  # z from the ground model (no table yet)
        actor.z_table, actor.k_lo = pos[:, 2].copy(), k_lo

    def _touches_obstacle(self, actor: _Actor) -> bool:
        """Does the actor's footprint (+0.1 m) overlap an obstacle circle at any table time?"""
        if self._obstacle_kd is None:
            return False
        # the pose is a function of the arc length only: check every 0.2 m of the stretch driven
        s_grid = np.arange(actor.s_table.min(), actor.s_table.max() + 0.2, 0.2)
        p, yaw, _ = self._pose_s(actor, s_grid)
        r_max = float(self.obstacles[:, 2].max())
        _, idx = self._obstacle_kd.query(p[:, :2], k=4, distance_upper_bound=actor.radius + r_max + 0.1)
        ti, kk = np.nonzero(idx < len(self.obstacles))
        if len(ti) == 0:
            return False
        oi = idx[ti, kk]
        rel = self.obstacles[oi, :2] - p[ti, :2]
        c, s = np.cos(yaw[ti]), np.sin(yaw[ti])
        u, v = c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1]
        hl, hw = actor.half_size
        du, dv = np.maximum(np.abs(u) - hl, 0.0), np.maximum(np.abs(v) - hw, 0.0)
        return bool((np.hypot(du, dv) < self.obstacles[oi, 2] + 0.1).any())

    def _touches_ego(self, actor: _Actor) -> bool:
        c = self.config
        tt = actor.t0 + np.arange(len(actor.s_table)) * c.time_step
        p, yaw, _ = self._pose_s(actor, actor.s_table)
        ego_p, ego_yaw = self.ego_pose(tt)
        front, rear, hw = c.ego_box
        ego_c = ego_p[:, :2] + 0.5 * (front + rear) * np.c_[np.cos(ego_yaw), np.sin(ego_yaw)]
        ego_h = np.tile([0.5 * (front - rear) + c.clearance, hw + c.clearance], (len(tt), 1))
        act_h = np.tile(actor.half_size, (len(tt), 1))
        near = np.linalg.norm(p[:, :2] - ego_c, axis=1) < 12.0
        if not near.any():
            return False
        return bool(_rects_overlap(ego_c[near], ego_yaw[near], ego_h[near], p[near, :2], yaw[near],
                                   act_h[near]).any())

    # ---- poses ----------------------------------------------------------------------------
    def ego_pose(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ego sensor position ``(n, 3)`` and heading ``(n,)`` on the path at times ``t``."""
        s = self.s_ego(np.asarray(t, np.float64))
        q = s / self.step
        xyz = np.stack([np.interp(q, np.arange(len(self.line)), self.line[:, k]) for k in range(3)], 1)
        return xyz, np.interp(q, np.arange(len(self.line)), self.heading)

    def _pose_s(self, actor: _Actor, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position ``(n, 3)`` (on the ground), yaw and lane tangent of ``actor`` at arc lengths ``s``."""
        q = np.clip(np.asarray(s, np.float64) / self.step, 0, len(self.line) - 1)
        k = np.minimum(q.astype(np.int64), len(self.line) - 2)
        f = (q - k)[:, None]
        lane = self._lane[k] * (1.0 - f) + self._lane[k + 1] * f  # x y z left_x left_y heading
        base, yaw = lane[:, :3], lane[:, 5]
        left = lane[:, 3:5] / np.maximum(np.sqrt(lane[:, 3] ** 2 + lane[:, 4] ** 2), 1e-9)[:, None]
        xy = base[:, :2] + actor.offset * left
        if actor.z_table is not None:
            j = np.clip(q - actor.k_lo, 0, len(actor.z_table) - 1)
            jk = np.minimum(j.astype(np.int64), max(len(actor.z_table) - 2, 0))
            jf = j - jk
            z = actor.z_table[jk] * (1.0 - jf) + actor.z_table[np.minimum(jk + 1, len(actor.z_table) - 1)] * jf
        elif self.ground is not None:
            z = self.ground(xy)
        else:
            z = base[:, 2] - self.sensor_height
            if actor.kind == KIND_PEDESTRIAN:
                z = z + 0.12  # on the curb
        if actor.backwards:
            yaw = yaw + np.pi
        pos = np.empty((len(q), 3))
        pos[:, :2], pos[:, 2] = xy, z
        return pos, yaw, left

    def _s_at(self, actor: _Actor, t: np.ndarray) -> np.ndarray:
        q = np.clip((np.asarray(t, np.float64) - actor.t0) / self.config.time_step, 0, len(actor.s_table) - 1)
        k = np.minimum(q.astype(np.int64), len(actor.s_table) - 2)
        f = q - k
        return actor.s_table[k] * (1.0 - f) + actor.s_table[k + 1] * f

    def alive(self, t_lo: float, t_hi: float) -> np.ndarray:
        """Indices of the actors alive at some time in ``[t_lo, t_hi]``."""
        return np.flatnonzero((self._t_start <= t_hi) & (self._t_stop >= t_lo))

    def state(self, index: int, t: np.ndarray) -> dict[str, np.ndarray]:
        """Actor ``index`` at times ``t``: ``position`` (ground point under its centre), ``yaw``,
        ``speed`` (m/s along its own lane, from the arc-length table) and ``alive``."""
        a = self.actors[index]
        t = np.atleast_1d(np.asarray(t, np.float64))
        s = self._s_at(a, t)
        p, yaw, _ = self._pose_s(a, s)
        k = np.clip(np.floor((t - a.t0) / self.config.time_step).astype(int), 0, len(a.s_table) - 2)
        # ds/dt on the ego lane times the stretch of the actor's own (offset) lane there
        p2 = self._pose_s(a, s + 1e-3)[0]  # the lane is piecewise linear between 0.5 m samples
        stretch = np.linalg.norm(p2[:, :2] - p[:, :2], axis=1) / 1e-3
        speed = np.abs(a.s_table[k + 1] - a.s_table[k]) / self.config.time_step * stretch
        alive = (t >= self._t_start[index]) & (t <= self._t_stop[index])
        return {"position": p, "yaw": yaw, "speed": speed, "alive": alive}

    def __len__(self) -> int:
        return len(self.actors)

    # ---- ray casting ----------------------------------------------------------------------
    def _scene(self, kind: int, template: int):
        key = (int(kind == KIND_PEDESTRIAN), template)
        if key not in self._scenes:
            import open3d as o3d

            meshes = self.pedestrian_meshes if key[0] else self.vehicle_meshes
            v, t, _, _ = meshes[template]
            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(o3d.core.Tensor(v), o3d.core.Tensor(t))
            self._scenes[key] = scene
        return self._scenes[key]

    def cast(self, origins: np.ndarray, directions: np.ndarray, times: np.ndarray,
             return_albedo: bool = False, nthreads: int = 1, max_range: float = 150.0):
        """Cast rays against the actors, each ray at its own time.

        Parameters
        ----------
        origins, directions : np.ndarray
            ``(N, 3)`` world ray origins and unit directions.
        times : np.ndarray
            ``(N,)`` float64 time of each ray (s, the path's time base).
        return_albedo : bool
            Also return the reflectance of each hit.
        nthreads : int
            open3d ray-casting threads.
        max_range : float
            Actors farther than this from the rays' origins are not cast (m).

        Returns
        -------
        t_hit : ``(N,)`` float32 distance along the ray, ``inf`` where no actor is hit.
        normals : ``(N, 3)`` float32 unit normals of the hit triangles (world; zeros where no hit).
        material : ``(N,)`` int32 material id (``MATERIAL``: car, glass, person; -1 where no hit).
        albedo : ``(N,)`` float32, only with ``return_albedo``.
        """
        import open3d as o3d

        o = np.asarray(origins).reshape(-1, 3)  # kept in the caller's dtype; subsets go to float64
        d = np.asarray(directions).reshape(-1, 3)
        t = np.asarray(times, np.float64).reshape(-1)
        n = len(o)
        if len(d) != n or len(t) != n:
            raise ValueError(f"Actors.cast: origins {o.shape}, directions {d.shape}, times {t.shape} differ")
        t_hit = np.full(n, np.inf, np.float32)
        normals = np.zeros((n, 3), np.float32)
        material = np.full(n, -1, np.int32)
        albedo = np.zeros(n, np.float32)
        if n == 0:
            return (t_hit, normals, material, albedo) if return_albedo else (t_hit, normals, material)
        live = self.alive(float(t.min()), float(t.max()))
        if len(live):
            o_lo = np.array([o[:, k].min() for k in range(3)])  # column-wise: axis=0 is slow
            o_hi = np.array([o[:, k].max() for k in range(3)])
            o_mean = 0.5 * (o_lo + o_hi)
            spread = 0.5 * float(np.linalg.norm(o_hi - o_lo))
            t_lo, t_hi = float(t.min()), float(t.max())
            t_mid = 0.5 * (t_lo + t_hi)
            half_span = 0.5 * float(t.max() - t.min())
            # float32 pi rounds above np.pi: clip so that the wrapped intervals below see every ray
            az = np.clip(np.arctan2(d[:, 1], d[:, 0]).astype(np.float64), -np.pi, np.pi)
            order = np.argsort(az, kind="stable")
            az_sorted = az[order]
        for i in live:
            a = self.actors[i]
            s_mid = float(self._s_at(a, t_mid))
            k = min(int(s_mid / self.step), len(self.line) - 1)
            lane = self._lane[k]
            cx, cy_ = lane[0] + a.offset * lane[3], lane[1] + a.offset * lane[4]
            dist = float(np.hypot(cx - o_mean[0], cy_ - o_mean[1]))
            # speeds are below 14 m/s; the nearest lane sample is within 0.25 m
            reach = a.radius + spread + 28.0 * half_span + 0.75
            if dist - reach > max_range:
                continue
            ends = self._pose_s(a, self._s_at(a, np.array([t_lo, t_hi])))[0]
            centre = 0.5 * (ends[0] + ends[1])
            reach = a.radius + spread + 0.5 * float(np.linalg.norm(ends[1] - ends[0])) + 0.05
            rel = centre[:2] - o_mean[:2]
            dist = float(np.hypot(*rel))
            if dist > reach:
                half = float(np.arcsin(min(1.0, reach / dist)))
                centre_az = float(np.arctan2(rel[1], rel[0]))
                sel = np.concatenate([order[np.searchsorted(az_sorted, lo_):np.searchsorted(az_sorted, hi_, side="right")]
                                      for lo_, hi_ in _wrapped_intervals(centre_az - half, centre_az + half)])
                # elevation window: the ray must pass between the actor's foot (-0.5 m) and top
                # (+2 m) somewhere within [dist - reach, dist + reach] of horizontal distance
                near_h = dist - reach
                zb, ztop = centre[2] - 0.5 - o_hi[2], centre[2] + 2.0 - o_lo[2]
                lo_slope = zb / near_h
                hi_slope = ztop / near_h if ztop > 0 else ztop / (dist + reach)
                ds = d[sel].astype(np.float64)
                slope = ds[:, 2] / np.maximum(np.sqrt(ds[:, 0] ** 2 + ds[:, 1] ** 2), 1e-9)
                sel = sel[(slope >= lo_slope) & (slope <= hi_slope)
                          & (t[sel] >= self._t_start[i]) & (t[sel] <= self._t_stop[i])]
            else:
                sel = np.flatnonzero((t >= self._t_start[i]) & (t <= self._t_stop[i]))
            if len(sel) == 0:
                continue
            ds = d[sel].astype(np.float64)
            s = self._s_at(a, t[sel])
            p, yaw, _ = self._pose_s(a, s)
            cy, sy = np.cos(yaw), np.sin(yaw)
            rel_o = o[sel].astype(np.float64) - p
            rays = np.empty((len(sel), 6), np.float32)
            rays[:, 0] = cy * rel_o[:, 0] + sy * rel_o[:, 1]
            rays[:, 1] = -sy * rel_o[:, 0] + cy * rel_o[:, 1]
            rays[:, 2] = rel_o[:, 2]
            rays[:, 3] = cy * ds[:, 0] + sy * ds[:, 1]
            rays[:, 4] = -sy * ds[:, 0] + cy * ds[:, 1]
            rays[:, 5] = ds[:, 2]
            hit = self._scene(a.kind, a.template).cast_rays(o3d.core.Tensor.from_numpy(rays), nthreads=nthreads)
            th = hit["t_hit"].numpy()
            better = th < t_hit[sel]
            if not better.any():
                continue
            j = sel[better]
            t_hit[j] = th[better]
            nl = hit["primitive_normals"].numpy()[better]
            c_, s_ = cy[better], sy[better]
            normals[j, 0] = c_ * nl[:, 0] - s_ * nl[:, 1]
            normals[j, 1] = s_ * nl[:, 0] + c_ * nl[:, 1]
            normals[j, 2] = nl[:, 2]
            prim = hit["primitive_ids"].numpy()[better]
            if a.kind == KIND_PEDESTRIAN:
                material[j] = MATERIAL["person"]
                albedo[j] = a.albedo
            else:
                glass = self.vehicle_meshes[a.template][2][prim]
                material[j] = np.where(glass, MATERIAL["glass"], MATERIAL["car"])
                albedo[j] = np.where(glass, 0.08, a.albedo)
        return (t_hit, normals, material, albedo) if return_albedo else (t_hit, normals, material)


class _Array:
    """Minimal stand-in for an open3d tensor (``.numpy()``)."""

    def __init__(self, a: np.ndarray):
        self._a = a

    def numpy(self) -> np.ndarray:
        return self._a


class SceneWithActors:
    """A static ``RaycastingScene`` plus the actors, for one scan (duck-types ``cast_rays``).

    Lets :func:`sensor.render_scan` render the actors unchanged: each ray's time is taken from
    its azimuth in the sensor frame (the sweep turns clockwise from ``sweep_start_azimuth``, π:
    backwards, over ``sweep_seconds``, centred on ``t_frame``: facing forward at mid-sweep, as
    :func:`gr_graph.datasets.synthetic.effects.column_times` times the renderer's columns), the nearer of
    the static and the actor hit is kept, and actor hits get primitive ids past the static
    mesh's that index the tables :attr:`albedo` and :attr:`material` (static ones first).
    """

    def __init__(self, scene, static_albedo: np.ndarray, static_material: np.ndarray, actors: Actors,
                 T_w_s: np.ndarray, t_frame: float, sweep_seconds: float = 0.1,
                 sweep_start_azimuth: float = np.pi):
        self.scene, self.actors, self.T_w_s = scene, actors, np.asarray(T_w_s, np.float64)
        self.t_frame, self.sweep_seconds, self.sweep_start = float(t_frame), sweep_seconds, sweep_start_azimuth
        self.n_static = len(static_albedo)
        names = ("car", "glass", "person")
        self.albedo = np.concatenate([static_albedo, np.zeros(len(names) * 101, np.float32)])
        self.material = np.concatenate([static_material, np.repeat(
            np.array([MATERIAL[k] for k in names], static_material.dtype), 101)])
        self.albedo[self.n_static:] = np.tile(np.linspace(0.0, 1.0, 101, dtype=np.float32), len(names))
        self._mat_slot = {MATERIAL[k]: i for i, k in enumerate(names)}

    def ray_times(self, directions: np.ndarray) -> np.ndarray:
        """Time of each world-frame ray direction from its azimuth in the sensor frame."""
        R = self.T_w_s[:3, :3].astype(np.float32)
        dx, dy, dz = (np.ascontiguousarray(directions[:, k], dtype=np.float32) for k in range(3))
        x = dx * R[0, 0] + dy * R[1, 0] + dz * R[2, 0]
        y = dx * R[0, 1] + dy * R[1, 1] + dz * R[2, 1]
        frac = np.float32(self.sweep_start) - np.arctan2(y, x)  # clockwise from the start
        frac = (frac % np.float32(2 * np.pi)) / np.float32(2 * np.pi)
        return self.t_frame + (frac.astype(np.float64) - 0.5) * self.sweep_seconds

    def cast_rays(self, rays, nthreads: int = 0) -> dict[str, _Array]:
        hit = self.scene.cast_rays(rays, nthreads=nthreads)
        r = rays.numpy()
        t_static = hit["t_hit"].numpy()
        th, nl, mat, alb = self.actors.cast(r[:, :3], r[:, 3:], self.ray_times(r[:, 3:]), return_albedo=True,
                                           nthreads=max(1, nthreads))
        nearer = th < t_static
        t_out = np.where(nearer, th, t_static).astype(np.float32)
        prim = hit["primitive_ids"].numpy().astype(np.int64)
        normals = hit["primitive_normals"].numpy().copy()
        if nearer.any():
            slot = np.array([self._mat_slot[m] for m in mat[nearer]], np.int64)
            prim[nearer] = self.n_static + slot * 101 + np.round(alb[nearer] * 100).astype(np.int64)
            normals[nearer] = nl[nearer]
        return {"t_hit": _Array(t_out), "primitive_ids": _Array(prim), "primitive_normals": _Array(normals)}
