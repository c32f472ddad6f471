"""KITTI / TUM trajectory I/O: round trips, the real KITTI 00 ground truth, clear errors."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gr_graph.trajectory import (
    Trajectory,
    TrajectoryFormatError,
    read_kitti_poses,
    read_kitti_times,
    read_tum_poses,
    write_kitti_poses,
    write_tum_poses,
)


def random_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.random(n, random_state=rng).as_matrix()
    T[:, :3, 3] = rng.normal(scale=300.0, size=(n, 3))
    return T


def test_kitti_round_trip_is_bit_exact(tmp_path: Path) -> None:
    poses = random_poses(50)
    poses[3, :3, 3] = [1e-300, -5e-324, 1.2345678901234567e17]  # extreme magnitudes
    path = write_kitti_poses(tmp_path / "sub" / "est.txt", poses)
    back = read_kitti_poses(path)
    assert back.dtype == np.float64 and back.shape == (50, 4, 4)
    np.testing.assert_array_equal(back, poses)
    # 12 fields a line, no trailing delimiter (evo's reader is strict about that)
    lines = path.read_text().splitlines()
    assert len(lines) == 50 and all(len(ln.split(" ")) == 12 for ln in lines)
    # no temp files left behind by the atomic write
    assert sorted(p.name for p in path.parent.iterdir()) == ["est.txt"]


def test_kitti_file_readable_by_evo(tmp_path: Path) -> None:
    from evo.tools import file_interface

    poses = random_poses(7, seed=1)
    path = write_kitti_poses(tmp_path / "p.txt", poses)
    evo_path = file_interface.read_kitti_poses_file(str(path))
    np.testing.assert_array_equal(np.asarray(evo_path.poses_se3), poses)


def test_tum_round_trip(tmp_path: Path) -> None:
    poses = random_poses(40, seed=2)
    ts = 1.6e9 + np.cumsum(np.random.default_rng(3).uniform(0.05, 0.15, 40))
    path = write_tum_poses(tmp_path / "est.tum", ts, poses)
    ts2, poses2 = read_tum_poses(path)
    np.testing.assert_array_equal(ts2, ts)
    np.testing.assert_allclose(poses2, poses, rtol=0, atol=1e-12 * max(1.0, np.abs(poses).max()))
    np.testing.assert_array_equal(poses2[:, :3, 3], poses[:, :3, 3])
    np.testing.assert_allclose(poses2[:, :3, :3], poses[:, :3, :3], rtol=0, atol=1e-14)
    # format is t x y z qx qy qz qw, readable by evo with the same result
    from evo.tools import file_interface

    evo_traj = file_interface.read_tum_trajectory_file(str(path))
    np.testing.assert_array_equal(evo_traj.timestamps, ts)
    np.testing.assert_allclose(np.asarray(evo_traj.poses_se3), poses, rtol=0, atol=1e-9)


def test_tum_quaternion_convention(tmp_path: Path) -> None:
    """A 90 deg yaw must be written as qz = qw = sqrt(1/2) (scalar last)."""
    T = np.eye(4)[None].copy()
    T[0, :3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    T[0, :3, 3] = [1, 2, 3]
    path = write_tum_poses(tmp_path / "a.tum", np.array([5.0]), T)
    vals = np.array(path.read_text().split(), dtype=float)
    np.testing.assert_allclose(vals, [5, 1, 2, 3, 0, 0, np.sqrt(0.5), np.sqrt(0.5)], atol=1e-15)


def test_trajectory_dataclass_and_evo(tmp_path: Path) -> None:
    poses = random_poses(10, seed=4)
    tr = Trajectory.from_poses(poses, dt=0.1)
    np.testing.assert_allclose(tr.timestamps, np.arange(10) * 0.1)
    evo_traj = tr.to_evo()
    back = Trajectory.from_evo(evo_traj)
    np.testing.assert_array_equal(back.poses, poses)
    np.testing.assert_array_equal(back.timestamps, tr.timestamps)
    tr.write_tum(tmp_path / "t.tum")
    again = Trajectory.read_tum(tmp_path / "t.tum")
    np.testing.assert_allclose(again.poses, poses, atol=1e-9)
    tr.write_kitti(tmp_path / "k.txt")
    (tmp_path / "times.txt").write_text("\n".join(f"{t:.6e}" for t in tr.timestamps) + "\n")
    k = Trajectory.read_kitti(tmp_path / "k.txt", tmp_path / "times.txt")
    np.testing.assert_array_equal(k.poses, poses)
    with pytest.raises(ValueError, match="strictly increasing"):
        Trajectory(np.zeros(10), poses)


def test_real_kitti00_ground_truth(kitti00_gt_dir: Path) -> None:
    poses = read_kitti_poses(kitti00_gt_dir / "00.txt")
    assert poses.shape == (4541, 4, 4)
    R = poses[:, :3, :3]
    gram = np.einsum("kji,kjl->kil", R, R)
    assert np.abs(gram - np.eye(3)).max() < 1e-6
    assert np.abs(np.linalg.det(R) - 1).max() < 1e-6
    np.testing.assert_array_equal(poses[:, 3], np.tile([0, 0, 0, 1.0], (4541, 1)))
    # first pose is the identity, frame 1 is 0.8587 m ahead along the camera z axis
    np.testing.assert_allclose(poses[0], np.eye(4), atol=1e-6)
    assert poses[1, 2, 3] == pytest.approx(8.586941e-01, abs=1e-12)
    times = read_kitti_times(kitti00_gt_dir / "times.txt")
    assert times.shape == (4541,)
    tr = Trajectory.read_kitti(kitti00_gt_dir / "00.txt", kitti00_gt_dir / "times.txt")
    assert len(tr) == 4541


# ----------------------------------------------------------------------------- errors

GOOD = "1 0 0 0 0 1 0 0 0 0 1 0"


@pytest.mark.parametrize(
    ("bad_line", "message"),
    [
        ("1 0 0 0 0 1 0 0 0 0 1", "need 12 numbers, got 11"),
        ("1 0 0 0 0 1 0 0 0 0 1 0 7", "need 12 numbers, got 13"),
        ("1 0 0 0 0 1 0 abc 0 0 1 0", "non-numeric value 'abc'"),
        ("1 0 0 nan 0 1 0 0 0 0 1 0", "non-finite"),
        ("1 0 0 0 0 1 0 0 0 0 inf 0", "non-finite"),
        ("1 0 0 0 0 1.01 0 0 0 0 1 0", "not orthonormal"),
        ("1 0 0 0 0 -1 0 0 0 0 1 0", "not orthonormal"),  # reflection, det = -1
    ],
)
def test_kitti_bad_rows_name_file_and_line(tmp_path: Path, bad_line: str, message: str) -> None:
    path = tmp_path / "bad.txt"
    path.write_text(f"# comment\n{GOOD}\n\n{GOOD}\n{bad_line}\n{GOOD}\n")
    with pytest.raises(TrajectoryFormatError, match=message) as info:
        read_kitti_poses(path)
    assert f"{path}:5:" in str(info.value)
    assert isinstance(info.value, ValueError)


def test_kitti_missing_and_empty(tmp_path: Path) -> None:
    with pytest.raises(TrajectoryFormatError, match="not found"):
        read_kitti_poses(tmp_path / "nope.txt")
    (tmp_path / "empty.txt").write_text("# only a comment\n\n")
    with pytest.raises(TrajectoryFormatError, match="empty"):
        read_kitti_poses(tmp_path / "empty.txt")


def test_kitti_rotation_tolerance_is_adjustable(tmp_path: Path) -> None:
    path = tmp_path / "loose.txt"
    path.write_text("1 0 0 0 0 1.001 0 0 0 0 1 0\n")
    with pytest.raises(TrajectoryFormatError, match=":1:"):
        read_kitti_poses(path)
    assert read_kitti_poses(path, rot_tol=1e-2)[0, 1, 1] == 1.001


TUM_GOOD = "0.0 1 2 3 0 0 0 1"


@pytest.mark.parametrize(
    ("bad_line", "message"),
    [
        ("0.2 1 2 3 0 0 0", "need 8 numbers, got 7"),
        ("0.2 1 2 x 0 0 0 1", "non-numeric value 'x'"),
        ("0.2 1 2 3 0 0 nan 1", "non-finite"),
        ("0.2 1 2 3 0 0 0.5 1", "quaternion norm"),
        ("0.2 1 2 3 0 0 0 0", "quaternion norm"),
        ("0.1 1 2 3 0 0 0 1", "does not increase"),
    ],
)
def test_tum_bad_rows_name_file_and_line(tmp_path: Path, bad_line: str, message: str) -> None:
    path = tmp_path / "bad.tum"
    path.write_text(f"{TUM_GOOD}\n0.1 1 2 3 0 0 0 1\n{bad_line}\n")
    with pytest.raises(TrajectoryFormatError, match=message) as info:
        read_tum_poses(path)
    assert f"{path}:3:" in str(info.value)


def test_writers_reject_bad_input_and_keep_old_file(tmp_path: Path) -> None:
    path = tmp_path / "out.txt"
    good = random_poses(3)
    write_kitti_poses(path, good)
    before = path.read_bytes()
    bad = good.copy()
    bad[1, 0, 0] = np.nan
    with pytest.raises(ValueError, match="pose 1 has non-finite"):
        write_kitti_poses(path, bad)
    bad = good.copy()
    bad[2, :3, :3] *= 1.1
    with pytest.raises(ValueError, match="pose 2 rotation is not orthonormal"):
        write_kitti_poses(path, bad)
    with pytest.raises(ValueError, match=r"\(K, 4, 4\)"):
        write_kitti_poses(path, good[:, :3, :])
    with pytest.raises(ValueError, match="strictly increasing"):
        write_tum_poses(tmp_path / "t.tum", np.array([0.0, 0.2, 0.1]), good)
    with pytest.raises(ValueError, match=r"expected shape \(3,\)"):
        write_tum_poses(tmp_path / "t.tum", np.array([0.0, 0.2]), good)
    assert path.read_bytes() == before
    assert not (tmp_path / "t.tum").exists()
    assert sorted(os.listdir(tmp_path)) == ["out.txt"]
