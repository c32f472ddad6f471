"""LiDAR sequences: KITTI odometry and raw drives, ROS bags and MCAP, folders of scans, and the synthetic rendering."""

from gr_graph.datasets.base import DatasetError, LidarFrame, LidarSequence

__all__ = ["DatasetError", "LidarFrame", "LidarSequence"]
