"""Learned-noise scan-matching factor: a gtsam ``CustomFactor`` between two ``Pose3`` keys.

For world poses ``X_t`` (target scan Q) and ``X_s`` (source scan P) the relative transform is
``T = X_t^-1 X_s`` (maps source points into the target frame, ``T̂_kl`` of the memory with
``k`` = source, ``l`` = target). The factor's error is the stack of whitened residuals::

    e_i = L_i^T d_i,     d_i = q_i - T p_i,     L_i L_i^T = Lambda_i

so that ``1/2 |e|^2 = 1/2 sum_i d_i^T Lambda_i d_i`` is exactly the WLS cost of
:mod:`factors.wls` and the factor's Gauss-Newton information for ``X_s`` (with ``X_t``
fixed at the identity) is ``WLSResult.hessian``. ``Lambda_i`` is ``(2 C_qi)^-1`` (paper) or,
with ``cov_p``, ``(C_qi + R_ref C_pi R_ref^T)^-1`` frozen at a reference rotation so that the
factor is a fixed least-squares problem with exact Jacobians.

Jacobians (right perturbations ``X o Exp(xi)``, ``xi = [omega, v]``)::

    d d_i / d xi_s = [R [p_i]_x, -R]          d d_i / d xi_t = [-[T p_i]_x, I]
"""

from __future__ import annotations

import functools

import gtsam
import numpy as np

from factors.noise import DEFAULT_K, NoiseModelError
from factors.se3 import hat, inverse_se3
from factors.wls import (
    WLSInputError,
    _as_points,
    _check_transform,
    residual_information,
)

__all__ = [
    "whitening_matrices",
    "scan_matching_error",
    "scan_matching_factor",
]


def whitening_matrices(info: np.ndarray) -> np.ndarray:
    """Upper-triangular ``W_i = L_i^T`` with ``L_i L_i^T = Lambda_i`` (so ``W_i^T W_i = Lambda_i``).

    Parameters
    ----------
    info : np.ndarray
        ``(N, 3, 3)`` symmetric positive-definite information matrices.

    Returns
    -------
    np.ndarray
        ``(N, 3, 3)`` whitening matrices; ``W_i d_i`` has identity covariance.
    """
    try:
        L = np.linalg.cholesky(np.asarray(info, dtype=np.float64))
    except np.linalg.LinAlgError as exc:
        raise WLSInputError("residual information is not positive definite") from exc
    return np.swapaxes(L, 1, 2)


