"""Random poses, points and anisotropic covariances shared by the factors tests."""

from __future__ import annotations

import numpy as np

from factors.se3 import exp_se3


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """Uniformly random rotation (QR of a Gaussian matrix, sign-fixed)."""
    Q, Rr = np.linalg.qr(rng.normal(size=(3, 3)))
    Q = Q * np.sign(np.diag(Rr))
    if np.linalg.det(Q) < 0:
        Q[:, 0] = -Q[:, 0]
    return Q


def random_pose(rng: np.random.Generator, rot_scale: float = 1.0, trans_scale: float = 3.0) -> np.ndarray:
    """Random (4, 4) transform with rotation angle ~ rot_scale and translation ~ trans_scale."""
    xi = np.concatenate([rng.normal(scale=rot_scale, size=3), rng.normal(scale=trans_scale, size=3)])
    return exp_se3(xi)


def random_anisotropic_covariances(
    rng: np.random.Generator, n: int, sigmas: tuple[float, float, float] = (0.5, 0.2, 0.01)
) -> np.ndarray:
    """(n, 3, 3) covariances with random orientation and per-axis std ~ sigmas (jittered)."""
    out = np.empty((n, 3, 3))
    for i in range(n):
        R = random_rotation(rng)
        s = np.asarray(sigmas) * np.exp(rng.uniform(-0.5, 0.5, size=3))
        out[i] = (R * s**2) @ R.T
    return 0.5 * (out + np.swapaxes(out, 1, 2))


def transform(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Apply a (4, 4) transform to (N, 3) points."""
    return p @ T[:3, :3].T + T[:3, 3]


def sample_gaussian(rng: np.random.Generator, cov: np.ndarray) -> np.ndarray:
    """One sample of N(0, cov_i) per row, (N, 3)."""
    L = np.linalg.cholesky(cov)
    return np.einsum("nij,nj->ni", L, rng.normal(size=(cov.shape[0], 3)))
