"""A procedural town laid out around any driving path (by default the generated route).

The town is a fixed world (one triangle mesh) built once from a seed:

- a ground height field that follows the path's own height (the sensor rides
  ``sensor_height`` above it), a road of ``road_half_width`` around the path, a raised
  sidewalk (curb) beyond it, and gently undulating terrain further out;
- building blocks of varied length, depth, height and set-back along both sides of the
  path, with gaps, some with an upper tier; low walls in some gaps;
- street poles (some with a lamp arm), trees (trunk + irregular crown), bushes,
  scattered park trees, and parked cars (body + cabin, raised off the ground).

Every object is checked against the *whole* path (a KD-tree of the path sampled every
0.5 m), so nothing stands on the road where the path passes, including at intersections
and on revisited stretches; objects are also checked against each other on an occupancy
grid, so a revisited stretch keeps the objects placed on the first pass and renders the
same structures again.

World effects (``TownConfig`` flags, all off by default so that the ``clean`` town stays
bit-identical; ``TownConfig.residential()`` turns them all on, the world side of the ``kitti``
preset). Each draws from its own generator, so turning one on never moves the others' objects
(except ``detached_houses``, which changes the building layout itself):

- ``porous_vegetation``: crowns, bushes and hedges as volumes of small randomly oriented
  leaf-cluster triangles at a one-sided leaf area density ``leaf_area_density`` (trees, 1 m²/m³;
  broadleaf crowns measure about 0.5-2.5 m²/m³, e.g. Weiss et al. 2004, Béland et al. 2014)
  and ``shrub_leaf_area_density`` (2 m²/m³), elements of ``leaf_size`` 0.25 m (clumps of
  leaves and twigs) and 0.12 m; a beam travels a Beer-Lambert free path of mean
  ``1 / (0.5 LAD)`` inside (2 m in a tree crown), so returns come from inside crowns and some
  beams pass through; trees get 4-7 branches;
- ``facade_details``: floor bands, window sills, balconies with railings, gable roofs
  (25-45 degrees) with eaves or flat roofs with a parapet or cornice (storey height 3 m);
- ``fences_hedges``: hedges (0.9-1.8 m), picket fences (0.9-1.3 m) and railings along the
  property line 8.1-8.6 m off the path;
- ``street_signs``: sign plates (0.5-0.8 m) on 2.2-3 m poles by the curb;
- ``curved_cars``: parked cars as curved bodies with windows and wheels
  (:func:`.meshes.car_mesh`) instead of two boxes (same sizes and places);
- ``sidewalk_parking``: cars on the left park half on the sidewalk (5.4-5.8 m off the path),
  clear of the oncoming lane;
- ``detached_houses``: 8-17.6 m buildings with 3-14 m gaps (residential streets);
- ``garden_vegetation``: shrubs and small trees in the front gardens 8.8-16 m off the path;
- ``terrain_roughness``: 1 m-scale height noise (σ, m) on lawns and verges beyond the sidewalk;
- ``window_recesses``: the wall surface of every facade stands ``window_recess`` (0.15 m by default) in
  front of the glass of its windows (about 15-35 % of the facade).

Composition amounts (``hedge_fraction``, ``hedge_height``, ``property_gap``, ``low_walls``,
``garden_shrub_*``, ``garden_tree_fraction``, ``street_tree_spacing``, ``roadside_bush_spacing``,
``building_setback_max``, ``parking_*``) default to the original town;
``TownConfig.kitti()`` sets them to the residential streets of KITTI 00 (the world of the
``kitti`` preset; see its docstring).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from gr_graph.datasets.synthetic.meshes import (
    MATERIAL,
    MeshBuilder,
    blob,
    box,
    car_mesh,
    cylinder,
    gable_roof,
    leaf_cloud,
    rod,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TownConfig:
    """Layout parameters of the procedural town (metres)."""

    sensor_height: float = 1.73
    road_half_width: float = 5.0
    sidewalk_width: float = 3.0
    curb_height: float = 0.12
    ground_cell: float = 1.0
    ground_extent: float = 135.0
    """The ground mesh covers everything within this distance of the path."""
    path_step: float = 0.5
    terrain_amplitude: float = 0.8
    building_clearance: float = 8.5
    car_clearance: float = 2.4
    furniture_clearance: float = 5.6
    # ---- world effects (all off by default: the ``clean`` town, bit-identical to before) ----
    porous_vegetation: bool = False
    """Tree crowns, bushes and hedges as porous volumes of small leaf/twig elements instead of
    closed blobs (returns from inside the crown, partial penetration)."""
    leaf_area_density: float = 1.0
    """One-sided leaf area per crown volume (m²/m³) of trees; measured values of broadleaf
    crowns are about 0.5-2.5 m²/m³ (e.g. Weiss et al. 2004; Béland et al. 2014)."""
    shrub_leaf_area_density: float = 2.0
    """The same for bushes and hedges (denser, about 1-4 m²/m³)."""
    leaf_size: float = 0.25
    """Side (m) of one leaf-cluster element of a tree crown (a clump of leaves and twigs)."""
    shrub_leaf_size: float = 0.12
    """Side (m) of one element of a bush or hedge."""
    facade_details: bool = False
    """Buildings get eaves or gable roofs, floor bands, window sills and balconies."""
    fences_hedges: bool = False
    """Picket fences, railings and hedges along the property lines behind the sidewalk."""
    street_signs: bool = False
    """Traffic signs (a thin pole and a plate) along the curb."""
    curved_cars: bool = False
    """Parked cars with a curved body, windows and wheels (:func:`meshes.car_mesh`) instead of two boxes."""
    sidewalk_parking: bool = False
    """Cars on the left of the path park half on the sidewalk (5.4-5.8 m off the path instead of
    3.55-3.95 m, common in German residential streets), which leaves the oncoming lane free for
    the moving vehicles of :mod:`.actors`."""
    detached_houses: bool = False
    """Residential blocks: buildings 8-17.6 m long, always 3-14 m apart (views between them),
    instead of 8-32 m blocks joined to the next one 45 % of the time."""
    garden_vegetation: bool = False
    """Front gardens: shrubs and small trees between the sidewalk and the houses (8.8-16 m off
    the path), as in the residential streets of KITTI 00."""
    garden_spacing: tuple[float, float] = (2.5, 8.0)
    """Distance (m) along the street between two garden plantings (where there is room)."""
    hedge_fraction: float = 0.4
    """Fraction of the property-line elements (``fences_hedges``) that are hedges; the rest are
    picket fences and railings in the ratio 35:25."""
    hedge_height: tuple[float, float] = (0.9, 1.8)
    """Height range (m) of the property-line hedges."""
    property_gap: tuple[float, float] = (1.0, 8.0)
    """Gap (m) along the street between two property-line elements."""
    garden_shrub_radii: tuple[float, float] = (0.5, 1.2)
    """Range (m) of the vertical semi-axis of a front-garden shrub (its top is 1.6 of it above
    the ground: 0.8-1.9 m by default)."""
    garden_shrub_width: tuple[float, float] = (0.5, 1.5)
    """Range (m) of the horizontal semi-axes of a front-garden shrub."""
    roadside_bush_spacing: tuple[float, float] = (3.0, 14.0)
    """Distance (m) along the street between two bushes 7.6-10 m off the path."""
    garden_tree_fraction: float = 0.35
    """Fraction of the front-garden plantings that are small trees (the rest are shrubs)."""
    window_recesses: bool = False
    """Facades with recessed windows: the wall surface stands ``window_recess`` in front of the
    glass, which fills windows 1.0-1.6 m wide and 1.2-1.6 m high (sill 0.8-1.0 m above the
    storey floor), every 2.2-3.6 m along each storey (3 m): a window-to-wall ratio of about
    15-35 %. Glass loses returns like car windows (``NoiseModel.glass_dropout``)."""
    window_recess: float = 0.15
    """Depth (m) of a window reveal. German masonry walls are 0.3-0.5 m thick (e.g. 36.5 cm
    solid brick, 17.5 cm sand-lime brick + 12-16 cm insulation) and the window frame sits in
    the middle or the inner third of the wall, so reveals of 0.1-0.3 m (assumption within that)."""
    low_walls: bool = True
    """Plain low walls (1-2.2 m boxes) in some gaps between buildings; ``False`` leaves the
    property line to ``fences_hedges`` (hedges, picket fences, railings)."""
    street_tree_spacing: tuple[float, float] = (7.0, 22.0)
    """Distance (m) along the street between two street trees on each side."""
    building_setback_max: float = 15.0
    """Largest distance (m) of a building's front from the path (the smallest is
    ``building_clearance + 0.5``)."""
    parking_stay: float = 0.75
    """Probability that the slot after a parked car is occupied too (parked cars come in runs)."""
    parking_start: float = 0.25
    """Probability that the slot after an empty slot is occupied; the long-run occupancy of the
    kerb is ``parking_start / (1 - parking_stay + parking_start)`` (0.5 by default)."""
    terrain_roughness: float = 0.0
    """Standard deviation (m) of the fine-scale (1 m) height roughness of the terrain beyond
    the sidewalk (uneven lawns and verges); 0 = smooth."""

    @classmethod
    def residential(cls, **overrides) -> "TownConfig":
        """Every world effect of the first residential world on, at their default amounts
        (kept for the per-effect tables of ``benchmarks/results/realism_world.md``; the
        ``kitti`` preset uses :meth:`kitti`)."""
        base = {"porous_vegetation": True, "facade_details": True, "fences_hedges": True,
                "street_signs": True, "curved_cars": True, "sidewalk_parking": True,
                "detached_houses": True, "garden_vegetation": True, "terrain_roughness": 0.04}
        base.update(overrides)
        return cls(**base)

    @classmethod
    def kitti(cls, **overrides) -> "TownConfig":
        """The world of the ``kitti`` preset: :meth:`residential` with recessed windows and the
        composition of the residential streets at the start of KITTI 00.

        ``benchmarks/results/realism_diagnosis.md`` found that the real scans are not thicker
        than ours on the ground or on clean walls (their clean walls are as thin as our
        facades), but that their points 0.5-2.2 m above the ground are mostly hedges, shrubs,
        parked cars and trunks, where ours were mostly plain facades and walls. The amounts
        (layout assumptions, each inside the range of what residential streets show; none is
        a literature value):

        - ``window_recesses`` with 0.25 m reveals (inside the 0.1-0.3 m of ``window_recess``);
        - property lines almost continuously planted: ``hedge_fraction`` 0.9, gaps 0.3-2 m,
          hedges 1.5-2.5 m high (privet, hornbeam or thuja front hedges are 1-2.5 m);
          ``low_walls`` off (the plain walls gave way to hedges and fences);
        - front gardens of shrubs, 0.5-2 m apart, ``garden_tree_fraction`` 0.05, shrubs with
          horizontal semi-axes of 0.8-2 m and a vertical one of 1-2 m (1.6-3.2 m tall:
          ornamental shrubs such as lilac, hazel or cherry laurel grow 1.5-4 m);
        - street trees every 5-12 m (street-tree rows are planted about 8-12 m apart);
        - houses up to 25 m from the path (front gardens of 3-15 m);
        - kerbside parking occupancy 0.8 (``parking_stay`` 0.9, ``parking_start`` 0.4; both
          kerbs of the real frames are lined with cars);
        - tree leaf area density 1.5 m²/m³ (inside the measured 0.5-2.5, see
          ``leaf_area_density``).
        """
        base = {"window_recesses": True, "window_recess": 0.25, "low_walls": False, "hedge_fraction": 0.9,
                "hedge_height": (1.5, 2.5), "property_gap": (0.3, 2.0), "garden_spacing": (0.5, 2.0),
                "garden_tree_fraction": 0.05, "garden_shrub_radii": (1.0, 2.0), "garden_shrub_width": (0.8, 2.0),
                "street_tree_spacing": (5.0, 12.0), "building_setback_max": 25.0,
                "parking_stay": 0.9, "parking_start": 0.4, "leaf_area_density": 1.5}
        base.update(overrides)
        return cls.residential(**base)

    @property
    def any_effect(self) -> bool:
        """True if any world effect is on."""
        return (self.porous_vegetation or self.facade_details or self.fences_hedges
                or self.street_signs or self.curved_cars or self.garden_vegetation or self.detached_houses
                or self.sidewalk_parking or self.window_recesses
                or self.terrain_roughness > 0)


@dataclass
class Town:
    """The town's triangle mesh, per-triangle reflectance/material, and its layout.

    Attributes
    ----------
    vertices : np.ndarray
        ``(V, 3)`` float32 world coordinates (world = LiDAR frame of scan 0, z up).
    triangles : np.ndarray
        ``(T, 3)`` uint32 vertex indices.
    albedo : np.ndarray
        ``(T,)`` float32 reflectance of each triangle in [0, 1].
    material : np.ndarray
        ``(T,)`` uint8 material id (see ``meshes.MATERIAL_NAMES``).
    footprints : dict
        ``kind -> (n, 4, 2)`` rectangle corners (buildings, walls, cars) or ``(n, 3)``
        circles ``x, y, r`` (trees, bushes, poles), for plots.
    path_xyz : np.ndarray
        ``(M, 3)`` the sensor path resampled every ``config.path_step`` metres.
    ground : GroundModel
        The analytic height field the ground mesh samples.
    seed : int
        The layout seed.
    config : TownConfig
        The layout parameters.
    build_seconds : float
        Wall time of :func:`build_town`.
    ground_grid : dict
        ``x`` ``(nx,)``, ``y`` ``(ny,)`` and ``z`` ``(nx, ny)`` (NaN off the ground mesh), for plots.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    albedo: np.ndarray
    material: np.ndarray
    footprints: dict[str, np.ndarray]
    path_xyz: np.ndarray
    ground: "GroundModel"
    seed: int
    config: TownConfig
    build_seconds: float = 0.0
    ground_grid: dict[str, np.ndarray] = field(default_factory=dict)


