"""Fixtures of the loader tests, built from scratch: a short synthetic drive and the files and bags
written from its frames (rosbags' writers, open3d, numpy).

The drive renders 16 rings along a short, gently curving TUM trajectory (its town is small, so it
builds in seconds); frames are the reference the loaders must give back.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from gr_graph.datasets.base import LidarFrame

FRAME_PERIOD_S = 0.1
START_NS = 1_700_000_000_000_000_000


def assert_same_frame(a: LidarFrame, b: LidarFrame) -> None:
    """Two frames agree in every field, bit for bit (arrays and their dtypes; None only where both are)."""
    assert (a.index, a.timestamp, a.n_rings, a.dropped_nonfinite) == (b.index, b.timestamp, b.n_rings, b.dropped_nonfinite)
    for name in ("points", "intensity", "ring", "time"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            assert x.dtype == y.dtype, name
            np.testing.assert_array_equal(x, y, err_msg=name)


def write_short_trajectory(path: Path, n_frames: int, speed: float = 8.0) -> Path:
    """A TUM file of ``n_frames`` poses 0.1 s apart along a gentle S-curve at ``speed`` m/s."""
    from gr_graph.trajectory import write_tum_poses

    ts = np.arange(n_frames) * FRAME_PERIOD_S
    yaw = 0.3 * np.sin(ts / 2.0)
    step = speed * FRAME_PERIOD_S
    x = np.concatenate([[0.0], np.cumsum(np.cos(yaw[1:]) * step)])
    y = np.concatenate([[0.0], np.cumsum(np.sin(yaw[1:]) * step)])
    T = np.tile(np.eye(4), (n_frames, 1, 1))
    c, s = np.cos(yaw), np.sin(yaw)
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c, -s, s, c
    T[:, 0, 3], T[:, 1, 3] = x, y
    return write_tum_poses(path, ts, T)


@lru_cache(maxsize=2)
def drive(preset: str = "clean", n_frames: int = 6, root: str = "") -> object:
    """A 16-ring :class:`SyntheticSequence` along :func:`write_short_trajectory` (cached)."""
    from gr_graph.datasets.synthetic import SyntheticSequence

    folder = Path(root)
    folder.mkdir(parents=True, exist_ok=True)
    traj = write_short_trajectory(folder / f"trajectory_{n_frames}.tum", n_frames)
    return SyntheticSequence(preset=preset, n_rings=16, nthreads=1, trajectory=traj)


@dataclass(frozen=True)
class CloudLayout:
    """How :func:`pointcloud2` lays out a frame's fields."""

    with_time: bool = False
    time_field: str = "t"
    time_dtype: str = "u4"  # u4: nanoseconds since the sweep start (Ouster); f4: seconds (Velodyne)
    with_ring: bool = True
    coordinate_dtype: str = "f4"
    padding: int = 0  # bytes after each point
    bigendian: bool = False
    organized: bool = False  # height 16 x width n_azimuth with NaN holes


POINTFIELD_CODES = {"i1": 1, "u1": 2, "i2": 3, "u2": 4, "i4": 5, "u4": 6, "f4": 7, "f8": 8}


def cloud_array(frame: LidarFrame, layout: CloudLayout, scan_period: float = FRAME_PERIOD_S) -> np.ndarray:
    """The frame's points as the structured array a driver would publish (see :class:`CloudLayout`)."""
    order = ">" if layout.bigendian else "<"
    fields = [("x", layout.coordinate_dtype), ("y", layout.coordinate_dtype), ("z", layout.coordinate_dtype),
              ("intensity", "f4")]
    if layout.with_ring:
        fields.append(("ring", "u2"))
    if layout.with_time:
        fields.append((layout.time_field, layout.time_dtype))
    dtype = np.dtype([(n, order + t) for n, t in fields])
    if layout.padding:
        dtype = np.dtype({"names": dtype.names, "formats": [dtype[n] for n in dtype.names],
                          "offsets": [dtype.fields[n][1] for n in dtype.names],
                          "itemsize": dtype.itemsize + layout.padding})
    arr = np.zeros(len(frame), dtype=dtype)
    for k, c in enumerate("xyz"):
        arr[c] = frame.points[:, k]
    arr["intensity"] = frame.intensity
    if layout.with_ring:
        arr["ring"] = frame.ring
    if layout.with_time:
        seconds = frame.time * scan_period
        arr[layout.time_field] = np.round(seconds * 1e9) if layout.time_dtype == "u4" else seconds
    return arr


