"""Differentiable weighted-least-squares pose ``T(C)`` (the paper's pose layer).

Problem (paper Eq. for ``T(C_q)``, same as ``factors.wls.solve_wls`` with ``cov_p=None``)::

    T(C) = argmin_T  f(T; C),   f = 1/2 sum_i d_i^T Lambda_i d_i,
    d_i = q_i - T p_i,          Lambda_i = (2 C_i)^-1

Conventions (gtsam's): tangent ``[omega, v]``, right perturbation ``T o Exp(xi)``; the residual
Jacobian is ``J_i = [R [p_i]_x, -R]``, ``g = sum J_i^T Lambda_i d_i``,
``H = sum J_i^T Lambda_i J_i`` (Gauss-Newton Hessian, returned for the pose likelihood).

Differentiation (implicit function theorem). The minimiser ``T*`` is found with no autograd
graph (Gauss-Newton with step halving, float64). Then one Newton step is taken *with*
gradients::

    xi(C) = -A^-1 g(T*; C),      T(C) = T* Exp(xi(C))

with ``A`` the exact Hessian of ``f`` at ``T*`` (detached). Since ``g(T*; C) = 0`` at the
optimum, ``xi`` is zero in value and its derivative ``-A^-1 dg/dC`` is exactly the IFT
derivative of the optimum. ``A`` is the Gauss-Newton Hessian plus the second-order residual
term ``-sum Hess_xi(r_i^T s_i(xi))`` (``r_i = R^T Lambda_i d_i``, ``s_i`` the second-order part
of ``Exp(xi) p_i``); using the Gauss-Newton ``H`` instead would give an approximation whose
error grows with the residuals (set ``exact_hessian=False`` to get it).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import torch

from training.se3_torch import exp_se3, hat

log = logging.getLogger(__name__)

__all__ = ["PoseLayerError", "PoseLayerResult", "solve_pose", "wls_terms", "exact_hessian", "kabsch", "inv3"]


class PoseLayerError(ValueError):
    """The WLS pose problem is degenerate or its inputs are malformed (message says which)."""


@dataclass
class PoseLayerResult:
    """Output of :func:`solve_pose`.

    Attributes
    ----------
    T : torch.Tensor
        ``(4, 4)`` float64 ``T(C)``, equal in value to the optimum, differentiable w.r.t. ``C``.
    H : torch.Tensor
        ``(6, 6)`` Gauss-Newton Hessian at ``T(C)``, differentiable w.r.t. ``C`` (directly
        and through ``T(C)``).
    T_opt : torch.Tensor
        ``(4, 4)`` detached optimum.
    iterations : int
        Gauss-Newton iterations of the no-grad solve.
    converged : bool
        Whether the last step's max-norm fell below ``tol``.
    """

    T: torch.Tensor
    H: torch.Tensor
    T_opt: torch.Tensor
    iterations: int
    converged: bool


def kabsch(p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """Unweighted closed-form rigid fit ``q ~ R p + t`` (warm start), ``(4, 4)``."""
    mp, mq = p.mean(0), q.mean(0)
    S = (q - mq).T @ (p - mp)
    U, _, Vt = torch.linalg.svd(S)
    d = torch.sign(torch.linalg.det(U @ Vt))
    D = torch.diag(torch.stack([torch.ones_like(d), torch.ones_like(d), d]))
    R = U @ D @ Vt
    T = torch.eye(4, dtype=p.dtype, device=p.device)
    T[:3, :3] = R
    T[:3, 3] = mq - R @ mp
    return T


def _jacobians(T: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    R = T[:3, :3]
    RP = R @ hat(p)  # (M,3,3)
    return torch.cat([RP, -R.expand(p.shape[0], 3, 3)], -1)  # (M,3,6)


def inv3(S: torch.Tensor) -> torch.Tensor:
    """Inverse of a batch of 3x3 matrices by the adjugate (differentiable, faster than LAPACK here)."""
    a, b, c = S[..., 0, 0], S[..., 0, 1], S[..., 0, 2]
    d, e, f = S[..., 1, 0], S[..., 1, 1], S[..., 1, 2]
    g, h, i = S[..., 2, 0], S[..., 2, 1], S[..., 2, 2]
    A, B, C = e * i - f * h, -(d * i - f * g), d * h - e * g
    det = a * A + b * B + c * C
    adj = torch.stack(
        [
            torch.stack([A, -(b * i - c * h), b * f - c * e], -1),
            torch.stack([B, a * i - c * g, -(a * f - c * d)], -1),
            torch.stack([C, -(a * h - b * g), a * e - b * d], -1),
        ],
        -2,
    )
    return adj / det[..., None, None]


def wls_terms(
    T: torch.Tensor, p: torch.Tensor, q: torch.Tensor, Lam: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Cost, gradient ``(6,)``, Gauss-Newton Hessian ``(6,6)`` and residuals at ``T``.

    ``Lam`` is the ``(M,3,3)`` residual information; gradients flow through ``Lam`` (and ``T``).
    """
    d = q - p @ T[:3, :3].T - T[:3, 3]
    J = _jacobians(T, p)  # (M,3,6)
    Ld = (Lam @ d[..., None])[..., 0]
    cost = 0.5 * (d * Ld).sum()
    LJ = Lam @ J  # (M,3,6)
    g = J.reshape(-1, 6).T @ Ld.reshape(-1)
    H = J.reshape(-1, 6).T @ LJ.reshape(-1, 6)
    return cost, g, H, d


