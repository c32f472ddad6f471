"""Neighbour structures for the covariance network, precomputed in numpy with scipy's cKDTree.

The network (``training.network``) never searches neighbours itself: every index it gathers
is computed here once per scan (in the dataset, i.e. outside autograd and reusable across
epochs), which keeps the forward pass to dense gathers and small MLPs.

Hierarchy (PointNet++-style)::

    level 0: all N input points; knn0 (N, k0) = k0 nearest input points of every point
    level 1: N1 = N // ratio1 centroids (random or farthest-point sampling of the input points);
             knn1 (N1, k1) = k1 nearest *input* points of every centroid
    level 2: N2 = N1 // ratio2 centroids (sampled from level 1); knn2 (N2, k2) into level 1
    up21 / w21: 3 nearest level-2 centroids of every level-1 point, inverse-distance weights
    up10 / w10: 3 nearest level-1 centroids of every input point, inverse-distance weights

Sampling: ``"random"`` (default) draws the centroids uniformly without replacement; on the
voxel-downsampled scans of the memory (roughly uniform density) this covers the scene about as
well as farthest-point sampling (``"fps"``, PointNet++'s choice), at a fraction of the cost
(FPS is O(N * N1) and dominated the time per training pair).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["Neighborhoods", "farthest_point_sampling", "build_neighborhoods"]


@dataclass
class Neighborhoods:
    """Index arrays of one scan (all int64 / float32 numpy, see module docstring)."""

    knn0: np.ndarray
    idx1: np.ndarray
    knn1: np.ndarray
    idx2: np.ndarray
    knn2: np.ndarray
    up21: np.ndarray
    w21: np.ndarray
    up10: np.ndarray
    w10: np.ndarray
    knnw: np.ndarray

    def as_dict(self) -> dict[str, np.ndarray]:
        """The arrays by name (for collation / torch conversion)."""
        return dict(self.__dict__)


def farthest_point_sampling(x: np.ndarray, m: int, start: int = 0) -> np.ndarray:
    """Indices of ``m`` points of ``x`` (N,3) chosen by farthest-point sampling from ``start``."""
    n = len(x)
    m = min(m, n)
    out = np.empty(m, np.int64)
    dist = np.full(n, np.inf)
    cur = start
    for i in range(m):
        out[i] = cur
        dist = np.minimum(dist, ((x - x[cur]) ** 2).sum(1))
        cur = int(np.argmax(dist))
    return out


def _knn(tree: cKDTree, queries: np.ndarray, k: int, n_src: int) -> tuple[np.ndarray, np.ndarray]:
    kk = min(k, n_src)
    d, i = tree.query(queries, k=kk)
    d = np.asarray(d, np.float64).reshape(len(queries), kk)
    i = np.asarray(i, np.int64).reshape(len(queries), kk)
    if kk < k:  # pad by repeating the nearest neighbour (max-pooling ignores duplicates)
        i = np.concatenate([i, np.repeat(i[:, :1], k - kk, 1)], 1)
        d = np.concatenate([d, np.repeat(d[:, :1], k - kk, 1)], 1)
    return d, i


def _interp_weights(d: np.ndarray) -> np.ndarray:
    """Inverse-distance weights (rows sum to 1, float32) of ``(M, 3)`` neighbour distances."""
    w = 1.0 / np.maximum(d, 1e-8)
    w /= w.sum(1, keepdims=True)
    return w.astype(np.float32)


def _interp(tree: cKDTree, queries: np.ndarray, n_src: int) -> tuple[np.ndarray, np.ndarray]:
    d, i = _knn(tree, queries, 3, n_src)
    return i, _interp_weights(d)


def build_neighborhoods(
    points: np.ndarray,
    k0: int = 16,
    ratio1: int = 4,
    k1: int = 16,
    ratio2: int = 4,
    k2: int = 16,
    start: int = 0,
    sampling: str = "random",
    kw: int = 16,
) -> Neighborhoods:
    """Precompute all neighbour indices of one (subsampled) scan.

    Parameters
    ----------
    points : (N, 3) array, N >= 1
        Input points of the network.
    k0, k1, k2 : int
        Group sizes of the three levels.
    ratio1, ratio2 : int
        Down-sampling ratios of levels 1 and 2 (at least one centroid is kept).
    start : int
        Seed of the random sampling / first index of the farthest-point sampling.
    sampling : str
        ``"random"`` or ``"fps"``.
    kw : int
        Size of the wide per-point neighbourhood (among level-1 centroids).
    """
    x = np.asarray(points, np.float64)
    if x.ndim != 2 or x.shape[1] != 3 or len(x) == 0:
        raise ValueError(f"build_neighborhoods: points must be a non-empty (N, 3) array, got {x.shape}")
    n = len(x)
    tree0 = cKDTree(x)
    _, knn0 = _knn(tree0, x, k0, n)
    n1 = max(1, n // ratio1)
    n2 = max(1, n1 // ratio2)
    if sampling == "fps":
        idx1 = farthest_point_sampling(x, n1, start % n)
        idx2 = farthest_point_sampling(x[idx1], n2, 0)
    elif sampling == "random":
        rng = np.random.default_rng(start)
        idx1 = np.sort(rng.choice(n, n1, replace=False))
        idx2 = np.sort(rng.choice(n1, n2, replace=False))
    else:
        raise ValueError(f"build_neighborhoods: sampling must be 'random' or 'fps', got {sampling!r}")
    x1 = x[idx1]
    _, knn1 = _knn(tree0, x1, k1, n)
    x2 = x1[idx2]
    tree1 = cKDTree(x1)
    _, knn2 = _knn(tree1, x2, k2, len(x1))
    tree2 = cKDTree(x2)
    up21, w21 = _interp(tree2, x1, len(x2))
    # one query of the input points in level 1 serves both the interpolation (3 nearest) and the
    # wide neighbourhood (kw nearest): the k nearest come sorted by distance
    d10, i10 = _knn(tree1, x, max(kw, 3), len(x1))
    up10, w10 = np.ascontiguousarray(i10[:, :3]), _interp_weights(d10[:, :3])
    knnw = np.ascontiguousarray(i10[:, :kw])
    return Neighborhoods(knn0, idx1, knn1, idx2, knn2, up21, w21, up10, w10, knnw)
