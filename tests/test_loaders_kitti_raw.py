"""KITTI raw drives: a fake drive (scans, date timestamps, OXTS made from known poses) reads back."""

from __future__ import annotations

from datetime import datetime, timedelta
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gr_graph.datasets.base import DatasetError
from gr_graph.datasets.kitti_raw import EARTH_RADIUS_M, KittiRawSequence, parse_kitti_datetime
from gr_graph.datasets.registry import guess_dataset, open_sequence
from gr_graph.sensors import SensorConfig

LAT0 = 49.011  # Karlsruhe


def _oxts_rows(T_w_imu: np.ndarray) -> np.ndarray:
    """lat lon alt roll pitch yaw of IMU poses in a Mercator world whose origin is (LAT0, 8.4 deg),
    by inverting the Mercator projection (the loader's forward conversion must undo it). The first
    pose must sit at the origin: the devkit's scale is the cosine of the first latitude."""
    scale = np.cos(np.radians(LAT0))
    mx0 = scale * EARTH_RADIUS_M * np.radians(8.4)
    my0 = scale * EARTH_RADIUS_M * np.log(np.tan(np.radians(90.0 + LAT0) / 2.0))
    x = T_w_imu[:, 0, 3] + mx0
    y = T_w_imu[:, 1, 3] + my0
    lon = np.degrees(x / (scale * EARTH_RADIUS_M))
    lat = np.degrees(2.0 * np.arctan(np.exp(y / (scale * EARTH_RADIUS_M)))) - 90.0
    yaw, pitch, roll = Rotation.from_matrix(T_w_imu[:, :3, :3]).as_euler("ZYX").T
    return np.column_stack([lat, lon, T_w_imu[:, 2, 3] + 110.0, roll, pitch, yaw])


def _fake_drive(root: Path, n: int, with_oxts: bool = True) -> tuple[Path, np.ndarray, list, np.ndarray]:
    rng = np.random.default_rng(3)
    drive = root / "2011_09_26" / "2011_09_26_drive_0001_sync"
    data = drive / "velodyne_points" / "data"
    data.mkdir(parents=True)
    scans = []
    for k in range(n):
        xyzi = rng.normal(0.0, 10.0, (500, 4)).astype(np.float32)
        xyzi[:, 3] = rng.uniform(0, 1, 500)
        xyzi.tofile(data / f"{k:010d}.bin")
        scans.append(xyzi)
    t0 = datetime(2011, 9, 26, 13, 2, 25)
    stamps = [t0 + timedelta(microseconds=103_712 * k + 17) for k in range(n)]
    (drive / "velodyne_points" / "timestamps.txt").write_text(
        "".join(s.strftime("%Y-%m-%d %H:%M:%S.%f") + "123\n" for s in stamps))
    seconds = np.array([(s - t0).total_seconds() for s in stamps])
    yaw = np.linspace(0.0, 0.6, n)
    T_w_imu = np.tile(np.eye(4), (n, 1, 1))
    T_w_imu[:, :3, :3] = Rotation.from_euler("ZYX", np.column_stack([yaw, 0.01 * yaw, -0.02 * yaw])).as_matrix()
    T_w_imu[:, :3, 3] = np.column_stack([np.arange(n) * 1.1, np.arange(n) * 0.3, 0.05 * np.arange(n)])
    if with_oxts:
        oxts = drive / "oxts" / "data"
        oxts.mkdir(parents=True)
        for k, row in enumerate(_oxts_rows(T_w_imu)):
            extra = " ".join(["0.1"] * 24)  # velocities, accelerations, accuracies, status
            (oxts / f"{k:010d}.txt").write_text(" ".join(f"{v:.15g}" for v in row) + " " + extra + "\n")
    return drive, T_w_imu, scans, seconds


def test_date_parsing_keeps_nanoseconds() -> None:
    a = parse_kitti_datetime("2011-09-26 13:02:25.964389445")
    b = parse_kitti_datetime("2011-09-26 13:02:26.068089445")
    assert b - a == 103_700_000


def test_kitti_raw_drive(tmp_path: Path) -> None:
    n = 5
    drive, T_w_imu, scans, seconds = _fake_drive(tmp_path, n)
    T_velo_imu = np.eye(4)
    T_velo_imu[:3, :3] = Rotation.from_euler("z", 0.02).as_matrix()
    T_velo_imu[:3, 3] = [-0.81, 0.32, -0.80]
    (drive.parent / "calib_imu_to_velo.txt").write_text(
        "calib_time: 25-May-2012 16:47:16\nR: " + " ".join(f"{v:.12g}" for v in T_velo_imu[:3, :3].ravel())
        + "\nT: " + " ".join(f"{v:.12g}" for v in T_velo_imu[:3, 3]) + "\n")
    assert guess_dataset(drive) == "kitti_raw"
    assert guess_dataset(drive / "velodyne_points") == "kitti_raw"
    seq, source = open_sequence(path=drive)
    assert "KITTI raw drive" in source and "ground truth" in source and "not motion-compensated" in source
    assert seq.motion_compensated is False
    np.testing.assert_allclose(seq.timestamps, seconds - seconds[0], atol=1e-12)
    T_w_velo = T_w_imu @ np.linalg.inv(T_velo_imu)
    expected = np.linalg.inv(T_w_velo[0]) @ T_w_velo
    np.testing.assert_allclose(seq.gt_poses, expected, atol=2e-6)  # Mercator round trip ~1e-7 deg
    raw = KittiRawSequence(drive, recover_ring_index=False)
    for k in (0, 3):
        np.testing.assert_array_equal(raw[k].points, scans[k][:, :3].astype(np.float64))
        np.testing.assert_array_equal(raw[k].intensity, scans[k][:, 3])


