"""LiDAR sequences: KITTI odometry on disk and the synthetic rendering (a generated route)."""

from gr_graph.datasets.base import DatasetError, LidarFrame, LidarSequence

__all__ = ["DatasetError", "LidarFrame", "LidarSequence"]
