"""Real LiDAR pair: our GICP-form Hessian / gradient against small_gicp's own linearisation.

small_gicp's ``RegistrationResult.H`` / ``.b`` are ``sum J^T Lambda J`` / ``sum J^T Lambda d``
with ``Lambda = (C_q + R C_p R^T)^-1`` and the same tangent order and side as gtsam, so at
the same pose, correspondences and covariances they must equal ours to round-off.
"""

from __future__ import annotations

import numpy as np
import pytest

from factors.degeneracy import degeneracy_report
from factors.noise import information_noise_model
from factors.wls import residual_information, solve_wls, wls_cost_gradient_hessian

small_gicp = pytest.importorskip("small_gicp")

MAX_CORR = 1.0  # small_gicp's max_correspondence_distance (m); it keeps squared distance < 1.0


@pytest.fixture(scope="module")
def aligned_pair(small_gicp_pair_dir):
    target = small_gicp.read_ply(str(small_gicp_pair_dir / "target.ply"))
    source = small_gicp.read_ply(str(small_gicp_pair_dir / "source.ply"))
    tgt, tree = small_gicp.preprocess_points(target, 0.5, num_threads=1)
    src, _ = small_gicp.preprocess_points(source, 0.5, num_threads=1)
    res = small_gicp.align(tgt, src, tree, np.eye(4), "GICP", max_correspondence_distance=MAX_CORR)
    assert res.converged
    T = np.asarray(res.T_target_source)
    # One more iteration started at T: its H and b are the linearisation at exactly T.
    lin = small_gicp.align(
        tgt, src, tree, T, "GICP", max_correspondence_distance=MAX_CORR, max_iterations=1
    )
    P = np.asarray(src.points())[:, :3]
    Q = np.asarray(tgt.points())[:, :3]
    idx, sq = tree.batch_nearest_neighbor_search(P @ T[:3, :3].T + T[:3, 3])
    idx = np.asarray(idx, dtype=np.int64).ravel()
    keep = np.asarray(sq).ravel() < MAX_CORR**2
    cov_p = np.asarray(src.covs())[keep, :3, :3]
    cov_q = np.asarray(tgt.covs())[idx[keep], :3, :3]
    return {
        "T": T,
        "lin": lin,
        "p": P[keep],
        "q": Q[idx[keep]],
        "cov_p": cov_p,
        "cov_q": cov_q,
        "reference_T": np.loadtxt(small_gicp_pair_dir / "T_target_source.txt"),
    }


def test_hessian_and_gradient_equal_small_gicp_linearisation(aligned_pair):
    a = aligned_pair
    assert a["p"].shape[0] == a["lin"].num_inliers
    info = residual_information(a["cov_q"], a["cov_p"], a["T"][:3, :3])
    cost, grad, H = wls_cost_gradient_hessian(a["T"], a["p"], a["q"], info)
    H_sg = np.asarray(a["lin"].H)
    assert np.abs(H - H_sg).max() <= 1e-10 * np.abs(H_sg).max()
    np.testing.assert_allclose(grad, np.asarray(a["lin"].b), rtol=0, atol=1e-9 * np.abs(grad).max())
    # small_gicp reports the error after its (tiny) final step, hence a looser cost check
    assert cost == pytest.approx(a["lin"].error, rel=1e-6)


def test_wls_refines_small_gicp_pose_and_gives_a_usable_noise_model(aligned_pair):
    a = aligned_pair
    res = solve_wls(a["p"], a["q"], a["cov_q"], a["cov_p"], T0=a["T"])
    assert res.converged
    # small_gicp stops at 0.1 deg / 1 mm steps; the fixed point is within that of its pose
    assert np.abs(res.T[:3, 3] - a["T"][:3, 3]).max() < 1e-3
    assert np.abs(res.T[:3, :3] - a["T"][:3, :3]).max() < np.radians(0.1)
    # and near the pair's reference transform (a few cm / a few tenths of a degree)
    assert np.linalg.norm(res.T[:3, 3] - a["reference_T"][:3, 3]) < 0.05
    model, report = information_noise_model(res.hessian)
    assert not report.was_floored
    np.testing.assert_allclose(model.information(), res.hessian, rtol=1e-9, atol=1e-9 * np.abs(res.hessian).max())
    rep = degeneracy_report(res.hessian)
    assert not rep.is_degenerate, rep.describe()
