"""Loop closures: Scan Context, candidates, verification, precision/recall bookkeeping."""

from __future__ import annotations

import numpy as np
import pytest
import small_gicp
from scipy.spatial.transform import Rotation

from gr_graph.config import GraphConfig, LoopConfig, PreprocessConfig
from gr_graph.loop_closure import (
    LoopCandidate,
    LoopClosureSchedule,
    ScanContextDatabase,
    loop_candidates,
    newest_candidate,
    proximity_candidate,
    scan_context,
    scan_context_distance,
    verify_loop,
    yaw_matrix,
)
from gr_graph.frame_loop import not_converged_counts
from gr_graph.loop_evaluation import loop_error, loop_precision_recall, true_revisits
from gr_graph.preprocess import preprocess_scan


@pytest.fixture(scope="module")
def kitti0(kitti_root):
    p = kitti_root / "sequences" / "00" / "velodyne" / "000000.bin"
    return np.fromfile(p, np.float32).reshape(-1, 4)[:, :3].astype(np.float64)


@pytest.fixture(scope="module")
def gicp_pair(small_gicp_pair_dir):
    src = np.asarray(small_gicp.read_ply(str(small_gicp_pair_dir / "source.ply")).points())[:, :3]
    tgt = np.asarray(small_gicp.read_ply(str(small_gicp_pair_dir / "target.ply")).points())[:, :3]
    T = np.loadtxt(small_gicp_pair_dir / "T_target_source.txt")
    return src.astype(np.float64), tgt.astype(np.float64), T


def test_scan_context_recovers_yaw(kitti0):
    """The same scan seen from a frame rotated by 7 sectors: distance ~0, shift 7, yaw guess exact."""
    n_s = 60
    psi = 7 * 2 * np.pi / n_s
    T_old_cur = yaw_matrix(psi)
    p_old = kitti0
    p_cur = p_old @ T_old_cur[:3, :3]  # R(ψ)ᵀ p
    d_same, s = scan_context_distance(scan_context(p_cur, n_sectors=n_s), scan_context(p_old, n_sectors=n_s))
    assert s == 7 and d_same < 0.02
    # an unrelated scan (other place) is far in descriptor space
    rng = np.random.default_rng(0)
    other = rng.uniform(-40, 40, size=(50000, 3)) * np.array([1, 1, 0.05])
    d_other, _ = scan_context_distance(scan_context(other, n_sectors=n_s), scan_context(p_old, n_sectors=n_s))
    assert d_other > 3 * d_same + 0.1


def test_scan_context_database_respects_frame_gap(kitti0):
    cfg = LoopConfig(min_frame_gap=3, sc_threshold=0.2)
    db = ScanContextDatabase(cfg)
    rng = np.random.default_rng(1)
    for _ in range(3):
        db.add(rng.uniform(-40, 40, size=(20000, 3)) * np.array([1, 1, 0.05]))
    db.add(kitti0)  # position 3
    db.add(kitti0 @ yaw_matrix(0.5)[:3, :3])  # position 4: same place, rotated
    assert db.query(2) is None  # nothing old enough
    c = db.query(4)
    assert c is None or c.match != 3  # gap 1 < 3: never the same place
    db.add(rng.uniform(-40, 40, size=(20000, 3)))
    db.add(kitti0 @ yaw_matrix(-0.3)[:3, :3])  # position 6: gap 3 to position 3
    c = db.query(6)
    assert c is not None and c.match == 3 and c.source == "scan_context"


def test_proximity_candidate():
    poses = np.repeat(np.eye(4)[None], 10, axis=0)
    for i in range(10):
        poses[i, 0, 3] = [0, 10, 20, 30, 40, 30.5, 20.2, 9.0, 0.1, -5][i]
    c = proximity_candidate(poses, 8, LoopConfig(min_frame_gap=4, radius=2.0))
    assert c is not None and c.match == 0
    np.testing.assert_allclose(c.guess, np.linalg.inv(poses[0]) @ poses[8])
    assert proximity_candidate(poses, 6, LoopConfig(min_frame_gap=4, radius=0.1)) is None


def stop_and_go_poses(n: int = 300) -> np.ndarray:
    """1 m a frame along x for frames 0-50, stopped at x = 50 for frames 50-249, then on at 1 m a frame."""
    x = np.concatenate([np.arange(51.0), np.full(199, 50.0), 50.0 + np.arange(1.0, n - 249)])
    poses = np.repeat(np.eye(4)[None], n, axis=0)
    poses[:, 0, 3] = x
    return poses


