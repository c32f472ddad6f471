"""VGICP odometry front end: against small_gicp run directly, synthetic ground truth, failures."""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np
import pytest
import small_gicp

from gr_graph.config import GraphConfig, OdometryConfig, PreprocessConfig
from gr_graph.odometry import VgicpOdometry, check_registration, scaled_information
from gr_graph.preprocess import ScanError, clean_points, preprocess_scan


def run_odometry(frames, ocfg=None, pcfg=None):
    pcfg = pcfg or PreprocessConfig()
    odo = VgicpOdometry(ocfg or OdometryConfig(), GraphConfig())
    for i, pts in enumerate(frames):
        odo.step(preprocess_scan(pts, pcfg, index=i))
    return odo


@pytest.fixture(scope="module")
def real_frames(kitti_root):
    from gr_graph.datasets.registry import open_sequence

    seq, _ = open_sequence("00", data_root=kitti_root)
    return [f.points for f in seq]


@pytest.mark.parametrize("mode", ["map", "scan"])
def test_real_kitti_matches_small_gicp_directly(real_frames, mode):
    """Edge (1, 0) against small_gicp.align on the raw scans (GICP, 0.25 m): within 3 cm / 0.2 deg.

    The official GT is a constant-velocity extrapolation here (0.86 m/frame); the real motion
    is ~0.69 m, which is what both registrations must find.
    """
    odo = run_odometry(real_frames[:2], OdometryConfig(mode=mode))
    ref = small_gicp.align(real_frames[0], real_frames[1], registration_type="GICP",
                           downsampling_resolution=0.25, max_correspondence_distance=1.0, num_threads=1)
    T_ref = np.asarray(ref.T_target_source)
    T = odo.edges[0].T
    assert odo.edges[0].ok
    assert np.linalg.norm(T[:3, 3] - T_ref[:3, 3]) < 0.03
    dR = T_ref[:3, :3].T @ T[:3, :3]
    assert np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))) < 0.2
    assert 0.64 < np.linalg.norm(T[:3, 3]) < 0.74  # not the GT's 0.86


def test_real_kitti_all_edges_ok_and_consistent(real_frames):
    odo = run_odometry(real_frames)
    assert len(odo.edges) == 5 and all(e.ok for e in odo.edges)
    steps = [np.linalg.norm(e.T[:3, 3]) for e in odo.edges]
    assert all(0.6 < s < 0.8 for s in steps)
    for e in odo.edges:
        assert e.inlier_ratio > 0.8
        w = np.linalg.eigvalsh(e.information)
        assert np.all(w > 0) and np.allclose(e.information, e.information.T)
        # edge pose composes the odometry poses: T_k = T_l T̂_kl
        np.testing.assert_allclose(odo.poses[e.target] @ e.T, odo.poses[e.source], atol=1e-9)


def test_synthetic_odometry_against_renderer_ground_truth():
    from gr_graph.datasets.synthetic import SyntheticSequence

    seq = SyntheticSequence(seed=0, preset="clean")
    idx = range(200, 230)
    odo = run_odometry([seq[i].points for i in idx])
    gt = seq.gt_poses[list(idx)]
    for e in odo.edges:
        T_gt = np.linalg.inv(gt[e.target]) @ gt[e.source]
        assert np.linalg.norm(e.T[:3, 3] - T_gt[:3, 3]) < 0.05, e
    drift = np.linalg.norm((np.linalg.inv(gt[0]) @ gt[-1])[:3, 3] - odo.poses[-1][:3, 3])
    assert drift < 0.3  # over ~25 m


def _box_scan(rng, n=20000, shift=np.zeros(3)):
    """Points on the walls/floor of a 40 x 30 x 8 m box seen from inside (enough structure)."""
    u = rng.uniform(size=(n, 2))
    face = rng.integers(0, 5, n)
    p = np.zeros((n, 3))
    L = np.array([40.0, 30.0, 8.0])
    for f, (ax, val) in enumerate([(0, 0), (0, 1), (1, 0), (1, 1), (2, 0)]):
        m = face == f
        other = [a for a in range(3) if a != ax]
        p[m, ax] = val * L[ax]
        p[m, other[0]] = u[m, 0] * L[other[0]]
        p[m, other[1]] = u[m, 1] * L[other[1]]
    # an extra column for rotation/translation observability
    m = rng.uniform(size=n) < 0.2
    p[m] = np.column_stack([12 + rng.uniform(0, 1, m.sum()), 9 + rng.uniform(0, 1, m.sum()), rng.uniform(0, 8, m.sum())])
    return p - np.array([20.0, 15.0, 1.7]) - shift


