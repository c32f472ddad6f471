"""World effects of the synthetic town (porous vegetation, details) and its moving actors."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from gr_graph.datasets.synthetic.actors import (
    KIND_LEAD,
    KIND_ONCOMING,
    KIND_PEDESTRIAN,
    Actors,
    ActorsConfig,
    SceneWithActors,
)
from gr_graph.datasets.synthetic.meshes import MATERIAL, MeshBuilder, blob
from gr_graph.datasets.synthetic.town import TownConfig, _porous_crown, build_town

o3d = pytest.importorskip("open3d")

# sha1 of (vertices, triangles, albedo, material) of build_town(_small_path(), seed=3), measured
# with the town code before the world effects were added (commit 577d39b)
CLEAN_TOWN_SHA1 = "5f37fb69c5743e1beb10338a3d0ecedc36a476b2"


def _small_path() -> np.ndarray:
    t = np.linspace(0, 1, 200)
    return np.c_[120 * t, 30 * np.sin(3 * t), 0.5 * t + 1.73]


def _digest(town) -> str:
    h = hashlib.sha1()
    for a in (town.vertices, town.triangles, town.albedo, town.material):
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def test_effects_off_is_the_clean_town_bit_identical():
    assert not TownConfig().any_effect and TownConfig.residential().any_effect
    assert _digest(build_town(_small_path(), seed=3)) == CLEAN_TOWN_SHA1


def test_effects_keep_the_layout_and_add_geometry():
    P = _small_path()
    clean = build_town(P, seed=3)
    # the two effects that move objects (houses, left parked cars) off: everything else only adds
    cfg = TownConfig.residential(detached_houses=False, sidewalk_parking=False)
    rich = build_town(P, seed=3, config=cfg)
    for kind in ("building", "car", "tree", "bush"):  # the same objects in the same places (gardens added)
        n = len(clean.footprints[kind])
        np.testing.assert_array_equal(clean.footprints[kind], rich.footprints[kind][:n])
    assert len(rich.footprints["wall"]) > len(clean.footprints["wall"])  # fences and hedges
    assert len(rich.triangles) > 1.5 * len(clean.triangles)
    assert _digest(build_town(P, seed=3, config=cfg)) == _digest(rich)


def _scene(mb: MeshBuilder):
    v, t, _, _ = mb.build()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(t))
    return scene


def _parallel_rays(n: int, radius: float, rng: np.random.Generator) -> np.ndarray:
    """Rays along +x from x = -10, within 0.3 ``radius`` of the x axis (through a crown's centre)."""
    yz = rng.uniform(-radius, radius, (n, 2))
    yz = yz[np.hypot(yz[:, 0], yz[:, 1]) < 0.3 * radius]  # near the crown's centre line
    rays = np.zeros((len(yz), 6), np.float32)
    rays[:, 0], rays[:, 1:3], rays[:, 3] = -10.0, yz, 1.0
    return rays


def test_porous_crown_returns_come_from_inside_and_some_pass_through():
    R, lad = 2.0, 1.0
    mb = MeshBuilder()
    _porous_crown(mb, np.random.default_rng(1), np.zeros(3), np.full(3, R), lad, 0.25, 0.2)
    rays = _parallel_rays(20000, R, np.random.default_rng(2))
    t = _scene(mb).cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    hit = np.isfinite(t)
    depth = np.linalg.norm(rays[hit, :3] + t[hit, None] * rays[hit, 3:], axis=1)  # from the centre
    # Beer-Lambert with G = 0.5: transmission along a chord of length L is exp(-G LAD L); the
    # chords here are 1.9-2 R long, so about exp(-2) = 0.135 passes through
    transmitted = 1.0 - hit.mean()
    assert 0.07 < transmitted < 0.25, transmitted
    # returns from deep inside the crown, not only from its hull
    assert (depth < 0.6 * R).mean() > 0.15
    assert (depth < 0.3 * R).any()
    # the closed blob of the clean town (lobes reach in to ~0.7 R): no return deeper than 0.6 R
    # the closed blob of the clean town: every ray near the centre line returns from the hull
    mb2 = MeshBuilder()
    mb2.add(blob(np.zeros(3), np.full(3, R), np.random.default_rng(1), subdivisions=2, roughness=0.3), 0.2,
            MATERIAL["foliage"])
    t2 = _scene(mb2).cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    assert np.isfinite(t2).all()
    depth2 = np.linalg.norm(rays[:, :3] + t2[:, None] * rays[:, 3:], axis=1)
    assert (depth2 > 0.6 * R).all()


def _test_path() -> tuple[np.ndarray, np.ndarray]:
    """10 Hz poses: 290 m east at 10 m/s with a 5 s stop, a U-turn of radius 6 m and back west
    12 m north of the first street."""
    a = np.linspace(-np.pi / 2, np.pi / 2, 40)
    line = np.concatenate([np.c_[np.arange(0, 290, 0.5), np.zeros(580)],
                           np.c_[290 + 6 * np.cos(a), 6 + 6 * np.sin(a)],
                           np.c_[np.arange(289.5, 0, -0.5), np.full(579, 12.0)]])
    seg = np.linalg.norm(np.diff(line, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    times = np.arange(0, s[-1] / 10.0 + 5.0, 0.1)
    stop_at, stop_len = 150.0, 5.0  # stand at s = 150 m for 5 s
    s_of_t = np.where(times < stop_at / 10, times * 10,
                      np.where(times < stop_at / 10 + stop_len, stop_at, (times - stop_len) * 10))
    s_of_t = np.minimum(s_of_t, s[-1])
    xy = np.c_[np.interp(s_of_t, s, line[:, 0]), np.interp(s_of_t, s, line[:, 1])]
    return times, np.c_[xy, np.full(len(xy), 1.73)]


@pytest.fixture(scope="module")
def actors() -> Actors:
    times, pos = _test_path()
    return Actors(times, pos, seed=4, config=ActorsConfig(n_lead=6, n_oncoming=10, n_pedestrians=20))


def test_actors_are_deterministic_per_seed():
    times, pos = _test_path()
    cfg = ActorsConfig(n_lead=3, n_oncoming=3, n_pedestrians=5)
    a, b, c = Actors(times, pos, seed=1, config=cfg), Actors(times, pos, seed=1, config=cfg), \
        Actors(times, pos, seed=2, config=cfg)
    assert len(a) == len(b) and len(a) > 0
    for x, y in zip(a.actors, b.actors):
        np.testing.assert_array_equal(x.s_table, y.s_table)
        assert (x.t0, x.offset, x.template) == (y.t0, y.offset, y.template)
    assert any(len(x.s_table) != len(y.s_table) or x.t0 != y.t0 for x, y in zip(a.actors, c.actors))


def test_actors_move_consistently(actors):
    kinds = {a.kind for a in actors.actors}
    assert kinds == {KIND_LEAD, KIND_ONCOMING, KIND_PEDESTRIAN}
    moved = 0
    for i, a in enumerate(actors.actors):
        t = actors._t_start[i] + np.linspace(0.2, actors._t_stop[i] - actors._t_start[i] - 0.3, 40)
        p0, p1 = actors.state(i, t)["position"], actors.state(i, t + 0.1)["position"]
        disp = np.linalg.norm(p1[:, :2] - p0[:, :2], axis=1)
        # mean speed over [t, t + 0.1] from the speeds reported at 20 instants inside it
        v = np.mean([actors.state(i, t + dt)["speed"] for dt in np.arange(0.0025, 0.1, 0.005)], axis=0)
        np.testing.assert_allclose(disp, 0.1 * v, rtol=0.03, atol=0.01)
        moved += (disp > 0.05).any()
        if a.kind == KIND_PEDESTRIAN:
            assert v.max() <= 1.5 * 1.3  # walking speed (x the stretch of an outer sidewalk in a turn)
    assert moved >= len(actors.actors) // 2


def _inside_ego(actors: Actors, pts: np.ndarray, t: np.ndarray) -> np.ndarray:
    front, rear, hw = actors.config.ego_box
    p, yaw = actors.ego_pose(t)
    rel = pts - p[:, None, :2]
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    x, y = c * rel[..., 0] + s * rel[..., 1], -s * rel[..., 0] + c * rel[..., 1]
    return (x <= front) & (x >= rear) & (np.abs(y) <= hw)


def test_actors_never_touch_the_ego_vehicle(actors):
    dt = 0.02  # finer than the checks inside Actors
    for i, a in enumerate(actors.actors):
        t = np.arange(actors._t_start[i], actors._t_stop[i], dt)
        st = actors.state(i, t)
        hl, hw = a.half_size
        u, v = np.meshgrid(np.linspace(-hl, hl, 9), np.linspace(-hw, hw, 5), indexing="ij")
        c, s = np.cos(st["yaw"])[:, None], np.sin(st["yaw"])[:, None]
        pts = np.stack([st["position"][:, :1] + c * u.ravel() - s * v.ravel(),
                        st["position"][:, 1:2] + s * u.ravel() + c * v.ravel()], axis=-1)
        assert not _inside_ego(actors, pts, t).any(), (i, a.kind)


def _brute_force(orig: np.ndarray, d: np.ndarray, v: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Möller-Trumbore of one ray against every triangle: nearest t or inf."""
    a, b, c = v[tris[:, 0]], v[tris[:, 1]], v[tris[:, 2]]
    e1, e2 = b - a, c - a
    p = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, p)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = orig - a
    u = np.einsum("ij,ij->i", s, p) * inv
    q = np.cross(s, e1)
    w = (q @ d) * inv
    t = np.einsum("ij,ij->i", e2, q) * inv
    hit = ok & (u >= 0) & (w >= 0) & (u + w <= 1) & (t > 0)
    return float(t[hit].min()) if hit.any() else np.inf


def test_cast_agrees_with_brute_force(actors):
    """Rays aimed near actors (and some at a time another actor is in the way) against
    Möller-Trumbore over every triangle of every actor alive at the ray's time."""
    rng = np.random.default_rng(0)
    n_rays = 15
    hits = checked = 0
    for i in rng.permutation(len(actors.actors))[:8]:
        t_ray = rng.uniform(actors._t_start[i] + 0.1, actors._t_stop[i] - 0.1, n_rays)
        st = actors.state(i, t_ray)
        target = st["position"] + np.c_[rng.normal(0, 0.6, (n_rays, 2)), rng.uniform(0.1, 1.6, n_rays)]
        ang = rng.uniform(0, 2 * np.pi, n_rays)
        origin = target + np.c_[8 * np.cos(ang), 8 * np.sin(ang), rng.uniform(0.0, 1.0, n_rays)]
        d = target - origin
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        th, normals, mat = actors.cast(origin.astype(np.float32), d.astype(np.float32), t_ray)
        o32, d32 = origin.astype(np.float32).astype(np.float64), d.astype(np.float32).astype(np.float64)
        for k in range(n_rays):
            ref = np.inf
            for j in actors.alive(t_ray[k], t_ray[k]):
                a = actors.actors[j]
                sj = actors.state(j, t_ray[k:k + 1])
                meshes = actors.pedestrian_meshes if a.kind == KIND_PEDESTRIAN else actors.vehicle_meshes
                c, s = np.cos(sj["yaw"][0]), np.sin(sj["yaw"][0])
                R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
                v_world = meshes[a.template][0].astype(np.float64) @ R.T + sj["position"][0]
                ref = min(ref, _brute_force(o32[k], d32[k], v_world, meshes[a.template][1]))
            assert np.isfinite(th[k]) == np.isfinite(ref), (i, k, th[k], ref)
            if np.isfinite(ref):
                assert abs(th[k] - ref) < 2e-3, (th[k], ref)
                assert abs(np.linalg.norm(normals[k]) - 1) < 1e-4
                assert mat[k] in (MATERIAL["car"], MATERIAL["glass"], MATERIAL["person"])
                hits += 1
            checked += 1
    assert hits > 0.3 * checked


def test_scene_with_actors_keeps_the_nearer_hit(actors):
    # a static wall 30 m east of the sensor; rays cast at an actor in front of it
    i = next(k for k, a in enumerate(actors.actors) if a.kind == KIND_LEAD)
    t_frame = 0.5 * (actors._t_start[i] + actors._t_stop[i])
    ego, yaw = actors.ego_pose(np.array([t_frame]))
    st = actors.state(i, np.array([t_frame]))
    T = np.eye(4)
    T[:3, :3] = [[np.cos(yaw[0]), -np.sin(yaw[0]), 0], [np.sin(yaw[0]), np.cos(yaw[0]), 0], [0, 0, 1]]
    T[:3, 3] = ego[0]
    far = st["position"][0] + 30.0 * (st["position"][0] - ego[0]) / np.linalg.norm(st["position"][0] - ego[0])
    mb = MeshBuilder()
    from gr_graph.datasets.synthetic.meshes import box
    mb.add(box(far[0], far[1], yaw[0] + np.pi / 2, 80.0, 0.5, -5.0, 20.0), 0.5, MATERIAL["building"])
    _, _, alb, mat = mb.build()
    static = _scene(mb)
    wrap = SceneWithActors(static, alb, mat, actors, T, t_frame)
    # aimed at points above the actor's centre from 0.2 m to 3 m (over its roof: the wall)
    targets = st["position"][0] + np.c_[np.zeros((40, 2)), np.linspace(0.2, 3.0, 40)]
    dirs = targets - ego[0]
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    rays = np.c_[np.repeat(ego, 40, 0), dirs].astype(np.float32)
    out = wrap.cast_rays(o3d.core.Tensor(rays))
    t_out, prim = out["t_hit"].numpy(), out["primitive_ids"].numpy()
    t_static = static.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    th, _, _ = actors.cast(rays[:, :3], rays[:, 3:], wrap.ray_times(rays[:, 3:]))
    np.testing.assert_array_equal(t_out, np.minimum(t_static, th))
    on_actor = th < t_static
    assert on_actor.any() and (~on_actor).any()
    assert set(wrap.material[prim[on_actor]]) <= {MATERIAL["car"], MATERIAL["glass"]}
    assert (prim[~on_actor & np.isfinite(t_out)] < len(alb)).all()
    # its rays' times are the renderer's: clockwise from behind, forward at mid-sweep (it cast forward
    # rays 50 ms early); an independent reference from the azimuth of the sensor-frame directions
    from gr_graph.deskew import times_from_azimuth

    sensor_dirs = rays[:, 3:].astype(np.float64) @ T[:3, :3]
    expected = t_frame + (times_from_azimuth(sensor_dirs) - 0.5) * 0.1
    np.testing.assert_allclose(wrap.ray_times(rays[:, 3:]), expected, atol=1e-6)
    forward = np.array([[np.cos(yaw[0]), np.sin(yaw[0]), 0.0]], np.float32)
    assert wrap.ray_times(forward)[0] == pytest.approx(t_frame, abs=1e-6)


def test_actors_avoid_obstacles():
    times, pos = _test_path()
    # parked cars (3 circles each) on the oncoming lane and trunks on the sidewalks every 25 m
    xs = np.arange(10.0, 280.0, 25.0)
    obstacles = np.concatenate([np.c_[xs + dx, np.full(len(xs), 3.3), np.full(len(xs), 0.9)] for dx in (-1.3, 0, 1.3)]
                               + [np.c_[xs + 12.0, np.full(len(xs), y), np.full(len(xs), 0.35)] for y in (-6.0, 6.0)])
    cfg = ActorsConfig(n_lead=4, n_oncoming=10, n_pedestrians=30)
    free = Actors(times, pos, seed=5, config=cfg)
    act = Actors(times, pos, seed=5, config=cfg, obstacles=obstacles)
    assert act.n_rejected > free.n_rejected or len(act) < len(free) or any(
        x.t0 != y.t0 for x, y in zip(act.actors, free.actors))
    assert len(act) > 0
    for i, a in enumerate(act.actors):
        t = np.arange(act._t_start[i], act._t_stop[i], 0.05)
        st = act.state(i, t)
        hl, hw = a.half_size
        u, v = np.meshgrid(np.linspace(-hl, hl, 9), np.linspace(-hw, hw, 5), indexing="ij")
        c, s = np.cos(st["yaw"])[:, None], np.sin(st["yaw"])[:, None]
        px = st["position"][:, :1] + c * u.ravel() - s * v.ravel()
        py = st["position"][:, 1:2] + s * u.ravel() + c * v.ravel()
        d = np.hypot(px[..., None] - obstacles[:, 0], py[..., None] - obstacles[:, 1])
        assert (d >= obstacles[:, 2]).all(), (i, a.kind)


def test_window_recesses_put_the_glass_behind_the_wall_surface():
    """Rays at a facade hit the wall panels ``recess`` in front of the block's face, or the glass
    in the face itself; glass covers a window-to-wall share of the facade in 15-35 %."""
    from gr_graph.datasets.synthetic.town import _window_facades

    mb = MeshBuilder()
    recess, depth = 0.15, 10.0
    # a 20 m x 10 m block of three storeys centred at the origin, its long faces at y = +-5
    _window_facades(mb, np.random.default_rng(0), np.zeros(2), 0.0, 20.0, depth, 0.0, -0.5, 9.5, 0.5, recess)
    v, t, alb, mat = mb.build()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(t))
    # a grid of rays towards -y onto the face at y = +5, from y = 20
    xs, zs = np.meshgrid(np.linspace(-9.0, 9.0, 181), np.linspace(0.1, 9.0, 90))
    rays = np.zeros((xs.size, 6), np.float32)
    rays[:, 0], rays[:, 1], rays[:, 2], rays[:, 4] = xs.ravel(), 20.0, zs.ravel(), -1.0
    hit = scene.cast_rays(o3d.core.Tensor(rays))
    t_hit = hit["t_hit"].numpy()
    assert np.isfinite(t_hit).all()
    y = 20.0 - t_hit
    glass = mat[hit["primitive_ids"].numpy()] == MATERIAL["glass"]
    np.testing.assert_allclose(y[~glass], 0.5 * depth + recess, atol=1e-4)  # the wall surface
    np.testing.assert_allclose(y[glass], 0.5 * depth + 0.02, atol=1e-4)  # the pane, in the block's face
    assert 0.15 <= glass.mean() <= 0.35
    assert not TownConfig(window_recesses=True) == TownConfig() and TownConfig(window_recesses=True).any_effect


def test_kitti_world_keeps_the_residential_effects_and_adds_its_composition():
    from gr_graph.datasets.synthetic.sequence import KITTI_TOWN, SyntheticSequence, preset_world

    assert KITTI_TOWN == TownConfig.kitti()
    res = TownConfig.residential()
    for flag in ("porous_vegetation", "facade_details", "fences_hedges", "street_signs", "curved_cars",
                 "sidewalk_parking", "detached_houses", "garden_vegetation"):
        assert getattr(KITTI_TOWN, flag) and getattr(res, flag)
    assert KITTI_TOWN.window_recesses and not KITTI_TOWN.low_walls
    assert preset_world("clean") == "clean" and preset_world("kitti") == preset_world("raw") == "kitti"
    clean, kitti = SyntheticSequence(preset="clean"), SyntheticSequence(preset="kitti")
    assert clean.town_config == TownConfig() and clean.actors_config is None
    assert kitti.town_config == KITTI_TOWN and kitti.actors_config == ActorsConfig()
    # explicit parts override the preset's world; the sensor effects stay the preset's
    assert SyntheticSequence(world="residential").town_config == res
    mixed = SyntheticSequence(preset="kitti", world="clean")
    assert mixed.town_config == TownConfig() and mixed.actors_config is None and not mixed.effects.is_clean
    assert SyntheticSequence(preset="kitti", actors=None).actors_config is None
    with pytest.raises(ValueError, match="world"):
        SyntheticSequence(world="urban")
