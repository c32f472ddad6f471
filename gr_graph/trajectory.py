"""Trajectory files: KITTI and TUM formats, read and written with full float precision.

Formats
-------
KITTI
    One pose a line, the first three rows of the 4x4 matrix ``T_w_i`` in row-major order:
    12 space-separated floats. No timestamps (KITTI keeps them in ``times.txt``). The
    official odometry ground truth is in the camera-0 frame.
TUM
    One pose a line: ``t x y z qx qy qz qw`` (timestamp in seconds, translation, unit
    quaternion with the scalar last), as in the TUM RGB-D benchmark and evo.

Both readers skip blank lines and lines starting with ``#``, and raise
:class:`TrajectoryFormatError` naming the file and the 1-based line for anything malformed:
non-numeric fields, a wrong column count, non-finite values, a rotation that is not
orthonormal (beyond ``rot_tol``), a quaternion far from unit norm, non-increasing
timestamps. Writers check their input (``ValueError``), format every float with
``%.17g`` (round-trips float64 bit-exactly) and write atomically (a temporary file in the
target directory, then :func:`os.replace`).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

from factors.se3 import ROT_TOL, check_poses, rotation_defects
from gr_graph.atomic import atomic_write_text

if TYPE_CHECKING:  # evo is only needed for the conversion helpers
    from evo.core.trajectory import PosePath3D, PoseTrajectory3D

logger = logging.getLogger(__name__)

PathLike = str | os.PathLike[str]

#: Default tolerance on ``| |q| - 1 |`` for TUM quaternions (files often hold 4-6 digits).
QUAT_NORM_TOL = 1e-3

_FLOAT_FMT = "%.17g"


class TrajectoryFormatError(ValueError):
    """A trajectory file is malformed; the message names the file and the line."""


# ----------------------------------------------------------------------------- helpers


def _check_timestamps(timestamps: np.ndarray, n: int, name: str = "timestamps") -> np.ndarray:
    ts = np.asarray(timestamps, dtype=np.float64)
    if ts.shape != (n,):
        raise ValueError(f"{name}: expected shape ({n},), got {ts.shape}")
    if not np.all(np.isfinite(ts)):
        raise ValueError(f"{name}: index {int(np.argmin(np.isfinite(ts)))} is not finite")
    if n > 1 and not np.all(np.diff(ts) > 0):
        k = int(np.argmin(np.diff(ts) > 0)) + 1
        raise ValueError(f"{name}: not strictly increasing at index {k} ({ts[k - 1]!r} -> {ts[k]!r})")
    return ts


def _format_rows(mat: np.ndarray) -> str:
    if len(mat) == 0:
        return ""
    fmt = " ".join([_FLOAT_FMT] * mat.shape[1])
    return "\n".join(fmt % tuple(row) for row in mat.tolist()) + "\n"


def _parse_rows(path: PathLike, n_cols: int, what: str) -> tuple[np.ndarray, list[int]]:
    """Parse a whitespace-separated numeric file into ``(rows, 1-based line numbers)``."""
    p = Path(path)
    if not p.is_file():
        raise TrajectoryFormatError(f"{p}: {what} file not found")
    rows: list[list[float]] = []
    lines: list[int] = []
    with p.open("r", encoding="utf-8", errors="replace") as fh:
        for lineno, raw in enumerate(fh, start=1):
            s = raw.strip()
            if not s or s.startswith("#"):
                continue
            fields = s.split()
            if len(fields) != n_cols:
                raise TrajectoryFormatError(
                    f"{p}:{lineno}: {what} rows need {n_cols} numbers, got {len(fields)}"
                )
            try:
                vals = [float(f) for f in fields]
            except ValueError:
                bad = next(f for f in fields if not _is_float(f))
                raise TrajectoryFormatError(f"{p}:{lineno}: non-numeric value {bad!r}") from None
            if not all(np.isfinite(vals)):
                raise TrajectoryFormatError(f"{p}:{lineno}: non-finite value in {s!r}")
            rows.append(vals)
            lines.append(lineno)
    if not rows:
        raise TrajectoryFormatError(f"{p}: no poses found (empty {what} file)")
    return np.asarray(rows, dtype=np.float64), lines


def _is_float(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


# ----------------------------------------------------------------------------- KITTI


def read_kitti_poses(path: PathLike, rot_tol: float = ROT_TOL) -> np.ndarray:
    """Read a KITTI pose file.

    Parameters
    ----------
    path : str or PathLike
        File with 12 floats a line (rows 0-2 of each 4x4 pose, row-major).
    rot_tol : float
        Tolerance on the orthonormality of each rotation block (see :data:`ROT_TOL`).

    Returns
    -------
    np.ndarray
        ``(K, 4, 4)`` float64 poses, exactly as stored (not re-orthonormalised).

    Raises
    ------
    TrajectoryFormatError
        Missing/empty file, or a line with the wrong column count, non-numeric or
        non-finite values, or a non-orthonormal rotation; the message names file and line.
    """
    rows, lines = _parse_rows(path, 12, "KITTI")
    K = len(rows)
    poses = np.zeros((K, 4, 4), dtype=np.float64)
    poses[:, :3, :] = rows.reshape(K, 3, 4)
    poses[:, 3, 3] = 1.0
    defects = rotation_defects(poses[:, :3, :3])
    bad = defects > rot_tol
    if bad.any():
        k = int(np.argmax(bad))
        raise TrajectoryFormatError(
            f"{Path(path)}:{lines[k]}: rotation is not orthonormal "
            f"(max |R^T R - I|, |det R - 1| = {defects[k]:.3g} > tolerance {rot_tol:g})"
        )
    logger.debug("read %d KITTI poses from %s", K, path)
    return poses


def write_kitti_poses(path: PathLike, poses: np.ndarray, rot_tol: float = ROT_TOL) -> Path:
    """Write ``(K, 4, 4)`` poses as a KITTI file (12 floats a line, ``%.17g``), atomically.

    Raises
    ------
    ValueError
        If ``poses`` is not a valid stack of rigid transforms (see :func:`check_poses`).
    """
    arr = check_poses(poses, "write_kitti_poses", rot_tol)
    return atomic_write_text(path, _format_rows(arr[:, :3, :].reshape(len(arr), 12)))


# ----------------------------------------------------------------------------- TUM


def poses_to_tum_rows(timestamps: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Return ``(K, 8)`` rows ``t x y z qx qy qz qw`` (quaternion with ``qw >= 0``)."""
    q = Rotation.from_matrix(poses[:, :3, :3]).as_quat()  # x, y, z, w
    q[q[:, 3] < 0] *= -1.0
    return np.column_stack([timestamps, poses[:, :3, 3], q])


