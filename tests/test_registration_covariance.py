"""Cluster-robust covariance of registrations: gradients against finite differences, the estimator
against Monte-Carlo spread of WLS estimates, correspondences against small_gicp's own Hessian."""

from __future__ import annotations

import numpy as np
import pytest
import small_gicp

from estimate_support import mean_nees, spread_ratio
from factors.se3 import exp_se3, log_se3
from factors.wls import solve_wls, wls_cost_gradient_hessian
from gr_graph.config import GraphConfig, OdometryConfig, PreprocessConfig
from gr_graph.odometry import VgicpOdometry, scaled_information
from gr_graph.preprocess import preprocess_scan
from gr_graph.registration_covariance import (
    Correspondences,
    cluster_robust_covariance,
    cluster_robust_information,
    cube_labels,
    gicp_correspondences,
    point_gradients,
    vgicp_correspondences,
)


def street(rng: np.random.Generator, n: int = 20000, noise: float = 0.01) -> np.ndarray:
    """A street: ground, two facades with recesses, a few boxes (x along the street)."""
    k = n // 4
    ground = np.c_[rng.uniform(-40, 40, 2 * k), rng.uniform(-9, 9, 2 * k), np.zeros(2 * k)]
    y_wall = np.where(rng.random(k) < 0.5, -9.0, 9.0)
    x_wall = rng.uniform(-40, 40, k)
    y_wall = y_wall + np.sign(y_wall) * 1.5 * (np.sin(x_wall / 3.0) > 0.6)  # recesses: hold x
    wall = np.c_[x_wall, y_wall, rng.uniform(0, 8, k)]
    boxes = []
    half = np.array([1.0, 2.0, 0.8])
    for cx, cy in ((-20, -4), (5, 3), (25, -5)):
        b = rng.uniform(-1, 1, (k // 3, 3)) * half
        axis = rng.integers(0, 3, len(b))  # each point on one face of the box
        b[np.arange(len(b)), axis] = np.sign(b[np.arange(len(b)), axis]) * half[axis]
        boxes.append(b + [cx, cy, 0.8])
    pts = np.vstack([ground, wall, *boxes])
    return pts + rng.normal(0, noise, pts.shape)


def numeric_point_gradient(T, p, q, info, eps=1e-6):
    out = np.zeros(6)
    for a in range(6):
        e = np.zeros(6)
        e[a] = eps
        c = []
        for s in (1, -1):
            Ts = T @ exp_se3(s * e)
            d = q - Ts[:3, :3] @ p - Ts[:3, 3]
            c.append(0.5 * d @ info @ d)
        out[a] = (c[0] - c[1]) / (2 * eps)
    return out


def test_point_gradients_against_finite_differences_and_their_sum():
    rng = np.random.default_rng(0)
    T = exp_se3(np.array([0.1, -0.2, 0.3, 1.0, -2.0, 0.5]))
    p = rng.normal(0, 5, (20, 3))
    q = p @ T[:3, :3].T + T[:3, 3] + rng.normal(0, 0.1, (20, 3))
    A = rng.normal(size=(20, 3, 3))
    info = A @ A.transpose(0, 2, 1) + 0.5 * np.eye(3)
    g = point_gradients(T, p, q, info)
    for i in range(0, 20, 5):
        np.testing.assert_allclose(g[i], numeric_point_gradient(T, p[i], q[i], info[i]), rtol=1e-5, atol=1e-7)
    _, grad, _ = wls_cost_gradient_hessian(T, p, q, info)
    np.testing.assert_allclose(g.sum(0), grad, rtol=1e-10, atol=1e-10)


def test_cube_labels_group_points_by_cube():
    pts = np.array([[0.1, 0.1, 0.1], [0.9, 0.2, 0.3], [1.1, 0.1, 0.1], [-0.1, 0.0, 0.0], [0.5, 0.5, 0.5]])
    labels, n = cube_labels(pts, 1.0)
    assert n == 3
    assert labels[0] == labels[1] == labels[4] and len({labels[0], labels[2], labels[3]}) == 3
    with pytest.raises(ValueError, match="positive"):
        cube_labels(pts, 0.0)


def test_cluster_robust_covariance_needs_enough_clusters_and_a_positive_hessian():
    rng = np.random.default_rng(1)
    g = rng.normal(size=(50, 6))
    labels = np.arange(50) % 10
    H = np.eye(6) * 4.0
    assert cluster_robust_covariance(H, g, labels, 10, min_clusters=11) is None
    assert cluster_robust_covariance(-H, g, labels, 10) is None
    cov = cluster_robust_covariance(H, g, labels, 10)
    sums = np.zeros((10, 6))
    np.add.at(sums, labels, g)
    np.testing.assert_allclose(cov, sums.T @ sums * (10 / 9) / 16.0)  # H^-1 M H^-1 with H = 4 I


def _wls_trials(clustered_sigma: float, point_sigma: float, trials: int = 300):
    """WLS estimates of a known pose from points whose noise is shared within 4 m cubes."""
    rng = np.random.default_rng(2)
    p = street(rng, n=1200, noise=0.0)
    p = p[rng.choice(len(p), 600, replace=False)]
    labels, n_clusters = cube_labels(p, 4.0)
    T_true = exp_se3(np.array([0.01, -0.02, 0.03, 0.5, 0.2, -0.1]))
    cov = np.broadcast_to(np.eye(3) * 0.01**2, (len(p), 3, 3))  # isotropic: Lambda proportional to I
    xi, sandwich, naive = [], [], []
    for _ in range(trials):
        shared = rng.normal(0, clustered_sigma, (n_clusters, 3))[labels]
        q = p @ T_true[:3, :3].T + T_true[:3, 3] + shared + rng.normal(0, point_sigma, p.shape)
        res = solve_wls(p, q, cov, cov, T0=T_true)
        info = np.linalg.inv(cov + res.T[:3, :3] @ cov @ res.T[:3, :3].T)
        g = point_gradients(res.T, p, q, info)
        sandwich.append(cluster_robust_covariance(res.hessian, g, labels, n_clusters))
        s2 = 2 * res.cost / (3 * len(p) - 6)  # the scaled Hessian's variance factor, hessian_scale 1
        naive.append(s2 * np.linalg.inv(res.hessian))
        xi.append(log_se3(np.linalg.inv(T_true) @ res.T))
    return np.array(xi), np.array(sandwich), np.array(naive), n_clusters


def test_sandwich_matches_the_spread_of_estimates_where_the_hessian_is_overconfident():
    """Noise shared within 4 m cubes (3 cm) beside independent noise (1 cm): the Hessian with its
    variance factor is far too small; the cluster-robust covariance matches the Monte-Carlo spread
    (NEES near 6: a 6x6 estimate from ~n_clusters sums inflates it by about G / (G - 7))."""
    xi, sandwich, naive, n_clusters = _wls_trials(0.03, 0.01)
    assert n_clusters >= 60
    nees_sandwich, nees_naive = mean_nees(xi, sandwich), mean_nees(xi, naive)
    assert 4.5 < nees_sandwich < 10.0, nees_sandwich
    assert nees_naive > 30.0, nees_naive
    ratio = spread_ratio(xi, sandwich)
    assert 0.7 < ratio < 1.4, ratio


def test_sandwich_agrees_with_the_scaled_hessian_for_independent_noise():
    xi, sandwich, naive, _ = _wls_trials(0.0, 0.01, trials=150)
    nees_sandwich, nees_naive = mean_nees(xi, sandwich), mean_nees(xi, naive)
    assert 4.5 < nees_naive < 7.5 and 4.5 < nees_sandwich < 8.5, (nees_naive, nees_sandwich)


@pytest.fixture(scope="module")
def scan_pair():
    rng = np.random.default_rng(3)
    world = street(rng)
    T = exp_se3(np.array([0.002, -0.001, 0.02, 0.8, 0.05, 0.01]))  # source into target
    target = world + rng.normal(0, 0.01, world.shape)
    source = (world - T[:3, 3]) @ T[:3, :3] + rng.normal(0, 0.01, world.shape)
    return target, source, T


def test_vgicp_correspondences_rebuild_small_gicps_hessian(scan_pair):
    target, source, T_true = scan_pair
    tgt, _ = small_gicp.preprocess_points(target, downsampling_resolution=0.25, num_threads=1)
    src, _ = small_gicp.preprocess_points(source, downsampling_resolution=0.25, num_threads=1)
    vm = small_gicp.GaussianVoxelMap(1.0)
    vm.insert(tgt)
    res = small_gicp.align(vm, src, init_T_target_source=T_true, max_correspondence_distance=1.0, num_threads=1)
    T = np.asarray(res.T_target_source)
    assert np.linalg.norm(log_se3(np.linalg.inv(T_true) @ T)) < 0.02
    corr = vgicp_correspondences(vm, src, T, 1.0, 1.0)
    assert abs(len(corr.p) - res.num_inliers) <= 0.02 * res.num_inliers
    info = np.linalg.inv(corr.cov_q + T[:3, :3] @ corr.cov_p @ T[:3, :3].T)
    cost, _, H = wls_cost_gradient_hessian(T, corr.p, corr.q, info)
    H_ref = np.asarray(res.H)
    assert np.abs(H - H_ref).max() < 0.03 * np.abs(H_ref).max()
    assert cost == pytest.approx(res.error, rel=0.05)


def test_gicp_correspondences_rebuild_small_gicps_hessian(scan_pair):
    target, source, T_true = scan_pair
    tgt, tree = small_gicp.preprocess_points(target, downsampling_resolution=0.25, num_threads=1)
    src, _ = small_gicp.preprocess_points(source, downsampling_resolution=0.25, num_threads=1)
    res = small_gicp.align(tgt, src, tree, init_T_target_source=T_true, registration_type="GICP",
                           max_correspondence_distance=1.0, num_threads=1)
    T = np.asarray(res.T_target_source)
    corr = gicp_correspondences(tgt, tree, src, T, 1.0)
    assert abs(len(corr.p) - res.num_inliers) <= 0.02 * res.num_inliers
    info = np.linalg.inv(corr.cov_q + T[:3, :3] @ corr.cov_p @ T[:3, :3].T)
    _, _, H = wls_cost_gradient_hessian(T, corr.p, corr.q, info)
    H_ref = np.asarray(res.H)
    assert np.abs(H - H_ref).max() < 0.03 * np.abs(H_ref).max()
    info_cr, n_clusters = cluster_robust_information(T, corr, 12.0, 20)
    assert n_clusters >= 20 and np.linalg.eigvalsh(info_cr)[0] > 0


def test_cluster_robust_information_falls_back_on_too_few_points():
    corr = Correspondences(np.zeros((3, 3)), np.zeros((3, 3)), np.tile(np.eye(3), (3, 1, 1)),
                           np.tile(np.eye(3), (3, 1, 1)))
    assert cluster_robust_information(np.eye(4), corr, 12.0, 20) == (None, 0)


def test_odometry_edges_carry_the_model_and_fall_back_with_too_few_clusters(scan_pair):
    target, source, _ = scan_pair
    scans = [preprocess_scan(target, PreprocessConfig(), index=0), preprocess_scan(source, PreprocessConfig(), index=1)]
    edges = {}
    for name, graph_cfg in (("robust", GraphConfig(registration_covariance="cluster_robust")),
                            ("fallback", GraphConfig(registration_covariance="cluster_robust", min_clusters=100000)),
                            ("scaled", GraphConfig())):
        odo = VgicpOdometry(OdometryConfig(), graph_cfg)
        for s in scans:
            odo.step(s)
        edges[name] = odo.edges[0]
    assert edges["robust"].info["covariance"] == "cluster_robust"
    assert edges["fallback"].info["covariance"] == "scaled_hessian_fallback"
    assert edges["scaled"].info["covariance"] == "scaled_hessian"
    np.testing.assert_allclose(edges["fallback"].information, edges["scaled"].information)
    e = edges["scaled"]
    n = round(e.inlier_ratio * scans[1].cloud.size())
    np.testing.assert_allclose(e.information, scaled_information(e.H_raw, e.error_per_inlier * n, n, 0.1), rtol=1e-6)
    assert np.linalg.eigvalsh(edges["robust"].information)[0] > 0
    assert not np.allclose(edges["robust"].information, e.information, rtol=0.1)


def test_round_summary_counts_the_information_each_accepted_edge_entered_the_graph_with():
    from types import SimpleNamespace

    from gr_graph.odometry import RegistrationEdge
    from gr_graph.round_output import round_summary

    def edge(model: str | None, ok: bool = True, kind: str = "odometry") -> RegistrationEdge:
        info = {} if model is None else {"covariance": model}
        return RegistrationEdge(1, 0, np.eye(4), np.eye(6), np.eye(6), 1.0, 0.1, 3, ok, "", kind, info)

    edges = [edge("cluster_robust"), edge("cluster_robust", kind="loop"), edge("scaled_hessian_fallback"),
             edge(None, ok=False), edge("fixed"), edge("cluster_robust"), edge("scaled_hessian")]
    edges[-2].info["edge_noise"] = "learned"  # the learned edge noise replaced its information
    edges[-1].info["edge_noise"] = "registration (no correspondences)"  # a learned-noise fallback keeps it
    res = SimpleNamespace(poses=np.zeros((6, 4, 4)), edges=edges, loops=[edges[1]], loop_attempts=[], graph_error=(1.0, 0.5),
                          info={"n_flagged_odometry": 1})
    summary = round_summary(0, res, "abc", 100.0)
    assert summary["registration_covariance"] == {"cluster_robust": 2, "scaled_hessian_fallback": 1, "fixed": 1,
                                                  "learned": 1, "scaled_hessian": 1}


def test_cloud_gaussians_come_in_the_clouds_order_even_with_duplicate_points():
    """The fast read (a fine voxel map) must give each point its own covariance in the cloud's
    order; a duplicate point would merge two voxels and shift the rows: then the slow read."""
    from gr_graph.registration_covariance import _cloud

    rng = np.random.default_rng(4)
    pts = street(rng, n=4000)
    for points in (pts, np.insert(pts, 100, pts[50], axis=0)):  # second: point 50 twice
        cloud = small_gicp.PointCloud(points)
        small_gicp.estimate_covariances(cloud, small_gicp.KdTree(cloud), num_neighbors=10)
        p, cov = _cloud(cloud)
        np.testing.assert_array_equal(p, np.asarray(cloud.points())[:, :3])
        np.testing.assert_allclose(cov, np.asarray(cloud.covs())[:, :3, :3], atol=1e-15)


def test_few_clusters_give_no_covariance_and_the_config_refuses_fewer_than_seven():
    rng = np.random.default_rng(5)
    g = rng.normal(size=(40, 6))
    g -= g.mean(0)
    assert cluster_robust_covariance(np.eye(6), g, np.arange(40) % 4, 4) is None  # rank(M) <= 4
    with pytest.raises(ValueError, match="min_clusters"):
        GraphConfig(min_clusters=5)
