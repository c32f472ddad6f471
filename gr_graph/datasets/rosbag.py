"""ROS1 bags, ROS2 bags (sqlite3 or MCAP) and bare ``.mcap`` files as LiDAR sequences, via ``rosbags``.

No ROS installation is needed: the pure-Python ``rosbags`` library reads the bag and
deserializes ``sensor_msgs/PointCloud2`` messages (decoded by :mod:`gr_graph.datasets.pointcloud2`).

Topic: the one PointCloud2 topic of the bag, or the one given (``topic``); a bag with several
PointCloud2 topics and none given is refused with the list, as is an unknown topic.

Streaming: opening the bag reads each message once to index it (its log time and header
stamp), holding nothing else; frames are then decoded on demand. Reading the frames in order
continues one pass through the bag; a jump starts a new pass at that message's log time.

Timestamps are the messages' ``header.stamp`` (seconds since the first), or the bag's log times
when the header stamps do not increase (logged). Per-point times (fields ``t``/``time``/
``timestamp``) make the sequence ``motion_compensated = False``
(:mod:`gr_graph.datasets.frame_fields` for units, references and rings, and how the ``sensor``
section overrides what is guessed); absolute per-point stamps that fall in the sweep starting
at a message's header stamp count from it. The bag has no ground truth;
``poses`` (a KITTI or TUM file with one LiDAR pose a message, at the message's stamp) adds it.
With per-point times (or ``sensor.frame_stamp``) the timestamps are then moved to the sweeps'
middles, where the deskewed poses refer, and the ground truth along itself with them
(:mod:`gr_graph.datasets.stamp_shift`; e.g. +0.05 s for a 10 Hz driver stamping a sweep's first point).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from gr_graph.datasets.base import DatasetError, LidarFrame, check_index, increasing_stamps
from gr_graph.datasets.frame_fields import FieldConventions, frame_period, no_time_field_note, probe_indices
from gr_graph.datasets.pointcloud2 import decode_pointcloud2
from gr_graph.datasets.stamp_shift import stamps_moved_by_conventions
from gr_graph.sensors import SensorConfig

log = logging.getLogger(__name__)

POINTCLOUD2_TYPES = ("sensor_msgs/msg/PointCloud2", "sensor_msgs/PointCloud2")
BAG_SUFFIXES = (".bag", ".mcap", ".db3")


def is_bag(path: Path) -> bool:
    """A ROS1 ``.bag``, a ``.mcap``/``.db3`` file, or a ROS2 bag folder (with ``metadata.yaml``)."""
    return (path.is_file() and path.suffix.lower() in BAG_SUFFIXES) or (path / "metadata.yaml").is_file()


def _open_reader(path: Path) -> Any:
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    try:
        reader = AnyReader([path], default_typestore=store)
        reader.open()
    except Exception as exc:  # rosbags raises its own error classes per format
        raise DatasetError(f"{path}: unreadable bag ({type(exc).__name__}: {exc})") from exc
    return reader


def pointcloud_topics(reader: Any) -> dict[str, int]:
    """PointCloud2 topics of an open reader and their message counts."""
    topics: dict[str, int] = {}
    for conn in reader.connections:
        if conn.msgtype in POINTCLOUD2_TYPES:
            topics[conn.topic] = topics.get(conn.topic, 0) + int(conn.msgcount)
    return topics


def choose_topic(path: Path, reader: Any, topic: str | None) -> str:
    """The PointCloud2 topic to read (see the module docstring)."""
    topics = pointcloud_topics(reader)
    listing = ", ".join(f"{t} ({n} messages)" for t, n in sorted(topics.items())) or "none"
    if topic is not None:
        if topic not in topics:
            others = sorted({c.topic for c in reader.connections} - set(topics))
            raise DatasetError(f"{path}: unknown topic {topic!r}; sensor_msgs/PointCloud2 topics: {listing}"
                               + (f" (other topics: {', '.join(others)})" if others else ""))
        return topic
    if not topics:
        all_topics = ", ".join(sorted(f"{c.topic} ({c.msgtype})" for c in reader.connections)) or "none"
        raise DatasetError(f"{path}: no sensor_msgs/PointCloud2 topic (topics: {all_topics})")
    if len(topics) > 1:
        raise DatasetError(f"{path}: several sensor_msgs/PointCloud2 topics, choose one with --topic "
                           f"(data.topic): {listing}")
    return next(iter(topics))


class RosbagSequence:
    """The PointCloud2 messages of one topic of a bag (LidarSequence protocol).

    Parameters
    ----------
    path : path
        A ROS1 ``.bag``, a ROS2 bag folder, or a ``.mcap``/``.db3`` file.
    topic : str, optional
        The PointCloud2 topic; required when the bag has several.
    poses : path, optional
        Ground truth: KITTI or TUM poses of the LiDAR, one a message.
    sensor : SensorConfig, optional
        The ``sensor`` section: its given time unit / reference / scan period, ``has_time`` /
        ``has_ring`` and beam count (:meth:`FieldConventions.probe`).

    Attributes
    ----------
    topic : str
    timestamps : (K,) array
    log_times : (K,) int64
        The bag's receive time of each message (ns).
    motion_compensated : bool
        False when the clouds carry per-point times.
    scan_period : float
        The sweep duration (s): ``sensor.scan_period`` when given, else the spacing of the stamps or
        a full revolution's per-point time span (:attr:`FieldConventions.scan_period_source`).
    """

    def __init__(self, path: str | Path, topic: str | None = None, poses: str | Path | None = None,
                 sensor: SensorConfig | None = None) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise DatasetError(f"{self.path}: no such bag")
        if not is_bag(self.path):
            raise DatasetError(f"{self.path}: not a ROS bag (a {'/'.join(BAG_SUFFIXES)} file or a ROS2 bag folder "
                               "with metadata.yaml)")
        self._lock = threading.Lock()
        self._reader = _open_reader(self.path)
        self.topic = choose_topic(self.path, self._reader, topic)
        self._connections = [c for c in self._reader.connections if c.topic == self.topic]
        self.name = f"bag-{self.path.stem}{self.topic.replace('/', '_')}"
        self.T_cam_velo = np.eye(4)
        log_times, stamps = [], []
        first_cloud, probe_index = None, 0
        for k, (conn, log_time, raw) in enumerate(self._reader.messages(connections=self._connections)):
            msg = self._deserialize(conn, raw, k)
            log_times.append(int(log_time))
            stamps.append(int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec))
            if first_cloud is None or not len(first_cloud.points):
                # the first message with points fixes the conventions (a warm-up message may be empty)
                first_cloud, probe_index = decode_pointcloud2(msg, self._source(k)), k
        if not log_times:
            raise DatasetError(f"{self.path}: topic {self.topic!r} has no messages")
        self.log_times = np.asarray(log_times, np.int64)
        stamp_ns = np.asarray(stamps, np.int64)
        self.stamps_are_log_times = len(stamp_ns) > 1 and not np.all(np.diff(stamp_ns) > 0)
        if self.stamps_are_log_times:
            log.warning("%s: header stamps of %s do not increase: using the bag's log times", self.path, self.topic)
            stamp_ns = increasing_stamps(self.log_times, f"{self.path}: topic {self.topic} log times")
        self.timestamps = (stamp_ns - stamp_ns[0]).astype(np.float64) * 1e-9
        self.stamps_s = stamp_ns.astype(np.float64) * 1e-9
        """The frames' stamps (s, the bag's clock): where absolute per-point times may count from."""
        self._cursor: tuple[int, Iterator] | None = None
        more_indices = probe_indices(len(self), probe_index)[1:]  # spread over the bag (FieldConventions.probe)
        more = [(decode_pointcloud2(self._message(k), self._source(k)), self._source(k)) for k in more_indices]
        self._cursor = None
        self.conventions = FieldConventions.probe(first_cloud, frame_period(self.timestamps), self._source(probe_index),
                                                  sensor, more,
                                                  [float(self.stamps_s[k]) for k in (probe_index, *more_indices)],
                                                  self.stamps_are_log_times)
        self.scan_period = self.conventions.scan_period  # sensor.scan_period, the spacing or the times' span
        self.motion_compensated = self.conventions.motion_compensated
        if self.motion_compensated:  # a driver's raw sweeps without times look the same: say what is assumed
            log.warning(no_time_field_note(f"{self.path}: topic {self.topic}"))
        self.gt_poses: np.ndarray | None = None
        if poses is not None:
            from gr_graph.datasets.folder import check_pose_times, read_pose_file

            self.gt_poses, pose_times = read_pose_file(Path(poses), len(self))
            if pose_times is not None:  # a TUM file: its times must follow the messages' (up to an offset)
                check_pose_times(pose_times, self.timestamps, Path(poses), self.path)
        self.timestamps, self.gt_poses, self.stamps_moved_by_s = stamps_moved_by_conventions(
            self.timestamps, self.gt_poses, self.conventions, f"{self.path}: topic {self.topic}")

    def _source(self, k: int) -> str:
        return f"{self.path}: topic {self.topic} message {k}"

    def _deserialize(self, conn: Any, raw: bytes, k: int) -> Any:
        try:
            return self._reader.deserialize(raw, conn.msgtype)
        except Exception as exc:  # truncated or foreign serialization
            raise DatasetError(f"{self._source(k)}: cannot deserialize ({type(exc).__name__}: {exc})") from exc

    def __len__(self) -> int:
        return len(self.log_times)

    def _message(self, i: int) -> Any:
        """The i-th message, continuing the current pass when it is the next one."""
        if self._cursor is None or self._cursor[0] != i:
            t = int(self.log_times[i])
            same_time_before = int(np.sum(self.log_times[:i] == t))
            it = self._reader.messages(connections=self._connections, start=t)
            for _ in range(same_time_before):
                next(it)
            self._cursor = (i, it)
        _, it = self._cursor
        try:
            conn, log_time, raw = next(it)
        except StopIteration as exc:
            raise DatasetError(f"{self._source(i)}: the bag ended early (it changed since it was opened?)") from exc
        if int(log_time) != int(self.log_times[i]):
            raise DatasetError(f"{self._source(i)}: log time {log_time} != indexed {self.log_times[i]} "
                               "(the bag changed since it was opened?)")
        self._cursor = (i + 1, it)
        return self._deserialize(conn, raw, i)

    def __getitem__(self, index: int) -> LidarFrame:
        i = check_index(index, len(self), self.name)
        with self._lock:
            msg = self._message(i)
        source = self._source(i)
        cloud = decode_pointcloud2(msg, source)
        if cloud.dropped_nonfinite:
            log.debug("%s: dropped %d points without a return (non-finite, or exactly at the origin)", source,
                      cloud.dropped_nonfinite)
        return self.conventions.frame(cloud, i, float(self.timestamps[i]), source, float(self.stamps_s[i]))

    @property
    def n_rings(self) -> int:
        """Rings of the sensor (:attr:`gr_graph.datasets.frame_fields.FieldConventions.n_rings`)."""
        return self.conventions.n_rings

    def __iter__(self) -> Iterator[LidarFrame]:
        for i in range(len(self)):
            yield self[i]

    def close(self) -> None:
        """Close the bag (frames can no longer be read)."""
        with self._lock:
            self._cursor = None
            self._reader.close()
