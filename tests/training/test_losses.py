"""The two likelihood losses against independent references."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.special import gammaln
from scipy.stats import multivariate_normal, multivariate_t

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


def test_corr_nll_student_t_matches_scipy_logpdf():
    """Twice the t's negative log density with scale 2C, less its constant; the Gaussian as dof -> inf."""
    rng = np.random.default_rng(3)
    C = _spd(rng, 20)
    d = rng.standard_t(3, size=(20, 3)) * 0.05
    for dof in (1.5, 4.0, 30.0):
        const = -2 * (gammaln((dof + 3) / 2) - gammaln(dof / 2) - 1.5 * np.log(dof * np.pi))
        ref = [-2 * multivariate_t(np.zeros(3), 2 * C[i], df=dof).logpdf(d[i]) - const for i in range(20)]
        got = corr_nll(torch.tensor(C), torch.tensor(d), "sum", "student_t", dof).item()
        assert got == pytest.approx(sum(ref), rel=1e-9)
    gauss = corr_nll(torch.tensor(C), torch.tensor(d), "mean").item()
    assert corr_nll(torch.tensor(C), torch.tensor(d), "mean", "student_t", 1e9).item() == pytest.approx(gauss, rel=1e-6)


def _t_scale_fixed_point(d: np.ndarray, dof: float, iterations: int = 500) -> np.ndarray:
    """Maximum-likelihood scale matrix of a zero-mean 3-d t by its EM fixed point
    ``S = mean_i w_i d_i d_i^T``, ``w_i = (dof + 3) / (dof + d_i^T S^-1 d_i)`` (numpy)."""
    S = d.T @ d / len(d)
    for _ in range(iterations):
        m = np.einsum("ni,ij,nj->n", d, np.linalg.inv(S), d)
        S = (d * ((dof + 3) / (dof + m))[:, None]).T @ d / len(d)
    return S


def test_corr_nll_student_t_keeps_the_surface_under_outliers():
    """A flat surface (normal std 1 cm) with 5 % of the correspondences on other surfaces within 1 m:
    the t's optimum (EM fixed point, where the loss's gradient vanishes) stays flat, the Gaussian's
    (the sample covariance) does not."""
    rng = np.random.default_rng(4)
    n_in, n_out = 1900, 100
    inliers = rng.normal(size=(n_in, 3)) * np.array([0.10, 0.10, 0.01]) * np.sqrt(2)
    direction = rng.normal(size=(n_out, 3))
    outliers = direction / np.linalg.norm(direction, axis=1, keepdims=True) * rng.uniform(0.2, 1.0, (n_out, 1))
    d = np.concatenate([inliers, outliers])
    dof = 4.0
    C_t = _t_scale_fixed_point(d, dof) / 2
    C = torch.tensor(C_t, requires_grad=True)
    (g,) = torch.autograd.grad(corr_nll(C.expand(len(d), 3, 3), torch.tensor(d), "mean", "student_t", dof), C)
    assert torch.abs(g).max().item() < 1e-6 * np.abs(np.linalg.inv(C_t)).max()
    C_gauss = d.T @ d / len(d) / 2
    normal_std_t, normal_std_gauss = np.sqrt(C_t[2, 2]), np.sqrt(C_gauss[2, 2])
    assert normal_std_t < 0.015 < 0.05 < normal_std_gauss  # the inliers' 1 cm against the outliers' spread
    w_t, w_g = np.linalg.eigvalsh(C_t), np.linalg.eigvalsh(C_gauss)
    assert w_t[0] / w_t[2] < 0.03 and w_g[0] / w_g[2] > 0.2  # flat (passes the 0.9 filter) against round
    # the t's loss prefers its own optimum to the Gaussian's, and the Gaussian's loss the reverse
    dt = torch.tensor(d)
    nll_t = [corr_nll(torch.tensor(c).expand(len(d), 3, 3), dt, "mean", "student_t", dof).item() for c in (C_t, C_gauss)]
    nll_g = [corr_nll(torch.tensor(c).expand(len(d), 3, 3), dt).item() for c in (C_t, C_gauss)]
    assert nll_t[0] < nll_t[1] and nll_g[1] < nll_g[0]


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
