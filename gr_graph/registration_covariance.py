"""Covariance of a registered pose from its own residuals, without assuming independent points.

A GICP / VGICP registration minimises ``1/2 sum_i d_i^T Lambda_i d_i`` with ``d_i = q_i - T p_i``
and ``Lambda_i = (C_qi + R C_pi R^T)^-1``. Its Gauss-Newton Hessian
``H = sum_i J_i^T Lambda_i J_i`` is the pose information only if the point residuals are
independent with covariance ``Lambda_i^-1``. They are neither: small_gicp's covariances are
unit-less plane shapes, and neighbouring points share the surface, the beam and the sensor's
errors (a beam whose elevation is off by a few hundredths of a degree tilts a whole ring of
ground points the same way). The registration-Hessian noise model
(:func:`gr_graph.odometry.scaled_information`) rescales ``H`` by the residuals' variance factor
and a fixed ``graph.hessian_scale``; one factor for all six axes, so it cannot say that roll and
pitch, held by a few rings of ground, are worse determined than the Hessian's shape claims.

The cluster-robust ("sandwich", Liang-Zeger / Huber-White) covariance estimates the spread of the
estimate from the residuals themselves and lets the residuals within a cluster be correlated
arbitrarily::

    g_i   = J_i^T Lambda_i d_i                    (the point's term of the cost gradient)
    g_c   = sum_{i in c} g_i                      (clusters: cubes of side ``cluster_size`` [m]
                                                  around the source points, source frame)
    M     = G / (G - 1) sum_c g_c g_c^T           (G clusters; the usual small-sample factor)
    Sigma = H^-1 M H^-1

At the optimum ``sum_i g_i = 0``; the spread of the cluster sums around it is what the data say
about the gradient's noise. If the residuals were independent with covariance ``s^2 Lambda^-1``,
``Sigma -> s^2 H^-1`` (the variance-factor-scaled Hessian without ``hessian_scale``). ``Sigma`` does
not depend on the cost's unit: scaling every ``Lambda_i`` by ``a`` scales ``H`` and ``g`` by ``a``.
Residuals that every cluster shares (a bias that moves the whole scan consistently, e.g. a
global elevation error common to both scans) are invisible to it, as to any residual-based
estimate. Ground truth is not used; :mod:`gr_graph.noise_consistency` checks the result.

Correspondences are rebuilt at the registration's result the way small_gicp builds them:
VGICP (odometry) takes the target voxel that contains the transformed source point, GICP (loop
verification) the nearest target point, both within the registration's correspondence distance.
``graph.registration_covariance: cluster_robust`` selects this model (fallback to the scaled
Hessian, counted, when fewer than ``graph.min_clusters`` clusters hold correspondences or the
result is not positive definite).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import small_gicp

from factors.wls import _components, _inv3_spd, _matrices, _rotate_covariances, _spd_flags, wls_cost_gradient_hessian

__all__ = ["point_gradients", "cube_labels", "cluster_robust_covariance", "Correspondences", "vgicp_correspondences",
           "gicp_correspondences", "cluster_robust_information", "sandwich_information"]

# Voxel keys are packed exactly into one int64: 21 bits per axis (+- 2^20 voxels).
_KEY_BITS = 21
_KEY_OFFSET = 1 << (_KEY_BITS - 1)


def point_gradients(T: np.ndarray, p: np.ndarray, q: np.ndarray, info: np.ndarray) -> np.ndarray:
    """``(N, 6)`` per-correspondence gradient terms ``J_i^T Lambda_i d_i`` ([omega, v], right perturbation).

    ``d_i = q_i - T p_i`` and ``J_i = [R [p_i]_x, -R]`` as in :func:`factors.wls.wls_residuals`, so
    ``J_i^T u = [(R^T u) x p_i, -R^T u]`` with ``u = Lambda_i d_i``. Their sum is
    :func:`factors.wls.wls_cost_gradient_hessian`'s gradient.

    Parameters
    ----------
    T : (4, 4) array
        Transform mapping source points ``p`` into the target frame.
    p, q : (N, 3) arrays
        Source and target points of the correspondences.
    info : (N, 3, 3) array
        Residual information ``Lambda_i``.
    """
    R, t = T[:3, :3], T[:3, 3]
    d = q - p @ R.T - t
    u = (info @ d[:, :, None])[:, :, 0] @ R  # rows R^T Lambda_i d_i
    return np.concatenate([np.cross(u, p), -u], axis=1)


def cube_labels(points: np.ndarray, size: float) -> tuple[np.ndarray, int]:
    """Cluster label of each point: the cube of side ``size`` it lies in; returns ``(labels, n_clusters)``."""
    if not size > 0:
        raise ValueError(f"cluster size must be positive, got {size}")
    keys = _pack(np.floor(np.asarray(points, np.float64) / size).astype(np.int64))
    _, labels = np.unique(keys, return_inverse=True)
    labels = labels.ravel()
    return labels, int(labels.max()) + 1 if len(labels) else 0


def cluster_robust_covariance(H: np.ndarray, gradients: np.ndarray, labels: np.ndarray, n_clusters: int,
                              min_clusters: int = 2) -> np.ndarray | None:
    """Sandwich covariance ``H^-1 M H^-1`` with ``M = G/(G-1) sum_c g_c g_c^T`` (module docstring).

    Parameters
    ----------
    H : (6, 6) array
        Gauss-Newton Hessian of the registration cost at its optimum.
    gradients : (N, 6) array
        Per-correspondence gradient terms (:func:`point_gradients`).
    labels : (N,) int array
        Cluster of each correspondence, ``0 .. n_clusters - 1``.
    n_clusters : int
    min_clusters : int
        Fewer clusters than this give ``None`` (the 6x6 ``M`` is not estimable from a handful; it
        has rank at most the number of clusters).

    Returns
    -------
    (6, 6) array or None
        The covariance, or ``None`` when there are too few clusters, ``H`` is not positive
        definite or the result is not finite and positive definite.
    """
    if n_clusters < max(min_clusters, 2) or len(gradients) == 0:
        return None
    sums = np.stack([np.bincount(labels, weights=gradients[:, a], minlength=n_clusters) for a in range(6)], axis=1)
    M = sums.T @ sums * (n_clusters / (n_clusters - 1))
    try:
        L = np.linalg.cholesky(0.5 * (H + H.T))
    except np.linalg.LinAlgError:
        return None
    H_inv = np.linalg.inv(L).T @ np.linalg.inv(L)
    cov = H_inv @ M @ H_inv
    cov = 0.5 * (cov + cov.T)
    if not np.all(np.isfinite(cov)):
        return None
    eigenvalues = np.linalg.eigvalsh(cov)
    if eigenvalues[0] <= 1e-9 * eigenvalues[-1]:  # M of rank < 6 (few clusters): singular to round-off
        return None
    return cov


@dataclass
class Correspondences:
    """Matched source / target points and covariances of a registration at its result."""

    p: np.ndarray  # (N, 3) source points, source frame
    q: np.ndarray  # (N, 3) target points, target frame
    cov_p: np.ndarray  # (N, 3, 3)
    cov_q: np.ndarray  # (N, 3, 3)


def _pack(keys: np.ndarray) -> np.ndarray:
    k = keys + _KEY_OFFSET
    return (k[:, 0] << (2 * _KEY_BITS)) | (k[:, 1] << _KEY_BITS) | k[:, 2]


#: Voxel size [m] of the copy through which a cloud's points and covariances are read (far below any
#: downsampling, so one point a voxel, whose Gaussian is the point's own)
_READ_RESOLUTION = 1e-3


def _cloud(cloud: small_gicp.PointCloud) -> tuple[np.ndarray, np.ndarray]:
    """A cloud's points ``(N, 3)`` and covariances ``(N, 3, 3)``, in the cloud's order.

    ``PointCloud.covs()`` returns a Python list of N 4x4 arrays (tens of ms a scan); a Gaussian voxel
    map of the cloud at :data:`_READ_RESOLUTION` returns the same Gaussians as two arrays, one voxel
    a point in insertion order. Where that does not hold (two points in one voxel, another
    order), checked against the cloud's points, the covariances are read the slow way.
    """
    points = np.asarray(cloud.points())[:, :3]
    voxels = small_gicp.GaussianVoxelMap(_READ_RESOLUTION)
    voxels.insert(cloud)
    voxel_points, voxel_covs = _gaussians(voxels)
    if voxel_points.shape == points.shape and np.array_equal(voxel_points, points):
        return points, voxel_covs
    return points, np.asarray(cloud.covs()).reshape(-1, 4, 4)[:, :3, :3]


def _gaussians(voxels: small_gicp.GaussianVoxelMap) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(voxels.voxel_points())[:, :3], np.asarray(voxels.voxel_covs()).reshape(-1, 4, 4)[:, :3, :3]


def _within(p: np.ndarray, q: np.ndarray, T: np.ndarray, max_distance: float) -> np.ndarray:
    d = q - p @ T[:3, :3].T - T[:3, 3]
    return np.einsum("ij,ij->i", d, d) < max_distance**2


def vgicp_correspondences(voxel_map: small_gicp.GaussianVoxelMap, cloud: small_gicp.PointCloud, T: np.ndarray,
                          resolution: float, max_distance: float) -> Correspondences:
    """VGICP's correspondences at ``T``: each source point with the target voxel (Gaussian) containing it.

    ``T`` maps the source cloud into the voxel map's frame; a pair counts when the voxel's mean lies
    within ``max_distance`` of the transformed point (small_gicp's correspondence rejection).
    """
    p, cov_p = _cloud(cloud)
    mu, cov_mu = _gaussians(voxel_map)
    if len(mu) == 0:
        return Correspondences(p[:0], mu, cov_p[:0], cov_mu)
    voxel_keys = _pack(np.floor(mu / resolution).astype(np.int64))
    order = np.argsort(voxel_keys)
    sorted_keys = voxel_keys[order]
    point_keys = _pack(np.floor((p @ T[:3, :3].T + T[:3, 3]) / resolution).astype(np.int64))
    pos = np.minimum(np.searchsorted(sorted_keys, point_keys), len(sorted_keys) - 1)
    i = np.nonzero(sorted_keys[pos] == point_keys)[0]
    j = order[pos[i]]
    keep = _within(p[i], mu[j], T, max_distance)
    i, j = i[keep], j[keep]
    return Correspondences(p[i], mu[j], cov_p[i], cov_mu[j])


def gicp_correspondences(target: small_gicp.PointCloud, target_tree: small_gicp.KdTree, source: small_gicp.PointCloud,
                         T: np.ndarray, max_distance: float) -> Correspondences:
    """GICP's correspondences at ``T``: each source point with its nearest target point within ``max_distance``."""
    p, cov_p = _cloud(source)
    q_all, cov_q_all = _cloud(target)  # the tree's indices are in the target cloud's order
    idx, d2 = target_tree.batch_nearest_neighbor_search(p @ T[:3, :3].T + T[:3, 3])
    idx, d2 = np.asarray(idx, np.int64), np.asarray(d2)
    i = np.nonzero((d2 < max_distance**2) & (idx >= 0) & (idx < len(q_all)))[0]
    j = idx[i]
    return Correspondences(p[i], q_all[j], cov_p[i], cov_q_all[j])


def cluster_robust_information(T: np.ndarray, corr: Correspondences, cluster_size: float,
                               min_clusters: int) -> tuple[np.ndarray | None, int]:
    """Information ``Sigma^-1`` of the registration's pose ([omega, v]) by the cluster-robust covariance.

    Returns ``(information or None, number of clusters)``; ``None`` when the covariance is not
    available (too few clusters, a singular Hessian, too few correspondences): the caller falls
    back to the scaled Hessian and counts it.
    """
    if len(corr.p) < 6:
        return None, 0
    # GICP residual information (C_q + R C_p R^T)^-1, in factors.wls's (9, N) layout; pairs whose sum is
    # not positive definite are left out (residual_information would raise on them)
    S = _components(corr.cov_q) + _rotate_covariances(_components(corr.cov_p), T[:3, :3])
    with np.errstate(all="ignore"):
        ok = np.isfinite(S).all(axis=0) & _spd_flags(S)
    p, q, info = corr.p[ok], corr.q[ok], _matrices(_inv3_spd(S[:, ok]))
    if len(p) < 6:
        return None, 0
    _, _, H = wls_cost_gradient_hessian(T, p, q, info)
    return sandwich_information(T, p, q, info, H, cluster_size, min_clusters)


def sandwich_information(T: np.ndarray, p: np.ndarray, q: np.ndarray, info: np.ndarray, H: np.ndarray,
                         cluster_size: float, min_clusters: int,
                         added_covariance: np.ndarray | None = None) -> tuple[np.ndarray | None, int]:
    """``(Sigma + added_covariance)^-1`` (symmetrised) for the sandwich ``Sigma`` of a WLS cost at ``T``.

    ``Sigma`` is :func:`cluster_robust_covariance` of ``H`` (the cost's Gauss-Newton Hessian at ``T``)
    and the pairs' gradient terms (:func:`point_gradients`) summed over cubes of ``cluster_size``
    around the source points ``p``. Returns ``(information or None, number of clusters)``; None when
    the covariance is not available (too few clusters, not positive definite, singular). Shared by
    :func:`cluster_robust_information` and :func:`gr_graph.edge_noise.learned_sandwich_information`.
    """
    labels, n_clusters = cube_labels(p, cluster_size)
    cov = cluster_robust_covariance(H, point_gradients(T, p, q, info), labels, n_clusters, min_clusters)
    if cov is None:
        return None, n_clusters
    if added_covariance is not None:
        cov = cov + added_covariance
    try:
        information = np.linalg.inv(cov)
    except np.linalg.LinAlgError:
        return None, n_clusters
    return 0.5 * (information + information.T), n_clusters
