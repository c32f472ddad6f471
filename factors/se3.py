"""SE(3) helpers in gtsam's convention, in plain numpy.

Conventions (the same as ``gtsam.Pose3``):

* a tangent vector is ``xi = [omega, v]`` (rotation first, then translation), shape ``(6,)``;
* ``exp_se3(xi)`` equals ``gtsam.Pose3.Expmap(xi).matrix()`` and ``log_se3(T)`` equals
  ``gtsam.Pose3.Logmap(gtsam.Pose3(T))``;
* perturbations are applied on the right: ``T @ exp_se3(xi)`` is ``Pose3.retract(xi)``.

Everything here is double precision and works on single poses; ``hat`` also accepts a
batch of vectors ``(..., 3)``.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "hat",
    "vee",
    "exp_so3",
    "log_so3",
    "rotation_angle",
    "ROT_TOL",
    "rotation_defects",
    "check_poses",
    "check_pose",
    "check_rotation",
    "exp_se3",
    "exp_se3_batch",
    "log_se3",
    "inverse_se3",
    "adjoint_se3",
]

_SMALL_ANGLE = 1e-5
# Below this angle the SE(3) coefficients are evaluated by their Taylor series.
_SERIES_ANGLE = 0.05
# Below this distance to pi the axis is read from the symmetric part of R (sin(theta) ~ 0).
_NEAR_PI = 1e-3
#: Default tolerance of the pose validators on ``max |R^T R - I|`` and ``|det R - 1|``. The
#: official KITTI ground truth (7 significant digits) deviates by about 2e-7.
ROT_TOL = 1e-4


def hat(w: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrix of a 3-vector, so that ``hat(w) @ x == np.cross(w, x)``.

    Parameters
    ----------
    w : np.ndarray
        ``(3,)`` vector or a batch ``(..., 3)``.

    Returns
    -------
    np.ndarray
        ``(3, 3)`` (or ``(..., 3, 3)``) skew-symmetric matrix.

    Raises
    ------
    ValueError
        If the last axis does not have length 3.
    """
    w = np.asarray(w, dtype=np.float64)
    if w.shape[-1:] != (3,):
        raise ValueError(f"hat expects a (..., 3) array, got shape {w.shape}")
    W = np.zeros(w.shape[:-1] + (3, 3), dtype=np.float64)
    W[..., 0, 1] = -w[..., 2]
    W[..., 0, 2] = w[..., 1]
    W[..., 1, 0] = w[..., 2]
    W[..., 1, 2] = -w[..., 0]
    W[..., 2, 0] = -w[..., 1]
    W[..., 2, 1] = w[..., 0]
    return W


def vee(W: np.ndarray) -> np.ndarray:
    """Inverse of :func:`hat`: the 3-vector of a (skew-symmetric) ``(..., 3, 3)`` matrix.

    Only the antisymmetric part of ``W`` is used.
    """
    W = np.asarray(W, dtype=np.float64)
    return 0.5 * np.stack(
        [W[..., 2, 1] - W[..., 1, 2], W[..., 0, 2] - W[..., 2, 0], W[..., 1, 0] - W[..., 0, 1]],
        axis=-1,
    )


