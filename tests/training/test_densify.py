"""Algorithm 2 lines 3-9: anisotropy filter and Gaussian sampling."""

from __future__ import annotations

import numpy as np
import pytest

from training.densify import anisotropy, densify, symmetric_eigenvalues


def _rot(rng, n):
    q, _ = np.linalg.qr(rng.normal(size=(n, 3, 3)))
    return q


def test_anisotropy_closed_form():
    rng = np.random.default_rng(0)
    lam = np.array([[1.0, 1.0, 1.0], [1.0, 0.5, 0.01], [4.0, 4.0, 1.0]])
    R = _rot(rng, 3)
    C = R @ (lam[:, :, None] * np.eye(3)) @ R.transpose(0, 2, 1)
    np.testing.assert_allclose(anisotropy(C), [0.0, 0.99, 0.75], atol=1e-12)
    with pytest.raises(ValueError, match="positive definite"):
        anisotropy(-C)
    # eigenvalues the caller computed already give the same filter; the wrong shape is an error
    w = symmetric_eigenvalues(C)
    np.testing.assert_allclose(w, np.sort(lam, 1), atol=1e-12)
    np.testing.assert_array_equal(anisotropy(C, w), anisotropy(C))
    with pytest.raises(ValueError, match="eigenvalues"):
        anisotropy(C, w[:2])


def test_densify_filters_and_samples_from_the_covariance():
    rng = np.random.default_rng(1)
    n = 400
    pts = rng.uniform(-10, 10, (n, 3))
    R = _rot(rng, n)
    flat = np.array([0.04, 0.02, 1e-4])
    iso = np.array([0.01, 0.01, 0.009])
    is_flat = np.arange(n) % 3 != 0
    lam = np.where(is_flat[:, None], flat, iso)
    C = R @ (lam[:, :, None] * np.eye(3)) @ R.transpose(0, 2, 1)
    dense, kept = densify(pts, C, tau_ani=0.9, M=500, seed=3)
    np.testing.assert_array_equal(kept, is_flat)
    assert dense.shape == (is_flat.sum() * 500, 3)
    s = dense.reshape(-1, 500, 3)
    # sample mean and covariance of each kept point's samples match N(s_i, C_i)
    dev = s - pts[kept][:, None]
    emp = np.einsum("nmi,nmj->nij", dev, dev) / 500
    err = np.linalg.norm(emp - C[kept], axis=(1, 2)) / np.linalg.norm(C[kept], axis=(1, 2))
    assert np.median(err) < 0.1
    # along the normal the samples stay within the tiny normal std
    normal = R[kept][:, :, 2]
    assert np.std(np.einsum("nmi,ni->nm", dev, normal)) == pytest.approx(1e-2, rel=0.05)
    d2, _ = densify(pts, C, tau_ani=0.9, M=500, seed=3)
    np.testing.assert_array_equal(dense, d2)  # deterministic
    d3, _ = densify(pts, C, tau_ani=0.9, M=2, seed=3, include_original=True)
    np.testing.assert_array_equal(d3[: is_flat.sum()], pts[kept])


def test_densify_rejects_bad_input():
    with pytest.raises(ValueError, match="C \\(N, 3, 3\\)"):
        densify(np.zeros((3, 3)), np.zeros((2, 3, 3)))
    C = np.tile(np.eye(3), (3, 1, 1))
    with pytest.raises(ValueError, match="non-finite"):
        densify(np.full((3, 3), np.nan), C)
    with pytest.raises(ValueError, match="M must be"):
        densify(np.zeros((3, 3)), C, M=0)