def test_min_path_length_keeps_a_stopped_vehicle_from_closing_loops_with_itself():
    poses = stop_and_go_poses()
    i = 249  # 199 frames stopped: frames 50-149 are old enough by frame count, and at the same place
    gap_only = LoopConfig(min_frame_gap=100, radius=10.0, use_scan_context=False)
    assert newest_candidate(poses, i, gap_only) == 149
    c = loop_candidates(poses, i, None, gap_only)
    assert len(c) == 1 and 50 <= c[0].match <= 149 and c[0].score == 0.0  # the car with itself
    # 20 m of path back: the newest candidate is frame 30 (50 − 30 = 20 m), 20 m away: beyond the radius
    by_path = gap_only.model_copy(update={"min_path_length": 20.0})
    assert newest_candidate(poses, i, by_path) == 30
    assert loop_candidates(poses, i, None, by_path) == []
    assert newest_candidate(poses, i, by_path.model_copy(update={"min_path_length": 20.5})) == 29
    # with a radius wide enough, the candidate is frame 30 itself, 20 m back
    c = loop_candidates(poses, i, None, by_path.model_copy(update={"radius": 25.0}))
    assert [x.match for x in c] == [30] and c[0].score == pytest.approx(20.0)
    # not that much path yet: no candidate at all; once moving, the frame gap decides again
    assert newest_candidate(poses, 120, by_path.model_copy(update={"min_path_length": 60.0})) == -1
    assert newest_candidate(poses, 299, by_path) == 199  # 100 frames back is 49 m of path back
    assert newest_candidate(poses[:40], 39, by_path) == -1  # fewer frames than the gap


def test_scan_context_query_respects_the_newest_candidate(kitti0):
    cfg = LoopConfig(min_frame_gap=1, sc_threshold=0.2)
    db = ScanContextDatabase(cfg)
    rng = np.random.default_rng(2)
    db.add(kitti0)  # 0
    db.add(rng.uniform(-40, 40, size=(20000, 3)) * np.array([1, 1, 0.05]))  # 1
    db.add(kitti0 @ yaw_matrix(0.4)[:3, :3])  # 2: the place of scan 0 again
    db.add(kitti0 @ yaw_matrix(-0.2)[:3, :3])  # 3: and again
    assert db.query(3).match in (0, 2)
    assert db.query(3, last=1).match == 0  # scan 2 is excluded
    assert db.query(3, last=-1) is None


def test_scan_context_height_offset_follows_the_sensor_height():
    """Points of a flat ground 3 m under the sensor: the default offset (2 m) leaves every bin empty,
    an offset of the sensor's height fills the bins the ground reaches."""
    rng = np.random.default_rng(3)
    ground = np.column_stack([rng.uniform(-30, 30, (5000, 2)), np.full(5000, -3.0) + rng.normal(0, 0.02, 5000)])
    wall = np.column_stack([np.full(500, 10.0), rng.uniform(-5, 5, 500), rng.uniform(-3, 1, 500)])
    pts = np.vstack([ground, wall])
    low, high = LoopConfig(), LoopConfig(sc_height_offset=3.5)
    dbs = [ScanContextDatabase(cfg) for cfg in (low, high)]
    for db in dbs:
        db.add(pts)
    occupied = [float((db.descs[0] > 0).mean()) for db in dbs]
    assert occupied[0] < 0.05 < 0.3 < occupied[1]  # the ground reaches 8-10 of the 20 rings (80 m)
    np.testing.assert_allclose(dbs[1].descs[0], scan_context(pts, z_offset=3.5))


