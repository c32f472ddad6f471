"""Algorithm 2, lines 3-9: anisotropy filter and sampling of M points ~ N(s, C) (numpy).

Anisotropy of a covariance with eigenvalues ``l1 >= l2 >= l3 > 0``::

    a = 1 - l3 / l1    in [0, 1)

``a`` is ~1 for a flat (planar, high-precision) local Gaussian and 0 for an isotropic one. The
paper keeps a point only if ``a > tau_ani`` (near-isotropic predictions mean the Gaussian
surface model does not fit there) and replaces it by ``M`` samples of ``N(s, C)``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["anisotropy", "densify", "symmetric_eigenvalues"]


def symmetric_eigenvalues(C: np.ndarray) -> np.ndarray:
    """``(N, 3)`` ascending eigenvalues of the symmetric parts of ``(N, 3, 3)`` matrices."""
    C = np.asarray(C, np.float64)
    return np.linalg.eigvalsh(0.5 * (C + C.transpose(0, 2, 1)))


def anisotropy(C: np.ndarray, eigenvalues: np.ndarray | None = None) -> np.ndarray:
    """``1 - lambda_min / lambda_max`` of every ``(N, 3, 3)`` SPD covariance, shape ``(N,)``.

    ``eigenvalues``: :func:`symmetric_eigenvalues` of ``C`` when the caller has them already.
    """
    C = np.asarray(C, np.float64)
    if C.ndim != 3 or C.shape[1:] != (3, 3):
        raise ValueError(f"anisotropy: C must be (N, 3, 3), got {C.shape}")
    w = symmetric_eigenvalues(C) if eigenvalues is None else np.asarray(eigenvalues, np.float64)
    if w.shape != (len(C), 3):
        raise ValueError(f"anisotropy: eigenvalues must be ({len(C)}, 3), got {w.shape}")
    if len(w) and w[:, 0].min() <= 0:
        raise ValueError("anisotropy: covariances must be positive definite")
    return 1.0 - w[:, 0] / w[:, 2]


def densify(
    points: np.ndarray,
    C: np.ndarray,
    tau_ani: float = 0.9,
    M: int = 4,
    seed: int = 0,
    include_original: bool = False,
    eigenvalues: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Densified scan ``S+`` of Algorithm 2.

    Parameters
    ----------
    points : (N, 3) array
        Scan points ``s_i``.
    C : (N, 3, 3) array
        Their covariances (e.g. from ``training.predict.predict_covariances``), m^2.
    tau_ani : float
        Anisotropy threshold: only points with ``a_i > tau_ani`` are kept.
    M : int
        Samples per kept point.
    seed : int
        Seed of the sampling (deterministic).
    include_original : bool
        Also keep the kept points themselves (the paper's ``S+`` holds only the samples).
    eigenvalues : (N, 3) array, optional
        :func:`symmetric_eigenvalues` of ``C``, when the caller computed them already.

    Returns
    -------
    dense : (N_kept * M [+ N_kept], 3) float64
        The samples, grouped by source point (``M`` consecutive rows per kept point).
    kept : (N,) bool
        Which input points passed the anisotropy filter.
    """
    x = np.asarray(points, np.float64)
    C = np.asarray(C, np.float64)
    if x.ndim != 2 or x.shape[1] != 3 or C.shape != (len(x), 3, 3):
        raise ValueError(f"densify: points must be (N, 3) and C (N, 3, 3); got {x.shape}, {C.shape}")
    if M < 1:
        raise ValueError(f"densify: M must be >= 1, got {M}")
    if not (np.isfinite(x).all() and np.isfinite(C).all()):
        raise ValueError("densify: non-finite points or covariances")
    kept = anisotropy(C, eigenvalues) > tau_ani
    xs, Cs = x[kept], C[kept]
    L = np.linalg.cholesky(0.5 * (Cs + Cs.transpose(0, 2, 1)))
    z = np.random.default_rng(seed).standard_normal((len(xs), M, 3))
    samples = xs[:, None, :] + np.einsum("nij,nmj->nmi", L, z)
    dense = samples.reshape(-1, 3)
    if include_original:
        dense = np.concatenate([xs, dense])
    return dense, kept
