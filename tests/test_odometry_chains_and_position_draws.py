"""Beyond the per-edge NEES (gr_graph.noise_consistency): chains of consecutive odometry edges
(chain_nees: the errors they add up to, against the covariance the pose graph's independence
implies) and the spread of one run's mean position NEES under an exact noise model
(position_nees_draws, Monte Carlo)."""

from __future__ import annotations

import json

import gtsam
import numpy as np
import pytest

from gr_graph.config import GraphConfig
from gr_graph.noise_consistency import (
    POSITION_BAND,
    chain_nees,
    main,
    odometry_chains,
    position_nees_draws,
    round_noise_consistency,
)
from gr_graph.pose_graph import build_pose_graph, position_covariance_world


def _exp(xi: np.ndarray) -> np.ndarray:
    return gtsam.Pose3.Expmap(np.asarray(xi, np.float64)).matrix()


def _trajectory(rng: np.random.Generator, K: int) -> np.ndarray:
    """A turning, climbing path of K poses, 1 m a step: (K, 4, 4)."""
    poses = [np.eye(4)]
    for _ in range(K - 1):
        step = np.r_[rng.normal(0, 0.01, 2), rng.normal(0.03, 0.02), 1.0, rng.normal(0, 0.05, 2)]
        poses.append(poses[-1] @ _exp(step))
    return np.array(poses)


def _edges(K: int) -> np.ndarray:
    return np.array([(k + 1, k) for k in range(K - 1)])


