"""Nearest-neighbour correspondences under T̂ against a brute-force search."""

from __future__ import annotations

import numpy as np

from factors.se3 import exp_se3
from gr_graph.correspondences import nearest_correspondences, target_tree


def _brute_force(source: np.ndarray, target: np.ndarray, T: np.ndarray, max_distance: float) -> np.ndarray:
    p = source @ T[:3, :3].T + T[:3, 3]
    d = np.linalg.norm(p[:, None, :] - target[None, :, :], axis=2)
    j = d.argmin(axis=1)
    i = np.flatnonzero(d[np.arange(len(p)), j] <= max_distance)
    return np.column_stack([i, j[i]])


def test_pairs_equal_brute_force_under_T():
    rng = np.random.default_rng(4)
    target = rng.uniform(-10, 10, (800, 3))
    T = exp_se3(np.array([0.1, -0.05, 0.3, 1.0, -2.0, 0.5]))
    # source: target points seen from T (p = T^-1 q) plus noise, and points far from everything
    Ti = np.linalg.inv(T)
    near = (target[:500] + rng.normal(0, 0.2, (500, 3))) @ Ti[:3, :3].T + Ti[:3, 3]
    far = rng.uniform(50, 60, (100, 3))
    source = rng.permutation(np.vstack([near, far]))
    pairs = nearest_correspondences(source, target_tree(target), T, 0.5)
    ref = _brute_force(source, target, T, 0.5)
    assert pairs.dtype == np.int32 and 300 < len(pairs) < 600
    np.testing.assert_array_equal(pairs, ref)


def test_empty_scans_give_no_pairs():
    pts = np.random.default_rng(0).normal(size=(10, 3))
    assert target_tree(np.zeros((0, 3))) is None
    assert nearest_correspondences(pts, None, np.eye(4), 1.0).shape == (0, 2)
    assert nearest_correspondences(np.zeros((0, 3)), target_tree(pts), np.eye(4), 1.0).shape == (0, 2)
