"""Pose layer T(C): agreement with factors.wls.solve_wls, IFT gradient vs finite differences."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from training.pose_layer import PoseLayerError, exact_hessian, solve_pose, wls_terms
from training.se3_torch import exp_se3, exp_so3, inverse_se3, log_se3, log_so3

torch.set_num_threads(1)


def _problem(M=80, seed=0, noise=0.02):
    rng = np.random.default_rng(seed)
    p = rng.uniform(-10, 10, (M, 3))
    A = rng.normal(size=(M, 3, 3)) * 0.05
    C = A @ A.transpose(0, 2, 1) + 1e-4 * np.eye(3)
    xi = np.r_[rng.normal(size=3) * 0.1, rng.normal(size=3)]
    T = exp_se3(torch.tensor(xi)).numpy()
    q = p @ T[:3, :3].T + T[:3, 3] + rng.normal(size=(M, 3)) * noise
    return p, q, C, T


def test_se3_matches_factors_and_roundtrip():
    fse3 = pytest.importorskip("factors.se3")
    rng = np.random.default_rng(1)
    for scale in (1e-9, 1e-5, 1.2e-4, 3e-4, 0.02, 0.06, 0.3, 2.5):  # both sides of the series' cut (0.05 rad)
        xi = rng.normal(size=6) * scale
        T = exp_se3(torch.tensor(xi)).numpy()
        np.testing.assert_allclose(T, fse3.exp_se3(xi), atol=1e-12)
        np.testing.assert_allclose(log_se3(torch.tensor(T)).numpy(), xi, atol=1e-11, rtol=1e-9)
        np.testing.assert_allclose(log_se3(torch.tensor(T)).numpy(), fse3.log_se3(T), atol=1e-11)


def test_log_so3_at_and_near_pi_matches_factors():
    """At pi, theta / sin(theta) is 0/0: the axis comes from the symmetric part (as factors.se3.log_so3)."""
    fse3 = pytest.importorskip("factors.se3")
    rng = np.random.default_rng(3)
    axes = rng.normal(size=(40, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.pi - np.r_[0.0, 1e-12, 1e-9, 1e-7, 1e-5, 9e-4, 1.1e-3, 1e-2, rng.uniform(0, 1e-3, 32)]
    R = np.stack([fse3.exp_so3(a * n) for a, n in zip(angles, axes)]
                 + [np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])])
    w = log_so3(torch.tensor(R)).numpy()  # one batch mixing both branches
    assert np.all(np.isfinite(w))
    expected = np.stack([fse3.log_so3(r) for r in R])
    # at exactly pi, w and -w are the same rotation: compare the rotations, and the vectors up to that sign
    np.testing.assert_allclose(exp_so3(torch.tensor(w)).numpy(), R, atol=1e-9)
    same = np.minimum(np.abs(w - expected).max(1), np.abs(w + expected).max(1))
    assert same.max() < 1e-7
    np.testing.assert_allclose(np.linalg.norm(w, axis=1)[:len(angles)], angles, atol=1e-9)
    assert np.all(np.linalg.norm(w, axis=1) <= np.pi + 1e-12)


def test_log_so3_gradient_of_ordinary_rotations_unchanged_beside_one_at_pi():
    """A batch holding a rotation by pi gives the other rotations (among them the identity, where the near-pi
    branch not taken divides by 1 - cos = 0 and by a zero column unless guarded) the same finite gradients as
    alone, in float64 and float32; the rotation by pi gets a finite one too."""
    rng = np.random.default_rng(4)
    rotations = np.stack([np.eye(3)] + [exp_so3(torch.tensor(rng.normal(size=3) * 0.3)).numpy() for _ in range(5)])
    for dtype in (torch.float64, torch.float32):
        ordinary = torch.tensor(rotations, dtype=dtype, requires_grad=True)
        alone = torch.autograd.grad(log_so3(ordinary).sum(), ordinary)[0]
        at_pi = torch.tensor(np.diag([1.0, -1.0, -1.0]), dtype=dtype)[None].requires_grad_(True)
        both = torch.autograd.grad(log_so3(torch.cat([ordinary, at_pi])).sum(), (ordinary, at_pi))
        assert torch.isfinite(both[0]).all() and torch.isfinite(both[1]).all(), dtype
        torch.testing.assert_close(both[0], alone, rtol=0, atol=0)


def test_agrees_with_factors_solve_wls():
    wls = pytest.importorskip("factors.wls")
    for seed in range(3):
        p, q, C, _ = _problem(seed=seed)
        ref = wls.solve_wls(p, q, C)
        res = solve_pose(torch.tensor(p), torch.tensor(q), torch.tensor(C), tol=1e-12)
        np.testing.assert_allclose(res.T.detach().numpy(), ref.T, atol=1e-8)
        np.testing.assert_allclose(res.H.detach().numpy(), ref.hessian, rtol=1e-8)


def test_exact_hessian_matches_autograd():
    p, q, C, T = _problem(M=30, seed=3, noise=0.3)
    pt, qt = torch.tensor(p), torch.tensor(q)
    Lam = torch.linalg.inv(2 * torch.tensor(C))
    T0 = torch.tensor(T)

    def f(xi):
        return wls_terms(T0 @ exp_se3(xi), pt, qt, Lam)[0]

    H_auto = torch.autograd.functional.hessian(f, torch.zeros(6, dtype=torch.float64))
    _, _, H_gn, d = wls_terms(T0, pt, qt, Lam)
    H_ex = exact_hessian(T0, pt, d, Lam, H_gn)
    np.testing.assert_allclose(H_ex.numpy(), H_auto.numpy(), rtol=1e-9, atol=1e-9 * H_auto.abs().max().item())
    assert (H_ex - H_gn).abs().max() > 1e-6 * H_gn.abs().max()  # the residual term matters here


def test_exp_and_log_derivatives_near_the_series_cut():
    """The closed-form coefficients lose digits at small angles and their autograd derivatives far
    more (a 1e-4 cut left dB/dθ² 600 % off at 1.01e-4): derivatives against central differences."""
    rng = np.random.default_rng(4)
    for angle in (1.01e-4, 5e-4, 0.01, 0.049, 0.051):
        axis = rng.normal(size=3)
        xi = np.r_[angle * axis / np.linalg.norm(axis), rng.normal(size=3)]
        x = torch.tensor(xi, requires_grad=True)
        J = torch.autograd.functional.jacobian(lambda v: exp_se3(v)[:3, :].reshape(-1), x)
        h = 1e-7
        for i in range(6):
            e = np.zeros(6)
            e[i] = h
            fd = (exp_se3(torch.tensor(xi + e)) - exp_se3(torch.tensor(xi - e)))[:3, :].reshape(-1) / (2 * h)
            np.testing.assert_allclose(J[:, i].numpy(), fd.numpy(), atol=2e-8, err_msg=f"angle {angle}, axis {i}")
        T = exp_se3(torch.tensor(xi))
        JL = torch.autograd.functional.jacobian(lambda v: log_se3(T @ exp_se3(v)), torch.zeros(6, dtype=torch.float64))
        np.testing.assert_allclose(log_se3(T).numpy(), xi, atol=1e-14)
        for i in range(6):
            e = np.zeros(6)
            e[i] = h
            fd = (log_se3(T @ exp_se3(torch.tensor(e))) - log_se3(T @ exp_se3(torch.tensor(-e)))) / (2 * h)
            np.testing.assert_allclose(JL[:, i].numpy(), fd.numpy(), atol=2e-8, err_msg=f"angle {angle}, axis {i}")


def test_ift_gradient_matches_finite_differences_of_whole_solve():
    # noise 0.3: the residual term of the exact Hessian matters (a Gauss-Newton step's derivative is off by ~6e-4)
    p, q, C, T = _problem(M=40, seed=5, noise=0.3)
    rng = np.random.default_rng(7)
    pt, qt = torch.tensor(p), torch.tensor(q)
    L0 = np.linalg.cholesky(C)
    wts = torch.tensor(rng.normal(size=6))
    Tref = torch.tensor(T)

    def phi(Lflat: torch.Tensor) -> torch.Tensor:
        Lm = Lflat.reshape(-1, 3, 3).tril()
        Cm = Lm @ Lm.transpose(-1, -2)
        res = solve_pose(pt, qt, Cm, T0=Tref, tol=1e-14, max_iterations=100)
        mu = log_se3(inverse_se3(Tref) @ res.T)
        return (wts * mu).sum() * 1e3 + res.H.trace() * 1e-3

    x = torch.tensor(L0.reshape(-1), requires_grad=True)
    val = phi(x)
    (grad,) = torch.autograd.grad(val, x)
    idx = [i for i in range(x.numel()) if (i % 9) in (0, 3, 4, 6, 7, 8)]  # lower-triangular entries
    sel = rng.choice(idx, 25, replace=False)
    h = 1e-6
    for i in sel:
        e = torch.zeros_like(x)
        e[i] = h
        with torch.no_grad():
            fd = (phi(x.detach() + e) - phi(x.detach() - e)) / (2 * h)
        assert abs(grad[i].item() - fd.item()) <= 1e-5 * max(1.0, abs(fd.item())), (i, grad[i].item(), fd.item())


def test_gauss_newton_step_derivative_is_only_approximate():
    """The exact-Hessian step is needed: the GN-Hessian step's derivative differs with big residuals."""
    p, q, C, T = _problem(M=40, seed=9, noise=0.5)
    pt, qt = torch.tensor(p), torch.tensor(q)
    Ct = torch.tensor(C, requires_grad=True)
    g1 = torch.autograd.grad(log_se3(solve_pose(pt, qt, Ct).T).sum(), Ct)[0]
    g2 = torch.autograd.grad(log_se3(solve_pose(pt, qt, Ct, exact_hessian_step=False).T).sum(), Ct)[0]
    assert (g1 - g2).abs().max() > 1e-4 * g1.abs().max()


def test_degenerate_geometry_raises():
    rng = np.random.default_rng(0)
    p = np.zeros((50, 3))
    p[:, 0] = rng.uniform(-5, 5, 50)  # all points on a line: rotation about it unobservable
    C = np.tile(np.eye(3) * 1e-2, (50, 1, 1))
    with pytest.raises(PoseLayerError, match="degenerate"):
        solve_pose(torch.tensor(p), torch.tensor(p), torch.tensor(C))
    with pytest.raises(PoseLayerError, match="at least 3"):
        solve_pose(torch.zeros(2, 3), torch.zeros(2, 3), torch.eye(3).expand(2, 3, 3))
    Cbad = torch.tensor(C).clone()
    Cbad[3, 0, 0] = float("nan")
    with pytest.raises(PoseLayerError, match="non-finite"):
        solve_pose(torch.tensor(p), torch.tensor(p), Cbad)
