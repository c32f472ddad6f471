"""A Velodyne HDL-64E-like beam model and the ray caster that renders one scan.

Beam model: 64 lasers from +2.0° down to -24.9° of elevation in two blocks, like the
HDL-64E: the upper 32 beams every 1/3° (+2.0° .. -8.33°), the lower 32 beams evenly from
-8.83° to -24.9° (about 0.52°). Ring 0 is the highest beam. Each frame fires every beam at
``n_azimuth`` evenly spaced azimuths starting at a per-frame random phase (real scans are
not aligned in azimuth), sweeping counter-clockwise from the x axis (forward) as in
KITTI's files, which are stored ring by ring from the top.

Returns: range noise ``N(0, range_sigma²)``, random drop-outs (``dropout``), extra
drop-outs at grazing incidence and on glass, no return beyond ``max_range``, below
``min_range`` or into the sky. Intensity = reflectance · (0.25 + 0.75 |cos θ|) with 5 %
multiplicative noise, quantised to 0.01 like KITTI's.

All per-ray random draws are made for the full 64 × ``n_azimuth`` grid, in a fixed order,
from a generator seeded by ``(seed, frame index)``, so frame *i* does not depend on which
frames were rendered before, and a 32/16-ring render is exactly the corresponding rings
of the 64-ring render.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gr_graph.datasets.synthetic.meshes import MATERIAL

N_BEAMS = 64


def hdl64_elevations_deg() -> np.ndarray:
    """The 64 beam elevations in degrees, ring 0 (highest) first, strictly decreasing."""
    upper = 2.0 - np.arange(32) / 3.0
    lower_top = upper[-1] - 0.5
    lower = lower_top - np.arange(32) * (24.9 + lower_top) / 31.0
    return np.concatenate([upper, lower])


@dataclass(frozen=True)
class BeamModel:
    """Rays of one scan.

    Attributes
    ----------
    n_rings : int
        64, 32, 16, ... (must divide 64): every ``64 // n_rings``-th beam is used.
    n_azimuth : int
        Azimuth steps per revolution.
    """

    n_rings: int = 64
    n_azimuth: int = 2000

    def __post_init__(self) -> None:
        if self.n_rings < 1 or N_BEAMS % self.n_rings:
            raise ValueError(f"n_rings must divide {N_BEAMS} (64, 32, 16, 8, ...), got {self.n_rings}")
        if self.n_azimuth < 8:
            raise ValueError(f"n_azimuth must be >= 8, got {self.n_azimuth}")

    @property
    def beam_indices(self) -> np.ndarray:
        """Indices into the 64-beam pattern of the beams used (ring r -> beam_indices[r])."""
        return np.arange(0, N_BEAMS, N_BEAMS // self.n_rings)

    @property
    def elevations_deg(self) -> np.ndarray:
        """Elevation of each ring in degrees (ring 0 first)."""
        return hdl64_elevations_deg()[self.beam_indices]

    def directions(self, phase: float) -> np.ndarray:
        """Unit ray directions ``(64 * n_azimuth, 3)`` of the FULL 64-beam grid, ring-major."""
        el = np.radians(hdl64_elevations_deg())
        az = phase + 2.0 * np.pi * np.arange(self.n_azimuth) / self.n_azimuth
        ce, se = np.cos(el)[:, None], np.sin(el)[:, None]
        d = np.empty((N_BEAMS, self.n_azimuth, 3))
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
    n_all = N_BEAMS * n_az
    # fixed draw order over the full 64-beam grid (independent of n_rings and of the hits)
    phase = rng.uniform(0.0, 2.0 * np.pi / n_az)
    range_noise = rng.standard_normal(n_all, dtype=np.float32)
    u_drop = rng.random(n_all, dtype=np.float32)
    u_int = rng.standard_normal(n_all, dtype=np.float32)

    d = beams.directions(phase)
    sel = None
    if beams.n_rings != N_BEAMS:
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
