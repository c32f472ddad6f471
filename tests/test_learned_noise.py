"""Learned edge noise (``training.edge_noise: learned``): odometry information = H(C) in rounds >= 1."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from estimate_support import mean_nees, spread_ratio
from factors.wls import solve_wls
from gr_graph.config import ConfigError, GraphConfig, load_config
from gr_graph.edge_noise import LearnedEdgeNoise, learned_information
from gr_graph.odometry import RegistrationEdge
from gr_graph.pose_graph import edge_noise_model


def _pose(rng: np.random.Generator) -> np.ndarray:
    w = rng.normal(0, 0.05, 3)
    th = np.linalg.norm(w)
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]) / th
    T = np.eye(4)
    T[:3, :3] = np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K
    T[:3, 3] = rng.normal(0, 0.5, 3)
    return T


def _spd(rng: np.random.Generator, n: int) -> np.ndarray:
    A = rng.normal(0, 0.1, (n, 3, 3))
    return A @ A.transpose(0, 2, 1) + 1e-3 * np.eye(3)


def _synthetic_edge(seed: int = 0, n: int = 2000):
    """Source p, target = shuffled T p plus 500 unmatched far points, covariances of the target."""
    rng = np.random.default_rng(seed)
    T = _pose(rng)
    p = rng.uniform([-30, -30, -2], [30, 30, 6], (n, 3))
    q = p @ T[:3, :3].T + T[:3, 3]
    extra = rng.uniform([100, 100, 0], [150, 150, 5], (500, 3))
    perm = rng.permutation(n + 500)
    target = np.vstack([q, extra])[perm]
    C = _spd(rng, n + 500)
    inv = np.argsort(perm)  # target[inv[i]] == q[i] for i < n
    return T, p, q, target, C, C[inv[:n]]


def _edge(T: np.ndarray, info: np.ndarray, ok: bool = True) -> RegistrationEdge:
    return RegistrationEdge(source=1, target=0, T=T, H_raw=np.eye(6), information=info.copy(), inlier_ratio=1.0,
                            error_per_inlier=0.0, iterations=1, ok=ok)


def test_learned_information_equals_wls_hessian_and_gtsam_information():
    T, p, q, target, C, Cq = _synthetic_edge()
    ref = solve_wls(p, q, Cq, T0=T)  # independent: converges to T (exact correspondences)
    np.testing.assert_allclose(ref.T, T, atol=1e-9)
    res = learned_information(T, p, target, C, max_distance=0.5, min_eigenvalue=None)
    assert res.reason == "" and res.n_correspondences == len(p) and not res.floored
    np.testing.assert_allclose(res.hessian, ref.hessian, rtol=1e-9, atol=1e-9 * np.abs(ref.hessian).max())
    np.testing.assert_allclose(res.information, ref.hessian, rtol=1e-9, atol=1e-9 * np.abs(ref.hessian).max())
    # with a floor between the eigenvalues: the floored H, and gtsam's model carries exactly it
    ev = np.linalg.eigvalsh(ref.hessian)
    floor = float(np.sqrt(ev[1] * ev[2]))
    res = learned_information(T, p, target, C, max_distance=0.5, min_eigenvalue=floor)
    assert res.floored
    w, V = np.linalg.eigh(ref.hessian)
    expect = (V * np.maximum(w, floor)) @ V.T
    np.testing.assert_allclose(res.information, expect, rtol=1e-8, atol=1e-8 * ev[-1])
    model = edge_noise_model(res.information, GraphConfig(min_information_eigenvalue=floor))
    np.testing.assert_allclose(model.information(), expect, rtol=1e-7, atol=1e-7 * ev[-1])


def test_edge_noise_apply_sets_information_and_counts():
    T, p, q, target, C, Cq = _synthetic_edge(seed=1)
    preds = {5: (p, np.tile(np.eye(3), (len(p), 1, 1))), 4: (target, C)}
    cfg = load_config(overrides={"odometry": {"corr_max_distance": 0.5}})
    en = LearnedEdgeNoise(preds.get, cfg)
    e = en.apply(_edge(T, np.eye(6)), 5, 4)
    np.testing.assert_allclose(e.information, solve_wls(p, q, Cq, T0=T).hessian, rtol=1e-8)
    assert e.info["edge_noise"] == "learned"
    e2 = en.apply(_edge(T, 7 * np.eye(6), ok=False), 5, 4)  # flagged registration: fallback kept
    e3 = en.apply(_edge(T, 7 * np.eye(6)), 6, 5)  # frame 6 has no covariances
    far = T.copy()
    far[:3, 3] += 50.0
    e4 = en.apply(_edge(far, 7 * np.eye(6)), 5, 4)  # no pair within 0.5 m
    for x in (e2, e3, e4):
        np.testing.assert_array_equal(x.information, 7 * np.eye(6))
    assert en.summary() == {"mode": "learned", "n_learned": 1, "n_floored": 0, "n_fallback": 3,
                            "fallbacks": {"registration_failed": 1, "no_covariances": 1, "few_correspondences": 1},
                            "loop": {"n_learned": 0, "n_floored": 0, "n_fallback": 0, "fallbacks": {}},
                            "edges": "all", "calibration": {"method": "none"}}


def test_planar_scene_is_degenerate_fallback_logged_and_counted(caplog):
    rng = np.random.default_rng(2)
    p = np.column_stack([rng.uniform(-20, 20, (3000, 2)), np.zeros(3000)])  # one plane, z = 0
    T = np.eye(4)
    T[:3, 3] = [0.3, 0.0, 0.0]
    q = p @ T[:3, :3].T + T[:3, 3]
    C_plane = np.diag([1.0, 1.0, 1e-6])  # plane-shaped: nothing constrains sliding along the plane
    preds = {1: (p, np.tile(C_plane, (len(p), 1, 1))), 0: (q, np.tile(C_plane, (len(q), 1, 1)))}
    en = LearnedEdgeNoise(preds.get, load_config())
    with caplog.at_level(logging.WARNING):
        e = en.apply(_edge(T, 3 * np.eye(6)), 1, 0)
    np.testing.assert_array_equal(e.information, 3 * np.eye(6))
    assert en.summary()["fallbacks"] == {"degenerate": 1} and en.n_learned == 0
    assert "degenerate" in caplog.text and "edge (1, 0)" in caplog.text
    # the raw H(C) was computed and is rank-deficient along x, y, yaw (relative to its largest eigenvalue)
    ev = np.linalg.eigvalsh(en.hessians[(1, 0)])
    assert ev[2] < 1e-4 * ev[-1]
    # an isotropic-covariance scene far from the origin is well-posed but weak: the floor is counted
    cfg = load_config(overrides={"graph": {"min_information_eigenvalue": 1e6}})
    big = 0.5 * np.eye(3)
    pts = rng.uniform(-20, 20, (500, 3))
    en2 = LearnedEdgeNoise({1: (pts, np.tile(big, (500, 1, 1))), 0: (pts, np.tile(big, (500, 1, 1)))}.get, cfg)
    with caplog.at_level(logging.WARNING):
        e = en2.apply(_edge(np.eye(4), np.eye(6)), 1, 0)
    assert en2.summary()["n_learned"] == 1 and en2.summary()["n_floored"] == 1
    assert np.linalg.eigvalsh(e.information)[0] == pytest.approx(1e6, rel=1e-9)


def test_densified_sequence_keeps_its_predictions():
    from gr_graph.config import PreprocessConfig, TrainingConfig
    from gr_graph.densify import densified_sequence
    from gr_graph.preprocess import preprocess_scan
    from test_learning_rounds import PlaneScenes, plane_predictor

    view = densified_sequence(PlaneScenes(n=4), plane_predictor, TrainingConfig(tau_ani=0.9, samples_per_point=2),
                              preprocess=PreprocessConfig(), keep_predictions=2)
    for i in range(4):
        view[i]
    assert view.predicted(0) is None and view.predicted(1) is None  # evicted
    pts, C = view.predicted(3)
    np.testing.assert_array_equal(C, plane_predictor(pts))
    np.testing.assert_array_equal(pts, preprocess_scan(PlaneScenes(n=4)[3].points, PreprocessConfig(), index=3).points)


# ----------------------------------------------------------------------------- end to end


@pytest.mark.slow
def test_round1_uses_learned_noise_end_to_end(learning_run):
    from scipy.spatial import cKDTree

    from gr_graph.pipeline import SlamPipeline
    from gr_graph.preprocess import preprocess_scan
    from training.predict import predict_covariances

    out = learning_run[0]  # the short --rounds 1 run shared with tests/test_learning_rounds.py
    r1 = json.loads((out / "round_1" / "round.json").read_text())
    en = r1["edge_noise"]
    assert en["mode"] == "learned" and en["n_learned"] > 0
    assert en["n_learned"] + en["n_fallback"] == r1["n_odometry_edges"]
    assert en["n_fallback"] == sum(en["fallbacks"].values())
    r0 = json.loads((out / "round_0" / "round.json").read_text())
    assert "edge_noise" not in r0  # round 0 unchanged

    cfg = load_config(out / "config.yaml")
    seq = SlamPipeline(cfg).sequence
    with np.load(out / "round_1" / "marginals.npz") as z:
        edges, kind, info, odom = z["edges"], z["edge_kind"], z["edge_information"], z["odometry_poses"]
    # recompute H(C) of odometry edge (k, l) = (12, 11) independently: network, NN, explicit Jacobians
    k, l = 12, 11
    row = int(np.flatnonzero((edges[:, 0] == k) & (edges[:, 1] == l) & (kind == 0))[0])
    T = np.linalg.inv(odom[l]) @ odom[k]
    model = out / "round_1" / "training" / "model.pt"
    sk = preprocess_scan(seq[k].points, cfg.preprocess, index=k).points
    sl = preprocess_scan(seq[l].points, cfg.preprocess, index=l).points
    Cl = predict_covariances(model, sl, device="cpu", seed=cfg.training.seed)
    pm = sk @ T[:3, :3].T + T[:3, 3]
    d, j = cKDTree(sl).query(pm, k=1, distance_upper_bound=cfg.odometry.corr_max_distance)
    ok = np.isfinite(d)
    p, Lam = sk[ok], np.linalg.inv(2.0 * Cl[j[ok]])
    H = np.zeros((6, 6))
    R = T[:3, :3]
    for pi, Li in zip(p, Lam):
        px = np.array([[0, -pi[2], pi[1]], [pi[2], 0, -pi[0]], [-pi[1], pi[0], 0]])
        J = -R @ np.hstack([-px, np.eye(3)])  # d(q - T Exp(xi) p)/d xi, xi = [omega, v]
        H += J.T @ Li @ J
    w, V = np.linalg.eigh(H)
    expect = (V * np.maximum(w, cfg.graph.min_information_eigenvalue)) @ V.T
    expect *= en["calibration"].get("scale", 1.0)  # the graph's variance factor (1 without loops)
    np.testing.assert_allclose(info[row], expect, rtol=1e-6, atol=1e-6 * w[-1])
    with np.load(out / "round_0" / "marginals.npz") as z0:  # round 0 (registration information) differs
        row0 = int(np.flatnonzero((z0["edges"][:, 0] == k) & (z0["edges"][:, 1] == l) & (z0["edge_kind"] == 0))[0])
        assert not np.allclose(info[row], z0["edge_information"][row0], rtol=1e-2)


def test_the_calibration_scales_only_the_learned_information():
    """Registered edges that kept their registration information are calibrated already: the graph's
    variance factor of the raw H(C) leaves them as they are."""
    from gr_graph.frame_loop import scale_learned_information
    from gr_graph.odometry import RegistrationEdge

    def edge(noise: str | None, ok: bool = True) -> RegistrationEdge:
        info = {} if noise is None else {"edge_noise": noise}
        return RegistrationEdge(1, 0, np.eye(4), np.eye(6), 4.0 * np.eye(6), 0.9, 0.01, 5, ok, info=info)

    edges = [edge("learned"), edge("registration (few_correspondences)"), edge("registration (registration_failed)",
                                                                               ok=False), edge(None), edge("learned")]
    assert scale_learned_information(edges, 0.01) == 2
    # a failed registration's fallback (a guess) is scaled with the learned edges: it stays weak beside them
    np.testing.assert_allclose([e.information[0, 0] for e in edges], [0.04, 4.0, 0.04, 4.0, 0.04])


def _clustered_trials(trials: int = 120, shared_sigma: float = 0.02, point_sigma: float = 0.01, seed: int = 4):
    """Monte-Carlo draws of a learned-weights WLS pose: noise shared within 6 m cubes beside
    independent noise; the weights Lambda = (2 C)^-1 of random learned covariances.

    Returns the estimates' errors ``xi`` (T_true^-1 T_est), the sandwich covariances computed from a
    start pose off the optimum (as a VGICP T̂ is), the same at the optimum, and the informations
    H(C) / s² (s² the residuals' variance factor)."""
    from factors.se3 import exp_se3, log_se3
    from factors.wls import residual_information
    from gr_graph.edge_noise import learned_sandwich_information
    from gr_graph.registration_covariance import cube_labels

    rng = np.random.default_rng(seed)
    n = 2500
    p = rng.uniform([-30, -30, -2], [30, 30, 6], (n, 3))
    labels, n_clusters = cube_labels(p, 6.0)
    T_true = exp_se3(np.array([0.01, -0.02, 0.05, 0.8, 0.1, -0.05]))
    C = _spd(rng, n) + 0.02 * np.eye(3)
    info = residual_information(C)
    xi, from_start, at_optimum, hessians = [], [], [], []
    for _ in range(trials):
        noise = rng.normal(0, shared_sigma, (n_clusters, 3))[labels] + rng.normal(0, point_sigma, (n, 3))
        q = p @ T_true[:3, :3].T + T_true[:3, 3] + noise
        est = solve_wls(p, q, C, T0=T_true)
        start = est.T @ exp_se3(rng.normal(0, [2e-3, 2e-3, 2e-3, 0.02, 0.02, 0.02]))
        from_start.append(np.linalg.inv(learned_sandwich_information(start, p, q, info, 6.0, 20)))
        at_optimum.append(np.linalg.inv(learned_sandwich_information(est.T, p, q, info, 6.0, 20)))
        hessians.append(est.hessian / (2 * est.cost / (3 * n - 6)))  # H(C) with its variance factor
        xi.append(log_se3(np.linalg.inv(T_true) @ est.T))
    return np.array(xi), np.array(from_start), np.array(at_optimum), np.array(hessians), n_clusters


def test_learned_sandwich_matches_the_spread_of_the_learned_estimate():
    """Against Monte Carlo: with noise shared within cubes, H(C) scaled by its variance factor is
    over-confident (its NEES far above 6), the sandwich's covariance matches the spread of the
    learned-weights estimate; computed from a start off the optimum (one Gauss-Newton step, the
    same pairs) it equals the one at the optimum."""
    xi, from_start, at_optimum, hessians, n_clusters = _clustered_trials()
    assert n_clusters >= 60
    np.testing.assert_allclose(from_start, at_optimum, rtol=1e-2, atol=1e-2 * np.abs(at_optimum).max())  # 1.5-50x off without the step
    nees_sandwich, nees_hessian = mean_nees(xi, from_start), mean_nees(xi, np.linalg.inv(hessians))
    assert 4.5 < nees_sandwich < 10.0, nees_sandwich
    assert nees_hessian > 30.0, nees_hessian
    assert 0.7 < spread_ratio(xi, from_start) < 1.4


def test_learned_information_cluster_robust_and_its_fallback():
    from factors.se3 import exp_se3
    from factors.wls import residual_information
    from gr_graph.edge_noise import learned_sandwich_information

    T, p, q, target, C, Cq = _synthetic_edge(seed=5)
    rng = np.random.default_rng(5)
    noisy = target + rng.normal(0, 0.02, target.shape)  # residuals for the sandwich to measure
    start = T @ exp_se3(np.array([1e-3, 0, 0, 0.01, 0, 0]))
    res = learned_information(start, p, noisy, C, max_distance=0.5, min_eigenvalue=None, covariance="cluster_robust",
                              cluster_size=8.0, min_clusters=20)
    assert res.reason == "" and res.model == "cluster_robust"
    hessian = learned_information(start, p, noisy, C, max_distance=0.5, min_eigenvalue=None)
    assert hessian.model == "hessian"
    np.testing.assert_allclose(res.hessian, hessian.hessian)  # the same pairs and weights
    assert not np.allclose(res.information, hessian.information, rtol=0.1)
    # the same pairs as learned_information's own search find (the pairing is checked here; the math by the
    # Monte-Carlo test above)
    from gr_graph.correspondences import nearest_correspondences, target_tree
    pairs = nearest_correspondences(p, target_tree(noisy, 1), start, 0.5, 1)
    expect = learned_sandwich_information(start, p[pairs[:, 0]], noisy[pairs[:, 1]],
                                          residual_information(C[pairs[:, 1]]), 8.0, 20)
    np.testing.assert_allclose(res.information, expect, rtol=1e-9)
    # one cube holds every pair: too few clusters, H(C) is kept and said so
    few = learned_information(start, p, noisy, C, max_distance=0.5, min_eigenvalue=None, covariance="cluster_robust",
                              cluster_size=1000.0, min_clusters=20)
    assert few.model == "hessian_fallback"
    np.testing.assert_allclose(few.information, hessian.information)
    with pytest.raises(ValueError, match="cluster_robust"):
        learned_information(start, p, noisy, C, max_distance=0.5, covariance="sandwich")


def test_the_offset_term_is_the_squared_distance_of_the_pose_from_the_learned_minimum():
    """cluster_robust_offset adds ``diag(s^2)``: against the learned cost's minimum found independently
    (factors.wls.solve_wls, iterated to convergence), ``s`` is log(T̂^-1 T_min) to first order."""
    from factors.se3 import exp_se3, log_se3
    from factors.wls import residual_information
    from gr_graph.edge_noise import learned_sandwich_information

    T, p, q, target, C, Cq = _synthetic_edge(seed=7)
    rng = np.random.default_rng(7)
    noisy_q = q + rng.normal(0, 0.02, q.shape)
    info = residual_information(Cq)
    T_min = solve_wls(p, noisy_q, Cq, T0=T).T
    start = T_min @ exp_se3(np.array([2e-3, -1e-3, 1.5e-3, 0.03, -0.02, 0.01]))
    without = np.linalg.inv(learned_sandwich_information(start, p, noisy_q, info, 8.0, 20))
    with_offset = np.linalg.inv(learned_sandwich_information(start, p, noisy_q, info, 8.0, 20, include_offset=True))
    s = log_se3(np.linalg.inv(start) @ T_min)
    np.testing.assert_allclose(with_offset - without, np.diag(s * s), rtol=0.02, atol=0.02 * np.abs(s).max() ** 2)
    assert np.abs(s).max() > 0.009  # the term is not negligible here


def test_learned_covariance_names_are_the_config_options_values():
    from gr_graph.edge_noise import LEARNED_COVARIANCES

    assert LEARNED_COVARIANCES == ("hessian", "cluster_robust", "cluster_robust_offset")
    for name in LEARNED_COVARIANCES:  # each a value the configuration accepts
        assert load_config(overrides={"training": {"learned_noise_covariance": name}}).training.learned_noise_covariance == name
    with pytest.raises(ConfigError, match="learned_noise_covariance"):
        load_config(overrides={"training": {"learned_noise_covariance": "sandwich"}})


def test_edge_noise_counts_what_each_learned_edge_is_made_of():
    T, p, q, target, C, Cq = _synthetic_edge(seed=6)
    rng = np.random.default_rng(6)
    noisy = target + rng.normal(0, 0.02, target.shape)
    preds = {5: (p, np.tile(np.eye(3), (len(p), 1, 1))), 4: (noisy, C)}
    cfg = load_config(overrides={"odometry": {"corr_max_distance": 0.5},
                                 "training": {"learned_noise_covariance": "cluster_robust"},
                                 "graph": {"cluster_size": 8.0}})
    en = LearnedEdgeNoise(preds.get, cfg)
    en.apply(_edge(T, np.eye(6)), 5, 4)
    loop = _edge(T, np.eye(6))
    loop.kind = "loop"
    en.apply(loop, 5, 4)
    few = load_config(overrides={"odometry": {"corr_max_distance": 0.5},
                                 "training": {"learned_noise_covariance": "cluster_robust"},
                                 "graph": {"cluster_size": 1000.0}})
    en_few = LearnedEdgeNoise(preds.get, few)
    en_few.apply(_edge(T, np.eye(6)), 5, 4)
    s, s_few = en.summary(), en_few.summary()
    assert s["models"] == {"cluster_robust": 1} and s["loop"]["models"] == {"cluster_robust": 1}
    assert s_few["models"] == {"hessian_fallback": 1} and s_few["n_learned"] == 1
    # the default (H(C)) keeps the summary of runs made before the option
    assert "models" not in LearnedEdgeNoise(preds.get, load_config()).summary()

