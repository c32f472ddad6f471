"""SE(3) / SO(3) maps in torch (float64), gtsam conventions.

Tangent vectors are ``xi = [omega, v]`` (rotation first) and perturbations act on the right,
``T o Exp(xi)``, exactly as gtsam's ``Pose3.Expmap`` / ``Pose3.Logmap`` and ``factors.se3``.
All functions are differentiable, including at (and near) the identity, where the
closed-form coefficients are replaced by their Taylor series.
"""

from __future__ import annotations

import torch

__all__ = ["hat", "vee", "exp_so3", "log_so3", "exp_se3", "log_se3", "inverse_se3"]

_SMALL = 1e-4  # below this angle (rad) log_so3 uses its Taylor branch (theta / sin theta has no cancellation)
_NEAR_PI = 1e-3  # within this of pi (rad) log_so3 reads the axis from the symmetric part (as factors.se3)
_SERIES_ANGLE = 0.05
"""Below this angle (rad) the coefficients of Exp and of V⁻¹ in Log are their Taylor series, to the
θ⁶ term (the next term is below 1e-16 there): the closed forms cancel digits for small angles, and
their autograd derivatives lose far more (B's derivative was 600 % off at 1.01e-4 with a 1e-4 cut)."""


def hat(w: torch.Tensor) -> torch.Tensor:
    """Skew-symmetric matrix ``[w]_x`` of ``(..., 3)`` vectors, shape ``(..., 3, 3)``."""
    z = torch.zeros_like(w[..., 0])
    x, y, s = w[..., 0], w[..., 1], w[..., 2]
    return torch.stack(
        [torch.stack([z, -s, y], -1), torch.stack([s, z, -x], -1), torch.stack([-y, x, z], -1)], -2
    )


def vee(W: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`hat` (uses the antisymmetric part)."""
    return 0.5 * torch.stack(
        [W[..., 2, 1] - W[..., 1, 2], W[..., 0, 2] - W[..., 2, 0], W[..., 1, 0] - W[..., 0, 1]], -1
    )


def _coeffs(theta2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``A = sin t / t``, ``B = (1 - cos t) / t^2``, ``Cc = (t - sin t) / t^3`` (safe at 0).

    ``B`` is computed as ``2 sin²(t/2) / t²`` (no cancellation), as in :mod:`factors.se3`."""
    small = theta2 < _SERIES_ANGLE**2
    t2s = torch.where(small, torch.ones_like(theta2), theta2)
    t = torch.sqrt(t2s)
    x = theta2
    A = torch.where(small, 1 - x / 6 + x**2 / 120 - x**3 / 5040, torch.sin(t) / t)
    B = torch.where(small, 0.5 - x / 24 + x**2 / 720 - x**3 / 40320, 2 * torch.sin(t / 2) ** 2 / t2s)
    Cc = torch.where(small, 1.0 / 6 - x / 120 + x**2 / 5040 - x**3 / 362880, (t - torch.sin(t)) / (t2s * t))
    return A, B, Cc


def exp_so3(w: torch.Tensor) -> torch.Tensor:
    """Rodrigues: ``(..., 3)`` -> ``(..., 3, 3)`` rotation."""
    W = hat(w)
    A, B, _ = _coeffs((w * w).sum(-1))
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand(W.shape)
    return eye + A[..., None, None] * W + B[..., None, None] * (W @ W)


def log_so3(R: torch.Tensor) -> torch.Tensor:
    """Rotation ``(..., 3, 3)`` -> axis-angle ``(..., 3)`` with ``|w| <= pi``, as :func:`factors.se3.log_so3`.

    Within ``_NEAR_PI`` of ``pi`` the axis is read from the symmetric part of ``R`` (``sin theta`` -> 0
    leaves the skew part without digits; ``theta / sin theta`` would be NaN at ``pi``); the value there
    is exact, its derivative is not used (the rotations training takes the log of are discrepancies
    between two estimates of the same relative pose, far from ``pi``). Every branch is computed with
    safe denominators, so the branches not taken give no NaN gradients.
    """
    s = vee(R)  # = sin(theta) * axis
    cos_t = ((R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2]) - 1) / 2
    sin_t = torch.linalg.norm(s, dim=-1)
    theta = torch.atan2(sin_t, cos_t)
    small = theta < _SMALL
    near_pi = (torch.pi - theta) < _NEAR_PI
    sin_safe = torch.where(small | near_pi, torch.ones_like(sin_t), sin_t)
    th2 = theta * theta
    factor = torch.where(small, 1 + th2 / 6 + 7 * th2 * th2 / 360, theta / sin_safe)
    regular = factor[..., None] * s
    if not bool(near_pi.any()):
        return regular
    # near pi: R ~ 2 n n^T - I (+ the sin term), so (sym(R) - cos I) / (1 - cos) = n n^T; the column of its
    # largest diagonal entry is n (up to sign), whose sign the skew part gives
    eye = torch.eye(3, dtype=R.dtype, device=R.device)
    one_minus_cos = torch.where(near_pi, 1 - cos_t, torch.ones_like(cos_t))
    nn = (0.5 * (R + R.transpose(-1, -2)) - cos_t[..., None, None] * eye) / one_minus_cos[..., None, None]
    diagonal = torch.diagonal(nn, dim1=-2, dim2=-1)
    k = diagonal.argmax(-1)
    column = torch.gather(nn, -1, k[..., None, None].expand(*k.shape, 3, 1))[..., 0]
    column_norm = torch.linalg.norm(column, dim=-1, keepdim=True)
    n = column / torch.where(near_pi[..., None], column_norm, torch.ones_like(column_norm))
    sign = torch.where((n * s).sum(-1) < 0, -torch.ones_like(theta), torch.ones_like(theta))
    return torch.where(near_pi[..., None], (sign * theta)[..., None] * n, regular)


