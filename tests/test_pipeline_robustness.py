"""Robustness of the pipeline to its input: dropped frames (the constant-velocity guess follows the
timestamps), runs in which no scan is usable (an error, not a trajectory of guesses) and resuming
into an ``--out`` whose data changed since (refused).

The scenes are small synthetic rooms (planes and columns) seen from poses of a known motion, written
as ``.npy`` scans into a folder, so that the whole command runs in a second or two.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from factors.se3 import exp_se3
from gr_graph.deskew import distort, times_from_azimuth
from gr_graph.config import GraphConfig, OdometryConfig, PreprocessConfig, load_config
from gr_graph.frame_loop import UnusableScansError, check_usable_scans
from gr_graph.odometry import MAX_GUESS_RATIO, VgicpOdometry, guess_time_ratio, time_scaled_motion
from gr_graph.pipeline import data_fingerprint
from gr_graph.preprocess import preprocess_scan
from gr_graph.slam import main

# one frame's motion at 10 Hz: 1.2 m forward, 1.5 deg yaw (12 m/s)
XI_FRAME = np.array([0.0, 0.0, np.radians(1.5), 1.2, 0.0, 0.0])
FRAME_PERIOD = 0.1


def room_points(rng: np.random.Generator, n: int = 30000) -> np.ndarray:
    """World points on the floor, walls and ceiling of a 80 x 40 x 8 m room with four columns."""
    L = np.array([80.0, 40.0, 8.0])
    faces = [(0, 0), (0, 1), (1, 0), (1, 1), (2, 0), (2, 1)]
    face = rng.integers(0, len(faces), n)
    u = rng.uniform(size=(n, 2))
    p = np.zeros((n, 3))
    for f, (ax, val) in enumerate(faces):
        m = face == f
        other = [a for a in range(3) if a != ax]
        p[m, ax] = val * L[ax]
        p[m, other[0]] = u[m, 0] * L[other[0]]
        p[m, other[1]] = u[m, 1] * L[other[1]]
    cols = []
    for cx, cy in ((25.0, 14.0), (33.0, 27.0), (45.0, 12.0), (55.0, 26.0)):
        k = n // 12
        a = rng.uniform(0, 2 * np.pi, k)
        cols.append(np.column_stack([cx + 0.8 * np.cos(a), cy + 0.8 * np.sin(a), rng.uniform(0, 8, k)]))
    return np.concatenate([p, *cols]) - np.array([15.0, 20.0, 1.7])  # the sensor starts at (15, 20, 1.7)


def wavy_street_points(rng: np.random.Generator, n: int = 30000) -> np.ndarray:
    """World points of a street with a wavy road and wavy facades: its shape changes over metres,
    so a registration started a few metres off still slides into place (in the room, whose walls
    are flat, a start 2.4 m off along the room finds no correspondence to pull it there)."""
    m = n // 3
    x = rng.uniform(-20.0, 90.0, (3, m))
    road = np.column_stack([x[0], rng.uniform(-9.0, 9.0, m), 0.4 * np.sin(x[0] / 3.0)])
    left = np.column_stack([x[1], 9.0 + 1.5 * np.sin(x[1] / 4.0), rng.uniform(0.0, 8.0, m)])
    right = np.column_stack([x[2], -9.0 - 1.5 * np.sin(x[2] / 5.0 + 1.0), rng.uniform(0.0, 8.0, m)])
    return np.concatenate([road, left, right]) - np.array([0.0, 0.0, 1.7])


def drive(keep: list[int], seed: int = 0, scene: Callable[[np.random.Generator], np.ndarray] = room_points,
          ) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """Scans (sensor frame, 1 cm noise) of ``scene`` (world points) from poses ``Exp(k XI_FRAME)``, k in
    ``keep``; their ground-truth poses (relative to the first kept one) and timestamps (k x 0.1 s)."""
    rng = np.random.default_rng(seed)
    scans, poses = [], []
    for k in keep:
        T = exp_se3(k * XI_FRAME)
        world = scene(rng)
        local = (world - T[:3, 3]) @ T[:3, :3]
        scans.append((local + rng.normal(scale=0.01, size=local.shape)).astype(np.float32))
        poses.append(T)
    poses = np.linalg.inv(poses[0]) @ np.asarray(poses)
    return scans, poses, np.asarray(keep, np.float64) * FRAME_PERIOD


def write_folder(folder: Path, scans: list[np.ndarray], times: np.ndarray | None = None) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for j, s in enumerate(scans):
        np.save(folder / f"{j:06d}.npy", s)
    if times is not None:
        np.savetxt(folder / "times.txt", times, fmt="%.6f")
    return folder


def run_cli(folder: Path, out: Path, *extra: str) -> int:
    return main([str(folder), "--out", str(out), "--rounds", "0", "--no-memory", "--no-progress", "--no-loops",
                 *extra])


def round_poses(out: Path) -> np.ndarray:
    with np.load(out / "round_0" / "marginals.npz") as z:
        return np.array(z["poses"])


def pose_errors(est: np.ndarray, gt: np.ndarray) -> np.ndarray:
    return np.linalg.norm(est[:, :3, 3] - gt[:, :3, 3], axis=1)


# ----------------------------------------------------------------------------- 1. dropped frames
GAP_KEEP = [0, 1, 2, 3, 7, 8, 9]  # frames 4-6 dropped: 0.4 s, 4.8 m between the 4th and 5th scans


def odometry_over(scans: list[np.ndarray], times: np.ndarray | None) -> VgicpOdometry:
    odo = VgicpOdometry(OdometryConfig(), GraphConfig())
    for i, pts in enumerate(scans):
        dt = None if times is None or i == 0 else float(times[i] - times[i - 1])
        odo.step(preprocess_scan(pts, PreprocessConfig(), index=i), dt)
    return odo


def test_guess_time_ratio_guards():
    assert guess_time_ratio(0.4, 0.1) == pytest.approx(4.0)
    assert guess_time_ratio(0.05, 0.1) == pytest.approx(0.5)
    # unknown, repeated, decreasing or non-finite times: the last motion as it is
    for dt, prev in ((None, 0.1), (0.1, None), (0.0, 0.1), (-0.1, 0.1), (0.1, 0.0), (np.nan, 0.1), (0.1, np.inf)):
        assert guess_time_ratio(dt, prev) == 1.0, (dt, prev)
    # jitter and float rounding of evenly spaced times: exactly 1
    assert guess_time_ratio(0.30000000000000004 - 0.2, 0.1) == 1.0
    assert guess_time_ratio(0.1037, 0.1020) == 1.0
    assert guess_time_ratio(100.0, 0.1) == MAX_GUESS_RATIO


def test_time_scaled_motion_is_the_same_velocity_for_longer():
    delta = exp_se3(XI_FRAME)
    assert time_scaled_motion(delta, 1.0) is delta  # bit-identical when the frames are evenly spaced
    np.testing.assert_allclose(time_scaled_motion(delta, 4.0), np.linalg.matrix_power(delta, 4), atol=1e-12)
    np.testing.assert_allclose(time_scaled_motion(delta, 0.5) @ time_scaled_motion(delta, 0.5), delta, atol=1e-12)


def test_odometry_across_dropped_frames_follows_the_timestamps():
    """With the times the gap's registration is accepted and every pose is right; without them
    (the guess is one frame's motion, 3.6 m short) the gap is not bridged."""
    scans, gt, times = drive(GAP_KEEP)
    odo = odometry_over(scans, times)
    assert all(e.ok for e in odo.edges), [e.reason for e in odo.edges]
    assert pose_errors(np.asarray(odo.poses), gt).max() < 0.05
    # the last motion and the time it spans (the deskewer scales the one by the other)
    assert odo.last_increment_period == pytest.approx(times[-1] - times[-2])
    blind = odometry_over(scans, None)
    assert not blind.edges[3].ok or pose_errors(np.asarray(blind.poses), gt).max() > 1.0


def test_evenly_spaced_times_change_nothing():
    """Float times k x 0.1 (not exactly 0.1 apart) give bit for bit the poses of the run without times."""
    scans, _, times = drive(list(range(5)), seed=1)
    with_times, without = odometry_over(scans, times), odometry_over(scans, None)
    np.testing.assert_array_equal(np.asarray(with_times.poses), np.asarray(without.poses))


def test_recording_that_starts_at_speed_is_registered(caplog):
    """Every other frame kept (2.4 m a frame, more than max_deviation_translation from the identity
    guess of a standing start): each edge is accepted and right; before, all were flagged and the
    trajectory stood still. Once motion is known the divergence test applies again."""
    scans, gt, times = drive([0, 2, 4, 6, 8], scene=wavy_street_points)
    with caplog.at_level(logging.INFO, logger="gr_graph.odometry"):
        odo = odometry_over(scans, times)
    assert all(e.ok for e in odo.edges), [e.reason for e in odo.edges]
    assert pose_errors(np.asarray(odo.poses), gt).max() < 0.05
    assert caplog.text.count("no motion known before") == 1
    # a jump of 6 frames' motion (7.2 m) where 2.4 m a frame is known, without times: flagged
    jump_scans, _, _ = drive([0, 2, 4, 10], scene=wavy_street_points)
    jump = odometry_over(jump_scans, None)
    assert jump.edges[1].ok and not jump.edges[2].ok and "diverged" in jump.edges[2].reason


def test_20hz_sweeps_without_timestamps_file_are_deskewed_as_with_one(tmp_path):
    """Sweeps of 0.05 s (per-point times in ns, 24 m/s) in a folder without times.txt: the sweep
    duration and the frame spacing come from the times' span, and the poses are those of the same
    folder with times.txt (0.05 s apart). Before, frames were taken 0.1 s apart with the times as
    half a sweep: half the motion was deskewed and the error grew 2 mm a frame (14 mm after 8)."""
    scans, gt, _ = drive(list(range(8)), scene=wavy_street_points)
    poses = {}
    for with_times in (True, False):
        folder = tmp_path / f"times_{with_times}"
        folder.mkdir()
        for j, scan in enumerate(scans):
            p = scan.astype(np.float64)
            frac = times_from_azimuth(p)
            moved = distort(p, frac, exp_se3(XI_FRAME))  # one frame's motion during the sweep
            arr = np.zeros(len(p), [("x", "f4"), ("y", "f4"), ("z", "f4"), ("t", "u4")])
            arr["x"], arr["y"], arr["z"] = moved.T
            arr["t"] = np.round(frac * 5e7)
            np.save(folder / f"{j:06d}.npy", arr)
        if with_times:
            np.savetxt(folder / "times.txt", 0.05 * np.arange(len(scans)), fmt="%.3f")
        assert run_cli(folder, tmp_path / f"out_{with_times}") == 0
        poses[with_times] = round_poses(tmp_path / f"out_{with_times}")
    np.testing.assert_allclose(poses[False], poses[True], atol=1e-4)  # span 0.0499 s vs spacing 0.05
    assert pose_errors(poses[False], gt).max() < 0.006


def test_cli_run_across_dropped_frames(tmp_path):
    scans, gt, times = drive(GAP_KEEP)
    folder = write_folder(tmp_path / "gap", scans, times)
    out = tmp_path / "out"
    assert run_cli(folder, out) == 0
    summary = json.loads((out / "round_0" / "round.json").read_text())
    assert summary["n_flagged_odometry_edges"] == 0 and summary["n_unusable_scans"] == 0
    assert pose_errors(round_poses(out), gt).max() < 0.05


# ----------------------------------------------------------------------------- 2. no usable scan
def test_millimetre_scans_are_an_error_not_a_trajectory(tmp_path, capsys):
    scans, _, _ = drive(list(range(4)))
    folder = write_folder(tmp_path / "millimetres", [s * 1000.0 for s in scans])
    out = tmp_path / "out"
    assert run_cli(folder, out) == 2
    err = capsys.readouterr().err
    assert "0 of 4 scans usable" in err and str(folder) in err
    assert "millimetres" in err and "max_range" in err and "min_range" in err
    # nothing that looks like a result
    assert not (out / "metrics.json").exists() and not (out / "poses_kitti.txt").exists()
    assert not (out / "round_0" / "round.json").exists() and not (out / "round_0").exists()


def test_check_usable_scans_counts(caplog):
    cfg = load_config()
    with pytest.raises(UnusableScansError, match="1 of 5 scans usable"):
        check_usable_scans(1, 5, "seq", cfg)
    with pytest.raises(UnusableScansError, match="0 of 1 scans usable"):
        check_usable_scans(0, 1, "seq", cfg)
    with caplog.at_level(logging.WARNING):
        check_usable_scans(1, 1, "seq", cfg)  # a one-frame sequence: its identity pose is right
        check_usable_scans(5, 5, "seq", cfg)
        assert caplog.text == ""
        check_usable_scans(2, 5, "seq", cfg)  # more than half unusable: warned with the counts
    assert [r.levelname for r in caplog.records] == ["WARNING"]
    assert "only 2 of 5 scans usable (3 unusable)" in caplog.text


def test_mostly_unusable_run_warns(tmp_path, caplog):
    scans, _, _ = drive(list(range(5)))
    scans = [scans[0], scans[1]] + [s * 1000.0 for s in scans[2:]]
    folder = write_folder(tmp_path / "mostly_mm", scans)
    with caplog.at_level(logging.WARNING):
        assert run_cli(folder, tmp_path / "out") == 0
    assert "only 2 of 5 scans usable (3 unusable)" in caplog.text
    assert json.loads((tmp_path / "out" / "round_0" / "round.json").read_text())["n_unusable_scans"] == 3


# ----------------------------------------------------------------------------- 3. resume and changed data
def test_resume_refuses_changed_data(tmp_path, capsys, caplog):
    scans, _, _ = drive(list(range(6)))
    other, _, _ = drive(list(range(0, 12, 2)), seed=3)  # twice as fast: another trajectory
    folder = write_folder(tmp_path / "scans", scans)
    out = tmp_path / "out"
    assert run_cli(folder, out) == 0
    rj = out / "round_0" / "round.json"
    first = rj.read_text()
    assert json.loads(first)["data_fingerprint"]["n_frames"] == 6
    assert json.loads((out / "metrics.json").read_text())["data_fingerprint"]["files"] == 6
    capsys.readouterr()
    with caplog.at_level(logging.INFO):  # unchanged data: skipped
        assert run_cli(folder, out) == 0
    assert "skipped (resume)" in caplog.text and rj.read_text() == first

    # the scans replaced (same names), their times kept: refused, nothing rewritten
    for j, s in enumerate(other):
        np.save(folder / f"{j:06d}.npy", s)
        os.utime(folder / f"{j:06d}.npy", ns=(1_000_000_000 * (j + 1),) * 2)
    metrics_before = (out / "metrics.json").read_text()
    assert run_cli(folder, out) == 2
    err = capsys.readouterr().err
    assert "round 0 is finished but was made from other data" in err and "--no-resume" in err and "new --out" in err
    assert rj.read_text() == first and (out / "metrics.json").read_text() == metrics_before

    # one scan deleted: refused, with the counts
    (folder / "000005.npy").unlink()
    assert run_cli(folder, out) == 2
    assert "6 frames then, 5 now" in capsys.readouterr().err
    assert json.loads((out / "metrics.json").read_text())["n_frames"] == 6  # still the finished run's

    # --no-resume recomputes into the same --out: poses, summary and metrics agree
    assert run_cli(folder, out, "--no-resume") == 0
    summary = json.loads(rj.read_text())
    metrics = json.loads((out / "metrics.json").read_text())
    assert summary["n_frames"] == metrics["n_frames"] == len(round_poses(out)) == 5
    assert summary["data_fingerprint"] == metrics["data_fingerprint"]


def test_round_json_without_data_fingerprint_still_resumes(tmp_path, caplog):
    """Runs finished before the data fingerprint existed stay finished."""
    scans, _, _ = drive(list(range(4)))
    folder = write_folder(tmp_path / "scans", scans)
    out = tmp_path / "out"
    assert run_cli(folder, out) == 0
    rj = out / "round_0" / "round.json"
    summary = json.loads(rj.read_text())
    del summary["data_fingerprint"]
    rj.write_text(json.dumps(summary))
    with caplog.at_level(logging.INFO):
        assert run_cli(folder, out) == 0
    assert "no data fingerprint" in caplog.text and "skipped (resume)" in caplog.text


def test_data_fingerprint_of_files_and_of_the_synthetic_world(tmp_path):
    from gr_graph.datasets.folder import FolderSequence
    from gr_graph.datasets.synthetic import SyntheticSequence

    scans, _, _ = drive(list(range(3)))
    folder = write_folder(tmp_path / "scans", scans)
    a = data_fingerprint(FolderSequence(folder))
    assert a["n_frames"] == 3 and a["files"] == 3 and a["digest"] == data_fingerprint(FolderSequence(folder))["digest"]
    os.utime(folder / "000001.npy", ns=(1, 1))  # touched or copied elsewhere: the same data
    assert data_fingerprint(FolderSequence(folder))["digest"] == a["digest"]
    shutil.copytree(folder, tmp_path / "copy")
    assert data_fingerprint(FolderSequence(tmp_path / "copy"))["digest"] == a["digest"]
    same_size = np.load(folder / "000002.npy")
    same_size[0, 0] += 1.0  # another scan of the same size (the last file is sampled)
    np.save(folder / "000002.npy", same_size)
    assert data_fingerprint(FolderSequence(folder))["digest"] != a["digest"]
    np.save(folder / "000002.npy", scans[2])
    assert data_fingerprint(FolderSequence(folder))["digest"] == a["digest"]
    np.savetxt(folder / "times.txt", [0.0, 0.1, 0.3])  # other timestamps: another identity
    b = data_fingerprint(FolderSequence(folder))
    np.savetxt(folder / "times.txt", [0.0, 0.1, 0.2])
    assert data_fingerprint(FolderSequence(folder))["digest"] != b["digest"]
    # the synthetic world has no files: its identity is its configuration (in the round fingerprint)
    syn = SyntheticSequence(seed=0, preset="clean")
    assert data_fingerprint(syn) == {"n_frames": len(syn), "files": None, "digest": None}
    # ... but for one rendered along a given pose file: that file's content is part of its identity
    from gr_graph.trajectory import write_kitti_poses

    path = np.tile(np.eye(4), (40, 1, 1))
    path[:, 0, 3] = np.arange(40) * 0.8
    write_kitti_poses(tmp_path / "path.txt", path)
    along = data_fingerprint(SyntheticSequence(seed=0, preset="clean", trajectory=tmp_path / "path.txt"))
    assert along["files"] is None and along["digest"] is not None
    path[20:, 1, 3] = 0.5  # the same file name, another path
    write_kitti_poses(tmp_path / "path.txt", path)
    assert data_fingerprint(SyntheticSequence(seed=0, preset="clean", trajectory=tmp_path / "path.txt"))["digest"] \
        != along["digest"]


def test_a_round_without_its_memory_is_recomputed_when_a_later_round_needs_it(tmp_path, caplog):
    """``--no-memory`` (round 0 only), then the printed ``--rounds 1`` command in the same --out:
    round 0 was resumed without the memory the training reads (a MemoryFormatError traceback, and
    the same at every rerun); now it is recomputed, logged."""
    from gr_graph.pipeline import SlamPipeline

    scans, _, _ = drive(list(range(4)))
    folder = write_folder(tmp_path / "scans", scans)
    out = tmp_path / "out"
    assert run_cli(folder, out) == 0 and not (out / "round_0" / "memory").exists()
    again = load_config(out / "config.yaml", {"output": {"write_memory": True}})
    assert SlamPipeline(again).finished_round(0) is not None  # round 0 alone: its memory is not read
    learning = load_config(out / "config.yaml", {"output": {"write_memory": True}, "training": {"rounds": 1}})
    pipe = SlamPipeline(learning)
    with caplog.at_level(logging.WARNING):
        assert pipe.finished_round(0) is None
    assert "without its memory" in caplog.text
    (out / "round_0" / "memory").mkdir()
    (out / "round_0" / "memory" / "meta.json").write_text("{}")
    assert pipe.finished_round(0) is not None
    (out / "round_0" / "memory" / "meta.json").unlink()
    pca = load_config(out / "config.yaml", {"output": {"write_memory": False}, "training": {
        "rounds": 1, "covariances": "pca", "acceptance": {"enabled": False}}})
    assert SlamPipeline(pca).finished_round(0) is not None  # no training, no test, no memory: it is not read
    # round 1 writing its memory stores round 0's scans: read (a resumed round 0 without it lost round 1
    # after its SLAM, at every rerun)
    pca_memory = load_config(out / "config.yaml", {"output": {"write_memory": True}, "training": {
        "rounds": 1, "covariances": "pca", "acceptance": {"enabled": False}}})
    assert SlamPipeline(pca_memory).finished_round(0) is None
    metrics = SlamPipeline(pca_memory).run()
    assert metrics["final_round"] == 1 and (out / "round_1" / "memory" / "meta.json").is_file()
    import shutil

    shutil.rmtree(out / "round_0" / "memory")  # pruned after every round finished: nothing to recompute
    assert SlamPipeline(pca_memory).finished_round(0) is not None


def test_a_recomputed_round_without_memory_leaves_no_memory_of_the_earlier_run(tmp_path):
    """Run A writes round 0's memory; run B (another configuration, --no-memory) recomputes round 0;
    run C with B's configuration and a learning round would have resumed round 0 with A's memory."""
    scans, _, _ = drive(list(range(4)))
    folder = write_folder(tmp_path / "scans", scans)
    out = tmp_path / "out"
    assert main([str(folder), "--out", str(out), "--rounds", "0", "--no-progress", "--no-loops"]) == 0
    assert (out / "round_0" / "memory" / "meta.json").is_file()
    assert run_cli(folder, out, "--map-keyframe", "0.1", "1") == 0  # another round 0, without a memory
    assert not (out / "round_0" / "memory").exists()


def test_a_rerun_leaves_no_map_ground_truth_or_rounds_plot_of_the_earlier_run(tmp_path):
    from gr_graph.pipeline import SlamPipeline
    from gr_graph.trajectory import write_kitti_poses

    scans, poses, _ = drive(list(range(4)))
    folder = write_folder(tmp_path / "scans", scans)
    write_kitti_poses(tmp_path / "gt.txt", poses)
    out = tmp_path / "out"
    assert main([str(folder), "--out", str(out), "--poses", str(tmp_path / "gt.txt"), "--no-progress",
                 "--no-loops"]) == 0
    assert (out / "gt_poses_kitti.txt").is_file() and (out / "round_0" / "map.ply").is_file()
    (out / "rounds.png").write_bytes(b"an earlier run's plot")
    cfg = load_config(out / "config.yaml", {"data": {"poses": None}, "output": {"map": {"enabled": False},
                                                                               "resume": False}})
    SlamPipeline(cfg).run()  # no ground truth, no map, one round
    assert not (out / "gt_poses_kitti.txt").exists() and not (out / "round_0" / "map.ply").exists()
    assert not (out / "rounds.png").exists()


def test_recomputing_a_round_drops_the_later_rounds_summaries(tmp_path):
    """A ``--no-resume`` rerun killed after round 0: the earlier run's round 1 (made from another
    round 0) must not be resumed by the next run."""
    scans, _, _ = drive(list(range(4)))
    folder = write_folder(tmp_path / "scans", scans)
    out = tmp_path / "out"
    assert run_cli(folder, out) == 0
    for r in (1, 2, 12):
        (out / f"round_{r}").mkdir()
        (out / f"round_{r}" / "round.json").write_text("{}")
    (out / "round_x").mkdir()
    (out / "round_x" / "round.json").write_text("{}")  # not a round: left alone
    assert run_cli(folder, out, "--no-resume") == 0
    assert (out / "round_0" / "round.json").is_file() and (out / "round_x" / "round.json").is_file()
    assert not [r for r in (1, 2, 12) if (out / f"round_{r}" / "round.json").exists()]


def test_an_out_that_cannot_be_written_is_refused_before_the_data_are_read(tmp_path, capsys):
    scans, _, _ = drive(list(range(2)))
    folder = write_folder(tmp_path / "scans", scans)
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    assert run_cli(folder, blocker) == 2
    assert "a_file is a file, not a folder" in capsys.readouterr().err
    assert run_cli(folder, blocker / "sub" / "out") == 2  # a file on the way
    assert "a_file is a file, not a folder" in capsys.readouterr().err


def test_a_config_file_that_is_not_yaml_is_an_error_naming_it(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("data:\n\tchannels: 16\n")  # a tab in the indentation
    with pytest.raises(ValueError, match="bad.yaml: not valid YAML"):
        load_config(bad)
    assert main(["--config", str(bad), "--dump-config"]) == 2
    assert "bad.yaml: not valid YAML" in capsys.readouterr().err
    assert load_config(None, {"output": {"out_dir": "~/runs/x"}}).output.out_dir == os.path.expanduser("~/runs/x")


def test_a_failed_rerun_leaves_no_final_trajectory_of_the_run_before(tmp_path, monkeypatch):
    from gr_graph.pipeline import SlamPipeline

    scans, _, _ = drive(list(range(4)))
    folder = write_folder(tmp_path / "scans", scans)
    out = tmp_path / "out"
    assert run_cli(folder, out) == 0 and (out / "poses_kitti.txt").is_file()
    pipe = SlamPipeline(load_config(out / "config.yaml", {"output": {"resume": False}}))

    def fails(*args, **kwargs):
        raise RuntimeError("the rerun fails")

    assert (out / "metrics.json").is_file() and (out / "trajectory.png").is_file()
    (out / "rounds.png").write_bytes(b"an earlier run's plot")
    monkeypatch.setattr(pipe, "slam_round", fails)
    with pytest.raises(RuntimeError, match="the rerun fails"):
        pipe.run()
    # nor its metrics and figures, which would be taken for the new config.yaml's
    assert not [n for n in ("poses_kitti.txt", "poses_tum.txt", "metrics.json", "trajectory.png", "rounds.png")
                if (out / n).exists()]
    # a folder of the user's own that no run wrote keeps its files of those names
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "metrics.json").write_text("{}")
    pipe = SlamPipeline(load_config(out / "config.yaml", {"output": {"resume": False, "out_dir": str(mine)}}))
    monkeypatch.setattr(pipe, "slam_round", fails)
    with pytest.raises(RuntimeError, match="the rerun fails"):
        pipe.run()
    assert (mine / "metrics.json").read_text() == "{}"


def test_a_rerun_refused_by_its_checks_keeps_the_earlier_runs_summary(tmp_path, monkeypatch, capsys):
    """--device cuda where torch has none is refused before round 0 (it failed in the trainer, after a
    whole round 0); the earlier run's config, metrics and poses stay as they were."""
    import torch

    scans, _, _ = drive(list(range(4)))
    folder = write_folder(tmp_path / "scans", scans)
    out = tmp_path / "out"
    assert run_cli(folder, out) == 0
    before = {n: (out / n).read_bytes() for n in ("config.yaml", "metrics.json", "poses_kitti.txt")}
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert run_cli(folder, out, "--rounds", "1", "--device", "cuda") == 2
    assert "--device: device 'cuda' asked for, but this torch" in capsys.readouterr().err
    assert {n: (out / n).read_bytes() for n in before} == before
    assert not (out / "round_1").exists()


def test_an_empty_range_window_is_refused_with_the_config(tmp_path):
    with pytest.raises(ValueError, match="min_range 200 m is not below max_range 100 m"):
        load_config(None, {"preprocess": {"min_range": 200.0, "max_range": 100.0}})
    assert load_config(None, {"preprocess": {"min_range": 0.5, "max_range": 1.0}}).preprocess.max_range == 1.0


def test_a_run_without_a_frame_cache_removes_the_one_an_interrupted_run_left(tmp_path):
    """A learning run interrupted in round 0 leaves <out>/frames; a later run into the same --out that keeps no
    cache (0 rounds) removes it, but not a folder of the user's own there."""
    scans, _, _ = drive(list(range(4)))
    folder = write_folder(tmp_path / "scans", scans)
    out = tmp_path / "out"
    cache = out / "frames"
    cache.mkdir(parents=True)
    (cache / "cache.json").write_text('{"key": "k", "n_frames": 4, "name": "x"}')
    (cache / "frame_000001.npz").write_bytes(b"a cached frame")
    assert run_cli(folder, out) == 0
    assert not cache.exists()
    cache.mkdir()
    (cache / "cache.json").write_text("{}")
    (cache / "notes.txt").write_text("mine")
    assert run_cli(folder, out) == 0
    assert (cache / "notes.txt").is_file()


def test_a_map_that_cannot_be_written_does_not_lose_the_round(tmp_path, monkeypatch, caplog):
    import gr_graph.pipeline as pipeline_module

    def no_space(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(pipeline_module, "write_round_map", no_space)
    scans, _, _ = drive(list(range(4)))
    out = tmp_path / "out"
    assert run_cli(write_folder(tmp_path / "scans", scans), out) == 0
    summary = json.loads((out / "round_0" / "round.json").read_text())
    assert "map.ply: OSError" in summary["map"]["error"] and "No space left" in summary["map"]["error"]
    assert (out / "poses_kitti.txt").is_file() and not (out / "round_0" / "map.ply").exists()
    assert any("the map" in r.getMessage() and r.levelname == "ERROR" for r in caplog.records)


def test_rounds_along_a_pose_file_finished_before_its_digest_was_kept_still_resume(tmp_path, caplog):
    """A synthetic world along a pose file: rounds written before the file's poses were hashed (digest None)
    resume; a round whose stored digest differs is refused, saying it is the pose file's poses."""
    from types import SimpleNamespace

    from gr_graph.pipeline import ResumeDataError, SlamPipeline

    now = {"n_frames": 50, "files": None, "digest": "abcdef0123456789"}
    stub = SimpleNamespace(data_fingerprint=now, source_description="the synthetic world", out=tmp_path,
                           round_dir=lambda r: tmp_path / f"round_{r}")
    with caplog.at_level(logging.INFO):
        SlamPipeline.check_round_data(stub, 0, {"data_fingerprint": {"n_frames": 50, "files": None, "digest": None}})
    assert "no digest of the synthetic world's pose file" in caplog.text
    with pytest.raises(ResumeDataError, match="poses of the pose file it is rendered along differ"):
        SlamPipeline.check_round_data(stub, 0, {"data_fingerprint": {**now, "digest": "0" * 16}})
    with pytest.raises(ResumeDataError, match="40 frames then, 50 now"):
        SlamPipeline.check_round_data(stub, 0, {"data_fingerprint": {"n_frames": 40, "files": None, "digest": None}})


def test_a_round_made_before_off_beat_stamps_were_moved_is_not_resumed(tmp_path):
    """Stamps off the sensor's beat enter the data fingerprint (the motion model moves them since
    2026-12-07): a round finished before, on the same files, is refused saying so; regular stamps keep the
    fingerprint of before."""
    from types import SimpleNamespace

    from gr_graph.datasets.folder import FolderSequence
    from gr_graph.pipeline import ResumeDataError, SlamPipeline

    scans, _, _ = drive(list(range(12)))
    times = np.arange(12) * FRAME_PERIOD
    regular = data_fingerprint(FolderSequence(write_folder(tmp_path / "regular", scans, times)))
    assert set(regular) == {"n_frames", "files", "digest"}
    times[5] = times[4] + 0.002  # received 2 ms after frame 4
    now = data_fingerprint(FolderSequence(write_folder(tmp_path / "displaced", scans, times)))
    assert now["stamps_off_beat"] == 1
    stub = SimpleNamespace(data_fingerprint=now, source_description="a folder", out=tmp_path,
                           round_dir=lambda r: tmp_path / f"round_{r}", sequence=SimpleNamespace(stamps_moved_by_s=0.0))
    before = {"data_fingerprint": {k: v for k, v in now.items() if k != "stamps_off_beat"}}
    with pytest.raises(ResumeDataError, match=r"1 of their frame stamps lie off the sensor's beat.*\(0 when the round"):
        SlamPipeline.check_round_data(stub, 0, before)
    SlamPipeline.check_round_data(stub, 0, {"data_fingerprint": now})  # made with the same handling: resumed


def test_a_finished_round_of_data_whose_stamps_are_now_moved_says_so(tmp_path):
    """Folders and bags with per-point times have their stamps moved to the sweeps' middles since 2026-12-06:
    their rounds finished before are other data, and the refusal says why (the user changed nothing)."""
    from types import SimpleNamespace

    from gr_graph.pipeline import ResumeDataError, SlamPipeline

    now = {"n_frames": 50, "files": 50, "digest": "abcdef0123456789"}
    before = {"data_fingerprint": {**now, "digest": "0" * 16}}
    for moved, said in ((0.05, True), (0.0, False)):
        stub = SimpleNamespace(data_fingerprint=now, source_description="a bag", out=tmp_path,
                               round_dir=lambda r: tmp_path / f"round_{r}",
                               sequence=SimpleNamespace(stamps_moved_by_s=moved))
        with pytest.raises(ResumeDataError, match="files differ") as info:
            SlamPipeline.check_round_data(stub, 0, before)
        assert ("moved +0.05 s to the sweeps' middles" in str(info.value)) is said


def test_a_second_run_into_the_same_out_is_refused_while_the_first_holds_it(tmp_path, capsys):
    """One run at a time in an --out (a requeued job beside its first attempt would mix their rounds):
    the second is refused naming the holder, writes nothing, and runs once the lock is free."""
    from gr_graph.folder_lock import folder_lock
    from gr_graph.pipeline import OUT_LOCK

    scans, _, _ = drive(list(range(4)))
    folder = write_folder(tmp_path / "scans", scans)
    out = tmp_path / "out"
    with folder_lock(out / OUT_LOCK, "the first run"):  # another open file: excluded even in this process
        assert run_cli(folder, out) == 2
        assert f"--out {out} is being run by process {os.getpid()}" in capsys.readouterr().err
        assert sorted(p.name for p in out.iterdir()) == [OUT_LOCK]
    assert run_cli(folder, out) == 0 and (out / "poses_kitti.txt").is_file()
