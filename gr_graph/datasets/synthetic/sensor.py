"""Beam models of spinning LiDARs and the ray caster that renders one scan.

Beam models (:class:`BeamModel`, elevations and datasheet numbers in the catalogue
:data:`gr_graph.sensors.SENSOR_MODELS`):

- ``hdl64e`` (default), Velodyne HDL-64E-like: 64 lasers from +2.0° down to -24.9° of elevation
  in two blocks, the upper 32 beams every 1/3° (+2.0° .. -8.33°), the lower 32 beams evenly
  from -8.83° to -24.9° (about 0.52°); 2,000 azimuth steps; 120 m;
- ``vlp16``, Velodyne VLP-16: 16 lasers from +15° to -15° every 2° (VLP-16 datasheet); 1,800
  azimuth steps (0.2° at 10 Hz); 100 m;
- ``os1-64``, Ouster OS1-64 with uniform beam spacing: 64 lasers evenly over +22.5° .. -22.5°
  (0.71° apart; OS1 Rev 6/7 datasheets); 1,024 columns (512 / 2,048 configurable); 120 m.

Ring 0 is the highest beam. Each frame fires every beam at ``n_azimuth`` evenly spaced
azimuths starting at a per-frame random phase (real scans are not aligned in azimuth),
sweeping counter-clockwise from the x axis (forward) as in KITTI's files, which are stored
ring by ring from the top. Every model uses the same return model (:class:`NoiseModel`) and
sensor effects; only the beam pattern, the column count and the range differ. All beams fire
from the sensor origin (the real sensors' few-cm beam offsets are left out).

Returns: range noise ``N(0, range_sigma²)``, random drop-outs (``dropout``), extra
drop-outs at grazing incidence and on glass, no return beyond ``max_range``, below
``min_range`` or into the sky. Intensity = reflectance · (0.25 + 0.75 |cos θ|) with 5 %
multiplicative noise, quantised to 0.01 like KITTI's.

All per-ray random draws are made for the sensor's full ``n_beams`` × ``n_azimuth`` grid, in a
fixed order, from a generator seeded by ``(seed, frame index)``, so frame *i* does not depend on
which frames were rendered before, and a 32/16-ring render of a 64-beam sensor is exactly the
corresponding rings of its 64-ring render.

:func:`render_scan` is that original (``clean``) render; :func:`render_frame` adds the
sensor effects of :mod:`.effects` (motion distortion, per-laser calibration errors, range
noise growing with range and incidence, mixed pixels, rough surfaces) and moving objects
(an ``actors`` object, see :class:`Actors`); with no effect and no actors it returns
:func:`render_scan`'s output unchanged (bit-identical). Its extra draws (mixed-pixel
positions, then the compensation's velocity errors) come after the original ones, so they
do not change them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, Protocol

import numpy as np

from gr_graph.datasets.synthetic.effects import LaserCalibration, SensorEffects, SweepMotion, hashed_uniform
from gr_graph.datasets.synthetic.meshes import MATERIAL
from gr_graph.sensors import DEFAULT_SENSOR, SensorModel, hdl64_elevations_deg, sensor_model

__all__ = ["N_BEAMS", "hdl64_elevations_deg", "BeamModel", "NoiseModel", "render_scan", "render_frame",
           "RenderedScan", "Actors", "ACTOR_ALBEDO"]

N_BEAMS = 64
"""Beams of the default sensor, the HDL-64E."""


@dataclass(frozen=True)
class BeamModel:
    """Rays of one scan.

    Attributes
    ----------
    n_rings : int, optional
        Rings rendered: all the sensor's beams (None, the default), or, for a 64-beam sensor,
        32, 16, 8, ... (a divisor of 64): every ``64 // n_rings``-th beam.
    n_azimuth : int, optional
        Azimuth steps per revolution (None: the sensor's, e.g. 2,000 for the HDL-64E).
    sensor : str
        Catalogue name of the beam pattern (``hdl64e``, ``vlp16``, ``os1-64``; see
        :data:`gr_graph.sensors.SENSOR_MODELS`).
    """

    n_rings: int | None = None
    n_azimuth: int | None = None
    sensor: str = DEFAULT_SENSOR

    def __post_init__(self) -> None:
        model = sensor_model(self.sensor)  # raises for an unknown name
        object.__setattr__(self, "sensor", model.name)
        n_beams = model.n_beams
        if self.n_rings is None:
            object.__setattr__(self, "n_rings", n_beams)
        if self.n_azimuth is None:
            object.__setattr__(self, "n_azimuth", model.n_azimuth)
        if self.n_rings != n_beams and (n_beams != 64 or self.n_rings < 1 or n_beams % self.n_rings):
            raise ValueError(
                f"n_rings must be {n_beams} (all beams of the {model.name})" if n_beams != 64 else
                f"n_rings must divide {n_beams} (64, 32, 16, 8, ...), got {self.n_rings}")
        if self.n_azimuth < 8:
            raise ValueError(f"n_azimuth must be >= 8, got {self.n_azimuth}")

    @property
    def model(self) -> SensorModel:
        """The catalogue entry of the sensor."""
        return sensor_model(self.sensor)

    @property
    def n_beams(self) -> int:
        """Beams of the sensor (the full grid the random draws cover)."""
        return self.model.n_beams

    def full_elevations_deg(self) -> np.ndarray:
        """Elevations of all the sensor's beams in degrees (ring 0 first)."""
        return np.asarray(self.model.elevations_deg, np.float64)

    @property
    def beam_indices(self) -> np.ndarray:
        """Indices into the sensor's beam pattern of the beams used (ring r -> beam_indices[r])."""
        return np.arange(0, self.n_beams, self.n_beams // self.n_rings)

    @property
    def elevations_deg(self) -> np.ndarray:
        """Elevation of each ring in degrees (ring 0 first)."""
        return self.full_elevations_deg()[self.beam_indices]

    def describe(self) -> str:
        """One line, e.g. ``sensor vlp16 (16 of 16 beams, 1800 azimuth steps)``."""
        return f"sensor {self.sensor} ({self.n_rings} of {self.n_beams} beams, {self.n_azimuth} azimuth steps)"

    def directions(self, phase: float) -> np.ndarray:
        """Unit ray directions ``(n_beams * n_azimuth, 3)`` of the sensor's FULL beam grid, ring-major."""
        el = np.radians(self.full_elevations_deg())
        az = phase + 2.0 * np.pi * np.arange(self.n_azimuth) / self.n_azimuth
        ce, se = np.cos(el)[:, None], np.sin(el)[:, None]
        d = np.empty((self.n_beams, self.n_azimuth, 3))
        d[..., 0] = ce * np.cos(az)
        d[..., 1] = ce * np.sin(az)
        d[..., 2] = se
        return d.reshape(-1, 3)


@dataclass(frozen=True)
class NoiseModel:
    """Return model parameters.

    Attributes
    ----------
    range_sigma : float
        Standard deviation of the Gaussian range noise (m).
    dropout : float
        Probability that a return is lost at random.
    max_range, min_range : float
        Returns outside ``[min_range, max_range]`` are dropped (m).
    grazing_cos : float
        Below this ``|cos θ|`` of incidence, returns fade out (linearly to always lost at 0).
    glass_dropout : float
        Probability that a return from glass (car windows) is lost.
    intensity_noise : float
        Relative (multiplicative) intensity noise.
    """

    range_sigma: float = 0.02
    dropout: float = 0.02
    max_range: float = 120.0
    min_range: float = 1.0
    grazing_cos: float = 0.05
    glass_dropout: float = 0.5
    intensity_noise: float = 0.05

    def __post_init__(self) -> None:
        if not (self.range_sigma >= 0 and 0 <= self.dropout < 1 and 0 <= self.glass_dropout <= 1):
            raise ValueError(f"invalid noise model {self}")
        if not 0 <= self.min_range < self.max_range:
            raise ValueError(f"need 0 <= min_range < max_range, got {self.min_range}, {self.max_range}")


def _scan_draws(rng: np.random.Generator, beams: BeamModel) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """The draws every scan starts with, in a fixed order over the sensor's full beam grid
    (independent of ``n_rings`` and of the hits): azimuth phase, range noise, drop-out and
    intensity noise. The clean renderer and the renderer with effects share them, so a frame's
    clean draws are the same whichever renders it."""
    n_all = beams.n_beams * beams.n_azimuth
    phase = rng.uniform(0.0, 2.0 * np.pi / beams.n_azimuth)
    range_noise = rng.standard_normal(n_all, dtype=np.float32)
    u_drop = rng.random(n_all, dtype=np.float32)
    u_int = rng.standard_normal(n_all, dtype=np.float32)
    return phase, range_noise, u_drop, u_int


def render_scan(scene, albedo: np.ndarray, material: np.ndarray, T_w_s: np.ndarray,
                beams: BeamModel, noise: NoiseModel, rng: np.random.Generator,
                nthreads: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cast one scan from pose ``T_w_s`` against an open3d ``RaycastingScene``.

    Parameters
    ----------
    scene : open3d.t.geometry.RaycastingScene
        Holding one mesh whose triangles index ``albedo`` and ``material``.
    T_w_s : np.ndarray
        ``(4, 4)`` sensor-to-world pose.
    rng : np.random.Generator
        Per-frame generator (see the module docstring for the draw order).

    Returns
    -------
    points : ``(N, 3)`` float64 in the sensor frame, ring-major (ring 0 first), azimuth
        increasing from the x axis within a ring.
    intensity : ``(N,)`` float32 in [0, 1].
    ring : ``(N,)`` int16.
    """
    import open3d as o3d

    n_az = beams.n_azimuth
    phase, range_noise, u_drop, u_int = _scan_draws(rng, beams)

    d = beams.directions(phase)
    sel = None
    if beams.n_rings != beams.n_beams:
        sel = (beams.beam_indices[:, None] * n_az + np.arange(n_az)[None, :]).ravel()
        d = d[sel]
        range_noise, u_drop, u_int = range_noise[sel], u_drop[sel], u_int[sel]
    R, t = T_w_s[:3, :3], T_w_s[:3, 3]
    rays = np.empty((len(d), 6), dtype=np.float32)
    rays[:, :3] = t
    for k in range(3):  # d @ R.T without BLAS (its threads thrash on a loaded machine)
        rays[:, 3 + k] = d[:, 0] * R[k, 0] + d[:, 1] * R[k, 1] + d[:, 2] * R[k, 2]
    hit = scene.cast_rays(o3d.core.Tensor.from_numpy(rays), nthreads=nthreads)
    # misses have t = inf and fail the range test
    r = hit["t_hit"].numpy().astype(np.float64) + noise.range_sigma * range_noise
    idx = np.flatnonzero((r >= noise.min_range) & (r <= noise.max_range))
    prim = hit["primitive_ids"].numpy()[idx]
    normals = hit["primitive_normals"].numpy()[idx]  # unit normals
    cos_inc = np.abs(np.einsum("ij,ij->i", normals, rays[idx, 3:]))
    mat = material[prim]
    p_drop = noise.dropout + (1 - noise.dropout) * np.clip(1.0 - cos_inc / noise.grazing_cos, 0.0, 1.0)
    p_drop[mat == MATERIAL["glass"]] = np.maximum(p_drop[mat == MATERIAL["glass"]], noise.glass_dropout)
    keep = u_drop[idx] >= p_drop
    idx, prim, cos_inc = idx[keep], prim[keep], cos_inc[keep]
    points = d[idx] * r[idx, None]
    inten = albedo[prim] * (0.25 + 0.75 * cos_inc) * (1.0 + noise.intensity_noise * u_int[idx])
    inten = (np.round(np.clip(inten, 0.0, 1.0) * 100.0) / 100.0).astype(np.float32)
    ring = (idx // n_az).astype(np.int16)
    return points, inten, ring


class Actors(Protocol):
    """Moving objects ray-cast at each ray's own time (implemented by the world's actors)."""

    def cast(self, origins: np.ndarray, directions: np.ndarray,
             times: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(N, 3)`` float32 world origins/unit directions, ``(N,)`` float64 times (s) ->
        ``t_hit (N,)`` float32 (inf: no hit), ``normals (N, 3)`` float32, ``material (N,)`` int."""
        ...


class RenderedScan(NamedTuple):
    """One rendered scan: as :func:`render_scan` plus each point's sweep fraction.

    ``time`` is ``(N,)`` float64 in [0, 1] (0 = start of the sweep) when the motion
    distortion is ``raw``, else None.
    """

    points: np.ndarray
    intensity: np.ndarray
    ring: np.ndarray
    time: np.ndarray | None


ACTOR_ALBEDO = 0.3
"""Reflectance of actor hits whose material has no entry in ``material_albedo``."""


def render_frame(scene, albedo: np.ndarray, material: np.ndarray, T_w_s: np.ndarray,
                 beams: BeamModel, noise: NoiseModel, rng: np.random.Generator,
                 effects: SensorEffects | None = None, laser_calib: LaserCalibration | None = None,
                 sweep=None, actors: Actors | None = None, timestamp: float = 0.0,
                 material_albedo: np.ndarray | None = None, roughness_seed: int = 0,
                 nthreads: int = 0) -> RenderedScan:
    """Render one scan with sensor effects and moving objects.

    Parameters
    ----------
    scene, albedo, material, T_w_s, beams, noise, rng, nthreads
        As :func:`render_scan`; ``T_w_s`` is the pose at mid-sweep.
    effects : SensorEffects, optional
        Which effects are on (None: none).
    laser_calib : LaserCalibration, optional
        The sensor's drawn per-laser errors (required when ``effects.calibration`` is on).
    sweep : callable, optional
        ``sweep(phase, rng) -> SweepMotion`` (required when the motion distortion is on):
        the sensor motion of this sweep, given the frame's azimuth phase.
    actors : Actors, optional
        Moving objects; each ray takes the nearer of the static and the actor hit.
    timestamp : float
        Time (s) of the frame (mid-sweep), the time of every ray without motion distortion.
    material_albedo : np.ndarray, optional
        Reflectance per material id, for actor hits.
    roughness_seed : int
        Seed of the fixed roughness height field.
    """
    effects = SensorEffects() if effects is None else effects
    if effects.is_clean and actors is None:
        return RenderedScan(*render_scan(scene, albedo, material, T_w_s, beams, noise, rng,
                                         nthreads=nthreads), None)
    import open3d as o3d

    n_az = beams.n_azimuth
    n_all = beams.n_beams * n_az
    # the clean renderer's draws first, in its order, then the effects' draws
    phase, range_noise, u_drop, u_int = _scan_draws(rng, beams)
    u_mix = rng.random(n_all, dtype=np.float32)
    motion: SweepMotion | None = None
    if effects.motion.enabled:
        if sweep is None:
            raise ValueError("render_frame: motion distortion needs the sweep motion (sweep=...)")
        motion = sweep(phase, rng)

    beam_idx = beams.beam_indices
    n_r = len(beam_idx)
    el_nom = np.radians(beams.full_elevations_deg())[beam_idx]
    az_col = phase + 2.0 * np.pi * np.arange(n_az) / n_az
    caz, saz = np.cos(az_col), np.sin(az_col)
    el_true = el_nom
    cal = effects.calibration.enabled
    if cal:
        if laser_calib is None:
            raise ValueError("render_frame: calibration errors need the sensor's laser_calib")
        el_true = el_nom + laser_calib.elevation_rad[beam_idx]
        daz = laser_calib.azimuth_rad[beam_idx]
        cd, sd = np.cos(daz).astype(np.float32)[:, None], np.sin(daz).astype(np.float32)[:, None]
        c32, s32 = caz.astype(np.float32)[None, :], saz.astype(np.float32)[None, :]
        cos_az, sin_az = cd * c32 - sd * s32, sd * c32 + cd * s32  # cos/sin(az + daz), (n_r, n_az)
    else:
        cos_az = np.broadcast_to(caz.astype(np.float32)[None, :], (n_r, n_az))
        sin_az = np.broadcast_to(saz.astype(np.float32)[None, :], (n_r, n_az))
    ce_t = np.cos(el_true).astype(np.float32)[:, None]
    se_t = np.sin(el_true).astype(np.float32)[:, None]
    # true beam directions in the sensor frame of each column's time, (n_r, n_az) per axis
    dx, dy, dz = ce_t * cos_az, ce_t * sin_az, np.broadcast_to(se_t, (n_r, n_az))
    rays = np.empty((n_r, n_az, 6), dtype=np.float32)
    if motion is None:
        R, t = T_w_s[:3, :3].astype(np.float32), T_w_s[:3, 3]
        rays[..., :3] = t
        for k in range(3):
            rays[..., 3 + k] = dx * R[k, 0] + dy * R[k, 1] + dz * R[k, 2]
        ray_time = np.full(n_r * n_az, float(timestamp))
    else:
        Rc = motion.T_w_col[:, :3, :3].astype(np.float32)
        rays[..., :3] = motion.T_w_col[None, :, :3, 3]
        for k in range(3):
            rays[..., 3 + k] = dx * Rc[None, :, k, 0] + dy * Rc[None, :, k, 1] + dz * Rc[None, :, k, 2]
        ray_time = np.broadcast_to(motion.column_time[None, :], (n_r, n_az)).ravel()
    rays = rays.reshape(-1, 6)
    sel = (beam_idx[:, None] * n_az + np.arange(n_az)[None, :]).ravel()
    if n_r != beams.n_beams:
        range_noise, u_drop, u_int, u_mix = range_noise[sel], u_drop[sel], u_int[sel], u_mix[sel]

    hit = scene.cast_rays(o3d.core.Tensor.from_numpy(rays), nthreads=nthreads)
    t_hit = hit["t_hit"].numpy().astype(np.float64)
    valid = np.flatnonzero(np.isfinite(t_hit))
    prim = hit["primitive_ids"].numpy()[valid]
    normals = hit["primitive_normals"].numpy()  # used at hits only
    if actors is not None:
        normals = normals.copy()
    mat = np.zeros(len(t_hit), dtype=np.int64)
    alb = np.zeros(len(t_hit), dtype=np.float32)
    mat[valid] = material[prim]
    alb[valid] = albedo[prim]
    if actors is not None:
        ta, na, ma = actors.cast(np.ascontiguousarray(rays[:, :3]), np.ascontiguousarray(rays[:, 3:]),
                                 np.asarray(ray_time, dtype=np.float64))
        ta = np.asarray(ta, dtype=np.float64)
        closer = np.flatnonzero(ta < t_hit)
        if len(closer):
            t_hit[closer] = ta[closer]
            normals[closer] = np.asarray(na)[closer]
            ma = np.asarray(ma)[closer].astype(np.int64)
            mat[closer] = ma
            a = np.full(len(ma), ACTOR_ALBEDO, dtype=np.float32)
            if material_albedo is not None:
                known = (ma >= 0) & (ma < len(material_albedo))
                a[known] = material_albedo[ma[known]]
            alb[closer] = a
    dirs = rays[:, 3:]
    cos_all = np.abs(np.einsum("ij,ij->i", normals, dirs))
    r = t_hit
    if effects.roughness.enabled:
        fin = np.flatnonzero(np.isfinite(r))
        sig = effects.roughness.sigma_by_material_id()[mat[fin]]
        rough = np.flatnonzero(sig > 0)
        fin, sig = fin[rough], sig[rough]
        r32 = np.where(np.isfinite(r), r, 0.0).astype(np.float32)
        p_w = rays[:, :3] + dirs * r32[:, None]  # all rays: cheaper than gathering first
        cells = np.floor(p_w[fin] / effects.roughness.cell_m)
        h = np.sqrt(3.0) * sig * hashed_uniform(cells, roughness_seed)  # height above the surface
        r = r.copy()
        r[fin] -= h / np.maximum(cos_all[fin], noise.grazing_cos)  # h along the normal
    if effects.mixed_pixels.enabled:
        r = _mix_pixels(r, u_mix, n_r, n_az, effects.mixed_pixels)
    if effects.range_noise.enabled:
        sigma = effects.range_noise.sigma(np.where(np.isfinite(r), r, 0.0), cos_all)
        r = r + sigma * range_noise
    else:
        r = r + noise.range_sigma * range_noise
    ring_all = np.repeat(np.arange(n_r), n_az)
    if cal:
        r = (1.0 + laser_calib.range_scale[beam_idx][ring_all]) * r + laser_calib.range_offset_m[beam_idx][ring_all]
    idx = np.flatnonzero((r >= noise.min_range) & (r <= noise.max_range))
    cos_inc, m = cos_all[idx], mat[idx]
    p_drop = noise.dropout + (1 - noise.dropout) * np.clip(1.0 - cos_inc / noise.grazing_cos, 0.0, 1.0)
    glass = m == MATERIAL["glass"]
    p_drop[glass] = np.maximum(p_drop[glass], noise.glass_dropout)
    idx = idx[u_drop[idx] >= p_drop]
    col = idx % n_az
    ring_idx = ring_all[idx]
    r_idx = r[idx]
    ce_r = np.cos(el_nom)[ring_idx] * r_idx
    points = np.empty((len(idx), 3))
    points[:, 0] = ce_r * caz[col]  # reported along the nominal beam directions
    points[:, 1] = ce_r * saz[col]
    points[:, 2] = np.sin(el_nom)[ring_idx] * r_idx
    time = None
    if motion is not None:
        if motion.T_mid_col_est is not None:  # compensated into the mid-sweep frame
            E = motion.T_mid_col_est
            x, y, z = points[:, 0].copy(), points[:, 1].copy(), points[:, 2].copy()
            for k in range(3):
                points[:, k] = (E[:, k, 0][col] * x + E[:, k, 1][col] * y + E[:, k, 2][col] * z
                                + E[:, k, 3][col])
        else:
            time = motion.column_fraction[col].astype(np.float64)
    inten = alb[idx] * (0.25 + 0.75 * cos_all[idx]) * (1.0 + noise.intensity_noise * u_int[idx])
    inten = (np.round(np.clip(inten, 0.0, 1.0) * 100.0) / 100.0).astype(np.float32)
    return RenderedScan(points, inten, ring_all[idx].astype(np.int16), time)


def _mix_pixels(r: np.ndarray, u: np.ndarray, n_r: int, n_az: int, cfg) -> np.ndarray:
    """Mixed returns where a beam footprint straddles a depth edge to its azimuth neighbour.

    The edge between ray ``j`` and ``j + 1`` of a ring lies at ``u_j * step`` from ray ``j``;
    a ray whose footprint (half-width ``divergence / 2``) covers it returns the mean range
    of both surfaces weighted by the covered footprint fractions when they are closer than
    ``merge_distance_m``, else its own surface. A depth edge is a gap that exceeds the mean
    of the two neighbouring gaps by more than ``min_edge_m`` (a jump, not a slope).
    """
    step = 2.0 * np.pi / n_az
    half = 0.5 * cfg.divergence_rad
    R = r.reshape(n_r, n_az)
    Rn = np.roll(R, -1, axis=1)  # right neighbour (wraps around the revolution)
    x = u.reshape(n_r, n_az).astype(np.float64) * step
    with np.errstate(invalid="ignore"):
        g = Rn - R  # gap between ray j and j + 1
        # a depth edge is a jump, not a slope: the gap departs from the neighbouring gaps
        # (on an oblique plane consecutive gaps change smoothly); a missing neighbour gap
        # (no return) is no evidence of a jump
        gl, gr = np.roll(g, 1, axis=1), np.roll(g, -1, axis=1)
        gl = np.where(np.isfinite(gl), gl, g)
        gr = np.where(np.isfinite(gr), gr, g)
        jump = np.abs(g) - 0.5 * (np.abs(gl) + np.abs(gr))
    edge = np.isfinite(g) & (jump >= cfg.min_edge_m) & (np.abs(g) <= cfg.merge_distance_m)
    out = R.copy()
    w_left = np.where(edge, np.clip((half - x) / cfg.divergence_rad, 0.0, None), 0.0)   # ray j covers the edge
    w_right = np.where(edge, np.clip((half - (step - x)) / cfg.divergence_rad, 0.0, None), 0.0)  # ray j+1 does
    with np.errstate(invalid="ignore"):
        out = np.where(w_left > 0, (1 - w_left) * R + w_left * Rn, out)
        out_r = np.where(w_right > 0, (1 - w_right) * Rn + w_right * R, np.nan)
    out_r = np.roll(out_r, 1, axis=1)  # back onto ray j+1
    out = np.where(np.isnan(out_r), out, out_r)
    return out.ravel()
