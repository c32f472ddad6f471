"""Trajectory metrics against evo's command-line tool and closed forms."""

from __future__ import annotations

import json
import logging
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gr_graph.metrics import (
    KITTI_LENGTHS,
    DegenerateAlignmentError,
    InsufficientTrajectoryError,
    ate,
    ate_by_axis,
    kitti_devkit_errors,
    kitti_devkit_segments,
    path_distances,
    rpe_translation,
    trajectory_metrics,
)
from gr_graph.trajectory import Trajectory, read_kitti_poses, write_kitti_poses


def drifted_copy(gt: np.ndarray, seed: int = 0) -> np.ndarray:
    """GT with a random-walk drift on translation (world) and rotation (body)."""
    rng = np.random.default_rng(seed)
    K = len(gt)
    dt = np.cumsum(rng.normal(scale=0.02, size=(K, 3)), axis=0)
    drot = Rotation.from_rotvec(np.cumsum(rng.normal(scale=2e-4, size=(K, 3)), axis=0)).as_matrix()
    est = gt.copy()
    est[:, :3, :3] = gt[:, :3, :3] @ drot
    # re-orthonormalise exactly (the 7-digit GT rotations are off by ~1e-7)
    u, _, vt = np.linalg.svd(est[:, :3, :3])
    est[:, :3, :3] = u @ vt
    est[:, :3, 3] += dt
    return est


def run_evo_rpe(ref: Path, est: Path, out: Path, all_pairs: bool) -> dict:
    """Run evo's own CLI (``evo_rpe``) and load the saved result."""
    from evo.tools import file_interface

    exe = shutil.which("evo_rpe")
    cmd = [exe] if exe else [sys.executable, "-c", "import sys; from evo.cli.entry_points import rpe; sys.exit(rpe())"]
    cmd += ["kitti", str(ref), str(est), "--delta", "300", "--delta_unit", "f",
            "--pose_relation", "trans_part", "--save_results", str(out), "--no_warnings"]
    if all_pairs:
        cmd.append("--all_pairs")
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr + proc.stdout
    res = file_interface.load_res_file(str(out))
    return {"stats": res.stats, "error": np.asarray(res.np_arrays["error_array"])}


