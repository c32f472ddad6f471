"""LiDAR sequences: KITTI odometry on disk and the synthetic KITTI-00 rendering."""

from gr_graph.datasets.base import DatasetError, LidarFrame, LidarSequence

__all__ = ["DatasetError", "LidarFrame", "LidarSequence"]
