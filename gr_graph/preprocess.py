"""Per-scan preprocessing, done once per scan: clean, crop, downsample, covariances, KdTree.

The downsampled points are what the memory stores for a scan (``Scan.points``); the
correspondences of the memory index into them.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import small_gicp

from gr_graph.config import PreprocessConfig

log = logging.getLogger(__name__)


class ScanError(ValueError):
    """A scan cannot be used (wrong shape, or too few valid points); the message says why."""


@dataclass
class Scan:
    """A preprocessed scan.

    Attributes
    ----------
    index : int
        Frame index in the sequence.
    points : np.ndarray
        ``(N, 3)`` float64 downsampled points in the LiDAR frame (what the memory stores).
    cloud : small_gicp.PointCloud or None
        The same points with GICP covariances (None when the scan is unusable).
    tree : small_gicp.KdTree or None
        KdTree over ``points``.
    n_raw : int
        Points in the raw scan.
    n_dropped : int
        Raw points dropped as non-finite.
    usable : bool
        False when fewer than ``min_points`` survived; such a scan gets a fallback edge.
    """

    index: int
    points: np.ndarray
    cloud: small_gicp.PointCloud | None
    tree: small_gicp.KdTree | None
    n_raw: int
    n_dropped: int
    usable: bool


def clean_points(points: np.ndarray, cfg: PreprocessConfig, index: int = -1) -> tuple[np.ndarray, int]:
    """Drop non-finite points and crop to ``[min_range, max_range]``.

    Returns
    -------
    points : (M, 3) float64
    n_nonfinite : int
        How many points were dropped for being non-finite (logged when > 0).

    Raises
    ------
    ScanError
        If ``points`` is not an ``(N, 3)`` (or ``(N, 4)``) array.
    """
    p = np.asarray(points)
    if p.ndim != 2 or p.shape[1] not in (3, 4):
        raise ScanError(f"scan {index}: points must be (N, 3), got shape {p.shape}")
    p = np.asarray(p[:, :3], dtype=np.float64)
    finite = np.isfinite(p).all(axis=1)
    n_bad = int(len(p) - finite.sum())
    if n_bad:
        log.warning("scan %d: dropped %d non-finite points", index, n_bad)
        p = p[finite]
    r2 = np.einsum("ij,ij->i", p, p)
    keep = (r2 >= cfg.min_range**2) & (r2 <= cfg.max_range**2)
    return np.ascontiguousarray(p[keep]), n_bad


def preprocess_scan(points: np.ndarray, cfg: PreprocessConfig, index: int = -1, num_threads: int = 1) -> Scan:
    """Clean, voxel-downsample, estimate per-point covariances and build a KdTree.

    A scan with fewer than ``cfg.min_points`` points after downsampling is returned with
    ``usable=False`` (and a logged warning) so that the caller can apply its fallback.
    """
    p, n_bad = clean_points(points, cfg, index)
    n_raw = len(points)
    if len(p) < cfg.min_points:
        log.warning("scan %d: only %d valid points after cropping (min %d): unusable", index, len(p), cfg.min_points)
        return Scan(index, p.reshape(-1, 3), None, None, n_raw, n_bad, False)
    cloud, tree = small_gicp.preprocess_points(
        p, downsampling_resolution=cfg.voxel_size, num_neighbors=cfg.num_neighbors, num_threads=num_threads
    )
    if cloud.size() < cfg.min_points:
        log.warning(
            "scan %d: only %d points after %.2f m downsampling (min %d): unusable",
            index,
            cloud.size(),
            cfg.voxel_size,
            cfg.min_points,
        )
        return Scan(index, np.asarray(cloud.points())[:, :3].copy(), None, None, n_raw, n_bad, False)
    pts = np.asarray(cloud.points())[:, :3].copy()
    return Scan(index, pts, cloud, tree, n_raw, n_bad, True)


def rebuild_scan(points: np.ndarray, cfg: PreprocessConfig, index: int = -1, num_threads: int = 1) -> Scan:
    """Rebuild covariances and KdTree for already-downsampled stored points (no downsampling).

    Used by loop verification and the memory pass, which keep only the stored points.
    """
    p = np.ascontiguousarray(np.asarray(points, dtype=np.float64)[:, :3])
    if len(p) < cfg.min_points:
        return Scan(index, p, None, None, len(p), 0, False)
    cloud = small_gicp.PointCloud(p)
    tree = small_gicp.KdTree(cloud, num_threads=num_threads)
    small_gicp.estimate_covariances(cloud, tree, num_neighbors=cfg.num_neighbors, num_threads=num_threads)
    return Scan(index, p, cloud, tree, len(p), 0, True)
