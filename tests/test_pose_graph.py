"""Pose graph against closed forms."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from gr_graph.config import GraphConfig
from gr_graph.pose_graph import PoseGraph, build_pose_graph, position_covariance_world


def pose(t=(0, 0, 0), yaw=0.0):
    T = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = t
    return T


def test_two_poses_marginal_equals_factor_covariance():
    """Prior (tight) on X0 and one between factor with information Λ: Σ(X1) = Λ⁻¹."""
    rng = np.random.default_rng(0)
    A = rng.normal(size=(6, 6))
    Lam = A @ A.T + 3 * np.eye(6)
    g = PoseGraph(GraphConfig(prior_sigma=1e-7, min_information_eigenvalue=1e-9))
    T01 = pose((1.0, 0.2, 0.0), 0.3)
    g.add_pose(np.eye(4))
    g.add_pose(T01 @ pose((0.1, 0, 0)))  # perturbed initial guess
    g.add_edge(1, 0, T01, Lam)  # edge (k=1, l=0): T̂_10 maps scan 1 into frame 0
    res = g.optimize(marginals=True)
    np.testing.assert_allclose(res.poses[1], T01, atol=1e-8)
    np.testing.assert_allclose(res.covariances[1], np.linalg.inv(Lam), rtol=1e-5, atol=1e-10)


def test_loop_distributes_error_like_the_linear_closed_form():
    """Translation-only chain: N odometry steps of 1 m and a loop saying L; equal isotropic
    information → every step becomes 1 + (L − N)/(N + 1)."""
    N, L = 6, 6.7
    info = np.eye(6) * 100.0
    g = PoseGraph(GraphConfig(prior_sigma=1e-8, loop_kernel="none"))
    for i in range(N + 1):
        g.add_pose(pose((i, 0, 0)))
    for i in range(N):
        g.add_edge(i + 1, i, pose((1, 0, 0)), info)
    g.add_edge(N, 0, pose((L, 0, 0)), info, loop=True)
    res = g.optimize(marginals=False)
    steps = np.diff(res.poses[:, 0, 3])
    np.testing.assert_allclose(steps, 1 + (L - N) / (N + 1), atol=1e-7)
    np.testing.assert_allclose(res.poses[:, 1:3, 3], 0, atol=1e-9)


def test_robust_two_stage_closes_a_large_loop_error():
    """A loop whose initial error is tens of metres (drifted estimate) still closes, and the
    correction lands in the weak (flagged) edge."""
    N = 20
    strong, weak = np.eye(6) * 1e4, np.diag([1e2] * 3 + [1.0] * 3)
    g = PoseGraph(GraphConfig(prior_sigma=1e-8, loop_kernel="cauchy"))
    init = [pose((i, 0, 0)) for i in range(N + 1)]
    init = init[:10] + [pose((i + 30, 0, 0)) for i in range(10, N + 1)]  # a 30 m jump at edge 10
    for T in init:
        g.add_pose(T)
    for i in range(N):
        g.add_edge(i + 1, i, pose((31 if i == 9 else 1, 0, 0)), weak if i == 9 else strong)
    g.add_edge(N, 0, pose((N, 0, 0)), strong, loop=True)
    res = g.optimize(marginals=True)
    # single cycle, linear in x: each edge absorbs the misclosure r in proportion to its variance
    r = (N - 1 + 31) - N
    var = np.array([1.0 if i == 9 else 1e-4 for i in range(N)] + [1e-4])
    corr = r * var / var.sum()
    steps = np.array([31.0 if i == 9 else 1.0 for i in range(N)]) - corr[:N]
    np.testing.assert_allclose(res.poses[1:, 0, 3], np.cumsum(steps), atol=1e-4)
    assert abs(res.poses[N, 0, 3] - N) < 0.01
    # the uncertainty is largest in the middle of the loop, small at both ends
    tr = np.trace(res.covariances[:, 3:, 3:], axis1=1, axis2=2)
    assert tr[10] > 10 * tr[N] and tr[10] > 10 * tr[1]


def test_position_covariance_world_rotates():
    P = pose((0, 0, 0), np.pi / 2)[None]
    S = np.zeros((1, 6, 6))
    S[0, 3:, 3:] = np.diag([4.0, 1.0, 0.25])  # body x uncertain
    W = position_covariance_world(P, S)[0]
    np.testing.assert_allclose(W, np.diag([1.0, 4.0, 0.25]), atol=1e-12)  # body x = world y


def test_bad_edges_are_clear_errors():
    g = PoseGraph(GraphConfig())
    g.add_pose(np.eye(4))
    with pytest.raises(IndexError, match="outside"):
        g.add_edge(1, 0, np.eye(4), np.eye(6))
    g.add_pose(np.eye(4))
    with pytest.raises(ValueError, match="finite 6x6"):
        g.add_edge(1, 0, np.eye(4), np.full((6, 6), np.nan))
    bad_T = np.eye(4)
    bad_T[0, 3] = np.nan  # gtsam took it: optimize() returned the initial poses with a NaN error, no word
    with pytest.raises(ValueError, match=r"edge \(1, 0\): the measured transform must be a finite 4x4 .* 1 non-finite"):
        g.add_edge(1, 0, bad_T, np.eye(6))
    assert g.graph.size() == 1  # the prior only: nothing added


def test_between_factor_convention_matches_memory():
    """BetweenFactorPose3(X(l), X(k), T̂_kl) has zero error at T̂_kl = T_l⁻¹ T_k."""
    Tk, Tl = pose((3, 1, 0), 0.4), pose((1, -2, 0.5), -0.2)
    f = gtsam.BetweenFactorPose3(1, 2, gtsam.Pose3(np.linalg.inv(Tl) @ Tk), gtsam.noiseModel.Unit.Create(6))
    v = gtsam.Values()
    v.insert(1, gtsam.Pose3(Tl))
    v.insert(2, gtsam.Pose3(Tk))
    assert f.error(v) < 1e-20


def test_unanchored_component_is_reported_and_anchored():
    """Two chains, the second tied to nothing: plain gtsam.Marginals raises (indeterminate);
    the fallback names the component, anchors its first pose, keeps the first chain exact."""
    Lam = np.diag([400.0, 400.0, 400.0, 100.0, 100.0, 100.0])
    g = PoseGraph(GraphConfig(prior_sigma=1e-7, min_information_eigenvalue=1e-9))
    for i in range(4):
        g.add_pose(pose((float(i), 0.0, 0.0)))
    g.add_edge(1, 0, pose((1.0, 0, 0)), Lam)
    g.add_edge(3, 2, pose((1.0, 0, 0)), Lam)
    res = g.optimize(marginals=False)  # optimisation itself works (LM damping)
    np.testing.assert_allclose(res.poses[1][:3, 3], [1.0, 0, 0], atol=1e-8)
    with pytest.raises(RuntimeError, match="ndetermina"):
        g.marginal_covariances()
    covs, report = g.marginals_with_fallback()
    assert report.status == "anchored"
    assert report.failed_near_pose in (2, 3)
    assert report.n_components == 2 and report.unanchored_components == [[2, 3, 2]]
    assert report.fallback_poses == 2
    # pose 1 and pose 3 (relative to its anchored pose 2): the factor's covariance, as in the closed form
    np.testing.assert_allclose(covs[1], np.linalg.inv(Lam), rtol=1e-5, atol=1e-10)
    np.testing.assert_allclose(covs[3], np.linalg.inv(Lam), rtol=1e-5, atol=1e-10)
    assert report.to_dict()["status"] == "anchored"


def test_poorly_conditioned_graph_gets_the_regularising_prior():
    """A connected graph with an edge that fixes nothing along z: anchoring cannot help; the
    weak prior on every pose (sigma s) does. Along z, poses 2 and 3 are tied together and held
    only by their two weak priors (information a = 1/s^2 each, coupled by c = 100): the 2x2
    information [[a+c, -c], [-c, a+c]] gives variance (a+c) / (a (a+2c)), about s^2 / 2."""
    from gr_graph.pose_graph import REGULARISING_SIGMA

    g = PoseGraph(GraphConfig(min_information_eigenvalue=1e-30))
    for _ in range(4):
        g.add_pose(np.eye(4))
    g.add_edge(1, 0, np.eye(4), np.eye(6) * 100.0)
    g.add_edge(2, 1, np.eye(4), np.diag([1e6] * 5 + [1e-30]))
    g.add_edge(3, 2, np.eye(4), np.eye(6) * 100.0)
    g.optimize(marginals=False)
    covs, report = g.marginals_with_fallback()
    assert report.status == "regularised" and report.regularising_sigma == REGULARISING_SIGMA
    assert report.n_components == 1 and report.unanchored_components == []
    assert report.fallback_poses == 4
    assert np.all(np.isfinite(covs))
    a, c = REGULARISING_SIGMA**-2, 100.0
    assert covs[3][5, 5] == pytest.approx((a + c) / (a * (a + 2 * c)), rel=1e-6)
    assert covs[1][5, 5] == pytest.approx(1 / c, rel=1e-3)  # held through the edge by the prior on pose 0


def test_connected_graph_marginals_report_ok():
    g = PoseGraph(GraphConfig())
    g.add_pose(np.eye(4))
    g.add_pose(pose((1.0, 0, 0)))
    g.add_edge(1, 0, pose((1.0, 0, 0)), np.eye(6) * 100.0)
    g.optimize(marginals=False)
    covs, report = g.marginals_with_fallback()
    assert report.status == "ok" and report.error is None and report.fallback_poses == 0
    np.testing.assert_allclose(covs, g.marginal_covariances())


def test_build_pose_graph_adds_the_poses_and_edges_it_is_given():
    poses = np.stack([pose((i, 0.1 * i, 0), yaw=0.05 * i) for i in range(5)])
    info = np.diag([1e4, 1e4, 1e4, 100, 100, 100.0])
    edges = [(k + 1, k, np.linalg.inv(poses[k]) @ poses[k + 1] @ pose((0.01, 0, 0)), info, False) for k in range(4)]
    edges.append((4, 0, np.linalg.inv(poses[0]) @ poses[4], 4 * info, True))
    cfg = GraphConfig()
    built = build_pose_graph(cfg, poses, iter(edges))  # any iterable, consumed once
    by_hand = PoseGraph(cfg)
    for T in poses:
        by_hand.add_pose(T)
    for k, l, T, H, loop in edges:
        by_hand.add_edge(k, l, T, H, loop=loop)
    assert built.n_poses == 5 and built.n_loops == 1 and built.graph.size() == by_hand.graph.size() == 6
    assert built.graph.error(built.values) == pytest.approx(by_hand.graph.error(by_hand.values), rel=1e-12)
    assert built.graph.error(built.values) > 0  # the odometry's 1 cm disagrees with the poses
    np.testing.assert_allclose(built.optimize(marginals=False).poses, by_hand.optimize(marginals=False).poses,
                               atol=1e-12)
