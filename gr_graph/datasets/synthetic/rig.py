"""The synthetic vehicle's sensor rig: the project's own calibration (not KITTI's numbers).

A LiDAR on the roof above a forward-looking camera, in the KITTI layout's conventions:

- LiDAR frame: x forward, y left, z up. Camera frame: x right, y down, z forward.
- ``T_cam_velo`` (LiDAR -> camera, KITTI's ``Tr``): the axis permutation
  ``x_cam = -y_velo, y_cam = -z_velo, z_cam = x_velo``, followed by a small mounting
  misalignment of the camera (0.25° roll, -0.6° pitch (looking slightly down), 0.15° yaw about
  its own axes); the LiDAR's origin sits 0.33 m above, 0.22 m behind and 0.04 m left of the
  camera's optical centre.
- ``P0``: the rectified projection of camera 0, a 1280 x 384 px image with a 700 px focal
  length and the principal point at (640.0, 192.0).

The sensor rides ``TownConfig.sensor_height`` (1.73 m) above the road.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

LIDAR_IN_CAMERA_M = np.array([-0.04, -0.33, -0.22])
"""The LiDAR origin in the camera frame (m): 4 cm left (-x), 33 cm above (-y), 22 cm behind (-z)."""
CAMERA_MISALIGNMENT_DEG = (0.25, -0.6, 0.15)
"""Roll (about z_cam), pitch (about x_cam; negative = looking down), yaw (about y_cam), degrees."""
IMAGE_SIZE = (1280, 384)
FOCAL_PX = 700.0


def T_cam_velo() -> np.ndarray:
    """The ``(4, 4)`` LiDAR -> camera transform of the synthetic rig."""
    perm = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    roll, pitch, yaw = np.radians(CAMERA_MISALIGNMENT_DEG)
    # the camera is turned by R_mis in its own frame: p_cam = R_mis^T p_nominal
    R_mis = Rotation.from_euler("zxy", [roll, pitch, yaw]).as_matrix()
    T = np.eye(4)
    T[:3, :3] = R_mis.T @ perm
    T[:3, 3] = LIDAR_IN_CAMERA_M
    return T


def P0() -> np.ndarray:
    """The ``(3, 4)`` projection matrix of camera 0 (no baseline)."""
    w, h = IMAGE_SIZE
    return np.array([[FOCAL_PX, 0.0, w / 2, 0.0], [0.0, FOCAL_PX, h / 2, 0.0], [0.0, 0.0, 1.0, 0.0]])
