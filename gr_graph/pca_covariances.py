"""Per-point covariances without a network: PCA of each point's nearest neighbours.

The ablation ``training.covariances: pca`` replaces the trained network f_theta by this
classical estimate (the GICP covariance): for every point ``s_i`` of a preprocessed scan, the
``k`` nearest points of the same scan (the point itself included) give

    C_i = 1/k sum_j (s_j - mu_i)(s_j - mu_i)^T + eps I,   mu_i = 1/k sum_j s_j,

with ``k = preprocess.num_neighbors`` and ``eps`` the network's ``trainer.net.eps`` (so that
the same floor applies as to the network's output). The result is used exactly where the
network's output would be: densification (:mod:`gr_graph.densify`) and the learned edge noise
(:mod:`gr_graph.edge_noise`). No training happens.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["pca_covariances", "PcaCovariances"]


def pca_covariances(points: np.ndarray, k: int, eps: float = 0.0) -> np.ndarray:
    """Covariance of the ``k`` nearest neighbours of every point, plus ``eps`` on the diagonal.

    Parameters
    ----------
    points : (N, 3) array
        A preprocessed scan.
    k : int
        Neighbours per point, the point itself included (at most ``N`` are used).
    eps : float
        Added to the diagonal [m^2]; 0: 1e-9 x the neighbourhood's trace instead (1e-12 m^2 when every
        neighbour is at one place), so that planar or straight neighbourhoods stay positive definite.

    Returns
    -------
    (N, 3, 3) float64 array

    Raises
    ------
    ValueError
        If ``points`` is not ``(N, 3)`` with ``N >= 2`` or ``k < 2``.
    """
    P = np.asarray(points, np.float64)
    if P.ndim != 2 or P.shape[1] != 3 or len(P) < 2:
        raise ValueError(f"pca_covariances: points must be (N, 3) with N >= 2, got {P.shape}")
    if k < 2:
        raise ValueError(f"pca_covariances: k must be >= 2, got {k}")
    kk = min(int(k), len(P))
    _, idx = cKDTree(P).query(P, k=kk)
    nb = P[idx]  # (N, k, 3)
    d = nb - nb.mean(axis=1, keepdims=True)
    C = np.einsum("nki,nkj->nij", d, d) / kk
    if eps > 0.0:
        C += float(eps) * np.eye(3)
        return C
    # eps 0 (valid with the network's geometric head): a planar or straight neighbourhood (noise-free
    # data) would be singular; a floor relative to its size keeps it positive definite
    floor = 1e-9 * np.trace(C, axis1=1, axis2=2)
    floor[floor <= 0.0] = 1e-12  # every neighbour at one place
    C += floor[:, None, None] * np.eye(3)
    return C


class PcaCovariances:
    """Callable ``points (N, 3) -> C (N, 3, 3)`` for :func:`gr_graph.densify.densified_sequence`."""

    def __init__(self, k: int, eps: float) -> None:
        self.k = int(k)
        self.eps = float(eps)

    def __call__(self, points: np.ndarray) -> np.ndarray:
        return pca_covariances(points, self.k, self.eps)
