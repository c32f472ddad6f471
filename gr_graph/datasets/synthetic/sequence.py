"""``SyntheticSequence``: a LiDAR sequence rendered on demand along a generated route.

Frames are ray cast (open3d ``RaycastingScene``) from the poses of the sensor path
(:mod:`.path`: by default the project's own route generated from ``route_seed``
(:mod:`.route`), or a given trajectory) into a procedural town built around that path
(:mod:`.town`) with the beam model of a sensor (:mod:`.sensor`: HDL-64E-like by default, VLP-16,
Ouster OS1-64). A preset is the whole world:
``kitti`` (the default) is the residential town of :meth:`.town.TownConfig.kitti` with moving
vehicles and pedestrians (:mod:`.actors`) seen through KITTI-like sensor effects
(:mod:`.effects`); ``raw`` is the same without motion compensation; ``clean`` is the plain
town without actors through an ideal sensor (for unit tests). The town is built lazily, once
per process, town seed and path, and cached; frames are not cached.
"""

from __future__ import annotations

import logging
import os
import threading
from collections import OrderedDict
from collections.abc import Iterator

import numpy as np

from gr_graph.datasets.base import LidarFrame, check_index
from gr_graph.datasets.synthetic.actors import (
    Actors,
    ActorsConfig,
    town_obstacles,
)
from gr_graph.datasets.synthetic.path import SensorPath, route_path, trajectory_path
from gr_graph.datasets.synthetic.effects import (PRESETS, SensorEffects, draw_laser_calibration,
                                                 preset as preset_effects, sweep_motion)
from gr_graph.datasets.synthetic.sensor import ACTOR_ALBEDO, BeamModel, NoiseModel, render_frame
from gr_graph.datasets.synthetic.town import Town, TownConfig, build_town
from gr_graph.sensors import DEFAULT_SENSOR, SensorConfig

log = logging.getLogger(__name__)

DEFAULT_PRESET = "kitti"
"""The preset of :class:`SyntheticSequence` when none is given: the KITTI-like world (sensor
effects and world effects, see :func:`preset_world`). Unit tests that need an ideal world ask
for ``clean`` explicitly."""

WORLDS = ("clean", "residential", "kitti")
"""The worlds: ``clean`` (``TownConfig()``, no moving actors), ``residential``
(``TownConfig.residential()``, every world effect at its first amounts, and ``ActorsConfig()``)
and ``kitti`` (:data:`KITTI_TOWN` and ``ActorsConfig()``, the world of the ``kitti`` preset)."""

KITTI_TOWN = TownConfig.kitti()
"""The town of the ``kitti`` and ``raw`` presets: every world effect on, at the amounts of
:meth:`TownConfig.kitti` (see it for the parameters and where they come from)."""

_FROM_WORLD = object()
"""Sentinel: take the moving actors from the world."""


def preset_world(preset: str) -> str:
    """The world of preset ``preset``: ``clean`` for ``clean``, ``kitti`` for ``kitti``/``raw``.

    A preset is the whole KITTI-like world: the sensor effects of :func:`.effects.preset` and
    this world (town effects and moving actors).
    """
    if preset not in PRESETS:
        raise ValueError(f"unknown synthetic preset {preset!r}; choose from {PRESETS}")
    return "clean" if preset == "clean" else "kitti"


def world_parts(world: str) -> tuple[TownConfig, ActorsConfig | None]:
    """The town configuration and the actors of world ``world`` (one of :data:`WORLDS`)."""
    if world == "clean":
        return TownConfig(), None
    if world == "residential":
        return TownConfig.residential(), ActorsConfig()
    if world == "kitti":
        return KITTI_TOWN, ActorsConfig()
    raise ValueError(f"unknown synthetic world {world!r}; choose from {WORLDS}")

_CACHE: "OrderedDict[tuple, tuple[Town, object]]" = OrderedDict()
_CACHE_SIZE = 2
_LOCK = threading.Lock()


def _scene_key(town_seed: int, path: SensorPath, town_config: TownConfig | None) -> tuple:
    """The cache key of the town of ``town_seed`` around ``path``."""
    return (int(town_seed), path.key(), town_config or TownConfig())