def test_kitti_raw_without_oxts_and_broken(tmp_path: Path) -> None:
    drive, _, _, _ = _fake_drive(tmp_path, 3, with_oxts=False)
    assert KittiRawSequence(drive, recover_ring_index=False).gt_poses is None
    times = drive / "velodyne_points" / "timestamps.txt"
    good_times = times.read_text()
    times.write_text(good_times.splitlines()[0] + "\n")
    with pytest.raises(DatasetError, match=r"velodyne_points/timestamps.txt: 1 timestamps for 3 scans"):
        KittiRawSequence(drive)
    times.write_text("yesterday\n")
    with pytest.raises(DatasetError, match=r"timestamps.txt:1: not a 'YYYY-MM-DD HH:MM:SS.fff' date"):
        KittiRawSequence(drive)
    (drive / "velodyne_points" / "data" / ".DS_Store").write_bytes(b"\0")  # hidden files are no scans
    times.write_text(good_times)
    assert len(KittiRawSequence(drive)) == 3
    (drive / "velodyne_points" / "data" / "notes.txt").write_text("x")
    with pytest.raises(DatasetError, match=r"data: mixed file types \(.bin and '.txt'\)"):
        KittiRawSequence(drive)


def test_oxts_file_too_short(tmp_path: Path) -> None:
    drive, _, _, _ = _fake_drive(tmp_path, 2)
    (drive / "oxts" / "data" / "0000000001.txt").write_text("49.0 8.4 110\n")
    with pytest.raises(DatasetError, match=r"oxts/data/0000000001.txt: needs at least 6 finite values"):
        KittiRawSequence(drive)


def test_kitti_raw_sweep_duration(tmp_path: Path) -> None:
    """From the start/end stamps when the drive has them, else the frame spacing; sensor.scan_period wins
    (before, the sensor section did not reach this loader and the deskewer could not be told)."""
    drive, _, _, seconds = _fake_drive(tmp_path, 4, with_oxts=False)
    assert KittiRawSequence(drive, recover_ring_index=False).scan_period == pytest.approx(np.median(np.diff(seconds)))
    velo = drive / "velodyne_points"
    t0 = datetime(2011, 9, 26, 13, 2, 25)
    for name, offset_us in (("timestamps_start.txt", 0), ("timestamps_end.txt", 98_500)):
        (velo / name).write_text("".join((t0 + timedelta(microseconds=103_712 * k + offset_us)).strftime(
            "%Y-%m-%d %H:%M:%S.%f") + "000\n" for k in range(4)))
    assert KittiRawSequence(drive, recover_ring_index=False).scan_period == pytest.approx(0.0985)
    said = KittiRawSequence(drive, recover_ring_index=False, sensor=SensorConfig(scan_period=0.1))
    assert said.scan_period == 0.1
    seq, _ = open_sequence(path=drive, sensor=SensorConfig(scan_period=0.09))
    assert seq.scan_period == 0.09


def test_repeated_and_backward_raw_timestamps_are_repaired_not_fatal(tmp_path: Path, caplog) -> None:
    """A repeated or backward line of velodyne_points/timestamps.txt: the trajectory files need
    increasing times, and the run failed over it after SLAM; now repaired when opened, logged."""
    import logging

    from gr_graph.datasets.base import increasing_stamps

    drive, _, _, seconds = _fake_drive(tmp_path, 12, with_oxts=False)
    times = drive / "velodyne_points" / "timestamps.txt"
    lines = times.read_text().splitlines()
    lines[2] = lines[1]  # repeated
    lines[7] = lines[0]  # backward
    times.write_text("\n".join(lines) + "\n")
    with caplog.at_level(logging.WARNING):
        seq = KittiRawSequence(drive, recover_ring_index=False)
    assert np.all(np.diff(seq.timestamps) > 0)
    assert "2 timestamps not after the one before (lines 3, 8)" in caplog.text
    step = float(np.diff(seconds)[0])  # the drive's (constant) spacing, the median of the forward steps
    kept = [0, 1, 3, 4, 5, 6, 8, 9, 10, 11]
    np.testing.assert_allclose(seq.timestamps[kept], seconds[kept] - seconds[0], atol=1e-6)
    np.testing.assert_allclose(seq.timestamps[2], seq.timestamps[1] + step, atol=1e-6)  # the previous + the spacing
    np.testing.assert_allclose(seq.timestamps[7], seq.timestamps[6] + step, atol=1e-6)
    ok = np.array([0, 5, 9], np.int64)
    assert increasing_stamps(ok, "x") is not ok and np.array_equal(increasing_stamps(ok, "x"), ok)  # unchanged