def scan_matching_error(
    X_target: np.ndarray,
    X_source: np.ndarray,
    p: np.ndarray,
    q: np.ndarray,
    whiten: np.ndarray,
    compute_jacobians: bool = True,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Stacked whitened residuals and their Jacobians w.r.t. both poses (pure numpy).

    Parameters
    ----------
    X_target, X_source : np.ndarray
        ``(4, 4)`` world poses of the target (Q) and source (P) scans.
    p, q : np.ndarray
        ``(N, 3)`` source points (source frame) and target points (target frame).
    whiten : np.ndarray
        ``(N, 3, 3)`` whitening matrices ``W_i`` with ``W_i^T W_i = Lambda_i``
        (see :func:`whitening_matrices`).
    compute_jacobians : bool
        If False, the Jacobians are returned as ``None``.

    Returns
    -------
    error : np.ndarray
        ``(3N,)`` ``[W_1 d_1, ..., W_N d_N]``, ``d_i = q_i - X_t^-1 X_s p_i``.
    J_target : np.ndarray or None
        ``(3N, 6)`` derivative w.r.t. ``xi_t`` in ``X_t o Exp(xi_t)``.
    J_source : np.ndarray or None
        ``(3N, 6)`` derivative w.r.t. ``xi_s`` in ``X_s o Exp(xi_s)``.
    """
    T = inverse_se3(X_target) @ np.asarray(X_source, dtype=np.float64)
    R, t = T[:3, :3], T[:3, 3]
    y = p @ R.T + t
    d = q - y
    e = np.einsum("nij,nj->ni", whiten, d).reshape(-1)
    if not compute_jacobians:
        return e, None, None
    n = p.shape[0]
    Js = np.empty((n, 3, 6))
    Js[:, :, :3] = R @ hat(p)
    Js[:, :, 3:] = -R
    Jt = np.empty((n, 3, 6))
    Jt[:, :, :3] = -hat(y)
    Jt[:, :, 3:] = np.eye(3)
    return e, (whiten @ Jt).reshape(-1, 6), (whiten @ Js).reshape(-1, 6)


def _error_function(
    p: np.ndarray,
    q: np.ndarray,
    whiten: np.ndarray,
    this: gtsam.CustomFactor,
    values: gtsam.Values,
    jacobians: list[np.ndarray] | None,
) -> np.ndarray:
    """CustomFactor callback (bound to its data with ``functools.partial``)."""
    keys = this.keys()
    X_t = values.atPose3(keys[0]).matrix()
    X_s = values.atPose3(keys[1]).matrix()
    e, Jt, Js = scan_matching_error(X_t, X_s, p, q, whiten, compute_jacobians=jacobians is not None)
    if jacobians is not None:
        jacobians[0] = Jt
        jacobians[1] = Js
    return e


def scan_matching_factor(
    key_target: int,
    key_source: int,
    p: np.ndarray,
    q: np.ndarray,
    cov_q: np.ndarray,
    cov_p: np.ndarray | None = None,
    *,
    T_ref: np.ndarray | None = None,
    kernel: str | None = None,
    k: float | None = None,
) -> gtsam.CustomFactor:
    """Scan-matching factor with learned per-point covariances between two Pose3 keys.

    Parameters
    ----------
    key_target : int
        Key of the target scan's pose ``X_t`` (scan Q, points ``q``).
    key_source : int
        Key of the source scan's pose ``X_s`` (scan P, points ``p``).
    p : np.ndarray
        ``(N, 3)`` source points in the source frame.
    q : np.ndarray
        ``(N, 3)`` corresponding target points in the target frame.
    cov_q : np.ndarray
        ``(N, 3, 3)`` covariances of ``q`` (learned).
    cov_p : np.ndarray, optional
        ``(N, 3, 3)`` covariances of ``p``; omitted: ``Lambda_i = (2 C_qi)^-1``.
    T_ref : np.ndarray, optional
        ``(4, 4)`` reference relative pose ``X_t^-1 X_s`` (e.g. the odometry estimate); its
        rotation fixes ``Lambda_i = (C_qi + R C_pi R^T)^-1``. Required when ``cov_p`` is given.
    kernel : {"huber", "cauchy"}, optional
        If given, a robust kernel (gtsam block reweighting over the whole stacked error) with
        threshold ``k`` (defaults as in :func:`factors.noise.robust_noise_model`).

    Returns
    -------
    gtsam.CustomFactor
        Factor on ``[key_target, key_source]`` with a unit noise model of dimension ``3N``;
        its ``error(values)`` equals the WLS cost at ``T = X_t^-1 X_s``.

    Raises
    ------
    WLSInputError
        On malformed points/covariances, equal keys, or ``cov_p`` without ``T_ref``.
    """
    if int(key_target) == int(key_source):
        raise WLSInputError(f"key_target and key_source must differ, both are {key_target}")
    p = _as_points(p, "p")
    q = _as_points(q, "q")
    if p.shape != q.shape:
        raise WLSInputError(f"p and q must have the same shape, got {p.shape} and {q.shape}")
    if p.shape[0] < 1:
        raise WLSInputError("need at least one correspondence")
    if cov_p is not None:
        if T_ref is None:
            raise WLSInputError(
                "cov_p given without T_ref: the GICP information (C_q + R C_p R^T)^-1 needs the "
                "reference relative rotation R; pass T_ref (e.g. the odometry estimate)"
            )
        R = _check_transform(T_ref, "T_ref")[:3, :3]
        info = residual_information(cov_q, cov_p, R)
    else:
        info = residual_information(cov_q)
    if info.shape[0] != p.shape[0]:
        raise WLSInputError(f"cov_q has {info.shape[0]} covariances for {p.shape[0]} points")
    whiten = whitening_matrices(info)
    noise: gtsam.noiseModel.Base = gtsam.noiseModel.Unit.Create(3 * p.shape[0])
    if kernel is not None:
        name = kernel.lower()
        if name not in DEFAULT_K:
            raise NoiseModelError(f"unknown robust kernel {kernel!r}; expected 'cauchy' or 'huber'")
        kk = DEFAULT_K[name] if k is None else float(k)
        est = (
            gtsam.noiseModel.mEstimator.Huber.Create(kk)
            if name == "huber"
            else gtsam.noiseModel.mEstimator.Cauchy.Create(kk)
        )
        noise = gtsam.noiseModel.Robust.Create(est, noise)
    func = functools.partial(_error_function, p.copy(), q.copy(), whiten)
    return gtsam.CustomFactor(noise, [int(key_target), int(key_source)], func)