def exact_hessian(T: torch.Tensor, p: torch.Tensor, d: torch.Tensor, Lam: torch.Tensor, H_gn: torch.Tensor) -> torch.Tensor:
    """Exact Hessian of ``f(T o Exp(xi))`` at ``xi = 0``: GN part plus the residual term.

    With ``r_i = R^T Lambda_i d_i`` and ``Exp(xi) p = p + w x p + v + s(xi) + O(3)``,
    ``s = 1/2 w x (w x p) + 1/2 w x v``, the extra term is ``-sum Hess(r_i^T s_i)`` where
    ``Hess(r^T s) = [[ (r p^T + p r^T)/2 - (r.p) I, -[r]_x/2 ], [ [r]_x/2, 0 ]]``.
    """
    r = (Lam @ d[..., None])[..., 0] @ T[:3, :3]  # (M,3) = (R^T Lam d)^T
    rp = (r[:, :, None] * p[:, None, :]).sum(0)
    rdotp = (r * p).sum()
    eye = torch.eye(3, dtype=p.dtype, device=p.device)
    Hww = 0.5 * (rp + rp.T) - rdotp * eye
    Rx = hat(r.sum(0))
    S = torch.zeros(6, 6, dtype=p.dtype, device=p.device)
    S[:3, :3] = Hww
    S[:3, 3:] = -0.5 * Rx
    S[3:, :3] = 0.5 * Rx
    return H_gn - S


def _check_inputs(p: torch.Tensor, q: torch.Tensor, C: torch.Tensor) -> None:
    if p.ndim != 2 or p.shape[1] != 3 or q.shape != p.shape:
        raise PoseLayerError(f"p and q must both be (M, 3); got {tuple(p.shape)} and {tuple(q.shape)}")
    if C.shape != (p.shape[0], 3, 3):
        raise PoseLayerError(f"C must be (M, 3, 3) = ({p.shape[0]}, 3, 3); got {tuple(C.shape)}")
    if p.shape[0] < 3:
        raise PoseLayerError(f"need at least 3 correspondences for a pose, got {p.shape[0]}")
    if not (torch.isfinite(p).all() and torch.isfinite(q).all()):
        raise PoseLayerError("p or q contains non-finite values")
    if not torch.isfinite(C).all():
        raise PoseLayerError("covariances C contain non-finite values")


