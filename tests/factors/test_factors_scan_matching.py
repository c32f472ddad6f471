"""factors.scan_matching: analytic Jacobians vs gtsam numerical derivatives, gtsam behaviour."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from factors_testutils import random_anisotropic_covariances, random_pose, sample_gaussian, transform
from gtsam.utils.numerical_derivative import numericalDerivative21, numericalDerivative22

from factors.noise import NoiseModelError
from factors.scan_matching import scan_matching_error, scan_matching_factor, whitening_matrices
from factors.se3 import inverse_se3
from factors.wls import WLSInputError, residual_information, solve_wls, wls_cost_gradient_hessian

# Central differences (delta = 1e-5) on residuals of size ~10: truncation ~1e-10, round-off
# ~1e-10; we require 1e-7 relative to the largest Jacobian entry (observed ~1e-10).
RTOL_NUMDIFF = 1e-7


def _edge(seed: int, n: int = 40, gicp: bool = False):
    rng = np.random.default_rng(seed)
    X_t, X_s = random_pose(rng, trans_scale=20.0), random_pose(rng, trans_scale=20.0)
    T = inverse_se3(X_t) @ X_s
    p = rng.uniform(-15, 15, size=(n, 3))
    cov_q = random_anisotropic_covariances(rng, n)
    cov_p = random_anisotropic_covariances(rng, n) if gicp else None
    q = transform(T, p) + sample_gaussian(rng, 2.0 * cov_q)
    return rng, X_t, X_s, T, p, q, cov_q, cov_p


def _rel_err(a, b) -> float:
    return float(np.abs(np.asarray(a) - np.asarray(b)).max() / max(1.0, np.abs(b).max()))


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
@pytest.mark.parametrize("gicp", [False, True])
def test_jacobians_match_gtsam_numerical_derivatives(seed, gicp):
    rng, X_t, X_s, T, p, q, cov_q, cov_p = _edge(seed, gicp=gicp)
    W = whitening_matrices(residual_information(cov_q, cov_p, T[:3, :3]))

    def h(Pt: gtsam.Pose3, Ps: gtsam.Pose3) -> np.ndarray:
        return scan_matching_error(Pt.matrix(), Ps.matrix(), p, q, W, compute_jacobians=False)[0]

    # evaluate away from the measurement too: perturb the source pose
    X_s_eval = X_s @ random_pose(rng, rot_scale=0.2, trans_scale=0.5)
    e, Jt, Js = scan_matching_error(X_t, X_s_eval, p, q, W)
    Pt, Ps = gtsam.Pose3(X_t), gtsam.Pose3(X_s_eval)
    num_t = numericalDerivative21(h, Pt, Ps)
    num_s = numericalDerivative22(h, Pt, Ps)
    assert _rel_err(Jt, num_t) < RTOL_NUMDIFF
    assert _rel_err(Js, num_s) < RTOL_NUMDIFF
    # whitening is right: |e|^2 / 2 is the WLS cost at the relative pose
    info = residual_information(cov_q, cov_p, T[:3, :3])
    cost = wls_cost_gradient_hessian(inverse_se3(X_t) @ X_s_eval, p, q, info)[0]
    assert 0.5 * e @ e == pytest.approx(cost, rel=1e-12)


@pytest.mark.parametrize("gicp", [False, True])
def test_custom_factor_uses_the_analytic_error_and_jacobians(gicp):
    rng, X_t, X_s, T, p, q, cov_q, cov_p = _edge(4, gicp=gicp)
    factor = scan_matching_factor(7, 3, p, q, cov_q, cov_p, T_ref=T if gicp else None)
    assert list(factor.keys()) == [7, 3]
    assert factor.dim() == 3 * p.shape[0]
    values = gtsam.Values()
    values.insert(7, gtsam.Pose3(X_t))
    values.insert(3, gtsam.Pose3(X_s))
    W = whitening_matrices(residual_information(cov_q, cov_p, T[:3, :3]))
    e, Jt, Js = scan_matching_error(X_t, X_s, p, q, W)
    A, b = factor.linearize(values).jacobian()
    np.testing.assert_allclose(A, np.hstack([Jt, Js]), rtol=0, atol=1e-12 * np.abs(A).max())
    np.testing.assert_allclose(b, -e, atol=1e-12 * np.abs(e).max())
    assert factor.error(values) == pytest.approx(0.5 * e @ e, rel=1e-12)


def test_graph_optimum_and_marginal_match_the_wls_solution():
    """Prior on the target + the factor: LM finds solve_wls's pose and marginal H^-1."""
    rng, X_t, X_s, T, p, q, cov_q, _ = _edge(5, n=200)
    res = solve_wls(p, q, cov_q)
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose3(1, gtsam.Pose3(X_t), gtsam.noiseModel.Isotropic.Sigma(6, 1e-9)))
    graph.add(scan_matching_factor(1, 2, p, q, cov_q))
    init = gtsam.Values()
    init.insert(1, gtsam.Pose3(X_t))
    init.insert(2, gtsam.Pose3(X_s @ random_pose(rng, rot_scale=0.05, trans_scale=0.3)))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-15)
    params.setAbsoluteErrorTol(1e-15)
    result = gtsam.LevenbergMarquardtOptimizer(graph, init, params).optimize()
    T_graph = inverse_se3(result.atPose3(1).matrix()) @ result.atPose3(2).matrix()
    np.testing.assert_allclose(T_graph, res.T, atol=1e-8)
    # With X_t pinned, the source marginal (tangent of X_s = X_t T) is H^-1 of the WLS pose,
    # since right perturbations of X_s and of T coincide.
    cov_s = gtsam.Marginals(graph, result).marginalCovariance(2)
    np.testing.assert_allclose(cov_s, np.linalg.inv(res.hessian), rtol=1e-5, atol=1e-12)


def test_robust_kernel_downweights_large_errors():
    _, X_t, X_s, T, p, q, cov_q, _ = _edge(6)
    q_bad = q + 5.0  # gross outliers
    plain = scan_matching_factor(1, 2, p, q_bad, cov_q)
    robust = scan_matching_factor(1, 2, p, q_bad, cov_q, kernel="cauchy", k=1.0)
    values = gtsam.Values()
    values.insert(1, gtsam.Pose3(X_t))
    values.insert(2, gtsam.Pose3(X_s))
    e = plain.unwhitenedError(values)
    s = float(e @ e)
    assert plain.error(values) == pytest.approx(0.5 * s, rel=1e-12)
    # gtsam's Cauchy loss of the whole (block-reweighted) error: k^2/2 log(1 + s / k^2)
    assert robust.error(values) == pytest.approx(0.5 * np.log1p(s), rel=1e-9)


def test_bad_input_raises_clear_errors():
    _, X_t, X_s, T, p, q, cov_q, cov_p = _edge(7, gicp=True)
    with pytest.raises(WLSInputError, match="T_ref"):
        scan_matching_factor(1, 2, p, q, cov_q, cov_p)
    with pytest.raises(WLSInputError, match="must differ"):
        scan_matching_factor(1, 1, p, q, cov_q)
    with pytest.raises(WLSInputError, match="same shape"):
        scan_matching_factor(1, 2, p, q[:-1], cov_q)
    with pytest.raises(WLSInputError, match="expected"):
        scan_matching_factor(1, 2, p, q, cov_q, cov_p[:-1], T_ref=T)
    with pytest.raises(NoiseModelError, match="kernel"):
        scan_matching_factor(1, 2, p, q, cov_q, kernel="tukey")