def test_verify_accepts_real_overlapping_pair(gicp_pair):
    """small_gicp's real pair: accepted; transform matches its reference (≤ 5 cm, 0.5°; the
    reference comes from 0.1 m GICP, small_gicp itself differs by ~0.3° at 0.25-0.5 m)."""
    src, tgt, T_ref = gicp_pair
    pc = PreprocessConfig(voxel_size=0.5)
    s, t = preprocess_scan(src, pc, 1), preprocess_scan(tgt, pc, 0)
    cand = LoopCandidate(1, 0, np.eye(4), "proximity", 0.5)
    e = verify_loop(s, t, cand, LoopConfig(), GraphConfig())
    assert e.ok, e.reason
    et, er = loop_error(e.T, np.stack([T_ref, np.eye(4)]), 0, 1)
    assert et < 0.05 and er < 0.5
    assert e.kind == "loop" and np.all(np.linalg.eigvalsh(e.information) > 0)
    assert e.info["covariance"] == "scaled_hessian"
    assert e.converged  # the last stage's registration converged within its 30 iterations
    # cut to one iteration a stage, the same pair stops before converging and says so
    real_align = small_gicp.align
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(small_gicp, "align", lambda *a, **kw: real_align(*a, **{**kw, "max_iterations": 1}))
        cut = verify_loop(s, t, cand, LoopConfig(), GraphConfig())
    assert cut.ok and not cut.converged  # kept: its inlier, rmse and Hessian tests pass
    assert not_converged_counts([e, cut]) == {"odometry": 0, "loop": 1}
    # the cluster-robust covariance of the same registration (same pose; its own information)
    r = verify_loop(s, t, cand, LoopConfig(), GraphConfig(registration_covariance="cluster_robust", min_clusters=10))
    assert r.ok and r.info["covariance"] == "cluster_robust"
    np.testing.assert_allclose(r.T, e.T)
    assert np.all(np.linalg.eigvalsh(r.information) > 0) and not np.allclose(r.information, e.information, rtol=0.1)


def test_verify_rejects_pair_far_apart(gicp_pair, kitti0):
    """Two scans of different places (small_gicp's data vs KITTI 00 frame 0) are rejected."""
    src, _, _ = gicp_pair
    pc = PreprocessConfig(voxel_size=0.5)
    s, t = preprocess_scan(src, pc, 1), preprocess_scan(kitti0, pc, 0)
    e = verify_loop(s, t, LoopCandidate(1, 0, np.eye(4), "scan_context", 0.1), LoopConfig(), GraphConfig())
    assert not e.ok and e.reason


def test_verify_rejects_wrong_offset_of_the_same_place(kitti0):
    """The same scan with a 40 m guess error (proximity): verification must not accept."""
    pc = PreprocessConfig(voxel_size=0.5)
    s = preprocess_scan(kitti0, pc, 1)
    t = preprocess_scan(kitti0 + np.array([40.0, 0, 0]), pc, 0)
    e = verify_loop(s, t, LoopCandidate(1, 0, np.eye(4), "proximity", 1.0), LoopConfig(), GraphConfig())
    assert not e.ok


def test_precision_recall_bookkeeping():
    # a path out along x and back: frames 0..9 out, 10..19 back over the same points
    x = np.concatenate([np.arange(10), np.arange(9, -1, -1)]).astype(float)
    gt = np.repeat(np.eye(4)[None], 20, axis=0)
    gt[:, 0, 3] = x
    rv = true_revisits(gt, min_frame_gap=5, radius=0.5)
    assert rv.tolist() == [False] * 12 + [True] * 8  # frame 10, 11 are within 5 frames of 9, 8
    checked = np.zeros(20, bool)
    checked[[12, 14, 16, 18]] = True
    good = (14, 5, np.linalg.inv(gt[5]) @ gt[14])
    T_bad = np.eye(4)
    T_bad[1, 3] = 3.0
    bad = (16, 3, T_bad)  # frame 16 and 3 are the same place in GT: T̂ = I would be right
    m = loop_precision_recall([good, bad], gt, checked, min_frame_gap=5, revisit_radius=0.5)
    assert m["n_loops"] == 2 and m["n_correct"] == 1 and m["precision"] == 0.5
    assert m["n_revisit_queries"] == 4 and m["n_revisit_found"] == 1 and m["recall"] == 0.25
    assert m["n_revisit_segments"] == 1 and m["segment_recall"] == 1.0