def _check_vec(x: np.ndarray, n: int, name: str) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    if x.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},), got {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{name} contains non-finite values: {x}")
    return x


def rotation_defects(R: np.ndarray) -> np.ndarray:
    """``max(max|R^T R - I|, |det R - 1|)`` of each of ``(..., 3, 3)`` matrices (0 for a rotation)."""
    R = np.asarray(R, dtype=np.float64)
    gram = np.einsum("...ji,...jl->...il", R, R) - np.eye(3)
    return np.maximum(np.abs(gram).max(axis=(-2, -1)), np.abs(np.linalg.det(R) - 1.0))


def _validate_stack(arr: np.ndarray, name: str, rot_tol: float, label: str) -> None:
    """Raise ``ValueError`` for the first bad pose of ``(K, 4, 4)`` ``arr`` (``label``: "" or " pose")."""

    def where(k: int) -> str:
        return f"{name}:{label} {k}" if label else name

    if not np.all(np.isfinite(arr)):
        k = int(np.argwhere(~np.isfinite(arr).all(axis=(1, 2)))[0, 0])
        raise ValueError(f"{where(k)} has non-finite entries")
    bottom_ok = np.all(np.abs(arr[:, 3, :] - np.array([0.0, 0.0, 0.0, 1.0])) <= 1e-9, axis=1)
    if not bottom_ok.all():
        k = int(np.argmin(bottom_ok))
        raise ValueError(f"{where(k)} bottom row is {arr[k, 3].tolist()}, not [0, 0, 0, 1]")
    if len(arr):
        defects = rotation_defects(arr[:, :3, :3])
        bad = defects > rot_tol
        if bad.any():
            k = int(np.argmax(bad))
            raise ValueError(f"{where(k)} rotation is not orthonormal (defect {defects[k]:.3g} > tolerance {rot_tol:g})")


def check_poses(poses: np.ndarray, name: str = "poses", rot_tol: float = ROT_TOL) -> np.ndarray:
    """Validate a stack of rigid transforms and return it as ``(K, 4, 4)`` float64.

    The one pose validator (:func:`check_pose` is the same for one pose).

    Parameters
    ----------
    poses : array_like
        ``(K, 4, 4)`` homogeneous transforms.
    name : str
        Name used in error messages.
    rot_tol : float
        Tolerance on ``max |R^T R - I|`` and ``|det R - 1|`` (:func:`rotation_defects`).

    Raises
    ------
    ValueError
        Wrong shape, non-finite entries, bottom row not ``[0, 0, 0, 1]``, or a rotation
        block that is not a proper rotation within ``rot_tol`` (the first bad index is named).
    """
    arr = np.asarray(poses, dtype=np.float64)
    if arr.ndim != 3 or arr.shape[1:] != (4, 4):
        raise ValueError(f"{name}: expected shape (K, 4, 4), got {arr.shape}")
    _validate_stack(arr, name, rot_tol, " pose")
    return arr


def check_pose(T: np.ndarray, name: str = "T", rot_tol: float = ROT_TOL) -> np.ndarray:
    """Validate one rigid transform (as :func:`check_poses`) and return it as ``(4, 4)`` float64."""
    arr = np.asarray(T, dtype=np.float64)
    if arr.shape != (4, 4):
        raise ValueError(f"{name} must be a (4, 4) homogeneous transform, got shape {arr.shape}")
    _validate_stack(arr[None], name, rot_tol, "")
    return arr


def check_rotation(R: np.ndarray, name: str = "R", rot_tol: float = ROT_TOL) -> np.ndarray:
    """Validate one rotation matrix (as :func:`check_pose`) and return it as ``(3, 3)`` float64."""
    arr = np.asarray(R, dtype=np.float64)
    if arr.shape != (3, 3):
        raise ValueError(f"{name} must be a (3, 3) rotation matrix, got shape {arr.shape}")
    T = np.eye(4)
    T[:3, :3] = arr
    _validate_stack(T[None], name, rot_tol, "")
    return arr


def _so3_coefficients(theta: float) -> tuple[float, float, float]:
    """Return ``(A, B, C) = (sin t / t, (1 - cos t) / t^2, (t - sin t) / t^3)``, stable at 0."""
    t2 = theta * theta
    if theta < _SERIES_ANGLE:
        # Taylor series; truncation error < t^8 / 1e6 for t < 0.05.
        A = 1.0 - t2 / 6.0 + t2 * t2 / 120.0 - t2**3 / 5040.0
        B = 0.5 - t2 / 24.0 + t2 * t2 / 720.0 - t2**3 / 40320.0
        C = 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0 - t2**3 / 362880.0
        return A, B, C
    s = np.sin(theta)
    half = np.sin(0.5 * theta)
    return s / theta, 2.0 * half * half / t2, (theta - s) / (t2 * theta)


def exp_so3(w: np.ndarray) -> np.ndarray:
    """Rotation matrix ``Exp(w)`` of a rotation vector ``w`` (Rodrigues' formula)."""
    w = _check_vec(w, 3, "w")
    theta = float(np.linalg.norm(w))
    A, B, _ = _so3_coefficients(theta)
    W = hat(w)
    return np.eye(3) + A * W + B * (W @ W)


def log_so3(R: np.ndarray) -> np.ndarray:
    """Rotation vector ``w`` with ``exp_so3(w) == R``, ``|w| <= pi``.

    Parameters
    ----------
    R : np.ndarray
        ``(3, 3)`` rotation matrix.

    Returns
    -------
    np.ndarray
        ``(3,)`` rotation vector.
    """
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3):
        raise ValueError(f"R must have shape (3, 3), got {R.shape}")
    axis_sin = vee(R)  # = sin(theta) * n
    s = float(np.linalg.norm(axis_sin))
    c = 0.5 * (float(np.trace(R)) - 1.0)
    theta = float(np.arctan2(s, c))
    if theta < _SMALL_ANGLE:
        # theta / sin(theta) = 1 + theta^2 / 6 + ...
        return (1.0 + theta * theta / 6.0) * axis_sin
    if np.pi - theta > _NEAR_PI:
        return (theta / s) * axis_sin
    # Near pi: R ~ 2 n n^T - I (+ sin term); read n from the symmetric part.
    S = 0.5 * (R + R.T)
    B = (S - c * np.eye(3)) / (1.0 - c)  # = n n^T exactly for a rotation
    k = int(np.argmax(np.diag(B)))
    n = B[:, k] / np.sqrt(max(B[k, k], 1e-300))
    n /= np.linalg.norm(n)
    if float(n @ axis_sin) < 0.0:
        n = -n
    return theta * n