def pointcloud2(typestore: object, arr: np.ndarray, stamp_ns: int, frame_id: str = "lidar",
                organized_shape: tuple[int, int] | None = None, ros1: bool = False) -> object:
    """A ``sensor_msgs/msg/PointCloud2`` of the structured array ``arr``."""
    types = typestore.types  # type: ignore[attr-defined]
    Time = types["builtin_interfaces/msg/Time"]
    Header = types["std_msgs/msg/Header"]
    PointField = types["sensor_msgs/msg/PointField"]
    Cloud = types["sensor_msgs/msg/PointCloud2"]
    fields = []
    for name in arr.dtype.names:
        base, offset = arr.dtype.fields[name][:2]
        fields.append(PointField(name=name, offset=offset, datatype=POINTFIELD_CODES[base.str[1:]], count=1))
    height, width = organized_shape or (1, len(arr))
    bigendian = arr.dtype[arr.dtype.names[0]].byteorder == ">"
    header_args = {"stamp": Time(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000),
                   "frame_id": frame_id}
    if ros1:
        header_args["seq"] = 0
    data = np.frombuffer(arr.tobytes(), dtype=np.uint8)
    return Cloud(header=Header(**header_args), height=height, width=width, fields=fields,
                 is_bigendian=bigendian, point_step=arr.dtype.itemsize, row_step=arr.dtype.itemsize * width,
                 data=data, is_dense=organized_shape is None)


def write_bag(path: Path, clouds: dict[str, list[np.ndarray]], kind: str = "ros2",
              stamps_ns: list[int] | None = None, header_stamps_ns: list[int] | None = None) -> Path:
    """Write the structured arrays of each topic as PointCloud2 messages: ``kind`` ros2 (sqlite3),
    mcap (ROS2 with MCAP storage) or ros1. Messages are 0.1 s apart from :data:`START_NS` (``stamps_ns``:
    other log times), their header stamps the log times unless ``header_stamps_ns`` says."""
    from rosbags.typesys import Stores, get_typestore

    n = max(len(v) for v in clouds.values())
    stamps = stamps_ns or [START_NS + int(k * FRAME_PERIOD_S * 1e9) for k in range(n)]
    headers = stamps if header_stamps_ns is None else header_stamps_ns
    msgtype = "sensor_msgs/msg/PointCloud2"
    if kind == "ros1":
        from rosbags.rosbag1 import Writer as Writer1

        store = get_typestore(Stores.ROS1_NOETIC)
        with Writer1(path) as writer:
            conns = {t: writer.add_connection(t, msgtype, typestore=store) for t in clouds}
            for k in range(n):
                for topic, arrs in clouds.items():
                    if k < len(arrs):
                        msg = pointcloud2(store, arrs[k], headers[k], ros1=True)
                        writer.write(conns[topic], stamps[k], store.serialize_ros1(msg, msgtype))
        return path
    from rosbags.rosbag2 import StoragePlugin, Writer as Writer2

    store = get_typestore(Stores.ROS2_HUMBLE)
    plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
    with Writer2(path, version=9, storage_plugin=plugin) as writer:
        conns = {t: writer.add_connection(t, msgtype, typestore=store) for t in clouds}
        for k in range(n):
            for topic, arrs in clouds.items():
                if k < len(arrs):
                    msg = pointcloud2(store, arrs[k], headers[k])
                    writer.write(conns[topic], stamps[k], store.serialize_cdr(msg, msgtype))
    return path


def float32_frame(frame: LidarFrame) -> np.ndarray:
    """The frame's points as float32 stores them, back in float64 (the exact expected values)."""
    return frame.points.astype(np.float32).astype(np.float64)
