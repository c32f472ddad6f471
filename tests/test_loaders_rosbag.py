"""ROS1 / ROS2 / MCAP bags: the rendered frames come back from bags written with rosbags' writers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gr_graph.datasets.base import DatasetError
from gr_graph.datasets.pointcloud2 import decode_pointcloud2
from gr_graph.datasets.registry import guess_dataset, open_sequence
from gr_graph.datasets.rosbag import RosbagSequence
from loader_support import (FRAME_PERIOD_S, START_NS, CloudLayout, cloud_array, drive, float32_frame, pointcloud2,
                            write_bag)

N_FRAMES = 4


@pytest.fixture(scope="module")
def frames(tmp_path_factory: pytest.TempPathFactory) -> list:
    seq = drive("raw", N_FRAMES, str(tmp_path_factory.mktemp("drive")))
    return [seq[i] for i in range(N_FRAMES)]


def _assert_same(frame_back, frame, with_time: bool) -> None:
    np.testing.assert_array_equal(frame_back.points, float32_frame(frame))
    np.testing.assert_array_equal(frame_back.intensity, frame.intensity)
    np.testing.assert_array_equal(frame_back.ring, frame.ring)
    assert frame_back.n_rings == 16
    if with_time:
        # u4 nanoseconds of a 0.1 s sweep: fractions come back to 1e-8, shifted by the earliest point's time
        np.testing.assert_allclose(frame_back.time, frame.time - frame.time.min(), atol=2e-8)
    else:
        assert frame_back.time is None


@pytest.mark.parametrize("kind", ["ros2", "ros1", "mcap"])
def test_bag_round_trip(tmp_path: Path, frames: list, kind: str) -> None:
    layout = CloudLayout(with_time=True)
    name = {"ros2": "drive_ros2", "ros1": "drive.bag", "mcap": "drive_mcap"}[kind]
    bag = write_bag(tmp_path / name, {"/points": [cloud_array(f, layout) for f in frames]}, kind=kind)
    assert guess_dataset(bag) == "rosbag"
    seq = RosbagSequence(bag)
    assert seq.topic == "/points" and len(seq) == N_FRAMES
    # the stamps mark the sweeps' starts (times from 0): moved to their middles
    assert seq.stamps_moved_by_s == pytest.approx(FRAME_PERIOD_S / 2, abs=1e-3)
    np.testing.assert_allclose(seq.timestamps, np.arange(N_FRAMES) * FRAME_PERIOD_S + seq.stamps_moved_by_s, atol=1e-9)
    assert seq.motion_compensated is False and seq.scan_period == pytest.approx(FRAME_PERIOD_S)
    for i in (0, 1, 3, 2, 2):  # in order, a jump ahead, a jump back, the same frame twice
        _assert_same(seq[i], frames[i], with_time=True)
        assert seq[i].index == i


def test_mcap_file_inside_the_bag_folder_opens_alone(tmp_path: Path, frames: list) -> None:
    bag = write_bag(tmp_path / "m", {"/points": [cloud_array(f, CloudLayout()) for f in frames[:2]]}, kind="mcap")
    mcap = next(bag.glob("*.mcap"))
    seq, source = open_sequence(path=mcap)
    assert "topic /points" in source and len(seq) == 2
    assert seq.motion_compensated is True  # no per-point times
    _assert_same(seq[1], frames[1], with_time=False)


def test_layouts_padding_bigendian_float64_and_seconds(tmp_path: Path, frames: list) -> None:
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    f = frames[1]
    for layout in (CloudLayout(padding=6), CloudLayout(bigendian=True), CloudLayout(coordinate_dtype="f8"),
                   CloudLayout(with_time=True, time_field="time", time_dtype="f4")):
        msg = pointcloud2(store, cloud_array(f, layout), START_NS)
        cloud = decode_pointcloud2(msg, "test")
        expected = f.points if layout.coordinate_dtype == "f8" else float32_frame(f)
        np.testing.assert_array_equal(cloud.points, expected)
        np.testing.assert_array_equal(cloud.intensity, f.intensity)
        np.testing.assert_array_equal(cloud.ring, f.ring)
        if layout.with_time:
            np.testing.assert_allclose(cloud.time, (f.time * FRAME_PERIOD_S).astype(np.float32))


def test_organized_cloud_drops_nans_and_row_padding(tmp_path: Path, frames: list) -> None:
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    f = frames[0]
    arr = cloud_array(f, CloudLayout())
    width = 64
    height = -(-len(arr) // width) + 2
    grid = np.zeros(height * width, dtype=arr.dtype)
    for c in "xyz":
        grid[c] = np.nan
    holes = np.random.default_rng(0).permutation(height * width)[: len(arr)]
    keep = np.sort(holes)
    grid[keep] = arr
    # rows padded by 8 bytes: the message's row_step is longer than width x point_step
    rows = grid.reshape(height, width).view(np.uint8).reshape(height, -1)
    padded = np.concatenate([rows, np.full((height, 8), 0xAB, np.uint8)], axis=1)
    msg = pointcloud2(store, grid, START_NS, organized_shape=(height, width))
    msg.data = padded.reshape(-1)
    msg.row_step = padded.shape[1]
    cloud = decode_pointcloud2(msg, "test")
    assert cloud.dropped_nonfinite == height * width - len(arr)
    np.testing.assert_array_equal(cloud.points, float32_frame(f))
    np.testing.assert_array_equal(cloud.ring, f.ring)


def test_rings_numbered_from_the_lowest_beam_are_flipped(tmp_path: Path, frames: list) -> None:
    arrs = []
    for f in frames[:2]:
        a = cloud_array(f, CloudLayout())
        a["ring"] = 15 - a["ring"]  # the Velodyne driver's convention: ring 0 is the lowest beam
        arrs.append(a)
    seq = RosbagSequence(write_bag(tmp_path / "flipped", {"/velodyne_points": arrs}))
    np.testing.assert_array_equal(seq[1].ring, frames[1].ring)


def test_several_topics_listed_and_chosen(tmp_path: Path, frames: list) -> None:
    a = [cloud_array(f, CloudLayout()) for f in frames[:2]]
    bag = write_bag(tmp_path / "two", {"/front/points": a, "/rear/points": a[:1]})
    with pytest.raises(DatasetError, match=r"two: several sensor_msgs/PointCloud2 topics.*"
                                           r"/front/points \(2 messages\), /rear/points \(1 messages\)"):
        RosbagSequence(bag)
    assert len(RosbagSequence(bag, topic="/rear/points")) == 1
    with pytest.raises(DatasetError, match=r"two: unknown topic '/lidar'.*/front/points"):
        RosbagSequence(bag, topic="/lidar")


def test_broken_messages_are_refused_naming_the_bag(tmp_path: Path, frames: list) -> None:
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    empty = np.zeros(0, dtype=cloud_array(frames[0], CloudLayout()).dtype)
    bag = write_bag(tmp_path / "empty_msg", {"/points": [cloud_array(frames[0], CloudLayout()), empty]})
    seq = RosbagSequence(bag)
    assert len(seq[1].points) == 0  # an empty message (warm-up, dropped sweep) is an empty frame, logged
    first_empty = RosbagSequence(write_bag(tmp_path / "empty_first", {"/points": [empty, cloud_array(frames[0],
                                                                                                      CloudLayout())]}))
    assert len(first_empty[0].points) == 0 and len(first_empty[1].points) > 0
    assert first_empty.n_rings == seq.n_rings  # the conventions come from the first message with points
    no_z = np.zeros(10, dtype=[("x", "<f4"), ("y", "<f4"), ("intensity", "<f4")])
    with pytest.raises(DatasetError, match=r"no_z.*message 0: no field z.*wrong field layout"):
        RosbagSequence(write_bag(tmp_path / "no_z", {"/points": [no_z]}))
    msg = pointcloud2(store, cloud_array(frames[0], CloudLayout()), START_NS)
    msg.point_step = 8  # fields reach past the point
    with pytest.raises(DatasetError, match=r"where: field 'z' .* does not fit in point_step 8"):
        decode_pointcloud2(msg, "where")
    (tmp_path / "junk.bag").write_bytes(b"#ROSBAG V2.0\n" + b"\0" * 64)
    with pytest.raises(DatasetError, match=r"junk.bag: unreadable bag"):
        RosbagSequence(tmp_path / "junk.bag")


def test_bag_without_pointcloud_topic(tmp_path: Path) -> None:
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    path = tmp_path / "imu_only"
    with Writer(path, version=9) as writer:
        conn = writer.add_connection("/imu", "std_msgs/msg/String", typestore=store)
        writer.write(conn, START_NS, store.serialize_cdr(store.types["std_msgs/msg/String"](data="x"),
                                                         "std_msgs/msg/String"))
    with pytest.raises(DatasetError, match=r"imu_only: no sensor_msgs/PointCloud2 topic \(topics: /imu"):
        open_sequence(path=path)


def test_registry_frames_and_poses(tmp_path: Path, frames: list) -> None:
    from gr_graph.trajectory import write_kitti_poses

    bag = write_bag(tmp_path / "b", {"/points": [cloud_array(f, CloudLayout()) for f in frames]})
    poses = np.tile(np.eye(4), (N_FRAMES, 1, 1))
    poses[:, 0, 3] = np.arange(N_FRAMES) + 5.0
    write_kitti_poses(tmp_path / "gt.txt", poses)
    seq, source = open_sequence(path=bag, frames="1:3", poses=tmp_path / "gt.txt")
    assert "ground truth" in source and len(seq) == 2 and seq[0].index == 1
    np.testing.assert_allclose(seq.gt_poses[:, 0, 3], [1.0, 2.0])  # relative to the first scan
    # a TUM file: its times must follow the messages' (up to an offset), else it is refused naming it
    from gr_graph.trajectory import write_tum_poses

    stamps = RosbagSequence(bag).timestamps
    write_tum_poses(tmp_path / "gt.tum", stamps + 100.0, poses)
    assert RosbagSequence(bag, poses=tmp_path / "gt.tum").gt_poses is not None
    write_tum_poses(tmp_path / "gt_2x.tum", 2 * stamps + 100.0, poses)
    with pytest.raises(DatasetError, match=r"gt_2x.tum: .*row by row.*b"):
        RosbagSequence(bag, poses=tmp_path / "gt_2x.tum")


def test_a_bag_without_per_point_times_says_what_it_assumes(tmp_path: Path, frames: list,
                                                            caplog: pytest.LogCaptureFixture) -> None:
    """XYZIR clouds (older Velodyne drivers) look like compensated scans: the assumption is logged with
    the option that deskews raw sweeps; a bag with times logs nothing of the kind."""
    import logging

    plain = write_bag(tmp_path / "plain", {"/points": [cloud_array(f, CloudLayout(with_time=False)) for f in frames]})
    timed = write_bag(tmp_path / "timed", {"/points": [cloud_array(f, CloudLayout(with_time=True)) for f in frames]})
    with caplog.at_level(logging.WARNING):
        assert RosbagSequence(plain).motion_compensated is True
    assert "no per-point time field" in caplog.text and "odometry.deskew: on" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        assert RosbagSequence(timed).motion_compensated is False
    assert "no per-point time field" not in caplog.text


def test_log_times_in_place_of_unset_header_stamps_put_the_sweep_middle_before_them(
        tmp_path: Path, frames: list, caplog: pytest.LogCaptureFixture) -> None:
    """Header stamps left at 0 (a bridge that does not set them): the frames take the bag's log times,
    when each message arrived, after its sweep; per-point times counted from the sweep cannot say where
    that lies, so the sweep's middle is put half a sweep before the log time (before, the offset the
    times show from a header stamp, +0.05 s, moved it half a sweep after: a sweep late). Ground truth
    moves with the stamps; sensor.frame_stamp still decides when given."""
    import logging

    from gr_graph.sensors import SensorConfig

    clouds = {"/points": [cloud_array(f, CloudLayout(with_time=True)) for f in frames]}
    bag = write_bag(tmp_path / "zero", clouds, header_stamps_ns=[0] * N_FRAMES)
    with caplog.at_level(logging.WARNING):
        seq = RosbagSequence(bag)
    assert "header stamps of /points do not increase" in caplog.text and "log times" in caplog.text
    assert seq.stamps_moved_by_s == pytest.approx(-FRAME_PERIOD_S / 2)
    assert seq.conventions.stamp_to_sweep_middle_source == "log times"
    np.testing.assert_allclose(seq.timestamps, np.arange(N_FRAMES) * FRAME_PERIOD_S - FRAME_PERIOD_S / 2, atol=1e-9)
    said = RosbagSequence(bag, sensor=SensorConfig(frame_stamp="sweep_start"))
    assert said.stamps_moved_by_s == pytest.approx(FRAME_PERIOD_S / 2)
    # header stamps that increase: the offset the per-point times show, as before
    assert RosbagSequence(write_bag(tmp_path / "set", clouds)).stamps_moved_by_s == pytest.approx(
        FRAME_PERIOD_S / 2, abs=1e-3)
