"""The KITTI odometry loader on the real KITTI 00 frames in ../shared/data/kitti, and on broken copies."""

from __future__ import annotations

import logging
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
    from gr_graph.datasets.registry import open_sequence

    with pytest.raises(DatasetError, match=r"000002\.bin.*multiple of 16.*\(1 of the 6 scans to read have such a size"):
        open_sequence(path=kitti_copy)  # when the sequence opens, not when SLAM reaches the frame
    assert len(open_sequence(path=kitti_copy, frames="3:6")[0]) == 3  # outside the frames asked for: not read


def test_times_must_increase(kitti_copy: Path) -> None:
    times = kitti_copy / "sequences/00/times.txt"
    times.write_text("0.0\n0.1\n0.1\n0.3\n0.2\n0.5\n")
    with pytest.raises(DatasetError, match=r"times\.txt:3: timestamp 0.1 s is not after the one before"):
        KittiSequence(kitti_copy, "00")


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


def _spherical(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    r = np.linalg.norm(p, axis=1)
    return r, np.arctan2(p[:, 1], p[:, 0]), np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1]))


@pytest.mark.parametrize("angle", [0.205, -0.5, 1.7])
def test_vertical_correction_raises_elevation_only(angle: float) -> None:
    """Closed form: elevation + angle, range and azimuth unchanged; the vertical axis stays put."""
    from gr_graph.datasets.kitti import correct_vertical_angle

    rng = np.random.default_rng(0)
    p = rng.normal(size=(2000, 3)) * [30, 30, 3]
    q = correct_vertical_angle(p, angle)
    r0, az0, el0 = _spherical(p)
    r1, az1, el1 = _spherical(q)
    np.testing.assert_allclose(r1, r0, rtol=1e-12)
    np.testing.assert_allclose(np.angle(np.exp(1j * (az1 - az0))), 0.0, atol=1e-12)
    np.testing.assert_allclose(el1 - el0, np.radians(angle), atol=1e-12)
    np.testing.assert_array_equal(correct_vertical_angle(np.array([[0.0, 0.0, 5.0]]), angle), [[0.0, 0.0, 5.0]])
    assert correct_vertical_angle(p, 0.0) is p


def test_vertical_correction_matches_kiss_icp() -> None:
    """KISS-ICP 1.3.0's own KITTI correction (0.205 degrees) as an independent reference."""
    pybind = pytest.importorskip("kiss_icp.pybind.kiss_icp_pybind")
    from gr_graph.datasets.kitti import correct_vertical_angle

    p = np.random.default_rng(1).normal(size=(500, 3)) * [30, 30, 3]
    ref = np.asarray(pybind._correct_kitti_scan(pybind._Vector3dVector(p)))
    np.testing.assert_allclose(correct_vertical_angle(p, 0.205), ref, atol=1e-9)


def test_loader_applies_the_configured_correction(kitti_root: Path) -> None:
    from gr_graph.config import load_config
    from gr_graph.datasets.kitti import correct_vertical_angle
    from gr_graph.datasets.registry import open_configured_sequence

    plain = KittiSequence(kitti_root, "00")
    assert plain.motion_compensated is True and plain.vertical_correction_deg == 0.0
    cfg = load_config(overrides={"data": {"data_root": str(kitti_root), "kitti_vertical_correction_deg": 0.205,
                                          "frames": "1:3"}})
    seq, source = open_configured_sequence(cfg.data)
    assert "vertical-angle correction 0.205 deg" in source and seq.motion_compensated is True
    f, ref = seq[1], plain[2]
    np.testing.assert_array_equal(f.points, correct_vertical_angle(ref.points, 0.205))
    np.testing.assert_array_equal(f.ring, ref.ring)  # rings recovered before the correction
    with pytest.raises(ValueError, match="vertical_correction_deg"):
        KittiSequence(kitti_root, "00", vertical_correction_deg=5.0)


def test_bin_scans_follow_the_folder_rules_for_intensity_and_points_at_the_origin(
        kitti_copy: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A NaN intensity keeps its point (intensity 0, logged) and a point exactly at the origin (no
    return) is dropped and counted: the same points a folder of the same ``.bin`` files gives."""
    from gr_graph.datasets.folder import FolderSequence

    f = kitti_copy / "sequences/00/velodyne/000002.bin"
    raw = np.fromfile(f, np.float32).reshape(-1, 4)
    raw[[5, 15, 25], 3] = np.nan
    raw[[7, 8], :3] = 0.0
    raw.tofile(f)
    with caplog.at_level(logging.WARNING):
        frame = KittiSequence(kitti_copy, "00")[2]
    assert frame.dropped_nonfinite == 2 and len(frame) == len(raw) - 2
    assert "3 non-finite intensity values at finite points replaced by 0" in caplog.text
    assert np.all(np.isfinite(frame.intensity)) and np.count_nonzero(frame.intensity == 0) >= 3
    folder = FolderSequence(kitti_copy / "sequences/00/velodyne")[2]
    np.testing.assert_array_equal(frame.points, folder.points)
    np.testing.assert_array_equal(frame.intensity, folder.intensity)
