"""f_theta: neighbourhoods against brute force, Cholesky parametrisation, inference wrapper."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from training.network import CovarianceNet, NetConfig, cholesky_to_cov, neighborhoods_to_torch
from training.neighbors import build_neighborhoods, farthest_point_sampling
from training.predict import predict_covariances

torch.set_num_threads(1)


def test_neighborhoods_match_brute_force():
    rng = np.random.default_rng(0)
    x = rng.uniform(-5, 5, (300, 3))
    for sampling in ("random", "fps"):
        nb = build_neighborhoods(x, k0=8, ratio1=4, k1=6, ratio2=3, k2=5, start=7, sampling=sampling)
        D = ((x[:, None] - x[None]) ** 2).sum(-1)
        np.testing.assert_array_equal(np.sort(nb.knn0, 1), np.sort(np.argsort(D, 1)[:, :8], 1))
        assert len(nb.idx1) == 75 and len(set(nb.idx1)) == 75 and len(nb.idx2) == 25
        x1 = x[nb.idx1]
        D1 = ((x1[:, None] - x[None]) ** 2).sum(-1)
        np.testing.assert_array_equal(np.sort(nb.knn1, 1), np.sort(np.argsort(D1, 1)[:, :6], 1))
        np.testing.assert_allclose(nb.w10.sum(1), 1, rtol=1e-6)
        np.testing.assert_allclose(nb.w21.sum(1), 1, rtol=1e-6)
    # farthest-point sampling: each new point is the farthest from those chosen before
    idx = farthest_point_sampling(x, 10, 0)
    for i in range(1, 10):
        dmin = ((x[:, None] - x[idx[:i]][None]) ** 2).sum(-1).min(1)
        assert dmin[idx[i]] == pytest.approx(dmin.max())
    small = build_neighborhoods(x[:5], k0=8)  # fewer points than k: padded, still valid
    assert small.knn0.shape == (5, 8) and small.knn0.max() < 5


def test_cholesky_parametrisation_gives_spd_covariances():
    raw = torch.randn(100, 6) * 3
    raw[0, :3] = 1e4  # clamped, no overflow
    raw[1, :3] = -1e4
    L, C = cholesky_to_cov(raw, 0.1, 1e-6)
    assert torch.all(torch.diagonal(L, dim1=1, dim2=2) > 0)
    assert torch.equal(L, torch.tril(L))
    assert torch.isfinite(C).all()
    torch.testing.assert_close(C, L @ L.transpose(1, 2) + 1e-6 * torch.eye(3))
    assert torch.linalg.eigvalsh(C.double()).min() >= 0.99e-6


def test_network_output_and_predict_wrapper():
    rng = np.random.default_rng(1)
    cfg = NetConfig(n_points=256, k0=8, k1=8, k2=8, c0=16, c1=16, c2=16)
    torch.manual_seed(0)
    net = CovarianceNet(cfg)
    for p in net.head.parameters():  # a non-trivial head
        torch.nn.init.normal_(p, std=0.3)
    x = rng.uniform(-20, 20, (200, 3)).astype(np.float32)
    L, C = net(torch.tensor(x), neighborhoods_to_torch(cfg.neighborhoods(x, start=3)))
    assert C.shape == (200, 3, 3) and torch.isfinite(C).all()
    # one chunk (N <= n_points): predict_covariances == a direct forward with the same sampling seed
    g = np.random.default_rng(0)
    perm = g.permutation(200)
    start = int(g.integers(200))
    _, C_direct = net(torch.tensor(x[perm]), neighborhoods_to_torch(cfg.neighborhoods(x[perm], start=start)))
    C_pred = predict_covariances(net, x, seed=0)
    np.testing.assert_allclose(C_pred[perm], C_direct.detach().double().numpy(), rtol=1e-5, atol=1e-9)
    # many chunks: every point gets an SPD covariance
    big = rng.uniform(-20, 20, (1000, 3))
    Cb = predict_covariances(net, big, n_points=256)
    assert Cb.shape == (1000, 3, 3) and np.linalg.eigvalsh(Cb).min() > 0
    with pytest.raises(ValueError, match="non-finite"):
        predict_covariances(net, np.full((4, 3), np.nan))


@pytest.mark.parametrize("head", ["geometric", "cholesky"])
def test_both_heads_give_spd_covariances_and_gradients(head):
    rng = np.random.default_rng(2)
    cfg = NetConfig(n_points=256, k0=8, k1=8, k2=8, c0=16, c1=16, c2=16, head=head)
    net = CovarianceNet(cfg)
    for p in net.parameters():
        torch.nn.init.normal_(p, std=0.2)
    x = rng.uniform(-20, 20, (256, 3)).astype(np.float32)
    L, C = net(torch.tensor(x), neighborhoods_to_torch(cfg.neighborhoods(x)))
    assert torch.isfinite(C).all() and torch.linalg.eigvalsh(C.double()).min() > 0
    assert torch.all(torch.diagonal(L, dim1=1, dim2=2) > 0)
    torch.testing.assert_close(C, L @ L.transpose(1, 2) + cfg.eps * torch.eye(3), rtol=1e-4, atol=1e-6)
    C.sum().backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in net.parameters())


def test_geometric_head_normal_follows_the_measured_surface():
    """On a noiseless plane, whatever the weights, C's smallest eigenvector is the plane normal."""
    rng = np.random.default_rng(3)
    cfg = NetConfig(n_points=400, k0=8, k1=8, k2=8, kw=8, c0=16, c1=16, c2=16)
    torch.manual_seed(1)
    net = CovarianceNet(cfg)
    for p in net.parameters():
        torch.nn.init.normal_(p, std=0.2)
    uv = rng.uniform(-5, 5, (400, 2))
    for axis in (np.array([0.0, 0.0, 1.0]), np.array([0.6, 0.0, 0.8]), np.array([0.0, 1.0, 0.0])):
        a = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
        a /= np.linalg.norm(a)
        b = np.cross(axis, a)
        x = (uv[:, :1] * a + uv[:, 1:] * b + np.array([3.0, -2.0, 1.0])).astype(np.float32)
        _, C = net(torch.tensor(x), neighborhoods_to_torch(cfg.neighborhoods(x)))
        w, v = np.linalg.eigh(C.detach().double().numpy())
        cosang = np.abs(v[:, :, 0] @ axis)
        assert cosang.min() > 1 - 1e-4
        assert (w[:, 1] / w[:, 0]).min() > 10  # clearly flat
