"""Degeneracy of a pose information matrix: the directions in which an edge is unconstrained.

A scan-matching edge in a corridor does not constrain translation along the corridor; an
edge whose correspondences lie on one plane does not constrain the two in-plane translations
nor the rotation about the plane normal. Those directions are the eigenvectors of the pose
information ``H`` (gtsam order ``[omega, v]``) with small eigenvalues.

Rotation (rad) and translation (m) have different units, so eigenvalues of ``H`` mix them.
``length_scale`` (optional) expresses rotations as arc length at that distance before the
analysis, ``H_n = S H S`` with ``S = diag(1/L, 1/L, 1/L, 1, 1, 1)``, which makes the
relative threshold unit-consistent; by default ``H`` is analysed as given.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["DegeneracyReport", "degeneracy_report", "check_information_matrix"]

_SYM_RTOL = 1e-8


def check_information_matrix(H: np.ndarray, name: str = "H", error: type[Exception] = ValueError) -> np.ndarray:
    """Validate a square, finite, symmetric matrix and return its float64 symmetric part.

    Parameters
    ----------
    H : np.ndarray
        Square matrix.
    name : str
        Name used in error messages.
    error : type
        Exception class raised on failure.

    Raises
    ------
    error
        If ``H`` is not square, has non-finite entries, or ``max|H - H^T|`` exceeds
        ``1e-8 * max|H|``.
    """
    H = np.asarray(H, dtype=np.float64)
    if H.ndim != 2 or H.shape[0] != H.shape[1] or H.shape[0] == 0:
        raise error(f"{name} must be a non-empty square matrix, got shape {H.shape}")
    if not np.all(np.isfinite(H)):
        raise error(f"{name} has non-finite entries (nan or inf)")
    asym = float(np.abs(H - H.T).max())
    scale = float(np.abs(H).max())
    if asym > _SYM_RTOL * max(scale, np.finfo(float).tiny):
        raise error(f"{name} is not symmetric: max|H - H^T| = {asym:.3g} with max|H| = {scale:.3g}")
    return 0.5 * (H + H.T)


def _fmt_vec(x: np.ndarray) -> str:
    x = np.where(np.abs(x) < 5e-4, 0.0, x)  # print -0.0 as 0.0
    return "[" + ", ".join(f"{c:.3f}" for c in x) + "]"


@dataclass(frozen=True)
class DegeneracyReport:
    """Eigen-analysis of a 6x6 pose information matrix.

    Attributes
    ----------
    eigenvalues : np.ndarray
        ``(6,)`` eigenvalues in ascending order (of the length-scaled matrix if
        ``length_scale`` was given).
    eigenvectors : np.ndarray
        ``(6, 6)`` unit eigenvectors as columns, ``[omega, v]`` order, sign fixed so the
        largest-magnitude component is positive.
    weak_directions : tuple[int, ...]
        Indices (into ``eigenvalues``) of the unconstrained directions.
    condition_number : float
        ``max eigenvalue / min eigenvalue`` (``inf`` if the smallest is <= 0).
    is_degenerate : bool
        Whether any weak direction was found.
    threshold : float
        The eigenvalue threshold that was applied.
    length_scale : float or None
        The ``length_scale`` of the analysis: the eigenvectors' rotational parts are then arc
        lengths at that distance (``omega * length_scale``).
    """

    eigenvalues: np.ndarray
    eigenvectors: np.ndarray
    weak_directions: tuple[int, ...]
    condition_number: float
    is_degenerate: bool
    threshold: float
    length_scale: float | None = None

    def direction_names(self) -> list[str]:
        """Human-readable name of every weak direction.

        A direction ``xi = [omega, v]`` moves a point ``x`` (source frame) by
        ``omega x x + v``. With a negligible rotational part (``|omega| < 0.1``; eigenvectors
        are unit vectors) it is named ``"translation along [vx, vy, vz]"``; otherwise it is
        the screw motion ``"rotation about [axis] through [point]"`` with
        ``point = omega x v / |omega|^2`` (omitted when at the origin) and a pitch (translation
        along the axis per radian) when that is not negligible. With a ``length_scale`` the
        test is on the arc-length part, and the point and pitch use ``omega`` itself (the
        eigenvector's rotational part divided by the length scale).
        """
        names = []
        for k in self.weak_directions:
            v = self.eigenvectors[:, k]
            w, t = v[:3], v[3:]
            nw = float(np.linalg.norm(w))
            if nw < 0.1:
                text = "translation along " + _fmt_vec(t / np.linalg.norm(t))
            else:
                axis = w / nw
                omega = w / self.length_scale if self.length_scale is not None else w
                n_omega = float(np.linalg.norm(omega))
                point = np.cross(omega, t) / n_omega**2
                pitch = float(omega @ t) / n_omega**2
                text = "rotation about " + _fmt_vec(axis)
                if np.linalg.norm(point) > 1e-3:
                    text += " through " + _fmt_vec(point)
                if abs(pitch) > 1e-3:
                    text += f" (pitch {pitch:.3g} per rad)"
            names.append(f"{text}, eigenvalue {self.eigenvalues[k]:.3g}")
        return names

    def describe(self) -> str:
        """One paragraph summarising the report, naming each weak direction."""
        if not self.is_degenerate:
            return (
                f"well constrained: all 6 eigenvalues above {self.threshold:.3g} "
                f"(condition number {self.condition_number:.3g})"
            )
        names = "; ".join(self.direction_names())
        return (
            f"degenerate in {len(self.weak_directions)} direction(s) (eigenvalue < "
            f"{self.threshold:.3g}, condition number {self.condition_number:.3g}): {names}"
        )


def degeneracy_report(
    H: np.ndarray,
    rel_threshold: float = 1e-3,
    abs_threshold: float | None = None,
    length_scale: float | None = None,
) -> DegeneracyReport:
    """Find the directions in which a pose information matrix is (nearly) unconstrained.

    Parameters
    ----------
    H : np.ndarray
        ``(6, 6)`` symmetric pose information (e.g. :attr:`WLSResult.hessian`), gtsam order
        ``[omega, v]``.
    rel_threshold : float
        A direction is weak when its eigenvalue is below ``rel_threshold * max eigenvalue``.
        The comparison is strict (an eigenvalue equal to the threshold is not weak); an
        eigenvalue within a few ulps of the threshold may fall either way with the
        eigen-solver's rounding, so choose thresholds away from expected eigenvalues.
    abs_threshold : float, optional
        Additionally weak when the eigenvalue is below this absolute value.
    length_scale : float, optional
        Metres; if given, rotations are measured as arc length at this distance (see the
        module docstring) before the eigen-analysis.

    Returns
    -------
    DegeneracyReport

    Raises
    ------
    ValueError
        If ``H`` is not a finite symmetric 6x6 matrix or a threshold is invalid.
    """
    H = check_information_matrix(H, "H")
    if H.shape != (6, 6):
        raise ValueError(f"H must be 6x6 (pose information), got shape {H.shape}")
    if not (0.0 <= rel_threshold < 1.0):
        raise ValueError(f"rel_threshold must be in [0, 1), got {rel_threshold}")
    if abs_threshold is not None and not (np.isfinite(abs_threshold) and abs_threshold >= 0.0):
        raise ValueError(f"abs_threshold must be finite and >= 0, got {abs_threshold}")
    if length_scale is not None:
        if not (np.isfinite(length_scale) and length_scale > 0.0):
            raise ValueError(f"length_scale must be positive, got {length_scale}")
        s = np.array([1.0 / length_scale] * 3 + [1.0] * 3)
        H = H * s[:, None] * s[None, :]
    evals, evecs = np.linalg.eigh(H)
    idx = np.argmax(np.abs(evecs), axis=0)
    signs = np.sign(evecs[idx, np.arange(6)])
    evecs = evecs * np.where(signs == 0, 1.0, signs)
    lmax = float(evals[-1])
    threshold = rel_threshold * max(lmax, 0.0)
    if abs_threshold is not None:
        threshold = max(threshold, float(abs_threshold))
    weak = tuple(int(k) for k in np.flatnonzero(evals < threshold))
    if lmax <= 0.0:
        weak = tuple(range(6))
    cond = float(lmax / evals[0]) if evals[0] > 0.0 else float("inf")
    return DegeneracyReport(
        eigenvalues=evals,
        eigenvectors=evecs,
        weak_directions=weak,
        condition_number=cond,
        is_degenerate=len(weak) > 0,
        threshold=threshold,
        length_scale=None if length_scale is None else float(length_scale),
    )
