"""The KITTI odometry loader on the real KITTI 00 frames in ../shared/data/kitti, and on broken copies."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from gr_graph.datasets.base import DatasetError, LidarSequence
from gr_graph.datasets.kitti import KittiSequence, read_calib


@pytest.fixture()
def kitti_copy(kitti_root: Path, tmp_path: Path) -> Path:
    """A writable copy of the real KITTI excerpt, to break in various ways."""
    dst = tmp_path / "kitti"
    shutil.copytree(kitti_root, dst)
    for p in dst.rglob("*"):
        p.chmod(0o755 if p.is_dir() else 0o644)
    return dst


def test_reads_real_frames(kitti_root: Path) -> None:
    seq = KittiSequence(kitti_root, "00")
    assert isinstance(seq, LidarSequence)
    assert len(seq) == 6
    raw = np.fromfile(kitti_root / "sequences/00/velodyne/000003.bin", np.float32).reshape(-1, 4)
    frame = seq[3]
    assert frame.index == 3 and len(frame) == len(raw)
    np.testing.assert_array_equal(frame.points, raw[:, :3].astype(np.float64))
    np.testing.assert_array_equal(frame.intensity, raw[:, 3])
    assert frame.timestamp == pytest.approx(0.3110752)
    assert seq[-1].index == 5
    assert [f.index for f in seq] == list(range(6))
    with pytest.raises(IndexError):
        seq[6]


def test_gt_poses_are_in_lidar_frame(kitti_root: Path) -> None:
    seq = KittiSequence(kitti_root, "00")
    calib = read_calib(kitti_root / "sequences/00/calib.txt")
    Tr = np.eye(4)
    Tr[:3] = calib["Tr"].reshape(3, 4)
    cam = np.loadtxt(kitti_root / "poses/00.txt").reshape(-1, 3, 4)
    T_w_cam = np.tile(np.eye(4), (len(cam), 1, 1))
    T_w_cam[:, :3] = cam
    expected = np.linalg.inv(Tr) @ T_w_cam @ Tr
    np.testing.assert_allclose(seq.gt_poses, expected, atol=1e-12)
    # The camera's z (forward) axis is the LiDAR's x axis: the car drives along LiDAR x.
    step = np.linalg.inv(seq.gt_poses[0]) @ seq.gt_poses[1]
    assert step[0, 3] > 0.8 and abs(step[1, 3]) < 0.05 and abs(step[2, 3]) < 0.05
    # Back to the camera frame exactly.
    np.testing.assert_allclose(seq.to_camera_frame(seq.gt_poses), T_w_cam, atol=1e-12)


def test_streams_without_holding_frames(kitti_root: Path) -> None:
    seq = KittiSequence(kitti_root, "00")
    held = [name for name, value in vars(seq).items() if isinstance(value, np.ndarray) and value.size > 1000]
    assert held == [], f"sequence holds large arrays: {held}"


def test_missing_folder(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="velodyne"):
        KittiSequence(tmp_path, "00")


def test_truncated_scan_names_file(kitti_copy: Path) -> None:
    f = kitti_copy / "sequences/00/velodyne/000002.bin"
    data = f.read_bytes()
    f.write_bytes(data[:-6])
    seq = KittiSequence(kitti_copy, "00")
    with pytest.raises(DatasetError, match=r"000002\.bin.*multiple of 16"):
        seq[2]


def test_calib_without_tr(kitti_copy: Path) -> None:
    calib = kitti_copy / "sequences/00/calib.txt"
    calib.write_text("\n".join(line for line in calib.read_text().splitlines() if not line.startswith("Tr")))
    with pytest.raises(DatasetError, match=r"calib\.txt.*no 'Tr'"):
        KittiSequence(kitti_copy, "00")


def test_pose_count_mismatch(kitti_copy: Path) -> None:
    poses = kitti_copy / "poses/00.txt"
    poses.write_text("\n".join(poses.read_text().splitlines()[:4]) + "\n")
    with pytest.raises(DatasetError, match=r"00\.txt.*4 poses for 6 scans"):
        KittiSequence(kitti_copy, "00")


def test_non_numeric_pose_row(kitti_copy: Path) -> None:
    poses = kitti_copy / "poses/00.txt"
    lines = poses.read_text().splitlines()
    lines[2] = lines[2].replace(lines[2].split()[3], "abc", 1)
    poses.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=r"00\.txt"):
        KittiSequence(kitti_copy, "00")


def test_times_count_mismatch(kitti_copy: Path) -> None:
    times = kitti_copy / "sequences/00/times.txt"
    times.write_text("0.0\n0.1\n")
    with pytest.raises(DatasetError, match=r"times\.txt.*2 timestamps for 6 scans"):
        KittiSequence(kitti_copy, "00")


def test_non_finite_points_dropped_and_counted(kitti_copy: Path) -> None:
    f = kitti_copy / "sequences/00/velodyne/000001.bin"
    raw = np.fromfile(f, np.float32).reshape(-1, 4)
    raw[[10, 20, 30], 0] = np.nan
    raw[40, 2] = np.inf
    raw.tofile(f)
    frame = KittiSequence(kitti_copy, "00")[1]
    assert frame.dropped_nonfinite == 4
    assert len(frame) == len(raw) - 4
    assert np.all(np.isfinite(frame.points))
    assert frame.ring is not None  # storage order survives the drop


def test_missing_times_falls_back_to_10hz(kitti_copy: Path, caplog: pytest.LogCaptureFixture) -> None:
    (kitti_copy / "sequences/00/times.txt").unlink()
    seq = KittiSequence(kitti_copy, "00")
    assert "times.txt missing" in caplog.text
    assert np.all(np.diff(seq.timestamps) > 0.09)
