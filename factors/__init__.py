"""gtsam factors and noise models whose uncertainty comes from learned geometry.

Modules
-------
se3
    ``hat``, ``exp_se3``, ``log_se3`` ... in gtsam's Pose3 convention (tangent ``[omega, v]``,
    right perturbation).
wls
    Weighted least-squares pose from correspondences with per-point covariances
    (``solve_wls``), its cost / gradient / Gauss-Newton Hessian, Horn/Umeyama warm start.
scan_matching
    Learned-noise scan-matching ``gtsam.CustomFactor`` with analytic Jacobians.
noise
    ``BetweenFactorPose3`` noise models from a pose information ``H`` (plain and robust).
degeneracy
    Weak eigen-directions of ``H`` (corridor, single plane) for front-end warnings.

Only numpy, scipy and gtsam are needed (no torch).
"""

from factors.degeneracy import DegeneracyReport, degeneracy_report
from factors.noise import (
    NoiseModelError,
    NoiseReport,
    between_factor,
    information_noise_model,
    robust_noise_model,
)
from factors.scan_matching import scan_matching_error, scan_matching_factor, whitening_matrices
from factors.se3 import adjoint_se3, exp_se3, hat, inverse_se3, log_se3
from factors.wls import (
    WLSInputError,
    WLSResult,
    residual_information,
    solve_wls,
    umeyama,
    wls_cost_gradient_hessian,
)

__all__ = [
    "DegeneracyReport",
    "NoiseModelError",
    "NoiseReport",
    "WLSInputError",
    "WLSResult",
    "adjoint_se3",
    "between_factor",
    "degeneracy_report",
    "exp_se3",
    "hat",
    "information_noise_model",
    "inverse_se3",
    "log_se3",
    "residual_information",
    "robust_noise_model",
    "scan_matching_error",
    "scan_matching_factor",
    "solve_wls",
    "umeyama",
    "whitening_matrices",
    "wls_cost_gradient_hessian",
]
