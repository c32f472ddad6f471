"""Tests of the synthetic sensor effects (gr_graph.datasets.synthetic.effects) and presets.

Each effect is checked on a small hand-made scene against a closed form (ground-plane
geometry, the range-noise model, a wall seen while moving, deskewed with the true motion),
plus: ``clean`` renders bit-identical to the renderer before the effects existed, presets
are deterministic per seed and selectable from the sequence and the exporter.
"""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest

from factors.se3 import exp_se3_batch
from gr_graph.datasets.synthetic import SyntheticSequence
from gr_graph.datasets.synthetic.__main__ import main as cli_main
from gr_graph.datasets.synthetic.effects import (CalibrationErrors, MixedPixels, MotionDistortion, RangeNoise,
                                                 Roughness, SensorEffects, draw_laser_calibration,
                                                 interpolate_poses, preset, sweep_motion)
from gr_graph.datasets.synthetic.meshes import MATERIAL, MeshBuilder, box
from gr_graph.datasets.synthetic.sensor import BeamModel, NoiseModel, hdl64_elevations_deg, render_frame, render_scan
from loader_support import assert_same_frame

H = 1.73


def _scene(meshes: list[tuple[tuple[np.ndarray, np.ndarray], str]]):
    import open3d as o3d

    mb = MeshBuilder()
    for mesh, mat in meshes:
        mb.add(mesh, 0.5, MATERIAL[mat])
    v, t, albedo, material = mb.build()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(t))
    return scene, albedo, material


def _quad(x0, x1, y0, y1, z):
    v = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], dtype=float)
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def _wall(x, y0, y1, z0, z1):
    v = np.array([[x, y0, z0], [x, y1, z0], [x, y1, z1], [x, y0, z1]], dtype=float)
    return v, np.array([[0, 1, 2], [0, 2, 3]])


NO_NOISE = NoiseModel(range_sigma=0.0, dropout=0.0, grazing_cos=1e-6, max_range=200.0)


def _digest(f) -> str:
    h = hashlib.sha1()
    for a in (f.points, f.intensity, f.ring):
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


#: Digests of frames 0 and 1500 of the render before sensor effects existed (commit 577d39b, open3d/numpy
#: of the project's environment), per processor: open3d's ray casting (Embree) picks its kernels by
#: instruction set, so the last bits of a hit differ between machines (deterministic on each).
CLEAN_RENDER_DIGESTS = {
    ("41b147dd0709e06a3c2be6413512465f2b3fee7a", "0826430dc1710a2186a4edc76063894764f7beff"): "AMD EPYC, AVX2",
    ("6670b85760f14a4d8bd0ec1d51a001dc0bd435bf", "b52a7bd8d5b55de133722f3920549c9ec162d98a"): "Intel Xeon, AVX-512",
}


def test_clean_preset_is_bit_identical_to_the_renderer_before_the_effects():
    """The clean preset must not change a bit of the render before the effects (on the processors of
    :data:`CLEAN_RENDER_DIGESTS`; on another one, add its digests after checking them at 577d39b)."""
    seq = SyntheticSequence(seed=0, n_rings=16, nthreads=1, preset="clean")
    assert seq.preset == "clean" and seq.effects.is_clean
    digests = (_digest(seq[0]), _digest(seq[1500]))
    assert digests in CLEAN_RENDER_DIGESTS, f"{digests}: not a digest of the render at 577d39b on a known processor"
    assert seq[0].time is None