@pytest.fixture(scope="module")
def route_gt(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The generated route's 4,541 poses as a KITTI ground-truth file (camera frame)."""
    from gr_graph.datasets.base import velo_to_cam_poses
    from gr_graph.datasets.synthetic import rig
    from gr_graph.datasets.synthetic.route import generate_route

    T = velo_to_cam_poses(np.asarray(generate_route(0).T_w_velo), rig.T_cam_velo())
    return write_kitti_poses(tmp_path_factory.mktemp("route") / "00.txt", T)


@pytest.fixture(scope="module")
def gt_poses(route_gt: Path) -> np.ndarray:
    return read_kitti_poses(route_gt)


@pytest.fixture(params=["route", "kitti00_gt"])
def gt_file(request: pytest.FixtureRequest, route_gt: Path) -> Path:
    """A ground-truth file as is: the generated route, and the real KITTI 00 one (its 7-digit,
    slightly non-orthonormal rotations; skipped without ../shared/data)."""
    if request.param == "route":
        return route_gt
    return request.getfixturevalue("kitti00_gt_dir") / "00.txt"


@pytest.mark.parametrize("all_pairs", [False, True], ids=["consecutive", "all_pairs"])
def test_rpe_matches_evo_cli(tmp_path: Path, gt_file: Path, all_pairs: bool) -> None:
    gt = read_kitti_poses(gt_file)
    ref_file = gt_file  # the file as is
    est_file = write_kitti_poses(tmp_path / "est.txt", drifted_copy(gt))
    est = read_kitti_poses(est_file)
    cli = run_evo_rpe(ref_file, est_file, tmp_path / "res.zip", all_pairs)
    ours = rpe_translation(est, gt, delta=300, all_pairs=all_pairs)
    assert ours.n == cli["error"].size == (4241 if all_pairs else 15)
    for key in ("mean", "rmse", "median", "max", "min", "std"):
        assert getattr(ours, key) == pytest.approx(cli["stats"][key], rel=0, abs=1e-9), key
    assert ours.mean > 0.1  # the drift is visible, so the agreement is not 0 == 0


def test_rpe_closed_form_scaled_positions() -> None:
    """Positions scaled by (1+s) about the origin, same rotations: error = s |t_j - t_i|."""
    rng = np.random.default_rng(5)
    K, d, s = 700, 300, 0.03
    ref = np.tile(np.eye(4), (K, 1, 1))
    ref[:, :3, :3] = Rotation.from_rotvec(np.cumsum(rng.normal(scale=0.01, size=(K, 3)), axis=0)).as_matrix()
    ref[:, :3, 3] = np.cumsum(rng.normal(size=(K, 3)), axis=0)
    est = ref.copy()
    est[:, :3, 3] *= 1 + s
    pairs = [(0, 300), (300, 600)]
    expected = np.array([s * np.linalg.norm(ref[j, :3, 3] - ref[i, :3, 3]) for i, j in pairs])
    r = rpe_translation(est, ref, delta=d, all_pairs=False)
    assert r.n == 2
    assert r.mean == pytest.approx(expected.mean(), rel=1e-12)
    assert r.rmse == pytest.approx(np.sqrt(np.mean(expected**2)), rel=1e-12)
    exp_all = np.array([s * np.linalg.norm(ref[i + d, :3, 3] - ref[i, :3, 3]) for i in range(K - d)])
    r_all = rpe_translation(est, ref, delta=d, all_pairs=True)
    assert r_all.n == K - d
    assert r_all.mean == pytest.approx(exp_all.mean(), rel=1e-12)
    assert r_all.max == pytest.approx(exp_all.max(), rel=1e-12)


def test_ate_rigid_and_similarity_copies() -> None:
    rng = np.random.default_rng(6)
    K = 400
    ref = np.tile(np.eye(4), (K, 1, 1))
    ref[:, :3, :3] = Rotation.from_rotvec(np.cumsum(rng.normal(scale=0.02, size=(K, 3)), axis=0)).as_matrix()
    ref[:, :3, 3] = np.cumsum(rng.normal(size=(K, 3)), axis=0) * 5
    G = np.eye(4)
    G[:3, :3] = Rotation.from_rotvec([0.3, -1.0, 2.0]).as_matrix()
    G[:3, 3] = [100.0, -40.0, 7.0]
    est = G @ ref
    assert ate(est, ref, align=True).rmse < 1e-9
    assert ate(est, ref, align=False).rmse > 50
    # constant offset without alignment: every error is |c|
    off = ref.copy()
    off[:, :3, 3] += [3.0, 4.0, 0.0]
    a = ate(off, ref, align=False)
    assert a.mean == pytest.approx(5.0, abs=1e-12) and a.max == pytest.approx(5.0, abs=1e-12)
    # scaled copy: SE(3) alignment leaves an error, Sim(3) removes it and finds the scale
    sim = G @ ref
    sim[:, :3, 3] *= 0.8
    assert ate(sim, ref, align=True).rmse > 1.0
    a7 = ate(sim, ref, align=True, correct_scale=True)
    assert a7.rmse < 1e-9
    assert a7.scale == pytest.approx(1 / 0.8, rel=1e-9)
    # inputs are not modified by the in-place evo alignment
    np.testing.assert_array_equal(sim[:, :3, 3], (G @ ref)[:, :3, 3] * 0.8)


def test_ate_by_axis_splits_height_from_the_plane_in_the_reference_frame() -> None:
    """A flat drive (camera frame: y is height) with an alternating error of 0.3 m in height and
    0.04 m along the world x axis (in the plane), seen through a rigid motion G: after alignment
    the split gives back the two injected sizes (alternating errors are nearly orthogonal to any
    rigid motion), the parts add up to evo's ATE, and a rigid copy has no error in either part."""
    K = 600
    rng = np.random.default_rng(3)
    yaw = np.cumsum(rng.normal(scale=0.01, size=K))
    ref = np.tile(np.eye(4), (K, 1, 1))
    ref[:, :3, :3] = Rotation.from_euler("y", yaw[:, None]).as_matrix()
    step = np.stack([np.sin(yaw), np.zeros(K), np.cos(yaw)], axis=1)
    ref[:, :3, 3] = np.cumsum(step, axis=0)
    sign = np.where(np.arange(K) % 2 == 0, 1.0, -1.0)
    noisy = ref.copy()
    noisy[:, 1, 3] += 0.3 * sign
    noisy[:, 0, 3] += 0.04 * sign[::-1]
    G = np.eye(4)
    G[:3, :3] = Rotation.from_rotvec([0.4, 1.2, -0.7]).as_matrix()
    G[:3, 3] = [20.0, -5.0, 3.0]
    split = ate_by_axis(G @ noisy, ref)
    assert split["vertical_rmse"] == pytest.approx(0.3, rel=1e-2)
    assert split["horizontal_rmse"] == pytest.approx(0.04, rel=2e-2)
    assert split["rmse"] == pytest.approx(ate(G @ noisy, ref).rmse, rel=1e-9)
    assert split["vertical_rmse"] ** 2 + split["horizontal_rmse"] ** 2 == pytest.approx(split["rmse"] ** 2, rel=1e-12)
    # the same trajectory in z-up coordinates (x, z, -y): its height is axis 2
    swap = np.eye(4)
    swap[:3, :3] = [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]  # (x, y, z) -> (x, z, -y)
    z_up = ate_by_axis(swap @ (G @ noisy) @ np.linalg.inv(swap), swap @ ref @ np.linalg.inv(swap), vertical_axis=2)
    assert z_up["vertical_rmse"] == pytest.approx(split["vertical_rmse"], rel=1e-6)
    rigid = ate_by_axis(G @ ref, ref)
    assert rigid["vertical_rmse"] < 1e-9 and rigid["horizontal_rmse"] < 1e-9
    with pytest.raises(ValueError, match="vertical_axis"):
        ate_by_axis(ref, ref, vertical_axis=3)
    with pytest.raises(InsufficientTrajectoryError):
        ate_by_axis(ref[:2], ref[:2])


# ----------------------------------------------------------------------------- KITTI devkit


def straight_line(K: int, spacing: float = 1.0) -> np.ndarray:
    """Camera-frame poses driving along +z, ``spacing`` metres a frame."""
    T = np.tile(np.eye(4), (K, 1, 1))
    T[:, 2, 3] = np.arange(K) * spacing
    return T


def test_path_distances_of_poses_and_of_positions() -> None:
    """The cumulative path of a straight line 0.5 m a frame, from poses and from their positions alike."""
    T = straight_line(5, spacing=0.5)
    np.testing.assert_allclose(path_distances(T), [0.0, 0.5, 1.0, 1.5, 2.0])
    np.testing.assert_array_equal(path_distances(T[:, :3, 3]), path_distances(T))


def devkit_segment_set(K: int, step: int = 10) -> list[tuple[int, float]]:
    """(first, L) of every segment for a 1 m-spaced straight line: last = first + L + 1."""
    return [(f, L) for f in range(0, K, step) for L in KITTI_LENGTHS if f + L + 1 <= K - 1]


def test_kitti_devkit_constant_scale_error() -> None:
    K, s = 1200, 0.02
    ref = straight_line(K)
    est = straight_line(K, 1 + s)
    segs = devkit_segment_set(K)
    # each segment spans L + 1 m of GT (first frame whose distance *exceeds* L), so the
    # translation error is s (L + 1), divided by the nominal L
    expected_t = 100 * np.mean([s * (L + 1) / L for _, L in segs])
    t_err, r_err = kitti_devkit_errors(est, ref)
    assert kitti_devkit_segments(est, ref).first.size == len(segs)
    assert t_err == pytest.approx(expected_t, rel=1e-12)
    assert t_err == pytest.approx(100 * s, rel=0.01)  # ~ s %
    assert r_err == 0.0


def test_kitti_devkit_constant_yaw_rate_bias() -> None:
    """est integrates the true motion (1 m forward) plus a yaw of b rad every frame."""
    K, b = 1200, 1e-4
    ref = straight_line(K)
    step = np.eye(4)
    step[:3, :3] = Rotation.from_rotvec([0.0, b, 0.0]).as_matrix()  # yaw about camera y
    step[2, 3] = 1.0
    est = np.empty_like(ref)
    est[0] = np.eye(4)
    for k in range(1, K):
        est[k] = est[k - 1] @ step
    segs = devkit_segment_set(K)
    n = np.array([L + 1 for _, L in segs])  # frames between first and last
    Ls = np.array([L for _, L in segs])
    # rotation error of a segment: n b
    expected_r = np.degrees(np.mean(n * b / Ls)) * 100
    # translation: est moved along an arc, sum_k (sin kb, 0, cos kb), GT n along z
    z = (1 - np.exp(1j * n * b)) / (1 - np.exp(1j * b))  # sum_{k<n} e^{ikb} = cos + i sin
    chord = np.stack([z.imag, np.zeros_like(n, dtype=float), z.real], axis=1)
    t_seg = np.linalg.norm(chord - np.stack([0 * n, 0 * n, n], axis=1), axis=1)
    expected_t = 100 * np.mean(t_seg / Ls)
    t_err, r_err = kitti_devkit_errors(est, ref)
    assert r_err == pytest.approx(expected_r, rel=1e-9)
    assert r_err == pytest.approx(np.degrees(b) * 100, rel=0.01)  # ~ deg per metre * 100
    assert t_err == pytest.approx(expected_t, rel=1e-7)


def test_kitti_devkit_identity_and_a_drive(gt_poses: np.ndarray) -> None:
    t, r = kitti_devkit_errors(gt_poses, gt_poses)
    assert t < 1e-12 and r < 1e-12
    # a rigid change of the world frame does not change any relative motion
    G = np.eye(4)
    G[:3, :3] = Rotation.from_rotvec([0.1, 0.2, -0.3]).as_matrix()
    G[:3, 3] = [5, 6, 7]
    t, r = kitti_devkit_errors(G @ gt_poses, gt_poses)
    assert t < 1e-9 and r < 1e-6
    est = drifted_copy(gt_poses)
    t, r = kitti_devkit_errors(est, gt_poses)
    assert 0.01 < t < 10 and 0.01 < r < 10


def test_kitti_devkit_matches_kiss_icp_port(gt_poses: np.ndarray) -> None:
    """Cross-check against an independent C++ port of the devkit (KISS-ICP's, float32 output)."""
    kiss_metrics = pytest.importorskip("kiss_icp.metrics", reason="kiss-icp (bench extra) not installed")
    for est in (drifted_copy(gt_poses), drifted_copy(gt_poses, seed=1)):
        t_ref, r_ref_deg_per_m = kiss_metrics.sequence_error(gt_poses, est)
        t, r = kitti_devkit_errors(est, gt_poses)
        assert t == pytest.approx(t_ref, rel=1e-5)
        # KISS-ICP reports deg / m and loses ~1e-4 relative in float32 acos near 1
        assert r == pytest.approx(100 * r_ref_deg_per_m, rel=2e-3)


def test_kitti_devkit_too_short() -> None:
    with pytest.raises(InsufficientTrajectoryError, match="shorter than the shortest segment"):
        kitti_devkit_errors(straight_line(50), straight_line(50))


# ----------------------------------------------------------------------------- bundle


def arc(K: int, yaw_rate: float = 2e-3) -> np.ndarray:
    """1 m a frame forward while turning at a constant yaw rate (a circle arc)."""
    step = np.eye(4)
    step[:3, :3] = Rotation.from_rotvec([0.0, yaw_rate, 0.0]).as_matrix()
    step[2, 3] = 1.0
    T = np.empty((K, 4, 4))
    T[0] = np.eye(4)
    for k in range(1, K):
        T[k] = T[k - 1] @ step
    return T


def test_trajectory_metrics_bundle() -> None:
    rng = np.random.default_rng(7)
    K = 800
    ref = arc(K)
    est = ref.copy()
    est[:, :3, 3] += np.cumsum(rng.normal(scale=0.01, size=(K, 3)), axis=0)
    m = trajectory_metrics(est, Trajectory.from_poses(ref))
    json.dumps(m)  # serialisable
    c = rpe_translation(est, ref, 300, all_pairs=False)
    a = rpe_translation(est, ref, 300, all_pairs=True)
    assert m["n_frames"] == K
    assert m["rpe300_consecutive_mean"] == c.mean and m["rpe300_consecutive_rmse"] == c.rmse
    assert m["rpe300_consecutive_n"] == 2
    assert m["rpe300_all_pairs_mean"] == a.mean and m["rpe300_all_pairs_rmse"] == a.rmse
    assert m["rpe300_all_pairs_n"] == 500
    assert m["ate_rmse"] == ate(est, ref).rmse
    t, r = kitti_devkit_errors(est, ref)
    assert m["kitti_t_err_percent"] == t and m["kitti_r_err_deg_per_100m"] == r
    assert m["kitti_n_segments"] > 0


def test_trajectory_metrics_short_and_mismatched(caplog: pytest.LogCaptureFixture) -> None:
    ref = straight_line(60)
    est = ref.copy()
    est[:, 0, 3] += 0.1
    with caplog.at_level(logging.WARNING, logger="gr_graph.metrics"):
        m = trajectory_metrics(est, ref, delta=300)
    assert m["rpe300_consecutive_mean"] is None and m["rpe300_all_pairs_rmse"] is None
    assert m["kitti_t_err_percent"] is None and m["kitti_n_segments"] == 0
    # a straight line leaves the rotation about it undetermined, not the error: the shift aligns away;
    # the scale is undetermined
    assert m["ate_rmse"] == pytest.approx(0.0, abs=1e-9) and m["ate_sim3_rmse"] is None
    assert "needs at least 301 poses, got 60" in caplog.text
    assert "shorter than 100 m" in caplog.text
    assert "collinear" in caplog.text
    json.dumps(m)
    # on a curved path of the same length the ATE exists; a constant offset aligns away
    curved = arc(60, 0.05)
    shifted = curved.copy()
    shifted[:, :3, 3] += [0.1, -0.2, 0.3]
    m = trajectory_metrics(shifted, curved, delta=300)
    assert m["ate_rmse"] == pytest.approx(0.0, abs=1e-9)
    assert m["rpe300_consecutive_mean"] is None
    with pytest.raises(InsufficientTrajectoryError):
        rpe_translation(est, ref, delta=300)
    with pytest.raises(ValueError, match="est has 59 poses but ref has 60"):
        trajectory_metrics(est[:-1], ref)
    with pytest.raises(ValueError, match="non-finite"):
        bad = est.copy()
        bad[3, 0, 3] = np.inf
        rpe_translation(bad, ref, delta=10)


def test_timed_trajectories_are_paired_only_where_their_times_agree() -> None:
    """Two timed trajectories of equal length but shifted times (an estimate of frames 5.. against a
    reference of frames 0..) are refused, not paired by index; equal times, or pose arrays, are paired."""
    ref_poses = arc(120, 0.05)
    times = 0.1 * np.arange(120)
    ref = Trajectory(times, ref_poses)
    same = Trajectory(times + 2e-4, ref_poses.copy())  # timestamp jitter below the tolerance
    assert ate(same, ref).rmse == pytest.approx(0.0, abs=1e-9)
    shifted = Trajectory(times + 0.5, ref_poses.copy())
    with pytest.raises(ValueError, match=r"timestamps differ by up to 0.5 s \(first at pose 0"):
        ate(shifted, ref)
    with pytest.raises(ValueError, match="timestamps differ"):
        trajectory_metrics(shifted, ref, delta=10)
    assert ate(shifted.poses, ref.poses).rmse == pytest.approx(0.0, abs=1e-9)  # arrays: the caller paired them


@pytest.mark.parametrize("which", ["straight estimate", "stationary estimate", "straight reference"])
def test_ate_of_a_straight_or_stationary_path_is_the_best_rigid_fit(which: str) -> None:
    """evo refuses rank-deficient alignments; a failed run (no motion, or constant velocity) still has an
    ATE: the minimum over rigid transforms, checked against a brute-force search."""
    from scipy.optimize import minimize

    K = 40
    t = np.arange(K, dtype=float)
    curved = np.tile(np.eye(4), (K, 1, 1))
    curved[:, :3, 3] = np.c_[t, 0.02 * t**2, 0.3 * np.sin(t / 4)]
    flat = np.tile(np.eye(4), (K, 1, 1))
    flat[:, :3, 3] = np.c_[1.05 * t, 0 * t, 0 * t] if which != "stationary estimate" else 3.0
    est, ref = (curved, flat) if which == "straight reference" else (flat, curved)

    def rmse(x: np.ndarray) -> float:
        R = Rotation.from_rotvec(x[:3]).as_matrix()
        d = est[:, :3, 3] @ R.T + x[3:] - ref[:, :3, 3]
        return float(np.sqrt(np.mean(np.sum(d**2, axis=1))))

    best = min(minimize(rmse, np.r_[np.random.default_rng(i).normal(size=3), 0, 0, 0], method="Powell",
                        options={"xtol": 1e-10, "ftol": 1e-13, "maxfev": 40000}).fun for i in range(6))
    assert ate(est, ref).rmse == pytest.approx(best, rel=1e-6)
    assert ate_by_axis(est, ref)["rmse"] == pytest.approx(best, rel=1e-6)
    with pytest.raises(DegenerateAlignmentError, match="positions are collinear or coincident"):
        ate(est, ref, correct_scale=True)