def write_tum_poses(
    path: PathLike, timestamps: np.ndarray, poses: np.ndarray, rot_tol: float = ROT_TOL
) -> Path:
    """Write a TUM trajectory (``t x y z qx qy qz qw`` a line, ``%.17g``), atomically.

    Parameters
    ----------
    path : str or PathLike
        Output file.
    timestamps : array_like
        ``(K,)`` strictly increasing, finite seconds.
    poses : array_like
        ``(K, 4, 4)`` rigid transforms.
    rot_tol : float
        Orthonormality tolerance of the rotation blocks.

    Raises
    ------
    ValueError
        Invalid poses or timestamps.
    """
    arr = check_poses(poses, "write_tum_poses", rot_tol)
    ts = _check_timestamps(timestamps, len(arr), "write_tum_poses timestamps")
    return atomic_write_text(path, _format_rows(poses_to_tum_rows(ts, arr)))


def read_tum_poses(
    path: PathLike, quat_norm_tol: float = QUAT_NORM_TOL
) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory file.

    Parameters
    ----------
    path : str or PathLike
        File with ``t x y z qx qy qz qw`` a line.
    quat_norm_tol : float
        Largest accepted ``| |q| - 1 |``; accepted quaternions are normalised.

    Returns
    -------
    timestamps : np.ndarray
        ``(K,)`` float64 seconds.
    poses : np.ndarray
        ``(K, 4, 4)`` float64 poses.

    Raises
    ------
    TrajectoryFormatError
        Missing/empty file, wrong column count, non-numeric or non-finite values, a
        quaternion far from unit norm, or timestamps that do not strictly increase.
    """
    rows, lines = _parse_rows(path, 8, "TUM")
    ts = rows[:, 0]
    q = rows[:, 4:8]
    norms = np.linalg.norm(q, axis=1)
    bad = np.abs(norms - 1.0) > quat_norm_tol
    if bad.any():
        k = int(np.argmax(bad))
        raise TrajectoryFormatError(
            f"{Path(path)}:{lines[k]}: quaternion norm {norms[k]:.6g} is not 1 "
            f"(tolerance {quat_norm_tol:g})"
        )
    dts = np.diff(ts)
    if (dts <= 0).any():
        k = int(np.argmax(dts <= 0)) + 1
        raise TrajectoryFormatError(
            f"{Path(path)}:{lines[k]}: timestamp {ts[k]!r} does not increase "
            f"(previous {ts[k - 1]!r})"
        )
    K = len(rows)
    poses = np.zeros((K, 4, 4), dtype=np.float64)
    poses[:, :3, :3] = Rotation.from_quat(q / norms[:, None]).as_matrix()
    poses[:, :3, 3] = rows[:, 1:4]
    poses[:, 3, 3] = 1.0
    logger.debug("read %d TUM poses from %s", K, path)
    return ts.copy(), poses


def read_kitti_times(path: PathLike) -> np.ndarray:
    """Read a KITTI ``times.txt`` (one float a line) into ``(K,)`` float64 seconds."""
    rows, lines = _parse_rows(path, 1, "times")
    ts = rows[:, 0]
    dts = np.diff(ts)
    if (dts <= 0).any():
        k = int(np.argmax(dts <= 0)) + 1
        raise TrajectoryFormatError(f"{Path(path)}:{lines[k]}: timestamp {ts[k]!r} does not increase")
    return ts.copy()


# ----------------------------------------------------------------------------- dataclass


@dataclass(frozen=True)
class Trajectory:
    """A timed sequence of poses.

    Attributes
    ----------
    timestamps : np.ndarray
        ``(K,)`` float64 seconds, strictly increasing.
    poses : np.ndarray
        ``(K, 4, 4)`` float64 ``T_w_i``.
    """

    timestamps: np.ndarray
    poses: np.ndarray

    def __post_init__(self) -> None:
        poses = check_poses(self.poses, "Trajectory.poses")
        ts = _check_timestamps(self.timestamps, len(poses), "Trajectory.timestamps")
        object.__setattr__(self, "poses", poses)
        object.__setattr__(self, "timestamps", ts)

    def __len__(self) -> int:
        return len(self.poses)

    @property
    def positions(self) -> np.ndarray:
        """``(K, 3)`` translations."""
        return self.poses[:, :3, 3]

    @classmethod
    def from_poses(cls, poses: np.ndarray, dt: float = 0.1) -> "Trajectory":
        """Build a trajectory with synthetic timestamps ``0, dt, 2 dt, ...``."""
        arr = np.asarray(poses, dtype=np.float64)
        return cls(np.arange(len(arr), dtype=np.float64) * dt, arr)

    @classmethod
    def read_kitti(cls, path: PathLike, times_path: PathLike | None = None, dt: float = 0.1) -> "Trajectory":
        """Read a KITTI pose file, with timestamps from ``times_path`` (else ``i * dt``)."""
        poses = read_kitti_poses(path)
        if times_path is None:
            return cls.from_poses(poses, dt)
        ts = read_kitti_times(times_path)
        if len(ts) != len(poses):
            raise TrajectoryFormatError(
                f"{times_path}: {len(ts)} timestamps for {len(poses)} poses in {path}"
            )
        return cls(ts, poses)

    @classmethod
    def read_tum(cls, path: PathLike) -> "Trajectory":
        """Read a TUM trajectory file."""
        ts, poses = read_tum_poses(path)
        return cls(ts, poses)

    def write_kitti(self, path: PathLike) -> Path:
        """Write the poses as a KITTI file (timestamps are not stored in this format)."""
        return write_kitti_poses(path, self.poses)

    def write_tum(self, path: PathLike) -> Path:
        """Write the trajectory as a TUM file."""
        return write_tum_poses(path, self.timestamps, self.poses)

    def to_evo(self) -> "PoseTrajectory3D":
        """Convert to :class:`evo.core.trajectory.PoseTrajectory3D` (copies the poses)."""
        from evo.core.trajectory import PoseTrajectory3D

        return PoseTrajectory3D(poses_se3=list(self.poses.copy()), timestamps=self.timestamps.copy())

    @classmethod
    def from_evo(cls, traj: "PosePath3D", dt: float = 0.1) -> "Trajectory":
        """Convert from an evo path/trajectory (timestamps ``i * dt`` if it has none)."""
        poses = np.asarray(traj.poses_se3, dtype=np.float64)
        ts = getattr(traj, "timestamps", None)
        if ts is None:
            return cls.from_poses(poses, dt)
        return cls(np.asarray(ts, dtype=np.float64), poses)


def to_evo_path(poses: np.ndarray) -> "PosePath3D":
    """Wrap ``(K, 4, 4)`` poses as an evo :class:`~evo.core.trajectory.PosePath3D` (copied)."""
    from evo.core.trajectory import PosePath3D

    arr = np.array(poses, dtype=np.float64, copy=True)
    return PosePath3D(poses_se3=list(arr))
