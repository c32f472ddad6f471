"""Frame stamps moved to the sweeps' middles (the instant a deskewed sweep's pose refers to), and the
ground truth along itself with them: :func:`gr_graph.deskew.sweep_middle_offset`,
:mod:`gr_graph.datasets.stamp_shift`, ``FieldConventions.stamp_to_sweep_middle`` and the bag loader."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from factors.se3 import exp_se3
from gr_graph.datasets.frame_fields import FieldConventions
from gr_graph.datasets.pointcloud2 import DecodedCloud
from gr_graph.datasets.rosbag import RosbagSequence
from gr_graph.datasets.stamp_shift import poses_at_times, stamps_at_sweep_middle
from gr_graph.deskew import normalise_times, sweep_middle_offset
from gr_graph.sensors import SensorConfig
from gr_graph.trajectory import write_kitti_poses
from loader_support import FRAME_PERIOD_S, START_NS, CloudLayout, cloud_array, drive, write_bag

PERIOD = 0.1
TWIST = np.array([0.02, -0.01, 0.3, 8.0, 0.5, 0.1])  # per second: turning while driving 8 m/s


def _path(times: np.ndarray) -> np.ndarray:
    """Poses of a constant-twist motion at ``times`` (a closed form to interpolate against)."""
    return np.array([exp_se3(TWIST * t) for t in times])


# ---------------------------------------------------------------- interpolation of the ground truth
def test_poses_at_times_follow_a_constant_twist_path_and_extrapolate_its_ends() -> None:
    times = np.array([0.0, 0.1, 0.25, 0.3, 0.42])  # uneven spacing
    query = np.array([-0.05, 0.0, 0.07, 0.25, 0.29, 0.41, 0.5])  # before, on, between and after the rows
    np.testing.assert_allclose(poses_at_times(times, _path(times), query), _path(query), atol=1e-12)
    one = poses_at_times(times[:1], _path(times[:1]), query)
    np.testing.assert_array_equal(one, np.repeat(_path(times[:1]), len(query), axis=0))
    with pytest.raises(ValueError, match="strictly increase"):
        poses_at_times(times[::-1], _path(times), query)
    with pytest.raises(ValueError, match="expected"):
        poses_at_times(times, _path(times)[:3], query)


def test_stamps_moved_with_the_ground_truth_re_anchored() -> None:
    stamps = np.arange(6) * PERIOD
    gt = _path(stamps)
    moved, moved_gt = stamps_at_sweep_middle(stamps, gt, 0.05, "test")
    np.testing.assert_allclose(moved, stamps + 0.05)
    want = np.linalg.inv(_path(np.array([0.05]))[0]) @ _path(stamps + 0.05)  # anchored at the first frame
    np.testing.assert_allclose(moved_gt, want, atol=1e-12)
    assert stamps_at_sweep_middle(stamps, gt, None, "test")[0] is stamps  # unknown: nothing moves
    assert stamps_at_sweep_middle(stamps, None, 0.0, "test")[1] is None


# ---------------------------------------------------------------- the offset the per-point times show
@pytest.mark.parametrize("times, sweep_start, offset", [
    (np.linspace(0.0, PERIOD, 50), None, 0.05),  # from the stamp at the sweep's start (Ouster, ROS2 Velodyne)
    (np.linspace(-PERIOD, 0.0, 50), None, -0.05),  # back from the stamp at its end (ROS1 Velodyne)
    (np.linspace(0.02, 0.05, 50), None, 0.05),  # a partial sweep keeps its place in the sweep
    (np.linspace(0.0005, 0.1, 50), None, 0.0505),  # the first firing 0.5 ms after the stamp: the sweep starts there
    (np.linspace(0.004, 0.1, 50), None, 0.05),  # 4 ms (beyond START_SLACK): a partial sweep, counted from the stamp
    (1.7e9 + np.linspace(0.0, PERIOD, 50), 1.7e9, 0.05),  # absolute stamps, the header at the first point
    (1.7e9 + np.linspace(-PERIOD, 0.0, 50), 1.7e9, -0.05),  # ... at the last
    (1.7e9 + np.linspace(0.0, PERIOD, 50), None, None),  # absolute without a stamp on their clock: unknown
    (np.zeros(0), None, None),
])
def test_sweep_middle_offset(times: np.ndarray, sweep_start: float | None, offset: float | None) -> None:
    got = sweep_middle_offset(times, PERIOD, sweep_start=sweep_start)
    if offset is None:
        assert got is None
        return
    assert got == pytest.approx(offset, abs=1e-6)
    # the instant of fraction 0.5 is stamp + offset: every fraction is 0.5 + (t - that instant) / period
    fractions = normalise_times(times, PERIOD, sweep_start=sweep_start)
    clock = times - (sweep_start or 0.0)
    np.testing.assert_allclose(fractions, np.clip(0.5 + (clock - got) / PERIOD, 0.0, 1.0), atol=1e-6)


def _decoded(times: np.ndarray) -> DecodedCloud:
    az = np.linspace(np.pi, -np.pi, len(times), endpoint=False)
    points = np.column_stack([10 * np.cos(az), 10 * np.sin(az), np.zeros(len(az))])
    return DecodedCloud(points, None, times, "t", None, 0)


def test_conventions_take_the_median_offset_of_the_probe_frames_or_the_sensor_section() -> None:
    full = np.linspace(0.0, PERIOD, 360) * 1e9  # ns from the stamp
    late = full + 0.02e9  # a frame whose driver stamped 20 ms early: outvoted by the median
    probes = [(_decoded(full), "b"), (_decoded(late), "c")]
    conv = FieldConventions.probe(_decoded(full), PERIOD, "a", None, probes)
    assert conv.stamp_to_sweep_middle == pytest.approx(0.05, abs=1e-6)
    assert conv.stamp_to_sweep_middle_source == "per-point times"
    # the sensor section wins (a stamp at the sweep's middle: nothing moves), whatever the times show
    said = FieldConventions.probe(_decoded(full), PERIOD, "a", SensorConfig(frame_stamp="sweep_middle"), probes)
    assert said.stamp_to_sweep_middle == 0.0 and said.stamp_to_sweep_middle_source == "sensor.frame_stamp"
    # without per-point times only the sensor section can say
    bare = DecodedCloud(_decoded(full).points, None, None, None, None, 0)
    assert FieldConventions.probe(bare, PERIOD, "a").stamp_to_sweep_middle is None
    end = FieldConventions.probe(bare, PERIOD, "a", SensorConfig(frame_stamp="sweep_end"))
    assert end.stamp_to_sweep_middle == pytest.approx(-0.05)
    # absolute times: each probe frame's own stamp on their clock
    stamps = [1.7e9, 1.7e9 + PERIOD]
    absolute = FieldConventions.probe(_decoded(1.7e9 * 1e9 + full), PERIOD, "a", SensorConfig(time_unit="ns"),
                                      [(_decoded(1.7e9 * 1e9 + PERIOD * 1e9 + full), "b")], stamps)
    assert absolute.stamp_to_sweep_middle == pytest.approx(0.05, abs=1e-4)
    with pytest.raises(ValueError, match="sweep_starts"):
        FieldConventions.probe(_decoded(full), PERIOD, "a", None, probes, stamps[:1])


# ---------------------------------------------------------------- a bag whose driver stamps the sweep's end
def test_a_bag_stamped_at_the_sweeps_end_moves_stamps_and_ground_truth_back(tmp_path: Path) -> None:
    seq = drive("raw", 4, str(tmp_path / "drive"))
    frames = [seq[i] for i in range(4)]
    # ROS1 Velodyne: float seconds counted back from the stamp at the sweep's last point
    layout = CloudLayout(with_time=True, time_field="time", time_dtype="f4")
    arrays = [cloud_array(f, layout) for f in frames]
    for a in arrays:
        a["time"] -= np.float32(FRAME_PERIOD_S)
    bag = write_bag(tmp_path / "velodyne.bag", {"/points": arrays}, kind="ros1")
    stamps = np.arange(4) * FRAME_PERIOD_S
    write_kitti_poses(tmp_path / "gt.txt", _path(stamps))  # at the stamps, as the loader's contract says
    loaded = RosbagSequence(bag, poses=tmp_path / "gt.txt")
    shift = loaded.stamps_moved_by_s
    assert shift == pytest.approx(-0.05, abs=1e-3)
    np.testing.assert_allclose(loaded.timestamps, stamps + shift, atol=1e-9)
    want = np.linalg.inv(_path(np.array([shift]))[0]) @ _path(stamps + shift)
    np.testing.assert_allclose(loaded.gt_poses, want, atol=1e-9)
    # the frames themselves do not change: the same sweep fractions as a bag stamped at the sweep's start
    start = RosbagSequence(write_bag(tmp_path / "ouster", {"/points": [cloud_array(f, CloudLayout(with_time=True))
                                                                       for f in frames]}))
    assert start.stamps_moved_by_s == pytest.approx(0.05, abs=1e-3)
    np.testing.assert_allclose(loaded[2].time, start[2].time, atol=1e-6)
    np.testing.assert_array_equal(loaded[2].points, start[2].points)
    # told where the stamps lie, the loader follows the sensor section
    kept = RosbagSequence(bag, poses=tmp_path / "gt.txt", sensor=SensorConfig(frame_stamp="sweep_middle"))
    assert kept.stamps_moved_by_s == 0.0
    np.testing.assert_allclose(kept.timestamps, stamps, atol=1e-9)
    np.testing.assert_allclose(kept.gt_poses, np.linalg.inv(_path(stamps[:1])[0]) @ _path(stamps), atol=1e-9)
    assert START_NS > 0  # the bag's stamps are absolute; the timestamps count from the first


def test_frame_stamp_on_data_that_keep_their_stamps_is_said(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    from gr_graph.datasets.registry import open_sequence

    seq_dir = tmp_path / "sequences" / "00"
    (seq_dir / "velodyne").mkdir(parents=True)
    rng = np.random.default_rng(0)
    for i in range(2):
        np.column_stack([rng.uniform(-20, 20, (500, 3)), np.full(500, 0.5)]).astype(np.float32).tofile(
            seq_dir / "velodyne" / f"{i:06d}.bin")
    (seq_dir / "times.txt").write_text("0.0\n0.1\n")
    (seq_dir / "calib.txt").write_text("Tr: " + " ".join(f"{v:.1f}" for v in np.eye(4)[:3].ravel()) + "\n")
    with caplog.at_level("WARNING"):
        seq, _ = open_sequence(path=seq_dir, sensor=SensorConfig(frame_stamp="sweep_start"))
    assert "sensor.frame_stamp (sweep_start) is read by the folder and bag loaders only" in caplog.text
    np.testing.assert_array_equal(seq.timestamps, [0.0, 0.1])  # KITTI's stamps stay
    caplog.clear()
    with caplog.at_level("WARNING"):
        open_sequence(path=seq_dir)
    assert "frame_stamp" not in caplog.text
