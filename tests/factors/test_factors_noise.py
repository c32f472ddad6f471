"""factors.noise: information noise models, eigenvalue floor, robust kernels, bad input."""

from __future__ import annotations

import logging

import gtsam
import numpy as np
import pytest
from factors_testutils import random_pose

from factors.noise import (
    NoiseModelError,
    between_factor,
    floored_information,
    information_noise_model,
    robust_noise_model,
)
from factors.se3 import exp_se3, inverse_se3, log_se3


def _random_spd(rng: np.random.Generator, eigenvalues) -> tuple[np.ndarray, np.ndarray]:
    Q, _ = np.linalg.qr(rng.normal(size=(6, 6)))
    H = (Q * np.asarray(eigenvalues, dtype=float)) @ Q.T
    return 0.5 * (H + H.T), Q


def _between_error(model, X1: np.ndarray, X2: np.ndarray, Z: np.ndarray) -> float:
    f = gtsam.BetweenFactorPose3(1, 2, gtsam.Pose3(Z), model)
    v = gtsam.Values()
    v.insert(1, gtsam.Pose3(X1))
    v.insert(2, gtsam.Pose3(X2))
    return f.error(v)


def test_information_model_has_information_h_in_a_between_factor():
    rng = np.random.default_rng(0)
    H, _ = _random_spd(rng, [10.0, 50.0, 200.0, 1e3, 5e3, 2e4])
    model, report = information_noise_model(H)
    np.testing.assert_allclose(model.information(), H, rtol=1e-10, atol=1e-10 * np.abs(H).max())
    assert report.floored == () and not report.was_floored
    np.testing.assert_allclose(report.eigenvalues, np.linalg.eigvalsh(H), rtol=1e-12)
    # BetweenFactorPose3 error = 1/2 mu^T H mu with mu = Log(Z^-1 X1^-1 X2), gtsam's convention
    X1, X2 = random_pose(rng), random_pose(rng)
    Z = inverse_se3(X1) @ X2 @ exp_se3(rng.normal(scale=0.05, size=6))
    mu = log_se3(np.linalg.inv(Z) @ inverse_se3(X1) @ X2)
    assert _between_error(model, X1, X2, Z) == pytest.approx(0.5 * mu @ H @ mu, rel=1e-9)

    scaled, rep2 = information_noise_model(H, scale=0.25)
    np.testing.assert_allclose(scaled.information(), 0.25 * H, rtol=1e-10, atol=1e-10 * np.abs(H).max())
    assert rep2.scale == 0.25


def test_eigenvalue_floor_keeps_directions_and_reports(caplog):
    rng = np.random.default_rng(1)
    H, Q = _random_spd(rng, [0.0, 1e-9, 300.0, 1e3, 5e3, 2e4])  # rank 4: a degenerate edge
    with pytest.raises(NoiseModelError, match="(?s)not positive definite.*min_eigenvalue"):
        information_noise_model(H)
    with caplog.at_level(logging.WARNING, logger="factors.noise"):
        model, report = information_noise_model(H, scale=2.0, min_eigenvalue=1.0)
    assert report.floored == (0, 1)
    assert report.was_floored and "2 eigenvalue(s) floored" in report.describe()
    assert any("floored" in r.getMessage() for r in caplog.records)
    info = model.information()
    evals, evecs = np.linalg.eigh(info)
    np.testing.assert_allclose(evals, [1.0, 1.0, 600.0, 2e3, 1e4, 4e4], rtol=1e-9)
    # the strong directions are untouched: info @ q_k = 2 lambda_k q_k
    for k, lam in zip(range(2, 6), [300.0, 1e3, 5e3, 2e4]):
        np.testing.assert_allclose(info @ Q[:, k], 2 * lam * Q[:, k], rtol=1e-9, atol=1e-7)
    # the floored directions now carry the floor information exactly
    for k in (0, 1):
        assert Q[:, k] @ info @ Q[:, k] == pytest.approx(1.0, rel=1e-9)
    # a floor below every eigenvalue changes nothing
    H_ok, _ = _random_spd(rng, [5.0, 6, 7, 8, 9, 10])
    out, rep = floored_information(H_ok, min_eigenvalue=1.0)
    assert rep.floored == ()
    np.testing.assert_array_equal(out, 0.5 * (H_ok + H_ok.T))