def test_effects_presets_are_deterministic_and_ring_consistent():
    # the sensor effects on the plain town (the kitti world is covered by the seed-0 tests below)
    a = SyntheticSequence(seed=3, n_rings=16, nthreads=1, preset="kitti", world="clean")[700]
    b = SyntheticSequence(seed=3, n_rings=16, nthreads=1, preset="kitti", world="clean")[700]
    c = SyntheticSequence(seed=4, town_seed=3, n_rings=16, nthreads=1, preset="kitti", world="clean")[700]
    assert _digest(a) == _digest(b) and _digest(a) != _digest(c)
    clean = SyntheticSequence(seed=3, n_rings=16, nthreads=1, preset="clean")[700]
    assert _digest(a) != _digest(clean)
    # the 16-ring render is exactly every 4th ring of the 64-ring render, effects included
    full = SyntheticSequence(seed=3, n_rings=64, nthreads=1, preset="raw", world="clean")[700]
    sub = SyntheticSequence(seed=3, n_rings=16, nthreads=1, preset="raw", world="clean")[700]
    keep = full.ring % 4 == 0
    np.testing.assert_array_equal(full.points[keep], sub.points)
    np.testing.assert_array_equal(full.ring[keep] // 4, sub.ring)
    np.testing.assert_array_equal(full.time[keep], sub.time)


def test_presets_selectable_and_raw_carries_per_point_times():
    raw = SyntheticSequence(seed=0, n_rings=16, nthreads=1, preset="raw")
    kitti = SyntheticSequence(seed=0, n_rings=16, nthreads=1, preset="kitti")
    assert not raw.motion_compensated and kitti.motion_compensated and raw.scan_period == 0.1
    assert raw.world == kitti.world == "kitti" and SyntheticSequence().preset == "kitti"
    f = raw[200]
    assert f.time is not None and f.time.min() >= 0 and f.time.max() <= 1
    # the sensor faces forward (+x) at mid-sweep and backwards at the start/end
    az = np.arctan2(f.points[:, 1], f.points[:, 0])
    fwd = np.abs(az) < 0.05
    back = np.abs(az) > np.pi - 0.05
    assert np.all(np.abs(f.time[fwd] - 0.5) < 0.02)
    assert np.all(np.minimum(f.time[back], 1 - f.time[back]) < 0.02)
    assert kitti[200].time is None
    sel = f.select(f.ring == 3)
    assert len(sel.time) == len(sel)
    with pytest.raises(ValueError, match="preset"):
        SyntheticSequence(preset="foggy")
    assert "kitti" in repr(kitti)


def test_exporter_writes_the_preset_and_raw_times(tmp_path):
    assert cli_main(["--out", str(tmp_path), "--frames", "10:12", "--channels", "16", "--preset", "raw",
                     "--threads", "1"]) == 0
    sdir = tmp_path / "sequences" / "00"
    meta = json.loads((sdir / "synthetic.json").read_text())
    assert meta["preset"] == "raw" and meta["motion_compensated"] is False
    pts = np.fromfile(sdir / "velodyne" / "000001.bin", dtype=np.float32).reshape(-1, 4)
    t = np.load(sdir / "times" / "000001.npy")
    ref = SyntheticSequence(seed=0, n_rings=16, preset="raw")[11]
    assert len(t) == len(pts) == len(ref)
    np.testing.assert_array_equal(t, ref.time.astype(np.float32))
    # read back: raw sweeps with their times (deskewed by default), not taken as motion-compensated
    from gr_graph.datasets.base import DatasetError
    from gr_graph.datasets.kitti import KittiSequence
    from gr_graph.datasets.registry import open_sequence

    back = KittiSequence(tmp_path, "00", n_rings=64)
    assert back.motion_compensated is False
    np.testing.assert_array_equal(back[1].time, ref.time.astype(np.float32).astype(np.float64))
    seq, _ = open_sequence(path=tmp_path)
    assert seq.motion_compensated is False and seq[0].time is not None
    from gr_graph.pipeline import data_fingerprint
    from gr_graph.sensors import SensorConfig

    said_no_time, _ = open_sequence(path=tmp_path, sensor=SensorConfig(has_time=False))
    assert said_no_time.motion_compensated is True and said_no_time[0].time is None  # sensor.has_time: false
    with_times = data_fingerprint(seq)["digest"]
    assert data_fingerprint(said_no_time)["digest"] != with_times  # the times are part of the data read
    (sdir / "times" / "000001.npy").unlink()  # times of some scans only: not used
    assert KittiSequence(tmp_path, "00").motion_compensated is True
    np.save(sdir / "times" / "000001.npy", t[:-3])  # not one a point: an error naming the file
    with pytest.raises(DatasetError, match=r"times/000001.npy: \d+ per-point times for the \d+ points of 000001.bin"):
        KittiSequence(tmp_path, "00")[1]
    # points without a return (exactly at the origin, or NaN) are dropped with their times
    pts0 = np.fromfile(sdir / "velodyne" / "000000.bin", dtype=np.float32).reshape(-1, 4)
    t0 = np.load(sdir / "times" / "000000.npy")
    pts0[[3, 9]] = [0.0, 0.0, 0.0, 0.5]
    pts0[4, 1] = np.nan
    pts0.tofile(sdir / "velodyne" / "000000.bin")
    f0 = KittiSequence(tmp_path, "00", n_rings=64)[0]
    keep = np.ones(len(pts0), bool)
    keep[[3, 4, 9]] = False
    assert f0.dropped_nonfinite == 3 and len(f0.time) == len(f0) == len(pts0) - 3
    np.testing.assert_array_equal(f0.time, t0[keep].astype(np.float64))


def test_calibration_errors_move_ring_elevations_by_the_drawn_offsets():
    """On a flat ground plane, a beam that truly points at e + d but is reported along e
    gives points whose range/height reveal d: z = r sin(e), r = H / sin(-(e + d))."""
    scene, albedo, material = _scene([(_quad(-300, 300, -300, 300, -H), "road")])
    cfg = CalibrationErrors(enabled=True, range_offset_sigma_m=0.0, range_scale_sigma=0.0)
    cal = draw_laser_calibration(cfg, seed=11)
    fx = SensorEffects(calibration=cfg)
    beams = BeamModel(n_rings=64, n_azimuth=360)
    out = render_frame(scene, albedo, material, np.eye(4), beams, NO_NOISE, np.random.default_rng(0),
                       effects=fx, laser_calib=cal)
    el_nom = np.radians(hdl64_elevations_deg())
    checked = 0
    for k in range(64):
        p = out.points[out.ring == k]
        if len(p) < 100 or np.linalg.norm(p, axis=1).max() > 150:
            continue
        r = np.linalg.norm(p, axis=1)
        np.testing.assert_allclose(p[:, 2] / r, np.sin(el_nom[k]), atol=1e-6)  # reported along nominal
        true_el = -np.arcsin(H / r)
        np.testing.assert_allclose(np.median(true_el - el_nom[k]), cal.elevation_rad[k], atol=2e-6)
        checked += 1
    assert checked > 30
    # the global vertical offset (0.22 deg) is in every laser's error
    assert abs(np.mean(cal.elevation_rad) - np.radians(0.22)) < np.radians(0.03)
    # range offset and scale: reported range = (1 + s) r + b
    cfg2 = CalibrationErrors(enabled=True, elevation_sigma_deg=0, azimuth_sigma_deg=0, vertical_offset_deg=0)
    cal2 = draw_laser_calibration(cfg2, seed=5)
    out2 = render_frame(scene, albedo, material, np.eye(4), beams, NO_NOISE, np.random.default_rng(0),
                        effects=SensorEffects(calibration=cfg2), laser_calib=cal2)
    for k in (40, 50, 63):
        r = np.linalg.norm(out2.points[out2.ring == k], axis=1)
        expect = (1 + cal2.range_scale[k]) * H / np.sin(-el_nom[k]) + cal2.range_offset_m[k]
        np.testing.assert_allclose(r, expect, rtol=1e-5)
    assert draw_laser_calibration(cfg, 11).elevation_rad.tolist() == cal.elevation_rad.tolist()


def _constant_twist_path(xi_per_s: np.ndarray, n: int = 5, dt: float = 0.1):
    """Poses ``Exp(t xi)`` (gtsam order ``[omega, v]``) every ``dt`` seconds."""
    times = np.arange(n) * dt
    poses = exp_se3_batch(times[:, None] * xi_per_s)
    return times, poses


def test_interpolated_sweep_poses_follow_a_constant_twist():
    xi = np.array([0.0, 0.0, 0.4, 10.0, 0.5, 0.0])
    times, poses = _constant_twist_path(xi)
    t = np.linspace(0.15, 0.25, 7)
    np.testing.assert_allclose(interpolate_poses(times, poses, t, 2), exp_se3_batch(t[:, None] * xi), atol=1e-9)
    # the end frames extrapolate their end segments (a sweep reaches half a frame past the path)
    for i, t in ((0, np.linspace(-0.05, 0.05, 5)), (len(times) - 1, np.linspace(0.35, 0.45, 5))):
        np.testing.assert_allclose(interpolate_poses(times, poses, t, i), exp_se3_batch(t[:, None] * xi), atol=1e-9)
    np.testing.assert_array_equal(interpolate_poses(times[:1], poses[:1], t, 0), np.repeat(poses[:1], len(t), axis=0))
    with pytest.raises(ValueError, match="strictly increase"):
        interpolate_poses(np.array([0.0, 0.1, 0.1, 0.3]), poses[:4], t, 2)


def test_motion_distortion_deskewed_with_the_true_motion_falls_back_on_the_wall():
    """A wall 12 m ahead, rendered while driving at 10 m/s and turning: the raw scan is
    distorted (up to v * 0.05 s = 0.5 m); moving every point with the true pose of its own
    time into the mid-sweep frame puts it back on the wall of the undistorted render."""
    xi = np.array([0.0, 0.0, 0.3, 10.0, 0.0, 0.0])  # 0.3 rad/s yaw, 10 m/s forward
    times, poses = _constant_twist_path(xi)
    i = 2
    wall_x = float(poses[i][0, 3] + 12.0)
    scene, albedo, material = _scene([(_wall(wall_x, -40, 40, -5, 10), "building")])
    beams = BeamModel(n_rings=16, n_azimuth=720)
    raw_fx = SensorEffects(motion=MotionDistortion(mode="raw"))

    def sweep(phase, rng, fx=raw_fx):
        return sweep_motion(fx.motion, times, poses, i, phase, beams.n_azimuth, rng)

    raw = render_frame(scene, albedo, material, poses[i], beams, NO_NOISE, np.random.default_rng(4),
                       effects=raw_fx, sweep=sweep, timestamp=times[i])
    still = render_frame(scene, albedo, material, poses[i], beams, NO_NOISE, np.random.default_rng(4))
    # the undistorted render lies on the wall x = wall_x in the world
    w_still = still.points @ poses[i][:3, :3].T + poses[i][:3, 3]
    np.testing.assert_allclose(w_still[:, 0], wall_x, atol=1e-3)
    # interpreted in the mid-sweep frame, the raw scan is off the wall
    w_raw = raw.points @ poses[i][:3, :3].T + poses[i][:3, 3]
    assert np.abs(w_raw[:, 0] - wall_x).max() > 0.05
    # deskew with the true motion: p_mid = T_mid^-1 T(t) p
    t_abs = times[i] + (raw.time - 0.5) * 0.1
    T_t = exp_se3_batch(t_abs[:, None] * xi)
    p_w = np.einsum("nij,nj->ni", T_t[:, :3, :3], raw.points) + T_t[:, :3, 3]
    np.testing.assert_allclose(p_w[:, 0], wall_x, atol=1e-3)
    # compensated with an exact velocity (no IMU error): the residual vanishes under a constant twist
    comp_fx = SensorEffects(motion=MotionDistortion(mode="compensated", velocity_sigma=0.0, rate_sigma_deg=0.0))
    comp = render_frame(scene, albedo, material, poses[i], beams, NO_NOISE, np.random.default_rng(4),
                        effects=comp_fx, sweep=lambda ph, rng: sweep(ph, rng, comp_fx), timestamp=times[i])
    assert comp.time is None
    w_comp = comp.points @ poses[i][:3, :3].T + poses[i][:3, 3]
    np.testing.assert_allclose(w_comp[:, 0], wall_x, atol=1e-3)
    # with the IMU's velocity error the residual is small but not zero
    kit_fx = SensorEffects(motion=MotionDistortion(mode="compensated", velocity_sigma=0.5, rate_sigma_deg=0.0))
    kit = render_frame(scene, albedo, material, poses[i], beams, NO_NOISE, np.random.default_rng(4),
                       effects=kit_fx, sweep=lambda ph, rng: sweep(ph, rng, kit_fx), timestamp=times[i])
    resid = np.abs(kit.points @ poses[i][:3, :3].T + poses[i][:3, 3] - [wall_x, 0, 0])[:, 0]
    assert 1e-3 < resid.max() < 0.5 * 0.05 * 4 + 1e-3


def _inside_sphere(radius: float):
    import open3d as o3d

    m = o3d.geometry.TriangleMesh.create_sphere(radius=radius, resolution=60)
    return np.asarray(m.vertices), np.asarray(m.triangles)


def test_range_noise_std_grows_with_range_as_modelled():
    rn = RangeNoise(enabled=True)
    fx = SensorEffects(range_noise=rn)
    beams = BeamModel(n_rings=64, n_azimuth=1000)
    stds = []
    for radius in (10.0, 80.0):
        scene, albedo, material = _scene([(_inside_sphere(radius), "building")])
        a = render_frame(scene, albedo, material, np.eye(4), beams, NO_NOISE, np.random.default_rng(2), effects=fx)
        b = render_frame(scene, albedo, material, np.eye(4), beams, NO_NOISE, np.random.default_rng(2))
        d = np.linalg.norm(a.points, axis=1) - np.linalg.norm(b.points, axis=1)
        expect = rn.sigma(np.array(radius), np.array(1.0))
        assert abs(np.std(d) / expect - 1) < 0.05, (radius, np.std(d), expect)
        stds.append(np.std(d))
    assert stds[1] > 1.5 * stds[0]
    # incidence: the same range at cos = 0.2 is noisier
    assert rn.sigma(np.array(40.0), np.array(0.2)) > 1.5 * rn.sigma(np.array(40.0), np.array(1.0))
    assert rn.sigma(np.array(0.0), np.array(1.0)) == pytest.approx(0.015)


def test_mixed_pixels_appear_only_at_depth_edges():
    """A panel 10 m ahead in front of a wall: mixed returns lie between the two and only next
    to the panel's vertical edges; a wall too far behind (beyond the merge distance) gives none."""
    beams = BeamModel(n_rings=64, n_azimuth=2000)
    fx = SensorEffects(mixed_pixels=MixedPixels(enabled=True))
    for wall_x, expect_mixed in ((11.0, True), (16.0, False)):
        scene, albedo, material = _scene([(_wall(10.0, -1.0, 1.0, -5, 10), "building"),
                                          (_wall(wall_x, -30, 30, -5, 10), "building")])
        out = render_frame(scene, albedo, material, np.eye(4), beams, NO_NOISE, np.random.default_rng(7), effects=fx)
        r = np.linalg.norm(out.points, axis=1)
        u = out.points / r[:, None]
        r_fg, r_bg = 10.0 / u[:, 0], wall_x / u[:, 0]  # ranges to the panel's and the wall's planes
        y_at_10 = u[:, 1] * r_fg
        mixed = (np.abs(r - r_fg) > 1e-3) & (np.abs(r - r_bg) > 1e-3)
        if not expect_mixed:
            assert not mixed.any()
            continue
        assert mixed.sum() > 20
        assert np.all((r[mixed] > r_fg[mixed]) & (r[mixed] < r_bg[mixed]))
        # next to the panel edges y = +-1 (within one azimuth step + half a divergence at 10 m)
        assert np.all(np.abs(np.abs(y_at_10[mixed]) - 1.0) < 10.0 * (2 * np.pi / 2000 + 0.00125) + 1e-3)


def test_rough_surfaces_displace_returns_along_the_normal_by_the_material_sigma():
    fx = SensorEffects(roughness=Roughness(enabled=True))
    beams = BeamModel(n_rings=64, n_azimuth=1000)
    for mat, sigma in (("terrain", 0.03), ("road", 0.002), ("car", 0.0)):
        scene, albedo, material = _scene([(_quad(-300, 300, -300, 300, -H), mat)])
        a = render_frame(scene, albedo, material, np.eye(4), beams, NO_NOISE, np.random.default_rng(1),
                         effects=fx, roughness_seed=0)
        z = a.points[:, 2][np.linalg.norm(a.points, axis=1) < 30]
        if sigma == 0:
            np.testing.assert_allclose(z, -H, atol=1e-5)
        else:
            assert abs(np.std(z + H) / sigma - 1) < 0.1
        # the height field is fixed in the world: another frame (another rng) sees the same bumps
        b = render_frame(scene, albedo, material, np.eye(4), beams, NO_NOISE, np.random.default_rng(9),
                         effects=fx, roughness_seed=0)
        pa = a.points[np.linalg.norm(a.points, axis=1) < 30]
        pb = b.points[np.linalg.norm(b.points, axis=1) < 30]
        from scipy.spatial import cKDTree
        d, j = cKDTree(pb[:, :2]).query(pa[:, :2])
        close = d < 0.01
        same = np.abs(pa[close, 2] - pb[j[close], 2]) < 2e-3  # up to 1 cm apart on a 0.1 m grid
        assert close.sum() > 1000 and same.mean() > 0.98


class _Ball:
    """A sphere of radius 1 moving along +x at 5 m/s from x = 8 (an actors stand-in)."""

    def __init__(self):
        self.calls = 0

    def cast(self, origins, directions, times):
        self.calls += 1
        c = np.c_[8.0 + 5.0 * times, np.zeros_like(times), np.zeros_like(times)]
        oc = origins - c
        b = np.einsum("ij,ij->i", oc, directions)
        disc = b * b - (np.einsum("ij,ij->i", oc, oc) - 1.0)
        t = np.where(disc >= 0, -b - np.sqrt(np.maximum(disc, 0)), np.inf)
        t = np.where(t > 0, t, np.inf).astype(np.float32)
        n = origins + directions * np.where(np.isfinite(t), t, 0)[:, None] - c
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        return t, n.astype(np.float32), np.full(len(t), MATERIAL["car"])


def test_actors_take_the_nearer_hit_at_each_rays_time():
    scene, albedo, material = _scene([(_wall(20.0, -40, 40, -5, 10), "building")])
    beams = BeamModel(n_rings=64, n_azimuth=1000)
    ball = _Ball()
    out = render_frame(scene, albedo, material, np.eye(4), beams, NO_NOISE, np.random.default_rng(0),
                       actors=ball, timestamp=0.4)  # ball centre at x = 10
    assert ball.calls == 1
    d = np.linalg.norm(out.points - [10.0, 0, 0], axis=1)
    on_ball = d < 1.0 + 1e-3
    assert on_ball.sum() > 50 and np.all(np.abs(d[on_ball] - 1.0) < 1e-3)
    np.testing.assert_allclose(out.points[~on_ball, 0], 20.0, atol=1e-3)  # the rest on the wall
    # no static hit behind the ball where the ball is
    assert not np.any((np.abs(out.points[:, 1]) < 0.5) & (np.abs(out.points[:, 2]) < 0.5)
                      & (out.points[:, 0] > 15))


def test_render_frame_without_effects_is_render_scan():
    scene, albedo, material = _scene([(box(15, 0, 0.3, 4, 2, -H, 1.0), "car"),
                                      (_quad(-100, 100, -100, 100, -H), "road")])
    beams = BeamModel(n_rings=16, n_azimuth=500)
    a = render_frame(scene, albedo, material, np.eye(4), beams, NoiseModel(), np.random.default_rng(3))
    b = render_scan(scene, albedo, material, np.eye(4), beams, NoiseModel(), np.random.default_rng(3))
    for x, y in zip(a[:3], b):
        np.testing.assert_array_equal(x, y)
    assert a.time is None
    assert preset("clean").is_clean and not preset("kitti").is_clean
    assert preset("kitti").motion.mode == "compensated" and preset("raw").motion.mode == "raw"
    with pytest.raises(ValueError):
        preset("kitti").with_effect("fog", True)


def test_preset_reaches_open_sequence_config_and_cli(monkeypatch, tmp_path):
    from gr_graph.config import SlamConfig
    from gr_graph.datasets.registry import KITTI_ROOT_ENV, open_sequence
    from gr_graph.slam import build_parser, overrides_from_args

    monkeypatch.delenv(KITTI_ROOT_ENV, raising=False)
    monkeypatch.chdir(tmp_path)  # no KITTI root found by default
    view, desc = open_sequence(channels=16, frames="5:7", synthetic_preset="raw")
    assert "raw" in desc and view.motion_compensated is False and view.scan_period == 0.1
    f = view[0]
    assert f.n_rings == 16 and f.time is not None and len(f.time) == len(f)
    args = build_parser().parse_args(["--synthetic-preset", "kitti"])
    assert overrides_from_args(args)["data"]["synthetic_preset"] == "kitti"
    assert SlamConfig().data.synthetic_preset is None
    with pytest.raises(ValueError):
        SlamConfig(data={"synthetic_preset": "foggy"})


def test_open_sequence_renders_only_the_kept_channels(monkeypatch, tmp_path):
    # fewer channels cast only the kept rings; the frames must be those of every ring rendered and
    # subsampled (what the registry did before), every field bit for bit, on the kitti world
    # (moving actors, every sensor effect, per-point times)
    from gr_graph.datasets.channels import subsample_channels
    from gr_graph.datasets.registry import KITTI_ROOT_ENV, open_sequence

    monkeypatch.delenv(KITTI_ROOT_ENV, raising=False)
    monkeypatch.chdir(tmp_path)
    every_ring = SyntheticSequence(seed=0, preset="raw")
    for channels in (32, 16):
        view, desc = open_sequence(channels=channels, frames="5:7", synthetic_preset="raw")
        assert f"({channels} of 64 beams" in desc  # the renderer casts the kept rings only
        for k in range(len(view)):
            got, want = view[k], subsample_channels(every_ring[5 + k], channels)
            assert got.n_rings == channels and got.time is not None  # the raw preset's per-point times compared too
            assert_same_frame(got, want)


def test_vertical_angle_error_is_undone_by_the_published_kitti_correction():
    """KISS-ICP / CT-ICP correct KITTI scans by rotating every point up by ~0.22 deg about
    ``p x z``; applied to our render of flat ground with only the global offset, it restores
    the plane z = -H exactly (the sign and size of the modelled error match the literature)."""
    from scipy.spatial.transform import Rotation

    scene, albedo, material = _scene([(_quad(-300, 300, -300, 300, -H), "road")])
    cfg = CalibrationErrors(enabled=True, elevation_sigma_deg=0, azimuth_sigma_deg=0,
                            range_offset_sigma_m=0, range_scale_sigma=0)
    out = render_frame(scene, albedo, material, np.eye(4), BeamModel(64, 500), NO_NOISE, np.random.default_rng(0),
                       effects=SensorEffects(calibration=cfg), laser_calib=draw_laser_calibration(cfg, 0))
    p = out.points[np.linalg.norm(out.points, axis=1) < 60]
    assert p[:, 2].min() < -H - 0.1  # bent down: far ground points lie too low
    axis = np.cross(p, [0.0, 0.0, 1.0])
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    q = Rotation.from_rotvec(axis * np.radians(0.22)).apply(p)
    np.testing.assert_allclose(q[:, 2], -H, atol=1e-5)
