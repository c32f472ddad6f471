"""The optimised map of a run: every scan placed with the final trajectory, voxel-downsampled, as PLY.

:class:`VoxelMap` accumulates points scan by scan into a voxel grid anchored at the world
origin (voxel ``floor(p / voxel_size)``) and keeps, per occupied voxel, the sum and the count
of its points; the map holds one point per voxel, the centroid of every point that fell into
it, and a ``count`` property. Points are buffered in batches of ``flush_points``; a batch is
reduced to its own voxels, then merged into the sorted grid (voxels already there are summed in
place, new ones inserted), so memory stays under about 2.5 times the downsampled map plus one
batch. (The merge used to concatenate the map with a batch as large as the map: a 1.6 GB
transient at the end of a full 64-channel sequence.) A whole sequence never sits in RAM point
by point.

:func:`write_map` does it for a run's scans (the downsampled, deskewed scans SLAM registered,
``SlamResult.scans``, LiDAR frame) and poses (``T_w_velo``, world = LiDAR frame of the first
scan); the pipeline writes ``round_<r>/map.ply`` with it (``output.map``).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from gr_graph.cloud_io import write_ply

__all__ = ["VoxelMap", "write_map", "MAP_NAME"]

log = logging.getLogger(__name__)

MAP_NAME = "map.ply"
_BITS = 21
_OFFSET = 1 << (_BITS - 1)
_MASK = (1 << _BITS) - 1


class VoxelMap:
    """Streaming voxel-grid downsampling (module docstring).

    Parameters
    ----------
    voxel_size : float
        Edge of a voxel [m].
    flush_points : int
        Smallest batch merged into the grid.
    """

    def __init__(self, voxel_size: float, flush_points: int = 1_000_000) -> None:
        if not voxel_size > 0:
            raise ValueError(f"VoxelMap: voxel_size must be > 0, got {voxel_size}")
        self.voxel_size = float(voxel_size)
        self.flush_points = int(flush_points)
        self._keys = np.zeros(0, np.int64)
        self._sums = np.zeros((0, 3), np.float64)
        self._counts = np.zeros(0, np.int64)
        self._buffer: list[np.ndarray] = []
        self._buffered = 0
        self.n_added = 0

    def keys(self, points: np.ndarray) -> np.ndarray:
        """One int64 per point naming its voxel (21 bits per axis: +-2^20 voxels from the origin)."""
        idx = np.floor(np.asarray(points, np.float64) / self.voxel_size).astype(np.int64)
        if len(idx) and (idx.min() < -_OFFSET or idx.max() >= _OFFSET):
            raise ValueError(f"VoxelMap: points beyond +-{_OFFSET * self.voxel_size:.0f} m of the origin "
                             f"at voxel {self.voxel_size} m")
        idx += _OFFSET
        return (idx[:, 0] << (2 * _BITS)) | (idx[:, 1] << _BITS) | idx[:, 2]

    def add(self, points: np.ndarray) -> None:
        """Add ``(N, 3)`` world points (non-finite rows are dropped)."""
        p = np.asarray(points, np.float64).reshape(-1, 3)
        p = p[np.isfinite(p).all(axis=1)]
        self._buffer.append(p)
        self._buffered += len(p)
        self.n_added += len(p)
        if self._buffered >= self.flush_points:
            self._flush()

    def _flush(self) -> None:
        if not self._buffer:
            return
        p = np.concatenate(self._buffer)
        self._buffer, self._buffered = [], 0
        # reduce the batch to its own voxels first, then merge them into the sorted grid
        batch_keys, inv = np.unique(self.keys(p), return_inverse=True)
        batch_sums = np.stack([np.bincount(inv, weights=p[:, c], minlength=len(batch_keys)) for c in range(3)], axis=1)
        batch_counts = np.bincount(inv, minlength=len(batch_keys)).astype(np.int64)
        del p, inv
        pos = np.searchsorted(self._keys, batch_keys)
        known = pos < len(self._keys)
        known[known] = self._keys[pos[known]] == batch_keys[known]
        self._sums[pos[known]] += batch_sums[known]
        self._counts[pos[known]] += batch_counts[known]
        new = ~known
        # one new copy of one array at a time; np.insert keeps the grid sorted (batch_keys is sorted)
        self._keys = np.insert(self._keys, pos[new], batch_keys[new])
        self._sums = np.insert(self._sums, pos[new], batch_sums[new], axis=0)
        self._counts = np.insert(self._counts, pos[new], batch_counts[new])

    def __len__(self) -> int:
        self._flush()
        return len(self._keys)

    def points(self) -> tuple[np.ndarray, np.ndarray]:
        """``(centroids (V, 3) float64, counts (V,) int64)``, one row per occupied voxel, by voxel key."""
        self._flush()
        return self._sums / self._counts[:, None], self._counts.copy()


def write_map(path: str | os.PathLike[str], scans: Iterable[np.ndarray], poses: np.ndarray,
              voxel_size: float) -> dict[str, float | int]:
    """Place every scan with its pose, voxel-downsample, write a PLY (``x, y, z`` float32 and
    ``count`` int32: points merged into the voxel; open3d reads no unsigned PLY properties) atomically; return ``{"points", "voxels", "voxel_size"}``,
    and ``scans_left_out`` when scans whose pose is not finite were left out (logged with their numbers).

    Parameters
    ----------
    scans : iterable of (N_k, 3) arrays
        Scans in the LiDAR frame, in the order of ``poses`` (read one at a time).
    poses : (K, 4, 4) array
        ``T_w_velo`` of each scan.
    """
    vmap = VoxelMap(voxel_size)
    n = 0
    left_out: list[int] = []
    for k, scan in enumerate(scans):
        if k >= len(poses):
            raise ValueError(f"{path}: more scans than the {len(poses)} poses")
        n += 1
        T = np.asarray(poses[k], np.float64)
        if not np.isfinite(T).all():
            left_out.append(k)
            continue
        s = np.asarray(scan, np.float64).reshape(-1, 3)
        vmap.add(s @ T[:3, :3].T + T[:3, 3])
    if n != len(poses):
        raise ValueError(f"{path}: {n} scans for {len(poses)} poses")
    if left_out:
        log.warning("%s: %d scans left out of the map, their poses are not finite (scans %s%s)", path,
                    len(left_out), ", ".join(map(str, left_out[:10])), ", ..." if len(left_out) > 10 else "")
    centroids, counts = vmap.points()
    write_ply(path, centroids, extra={"count": np.minimum(counts, np.iinfo(np.int32).max).astype(np.int32)})
    out: dict[str, float | int] = {"points": int(vmap.n_added), "voxels": int(len(centroids)),
                                   "voxel_size": float(voxel_size)}
    if left_out:
        out["scans_left_out"] = len(left_out)
    return out


def map_path(round_dir: str | os.PathLike[str]) -> Path:
    """``round_dir / map.ply``."""
    return Path(round_dir) / MAP_NAME