def _drive(rng: np.random.Generator, K: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ground truth of :func:`_trajectory`, its odometry edges and their true relative poses."""
    gt = _trajectory(rng, K)
    edges = _edges(K)
    return gt, edges, np.linalg.inv(gt[edges[:, 1]]) @ gt[edges[:, 0]]


def _measured_drive(seed: int, K: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_drive` with each edge measured with independent errors and the exact information."""
    rng = np.random.default_rng(seed)
    gt, edges, T_gt = _drive(rng, K)
    sigma = np.r_[0.002, 0.002, 0.004, 0.02, 0.01, 0.01]
    measured = np.array([T @ _exp(-rng.normal(0.0, sigma)) for T in T_gt])
    return gt, edges, measured, np.tile(np.diag(1 / sigma**2), (K - 1, 1, 1))


def test_odometry_chains_follow_consecutive_edges_and_break_at_gaps():
    edges = np.array([(3, 2), (1, 0), (2, 1), (5, 4), (6, 5), (7, 6), (4, 3), (9, 8), (10, 9)])
    # sorted by target: (1,0) (2,1) (3,2) (4,3) (5,4) (6,5) (7,6) | gap (8 missing as a target) | (9,8) (10,9)
    assert [c.tolist() for c in odometry_chains(edges, 3)] == [[1, 2, 0], [6, 3, 4]]
    assert [c.tolist() for c in odometry_chains(edges, 2)] == [[1, 2], [0, 6], [3, 4], [7, 8]]
    assert len(odometry_chains(edges, 1)) == len(edges)
    assert odometry_chains(edges, 8) == []
    with pytest.raises(ValueError, match="m must be"):
        odometry_chains(edges, 0)


def test_chain_nees_is_zero_for_exact_edges_and_six_for_independent_errors():
    rng = np.random.default_rng(0)
    K = 2001
    gt, edges, T_gt = _drive(rng, K)
    # covariances that differ edge to edge, rotation errors large enough that their lever arm matters
    sigmas = np.exp(rng.uniform(np.log(0.3), np.log(3.0), (K - 1, 1))) * np.r_[0.004, 0.004, 0.008, 0.02, 0.01, 0.01]
    info = np.array([np.diag(1.0 / s**2) for s in sigmas])
    exact = chain_nees(edges, T_gt, info, gt, 10)
    assert exact["n"] == 200 and exact["mean"] == pytest.approx(0.0, abs=1e-12)
    # measurement T̂ with T = T̂ Exp(xi), xi ~ N(0, Sigma): T̂ = T Exp(-xi)
    noisy = np.array([T @ _exp(-rng.normal(0.0, s)) for T, s in zip(T_gt, sigmas)])
    for m in (1, 10, 50):
        out = chain_nees(edges, noisy, info, gt, m)
        assert out["n"] == (K - 1) // m
        # chi2(6) over n chains: std of the mean sqrt(12 / n); 4 of those
        assert out["mean"] == pytest.approx(6.0, abs=4 * np.sqrt(12 / out["n"]) + 0.1), m
        assert np.allclose(out["edge_z2_mean"], 1.0, atol=0.15)
    # the same errors without carrying each edge's covariance into the chain's last frame (Ad left out)
    # would misstate the translation: the lever arm of the rotation errors is what chain_nees adds
    chains = odometry_chains(edges, 50)
    naive = []
    for c in chains:
        measured = np.linalg.multi_dot(noisy[c])
        true = np.linalg.multi_dot(T_gt[c])
        xi = gtsam.Pose3.Logmap(gtsam.Pose3(measured).between(gtsam.Pose3(true)))
        cov = sum(np.diag(sigmas[i] ** 2) for i in c)
        naive.append(xi @ np.linalg.solve(cov, xi))
    assert np.mean(naive) > 2 * 6.0


def test_chain_nees_sees_errors_that_cancel_along_the_chain():
    """Each scan's own error enters the edges on both of its sides: the edge errors
    ``s_{k+1} - s_k`` (translation only, a straight path, so the chain adds them exactly) have
    the right per-edge variance, but a chain of m of them holds only its two ends: NEES 3 / m
    (three translation axes) where independent errors would give 6."""
    rng = np.random.default_rng(1)
    K = 3001
    gt = np.array([np.eye(4) for _ in range(K)])
    gt[:, 0, 3] = np.arange(K, dtype=float)
    edges = _edges(K)
    T_gt = np.linalg.inv(gt[edges[:, 1]]) @ gt[edges[:, 0]]
    s = rng.normal(0.0, 0.01, (K, 3))  # each scan's own translation error
    xi = s[edges[:, 0]] - s[edges[:, 1]]
    measured = T_gt.copy()
    measured[:, :3, 3] -= xi  # T = T̂ Exp(xi) with no rotation: t = t̂ + xi
    var = np.r_[1e-6, 1e-6, 1e-6, np.full(3, 2 * 0.01**2)]  # the per-edge variance of s_{k+1} - s_k
    info = np.tile(np.diag(1.0 / var), (K - 1, 1, 1))
    one = chain_nees(edges, measured, info, gt, 1)
    assert one["mean"] == pytest.approx(3.0, rel=0.1)  # every edge alone is consistent
    assert np.allclose(one["z2_mean"][3:], 1.0, atol=0.1)
    ten = chain_nees(edges, measured, info, gt, 10)
    assert ten["mean"] == pytest.approx(0.3, rel=0.25)
    assert np.allclose(ten["edge_z2_mean"][3:], 1.0, atol=0.1)
    assert np.allclose(ten["z2_mean"][3:], 0.1, rtol=0.3)


def test_round_noise_consistency_reports_odometry_chains(tmp_path):
    rng = np.random.default_rng(2)
    K = 241
    gt = _trajectory(rng, K)
    edges = np.r_[_edges(K), [(200, 10)]]
    T_gt = np.linalg.inv(gt[edges[:, 1]]) @ gt[edges[:, 0]]
    sigma = np.r_[0.002, 0.002, 0.004, 0.02, 0.01, 0.01]
    measured = np.array([T @ _exp(-rng.normal(0.0, sigma)) for T in T_gt])
    rd = tmp_path / "round_0"
    rd.mkdir()
    ok = np.ones(len(edges), bool)
    ok[105] = False  # a flagged registration breaks a chain
    np.savez(rd / "marginals.npz", poses=gt, gt_poses=gt, covariance=np.tile(np.eye(6), (K, 1, 1)),
             position_cov_world=np.tile(np.eye(3), (K, 1, 1)), edges=edges, edge_T=measured,
             edge_information=np.tile(np.diag(1 / sigma**2), (len(edges), 1, 1)),
             edge_kind=np.r_[np.zeros(K - 1, np.uint8), 1], edge_ok=ok)
    chains = round_noise_consistency(rd)["edges"]["odometry"]["chains"]
    assert set(chains) == {"10", "100"}
    assert chains["10"]["n"] == 10 + 13 and chains["100"]["n"] == 1 + 1  # 105 edges, then 134
    keep = ok & (np.arange(len(edges)) < K - 1)
    assert chains["10"] == chain_nees(edges[keep], measured[keep], np.tile(np.diag(1 / sigma**2), (keep.sum(), 1, 1)),
                                      gt, 10)


def _loop_round(tmp_path, rng: np.random.Generator, cov_factor: float = 1.0, with_gt: bool = True):
    """A round folder: two laps of a circle (60 poses, 10 loops), measurements drawn from the
    informations the graph is given, solved with marginals; the stored position covariances
    ``cov_factor`` x the graph's."""
    K = 60
    t = np.linspace(0, 4 * np.pi, K)
    gt = np.stack([_exp(np.array([0, 0, ti, 0, 0, 0])) for ti in t])
    gt[:, :3, 3] = np.column_stack([20 * np.cos(t), 20 * np.sin(t), 0.1 * t])
    pairs = [(k + 1, k) for k in range(K - 1)] + [(int(i), int(i) - K // 2) for i in
                                                  rng.choice(np.arange(K // 2, K), 10, replace=False)]
    info = np.diag([4e4, 4e4, 1e4, 400, 400, 100.0])
    chol = np.linalg.cholesky(np.linalg.inv(info))
    edge_T = np.array([np.linalg.inv(gt[l]) @ gt[k] @ _exp(-chol @ rng.normal(size=6)) for k, l in pairs])
    cfg = GraphConfig(loop_kernel="none")
    graph = build_pose_graph(cfg, gt, ((k, l, T, info, k != l + 1) for (k, l), T in zip(pairs, edge_T)))
    res = graph.optimize(marginals=True)
    rd = tmp_path / "run" / "round_0"
    rd.mkdir(parents=True)
    arrays = dict(poses=res.poses, covariance=res.covariances, edges=np.array(pairs), edge_T=edge_T,
                  position_cov_world=cov_factor * position_covariance_world(res.poses, res.covariances),
                  edge_information=np.tile(info, (len(pairs), 1, 1)),
                  edge_kind=np.array([k != l + 1 for k, l in pairs], np.uint8), edge_ok=np.ones(len(pairs), bool))
    if with_gt:
        arrays["gt_poses"] = gt
    np.savez(rd / "marginals.npz", **arrays)
    return rd, cfg


def test_position_nees_draws_scatter_around_three_under_an_exact_model(tmp_path):
    """Measurements drawn from the informations the graph uses: the draws' mean position NEES is
    3 (horizontal 2, vertical 1; 200 draws, each a mean over 59 correlated poses), while single
    runs scatter widely; stored covariances 4x too large read 4x lower."""
    rd, cfg = _loop_round(tmp_path, np.random.default_rng(4))
    out = position_nees_draws(rd, cfg, n_draws=200, seed=1)
    assert out["n_draws"] == 200 and out["seed"] == 1
    assert out["position"]["mean"] == pytest.approx(3.0, abs=0.35)
    assert out["horizontal"]["mean"] == pytest.approx(2.0, abs=0.3)
    assert out["vertical"]["mean"] == pytest.approx(1.0, abs=0.2)
    draws = np.array(out["position"]["draws"])
    assert len(draws) == 200 and draws.mean() == pytest.approx(out["position"]["mean"])
    q = out["position"]["percentiles"]
    assert [q["5"], q["50"], q["95"]] == pytest.approx(np.percentile(draws, [5, 50, 95]))
    assert q["95"] - q["5"] > 1.0  # one run's mean is no precise figure
    lo, hi = POSITION_BAND
    assert out["position"]["frac_in_band"] == pytest.approx(np.mean((draws >= lo) & (draws <= hi)))
    # the round's own figure against its ground truth, placed among the draws
    observed = round_noise_consistency(rd)["position"]["mean"]
    assert out["position"]["observed"] == pytest.approx(observed)
    assert out["position"]["observed_percentile"] == pytest.approx(100 * np.mean(draws < observed))
    again = position_nees_draws(rd, cfg, n_draws=200, seed=1)
    assert again == out
    assert position_nees_draws(rd, cfg, n_draws=200, seed=2)["position"]["mean"] != out["position"]["mean"]
    # the same edges, the position marginals stored 4x too large: the draws are scored against them
    wide, cfg = _loop_round(tmp_path / "wide", np.random.default_rng(4), cov_factor=4.0)
    assert position_nees_draws(wide, cfg, n_draws=200, seed=1)["position"]["mean"] == pytest.approx(
        out["position"]["mean"] / 4.0, rel=1e-6)


def test_position_nees_draws_floor_the_informations_and_leave_out_poses_as_the_nees_does(tmp_path):
    """An edge without information along one axis (the graph floors it; without the floor it could
    not be sampled) and poses whose marginals failed (NaN) or were anchored apart: the draws stay
    finite and the observed figure is round_noise_consistency's."""
    rd, cfg = _loop_round(tmp_path, np.random.default_rng(8))
    with np.load(rd / "marginals.npz") as z:
        arrays = {k: np.array(z[k]) for k in z.files}
    arrays["edge_information"][5] = np.diag([4e4, 4e4, 1e4, 0.0, 400, 100.0])  # x unconstrained
    arrays["edge_ok"][7] = False  # a flagged edge stays in the graph, as in a run
    arrays["position_cov_world"][[4, 9]] = np.nan
    np.savez(rd / "marginals.npz", **arrays)
    (rd / "round.json").write_text(json.dumps({"marginals": {"status": "anchored",
                                                              "unanchored_components": [[40, 44, 5]]}}))
    out = position_nees_draws(rd, cfg, n_draws=10, seed=0)
    assert np.isfinite(out["position"]["draws"]).all()
    reference = round_noise_consistency(rd)["position"]
    assert reference["n_left_out"] == 7
    assert out["position"]["observed"] == pytest.approx(reference["mean"])


def test_chain_nees_floors_an_unconstrained_axis_as_the_graph_does():
    gt, edges, measured, info = _measured_drive(9, 41)
    info[3, 3, 3] = 0.0
    floored = info.copy()
    floored[3, 3, 3] = 1e-2  # GraphConfig's min_information_eigenvalue
    out = chain_nees(edges, measured, info, gt, 10)
    assert np.isfinite(out["mean"]) and np.isfinite(out["z2_mean"]).all() and np.isfinite(out["edge_z2_mean"]).all()
    assert out == chain_nees(edges, measured, floored, gt, 10)
    assert chain_nees(edges, measured, info, gt, 10, min_eigenvalue=1.0) != out


def test_round_noise_consistency_floors_the_chains_at_the_runs_own_eigenvalue_floor(tmp_path):
    """The chains floor each edge's information where the run's graph did: its config.yaml's
    graph.min_information_eigenvalue, the default without one; an explicit floor wins; a broken value
    in the config is an error naming the file."""
    K = 61
    gt, edges, measured, info = _measured_drive(4, K)
    info[:, 3, 3] = 0.0  # roll unconstrained: the floor decides it
    run = tmp_path / "run"
    rd = run / "round_0"
    rd.mkdir(parents=True)
    np.savez(rd / "marginals.npz", poses=gt, gt_poses=gt, covariance=np.tile(np.eye(6), (K, 1, 1)),
             position_cov_world=np.tile(np.eye(3), (K, 1, 1)), edges=edges, edge_T=measured,
             edge_information=info, edge_kind=np.zeros(K - 1, np.uint8), edge_ok=np.ones(K - 1, bool))
    default = round_noise_consistency(rd)["edges"]["odometry"]
    assert default["chain_min_eigenvalue"] == GraphConfig().min_information_eigenvalue
    assert default["chains"]["10"] == chain_nees(edges, measured, info, gt, 10)
    (run / "config.yaml").write_text("graph:\n  min_information_eigenvalue: 5.0\n")
    own = round_noise_consistency(rd)["edges"]["odometry"]
    assert own["chain_min_eigenvalue"] == 5.0
    assert own["chains"]["10"] == chain_nees(edges, measured, info, gt, 10, min_eigenvalue=5.0)
    assert own["chains"]["10"]["mean"] != default["chains"]["10"]["mean"]
    assert round_noise_consistency(rd, min_eigenvalue=1e-2)["edges"]["odometry"]["chains"] == default["chains"]
    (run / "config.yaml").write_text("graph:\n  min_information_eigenvalue: 5e0\n")  # YAML's string '5e0'
    assert round_noise_consistency(rd)["edges"]["odometry"]["chain_min_eigenvalue"] == 5.0
    (run / "config.yaml").write_text("graph:\n  min_information_eigenvalue: -1\n")
    with pytest.raises(ValueError, match="config.yaml.*min_information_eigenvalue"):
        round_noise_consistency(rd)


def test_position_nees_draws_without_ground_truth_and_bad_input(tmp_path, capsys):
    rd, cfg = _loop_round(tmp_path, np.random.default_rng(5), with_gt=False)
    out = position_nees_draws(rd, cfg, n_draws=5)
    assert out["position"]["observed"] is None and out["position"]["observed_percentile"] is None
    with pytest.raises(ValueError, match="n_draws"):
        position_nees_draws(rd, cfg, n_draws=0)
    with pytest.raises(FileNotFoundError, match="marginals.npz"):
        position_nees_draws(tmp_path / "nowhere", cfg)
    with np.load(rd / "marginals.npz") as z:
        failed = {k: np.array(z[k]) for k in z.files}
    failed["position_cov_world"][:] = np.nan  # every marginal failed: nothing to score
    np.savez(rd / "marginals.npz", **failed)
    with pytest.raises(ValueError, match="no pose besides the first"):
        position_nees_draws(rd, cfg, n_draws=2)
    # the command line: a run with ground truth and its config.yaml
    rd, cfg = _loop_round(tmp_path / "cli", np.random.default_rng(6))
    (rd.parent / "config.yaml").write_text("graph: {loop_kernel: none}\n")
    assert main([str(rd.parent), "--draws", "20"]) == 0
    text = capsys.readouterr().out
    assert "round 0: mean position NEES if the edges' information were exact (20 draws)" in text
    assert f"in {POSITION_BAND[0]:g}-{POSITION_BAND[1]:g} in" in text and "above" in text
    (rd.parent / "config.yaml").unlink()
    assert main([str(rd.parent), "--draws", "20"]) == 2
    assert "config.yaml" in capsys.readouterr().err


def test_position_nees_study_reports_chains_shuffled_chains_and_draws(tmp_path, capsys, monkeypatch):
    from benchmark_support import benchmark_script

    study = benchmark_script("position_nees_study")
    rd, cfg = _loop_round(tmp_path, np.random.default_rng(7))
    (rd.parent / "config.yaml").write_text("graph: {loop_kernel: none}\n")
    assert study.main(["two-laps", f"{rd.parent}@0", "--draws", "8", "--seed", "3"]) == 0
    text = capsys.readouterr().out
    row = next(line for line in text.splitlines() if line.startswith("| two-laps | ") and "%" in line)
    draws = position_nees_draws(rd, cfg, 8, 3)
    assert f"{draws['position']['observed_percentile']:.0f} % |" in row
    # the shuffled column: every edge of the ordered chains once, in the seed's order (10 a chain here)
    monkeypatch.setattr(study, "LONG", 10)
    with np.load(rd / "marginals.npz") as z:
        odo = z["edge_kind"] == 0
        edges = z["edges"][odo]
    ordered = odometry_chains(edges, 10)
    shuffled = study.shuffled_chains(ordered, 3)
    assert [len(c) for c in shuffled] == [10] * 5
    assert sorted(np.concatenate(shuffled).tolist()) == sorted(np.concatenate(ordered).tolist())
    assert [c.tolist() for c in shuffled] != [c.tolist() for c in ordered]
    assert study.shuffled_chains([], 3) == []
    r = study.study_round(rd, 3, cfg, 0)
    assert "position_draws" not in r and r["chains_shuffled"]["10"]["n"] == 5


def test_position_nees_figure_draws_the_rounds_with_draws(tmp_path):
    from benchmark_support import benchmark_script

    figure = benchmark_script("position_nees_figure")
    rng = np.random.default_rng(10)
    runs = [{"label": f"r{i}", "position_draws": {"position": {"draws": rng.chisquare(3, 50).tolist(),
                                                               "observed": 1.0 + i}}} for i in range(3)]
    runs.append({"label": "no-draws"})
    (tmp_path / "study.json").write_text(json.dumps({"runs": runs}))
    out = tmp_path / "fig" / "draws.png"
    assert figure.main([str(tmp_path / "study.json"), str(out)]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 5000
    (tmp_path / "none.json").write_text(json.dumps({"runs": [{"label": "no-draws"}]}))
    with pytest.raises(SystemExit):
        figure.main([str(tmp_path / "none.json"), str(tmp_path / "none.png")])
    assert not (tmp_path / "none.png").exists()