def get_town_and_scene(town_seed: int, path: SensorPath,
                       town_config: TownConfig | None = None) -> tuple[Town, object]:
    """The town of ``town_seed`` around ``path`` and its RaycastingScene (cached, built once)."""
    town_config = town_config or TownConfig()
    key = _scene_key(town_seed, path, town_config)
    with _LOCK:
        if key in _CACHE:
            _CACHE.move_to_end(key)
            return _CACHE[key]
        import open3d as o3d

        town = build_town(path.T_w_velo[:, :3, 3], seed=town_seed, config=town_config)
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(town.vertices), o3d.core.Tensor(town.triangles))
        _CACHE[key] = (town, scene)
        while len(_CACHE) > _CACHE_SIZE:
            _CACHE.popitem(last=False)
        return town, scene


def clear_scene_cache() -> None:
    """Forget every cached town/scene (the next frame rebuilds it)."""
    with _LOCK:
        _CACHE.clear()


class SyntheticSequence:
    """A generated route rendered through a procedural town (LidarSequence protocol).

    Parameters
    ----------
    seed : int
        Seeds the per-frame noise (from ``(seed, frame index)``) and, unless ``town_seed``
        is given, the town. Same seeds -> bit-identical frames.
    n_rings : int, optional
        Rings rendered; None (default): all the sensor's beams. For a 64-beam sensor also 32 or
        16 (any divisor of 64): every ``64 // n_rings``-th beam; a lower-ring render equals those
        rings of the 64-ring render exactly.
    max_range : float, optional
        Returns beyond this range (m) are dropped (at most ``ground_extent - 5`` = 130 m);
        None: the sensor's (HDL-64E and OS1-64 120 m, VLP-16 100 m).
    n_azimuth : int, optional
        Azimuth steps per revolution; None: the sensor's (2,000, 1,800, 1,024).
    range_sigma, dropout, min_range : float
        See :class:`~gr_graph.datasets.synthetic.sensor.NoiseModel`.
    town_seed : int, optional
        Seed of the town layout (default: ``seed``).
    nthreads : int
        Ray-casting threads (0 = open3d's default, all cores).
    route_seed : int
        Seed of the generated route (:func:`~gr_graph.datasets.synthetic.route.generate_route`);
        independent of ``seed``.
    trajectory : path, optional
        Render along this trajectory instead of the generated route: a KITTI or TUM pose
        file or a KITTI root (see :func:`~gr_graph.datasets.synthetic.path.trajectory_path`).
    trajectory_seq : str
        The sequence whose poses are used when ``trajectory`` is a KITTI root.
    preset : str
        The world and its sensor: ``clean`` (the plain town without moving actors, an ideal
        sensor with constant 2 cm range noise: for unit tests), ``kitti`` (the residential
        world of :data:`KITTI_TOWN` with moving vehicles and pedestrians, and the sensor
        effects of :mod:`.effects`: calibration errors, range noise growing with range and
        incidence, mixed pixels, rough surfaces, the residual motion distortion of KITTI's
        GPS/IMU compensation) or ``raw`` (the same with the full motion distortion and
        per-point ``time``). Default :data:`DEFAULT_PRESET`.
    effects : SensorEffects, optional
        Explicit sensor effects, overriding those of ``preset`` (e.g. one effect alone); the
        world still follows ``preset`` (or ``world``).
    world : str, optional
        ``clean``, ``residential`` or ``kitti`` (:data:`WORLDS`), overriding the world of
        ``preset`` (:func:`preset_world`).
    town_config : TownConfig, optional
        The town's layout and world effects, overriding the world's (``TownConfig()``: every
        effect off; ``TownConfig.residential()``: every world effect on).
    actors : ActorsConfig or object, optional
        Moving vehicles and pedestrians, overriding the world's: an
        :class:`~gr_graph.datasets.synthetic.actors.ActorsConfig` (built on first use, seeded by
        the town seed) or any object with ``cast(origins, directions, times)``; None = none.
    sensor : str
        The beam model, a catalogue name of :data:`gr_graph.sensors.SENSOR_MODELS`: ``hdl64e``
        (default), ``vlp16`` or ``os1-64``. The sweep lasts the effects' ``sweep_seconds`` (0.1 s:
        10 Hz, the route's rate and every model's catalogue rate).

    Attributes
    ----------
    path : SensorPath
        The sensor path (``path.route``: the generated route with its revisits and stops,
        None for a given trajectory).
    motion_compensated : bool
        False for the ``raw`` motion distortion (the scans need deskewing), else True.
    scan_period : float
        Sweep duration (s).
    sensor : gr_graph.sensors.SensorConfig
        The sensor's description (rings in the data; per-point times with the ``raw`` preset).
    """

    def __init__(self, seed: int = 0, n_rings: int | None = None, max_range: float | None = None,
                 n_azimuth: int | None = None, range_sigma: float = 0.02, dropout: float = 0.02,
                 min_range: float = 1.0, town_seed: int | None = None, nthreads: int = 0,
                 route_seed: int = 0, trajectory: str | os.PathLike[str] | None = None,
                 trajectory_seq: str = "00", preset: str | None = None,
                 effects: SensorEffects | None = None, town_config: TownConfig | None = None,
                 actors=_FROM_WORLD, world: str | None = None, sensor: str = DEFAULT_SENSOR):
        self.seed = int(seed)
        self.town_seed = self.seed if town_seed is None else int(town_seed)
        self.route_seed = int(route_seed)
        if self.seed < 0 or self.town_seed < 0 or self.route_seed < 0:
            raise ValueError(f"seeds must be >= 0, got seed={seed}, town_seed={town_seed}, "
                             f"route_seed={route_seed}")
        self.beams = BeamModel(n_rings=None if n_rings is None else int(n_rings),
                               n_azimuth=None if n_azimuth is None else int(n_azimuth), sensor=sensor)
        model = self.beams.model
        max_range = model.max_range if max_range is None else float(max_range)
        limit = TownConfig().ground_extent - 5.0
        if not 0 < max_range <= limit:
            raise ValueError(f"max_range must be in (0, {limit}] m (the town's ground extends "
                             f"{limit + 5:.0f} m from the path), got {max_range}")
        self.noise = NoiseModel(range_sigma=range_sigma, dropout=dropout, max_range=max_range,
                                min_range=min_range)
        self.nthreads = int(nthreads)
        self.preset = DEFAULT_PRESET if preset is None else str(preset)
        if self.preset not in PRESETS:
            raise ValueError(f"unknown synthetic preset {preset!r}; choose from {PRESETS}")
        self.effects = preset_effects(self.preset) if effects is None else effects
        if effects is not None:
            self.preset = "custom"
        self.laser_calib = draw_laser_calibration(self.effects.calibration, self.seed, n_beams=model.n_beams)
        self.world = preset_world(DEFAULT_PRESET if preset is None else str(preset)) if world is None else world
        world_town, world_actors = world_parts(self.world)
        self.town_config = world_town if town_config is None else town_config
        if actors is _FROM_WORLD:
            actors = world_actors
        self.actors_config = actors if isinstance(actors, ActorsConfig) else None
        self._actors = None if isinstance(actors, ActorsConfig) else actors
        self.motion_compensated = self.effects.motion.mode != "raw"
        self.scan_period = float(self.effects.motion.sweep_seconds)
        self._material_albedo: np.ndarray | None = None
        self.trajectory = None if trajectory is None else str(trajectory)
        self.path = (route_path(self.route_seed) if trajectory is None
                     else trajectory_path(trajectory, trajectory_seq))
        self.name = "synthetic-00" if model.name == DEFAULT_SENSOR else f"synthetic-00-{model.name}"
        self.sensor = SensorConfig(model=model.name, has_ring=True, has_time=not self.motion_compensated,
                                   scan_period=self.scan_period)
        self.timestamps = self.path.times.copy()
        self.T_cam_velo = self.path.T_cam_velo.copy()
        self.gt_poses = self.path.T_w_velo.copy()

    @property
    def n_rings(self) -> int:
        return self.beams.n_rings

    def __getstate__(self) -> dict:
        """State for pickling (the render process of :mod:`.render_process`): moving actors built
        from ``actors_config`` and the actors' albedo table are left out and rebuilt on first use
        (they hold ray-casting scenes); actors given as an object are kept. The town is never in
        the state (it lives in the module's cache)."""
        state = self.__dict__.copy()
        if self.actors_config is not None:
            state["_actors"] = None
        state["_material_albedo"] = None
        return state

    def release_cache(self) -> bool:
        """Drop this sequence's town and ray-casting scene from the cache (about 2 GB on the
        default route), e.g. once a SLAM round has read every frame. The next frame read
        rebuilds them, identical (they are seeded). Returns whether anything was dropped."""
        key = _scene_key(self.town_seed, self.path, self.town_config)
        with _LOCK:
            return _CACHE.pop(key, None) is not None

    @property
    def town(self) -> Town:
        """The (cached) procedural town; built on first use."""
        return get_town_and_scene(self.town_seed, self.path, self.town_config)[0]

    @property
    def actors(self) -> Actors | None:
        """The moving actors (None without ``actors``); built on first use."""
        if self.actors_config is not None and self._actors is None:
            self._actors = Actors(self.path.times, self.path.T_w_velo[:, :3, 3], seed=self.town_seed,
                                  config=self.actors_config, ground=self.town.ground,
                                  sensor_height=self.town_config.sensor_height,
                                  obstacles=town_obstacles(self.town.footprints))
        return self._actors

    def __len__(self) -> int:
        return len(self.gt_poses)

    def __repr__(self) -> str:
        where = (f"route_seed={self.route_seed}" if self.trajectory is None
                 else f"trajectory={self.trajectory!r}")
        return (f"SyntheticSequence(seed={self.seed}, town_seed={self.town_seed}, {where}, "
                f"sensor={self.beams.sensor!r}, n_rings={self.n_rings}, max_range={self.noise.max_range}, "
                f"n_azimuth={self.beams.n_azimuth}, preset={self.preset!r}, world={self.world!r}, "
                f"effects={self.effects.describe()!r}"
                + (f", town_config={self.town_config}" if self.town_config != world_parts(self.world)[0] else "")
                + (f", actors={self.actors_config}" if self.actors_config != world_parts(self.world)[1] else "")
                + ")")

    def frame_rng(self, index: int) -> np.random.Generator:
        """The generator of frame ``index``'s noise: seeded by ``(seed, index)`` only."""
        return np.random.default_rng([self.seed, int(index), 0x5CA9])

    def __getitem__(self, index: int) -> LidarFrame:
        i = check_index(index, len(self), self.name)
        town, scene = get_town_and_scene(self.town_seed, self.path, self.town_config)
        if self.actors is not None and self._material_albedo is None:
            count = np.bincount(town.material, minlength=256)
            total = np.bincount(town.material, weights=town.albedo, minlength=256)
            mean_albedo = np.where(count > 0, total / np.maximum(count, 1), ACTOR_ALBEDO)
            self._material_albedo = mean_albedo.astype(np.float32)

        def sweep(phase: float, rng: np.random.Generator):
            return sweep_motion(self.effects.motion, self.timestamps, self.gt_poses, i, phase,
                                self.beams.n_azimuth, rng)

        points, intensity, ring, time = render_frame(
            scene, town.albedo, town.material, self.gt_poses[i], self.beams, self.noise,
            self.frame_rng(i), effects=self.effects, laser_calib=self.laser_calib, sweep=sweep,
            actors=self.actors, timestamp=float(self.timestamps[i]),
            material_albedo=self._material_albedo, roughness_seed=self.town_seed, nthreads=self.nthreads)
        return LidarFrame(index=i, timestamp=float(self.timestamps[i]), points=points,
                          intensity=intensity, ring=ring, n_rings=self.n_rings, time=time)

    def __iter__(self) -> Iterator[LidarFrame]:
        for i in range(len(self)):
            yield self[i]
