"""gtsam noise models whose information is a learned pose-likelihood Hessian ``H(C)``.

``information_noise_model(H)`` gives ``gtsam.noiseModel.Gaussian.Information(scale * H)``
(with an optional eigenvalue floor) for a ``BetweenFactorPose3``; ``robust_noise_model``
wraps it in a Huber or Cauchy m-estimator for loop closures. ``H`` is in gtsam's Pose3
tangent order ``[omega, v]`` (as :attr:`factors.wls.WLSResult.hessian` and small_gicp's
``RegistrationResult.H``).

Eigenvalue floor: a degenerate edge (corridor, single plane) has near-zero eigenvalues; a
floor ``min_eigenvalue`` replaces every eigenvalue of ``scale * H`` below it by the floor,
keeping the eigenvectors, so the factor stays well posed. Floored directions are listed in
the returned :class:`NoiseReport` and logged as a warning. Without a floor, non-positive-
definite input is rejected.

Why ``H`` is the right information: the WLS pose satisfies ``T = T* Exp(eta)`` with
``eta ~ N(0, H^-1)`` (right perturbation), and ``BetweenFactorPose3(X(l), X(k), T̂_kl)``
penalises ``mu = Log(T̂_kl^-1 X_l^-1 X_k)``, a right perturbation of the measurement, with
``1/2 mu^T Lambda mu``; so ``Lambda = H`` (see :func:`between_factor`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import gtsam
import numpy as np

from factors.degeneracy import check_information_matrix
from factors.se3 import check_pose

log = logging.getLogger(__name__)

__all__ = [
    "NoiseModelError",
    "NoiseReport",
    "floored_information",
    "information_noise_model",
    "robust_noise_model",
    "between_factor",
]

# Negative eigenvalues down to -_NEG_RTOL * max|eigenvalue| are treated as round-off of a PSD H.
_NEG_RTOL = 1e-9
# Without a floor, smallest / largest eigenvalue at or below this is numerically singular.
_SINGULAR_RTOL = 1e-12
# Default m-estimator thresholds (in whitened units): 95 % efficiency under Gaussian noise of ONE
# dimension. gtsam's Robust model weighs a factor's whole whitened error by w(||e||): for a 6-dof
# edge consistent with its information (||e||^2 ~ chi2(6), mean 6) the mean Cauchy weight at 2.3849
# is about 0.53, not 0.88 (a loop keeps about half its information in the robust solve).
DEFAULT_K = {"huber": 1.345, "cauchy": 2.3849}


class NoiseModelError(ValueError):
    """An information matrix cannot define a noise model (non-symmetric, non-finite, not PD)."""


@dataclass(frozen=True)
class NoiseReport:
    """What :func:`information_noise_model` did to the input information.

    Attributes
    ----------
    eigenvalues : np.ndarray
        Ascending eigenvalues of ``scale * H`` (before flooring).
    eigenvectors : np.ndarray
        Matching unit eigenvectors (columns), gtsam order ``[omega, v]``.
    floored : tuple[int, ...]
        Indices of the eigenvalues raised to the floor (empty if none).
    min_eigenvalue : float or None
        The floor that was applied.
    scale : float
        Scale applied to ``H``.
    information : np.ndarray
        The information matrix handed to gtsam (scaled, floored, exactly symmetric).
    """

    eigenvalues: np.ndarray
    eigenvectors: np.ndarray
    floored: tuple[int, ...]
    min_eigenvalue: float | None
    scale: float
    information: np.ndarray

    @property
    def was_floored(self) -> bool:
        """Whether any eigenvalue was raised to the floor (the edge is degenerate)."""
        return len(self.floored) > 0

    def describe(self) -> str:
        """One line naming the floored eigen-directions, if any."""
        if not self.floored:
            return f"information ok: eigenvalues {np.array2string(self.eigenvalues, precision=3)}"
        dirs = ", ".join(
            "[" + ", ".join(f"{x:.2f}" for x in self.eigenvectors[:, k]) + f"] ({self.eigenvalues[k]:.3g})"
            for k in self.floored
        )
        return f"{len(self.floored)} eigenvalue(s) floored to {self.min_eigenvalue:.3g}: {dirs}"


def floored_information(
    H: np.ndarray, scale: float = 1.0, min_eigenvalue: float | None = None
) -> tuple[np.ndarray, NoiseReport]:
    """Validate, scale and floor an information matrix (no gtsam object is built).

    Parameters
    ----------
    H : np.ndarray
        Square symmetric information matrix (``(6, 6)`` for a Pose3 edge).
    scale : float
        Positive factor multiplying ``H`` (e.g. to inflate an over-confident ``H``).
    min_eigenvalue : float, optional
        Positive floor for the eigenvalues of ``scale * H``.

    Returns
    -------
    information : np.ndarray
        ``scale * H`` with eigenvalues below the floor raised to it.
    report : NoiseReport

    Raises
    ------
    NoiseModelError
        If ``H`` is non-square, non-finite or non-symmetric; if ``scale`` or the floor is not
        a positive finite number; if ``H`` has a clearly negative eigenvalue (below
        ``-1e-9 * max|eigenvalue|``); or, without a floor, if ``scale * H`` is not positive
        definite (smallest eigenvalue ``<= 1e-12 *`` largest counts as singular).
    """
    H = check_information_matrix(H, "H (information)", error=NoiseModelError)
    if not (np.isfinite(scale) and scale > 0.0):
        raise NoiseModelError(f"scale must be a positive finite number, got {scale}")
    if min_eigenvalue is not None and not (np.isfinite(min_eigenvalue) and min_eigenvalue > 0.0):
        raise NoiseModelError(f"min_eigenvalue must be a positive finite number, got {min_eigenvalue}")
    info = float(scale) * H
    evals, evecs = np.linalg.eigh(info)
    top = float(np.abs(evals).max())
    if evals[0] < -_NEG_RTOL * top:
        raise NoiseModelError(
            f"H (information) is not positive semi-definite: smallest eigenvalue {evals[0]:.6g} "
            f"(largest {evals[-1]:.6g})"
        )
    floored: tuple[int, ...] = ()
    if min_eigenvalue is None:
        if evals[0] <= _SINGULAR_RTOL * evals[-1]:
            raise NoiseModelError(
                f"H (information) is not positive definite: smallest eigenvalue {evals[0]:.6g}, "
                f"largest {evals[-1]:.6g} (ratio below {_SINGULAR_RTOL:g} counts as singular); "
                "pass min_eigenvalue to floor degenerate directions"
            )
        out = info
    else:
        low = evals < min_eigenvalue
        floored = tuple(int(k) for k in np.flatnonzero(low))
        if floored:
            new = np.where(low, float(min_eigenvalue), evals)
            out = (evecs * new) @ evecs.T
            out = 0.5 * (out + out.T)
        else:
            out = info
    report = NoiseReport(
        eigenvalues=evals,
        eigenvectors=evecs,
        floored=floored,
        min_eigenvalue=None if min_eigenvalue is None else float(min_eigenvalue),
        scale=float(scale),
        information=out,
    )
    if floored:
        log.warning("noise model: %s", report.describe())
    return out, report


def information_noise_model(
    H: np.ndarray, scale: float = 1.0, min_eigenvalue: float | None = None
) -> tuple[gtsam.noiseModel.Base, NoiseReport]:
    """Gaussian noise model with information ``scale * H`` (eigenvalues floored if asked).

    Parameters
    ----------
    H : np.ndarray
        ``(6, 6)`` pose information of an edge, gtsam order ``[omega, v]``.
    scale : float
        Positive factor multiplying ``H``.
    min_eigenvalue : float, optional
        Floor for the eigenvalues of ``scale * H`` (see the module docstring).

    Returns
    -------
    model : gtsam.noiseModel.Base
        ``gtsam.noiseModel.Gaussian.Information(information)`` (gtsam may return its
        ``Diagonal`` subclass for a diagonal matrix).
    report : NoiseReport
        Eigenvalues, which were floored, and the information actually used.

    Raises
    ------
    NoiseModelError
        See :func:`floored_information`.
    """
    info, report = floored_information(H, scale=scale, min_eigenvalue=min_eigenvalue)
    return gtsam.noiseModel.Gaussian.Information(info), report


def robust_noise_model(
    H: np.ndarray,
    kernel: str = "cauchy",
    k: float | None = None,
    scale: float = 1.0,
    min_eigenvalue: float | None = None,
) -> tuple[gtsam.noiseModel.Base, NoiseReport]:
    """Robust (Huber / Cauchy) noise model around :func:`information_noise_model`, for loops.

    Parameters
    ----------
    H : np.ndarray
        ``(6, 6)`` pose information, gtsam order ``[omega, v]``.
    kernel : {"cauchy", "huber"}
        m-estimator applied to the whitened error norm (gtsam's block reweighting).
    k : float, optional
        Kernel threshold in whitened units; default 1.345 (Huber) or 2.3849 (Cauchy).
    scale, min_eigenvalue
        As in :func:`information_noise_model`.

    Returns
    -------
    model : gtsam.noiseModel.Robust
    report : NoiseReport

    Raises
    ------
    NoiseModelError
        On an unknown kernel, a non-positive ``k``, or an invalid ``H`` (see
        :func:`floored_information`).
    """
    name = str(kernel).lower()
    if name not in DEFAULT_K:
        raise NoiseModelError(f"unknown robust kernel {kernel!r}; expected 'cauchy' or 'huber'")
    kk = DEFAULT_K[name] if k is None else float(k)
    if not (np.isfinite(kk) and kk > 0.0):
        raise NoiseModelError(f"robust kernel threshold k must be positive and finite, got {k}")
    base, report = information_noise_model(H, scale=scale, min_eigenvalue=min_eigenvalue)
    if name == "huber":
        est = gtsam.noiseModel.mEstimator.Huber.Create(kk)
    else:
        est = gtsam.noiseModel.mEstimator.Cauchy.Create(kk)
    return gtsam.noiseModel.Robust.Create(est, base), report


def between_factor(
    key_target: int,
    key_source: int,
    T_target_source: np.ndarray,
    H: np.ndarray,
    *,
    scale: float = 1.0,
    min_eigenvalue: float | None = None,
    kernel: str | None = None,
    k: float | None = None,
) -> tuple[gtsam.BetweenFactorPose3, NoiseReport]:
    """``BetweenFactorPose3(key_target, key_source, T̂)`` with information ``scale * H``.

    Parameters
    ----------
    key_target, key_source : int
        Keys of ``X_l`` (target scan) and ``X_k`` (source scan); the factor measures
        ``X_l^-1 X_k = T̂_kl``.
    T_target_source : np.ndarray
        ``(4, 4)`` measured ``T̂_kl`` (maps source points into the target frame).
    H : np.ndarray
        ``(6, 6)`` information of ``T̂_kl`` (e.g. ``WLSResult.hessian``), gtsam order.
    scale, min_eigenvalue
        As in :func:`information_noise_model`.
    kernel, k
        If ``kernel`` is given, a robust model as in :func:`robust_noise_model`.

    Returns
    -------
    factor : gtsam.BetweenFactorPose3
    report : NoiseReport

    Raises
    ------
    NoiseModelError
        On an invalid ``H``, kernel or a malformed transform.
    """
    try:
        T = check_pose(T_target_source, "T_target_source", rot_tol=1e-6)
    except ValueError as exc:
        raise NoiseModelError(str(exc)) from None
    if kernel is None:
        model, report = information_noise_model(H, scale=scale, min_eigenvalue=min_eigenvalue)
    else:
        model, report = robust_noise_model(H, kernel=kernel, k=k, scale=scale, min_eigenvalue=min_eigenvalue)
    return gtsam.BetweenFactorPose3(int(key_target), int(key_source), gtsam.Pose3(T), model), report
