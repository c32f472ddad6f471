"""Helpers shared by the tests that check a pose covariance against Monte-Carlo draws of its estimate."""

from __future__ import annotations

import numpy as np


def mean_nees(errors: np.ndarray, covariances: np.ndarray) -> float:
    """Mean ``e^T Sigma^-1 e`` over draws: ``errors (T, 6)``, ``covariances (T, 6, 6)`` (ideal 6)."""
    return float(np.einsum("ti,tij,tj->t", errors, np.linalg.inv(covariances), errors).mean())


def spread_ratio(errors: np.ndarray, covariances: np.ndarray) -> float:
    """``trace(mean(Sigma)^-1 cov(errors)) / 6``: the draws' spread over the mean claimed one (ideal 1)."""
    return float(np.trace(np.linalg.solve(covariances.mean(0), np.cov(errors.T))) / 6)