def rotation_angle(R: np.ndarray) -> float | np.ndarray:
    """Angle ``theta`` in ``[0, pi]`` of rotation matrices ``R`` (``(3, 3)`` or ``(..., 3, 3)``).

    ``theta = atan2(|vee(R - R^T)| / 2, (trace R - 1) / 2)``: the sine from the skew part and
    the cosine from the trace. For a rotation this is ``acos((trace R - 1) / 2)`` (KITTI's
    devkit formula), but accurate over the whole range, where ``acos`` loses half the digits
    near 0 and ``pi`` (it reports ~1e-8 rad for an exact match).

    Returns
    -------
    float or np.ndarray
        A float for one matrix, else an array of shape ``R.shape[:-2]``.
    """
    R = np.asarray(R, dtype=np.float64)
    if R.ndim < 2 or R.shape[-2:] != (3, 3):
        raise ValueError(f"R must have shape (..., 3, 3), got {R.shape}")
    c = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    skew = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], axis=-1)
    s = 0.5 * np.linalg.norm(skew, axis=-1)
    theta = np.arctan2(s, c)
    return float(theta) if theta.ndim == 0 else theta


def exp_se3(xi: np.ndarray) -> np.ndarray:
    """Homogeneous transform ``Exp(xi)`` for ``xi = [omega, v]`` (gtsam ``Pose3.Expmap``).

    Parameters
    ----------
    xi : np.ndarray
        ``(6,)`` tangent vector, rotation first.

    Returns
    -------
    np.ndarray
        ``(4, 4)`` transform ``[[Exp(omega), V(omega) v], [0, 1]]``.
    """
    xi = _check_vec(xi, 6, "xi")
    w, v = xi[:3], xi[3:]
    theta = float(np.linalg.norm(w))
    A, B, C = _so3_coefficients(theta)
    W = hat(w)
    W2 = W @ W
    T = np.eye(4)
    T[:3, :3] = np.eye(3) + A * W + B * W2
    T[:3, 3] = (np.eye(3) + B * W + C * W2) @ v
    return T


def exp_se3_batch(xi: np.ndarray) -> np.ndarray:
    """:func:`exp_se3` of every tangent vector of a batch: ``(..., 6) [omega, v] -> (..., 4, 4)``."""
    xi = np.asarray(xi, dtype=np.float64)
    if xi.shape[-1:] != (6,):
        raise ValueError(f"xi must have shape (..., 6), got {xi.shape}")
    w, v = xi[..., :3], xi[..., 3:]
    theta = np.linalg.norm(w, axis=-1)
    t2 = theta * theta
    series = theta < _SERIES_ANGLE
    ts = np.where(series, 1.0, theta)
    A = np.where(series, 1.0 - t2 / 6.0 + t2 * t2 / 120.0 - t2**3 / 5040.0, np.sin(ts) / ts)
    B = np.where(series, 0.5 - t2 / 24.0 + t2 * t2 / 720.0 - t2**3 / 40320.0,
                 2.0 * np.sin(0.5 * ts) ** 2 / (ts * ts))
    C = np.where(series, 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0 - t2**3 / 362880.0,
                 (ts - np.sin(ts)) / (ts * ts * ts))
    W = hat(w)
    W2 = W @ W
    eye = np.eye(3)
    T = np.zeros(xi.shape[:-1] + (4, 4))
    T[..., :3, :3] = eye + A[..., None, None] * W + B[..., None, None] * W2
    V = eye + B[..., None, None] * W + C[..., None, None] * W2
    T[..., :3, 3] = np.einsum("...ij,...j->...i", V, v)
    T[..., 3, 3] = 1.0
    return T


def log_se3(T: np.ndarray) -> np.ndarray:
    """Tangent vector ``xi = [omega, v]`` with ``exp_se3(xi) == T`` (gtsam ``Pose3.Logmap``).

    Parameters
    ----------
    T : np.ndarray
        ``(4, 4)`` rigid transform.

    Returns
    -------
    np.ndarray
        ``(6,)`` tangent vector, rotation first.
    """
    T = check_pose(T)
    w = log_so3(T[:3, :3])
    theta = float(np.linalg.norm(w))
    W = hat(w)
    if theta < _SERIES_ANGLE:
        t2 = theta * theta
        coef = 1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0 + t2**3 / 1209600.0
    else:
        half = 0.5 * theta
        coef = (1.0 - half * np.cos(half) / np.sin(half)) / (theta * theta)
    V_inv = np.eye(3) - 0.5 * W + coef * (W @ W)
    return np.concatenate([w, V_inv @ T[:3, 3]])


def inverse_se3(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform, ``[[R^T, -R^T t], [0, 1]]``."""
    T = check_pose(T)
    Ti = np.eye(4)
    Ti[:3, :3] = T[:3, :3].T
    Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return Ti


def adjoint_se3(T: np.ndarray) -> np.ndarray:
    """Adjoint ``(6, 6)`` of ``T`` in the ``[omega, v]`` order (gtsam ``Pose3.AdjointMap``).

    ``T @ exp_se3(xi) @ inverse_se3(T) == exp_se3(adjoint_se3(T) @ xi)``.
    """
    T = check_pose(T)
    R, t = T[:3, :3], T[:3, 3]
    Ad = np.zeros((6, 6))
    Ad[:3, :3] = R
    Ad[3:, :3] = hat(t) @ R
    Ad[3:, 3:] = R
    return Ad
