"""The two likelihood losses against independent references."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.stats import multivariate_normal

from training.losses import LOG_2PI, LossError, corr_nll, default_gamma, pose_nll
from training.pose_layer import solve_pose
from training.se3_torch import exp_se3

torch.set_num_threads(1)


def _spd(rng, n, scale=0.05):
    A = rng.normal(size=(n, 3, 3)) * scale
    return A @ A.transpose(0, 2, 1) + 1e-4 * np.eye(3)


def test_corr_nll_matches_scipy_gaussian_logpdf():
    rng = np.random.default_rng(0)
    C = _spd(rng, 20)
    d = rng.normal(size=(20, 3)) * 0.05
    ref = [-2 * multivariate_normal(np.zeros(3), 2 * C[i]).logpdf(d[i]) - 3 * LOG_2PI for i in range(20)]
    got = corr_nll(torch.tensor(C), torch.tensor(d), "sum").item()
    assert got == pytest.approx(sum(ref), rel=1e-10)
    assert corr_nll(torch.tensor(C), torch.tensor(d), "mean").item() == pytest.approx(np.mean(ref), rel=1e-10)


def test_corr_nll_minimised_at_closed_form_scale():
    """For C = s C0 the NLL is minimal at s* = mean(d^T (2C0)^-1 d) / 3; gradient vanishes there."""
    rng = np.random.default_rng(1)
    C0 = torch.tensor(_spd(rng, 500))
    d = torch.tensor(rng.normal(size=(500, 3)) * 0.03)
    m = (d[:, None, :] @ torch.linalg.inv(2 * C0) @ d[:, :, None]).mean().item()
    s = torch.tensor(m / 3, dtype=torch.float64, requires_grad=True)
    (g,) = torch.autograd.grad(corr_nll(s * C0, d), s)
    assert abs(g.item()) < 1e-8 / s.item()
    assert corr_nll(s * C0 * 1.1, d) > corr_nll(s * C0, d) < corr_nll(s * C0 / 1.1, d)


def test_corr_nll_rejects_bad_input():
    with pytest.raises(LossError, match="no correspondences"):
        corr_nll(torch.zeros(0, 3, 3), torch.zeros(0, 3))
    C = torch.eye(3).repeat(4, 1, 1)
    C[2] = -C[2]
    with pytest.raises(LossError, match="not positive definite"):
        corr_nll(C, torch.zeros(4, 3))


def test_pose_nll_value_matches_formula():
    rng = np.random.default_rng(2)
    xi = rng.normal(size=6) * 0.01
    T_hat = exp_se3(torch.tensor(rng.normal(size=6)))
    T_C = T_hat @ exp_se3(torch.tensor(-xi))  # T(C)^-1 T_hat = Exp(xi)  ->  mu = xi
    A = rng.normal(size=(6, 6))
    H = torch.tensor(A @ A.T + 6 * np.eye(6)) * 1e4
    G = default_gamma(1e-3, 1e-2)
    W = G.numpy() + np.linalg.inv(H.numpy())
    ref = xi @ np.linalg.solve(W, xi) + np.linalg.slogdet(W)[1]
    assert pose_nll(T_C, T_hat, H, G).item() == pytest.approx(ref, rel=1e-9)


@pytest.mark.slow
def test_pose_nll_minimal_near_true_covariance_scale():
    """Toy problem: data drawn with d ~ N(0, 2 C_true), T̂ = T_true, Gamma ~ 0.

    Averaged over trials, pose NLL(s C_true) is minimal at s = 1 (theory: E = 6/s + 6 log s).
    """
    rng = np.random.default_rng(3)
    scales = np.exp(np.linspace(np.log(0.5), np.log(2.0), 9))
    G = default_gamma(1e-7, 1e-7)
    total = np.zeros_like(scales)
    M = 150
    for trial in range(120):
        p = rng.uniform(-10, 10, (M, 3))
        n = rng.normal(size=(M, 3))
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        # planar-like true covariances: 4 cm along the tangent plane, 1 cm along the normal
        C_true = 0.04**2 * (np.eye(3) - n[:, :, None] * n[:, None, :]) + 0.01**2 * n[:, :, None] * n[:, None, :]
        T_true = exp_se3(torch.tensor(np.r_[rng.normal(size=3) * 0.05, rng.normal(size=3)])).numpy()
        d = np.einsum("nij,nj->ni", np.linalg.cholesky(2 * C_true), rng.normal(size=(M, 3)))
        q = p @ T_true[:3, :3].T + T_true[:3, 3] + d
        for i, s in enumerate(scales):
            res = solve_pose(torch.tensor(p), torch.tensor(q), torch.tensor(s * C_true), T0=torch.tensor(T_true))
            total[i] += pose_nll(res.T, torch.tensor(T_true), res.H, G).item()
    s_best = scales[np.argmin(total)]
    assert 0.8 < s_best < 1.25, s_best
    assert total[0] > total[4] + 50 and total[-1] > total[4] + 50  # a clear minimum, not a flat curve
