"""``SyntheticSequence``: a LiDAR sequence rendered on demand along the KITTI 00 trajectory.

Frames are ray cast (open3d ``RaycastingScene``) from the ground-truth LiDAR poses of KITTI
odometry sequence 00 (shipped in ``gr_graph/data/kitti00``; KITTI: Geiger, Lenz, Urtasun,
CVPR 2012, CC BY-NC-SA 3.0) into a procedural town (:mod:`.town`) with an HDL-64E-like
beam model (:mod:`.sensor`). The town is built lazily, once per process and seed, and
cached; frames are not cached.
"""

from __future__ import annotations

import logging
import threading
from collections import OrderedDict
from collections.abc import Iterator

import numpy as np

from gr_graph.datasets.base import LidarFrame, check_index
from gr_graph.datasets.synthetic.path import load_kitti00_path
from gr_graph.datasets.synthetic.sensor import BeamModel, NoiseModel, render_scan
from gr_graph.datasets.synthetic.town import Town, TownConfig, build_town

log = logging.getLogger(__name__)

_CACHE: "OrderedDict[int, tuple[Town, object]]" = OrderedDict()
_CACHE_SIZE = 2
_LOCK = threading.Lock()


def get_town_and_scene(town_seed: int) -> tuple[Town, object]:
    """The town of ``town_seed`` around KITTI 00 and its RaycastingScene (cached, built once)."""
    with _LOCK:
        if town_seed in _CACHE:
            _CACHE.move_to_end(town_seed)
            return _CACHE[town_seed]
        import open3d as o3d

        path = load_kitti00_path()
        town = build_town(path.T_w_velo[:, :3, 3], seed=town_seed)
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(town.vertices), o3d.core.Tensor(town.triangles))
        _CACHE[town_seed] = (town, scene)
        while len(_CACHE) > _CACHE_SIZE:
            _CACHE.popitem(last=False)
        return town, scene


def clear_scene_cache() -> None:
    """Forget every cached town/scene (the next frame rebuilds it)."""
    with _LOCK:
        _CACHE.clear()


class SyntheticSequence:
    """KITTI 00's trajectory rendered through a procedural town (LidarSequence protocol).

    Parameters
    ----------
    seed : int
        Seeds the per-frame noise (from ``(seed, frame index)``) and, unless ``town_seed``
        is given, the town. Same seed -> bit-identical frames.
    n_rings : int
        64, 32 or 16 (any divisor of 64): every ``64 // n_rings``-th HDL-64E beam. A
        lower-ring render equals those rings of the 64-ring render exactly.
    max_range : float
        Returns beyond this range (m) are dropped (at most ``ground_extent - 5`` = 130 m).
    n_azimuth : int
        Azimuth steps per revolution.
    range_sigma, dropout, min_range : float
        See :class:`~gr_graph.datasets.synthetic.sensor.NoiseModel`.
    town_seed : int, optional
        Seed of the town layout (default: ``seed``).
    nthreads : int
        Ray-casting threads (0 = open3d's default, all cores).
    """

    def __init__(self, seed: int = 0, n_rings: int = 64, max_range: float = 120.0,
                 n_azimuth: int = 2000, range_sigma: float = 0.02, dropout: float = 0.02,
                 min_range: float = 1.0, town_seed: int | None = None, nthreads: int = 0):
        self.seed = int(seed)
        self.town_seed = self.seed if town_seed is None else int(town_seed)
        if self.seed < 0 or self.town_seed < 0:
            raise ValueError(f"seeds must be >= 0, got seed={seed}, town_seed={town_seed}")
        self.beams = BeamModel(n_rings=int(n_rings), n_azimuth=int(n_azimuth))
        limit = TownConfig().ground_extent - 5.0
        if not 0 < max_range <= limit:
            raise ValueError(f"max_range must be in (0, {limit}] m (the town's ground extends "
                             f"{limit + 5:.0f} m from the path), got {max_range}")
        self.noise = NoiseModel(range_sigma=range_sigma, dropout=dropout, max_range=max_range,
                                min_range=min_range)
        self.nthreads = int(nthreads)
        path = load_kitti00_path()
        self.name = "synthetic-00"
        self.timestamps = path.times.copy()
        self.T_cam_velo = path.T_cam_velo.copy()
        self.gt_poses = path.T_w_velo.copy()
        self.motion_compensated = True  # every ray is cast from the frame's (mid-sweep) pose

    @property
    def n_rings(self) -> int:
        return self.beams.n_rings

    @property
    def town(self) -> Town:
        """The (cached) procedural town; built on first use."""
        return get_town_and_scene(self.town_seed)[0]

    def __len__(self) -> int:
        return len(self.gt_poses)

    def __repr__(self) -> str:
        return (f"SyntheticSequence(seed={self.seed}, n_rings={self.n_rings}, "
                f"max_range={self.noise.max_range}, n_azimuth={self.beams.n_azimuth})")

    def frame_rng(self, index: int) -> np.random.Generator:
        """The generator of frame ``index``'s noise: seeded by ``(seed, index)`` only."""
        return np.random.default_rng([self.seed, int(index), 0x5CA9])

    def __getitem__(self, index: int) -> LidarFrame:
        i = check_index(index, len(self), self.name)
        town, scene = get_town_and_scene(self.town_seed)
        points, intensity, ring = render_scan(
            scene, town.albedo, town.material, self.gt_poses[i], self.beams, self.noise,
            self.frame_rng(i), nthreads=self.nthreads)
        return LidarFrame(index=i, timestamp=float(self.timestamps[i]), points=points,
                          intensity=intensity, ring=ring, n_rings=self.n_rings)

    def __iter__(self) -> Iterator[LidarFrame]:
        for i in range(len(self)):
            yield self[i]