def test_true_revisits_at_a_stop_need_the_path_too():
    """Frames 150-249 of the stop are "revisits" by frame gap alone (frames 50-149, same place);
    with 20 m of path asked for there are none, and a real return still counts."""
    gt = stop_and_go_poses()
    by_gap = true_revisits(gt, min_frame_gap=100, radius=5.0)
    assert np.flatnonzero(by_gap).tolist() == list(range(145, 255))  # the stop (45-49 within 5 m), 5 m on
    assert not true_revisits(gt, min_frame_gap=100, radius=5.0, min_path_length=20.0).any()
    back = np.concatenate([gt, gt[::-1][:60]])  # then driven back to x = 50 (frames 300-359)
    rv = true_revisits(back, min_frame_gap=100, radius=5.0, min_path_length=20.0)
    path = np.concatenate([[0.0], np.cumsum(np.abs(np.diff(back[:, 0, 3])))])
    expected = [i for i in range(100, len(back))
                if any(abs(back[j, 0, 3] - back[i, 0, 3]) <= 5.0 for j in range(i - 99) if path[i] - path[j] >= 20.0)]
    assert np.flatnonzero(rv).tolist() == expected and expected[0] > 300
    m = loop_precision_recall([], back, np.ones(len(back), bool), 100, revisit_radius=5.0, min_path_length=20.0)
    assert m["n_revisit_queries"] == len(expected)


def test_loop_rmse_threshold_scales_with_sparsity():
    from gr_graph.config import SensorConfig, loop_max_rmse

    auto, hdl = LoopConfig(), SensorConfig()
    vals = [loop_max_rmse(auto, hdl, ch) for ch in (64, 32, 16)]
    assert vals[0] == pytest.approx(0.35) and vals[0] < vals[1] < vals[2] < 0.5
    assert loop_max_rmse(LoopConfig(max_rmse=0.2), hdl, 16) == 0.2


def test_schedule_checks_every_nth_usable_frame_with_cooldown_and_reoptimises():
    cfg = LoopConfig(check_every=5, min_frame_gap=20, cooldown=2, reoptimize_every=30)
    sch = LoopClosureSchedule(cfg)
    assert [i for i in range(40) if LoopClosureSchedule(cfg).should_check(i, True)] == [20, 25, 30, 35]
    assert not sch.should_check(25, usable=False)
    assert sch.should_check(25, True) and not sch.should_reoptimize(25)  # no loop yet
    sch.loop_accepted()  # at 25: the next 2 checks (30, 35) are skipped, then 40 is checked
    assert [i for i in (26, 30, 31, 35, 40) if sch.should_check(i, True)] == [40]
    assert sch.should_reoptimize(40)  # 40 - 0 >= 30 with a pending loop
    sch.reoptimized(40)
    assert not sch.should_reoptimize(45)
    sch.loop_accepted()
    assert not sch.should_reoptimize(65) and sch.should_reoptimize(70)  # 30 frames after the last


def test_row_buffer_and_the_estimate_equal_the_list_conversion_they_replace():
    """The loop check's ring keys and trajectory estimate come from arrays that grow with the run:
    the same values as converting the lists at each check, past several capacity doublings, and
    the estimate is a new array each time (a caller changing it changes nothing kept)."""
    from gr_graph.frame_loop import LoopCorrectedEstimate
    from gr_graph.loop_closure import RowBuffer

    rng = np.random.default_rng(0)
    rows = [rng.random(20) for _ in range(100)]
    buf = RowBuffer((20,))
    for k, r in enumerate(rows):
        buf.append(r)
        if k in (0, 15, 16, 63, 99):
            np.testing.assert_array_equal(buf.rows(), np.asarray(rows[: k + 1]))
    np.testing.assert_array_equal(buf.rows(40), np.asarray(rows[:40]))
    assert not buf.rows().flags.writeable
    poses = [np.eye(4) for _ in range(70)]
    for k, T in enumerate(poses):
        T[:3, :3] = Rotation.from_rotvec([0.0, 0.0, 0.01 * k]).as_matrix()
        T[:3, 3] = [0.8 * k, 0.1 * k, 0.0]
    est = LoopCorrectedEstimate(poses[:30])
    np.testing.assert_array_equal(est.poses(30), np.asarray(poses[:30]))
    est.odometry_poses.extend(poses[30:])  # the odometry's list grows in place
    est.optimised = np.asarray(poses[:50]) + 1e-3  # an optimisation moved the first 50
    odom = np.asarray(poses)
    corr = est.optimised[49] @ np.linalg.inv(odom[49])
    np.testing.assert_array_equal(est.poses(70), np.concatenate([est.optimised, corr[None] @ odom[50:]]))
    first = est.poses(20)
    first[:] = 0.0
    np.testing.assert_array_equal(est.poses(20), np.asarray(poses[:20]) + 1e-3)
    est.optimised = np.zeros((0, 4, 4))
    mine = est.poses(70)
    mine[:] = 0.0
    np.testing.assert_array_equal(est.poses(70), odom)