def test_empty_scan_gets_logged_fallback(caplog):
    rng = np.random.default_rng(0)
    frames = [_box_scan(rng, shift=np.array([0.5 * i, 0, 0])) for i in range(3)]
    frames.insert(2, np.zeros((0, 3)))
    with caplog.at_level(logging.WARNING):
        odo = run_odometry(frames)
    bad = odo.edges[1]
    assert not bad.ok and "unusable" in bad.reason
    assert "constant-velocity" in caplog.text
    # the fallback is the previous motion (constant velocity)
    np.testing.assert_allclose(bad.T, odo.edges[0].T, atol=1e-12)
    # fallback information is the configured weak one
    np.testing.assert_allclose(np.diag(bad.information), 1 / np.array(GraphConfig().fallback_sigmas) ** 2)


def test_nonfinite_points_are_dropped_and_logged(caplog):
    rng = np.random.default_rng(1)
    p = _box_scan(rng)
    p[:50] = np.nan
    with caplog.at_level(logging.WARNING):
        clean, n_bad = clean_points(p, PreprocessConfig(), index=7)
    assert n_bad == 50 and np.isfinite(clean).all()
    assert "scan 7: dropped 50 non-finite points" in caplog.text


def test_wrong_shape_is_a_clear_error():
    with pytest.raises(ScanError, match=r"scan 3: points must be \(N, 3\)"):
        preprocess_scan(np.zeros((10, 2)), PreprocessConfig(), index=3)


def test_unrelated_scan_is_flagged_not_kept(caplog):
    """A scan of a different place: the registration fails its checks and the edge is flagged."""
    rng = np.random.default_rng(2)
    frames = [_box_scan(rng, shift=np.array([0.5 * i, 0, 0])) for i in range(3)]
    frames.append(rng.uniform(-50, 50, size=(20000, 3)) * np.array([1, 1, 0.05]) + np.array([0, 0, 30]))
    with caplog.at_level(logging.WARNING):
        odo = run_odometry(frames)
    assert [e.ok for e in odo.edges] == [True, True, False]
    assert odo.edges[-1].reason


def test_check_registration_reasons():
    I = np.eye(4)
    T = np.eye(4)
    T[0, 3] = 3.0
    assert check_registration(I, I, 0.9, 0.3, 2.0, 15.0) == ""
    assert "diverged" in check_registration(T, I, 0.9, 0.3, 2.0, 15.0)
    assert "inlier ratio" in check_registration(I, I, 0.1, 0.3, 2.0, 15.0)
    assert "non-finite" in check_registration(I * np.nan, I, 0.9, 0.3, 2.0, 15.0)


def test_scaled_information_closed_form():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(6, 6))
    H = A @ A.T + 6 * np.eye(6)
    n, err = 1000, 12.5
    sigma2 = 2 * err / (3 * n - 6)
    np.testing.assert_allclose(scaled_information(H, err, n, 0.5), 0.5 * H / sigma2)