def resample_path(positions: np.ndarray, step: float) -> np.ndarray:
    """Resample a polyline ``(K, 3)`` by arc length (xy) every ``step`` metres."""
    return resample_path_with_arc_length(positions, step)[0]


def resample_path_with_arc_length(positions: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`resample_path`, and the xy arc length ``(K,)`` of each input point along the polyline."""
    seg = np.linalg.norm(np.diff(positions[:, :2], axis=0), axis=1)
    s_in = np.concatenate([[0.0], np.cumsum(seg)])
    keep = np.concatenate([[True], seg > 1e-9])  # drop stationary duplicates
    s, kept = s_in[keep], positions[keep]
    q = np.arange(0.0, s[-1] + 1e-9, step)
    return np.stack([np.interp(q, s, kept[:, k]) for k in range(3)], axis=1), s_in


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


class GroundModel:
    """Analytic ground height ``h(x, y)``.

    ``h = h_path + curb(d) + undulation(x, y) · blend(d)``, where ``h_path`` is an
    inverse-distance-weighted average of the path's ground height (sensor height minus
    ``sensor_height``) over the 16 nearest path samples taken every metre (weights
    ``1 / (d² + 16 m²)``), ``d`` the distance to the path, the
    curb raises the sidewalk by ``curb_height`` just beyond the road edge, and the
    undulation (a few long-wavelength sinusoids) fades in from 12 m to 42 m off the road.
    """

    def __init__(self, path_xyz: np.ndarray, config: TownConfig, rng: np.random.Generator):
        self.config = config
        self.path_xyz = path_xyz
        self.kd = cKDTree(path_xyz[:, :2])
        stride = max(1, int(round(1.0 / config.path_step)))
        self.kd_h = cKDTree(path_xyz[::stride, :2])
        self.h_samples = path_xyz[::stride, 2] - config.sensor_height
        n = 4
        ang = rng.uniform(0, np.pi, n)
        self.wave_dir = np.c_[np.cos(ang), np.sin(ang)]
        self.wave_k = 2 * np.pi / rng.uniform(60.0, 180.0, n)
        self.wave_phase = rng.uniform(0, 2 * np.pi, n)
        self.wave_amp = rng.uniform(0.5, 1.0, n) * config.terrain_amplitude / n * 2

    def distance(self, xy: np.ndarray, upper: float = np.inf) -> np.ndarray:
        """Distance of each xy to the path (``inf`` beyond ``upper``)."""
        return self.kd.query(xy, k=1, distance_upper_bound=upper, workers=-1)[0]

    def __call__(self, xy: np.ndarray, d: np.ndarray | None = None) -> np.ndarray:
        """Ground height at ``xy`` ``(N, 2)``; ``d`` (distance to the path) if known."""
        xy = np.atleast_2d(np.asarray(xy, dtype=np.float64))
        h = np.empty(len(xy))
        k = min(16, len(self.h_samples))
        for s in range(0, len(xy), 65536):  # chunks bound the memory of the k-NN query
            dist, idx = self.kd_h.query(xy[s:s + 65536], k=k, workers=-1)
            dist, idx = dist.reshape(len(dist), -1), idx.reshape(len(idx), -1)
            w = 1.0 / (dist**2 + 16.0)
            h[s:s + 65536] = (w * self.h_samples[idx]).sum(axis=1) / w.sum(axis=1)
        if d is None:
            d = self.distance(xy)
        c = self.config
        h = h + c.curb_height * _smoothstep((d - c.road_half_width) / 0.5)
        wave = (self.wave_amp * np.sin(xy @ self.wave_dir.T * self.wave_k + self.wave_phase)).sum(1)
        return h + wave * _smoothstep((d - 12.0) / 30.0)


class _Layout:
    """Occupancy grid + path-clearance checks for placing footprints."""

    def __init__(self, ground: GroundModel, lo: np.ndarray, hi: np.ndarray, cell: float = 0.5):
        self.ground = ground
        self.lo, self.cell = lo, cell
        shape = np.ceil((hi - lo) / cell).astype(int) + 1
        self.occ = np.zeros(shape, dtype=bool)

    @staticmethod
    def rect_samples(cx, cy, yaw, length, width, spacing=0.35) -> np.ndarray:
        nl = max(2, int(np.ceil(length / spacing)) + 1)
        nw = max(2, int(np.ceil(width / spacing)) + 1)
        u, v = np.meshgrid(np.linspace(-length / 2, length / 2, nl),
                           np.linspace(-width / 2, width / 2, nw), indexing="ij")
        c, s = np.cos(yaw), np.sin(yaw)
        return np.c_[cx + c * u.ravel() - s * v.ravel(), cy + s * u.ravel() + c * v.ravel()]

    def _cells(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        ij = np.floor((pts - self.lo) / self.cell).astype(int)
        if (ij < 0).any() or (ij[:, 0] >= self.occ.shape[0]).any() or (ij[:, 1] >= self.occ.shape[1]).any():
            return None
        return ij[:, 0], ij[:, 1]

    def try_place(self, pts: np.ndarray, clearance: float, occupy_pts: np.ndarray | None = None) -> bool:
        """Place a footprint sampled by ``pts`` if it is ``clearance`` off the path and free."""
        cells = self._cells(pts)
        if cells is None or self.occ[cells].any():
            return False
        if np.isfinite(self.ground.distance(pts, upper=clearance)).any():
            return False
        occ = cells if occupy_pts is None else self._cells(occupy_pts)
        if occ is not None:
            self.occ[occ] = True
        return True


def _rect_corners(cx, cy, yaw, length, width) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    local = np.array([[-length / 2, -width / 2], [length / 2, -width / 2],
                      [length / 2, width / 2], [-length / 2, width / 2]])
    return local @ np.array([[c, s], [-s, c]]) + (cx, cy)


def _ellipsoid_volume_points(rng: np.random.Generator, centre: np.ndarray, radii: np.ndarray,
                             n: int) -> np.ndarray:
    """``n`` points uniform in the ellipsoid ``centre``, ``radii``."""
    d = rng.normal(size=(n, 3))
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    return centre + d * (rng.random(n) ** (1.0 / 3.0))[:, None] * radii


def _leaf_count(volume: float, leaf_area_density: float, leaf_size: float) -> int:
    """Elements of side ``leaf_size`` carrying ``leaf_area_density`` (one-sided) in ``volume``."""
    return int(round(leaf_area_density * volume / (np.sqrt(3.0) / 4.0 * leaf_size ** 2)))


def _porous_crown(mb: MeshBuilder, rng: np.random.Generator, centre: np.ndarray, radii: np.ndarray,
                  leaf_area_density: float, leaf_size: float, albedo: float,
                  trunk: tuple[float, float, float, float] | None = None, trunk_albedo: float = 0.3) -> None:
    """A crown (or bush) as a porous volume of randomly oriented leaf-cluster elements.

    With one-sided leaf area density ``LAD`` and randomly oriented elements (projection
    factor G = 0.5, the spherical leaf angle distribution), a ray inside the crown travels a
    free path of mean ``1 / (G LAD)`` (2 m for 1 m²/m³), so the beam returns from the
    hull, from inside the crown or passes through (Beer-Lambert gap fraction). Elements
    are ``leaf_size`` x U(0.7, 1.3); a tree also gets 4-7 branches from the trunk top.
    """
    volume = 4.0 / 3.0 * np.pi * float(np.prod(radii))
    n = max(1, _leaf_count(volume, leaf_area_density, leaf_size))
    pts = _ellipsoid_volume_points(rng, centre, radii, n)
    size = leaf_size * rng.uniform(0.7, 1.3, n)
    alb = np.clip(albedo + rng.normal(0.0, 0.03, n), 0.02, 1.0).astype(np.float32)
    mb.add(leaf_cloud(pts, size, rng), alb, MATERIAL["foliage"])
    if trunk is not None:
        x, y, z, r = trunk
        for _ in range(int(rng.integers(4, 8))):
            a = rng.uniform(0, 2 * np.pi)
            reach = rng.uniform(0.5, 0.85)
            end = centre + np.array([np.cos(a) * radii[0] * reach, np.sin(a) * radii[1] * reach,
                                     rng.uniform(-0.2, 0.5) * radii[2]])
            mb.add(rod((x, y, z - rng.uniform(0.0, 0.6)), end, 0.35 * r), trunk_albedo, MATERIAL["trunk"])


def _facade_details(mb: MeshBuilder, rng: np.random.Generator, centre: np.ndarray, yaw: float,
                    length: float, depth: float, g: float, zt: float, albedo: float, roof: bool) -> None:
    """Eaves or a gable roof, floor bands, window sills and balconies on one building block.

    Storey height 3 m; sills 1.2 m wide protruding 0.1-0.15 m every 2.4-3.6 m; balconies
    1.0-1.5 m deep and 2.4-4 m wide with a 1 m railing (residential building codes require
    railings of about 0.9-1.1 m); roof pitch 25-45 degrees; eaves overhang 0.3-0.7 m.
    """
    ex = np.array([np.cos(yaw), np.sin(yaw)])
    ey = np.array([-np.sin(yaw), np.cos(yaw)])
    n_floors = max(1, int((zt - g) / 3.0))
    bands, sills, balconies = rng.uniform() < 0.5, rng.uniform() < 0.8, rng.uniform() < 0.5
    faces = [(ex, 0.5 * length, ey, depth), (-ex, 0.5 * length, -ey, depth),
             (ey, 0.5 * depth, -ex, length), (-ey, 0.5 * depth, ex, length)]

    def detail(n, dist, t, u, w, p, z0, z1, alb=albedo):
        q = centre + n * (dist + 0.5 * p) + t * u
        mb.add(box(q[0], q[1], np.arctan2(t[1], t[0]), w, p, z0, z1), alb, MATERIAL["building"])

    for n, dist, t, fw in faces:
        if bands:
            p = rng.uniform(0.08, 0.2)
            for f in range(1, n_floors):
                detail(n, dist, t, 0.0, fw + 2 * p, p, g + 3.0 * f - 0.1, g + 3.0 * f + 0.15)
        if sills and fw > 3.0:
            spacing = rng.uniform(2.4, 3.6)
            us = np.arange(-0.5 * fw + 1.2, 0.5 * fw - 1.2 + 1e-9, spacing)
            p = rng.uniform(0.1, 0.15)
            for f in range(n_floors):
                for u in us:
                    detail(n, dist, t, u, 1.2, p, g + 3.0 * f + 0.85, g + 3.0 * f + 0.95)
        if balconies and fw > 6.0 and n_floors > 1 and abs(n @ ey) > 0.5:
            for u in np.arange(-0.5 * fw + 3.0, 0.5 * fw - 2.0, rng.uniform(6.0, 9.0)):
                if rng.uniform() < 0.4:
                    continue
                w, p = rng.uniform(2.4, 4.0), rng.uniform(1.0, 1.5)
                for f in range(1, n_floors):
                    z = g + 3.0 * f
                    detail(n, dist, t, u, w, p, z - 0.15, z)
                    detail(n, dist + p - 0.05, t, u, w, 0.05, z, z + 1.0, albedo * 0.7)
    if not roof:
        return
    if zt - g < 13.0 and rng.uniform() < 0.6:
        pitch = np.radians(rng.uniform(25.0, 45.0))
        over = rng.uniform(0.3, 0.7)
        if length >= depth:
            mb.add(gable_roof(centre[0], centre[1], yaw, length, depth, zt, 0.5 * depth * np.tan(pitch), over),
                   albedo * 0.6, MATERIAL["building"])
        else:
            mb.add(gable_roof(centre[0], centre[1], yaw + np.pi / 2, depth, length, zt,
                              0.5 * length * np.tan(pitch), over), albedo * 0.6, MATERIAL["building"])
    elif rng.uniform() < 0.5:  # a parapet around a flat roof
        for n, dist, t, fw in faces:
            detail(n, dist - 0.2, t, 0.0, fw, 0.2, zt, zt + rng.uniform(0.5, 1.0))
    else:  # a cornice overhanging the walls
        over = rng.uniform(0.3, 0.6)
        mb.add(box(centre[0], centre[1], yaw, length + 2 * over, depth + 2 * over, zt - 0.3, zt),
               albedo * 0.8, MATERIAL["building"])


def _window_facades(mb: MeshBuilder, rng: np.random.Generator, centre: np.ndarray, yaw: float,
                    length: float, depth: float, g: float, z0: float, zt: float, albedo: float,
                    recess: float) -> None:
    """Recessed windows on every face of a building block (see ``TownConfig.window_recesses``).

    The block's own faces become the glass plane; the wall between the windows is added as
    panels ``recess`` thick in front of it: per storey a band below the sills, a band above
    the windows and piers between them, plus a band from the last storey to the top.
    """
    ex = np.array([np.cos(yaw), np.sin(yaw)])
    ey = np.array([-np.sin(yaw), np.cos(yaw)])
    faces = [(ey, 0.5 * depth, ex, length), (-ey, 0.5 * depth, ex, length),
             (ex, 0.5 * length, ey, depth), (-ex, 0.5 * length, ey, depth)]
    n_floors = max(1, int((zt - g) / 3.0))
    wall = MATERIAL["building"]

    def panel(n, dist, t, u, w, th, za, zb, alb, mat):
        if w <= 0.02 or zb <= za:
            return
        q = centre + n * (dist + 0.5 * th) + t * u
        mb.add(box(q[0], q[1], np.arctan2(t[1], t[0]), w, th, za, zb), alb, mat)

    for n, dist, t, fw in faces:
        span = fw + 2.0 * recess  # the panels close the corners
        ww, wh = rng.uniform(1.0, 1.6), rng.uniform(1.2, 1.6)
        sill = rng.uniform(0.8, 1.0)
        spacing = max(rng.uniform(2.2, 3.6), ww + 0.6)
        n_win = int((fw - 1.0) // spacing)
        if n_win < 1:
            panel(n, dist, t, 0.0, span, recess, z0, zt, albedo, wall)
            continue
        us = (np.arange(n_win) - 0.5 * (n_win - 1)) * spacing
        edges = np.concatenate([[-0.5 * span], np.ravel(np.c_[us - 0.5 * ww, us + 0.5 * ww]), [0.5 * span]])
        z_lo = z0
        for f in range(n_floors):
            zf = g + 3.0 * f
            za, zb = zf + sill, min(zf + sill + wh, zt - 0.3)
            if zb - za < 0.5:
                break
            panel(n, dist, t, 0.0, span, recess, z_lo, za, albedo, wall)
            for a, b in zip(edges[0::2], edges[1::2]):  # piers between the windows
                panel(n, dist, t, 0.5 * (a + b), b - a, recess, za, zb, albedo, wall)
            for u in us:  # the glass, in the block's face
                panel(n, dist, t, u, ww, 0.02, za, zb, 0.08, MATERIAL["glass"])
            z_lo = zb
        panel(n, dist, t, 0.0, span, recess, z_lo, zt, albedo, wall)


def _fence_or_hedge(mb: MeshBuilder, rng: np.random.Generator, c: TownConfig, kind: float,
                    centre: np.ndarray, yaw: float, length: float, width: float, ground: GroundModel,
                    fp: dict[str, list]) -> None:
    """One property-line element: a hedge (``kind`` < 0.4), a picket fence (< 0.75) or a railing.

    Hedges 0.9-1.8 m high and ``width`` thick (porous like bushes when
    ``c.porous_vegetation``); picket fences 0.9-1.3 m with 8 cm pickets 12-20 cm apart;
    railings 1.0-1.8 m with posts every 2.5 m and two rails.
    """
    ex = np.array([np.cos(yaw), np.sin(yaw)])
    albedo = rng.uniform(0.25, 0.75)
    hedge = c.hedge_fraction
    if kind < hedge:
        h = rng.uniform(*c.hedge_height)
        g = float(ground(centre[None])[0])
        alb = rng.uniform(0.15, 0.35)
        if c.porous_vegetation:
            n = max(1, _leaf_count(length * width * h, c.shrub_leaf_area_density, c.shrub_leaf_size))
            local = rng.uniform(-0.5, 0.5, (n, 3)) * (length, width, h)
            pts = np.c_[centre[0] + ex[0] * local[:, 0] - ex[1] * local[:, 1],
                        centre[1] + ex[1] * local[:, 0] + ex[0] * local[:, 1], g + 0.5 * h + local[:, 2]]
            size = c.shrub_leaf_size * rng.uniform(0.7, 1.3, n)
            mb.add(leaf_cloud(pts, size, rng), alb, MATERIAL["foliage"])
        else:
            mb.add(box(centre[0], centre[1], yaw, length, width, g - 0.1, g + h), alb, MATERIAL["foliage"])
    elif kind < hedge + (1.0 - hedge) * 35.0 / 60.0:
        h, spacing = rng.uniform(0.9, 1.3), rng.uniform(0.12, 0.2)
        us = np.arange(-0.5 * length + 0.05, 0.5 * length, spacing)
        q = centre + us[:, None] * ex
        gs = ground(q)
        for (qx, qy), g in zip(q, gs):
            mb.add(box(qx, qy, yaw, 0.08, 0.02, g - 0.05, g + h), albedo, MATERIAL["wall"])
        g0 = float(gs.mean())
        for z in (0.25, h - 0.2):
            mb.add(box(centre[0], centre[1], yaw, length, 0.03, g0 + z, g0 + z + 0.08), albedo, MATERIAL["wall"])
    else:
        h = rng.uniform(1.0, 1.8)
        us = np.arange(-0.5 * length, 0.5 * length + 1e-9, 2.5)
        q = centre + us[:, None] * ex
        gs = ground(q)
        for (qx, qy), g in zip(q, gs):
            mb.add(box(qx, qy, yaw, 0.06, 0.06, g - 0.1, g + h), albedo, MATERIAL["pole"])
        g0 = float(gs.mean())
        a, b = centre - 0.5 * length * ex, centre + 0.5 * length * ex
        for z in (0.45 * h, h - 0.05):
            mb.add(rod((a[0], a[1], g0 + z), (b[0], b[1], g0 + z), 0.025, 4), albedo, MATERIAL["pole"])
    fp["wall"].append(_rect_corners(centre[0], centre[1], yaw, length, width))


def build_town(positions: np.ndarray, seed: int = 0, config: TownConfig | None = None) -> Town:
    """Build the town around the sensor path ``positions`` ``(K, 3)`` (world frame, z up).

    Deterministic for ``(positions, seed, config)``.
    """
    t0 = time.perf_counter()
    c = config or TownConfig()
    positions = np.asarray(positions, dtype=np.float64)
    if positions.ndim != 2 or positions.shape[1] != 3 or len(positions) < 2:
        raise ValueError(f"build_town: positions must be (K>=2, 3), got {positions.shape}")
    if not np.isfinite(positions).all():
        raise ValueError("build_town: positions contain non-finite values")
    ss = np.random.SeedSequence([int(seed), 0x70776E])
    rngs = [np.random.default_rng(s) for s in ss.spawn(10)]
    # the world effects draw from their own generators, so the layout (and, with every effect
    # off, the whole town) is the same with and without them
    fx = [np.random.default_rng(s) for s in np.random.SeedSequence([int(seed), 0x70776E, 1]).spawn(9)]
    path = resample_path(positions, c.path_step)
    if len(path) < 4:
        raise ValueError("build_town: the path is shorter than 2 m")
    ground = GroundModel(path, c, rngs[0])
    mb = MeshBuilder()

    # ---- ground height field -------------------------------------------------------------
    lo = path[:, :2].min(0) - c.ground_extent
    hi = path[:, :2].max(0) + c.ground_extent
    xs = np.arange(lo[0], hi[0] + c.ground_cell, c.ground_cell)
    ys = np.arange(lo[1], hi[1] + c.ground_cell, c.ground_cell)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    gxy = np.c_[gx.ravel(), gy.ravel()]
    vd = ground.distance(gxy, upper=c.ground_extent + 2 * c.ground_cell)
    vmask = np.isfinite(vd)
    vz = np.full(len(gxy), np.nan)
    vz[vmask] = ground(gxy[vmask], vd[vmask])
    if c.terrain_roughness > 0:  # uneven lawns/verges beyond the sidewalk (not the road or sidewalk)
        fade = _smoothstep((vd[vmask] - c.road_half_width - c.sidewalk_width - 0.5) / 1.5)
        vz[vmask] += c.terrain_roughness * fx[0].standard_normal(int(vmask.sum())) * fade
    nx, ny = len(xs), len(ys)
    i, j = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1), indexing="ij")
    i, j = i.ravel(), j.ravel()
    v00, v10, v01, v11 = i * ny + j, (i + 1) * ny + j, i * ny + j + 1, (i + 1) * ny + j + 1
    cmask = vmask[v00] & vmask[v10] & vmask[v01] & vmask[v11]
    v00, v10, v01, v11 = v00[cmask], v10[cmask], v01[cmask], v11[cmask]
    cd = 0.25 * (vd[v00] + vd[v10] + vd[v01] + vd[v11])  # ~ distance of the cell centre
    keep = cd <= c.ground_extent
    v00, v10, v01, v11, cd = v00[keep], v10[keep], v01[keep], v11[keep], cd[keep]
    used = np.zeros(len(gxy), dtype=bool)
    used[np.concatenate([v00, v10, v01, v11])] = True
    remap = np.cumsum(used) - 1
    gverts = np.c_[gxy[used], vz[used]]
    gtris = np.concatenate([np.c_[remap[v00], remap[v10], remap[v11]],
                            np.c_[remap[v00], remap[v11], remap[v01]]])
    mat = np.where(cd < c.road_half_width, MATERIAL["road"],
                   np.where(cd < c.road_half_width + c.sidewalk_width, MATERIAL["sidewalk"],
                            MATERIAL["terrain"])).astype(np.uint8)
    base_albedo = np.array([0.16, 0.32, 0.42], np.float32)[mat]
    alb = np.clip(base_albedo + rngs[1].normal(0, 0.03, len(mat)).astype(np.float32), 0.02, 1)
    mb.add((gverts, gtris), np.concatenate([alb, alb]), np.concatenate([mat, mat]))
    grid_z = vz.reshape(nx, ny)

    # ---- tangents / normals along the path --------------------------------------------------
    xy = path[:, :2]
    w = max(1, int(round(2.0 / c.path_step)))
    tang = xy[np.minimum(np.arange(len(xy)) + w, len(xy) - 1)] - xy[np.maximum(np.arange(len(xy)) - w, 0)]
    tang /= np.maximum(np.linalg.norm(tang, axis=1, keepdims=True), 1e-9)
    left = np.c_[-tang[:, 1], tang[:, 0]]
    heading = np.arctan2(tang[:, 1], tang[:, 0])
    total = (len(path) - 1) * c.path_step
    layout = _Layout(ground, lo, hi)
    fp: dict[str, list] = {k: [] for k in ("building", "wall", "car", "tree", "bush", "pole")}

    def frame_at(s: float) -> int:
        return int(np.clip(round(s / c.path_step), 0, len(path) - 1))

    def place_rect(s, side, offset, length, width, clearance, yaw_jitter=0.0, rng=None):
        k = frame_at(s)
        centre = xy[k] + side * left[k] * offset
        yaw = heading[k] + (rng.uniform(-yaw_jitter, yaw_jitter) if yaw_jitter else 0.0)
        pts = layout.rect_samples(centre[0], centre[1], yaw, length, width)
        if not layout.try_place(pts, clearance):
            return None
        return centre, yaw, pts

    # ---- buildings -------------------------------------------------------------------------
    rng = rngs[2]
    for side in (1.0, -1.0):
        s = rng.uniform(0.0, 10.0)
        while s < total:
            length = rng.uniform(8.0, 32.0)
            if c.detached_houses:
                length = 8.0 + 0.4 * (length - 8.0)
            depth = rng.uniform(8.0, 18.0)
            setback = rng.uniform(c.building_clearance + 0.5, c.building_setback_max)
            kind = rng.uniform()
            height = (rng.uniform(3.0, 5.0) if kind < 0.1 else rng.uniform(6.0, 12.0)
                      if kind < 0.7 else rng.uniform(12.0, 24.0))
            tier, gap_draw, albedo = rng.uniform(), rng.uniform(), rng.uniform(0.3, 0.7)
            got = place_rect(s + length / 2, side, setback + depth / 2, length, depth,
                             c.building_clearance)
            if got is None:
                s += 3.0
                continue
            centre, yaw, pts = got
            hg = ground(pts[:: max(1, len(pts) // 64)])
            z0, zt = hg.min() - 0.5, hg.mean() + height
            mb.add(box(centre[0], centre[1], yaw, length, depth, z0, zt), albedo, MATERIAL["building"])
            fp["building"].append(_rect_corners(centre[0], centre[1], yaw, length, depth))
            has_tier = tier < 0.35 and length > 10 and depth > 9
            if has_tier:
                # an upper tier set back 2 m from every side of the block
                mb.add(box(centre[0], centre[1], yaw, length - 4.0, depth - 4.0, zt - 0.2,
                           zt + rng.uniform(3.0, 8.0)), albedo * 0.9, MATERIAL["building"])
            if c.window_recesses:
                _window_facades(mb, fx[8], centre, yaw, length, depth, float(hg.mean()), z0, zt, albedo,
                                c.window_recess)
            if c.facade_details:
                _facade_details(mb, fx[1], centre, yaw, length, depth, float(hg.mean()), zt, albedo,
                                roof=not has_tier)
            if c.detached_houses:
                s += length + rng.uniform(3.0, 14.0)
            else:
                s += length + (0.0 if gap_draw < 0.45 else rng.uniform(2.0, 14.0))

    # ---- low walls / fences (fill some gaps) ------------------------------------------------
    rng = rngs[3]
    for side in (1.0, -1.0) if c.low_walls else ():
        s = rng.uniform(0.0, 20.0)
        while s < total:
            length = rng.uniform(4.0, 16.0)
            off = rng.uniform(c.building_clearance + 0.3, 10.5)
            height = rng.uniform(1.0, 2.2)
            albedo = rng.uniform(0.25, 0.6)
            got = place_rect(s + length / 2, side, off, length, 0.3, c.building_clearance)
            if got is not None:
                centre, yaw, pts = got
                hg = ground(pts[::8])
                mb.add(box(centre[0], centre[1], yaw, length, 0.3, hg.min() - 0.3, hg.mean() + height),
                       albedo, MATERIAL["wall"])
                fp["wall"].append(_rect_corners(centre[0], centre[1], yaw, length, 0.3))
            s += length + rng.uniform(5.0, 25.0)

    # ---- trees along the sidewalk, bushes, poles ---------------------------------------------
    def add_tree(x, y, rng, crown_scale=1.0, crown_check=1.0) -> bool:
        rc = rng.uniform(1.5, 3.0) * crown_scale
        rz = rng.uniform(1.5, 3.5) * crown_scale
        trunk_r, trunk_h = rng.uniform(0.15, 0.3), rng.uniform(2.0, 3.5)
        stretch = rng.uniform(0.8, 1.2)
        rcheck = max(rc * crown_check, 2 * trunk_r)
        crown_pts = layout.rect_samples(x, y, 0.0, 2 * rcheck, 2 * rcheck, spacing=0.5)
        trunk_pts = layout.rect_samples(x, y, 0.0, 2 * trunk_r, 2 * trunk_r)
        cells = layout._cells(crown_pts)
        if cells is None or layout.occ[cells].any():
            return False
        if not layout.try_place(trunk_pts, c.furniture_clearance, occupy_pts=crown_pts):
            return False
        g = float(ground(np.array([[x, y]]))[0])
        trunk_albedo = rng.uniform(0.25, 0.4)
        mb.add(cylinder(x, y, trunk_r, g - 0.3, g + trunk_h + 0.5 * rz, 7), trunk_albedo,
               MATERIAL["trunk"])
        crown_c = np.array([x, y, g + trunk_h + 0.8 * rz])
        crown_r = np.array([rc * stretch, rc / stretch, rz])
        crown = blob(crown_c, crown_r, rng, subdivisions=2, roughness=0.3)  # draws kept either way
        foliage_albedo = rng.uniform(0.15, 0.3)
        if c.porous_vegetation:
            _porous_crown(mb, fx[2], crown_c, crown_r, c.leaf_area_density, c.leaf_size, foliage_albedo,
                          trunk=(x, y, g + trunk_h + 0.5 * rz, trunk_r), trunk_albedo=trunk_albedo)
        else:
            mb.add(crown, foliage_albedo, MATERIAL["foliage"])
        fp["tree"].append((x, y, rc))
        return True

    rng = rngs[4]
    for side in (1.0, -1.0):
        s = rng.uniform(0.0, 15.0)
        while s < total:
            k = frame_at(s)
            off = rng.uniform(6.0, 7.5)
            p = xy[k] + side * left[k] * off
            # street trees: smaller crowns that may reach over facades a little
            add_tree(p[0], p[1], rng, crown_scale=0.75, crown_check=0.5)
            s += rng.uniform(*c.street_tree_spacing)

    rng = rngs[5]
    for side in (1.0, -1.0):
        s = rng.uniform(0.0, 30.0)
        while s < total:
            k = frame_at(s)
            off = rng.uniform(5.7, 6.4)
            p = xy[k] + side * left[k] * off
            r, h = rng.uniform(0.08, 0.16), rng.uniform(5.0, 9.0)
            arm = rng.uniform() < 0.5
            pts = layout.rect_samples(p[0], p[1], 0.0, 2 * r + 0.2, 2 * r + 0.2)
            if layout.try_place(pts, c.furniture_clearance):
                g = float(ground(p[None])[0])
                mb.add(cylinder(p[0], p[1], r, g - 0.3, g + h, 8), rng.uniform(0.4, 0.7), MATERIAL["pole"])
                if arm:  # a lamp arm reaching over the road
                    q = p - side * left[k] * 1.0
                    yaw = np.arctan2(left[k, 1], left[k, 0])
                    mb.add(box(q[0], q[1], yaw, 2.0, 0.15, g + h - 0.25, g + h - 0.05), 0.5, MATERIAL["pole"])
                fp["pole"].append((p[0], p[1], r))
            s += rng.uniform(18.0, 45.0)

    rng = rngs[6]
    for side in (1.0, -1.0):
        s = rng.uniform(0.0, 8.0)
        while s < total:
            k = frame_at(s)
            off = rng.uniform(7.6, 10.0)
            p = xy[k] + side * left[k] * off
            rr = rng.uniform(0.4, 1.2, 2)
            rz = rng.uniform(0.35, 0.9)
            pts = layout.rect_samples(p[0], p[1], 0.0, 2 * rr.max(), 2 * rr.max(), spacing=0.4)
            if layout.try_place(pts, c.furniture_clearance + 1.0):
                g = float(ground(p[None])[0])
                bush_c, bush_r = np.array([p[0], p[1], g + 0.6 * rz]), np.array([rr[0], rr[1], rz])
                bush = blob(bush_c, bush_r, rng, subdivisions=1, roughness=0.4)
                bush_albedo = rng.uniform(0.15, 0.35)
                if c.porous_vegetation:
                    _porous_crown(mb, fx[3], bush_c, bush_r, c.shrub_leaf_area_density, c.shrub_leaf_size,
                                  bush_albedo)
                else:
                    mb.add(bush, bush_albedo, MATERIAL["foliage"])
                fp["bush"].append((p[0], p[1], rr.max()))
            s += rng.uniform(*c.roadside_bush_spacing)

    # ---- parks: trees scattered in open space off the road -----------------------------------
    rng = rngs[7]
    n_try = int(total / 2.5)
    for _ in range(n_try):
        k = rng.integers(len(path))
        side = 1.0 if rng.uniform() < 0.5 else -1.0
        off = rng.uniform(11.0, 70.0)
        p = xy[k] + side * left[k] * off + rng.normal(0, 5.0, 2)
        if np.isfinite(ground.distance(p[None], upper=c.building_clearance)).any():
            continue
        add_tree(p[0], p[1], rng, crown_scale=rng.uniform(0.9, 1.5))

    # ---- parked cars ------------------------------------------------------------------------
    rng = rngs[8]
    for side in (1.0, -1.0):
        s = rng.uniform(0.0, 10.0)
        parked = False
        while s < total:
            slot = rng.uniform(5.5, 8.0)
            parked = rng.uniform() < (c.parking_stay if parked else c.parking_start)
            if parked:
                L, W = rng.uniform(3.8, 4.9), rng.uniform(1.7, 1.95)
                off = rng.uniform(3.55, 3.95)
                if c.sidewalk_parking and side > 0:  # half on the left sidewalk, clear of the oncoming lane
                    off += 5.4 - 3.55
                got = place_rect(s + slot / 2, side, off, L, W, c.car_clearance, yaw_jitter=0.06, rng=rng)
                if got is not None:
                    centre, yaw, pts = got
                    g = float(ground(centre[None])[0])
                    hb, hc = rng.uniform(0.65, 0.9), rng.uniform(0.45, 0.65)
                    clear = rng.uniform(0.2, 0.32)
                    colour = rng.uniform(0.2, 0.85)
                    shift = rng.uniform(-0.4, 0.1) * L / 2
                    cabin_length = rng.uniform(0.45, 0.6) * L
                    if c.curved_cars:
                        cv, ct, glass = car_mesh(L, W, clear + hb + hc, clearance=clear - 0.08, rng=fx[4])
                        cs, sn = np.cos(yaw), np.sin(yaw)
                        wv = np.c_[centre[0] + cs * cv[:, 0] - sn * cv[:, 1],
                                   centre[1] + sn * cv[:, 0] + cs * cv[:, 1], g + cv[:, 2]]
                        mb.add((wv, ct), np.where(glass, 0.08, colour).astype(np.float32),
                               np.where(glass, MATERIAL["glass"], MATERIAL["car"]))
                    else:
                        mb.add(box(centre[0], centre[1], yaw, L, W, g + clear, g + clear + hb), colour,
                               MATERIAL["car"])
                        cc = centre + shift * np.array([np.cos(yaw), np.sin(yaw)])
                        mb.add(box(cc[0], cc[1], yaw, cabin_length, W - 0.15,
                                   g + clear + hb - 0.05, g + clear + hb + hc), 0.08, MATERIAL["glass"])
                    fp["car"].append(_rect_corners(centre[0], centre[1], yaw, L, W))
            s += slot

    # ---- fences, hedges and signs (world effects; placed after everything else) --------------
    if c.fences_hedges:
        rng = fx[5]
        for side in (1.0, -1.0):
            s = rng.uniform(0.0, 10.0)
            while s < total:
                length = rng.uniform(4.0, 16.0)
                kind = rng.uniform()
                off = rng.uniform(8.1, 8.6)
                width = 0.7 if kind < c.hedge_fraction else 0.12
                got = place_rect(s + length / 2, side, off, length, width + 0.2, 7.8)
                if got is not None:
                    centre, yaw, pts = got
                    _fence_or_hedge(mb, rng, c, kind, centre, yaw, length, width, ground, fp)
                s += length + rng.uniform(*c.property_gap)
    if c.street_signs:
        rng = fx[6]
        for side in (1.0, -1.0):
            s = rng.uniform(0.0, 30.0)
            while s < total:
                k = frame_at(s)
                p = xy[k] + side * left[k] * rng.uniform(5.35, 5.7)
                h, plate = rng.uniform(2.2, 3.0), rng.uniform(0.5, 0.8)
                pts = layout.rect_samples(p[0], p[1], 0.0, 0.3, 0.3)
                if layout.try_place(pts, 5.2):
                    g = float(ground(p[None])[0])
                    mb.add(cylinder(p[0], p[1], 0.035, g - 0.2, g + h, 6), 0.5, MATERIAL["pole"])
                    # the plate faces the traffic: its plane is across the road direction
                    yaw = heading[k] + np.pi / 2
                    q = p + 0.05 * np.array([np.cos(heading[k]), np.sin(heading[k])])
                    mb.add(box(q[0], q[1], yaw, plate, 0.03, g + h - plate, g + h), 0.9, MATERIAL["pole"])
                    fp["pole"].append((p[0], p[1], 0.035))
                s += rng.uniform(25.0, 70.0)

    if c.garden_vegetation:
        rng = fx[7]
        for side in (1.0, -1.0):
            s = rng.uniform(0.0, 6.0)
            while s < total:
                k = frame_at(s)
                p = xy[k] + side * left[k] * rng.uniform(8.8, 16.0)
                if rng.uniform() < c.garden_tree_fraction:
                    add_tree(p[0], p[1], rng, crown_scale=rng.uniform(0.55, 0.9), crown_check=0.6)
                else:
                    rr, rz = rng.uniform(*c.garden_shrub_width, 2), rng.uniform(*c.garden_shrub_radii)
                    pts = layout.rect_samples(p[0], p[1], 0.0, 2 * rr.max(), 2 * rr.max(), spacing=0.4)
                    if layout.try_place(pts, 8.0):
                        g = float(ground(p[None])[0])
                        centre_b, radii_b = np.array([p[0], p[1], g + 0.6 * rz]), np.array([rr[0], rr[1], rz])
                        alb = rng.uniform(0.15, 0.35)
                        if c.porous_vegetation:
                            _porous_crown(mb, fx[3], centre_b, radii_b, c.shrub_leaf_area_density,
                                          c.shrub_leaf_size, alb)
                        else:
                            mb.add(blob(centre_b, radii_b, rng, subdivisions=1, roughness=0.4), alb,
                                   MATERIAL["foliage"])
                        fp["bush"].append((p[0], p[1], rr.max()))
                s += rng.uniform(*c.garden_spacing)

    verts, tris, albedo, material = mb.build()
    footprints = {k: np.asarray(v, dtype=np.float64) for k, v in fp.items()}
    town = Town(
        vertices=verts.astype(np.float32), triangles=tris, albedo=albedo, material=material,
        footprints=footprints, path_xyz=path, ground=ground, seed=int(seed), config=c,
        ground_grid={"x": xs, "y": ys, "z": grid_z},
    )
    town.build_seconds = time.perf_counter() - t0
    log.info("built town (seed %d): %d triangles, %s in %.1f s", seed, len(tris),
             ", ".join(f"{len(v)} {k}{'es' if k.endswith('sh') else 's'}" for k, v in footprints.items()), town.build_seconds)
    return town