def exp_se3(xi: torch.Tensor) -> torch.Tensor:
    """``(..., 6)`` tangent ``[omega, v]`` -> ``(..., 4, 4)`` transform (gtsam Pose3.Expmap)."""
    w, v = xi[..., :3], xi[..., 3:]
    W = hat(w)
    A, B, Cc = _coeffs((w * w).sum(-1))
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device).expand(W.shape)
    W2 = W @ W
    R = eye + A[..., None, None] * W + B[..., None, None] * W2
    V = eye + B[..., None, None] * W + Cc[..., None, None] * W2
    t = (V @ v[..., None])[..., 0]
    top = torch.cat([R, t[..., None]], -1)
    bottom = torch.zeros(top.shape[:-2] + (1, 4), dtype=xi.dtype, device=xi.device)
    bottom[..., 0, 3] = 1
    return torch.cat([top, bottom], -2)


def log_se3(T: torch.Tensor) -> torch.Tensor:
    """``(..., 4, 4)`` transform -> ``(..., 6)`` tangent ``[omega, v]`` (gtsam Pose3.Logmap)."""
    w = log_so3(T[..., :3, :3])
    t = T[..., :3, 3]
    theta2 = (w * w).sum(-1)
    small = theta2 < _SERIES_ANGLE**2
    t2s = torch.where(small, torch.ones_like(theta2), theta2)
    th = torch.sqrt(t2s)
    half = th / 2
    # V^-1 = I - W/2 + D W^2 with D = (1 - (t/2) cot(t/2)) / t^2  (-> 1/12 at 0)
    x = theta2
    D = torch.where(small, 1.0 / 12 + x / 720 + x**2 / 30240 + x**3 / 1209600,
                    (1 - half * torch.cos(half) / torch.sin(half)) / t2s)
    W = hat(w)
    Wt = (W @ t[..., None])[..., 0]
    WWt = (W @ Wt[..., None])[..., 0]
    v = t - 0.5 * Wt + D[..., None] * WWt
    return torch.cat([w, v], -1)


def inverse_se3(T: torch.Tensor) -> torch.Tensor:
    """Inverse of ``(..., 4, 4)`` rigid transforms."""
    R = T[..., :3, :3]
    t = T[..., :3, 3:]
    Rt = R.transpose(-1, -2)
    top = torch.cat([Rt, -Rt @ t], -1)
    return torch.cat([top, T[..., 3:, :]], -2)