def test_map_keyframe_thresholds_decide_which_scans_enter_the_map():
    """A scan closer than both thresholds to the last scan that entered the map stays out (counted);
    the first scan always enters; with the defaults (0 and 0) every scan does."""
    scan = preprocess_scan(_box_scan(np.random.default_rng(3)), PreprocessConfig(), index=0)

    def pose(x, yaw_deg=0.0):
        T = np.eye(4)
        c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
        T[:2, :2] = [[c, -s], [s, c]]
        T[0, 3] = x
        return T

    # stand, creep 5 cm, 12 cm (>= 0.1 m from 0: in), stand, 0.19 m (0.07 from 0.12: out), turn 1.2 deg (in)
    poses = [pose(0), pose(0), pose(0.05), pose(0.12), pose(0.12), pose(0.19), pose(0.19, 1.2)]

    def entered(cfg):
        """The odometry after inserting the scan at every pose, and whether each insertion entered the map."""
        odo = VgicpOdometry(cfg, GraphConfig())
        got = []
        for T in poses:
            before = odo.scans_left_out_of_map
            odo._insert(scan, T)
            got.append(odo.scans_left_out_of_map == before)
        return odo, got

    assert entered(OdometryConfig())[1] == [True] * 7
    odo, got = entered(OdometryConfig(map_keyframe_translation=0.1, map_keyframe_rotation_deg=1.0))
    assert got == [True, False, False, True, False, False, True]
    odo.poses = poses  # a rebuilt map counts again, from its first scan
    odo.rebuild_map([scan] * len(poses))
    assert odo.scans_left_out_of_map == 4
    np.testing.assert_array_equal(odo._last_map_pose, poses[-1])
    # one threshold 0: that test is left out, the other decides alone
    for t, r, expected in ((0.1, 0.0, [True, False, False, True, False, False, False]),
                           (0.0, 1.0, [True, False, False, False, False, False, True])):
        assert entered(OdometryConfig(map_keyframe_translation=t, map_keyframe_rotation_deg=r))[1] == expected, (t, r)
    # 'scan' mode keeps only the previous scan: nothing is left out
    odo, _ = entered(OdometryConfig(mode="scan", map_keyframe_translation=0.1, map_keyframe_rotation_deg=1.0))
    assert odo.scans_left_out_of_map == 0


def test_map_keyframes_follow_the_pitch_at_motion_start():
    """The generated route's car stands ~11 s at a stop line (frames ~348-458) and pitches nose-up
    as it pulls away (squat): -4.85 mrad between frames 440 and 471. With every scan in the map,
    the 16-ring scans of the stop fill it with one ring pattern and the odometry follows the pattern
    (a third of the pitch found, measured: -1.6 mrad); with map keyframes the map keeps the scans of
    the approach and the pitch is found (-5.0 mrad)."""
    import gtsam

    from gr_graph.datasets.synthetic import SyntheticSequence

    seq = SyntheticSequence(seed=0, n_rings=16, preset="clean")
    idx = list(range(320, 440, 4)) + list(range(440, 472))
    frames = [seq[i].points for i in idx]
    gt = seq.gt_poses[idx]
    start = idx.index(440)
    assert np.linalg.norm(gt[start, :3, 3] - gt[start - 10, :3, 3]) < 1e-3  # standing since frame 400
    pitch_gt = gtsam.Pose3.Logmap(gtsam.Pose3(np.linalg.inv(gt[start]) @ gt[-1]))[1]
    assert pitch_gt < -4e-3

    def pitch_error(ocfg):
        odo = run_odometry(frames, ocfg)
        assert all(e.ok for e in odo.edges)
        est = gtsam.Pose3.Logmap(gtsam.Pose3(np.linalg.inv(odo.poses[start]) @ odo.poses[-1]))[1]
        return abs(est - pitch_gt), odo.scans_left_out_of_map

    every, left_out_every = pitch_error(OdometryConfig())
    keyframes, left_out = pitch_error(OdometryConfig(map_keyframe_translation=0.1, map_keyframe_rotation_deg=1.0))
    assert left_out_every == 0 and left_out > 40
    assert every > 2e-3  # the failure the option is for
    assert keyframes < 1e-3 and keyframes < 0.2 * every


def test_registration_at_its_iteration_limit_is_kept_and_marked_not_converged():
    """An edge whose registration stops at ``max_iterations`` before converging passes the other
    tests here (kept, as before) but says so (``converged`` False), and the round counts it."""
    from gr_graph.frame_loop import not_converged_counts

    rng = np.random.default_rng(2)
    frames = [_box_scan(rng, shift=np.array([0.5 * i, 0, 0])) for i in range(3)]
    cut = run_odometry(frames, OdometryConfig(max_iterations=1))
    full = run_odometry(frames, OdometryConfig())
    assert all(e.ok for e in cut.edges + full.edges)
    # edge (2, 1) starts from the constant-velocity guess: converged within the default 30 iterations, not in 1
    assert full.edges[1].converged and not cut.edges[1].converged
    assert np.linalg.norm(full.edges[1].T[:3, 3] - [0.5, 0, 0]) < 0.01
    assert not_converged_counts(cut.edges) == {"odometry": 2, "loop": 0}  # (edge (1, 0) from identity: neither)
    # failed edges carry no registration and are not counted
    failed = replace(cut.edges[1], ok=False)
    assert not_converged_counts([failed]) == {"odometry": 0, "loop": 0}
