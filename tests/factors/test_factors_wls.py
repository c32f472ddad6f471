"""factors.wls: derivatives vs numerical derivatives, closed forms, statistics, bad input."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from factors_testutils import (
    random_anisotropic_covariances,
    random_pose,
    random_rotation,
    sample_gaussian,
    transform,
)
from gtsam.utils.numerical_derivative import numericalDerivative11
from scipy.stats import chi2

from factors.degeneracy import degeneracy_report
from factors.scan_matching import scan_matching_factor
from factors.se3 import exp_se3, inverse_se3, log_se3
from factors.wls import (
    WLSInputError,
    residual_information,
    solve_wls,
    umeyama,
    wls_cost_gradient_hessian,
    wls_residuals,
)

# Central differences (gtsam, delta = 1e-5) have truncation error ~delta^2 ~ 1e-10 and
# round-off ~ eps * |f| / delta ~ 2e-11 |f|; analytic vs numerical derivatives must agree to
# 1e-6 relative to the largest entry (the observed agreement is ~1e-9).
RTOL_NUMDIFF = 1e-6


def _problem(seed: int, n: int = 60, noise: bool = True, sigmas=(0.3, 0.1, 0.01)):
    rng = np.random.default_rng(seed)
    p = rng.uniform(-10.0, 10.0, size=(n, 3))
    T_true = random_pose(rng)
    cov_q = random_anisotropic_covariances(rng, n, sigmas)
    q = transform(T_true, p)
    if noise:
        q = q + sample_gaussian(rng, 2.0 * cov_q)
    return rng, p, q, cov_q, T_true


def _assert_close_rel(actual, desired, rtol, what):
    scale = max(1.0, float(np.abs(desired).max()))
    err = float(np.abs(np.asarray(actual) - np.asarray(desired)).max())
    assert err <= rtol * scale, f"{what}: max abs error {err:.3g} > {rtol:g} * {scale:.3g}"


# --------------------------------------------------------------------------- derivatives


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("gicp", [False, True])
def test_gradient_and_residual_jacobian_match_numerical_derivative(seed, gicp):
    rng, p, q, cov_q, _ = _problem(seed)
    cov_p = random_anisotropic_covariances(rng, p.shape[0]) if gicp else None
    T = random_pose(rng)  # arbitrary evaluation point, far from the optimum
    info = residual_information(cov_q, cov_p, T[:3, :3])
    cost, grad, H = wls_cost_gradient_hessian(T, p, q, info)

    # cost at T equals the definition 1/2 sum d^T Lambda d
    d_ref = q - transform(T, p)
    assert cost == pytest.approx(0.5 * np.einsum("ni,nij,nj->", d_ref, info, d_ref), rel=1e-12)

    # gradient (Lambda frozen at T's rotation in the GICP form)
    def f(P: gtsam.Pose3) -> float:
        return wls_cost_gradient_hessian(P.matrix(), p, q, info)[0]

    num_grad = numericalDerivative11(f, gtsam.Pose3(T))[0]
    _assert_close_rel(grad, num_grad, RTOL_NUMDIFF, "gradient")

    # residual Jacobians J_i = [R [p]_x, -R]
    d, J = wls_residuals(T, p, q)
    num_J = numericalDerivative11(lambda P: wls_residuals(P.matrix(), p, q)[0].reshape(-1), gtsam.Pose3(T))
    _assert_close_rel(J.reshape(-1, 6), num_J, RTOL_NUMDIFF, "residual Jacobian")

    # Hessian is J^T Lambda J built from those Jacobians
    H_ref = np.einsum("nia,nij,njb->ab", J, info, J)
    _assert_close_rel(H, H_ref, 1e-12, "Hessian vs J^T Lambda J")


@pytest.mark.parametrize("seed", [3, 4])
def test_hessian_is_exact_on_noise_free_data(seed):
    _, p, q, cov_q, T_true = _problem(seed, noise=False)
    info = residual_information(cov_q)
    _, grad, H = wls_cost_gradient_hessian(T_true, p, q, info)
    assert np.abs(grad).max() < 1e-8 * np.abs(H).max()

    # (a) numerical Jacobian of the analytic gradient
    num_H = numericalDerivative11(
        lambda P: wls_cost_gradient_hessian(P.matrix(), p, q, info)[1], gtsam.Pose3(T_true)
    )
    _assert_close_rel(num_H, H, RTOL_NUMDIFF, "d(gradient)/dxi")

    # (b) second central differences of the cost itself, f(T Exp(xi)) around xi = 0
    delta = 1e-4

    def cost(xi):
        return wls_cost_gradient_hessian(T_true @ exp_se3(xi), p, q, info)[0]

    E = np.eye(6) * delta
    num_H2 = np.empty((6, 6))
    for j in range(6):
        for k in range(6):
            num_H2[j, k] = (
                cost(E[j] + E[k]) - cost(E[j] - E[k]) - cost(-E[j] + E[k]) + cost(-E[j] - E[k])
            ) / (4 * delta * delta)
    # truncation ~delta^2 relative: 1e-5 is a tight bound for this second difference
    _assert_close_rel(num_H2, H, 1e-5, "second differences of the cost")


@pytest.mark.parametrize("gicp", [False, True])
def test_hessian_equals_gtsam_linearization_of_the_factor(gicp):
    rng, p, q, cov_q, _ = _problem(5)
    cov_p = random_anisotropic_covariances(rng, p.shape[0]) if gicp else None
    res = solve_wls(p, q, cov_q, cov_p)
    assert res.converged
    factor = scan_matching_factor(
        1, 2, p, q, cov_q, cov_p, T_ref=res.T if gicp else None
    )
    values = gtsam.Values()
    values.insert(1, gtsam.Pose3())
    values.insert(2, gtsam.Pose3(res.T))
    lin = factor.linearize(values)
    A, b = lin.jacobian()
    A_s = A[:, 6:]  # columns of the source key
    _assert_close_rel(A_s.T @ A_s, res.hessian, 1e-12, "J^T Lambda J of gtsam's linearization")
    _assert_close_rel(lin.information()[6:, 6:], res.hessian, 1e-12, "linearized information")
    # gradient of 1/2 |A dx - b|^2 at dx = 0 is -A^T b
    _assert_close_rel(-A_s.T @ b, res.gradient, 1e-9, "gradient from gtsam's linearization")
    assert factor.error(values) == pytest.approx(res.cost, rel=1e-12)


# --------------------------------------------------------------------------- closed forms


def test_isotropic_equal_covariances_give_the_horn_umeyama_pose():
    rng, p, q, _, _ = _problem(6, n=80)
    cov = np.tile(0.04 * np.eye(3), (p.shape[0], 1, 1))
    res = solve_wls(p, q, cov)
    T_umeyama = umeyama(p, q)
    T_gtsam = gtsam.Pose3.Align(q.T.copy(), p.T.copy()).matrix()  # independent reference
    np.testing.assert_allclose(T_umeyama, T_gtsam, atol=1e-9)
    np.testing.assert_allclose(res.T, T_gtsam, atol=1e-9)
    # and from a bad start (identity) GN still reaches it
    res0 = solve_wls(p, q, cov, T0=np.eye(4))
    assert res0.converged
    np.testing.assert_allclose(res0.T, T_gtsam, atol=1e-9)


def test_weighted_umeyama_equals_duplicated_points():
    rng = np.random.default_rng(8)
    p = rng.normal(size=(20, 3)) * 4
    q = transform(random_pose(rng), p) + rng.normal(scale=0.3, size=(20, 3))
    w = rng.integers(1, 5, size=20)
    T_w = umeyama(p, q, weights=w.astype(float))
    T_dup = umeyama(np.repeat(p, w, axis=0), np.repeat(q, w, axis=0))
    np.testing.assert_allclose(T_w, T_dup, atol=1e-12)
    # a reflection-prone configuration still gives a proper rotation
    assert np.linalg.det(umeyama(p, -q)[:3, :3]) == pytest.approx(1.0)


@pytest.mark.parametrize("gicp", [False, True])
def test_noise_free_correspondences_give_the_true_pose(gicp):
    rng, p, q, cov_q, T_true = _problem(9, n=200, noise=False)
    cov_p = random_anisotropic_covariances(rng, p.shape[0]) if gicp else None
    res = solve_wls(p, q, cov_q, cov_p)
    assert res.converged
    np.testing.assert_allclose(res.T, T_true, atol=1e-9)
    assert res.cost < 1e-15 * float(np.abs(res.hessian).max())


def test_points_on_one_plane_have_exactly_three_weak_directions():
    rng = np.random.default_rng(10)
    n = 300
    normal_t = random_rotation(rng)[:, 2]  # plane normal in the target frame
    basis = np.linalg.svd(normal_t[None, :])[2][1:]  # two in-plane unit vectors
    uv = rng.uniform(-10, 10, size=(n, 2))
    q = 2.0 * normal_t + uv @ basis  # plane n.x = 2
    U = np.stack([basis[0], basis[1], normal_t], axis=1)
    cov_q = np.tile((U * np.array([0.5, 0.5, 1e-3]) ** 2) @ U.T, (n, 1, 1))  # flat Gaussians
    T_true = random_pose(rng)
    p = transform(inverse_se3(T_true), q)
    res = solve_wls(p, q, cov_q, T0=T_true)
    rep = degeneracy_report(res.hessian)
    assert rep.weak_directions == (0, 1, 2), rep.describe()
    assert rep.eigenvalues[3] > 1e3 * rep.eigenvalues[2]
    # the weak subspace is {in-plane translation, rotation about the normal} in the source frame
    R = T_true[:3, :3]
    n_s = R.T @ normal_t
    expected = np.zeros((6, 3))
    expected[:3, 0] = n_s
    expected[3:, 1] = R.T @ basis[0]
    expected[3:, 2] = R.T @ basis[1]
    cosines = np.linalg.svd(rep.eigenvectors[:, :3].T @ expected, compute_uv=False)
    np.testing.assert_allclose(cosines, 1.0, atol=1e-6)
    text = rep.describe()
    assert text.count("translation along") == 2 and text.count("rotation about") == 1


# --------------------------------------------------------------------------- statistics


def test_nees_is_consistent_with_the_inverse_hessian():
    """d_i ~ N(0, 2 C_qi): eta = Log(T*^-1 T_hat) should satisfy eta^T H eta ~ chi^2(6)."""
    rng = np.random.default_rng(11)
    trials, n = 400, 100
    nees = np.empty(trials)
    for k in range(trials):
        p = rng.uniform(-10, 10, size=(n, 3))
        cov_q = random_anisotropic_covariances(rng, n, sigmas=(0.1, 0.05, 0.01))
        T_true = random_pose(rng)
        q = transform(T_true, p) + sample_gaussian(rng, 2.0 * cov_q)
        res = solve_wls(p, q, cov_q)
        assert res.converged
        eta = log_se3(inverse_se3(T_true) @ res.T)
        nees[k] = eta @ res.hessian @ eta
    # mean of 400 chi^2(6) draws: std = sqrt(12 / 400) = 0.17; band = +-4 std
    assert 5.3 < nees.mean() < 6.7, nees.mean()
    # and the tail: fraction below the 95 % quantile, std = 0.011; band = +-3 std
    frac = float(np.mean(nees < chi2.ppf(0.95, 6)))
    assert 0.917 < frac < 0.983, frac


# --------------------------------------------------------------------------- GICP form


def test_gicp_form_uses_rotated_source_covariance_and_converges_to_its_fixed_point():
    rng, p, q, cov_q, _ = _problem(12)
    cov_p = random_anisotropic_covariances(rng, p.shape[0])
    R = random_rotation(rng)
    info = residual_information(cov_q, cov_p, R)
    np.testing.assert_allclose(
        info, np.linalg.inv(cov_q + R @ cov_p @ R.T), rtol=1e-10, atol=1e-10 * np.abs(info).max()
    )
    # without cov_p: the paper's (2 C_q)^-1; with cov_p = cov_q and R = I it coincides
    np.testing.assert_allclose(residual_information(cov_q), np.linalg.inv(2 * cov_q), rtol=1e-10)
    np.testing.assert_allclose(residual_information(cov_q, cov_q, np.eye(3)), residual_information(cov_q), rtol=1e-12)

    res = solve_wls(p, q, cov_q, cov_p)
    assert res.converged
    info_T = residual_information(cov_q, cov_p, res.T[:3, :3])
    cost, grad, H = wls_cost_gradient_hessian(res.T, p, q, info_T)
    assert res.cost == pytest.approx(cost, rel=1e-12)
    np.testing.assert_allclose(res.hessian, H, rtol=1e-12)
    # fixed point: the frozen-Lambda gradient vanishes (relative to the Hessian scale)
    assert np.abs(res.gradient).max() < 1e-7 * np.abs(res.hessian).max()


# --------------------------------------------------------------------------- bad input


def test_bad_input_raises_clear_errors():
    _, p, q, cov_q, _ = _problem(13, n=10)
    bad = cov_q.copy()
    bad[4] = -bad[4]
    with pytest.raises(WLSInputError, match=r"cov_q\[4\] is not positive definite"):
        solve_wls(p, q, bad)
    asym = cov_q.copy()
    asym[2, 0, 1] += 0.1
    with pytest.raises(WLSInputError, match=r"cov_q\[2\] is not symmetric"):
        solve_wls(p, q, asym)
    nan = cov_q.copy()
    nan[7, 1, 1] = np.nan
    with pytest.raises(WLSInputError, match=r"non-finite.*index 7"):
        solve_wls(p, q, nan)
    p_nan = p.copy()
    p_nan[3, 0] = np.inf
    with pytest.raises(WLSInputError, match="p has non-finite rows, first at index 3"):
        solve_wls(p_nan, q, cov_q)
    with pytest.raises(WLSInputError, match="same shape"):
        solve_wls(p, q[:-1], cov_q)
    with pytest.raises(WLSInputError, match="expected 10"):
        solve_wls(p, q, cov_q[:-1])
    with pytest.raises(WLSInputError, match="at least 3"):
        solve_wls(p[:2], q[:2], cov_q[:2])
    with pytest.raises(WLSInputError, match="T0"):
        solve_wls(p, q, cov_q, T0=np.diag([1.0, 1.0, -1.0, 1.0]))
    with pytest.raises(WLSInputError, match="rotation"):
        residual_information(cov_q, cov_q, np.ones((3, 3)))


@pytest.mark.parametrize("flatness", [1e-4, 1e-6])
@pytest.mark.parametrize("noise", [False, True])
def test_ill_conditioned_planar_problem_converges_at_round_off(flatness, noise):
    """Very flat Gaussians on one plane: cost differences hit round-off before the step does."""
    rng = np.random.default_rng(14)
    n = 300
    normal_t = random_rotation(rng)[:, 2]
    basis = np.linalg.svd(normal_t[None, :])[2][1:]
    q = 20.0 * normal_t + rng.uniform(-30, 30, size=(n, 2)) @ basis
    U = np.stack([basis[0], basis[1], normal_t], axis=1)
    cov = np.tile((U * np.array([0.5, 0.5, flatness]) ** 2) @ U.T, (n, 1, 1))
    T_true = random_pose(rng)
    p = transform(inverse_se3(T_true), q)
    if noise:
        q = q + sample_gaussian(rng, 2.0 * cov)
    res = solve_wls(p, q, cov)
    assert res.converged
    # the constrained directions (normal offset, tilts) are right to the noise level
    eta = log_se3(inverse_se3(T_true) @ res.T)
    H = res.hessian
    assert eta @ H @ eta < (chi2.ppf(0.999, 6) if noise else 1e-6)


def test_non_convergence_is_reported_not_raised(caplog):
    _, p, q, cov_q, T_true = _problem(15, noise=True)
    T0 = T_true @ exp_se3(np.array([0.5, -0.4, 0.3, 2.0, 1.0, -1.0]))
    with caplog.at_level("WARNING", logger="factors.wls"):
        res = solve_wls(p, q, cov_q, T0=T0, max_iterations=1)
    assert not res.converged and res.iterations == 1
    assert any("not converged" in r.getMessage() for r in caplog.records)
    # the returned cost / gradient / Hessian belong to the returned pose
    info = residual_information(cov_q)
    cost, grad, H = wls_cost_gradient_hessian(res.T, p, q, info)
    assert res.cost == pytest.approx(cost, rel=1e-12)
    np.testing.assert_allclose(res.gradient, grad, rtol=1e-9, atol=1e-9 * np.abs(grad).max())