@pytest.mark.parametrize("kernel,k", [("cauchy", 2.0), ("huber", 1.5), ("Huber", None)])
def test_robust_model_applies_the_kernel_to_the_mahalanobis_distance(kernel, k):
    rng = np.random.default_rng(2)
    H, _ = _random_spd(rng, [10.0, 50.0, 200.0, 1e3, 5e3, 2e4])
    model, report = robust_noise_model(H, kernel=kernel, k=k)
    assert isinstance(model, gtsam.noiseModel.Robust)
    kk = k if k is not None else 1.345
    X1 = random_pose(rng)
    for size in (0.001, 0.5):  # inside and far outside the kernel threshold
        xi = rng.normal(size=6)
        xi *= size / np.sqrt(xi @ H @ xi) * 10
        Z = exp_se3(np.zeros(6))
        X2 = X1 @ exp_se3(xi)
        mu = log_se3(inverse_se3(X1) @ X2)
        r = float(np.sqrt(mu @ H @ mu))
        if kernel.lower() == "cauchy":
            expected = 0.5 * kk**2 * np.log1p((r / kk) ** 2)
        else:
            expected = 0.5 * r**2 if r <= kk else kk * r - 0.5 * kk**2
        assert _between_error(model, X1, X2, Z) == pytest.approx(expected, rel=1e-9)


def test_bad_information_is_rejected_with_clear_errors():
    rng = np.random.default_rng(3)
    H, _ = _random_spd(rng, [1.0, 2, 3, 4, 5, 6])
    asym = H.copy()
    asym[0, 5] += 1e-3
    with pytest.raises(NoiseModelError, match="not symmetric"):
        information_noise_model(asym)
    nan = H.copy()
    nan[2, 2] = np.nan
    with pytest.raises(NoiseModelError, match="non-finite"):
        information_noise_model(nan)
    with pytest.raises(NoiseModelError, match="non-finite"):
        robust_noise_model(np.full((6, 6), np.inf))
    neg, _ = _random_spd(rng, [-1.0, 2, 3, 4, 5, 6])
    with pytest.raises(NoiseModelError, match="not positive semi-definite"):
        information_noise_model(neg, min_eigenvalue=1.0)  # a floor does not excuse a wrong sign
    with pytest.raises(NoiseModelError, match="not positive semi-definite"):
        information_noise_model(neg)
    tiny, _ = _random_spd(rng, [1e-14, 2, 3, 4, 5, 6])  # PD on paper, singular numerically
    with pytest.raises(NoiseModelError, match="not positive definite"):
        information_noise_model(tiny)
    with pytest.raises(NoiseModelError, match="square"):
        information_noise_model(np.eye(6)[:5])
    with pytest.raises(NoiseModelError, match="scale"):
        information_noise_model(H, scale=0.0)
    with pytest.raises(NoiseModelError, match="min_eigenvalue"):
        information_noise_model(H, min_eigenvalue=-1.0)
    with pytest.raises(NoiseModelError, match="unknown robust kernel"):
        robust_noise_model(H, kernel="tukey")
    with pytest.raises(NoiseModelError, match="k must be positive"):
        robust_noise_model(H, kernel="huber", k=0.0)
    assert issubclass(NoiseModelError, ValueError)


def test_between_factor_from_wls_hessian_penalises_right_perturbations_with_h():
    rng = np.random.default_rng(4)
    H, _ = _random_spd(rng, [10.0, 50.0, 200.0, 1e3, 5e3, 2e4])
    T_hat = random_pose(rng)
    factor, report = between_factor(5, 9, T_hat, H, scale=0.5)
    assert list(factor.keys()) == [5, 9] and report.scale == 0.5
    X_l = random_pose(rng)
    mu = rng.normal(scale=0.01, size=6)
    X_k = X_l @ T_hat @ exp_se3(mu)  # X_l^-1 X_k = T_hat Exp(mu)
    v = gtsam.Values()
    v.insert(5, gtsam.Pose3(X_l))
    v.insert(9, gtsam.Pose3(X_k))
    assert factor.error(v) == pytest.approx(0.5 * 0.5 * mu @ H @ mu, rel=1e-9)
    robust, _ = between_factor(5, 9, T_hat, H, kernel="huber")
    assert isinstance(robust.noiseModel(), gtsam.noiseModel.Robust)
    with pytest.raises(NoiseModelError, match="rotation"):
        between_factor(5, 9, np.diag([1.0, 1.0, -1.0, 1.0]), H)