def solve_pose(
    p: torch.Tensor,
    q: torch.Tensor,
    C: torch.Tensor,
    T0: torch.Tensor | None = None,
    max_iterations: int = 50,
    tol: float = 1e-10,
    exact_hessian_step: bool = True,
    max_condition: float = 1e12,
) -> PoseLayerResult:
    """Solve the WLS pose with ``Lambda_i = (2 C_i)^-1`` and make it differentiable in ``C``.

    Parameters
    ----------
    p, q : torch.Tensor
        ``(M, 3)`` corresponding source / target points (cast to float64).
    C : torch.Tensor
        ``(M, 3, 3)`` target covariances ``C_q`` (SPD); gradients flow through it.
    T0 : torch.Tensor, optional
        ``(4, 4)`` warm start (e.g. the memory's ``T̂``); default: unweighted Kabsch fit.
    max_iterations, tol
        Gauss-Newton limits; ``tol`` is on the max-norm of the tangent step.
    exact_hessian_step : bool
        Use the exact Hessian in the differentiable step (exact IFT derivative); if False, the
        Gauss-Newton Hessian (cheaper, approximate derivative).
    max_condition : float
        Raise :class:`PoseLayerError` if ``cond(H)`` exceeds this (degenerate geometry).

    Returns
    -------
    PoseLayerResult
    """
    _check_inputs(p, q, C)
    p = p.to(torch.float64)
    q = q.to(torch.float64)
    C = C.to(torch.float64)
    Cs = 0.5 * (C + C.transpose(-1, -2))
    with torch.no_grad():
        Lam0 = inv3(2.0 * Cs.detach())
        if not torch.isfinite(Lam0).all():
            raise PoseLayerError("covariances C are singular")
        T = (T0.detach().to(torch.float64).clone() if T0 is not None else kabsch(p, q))
        cost, g, H, _ = wls_terms(T, p, q, Lam0)
        converged = False
        it = 0
        for it in range(1, max_iterations + 1):
            ev = torch.linalg.eigvalsh(H)
            if not (ev[0] > 0 and ev[-1] / ev[0] < max_condition):
                raise PoseLayerError(
                    f"degenerate WLS Hessian (eigenvalues {ev[0].item():.3g} .. {ev[-1].item():.3g}); "
                    "correspondences do not constrain all 6 degrees of freedom"
                )
            step = -torch.linalg.solve(H, g)
            alpha = 1.0
            for _ in range(30):
                Tn = T @ exp_se3(alpha * step)
                cn, gn, Hn, _ = wls_terms(Tn, p, q, Lam0)
                if cn <= cost + 1e-12 * abs(cost.item()) + 1e-300:
                    break
                alpha *= 0.5
            T, cost, g, H = Tn, cn, gn, Hn
            if (alpha * step).abs().max() < tol:
                converged = True
                break
        if not converged:
            log.warning("pose layer: Gauss-Newton did not converge in %d iterations", max_iterations)
    T_opt = T
    Lam = inv3(2.0 * Cs)
    _, g, H_gn, d = wls_terms(T_opt, p, q, Lam)
    ev = torch.linalg.eigvalsh(H_gn.detach())
    if not (ev[0] > 0 and ev[-1] / ev[0] < max_condition):
        raise PoseLayerError(f"degenerate WLS Hessian at the optimum (eigenvalues {ev[0].item():.3g} .. {ev[-1].item():.3g})")
    A = exact_hessian(T_opt, p, d.detach(), Lam.detach(), H_gn.detach()) if exact_hessian_step else H_gn.detach()
    xi = -torch.linalg.solve(A, g)
    T_C = T_opt @ exp_se3(xi)
    # H at T(C) (equal in value to H_gn) so that its derivative includes the path through T(C).
    J_C = _jacobians(T_C, p)
    H_C = J_C.reshape(-1, 6).T @ (Lam @ J_C).reshape(-1, 6)
    return PoseLayerResult(T=T_C, H=H_C, T_opt=T_opt, iterations=it, converged=converged)
