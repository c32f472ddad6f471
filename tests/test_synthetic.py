"""Tests of the synthetic renderer (gr_graph.datasets.synthetic) along the generated route.

References used: the route's poses and the rig's calibration composed with plain numpy, the
beam model's closed form, small_gicp registration (independent of the renderer), an exact
point-to-polyline distance, numpy reads of the written .bin files, and trajectory files
written here and read back through ``--trajectory``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from gr_graph.datasets.base import DatasetError, LidarFrame, LidarSequence
from gr_graph.datasets.synthetic import SyntheticSequence, rig
from gr_graph.datasets.synthetic.__main__ import main as cli_main
from gr_graph.datasets.synthetic.sensor import BeamModel, hdl64_elevations_deg
from gr_graph.datasets.synthetic.sequence import clear_scene_cache
from gr_graph.datasets.synthetic.route import generate_route
from gr_graph.datasets.synthetic.town import build_town
from gr_graph.trajectory import write_kitti_poses, write_tum_poses


@pytest.fixture(scope="module")
def seq() -> SyntheticSequence:
    return SyntheticSequence(seed=0, preset="clean")


@pytest.fixture(scope="module")
def frame1000(seq) -> LidarFrame:
    return seq[1000]


def _camera_poses(T_w_velo: np.ndarray) -> np.ndarray:
    """KITTI's ground-truth convention: camera-0 poses ``Tr · T_w_velo · Tr⁻¹`` (rig's Tr)."""
    Tr = rig.T_cam_velo()
    return Tr @ T_w_velo @ np.linalg.inv(Tr)


def _rot_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


# ---------------------------------------------------------------- beam model ------------
def test_beam_model_matches_hdl64e_pattern():
    el = hdl64_elevations_deg()
    assert el.shape == (64,)
    assert el[0] == pytest.approx(2.0) and el[-1] == pytest.approx(-24.9)
    assert np.all(np.diff(el) < 0), "ring 0 must be the highest beam, strictly decreasing"
    np.testing.assert_allclose(np.diff(el[:32]), -1 / 3, atol=1e-12)  # dense upper block
    lower = -np.diff(el[32:])
    np.testing.assert_allclose(lower, lower[0], atol=1e-12)
    assert 0.45 < lower[0] < 0.55  # about 1/2 deg in the lower block
    np.testing.assert_array_equal(BeamModel(n_rings=16).beam_indices, np.arange(0, 64, 4))
    with pytest.raises(ValueError, match="n_rings"):
        BeamModel(n_rings=20)


def test_rendered_rings_have_the_beam_elevations(frame1000):
    f = frame1000
    el = np.degrees(np.arctan2(f.points[:, 2], np.hypot(f.points[:, 0], f.points[:, 1])))
    expected = hdl64_elevations_deg()[f.ring]
    assert np.abs(el - expected).max() < 1e-6  # range noise is along the ray
    means = np.array([el[f.ring == r].mean() for r in range(64)])
    assert np.all(np.diff(means) < 0)  # ring 0 highest
    assert np.all(np.diff(f.ring) >= 0), "points are stored ring by ring from ring 0"


# ---------------------------------------------------------------- frames -----------------
def test_frame_shape_types_and_ranges(seq, frame1000):
    f = frame1000
    assert isinstance(seq, LidarSequence)
    assert seq.name == "synthetic-00" and len(seq) == 4541
    assert f.index == 1000 and f.n_rings == 64
    assert f.points.dtype == np.float64 and f.points.shape[1] == 3
    assert f.intensity.dtype == np.float32 and f.ring.dtype == np.int16
    assert np.isfinite(f.points).all() and np.isfinite(f.intensity).all()
    assert 80_000 < len(f) <= 64 * 2000  # a dense town: most rays return, some drop out
    r = np.linalg.norm(f.points, axis=1)
    assert r.min() >= 1.0 and r.max() <= 120.0
    assert f.intensity.min() >= 0 and f.intensity.max() <= 1 and f.intensity.std() > 0.02
    assert set(np.unique(f.ring)) == set(range(64))
    assert f.timestamp == pytest.approx(seq.timestamps[1000])
    # structure on both sides of the road: returns > 0.7 m above the ground, left and right
    tall = (f.points[:, 2] > -1.0) & (np.hypot(f.points[:, 0], f.points[:, 1]) < 40)
    assert (f.points[tall, 1] > 6).sum() > 2000 and (f.points[tall, 1] < -6).sum() > 2000


def test_max_range_and_ring_subsample(frame1000):
    short = SyntheticSequence(seed=0, max_range=30.0, preset="clean")[1000]
    assert np.linalg.norm(short.points, axis=1).max() <= 30.0
    assert len(short) < len(frame1000)
    f16 = SyntheticSequence(seed=0, n_rings=16, preset="clean")[1000]
    assert f16.n_rings == 16 and set(np.unique(f16.ring)) == set(range(16))
    sub = frame1000.select(frame1000.ring % 4 == 0)
    # the 16-ring render is exactly every 4th ring of the 64-ring render
    np.testing.assert_array_equal(f16.points, sub.points)
    np.testing.assert_array_equal(f16.intensity, sub.intensity)
    np.testing.assert_array_equal(f16.ring, sub.ring // 4)
    with pytest.raises(ValueError, match="max_range"):
        SyntheticSequence(max_range=500.0, preset="clean")


def test_deterministic_for_a_seed_and_independent_of_order(seq, frame1000):
    other = SyntheticSequence(seed=0, preset="clean")
    other[50]  # render something else first
    again = other[1000]
    np.testing.assert_array_equal(again.points, frame1000.points)
    np.testing.assert_array_equal(again.intensity, frame1000.intensity)
    np.testing.assert_array_equal(again.ring, frame1000.ring)
    import pickle  # e.g. DataLoader workers: the copy renders the same frame

    np.testing.assert_array_equal(pickle.loads(pickle.dumps(seq))[1000].points, frame1000.points)
    noise1 = SyntheticSequence(seed=1, town_seed=0, preset="clean")[1000]  # same town, other noise
    assert len(noise1) != len(frame1000) or not np.array_equal(noise1.points, frame1000.points)
    assert seq[-1].index == 4540
    with pytest.raises(IndexError):
        seq[4541]


@pytest.mark.slow
def test_town_rebuild_is_bit_identical(frame1000):
    clear_scene_cache()  # rebuild the town and its ray-casting scene from scratch
    again = SyntheticSequence(seed=0, preset="clean")[1000]
    np.testing.assert_array_equal(again.points, frame1000.points)
    np.testing.assert_array_equal(again.intensity, frame1000.intensity)


def test_town_depends_on_seed_and_is_deterministic():
    P = generate_route(0).T_w_velo[:300, :3, 3]  # any 3-D path works
    a, b, c = build_town(P, seed=5), build_town(P, seed=5), build_town(P, seed=6)
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.triangles, b.triangles)
    assert a.vertices.shape != c.vertices.shape or not np.array_equal(a.vertices, c.vertices)
    with pytest.raises(ValueError, match="positions"):
        build_town(np.zeros((5, 2)))


# ---------------------------------------------------------------- ground truth ----------
def test_gt_poses_are_the_generated_route_and_the_rig_is_its_own(seq):
    route = generate_route(0)
    np.testing.assert_array_equal(seq.gt_poses, route.T_w_velo)
    np.testing.assert_array_equal(seq.timestamps, route.times)
    np.testing.assert_array_equal(seq.T_cam_velo, rig.T_cam_velo())
    assert seq.path.route is route and seq.gt_poses.shape == (4541, 4, 4)
    # another route seed drives elsewhere through its own town; the noise seed is unchanged
    other = SyntheticSequence(seed=0, route_seed=1, preset="clean")
    assert other.seed == seq.seed and other.route_seed == 1
    assert np.linalg.norm(other.gt_poses[-1, :3, 3] - seq.gt_poses[-1, :3, 3]) > 10.0
    with pytest.raises(ValueError, match="route_seed"):
        SyntheticSequence(route_seed=-1, preset="clean")


def _kitti_calib(path: Path, Tr: np.ndarray) -> None:
    P0 = "P0: " + " ".join(["1"] + ["0"] * 11)
    path.write_text(P0 + "\nTr: " + " ".join(f"{v:.17g}" for v in Tr[:3].ravel()) + "\n")


def test_renders_along_a_given_trajectory(tmp_path):
    """--trajectory: KITTI file (with and without calib/times beside it), TUM file, KITTI root."""
    T = np.asarray(generate_route(0).T_w_velo[2000:2040])  # 40 frames of some drive, not from 0
    ts = 5.0 + np.arange(40) * 0.1037
    base = np.linalg.inv(T[0]) @ T  # every source is re-based on its first pose
    # KITTI camera-frame file alone: the rig's Tr, 0.1 s steps
    f = write_kitti_poses(tmp_path / "a" / "poses.txt", _camera_poses(T))
    s = SyntheticSequence(trajectory=f, preset="clean")
    np.testing.assert_allclose(s.gt_poses, base, atol=1e-9)
    np.testing.assert_allclose(s.timestamps, np.arange(40) * 0.1, atol=1e-12)
    assert s.path.route is None and "KITTI format" in s.path.source
    # with a calib.txt (another Tr) and times.txt beside it
    Tr = rig.T_cam_velo()
    Tr[:3, 3] += [0.1, -0.2, 0.3]
    d = tmp_path / "b"
    d.mkdir()
    write_kitti_poses(d / "poses.txt", Tr @ T @ np.linalg.inv(Tr))
    _kitti_calib(d / "calib.txt", Tr)
    (d / "times.txt").write_text("".join(f"{t:.6f}\n" for t in ts))
    s = SyntheticSequence(trajectory=d / "poses.txt", preset="clean")
    np.testing.assert_allclose(s.gt_poses, base, atol=1e-9)
    np.testing.assert_allclose(s.T_cam_velo, Tr, atol=1e-15)
    np.testing.assert_allclose(s.timestamps, ts - ts[0], atol=1e-9)
    # TUM: LiDAR poses with their timestamps
    s = SyntheticSequence(trajectory=write_tum_poses(tmp_path / "c.tum", ts, T), preset="clean")
    np.testing.assert_allclose(s.gt_poses, base, atol=1e-6)
    np.testing.assert_allclose(s.timestamps, ts - ts[0], atol=1e-9)
    # a KITTI root: poses/<seq>.txt, sequences/<seq>/calib.txt and times.txt
    root = tmp_path / "root"
    (root / "sequences" / "07").mkdir(parents=True)
    write_kitti_poses(root / "poses" / "07.txt", Tr @ T @ np.linalg.inv(Tr))
    _kitti_calib(root / "sequences" / "07" / "calib.txt", Tr)
    (root / "sequences" / "07" / "times.txt").write_text("".join(f"{t:.6f}\n" for t in ts))
    s = SyntheticSequence(trajectory=root, trajectory_seq="07", preset="clean")
    np.testing.assert_allclose(s.gt_poses, base, atol=1e-9)
    # bad input names the file
    bad = tmp_path / "bad.txt"
    bad.write_text("1 2 3\n")
    for path, msg in ((bad, "bad.txt: 3 columns"), (tmp_path / "none.txt", "none.txt: trajectory file not found"),
                      (tmp_path / "a", "no poses/00.txt")):
        with pytest.raises(DatasetError, match=msg):
            SyntheticSequence(trajectory=path, preset="clean")


def test_renders_a_scan_along_a_given_trajectory(tmp_path):
    """The town is built around the given path: frames along it see streets on both sides."""
    T = np.asarray(generate_route(3).T_w_velo[1000:1400:4])
    s = SyntheticSequence(trajectory=write_tum_poses(tmp_path / "t.tum", np.arange(len(T)) * 0.4, T),
                          n_rings=16, n_azimuth=500, seed=2, preset="clean")
    f = s[50]
    assert len(f) > 3000 and s.town.path_xyz[:, :2].max(0)[0] - s.town.path_xyz[:, :2].min(0)[0] > 10
    assert repr(s).startswith("SyntheticSequence(seed=2, town_seed=2, trajectory=")
    # the exporter renders along it too, and says so
    out = tmp_path / "export"
    assert cli_main(["--out", str(out), "--trajectory", str(tmp_path / "t.tum"), "--frames", "50:51",
                     "--seed", "2", "--channels", "16", "--n-azimuth", "500", "--preset", "clean"]) == 0
    meta = json.loads((out / "sequences" / "00" / "synthetic.json").read_text())
    assert meta["trajectory"] == str(tmp_path / "t.tum") and "TUM format" in meta["source"]
    raw = np.fromfile(out / "sequences" / "00" / "velodyne" / "000000.bin", dtype=np.float32).reshape(-1, 4)
    np.testing.assert_array_equal(raw[:, :3], f.points.astype(np.float32))
    assert cli_main(["--out", str(tmp_path / "x"), "--trajectory", str(tmp_path / "missing.txt")]) == 2


@pytest.mark.slow
def test_renders_along_the_real_kitti00_ground_truth(kitti00_gt_dir):
    """The real KITTI 00 trajectory (../shared/data, never shipped) as the sensor path."""
    s = SyntheticSequence(trajectory=kitti00_gt_dir / "00.txt", n_rings=16, preset="clean")
    assert len(s) == 4541
    official = np.loadtxt(kitti00_gt_dir / "00.txt")
    T_cam = np.tile(np.eye(4), (4541, 1, 1))
    T_cam[:, :3, :] = official.reshape(-1, 3, 4)
    Tr = rig.T_cam_velo()  # no calib.txt beside the file: the rig's own Tr
    T_velo = np.linalg.inv(Tr) @ T_cam @ Tr
    np.testing.assert_allclose(s.gt_poses, np.linalg.inv(T_velo[0]) @ T_velo, atol=1e-6)
    np.testing.assert_allclose(s.timestamps, np.loadtxt(kitti00_gt_dir / "times.txt"), atol=1e-9)
    f = s[1000]
    tall = (f.points[:, 2] > -1.0) & (np.hypot(f.points[:, 0], f.points[:, 1]) < 40)
    assert (f.points[tall, 1] > 6).sum() > 200 and (f.points[tall, 1] < -6).sum() > 200


def _polyline_distance(points: np.ndarray, path: np.ndarray) -> np.ndarray:
    """Distance of 2-D points to the polyline through ``path``, to within 1 cm.

    The polyline is subdivided every 2 cm (every frame-to-frame segment of the full-rate
    trajectory, not the town's resampling); the nearest of those points is at most 1 cm
    farther than the polyline.
    """
    from scipy.spatial import cKDTree

    seg = np.diff(path, axis=0)
    n = np.maximum(1, np.ceil(np.linalg.norm(seg, axis=1) / 0.02).astype(int))
    k = np.repeat(np.arange(len(seg)), n)
    t = np.concatenate([np.arange(m) / m for m in n])
    dense = np.concatenate([path[k] + t[:, None] * seg[k], path[-1:]])
    return cKDTree(dense).query(points)[0] - 0.01


def _edge_samples(rects: np.ndarray, step: float = 0.5) -> np.ndarray:
    pts = []
    for r in rects:
        for k in range(4):
            p, q = r[k], r[(k + 1) % 4]
            n = max(2, int(np.linalg.norm(q - p) / step) + 1)
            pts.append(p + np.linspace(0, 1, n)[:, None] * (q - p))
    return np.concatenate(pts)


def test_nothing_stands_on_the_road_anywhere_along_the_path(seq):
    town = seq.town
    path = seq.gt_poses[:, :2, 3]
    keep = np.r_[True, np.linalg.norm(np.diff(path, axis=0), axis=1) > 1e-6]
    path = path[keep]
    fp = town.footprints
    assert len(fp["building"]) > 100 and len(fp["tree"]) > 100 and len(fp["car"]) > 100
    # the layout samples footprints every 0.35 m against a 0.5 m path sampling: allow 0.1 m
    assert _polyline_distance(_edge_samples(fp["building"]), path).min() > 8.5 - 0.1
    assert _polyline_distance(_edge_samples(fp["car"]), path).min() > 2.4 - 0.1
    poles = fp["pole"]
    assert (_polyline_distance(poles[:, :2], path) - poles[:, 2]).min() > 5.6 - 0.1


def test_sensor_rides_1_73_m_above_the_ground(seq):
    P = seq.gt_poses[:, :3, 3]
    h = P[:, 2] - seq.town.ground(P[:, :2])
    # the route's height is a function of place, so every pass of a street agrees with the
    # one ground surface built from the path
    assert np.median(h) == pytest.approx(1.73, abs=0.01)
    assert np.mean(np.abs(h - 1.73) < 0.03) > 0.95
    assert np.abs(h - 1.73).max() < 0.1


# ---------------------------------------------------------------- geometry vs GT --------
def _align(target: LidarFrame, source: LidarFrame, init: np.ndarray) -> np.ndarray:
    small_gicp = pytest.importorskip("small_gicp")
    res = small_gicp.align(target.points, source.points, init_T_target_source=init,
                           registration_type="GICP", downsampling_resolution=0.25,
                           max_correspondence_distance=1.0, num_threads=1)
    assert res.converged
    return res.T_target_source


def _revisit_pair(direction: str) -> tuple[int, int]:
    """A frame of the route's first ``direction`` revisit and the earlier frame nearest to it."""
    route = generate_route(0)
    r = next(r for r in route.revisits if r.direction == direction)
    j = (r.frames[0] + r.frames[1]) // 2
    P = route.T_w_velo[:, :3, 3]
    i = r.earlier[0] + int(np.argmin(np.linalg.norm(P[r.earlier[0]:r.earlier[1]] - P[j], axis=1)))
    return i, j


@pytest.mark.parametrize("i, j, from_identity", [(1000, 1003, False), (2000, 2001, True),
                                                  (*_revisit_pair("same"), False),
                                                  (*_revisit_pair("opposite"), False)],
                         ids=["odometry", "odometry-from-identity", "revisit", "revisit-opposite"])
def test_frames_register_onto_their_ground_truth(seq, i, j, from_identity):
    """small_gicp recovers the GT relative pose (odometry pairs and loop revisits, one driven
    the other way on the other lane: the town renders the same structures again)."""
    T_gt = np.linalg.inv(seq.gt_poses[j]) @ seq.gt_poses[i]
    if from_identity:
        init = np.eye(4)  # plain odometry: no help from GT
    else:  # start 0.3 m and 2 deg off
        c, s = np.cos(np.radians(2)), np.sin(np.radians(2))
        pert = np.eye(4)
        pert[:2, :2] = [[c, -s], [s, c]]
        pert[:3, 3] = [0.3, -0.2, 0.05]
        init = T_gt @ pert
    T = _align(seq[j], seq[i], init)
    E = np.linalg.inv(T_gt) @ T
    assert np.linalg.norm(E[:3, 3]) < 0.03
    assert _rot_deg(E[:3, :3]) < 0.15


# ---------------------------------------------------------------- writer / CLI ----------
def test_cli_writes_exactly_the_frames_in_kitti_layout(tmp_path, seq):
    out = tmp_path / "synth"
    assert cli_main(["--out", str(out), "--frames", "20:23", "--seed", "0", "--preset", "clean"]) == 0
    sdir = out / "sequences" / "00"
    bins = sorted((sdir / "velodyne").glob("*.bin"))
    assert [b.name for b in bins] == ["000000.bin", "000001.bin", "000002.bin"]
    for k, b in enumerate(bins):
        raw = np.fromfile(b, dtype=np.float32).reshape(-1, 4)
        f = seq[20 + k]
        np.testing.assert_array_equal(raw[:, :3], f.points.astype(np.float32))
        np.testing.assert_array_equal(raw[:, 3], f.intensity)
    times = np.loadtxt(sdir / "times.txt")
    np.testing.assert_array_equal(times, seq.timestamps[20:23])
    poses = np.loadtxt(out / "poses" / "00.txt")
    np.testing.assert_allclose(poses, _camera_poses(seq.gt_poses[20:23])[:, :3, :].reshape(3, 12), atol=1e-9)
    calib = {l.split(":")[0]: np.array(l.split()[1:], float)
             for l in (sdir / "calib.txt").read_text().splitlines()}
    assert set(calib) == {"P0", "Tr"}
    np.testing.assert_allclose(calib["Tr"], rig.T_cam_velo()[:3].ravel(), rtol=1e-12)
    np.testing.assert_allclose(calib["P0"], rig.P0().ravel(), rtol=1e-12)
    meta = json.loads((sdir / "synthetic.json").read_text())
    assert meta["first_frame"] == 20 and meta["n_frames"] == 3 and meta["seed"] == 0
    assert meta["route_seed"] == 0 and meta["trajectory"] is None and "generated route" in meta["source"]
    # a second run into the same folder refuses to mix runs unless --overwrite
    assert cli_main(["--out", str(out), "--frames", "0:1"]) == 2
    assert cli_main(["--out", str(out), "--frames", "0:1", "--overwrite", "--preset", "clean"]) == 0
    assert len(list((sdir / "velodyne").glob("*.bin"))) == 1
    assert cli_main(["--out", str(out), "--frames", "9:4"]) == 2


def test_written_sequence_reads_back_through_the_kitti_loader(tmp_path, seq):
    kitti = pytest.importorskip("gr_graph.datasets.kitti")
    out = tmp_path / "synth"
    assert cli_main(["--out", str(out), "--frames", "30:32", "--preset", "clean"]) == 0
    ks = kitti.KittiSequence(out, seq="00")
    assert len(ks) == 2
    for k in range(2):
        f, g = ks[k], seq[30 + k]
        np.testing.assert_array_equal(f.points, g.points.astype(np.float32).astype(np.float64))
        np.testing.assert_array_equal(f.intensity, g.intensity)
    np.testing.assert_allclose(ks.T_cam_velo, seq.T_cam_velo, atol=1e-15)
    np.testing.assert_allclose(ks.timestamps, seq.timestamps[30:32], atol=0)
    # KITTI-frame GT maps back to the same relative LiDAR motion
    rel_k = np.linalg.inv(ks.gt_poses[0]) @ ks.gt_poses[1]
    rel_s = np.linalg.inv(seq.gt_poses[30]) @ seq.gt_poses[31]
    np.testing.assert_allclose(rel_k, rel_s, atol=1e-9)


def test_kitti_loader_recovers_the_rendered_rings(tmp_path, seq):
    kitti = pytest.importorskip("gr_graph.datasets.kitti")
    out = tmp_path / "synth"
    assert cli_main(["--out", str(out), "--frames", "30:31", "--preset", "clean"]) == 0
    f = kitti.KittiSequence(out, seq="00")[0]
    assert f.ring is not None
    np.testing.assert_array_equal(f.ring, seq[30].ring)


def test_release_cache_frees_the_town_and_frames_come_back_identical(tmp_path):
    from loader_support import write_short_trajectory

    from gr_graph.datasets.base import release_render_cache
    from gr_graph.datasets.registry import SequenceView
    from gr_graph.datasets.synthetic import sequence as synthetic_sequence

    s = SyntheticSequence(preset="clean", n_rings=16, nthreads=1,
                          trajectory=write_short_trajectory(tmp_path / "t.tum", 6))
    before = s[3]
    key = synthetic_sequence._scene_key(s.town_seed, s.path, s.town_config)
    assert key in synthetic_sequence._CACHE
    assert release_render_cache(SequenceView(s, 1, 5))  # found through the view's parent
    assert key not in synthetic_sequence._CACHE
    assert not release_render_cache(s)  # nothing left to free
    assert not release_render_cache(object())  # a sequence without a render cache
    again = s[3]  # rebuilt on demand, the same frame
    assert key in synthetic_sequence._CACHE
    np.testing.assert_array_equal(again.points, before.points)
    np.testing.assert_array_equal(again.intensity, before.intensity)
