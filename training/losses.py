"""The paper's two likelihood losses (Algorithm 1, lines 8 and 11), float64.

Correspondence NLL (paper Eq. corr_nll, without its constant 1/2, as in Algorithm 1)::

    L_corr = sum_i [ log|2 C_qi| + d~_i^T (2 C_qi)^-1 d~_i ],   d~_i = q_j - T̂_kl p_i

Pose NLL (paper Eq. pose_nll, without its 1/2, as in Algorithm 1)::

    L_pose = mu^T W^-1 mu + log|W|,   mu = Log(T(C)^-1 T̂),   W = Gamma + H(C)^-1

``H(C)`` is the Gauss-Newton Hessian of the WLS cost ``1/2 sum d^T (2C)^-1 d`` at its optimum
(the information of ``T(C)``, same as ``factors.wls.solve_wls(...).hessian``), and ``Gamma``
the covariance of the pose observation ``T̂`` in gtsam's tangent order ``[omega, v]``:
rad^2 for the three rotation entries, m^2 for the three translation entries.

Robust variant (``corr_likelihood="student_t"``, not the paper's; the trainer's default since
2026-12-05, ``"gaussian"`` gives the paper's): ``d~_i`` follows a multivariate
Student t with ``nu`` degrees of freedom and scale matrix ``2 C_qi`` (twice its negative log
density without the constant, so that it tends to ``L_corr`` as ``nu -> inf``)::

    L_corr_t = sum_i [ log|2 C_qi| + (nu + 3) log(1 + d~_i^T (2 C_qi)^-1 d~_i / nu) ]

Nearest-neighbour correspondences have heavy tails (a few per cent of them land on another
surface within the 1 m gate); under the Gaussian those few set the covariance's size along every
axis, under the t they weigh little and ``C`` describes the surface the inliers lie on.

The total per pair is ``lambda_corr * L_corr + lambda_pose * L_pose`` (see
:class:`training.trainer.TrainConfig`). ``L_corr`` can be summed (paper) or averaged over the
correspondences (default here, so that its size does not depend on how many correspondences
an edge has; with ``sum`` it is typically ~1000x larger than ``L_pose``).
"""

from __future__ import annotations

import math

import torch

from training.se3_torch import inverse_se3, log_se3

__all__ = ["LossError", "corr_nll", "pose_nll", "default_gamma", "LOG_2PI"]

#: ``corr_likelihood`` values of :func:`corr_nll`
CORR_LIKELIHOODS = ("gaussian", "student_t")

LOG_2PI = math.log(2 * math.pi)


class LossError(ValueError):
    """A loss received malformed or non-finite input (message says which)."""


def default_gamma(rot_std_rad: float = 2e-3, trans_std_m: float = 2e-2) -> torch.Tensor:
    """Diagonal ``Gamma`` (6x6, float64): ``rot_std_rad^2`` (rad^2) x3, ``trans_std_m^2`` (m^2) x3."""
    return torch.diag(torch.tensor([rot_std_rad**2] * 3 + [trans_std_m**2] * 3, dtype=torch.float64))


def corr_nll(C: torch.Tensor, d: torch.Tensor, reduction: str = "mean", likelihood: str = "gaussian",
             dof: float = 4.0) -> torch.Tensor:
    """Correspondence NLL ``sum_i log|2C_i| + d_i^T (2C_i)^-1 d_i`` (or its Student t form).

    Parameters
    ----------
    C : (M, 3, 3) SPD covariances of the target points (any float dtype; computed in float64).
    d : (M, 3) residuals ``q_j - T̂ p_i``.
    reduction : "mean" or "sum".
    likelihood : "gaussian" (the paper's) or "student_t": ``log|2C_i| + (dof + 3) log(1 + m_i / dof)``
        with ``m_i = d_i^T (2C_i)^-1 d_i`` (module docstring).
    dof : the t's degrees of freedom ``nu`` (> 0); unused by the Gaussian.
    """
    if C.ndim != 3 or C.shape[1:] != (3, 3) or d.shape != (C.shape[0], 3):
        raise LossError(f"corr_nll: C must be (M,3,3) and d (M,3); got {tuple(C.shape)}, {tuple(d.shape)}")
    if C.shape[0] == 0:
        raise LossError("corr_nll: no correspondences")
    if likelihood not in CORR_LIKELIHOODS:
        raise LossError(f"corr_nll: unknown likelihood {likelihood!r} (use one of {', '.join(CORR_LIKELIHOODS)})")
    if likelihood == "student_t" and not (math.isfinite(dof) and dof > 0):
        raise LossError(f"corr_nll: the Student t needs dof > 0, got {dof}")
    S = 2.0 * C.to(torch.float64)
    S = 0.5 * (S + S.transpose(-1, -2))
    L, info = torch.linalg.cholesky_ex(S)
    if bool((info != 0).any()):
        raise LossError(f"corr_nll: {int((info != 0).sum())} covariances are not positive definite")
    logdet = 2.0 * torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum(-1)
    z = torch.linalg.solve_triangular(L, d.to(torch.float64)[..., None], upper=False)[..., 0]
    mahalanobis = (z * z).sum(-1)
    if likelihood == "student_t":
        per = logdet + (dof + 3.0) * torch.log1p(mahalanobis / dof)
    else:
        per = logdet + mahalanobis
    if reduction == "mean":
        return per.mean()
    if reduction == "sum":
        return per.sum()
    raise LossError(f"corr_nll: unknown reduction {reduction!r} (use 'mean' or 'sum')")


def pose_nll(T_C: torch.Tensor, T_hat: torch.Tensor, H: torch.Tensor, Gamma: torch.Tensor) -> torch.Tensor:
    """Pose NLL ``mu^T W^-1 mu + log|W|`` with ``mu = Log(T(C)^-1 T̂)``, ``W = Gamma + H^-1``.

    Parameters
    ----------
    T_C : (4, 4) differentiable ``T(C)`` from :func:`training.pose_layer.solve_pose`.
    T_hat : (4, 4) the memory's ``T̂_kl``.
    H : (6, 6) Gauss-Newton Hessian at ``T(C)`` (differentiable).
    Gamma : (6, 6) SPD covariance of ``T̂`` ([omega, v]: rad^2, m^2).
    """
    T_hat = T_hat.to(torch.float64)
    mu = log_se3(inverse_se3(T_C) @ T_hat)
    W = Gamma.to(torch.float64) + torch.linalg.inv(H)
    W = 0.5 * (W + W.T)
    L, info = torch.linalg.cholesky_ex(W)
    if int(info) != 0:
        raise LossError("pose_nll: W = Gamma + H^-1 is not positive definite")
    z = torch.linalg.solve_triangular(L, mu[:, None], upper=False)[:, 0]
    return (z * z).sum() + 2.0 * torch.log(torch.diagonal(L)).sum()
