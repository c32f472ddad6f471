"""Weighted least-squares (WLS) pose from correspondences with per-point covariances.

Problem
-------
Given correspondences ``(p_i, q_i)`` (source point ``p_i`` of scan P, target point ``q_i`` of
scan Q) and per-point covariances, find the rigid transform ``T = (R, t)`` that maps source
points into the target frame by minimising::

    f(T) = 1/2 * sum_i d_i^T Lambda_i d_i,        d_i = q_i - T p_i = q_i - R p_i - t

with the residual information ``Lambda_i`` (see :func:`residual_information`):

* paper's case (shared local geometry):  ``Lambda_i = (2 C_qi)^-1``;
* GICP form:                             ``Lambda_i = (C_qi + R C_pi R^T)^-1``.

The factor 1/2 makes ``f`` the negative log-likelihood of the residuals (up to a constant),
so the Gauss-Newton Hessian ``H = sum_i J_i^T Lambda_i J_i`` is the Fisher information of the
pose and ``H^-1`` its covariance (the paper's ``H(C_q)``).

Conventions (gtsam's): tangent ``xi = [omega, v]`` (rotation first) and right perturbation
``T o Exp(xi)``. For that perturbation the residual Jacobian is
``J_i = d d_i / d xi = [R [p_i]_x, -R]`` (3x6), the gradient is
``g = sum_i J_i^T Lambda_i d_i`` and a Gauss-Newton step is ``T <- T Exp(-H^-1 g)``.

GICP form: ``Lambda_i`` depends on ``R``. Like GICP / small_gicp, the gradient and the Hessian
returned here treat ``Lambda_i`` as *fixed at the current R* (the solver recomputes it at every
iterate). The converged pose is therefore the fixed point where that fixed-Lambda gradient
vanishes, not a stationary point of the full ``f(T)`` with ``Lambda(R)`` differentiated. In
the paper's case ``Lambda_i`` does not depend on ``T`` and both notions coincide. With
small_gicp's covariances and correspondences, cost, gradient and Hessian equal small_gicp's
``RegistrationResult.error / b / H`` (tested on the real pair in ``../shared/data``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from factors.se3 import check_pose, check_rotation, exp_se3, hat

log = logging.getLogger(__name__)

__all__ = [
    "WLSResult",
    "WLSInputError",
    "validate_covariances",
    "residual_information",
    "umeyama",
    "wls_residuals",
    "wls_cost_gradient_hessian",
    "solve_wls",
]

# Relative asymmetry accepted in an input covariance (float32 round-off of a learned C).
_SYM_RTOL = 1e-6


class WLSInputError(ValueError):
    """Input of the WLS pose problem is malformed; the message names the offending argument."""


@dataclass(frozen=True)
class WLSResult:
    """Result of :func:`solve_wls`.

    Attributes
    ----------
    T : np.ndarray
        ``(4, 4)`` estimated transform mapping source points ``p`` into the target frame.
    cost : float
        ``1/2 sum_i d_i^T Lambda_i d_i`` at ``T``.
    gradient : np.ndarray
        ``(6,)`` gradient of the cost w.r.t. the right perturbation ``xi = [omega, v]`` at ``T``
        (``Lambda`` held fixed at ``T``'s rotation in the GICP form). Near zero when converged.
    hessian : np.ndarray
        ``(6, 6)`` Gauss-Newton Hessian ``sum_i J_i^T Lambda_i J_i`` at ``T``: the pose
        information in gtsam's ``[omega, v]`` order.
    iterations : int
        Number of Gauss-Newton steps taken after the warm start.
    converged : bool
        Whether the last step was smaller than ``tol`` (max-norm of the tangent step), or
        no further decrease was possible above the cost's round-off (see :func:`solve_wls`).
    """

    T: np.ndarray
    cost: float
    gradient: np.ndarray
    hessian: np.ndarray
    iterations: int
    converged: bool


def _as_points(x: np.ndarray, name: str) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3:
        raise WLSInputError(f"{name} must have shape (N, 3), got {x.shape}")
    if not np.all(np.isfinite(x)):
        bad = np.flatnonzero(~np.all(np.isfinite(x), axis=1))
        raise WLSInputError(f"{name} has non-finite rows, first at index {int(bad[0])}")
    return x


#: rotation tolerance of the inputs (tighter than a trajectory file's: they come from computation)
_ROT_TOL = 1e-6


def _check_rotation(R: np.ndarray, name: str = "R") -> np.ndarray:
    try:
        return check_rotation(R, name, _ROT_TOL)
    except ValueError as exc:
        raise WLSInputError(str(exc)) from None


def _check_transform(T: np.ndarray, name: str = "T") -> np.ndarray:
    try:
        return check_pose(T, name, _ROT_TOL)
    except ValueError as exc:
        raise WLSInputError(str(exc)) from None


# Internally a batch of 3x3 matrices is kept component-major: ``(9, N)`` contiguous, row
# ``3 a + b`` holding entry ``(a, b)`` of every matrix, and points as ``(3, N)``. Every
# per-point operation is then a handful of contiguous vector operations.


def _components(M: np.ndarray) -> np.ndarray:
    """``(N, 3, 3)`` -> contiguous ``(9, N)``."""
    return np.ascontiguousarray(M.reshape(-1, 9).T)


def _matrices(L: np.ndarray) -> np.ndarray:
    """Contiguous ``(9, N)`` -> ``(N, 3, 3)``."""
    return np.ascontiguousarray(L.T).reshape(-1, 3, 3)


def _rows(x: np.ndarray) -> np.ndarray:
    """``(N, 3)`` -> contiguous ``(3, N)``."""
    return np.ascontiguousarray(x.T)


def _spd_flags(C: np.ndarray) -> np.ndarray:
    """Sylvester's criterion for symmetric 3x3 matrices in ``(9, N)`` layout: True where PD."""
    a, b, c, _, e, f, _, _, i = C
    m2 = a * e - b * b
    det = a * (e * i - f * f) - b * (b * i - f * c) + c * (b * f - e * c)
    return (a > 0.0) & (m2 > 0.0) & (det > 0.0)


def _validated_components(cov: np.ndarray, name: str, n: int | None) -> np.ndarray:
    """Validate ``(N, 3, 3)`` covariances; return them symmetrised in ``(9, N)`` layout."""
    C = np.asarray(cov, dtype=np.float64)
    if C.ndim != 3 or C.shape[1:] != (3, 3):
        raise WLSInputError(f"{name} must have shape (N, 3, 3), got {C.shape}")
    if n is not None and C.shape[0] != n:
        raise WLSInputError(f"{name} has {C.shape[0]} covariances, expected {n} (one per point)")
    L = _components(C)
    if not np.isfinite(L).all():
        k = int(np.argmin(np.isfinite(L).all(axis=0)))
        raise WLSInputError(f"{name} has non-finite entries, first at index {k}")
    asym = np.maximum(np.maximum(np.abs(L[1] - L[3]), np.abs(L[2] - L[6])), np.abs(L[5] - L[7]))
    scale = np.maximum(np.maximum(np.abs(L[0]), np.abs(L[4])), np.abs(L[8]))
    bad = asym > _SYM_RTOL * np.maximum(scale, np.finfo(float).tiny)
    if bad.any():
        k = int(np.argmax(bad))
        raise WLSInputError(
            f"{name}[{k}] is not symmetric (max |C - C^T| = {asym[k]:.3g}, max |C| = {scale[k]:.3g})"
        )
    pd = _spd_flags(L)
    if not pd.all():
        k = int(np.argmin(pd))
        raise WLSInputError(
            f"{name}[{k}] is not positive definite (eigenvalues {np.linalg.eigvalsh(C[k])})"
        )
    for lo, up in ((3, 1), (6, 2), (7, 5)):
        L[lo] = L[up] = 0.5 * (L[lo] + L[up])
    return L


def validate_covariances(cov: np.ndarray, name: str, n: int | None = None) -> np.ndarray:
    """Check a batch of 3x3 covariances and return it symmetrised, as float64.

    Parameters
    ----------
    cov : np.ndarray
        ``(N, 3, 3)`` covariances.
    name : str
        Argument name used in error messages.
    n : int, optional
        Expected ``N``.

    Returns
    -------
    np.ndarray
        ``(N, 3, 3)`` float64, ``(C + C^T) / 2``.

    Raises
    ------
    WLSInputError
        On a wrong shape, non-finite entries, asymmetry beyond a relative ``1e-6`` or a
        matrix that is not positive definite (the message gives the first bad index).
    """
    return _matrices(_validated_components(cov, name, n))


def _inv3_spd(S: np.ndarray) -> np.ndarray:
    """Inverse of symmetric 3x3 matrices (``(9, N)`` layout) by the adjugate, upper triangles.

    Exact for SPD input (validated by the callers); the result is exactly symmetric.
    """
    a, b, c, _, e, f, _, _, i = S
    A = e * i - f * f
    B = c * f - b * i
    Cc = b * f - c * e
    inv_det = 1.0 / (a * A + b * B + c * Cc)
    out = np.empty_like(S)
    np.multiply(A, inv_det, out=out[0])
    np.multiply(B, inv_det, out=out[1])
    np.multiply(Cc, inv_det, out=out[2])
    np.multiply(a * i - c * c, inv_det, out=out[4])
    np.multiply(b * c - a * f, inv_det, out=out[5])
    np.multiply(a * e - b * b, inv_det, out=out[8])
    out[3], out[6], out[7] = out[1], out[2], out[5]
    return out


def _kron3(R: np.ndarray) -> np.ndarray:
    """``np.kron(R, R)`` for a 3x3 ``R``: ``[(a, b), (k, l)] = R[a, k] R[b, l]``."""
    return (R[:, None, :, None] * R[None, :, None, :]).reshape(9, 9)


def _rotate_covariances(C: np.ndarray, R: np.ndarray) -> np.ndarray:
    """``R C_i R^T`` in ``(9, N)`` layout: one ``(9, 9) x (9, N)`` product with ``R (x) R``."""
    return _kron3(R) @ C


def residual_information(
    cov_q: np.ndarray, cov_p: np.ndarray | None = None, R: np.ndarray | None = None
) -> np.ndarray:
    """Information ``Lambda_i`` of the residuals ``d_i = q_i - T p_i``.

    Parameters
    ----------
    cov_q : np.ndarray
        ``(N, 3, 3)`` covariances of the target points ``q_i`` (target frame).
    cov_p : np.ndarray, optional
        ``(N, 3, 3)`` covariances of the source points ``p_i`` (source frame). When omitted,
        the paper's shared-geometry case ``Lambda_i = (2 C_qi)^-1`` is returned.
    R : np.ndarray, optional
        ``(3, 3)`` rotation of the current ``T``, used only with ``cov_p``:
        ``Lambda_i = (C_qi + R C_pi R^T)^-1``. ``None`` means the identity rotation.

    Returns
    -------
    np.ndarray
        ``(N, 3, 3)`` symmetric positive-definite information matrices.

    Raises
    ------
    WLSInputError
        If a covariance is malformed, non-finite, non-symmetric or not positive definite, or
        ``R`` is not a rotation.
    """
    Cq = _validated_components(cov_q, "cov_q", None)
    if cov_p is None:
        S = 2.0 * Cq
    else:
        Cp = _validated_components(cov_p, "cov_p", Cq.shape[1])
        S = Cq + (Cp if R is None else _rotate_covariances(Cp, _check_rotation(R)))
    return _matrices(_inv3_spd(S))


def umeyama(p: np.ndarray, q: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Closed-form rigid transform minimising ``sum_i w_i |q_i - R p_i - t|^2`` (Horn/Umeyama).

    Parameters
    ----------
    p, q : np.ndarray
        ``(N, 3)`` source and target points, ``N >= 3``.
    weights : np.ndarray, optional
        ``(N,)`` non-negative scalar weights (default: all ones).

    Returns
    -------
    np.ndarray
        ``(4, 4)`` transform with ``q_i ~ R p_i + t`` (a proper rotation, det = +1; no scale).

    Raises
    ------
    WLSInputError
        On malformed points or weights. A rank-deficient configuration (collinear points)
        gives one of the optimal rotations and logs a warning.
    """
    p = _as_points(p, "p")
    q = _as_points(q, "q")
    if p.shape != q.shape:
        raise WLSInputError(f"p and q must have the same shape, got {p.shape} and {q.shape}")
    if p.shape[0] < 3:
        raise WLSInputError(f"need at least 3 correspondences, got {p.shape[0]}")
    if weights is None:
        w = np.full(p.shape[0], 1.0 / p.shape[0])
    else:
        w = np.asarray(weights, dtype=np.float64)
        if w.shape != (p.shape[0],):
            raise WLSInputError(f"weights must have shape ({p.shape[0]},), got {w.shape}")
        if not np.all(np.isfinite(w)) or np.any(w < 0.0) or w.sum() <= 0.0:
            raise WLSInputError("weights must be finite, non-negative and not all zero")
        w = w / w.sum()
    return _umeyama_rows(_rows(p), _rows(q), w)


def _umeyama_rows(pT: np.ndarray, qT: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Unchecked core of :func:`umeyama`; points as ``(3, N)``, weights summing to one."""
    mp = pT @ w
    mq = qT @ w
    # sum_i w_i (q_i - mq)(p_i - mp)^T without (3, N) temporaries of the centred points
    K = (qT * w) @ pT.T - np.outer(mq, mp)
    U, s, Vt = np.linalg.svd(K)
    if s[1] <= 1e-12 * max(s[0], np.finfo(float).tiny):
        log.warning("umeyama: correspondences are (nearly) collinear; rotation is not unique")
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    R = U @ D @ Vt
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = mq - R @ mp
    return T


def wls_residuals(T: np.ndarray, p: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Residuals ``d_i = q_i - T p_i`` and their Jacobians w.r.t. the right perturbation.

    Parameters
    ----------
    T : np.ndarray
        ``(4, 4)`` transform.
    p, q : np.ndarray
        ``(N, 3)`` float64 points (not validated here).

    Returns
    -------
    d : np.ndarray
        ``(N, 3)`` residuals.
    J : np.ndarray
        ``(N, 3, 6)`` Jacobians ``[R [p_i]_x, -R]`` of ``d_i`` w.r.t. ``xi`` in ``T o Exp(xi)``.
    """
    R, t = T[:3, :3], T[:3, 3]
    d = q - p @ R.T - t
    J = np.empty((p.shape[0], 3, 6))
    J[:, :, :3] = R @ hat(p)  # R [p]_x, broadcast over N
    J[:, :, 3:] = -R
    return d, J


def wls_cost_gradient_hessian(
    T: np.ndarray, p: np.ndarray, q: np.ndarray, info: np.ndarray
) -> tuple[float, np.ndarray, np.ndarray]:
    """Cost, gradient and Gauss-Newton Hessian of the WLS objective at a given ``T``.

    Parameters
    ----------
    T : np.ndarray
        ``(4, 4)`` transform mapping ``p`` into the target frame.
    p, q : np.ndarray
        ``(N, 3)`` source / target points.
    info : np.ndarray
        ``(N, 3, 3)`` residual information ``Lambda_i`` (symmetric), held fixed.

    Returns
    -------
    cost : float
        ``1/2 sum_i d_i^T Lambda_i d_i``.
    grad : np.ndarray
        ``(6,)`` ``sum_i J_i^T Lambda_i d_i``: derivative of the cost w.r.t. ``xi`` in
        ``T o Exp(xi)``, ``xi = [omega, v]``.
    H : np.ndarray
        ``(6, 6)`` ``sum_i J_i^T Lambda_i J_i`` (symmetric positive semi-definite).

    Notes
    -----
    Evaluated without forming the ``(N, 3, 6)`` Jacobians: the Hessian is assembled from
    the information moments ``sum Lambda_i``, ``sum p_i Lambda_i``, ``sum p_i p_i^T Lambda_i``
    (matrix products with the ``(9, N)`` component-major information), rotated by ``R``;
    the gradient from ``sum Lambda_i d_i`` and ``sum Lambda_i d_i p_i^T``.
    """
    T = _check_transform(T)
    p = _as_points(p, "p")
    q = _as_points(q, "q")
    n = p.shape[0]
    if q.shape[0] != n:
        raise WLSInputError(f"p and q must have the same length, got {n} and {q.shape[0]}")
    info = np.asarray(info, dtype=np.float64)
    if info.shape != (n, 3, 3):
        raise WLSInputError(f"info must have shape ({n}, 3, 3), got {info.shape}")
    L = _components(info)
    pT, qT = _rows(p), _rows(q)
    cost, grad = _cost_gradient(T, pT, qT, L)
    return cost, grad, _hessian_from_moments(T[:3, :3], _moments(pT, L))


# _EPS[c] = hat(e_c): hat(r) = sum_c r_c _EPS[c].
_EPS = hat(np.eye(3))


def _moments(pT: np.ndarray, L: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Information moments ``sum Lambda``, ``sum p_k Lambda``, ``sum p_k p_l Lambda`` (O(N)).

    ``pT`` is ``(3, N)``, ``L`` the ``(9, N)`` information. They do not depend on ``T``;
    with them the Hessian at any ``T`` costs O(1).
    """
    n = pT.shape[1]
    m0 = L.sum(axis=1).reshape(3, 3)
    m1 = (pT @ L.T).reshape(3, 3, 3)
    pp = (pT[:, None, :] * pT[None, :, :]).reshape(9, n)
    m2 = (pp @ L.T).reshape(3, 3, 3, 3)
    return m0, m1, m2


# Constant linear maps used by _hessian_from_moments (built once from _EPS):
# (sum Lambda [r]_x).ravel() = _M_MAP @ S.ravel(),  S[c] = sum r_c Lambda;
# (sum [r]_x^T Lambda [r]_x).ravel() = _K_MAP @ Q.ravel(),  Q[c, e] = sum r_c r_e Lambda.
_M_MAP = np.einsum("ay,cbj->ajcyb", np.eye(3), _EPS).reshape(9, 27)
_K_MAP = np.einsum("cai,ebj->ijceab", _EPS, _EPS).reshape(9, 81)


def _hessian_from_moments(
    R: np.ndarray, moments: tuple[np.ndarray, np.ndarray, np.ndarray]
) -> np.ndarray:
    """Gauss-Newton Hessian at rotation ``R`` from :func:`_moments` (O(1)).

    With ``r_i = R p_i``, ``J_i = [[r_i]_x, -I] diag(R, R)``, hence
    ``H = diag(R, R)^T K diag(R, R)`` with ``K = sum [[r]_x^T L [r]_x, -[r]_x^T L], [-L [r]_x, L]]``;
    the sums over ``r`` are the moments rotated by ``R``.
    """
    m0, m1, m2 = moments
    S = R @ m1.reshape(3, 9)  # S[c] = sum r_c Lambda, r = R p
    Q = _kron3(R) @ m2.reshape(9, 9)  # Q[(c, e)] = sum r_c r_e Lambda
    M = (_M_MAP @ S.ravel()).reshape(3, 3)  # sum Lambda [r]_x
    K = np.empty((6, 6))
    K[:3, :3] = (_K_MAP @ Q.ravel()).reshape(3, 3)  # sum [r]_x^T Lambda [r]_x
    K[:3, 3:] = -M.T
    K[3:, :3] = -M
    K[3:, 3:] = m0
    B = np.zeros((6, 6))
    B[:3, :3] = R
    B[3:, 3:] = R
    H = B.T @ K @ B
    return 0.5 * (H + H.T)


def _cost_gradient(
    T: np.ndarray, pT: np.ndarray, qT: np.ndarray, L: np.ndarray
) -> tuple[float, np.ndarray]:
    """Cost ``1/2 sum d^T Lambda d`` and gradient ``sum J^T Lambda d`` (O(N), exact sums).

    ``pT, qT`` are ``(3, N)``, ``L`` the ``(9, N)`` information.
    """
    R, t = T[:3, :3], T[:3, 3]
    d = qT - R @ pT - t[:, None]
    u = np.empty_like(d)  # Lambda_i d_i
    for a in range(3):
        np.multiply(L[3 * a], d[0], out=u[a])
        u[a] += L[3 * a + 1] * d[1]
        u[a] += L[3 * a + 2] * d[2]
    cost = 0.5 * float(d.ravel() @ u.ravel())
    # J_i^T u_i = [[p_i]_x^T R^T u_i ; -R^T u_i] = [(R^T u_i) x p_i ; -R^T u_i]
    G = R.T @ (u @ pT.T)  # sum (R^T u) p^T
    grad = np.empty(6)
    grad[:3] = (G[1, 2] - G[2, 1], G[2, 0] - G[0, 2], G[0, 1] - G[1, 0])
    grad[3:] = -(R.T @ u.sum(axis=1))
    return cost, grad


def _gn_step(H: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Solve ``H step = -g``; a singular ``H`` gets the minimum-norm least-squares step."""
    try:
        np.linalg.cholesky(H)  # positive definite?
        step = np.linalg.solve(H, -g)
        if np.all(np.isfinite(step)):
            return step
    except np.linalg.LinAlgError:
        pass
    log.warning("solve_wls: Hessian is singular (degenerate geometry); using a least-squares step")
    return np.linalg.lstsq(H, -g, rcond=1e-12)[0]


def solve_wls(
    p: np.ndarray,
    q: np.ndarray,
    cov_q: np.ndarray,
    cov_p: np.ndarray | None = None,
    T0: np.ndarray | None = None,
    max_iterations: int = 50,
    tol: float = 1e-10,
) -> WLSResult:
    """Weighted least-squares pose: closed-form warm start, then Gauss-Newton on SE(3).

    Parameters
    ----------
    p : np.ndarray
        ``(N, 3)`` source points (scan P), ``N >= 3``.
    q : np.ndarray
        ``(N, 3)`` corresponding target points (scan Q).
    cov_q : np.ndarray
        ``(N, 3, 3)`` covariances of ``q`` (target frame).
    cov_p : np.ndarray, optional
        ``(N, 3, 3)`` covariances of ``p`` (source frame). Omitted: paper's case
        ``Lambda_i = (2 C_qi)^-1``; given: GICP form ``Lambda_i = (C_qi + R C_pi R^T)^-1``,
        recomputed at each iterate and held fixed within a step (see the module docstring).
    T0 : np.ndarray, optional
        ``(4, 4)`` initial guess. Default: the Horn/Umeyama pose with isotropic weights
        ``w_i = 3 / trace(S_i)``, ``S_i`` the residual covariance (``trace`` is rotation
        invariant, so no rotation is needed for the GICP form).
    max_iterations : int
        Maximum number of Gauss-Newton steps.
    tol : float
        Convergence threshold on the max-norm of the tangent step ``[omega, v]``.

    Returns
    -------
    WLSResult
        Pose, cost ``1/2 sum d^T Lambda d``, gradient, Gauss-Newton Hessian (pose information,
        gtsam ``[omega, v]`` order, right perturbation), iterations, convergence flag; cost,
        gradient and Hessian are evaluated at the returned pose.

    Raises
    ------
    WLSInputError
        On malformed points, covariances or ``T0``.

    Notes
    -----
    A step that increases the (fixed-Lambda) cost is halved up to 30 times, so a poor warm
    start cannot make the iteration diverge. If no fraction of the step lowers the cost and
    the predicted decrease ``-g^T step / 2`` is within the cost's floating-point round-off
    (ill-conditioned, e.g. planar, problems at their optimum), the solve counts as converged.
    Non-convergence is logged and reported via ``converged=False``, never raised.
    """
    p = _as_points(p, "p")
    q = _as_points(q, "q")
    if p.shape != q.shape:
        raise WLSInputError(f"p and q must have the same shape, got {p.shape} and {q.shape}")
    n = p.shape[0]
    if n < 3:
        raise WLSInputError(f"need at least 3 correspondences, got {n}")
    if max_iterations < 0:
        raise WLSInputError(f"max_iterations must be >= 0, got {max_iterations}")
    if not (tol > 0.0):
        raise WLSInputError(f"tol must be positive, got {tol}")
    Lq = _validated_components(cov_q, "cov_q", n)
    Lp = None if cov_p is None else _validated_components(cov_p, "cov_p", n)
    pT, qT = _rows(p), _rows(q)

    if Lp is None:
        fixed_info = _inv3_spd(2.0 * Lq)
        fixed_moments = _moments(pT, fixed_info)
        trace_s = 2.0 * (Lq[0] + Lq[4] + Lq[8])
    else:
        fixed_info = None
        trace_s = Lq[0] + Lq[4] + Lq[8] + Lp[0] + Lp[4] + Lp[8]

    def info_at(T: np.ndarray) -> np.ndarray:
        if fixed_info is not None:
            return fixed_info
        return _inv3_spd(Lq + _rotate_covariances(Lp, T[:3, :3]))

    def hessian_at(T: np.ndarray, info: np.ndarray) -> np.ndarray:
        moments = fixed_moments if fixed_info is not None else _moments(pT, info)
        return _hessian_from_moments(T[:3, :3], moments)

    if T0 is None:
        w = 1.0 / trace_s  # isotropic weights 3 / trace(S_i), normalised
        T = _umeyama_rows(pT, qT, w / w.sum())
    else:
        T = _check_transform(T0, "T0").copy()

    info = info_at(T)
    cost, g = _cost_gradient(T, pT, qT, info)
    H = hessian_at(T, info)
    converged = False
    iterations = 0
    for _ in range(max_iterations):
        step = _gn_step(H, g)
        alpha = 1.0
        for _halving in range(30):
            T_new = _orthonormalize(T @ exp_se3(alpha * step))
            cost_new, g_new = _cost_gradient(T_new, pT, qT, info)  # Lambda frozen at T
            if cost_new <= cost + 1e-12 * abs(cost) + 1e-300:
                break
            alpha *= 0.5
        else:
            # Even a 2^-30 fraction of a descent direction did not lower the cost: the cost
            # differences are below its round-off. Converged if the Gauss-Newton model agrees.
            predicted = -0.5 * float(g @ step)
            level = _cost_roundoff(T, pT, qT, info, cost)
            converged = predicted <= 1e3 * level
            if not converged:
                log.warning(
                    "solve_wls: no descent along the Gauss-Newton step (predicted decrease %.3g, "
                    "cost round-off %.3g); stopping",
                    predicted,
                    level,
                )
            break
        T = T_new
        iterations += 1
        if fixed_info is None:  # GICP form: Lambda moves with R
            info = info_at(T)
            cost_new, g_new = _cost_gradient(T, pT, qT, info)
        cost, g = cost_new, g_new
        H = hessian_at(T, info)
        if np.max(np.abs(alpha * step)) < tol:
            converged = True
            break
    if not converged:
        log.warning(
            "solve_wls: not converged after %d iterations (tol=%g); returning the last iterate",
            iterations,
            tol,
        )
    return WLSResult(T=T, cost=cost, gradient=g, hessian=H, iterations=iterations, converged=converged)


def _cost_roundoff(T: np.ndarray, pT: np.ndarray, qT: np.ndarray, L: np.ndarray, cost: float) -> float:
    """Size of the floating-point noise in the cost at ``T``.

    Each residual carries an error ~ ``eps (|q_i| + |R p_i| + |t|)`` that enters the cost
    through ``d_i^T Lambda_i``; the sum adds ``eps * cost``.
    """
    R, t = T[:3, :3], T[:3, 3]
    r = R @ pT
    d = qT - r - t[:, None]
    u = np.einsum("an,abn->bn", d, L.reshape(3, 3, -1))  # Lambda_i d_i (Lambda symmetric)
    scale = np.abs(qT).sum(axis=0) + np.abs(r).sum(axis=0) + np.abs(t).sum()
    eps = np.finfo(float).eps
    return float(eps * (abs(cost) + (np.abs(u).sum(axis=0) * scale).sum()))


def _orthonormalize(T: np.ndarray) -> np.ndarray:
    """Project the rotation block back onto SO(3) (stops round-off drift over many steps)."""
    U, _, Vt = np.linalg.svd(T[:3, :3])
    T = T.copy()
    T[:3, :3] = U @ Vt
    return T
