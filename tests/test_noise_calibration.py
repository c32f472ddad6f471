"""One scale for every edge (gr_graph.noise_calibration), NEES against ground truth
(gr_graph.noise_consistency), learned information on loop edges (gr_graph.edge_noise)."""

from __future__ import annotations

import json

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import X

from gr_graph.config import GraphConfig, load_config
from gr_graph.noise_calibration import (
    between_residuals,
    factor_redundancies,
    loop_axis_variance_factors,
    loop_variance_factor,
    outlying_loop,
    variance_factor,
)
from gr_graph.noise_consistency import (
    axis_stats,
    edge_nees,
    main,
    position_nees,
    round_noise_consistency,
)
from gr_graph.odometry import RegistrationEdge
from gr_graph.pose_graph import PoseGraph


def _exp(xi: np.ndarray) -> np.ndarray:
    return gtsam.Pose3.Expmap(xi).matrix()


def _simulated_graph(rng: np.random.Generator, K: int = 120, n_loops: int = 30, true_factor: float = 25.0,
                     loop_factor: float | None = None, loop_axes: np.ndarray | None = None):
    """A closed drive (circle, 2 laps) with odometry and loop measurements whose real error
    covariance is ``true_factor`` (loops: ``loop_factor``, default the same) x the inverse of
    the information they carry; ``loop_axes`` (6 standard-deviation factors) makes the loops'
    real covariance ``S (loop_factor Sigma) S`` with ``S = diag(loop_axes)``."""
    t = np.linspace(0, 4 * np.pi, K)
    gt = np.stack([_exp(np.array([0, 0, ti, 0, 0, 0])) for ti in t])
    gt[:, :3, 3] = np.column_stack([20 * np.cos(t), 20 * np.sin(t), 0.1 * t])
    A = rng.normal(size=(6, 6))
    info = A @ A.T + np.diag([4e4, 4e4, 4e4, 400, 400, 400])  # the claimed information
    cov_true = true_factor * np.linalg.inv(info)
    chol = {"odometry": np.linalg.cholesky(cov_true),
            "loop": np.linalg.cholesky((true_factor if loop_factor is None else loop_factor)
                                       * _axes_scaled(np.linalg.inv(info), loop_axes))}
    pairs = [(k + 1, k) for k in range(K - 1)]
    half = K // 2
    loops = rng.choice(np.arange(half, K), n_loops, replace=False)
    pairs += [(int(i), int(i) - half) for i in loops]  # one lap apart: the same place
    edges = []
    for k, l in pairs:
        kind = "odometry" if k == l + 1 else "loop"
        T = np.linalg.inv(gt[l]) @ gt[k] @ _exp(chol[kind] @ rng.normal(size=6))
        edges.append(RegistrationEdge(k, l, T, info, info.copy(), 1.0, 0.0, 1, True, "", kind))
    return gt, edges, cov_true


def _axes_scaled(cov: np.ndarray, sd_factors: np.ndarray | None) -> np.ndarray:
    """``S cov S`` with ``S = diag(sd_factors)`` (``cov`` itself without factors)."""
    if sd_factors is None:
        return cov
    return np.asarray(sd_factors)[:, None] * cov * np.asarray(sd_factors)[None, :]


def _solve(gt: np.ndarray, edges: list[RegistrationEdge], marginals: bool = False):
    g = PoseGraph(GraphConfig(loop_kernel="none", marginals=marginals))
    for T in gt:
        g.add_pose(T @ _exp(np.full(6, 1e-3)))
    for e in edges:
        g.add_edge(e.source, e.target, e.T, e.information, loop=e.kind == "loop")
    return g, g.optimize()


def test_between_residuals_are_gtsam_factor_errors():
    rng = np.random.default_rng(0)
    gt, edges, _ = _simulated_graph(rng, K=20, n_loops=4)
    _, res = _solve(gt, edges)
    r = between_residuals(res.poses, edges)
    values = gtsam.Values()
    for i, T in enumerate(res.poses):
        values.insert(X(i), gtsam.Pose3(T))
    for e, re in zip(edges, r):
        f = gtsam.BetweenFactorPose3(X(e.target), X(e.source), gtsam.Pose3(e.T),
                                     gtsam.noiseModel.Gaussian.Information(e.information))
        assert 2.0 * f.error(values) == pytest.approx(re @ e.information @ re, rel=1e-9)


def test_variance_factor_recovers_the_true_scale_and_makes_nees_consistent():
    """Information overconfident by 25x: sigma0^2 finds the factor (within its sampling spread,
    redundancy 180: +-11 % at one sigma) without ground truth; after scaling, the mean edge
    NEES against ground truth is ~6 for both kinds and the marginals' position NEES ~3."""
    rng = np.random.default_rng(1)
    gt, edges, _ = _simulated_graph(rng)
    _, res = _solve(gt, edges)
    vf = variance_factor(res.poses, edges)
    assert vf.redundancy == 6 * 30 and vf.n_edges == {"odometry": 119, "loop": 30}
    assert 25.0 / 1.35 < vf.sigma0_sq < 25.0 * 1.35
    assert vf.scale == pytest.approx(1.0 / vf.sigma0_sq)
    # uncalibrated: NEES ~ 6 x 25
    nees0 = edge_nees(np.array([(e.source, e.target) for e in edges]), np.array([e.T for e in edges]),
                      np.array([e.information for e in edges]), gt)
    assert nees0.mean() > 80
    for e in edges:
        e.information = vf.scale * e.information
    nees = edge_nees(np.array([(e.source, e.target) for e in edges]), np.array([e.T for e in edges]),
                     np.array([e.information for e in edges]), gt)
    kinds = np.array([e.kind for e in edges])
    assert 4.0 < nees[kinds == "odometry"].mean() < 9.0 and 3.0 < nees[kinds == "loop"].mean() < 12.0
    _, res = _solve(gt, edges, marginals=True)
    from gr_graph.pose_graph import position_covariance_world

    # anchor both at the first pose as the pipeline does
    est = np.linalg.inv(res.poses[0]) @ res.poses
    ref = np.linalg.inv(gt[0]) @ gt
    pn = position_nees(est, position_covariance_world(est, res.covariances), ref)
    assert 1.5 < pn.mean() < 6.0


def _wrong_loop(gt: np.ndarray, edges: list[RegistrationEdge]) -> RegistrationEdge:
    """A loop that passed verification but is 4.5 m and 10 deg off, between poses 100 and 40."""
    info = edges[0].information
    T = np.linalg.inv(gt[40]) @ gt[100] @ _exp(np.array([0, 0, 0.17, 4.0, 2.0, 0]))
    return RegistrationEdge(100, 40, T, info, info.copy(), 1.0, 0.0, 1, True, "", "loop")


def _gaussian(gt: np.ndarray, edges: list[RegistrationEdge]) -> PoseGraph:
    g, _ = _solve(gt, edges)
    return g


def test_a_wrong_loop_is_left_out_of_the_variance_factor_and_good_ones_are_not():
    """The deletion F test (no ground truth): no loop of 8 correct graphs fails it at 1e-4; a loop
    4.5 m off does, and the variance factor without it is back in the band of the correct graph,
    while with it the factor is 1.7x too large (it would weaken every edge)."""
    for seed in range(8):
        gt, edges, _ = _simulated_graph(np.random.default_rng(seed))
        g = _gaussian(gt, edges)
        assert outlying_loop(g.graph, g.values, edges, 1e-4) is None, seed
    gt, edges, _ = _simulated_graph(np.random.default_rng(1))
    bad = edges + [_wrong_loop(gt, edges)]
    g = _gaussian(gt, bad)
    found = outlying_loop(g.graph, g.values, bad, 1e-4)
    assert found is not None and found[0] == len(bad) - 1 and found[1] > found[2] > 1.0
    assert outlying_loop(g.graph, g.values, bad, 0.0) is None  # alpha 0: the test is off
    with_it = variance_factor(g.optimize(marginals=False).poses, bad).sigma0_sq
    _, res = _solve(gt, edges)
    without = variance_factor(res.poses, edges).sigma0_sq
    assert 25.0 / 1.35 < without < 25.0 * 1.35 and with_it > 1.5 * without


def test_the_deletion_statistic_is_what_the_loop_adds_to_the_chi_square():
    """The F statistic from the redundancy matrix equals the one from solving the graph without the loop
    (the change of the total chi-square over the variance factor of the rest; exact for a linear graph)."""
    gt, edges, _ = _simulated_graph(np.random.default_rng(1))
    bad = edges + [_wrong_loop(gt, edges)]
    g = _gaussian(gt, bad)
    index, stat, threshold = outlying_loop(g.graph, g.values, bad, 1e-4)
    total_with = 2.0 * g.graph.error(g.values)
    g_without = _gaussian(gt, edges)
    total_without = 2.0 * g_without.graph.error(g_without.values)
    rest = 6 * (len(bad) - len(gt) + 1) - 6
    direct = ((total_with - total_without) / 6) / (total_without / rest)
    assert stat == pytest.approx(direct, rel=0.02)
    # solved a loop at a time (the memory bound of long runs): the same statistic
    import gr_graph.noise_calibration as nc

    nc_bytes = nc.SOLVE_CHUNK_BYTES
    try:
        nc.SOLVE_CHUNK_BYTES = 1.0
        assert outlying_loop(g.graph, g.values, bad, 1e-4) == pytest.approx((index, stat, threshold), rel=1e-9)
    finally:
        nc.SOLVE_CHUNK_BYTES = nc_bytes


def test_calibration_leaves_the_wrong_loop_out_and_keeps_it_in_the_robust_graph():
    """The frame loop's calibration of learned edges: the wrong loop is named in the summary, the scale
    comes from the other edges, and the loop still weighs in the robust graph (its kernel decides)."""
    import types

    from gr_graph.frame_loop import _FrameLoop

    gt, edges, _ = _simulated_graph(np.random.default_rng(1))
    bad = edges + [_wrong_loop(gt, edges)]
    for e in bad:
        e.info["edge_noise"] = "learned"
    raw = [e.information.copy() for e in bad]
    loop = object.__new__(_FrameLoop)  # only what the calibration uses
    loop.edges, loop.cfg = bad, load_config(None, {"training": {"learned_noise_outlier_alpha": 1e-4}})
    loop.edge_noise = types.SimpleNamespace(calibration=None)
    loop.calibrate_noise(gt @ _exp(np.full(6, 1e-3)))
    cal = loop.edge_noise.calibration
    assert [t["loop"] for t in cal["loops_left_out"]] == [[100, 40]] and cal["loops_left_out_max"] == 3
    assert cal["redundancy"] == 6 * 30 and 25.0 / 1.35 < cal["sigma0_sq"] < 25.0 * 1.35
    for e, info in zip(bad, raw):
        np.testing.assert_allclose(e.information, cal["scale"] * info)
    assert loop.graph.graph.size() == 1 + len(bad) and loop.graph.n_loops == 31
    # the test off (the default): every loop counts, as before
    for e, info in zip(bad, raw):
        e.information = info.copy()
    loop.cfg = load_config(None, {})
    loop.calibrate_noise(gt @ _exp(np.full(6, 1e-3)))
    assert loop.edge_noise.calibration["loops_left_out"] == []
    assert loop.edge_noise.calibration["sigma0_sq"] > 1.5 * cal["sigma0_sq"]


def test_no_loops_no_calibration():
    rng = np.random.default_rng(2)
    gt, edges, _ = _simulated_graph(rng, K=15, n_loops=0)
    _, res = _solve(gt, edges)
    vf = variance_factor(res.poses, edges)
    assert vf.sigma0_sq is None and vf.scale == 1.0 and vf.redundancy == 0
    assert vf.summary()["method"] == "graph_residuals"


def test_factor_redundancies_closed_form():
    """Pose 0 pinned by the prior, pose 1 measured twice with the same relative pose and
    informations a I and b I: edge 1's redundancy is 6 b / (a + b), edge 2's 6 a / (a + b);
    all factors together: rows - unknowns = 18 - 12."""
    a, b = 100.0, 300.0
    g = PoseGraph(GraphConfig(loop_kernel="none", marginals=False))
    T01 = _exp(np.array([0.1, -0.2, 0.3, 1.0, 2.0, -0.5]))
    g.add_pose(np.eye(4))
    g.add_pose(T01)
    g.add_edge(1, 0, T01, a * np.eye(6))
    g.add_edge(1, 0, T01, b * np.eye(6), loop=True)
    g.optimize(marginals=False)
    r_prior, r1, r2 = factor_redundancies(g.graph, g.values, [[0], [1], [2]])
    assert r1 == pytest.approx(6 * b / (a + b), rel=1e-5) and r2 == pytest.approx(6 * a / (a + b), rel=1e-5)
    assert r_prior + r1 + r2 == pytest.approx(6.0, rel=1e-6)
    assert factor_redundancies(g.graph, g.values, [[1, 2]])[0] == pytest.approx(r1 + r2, rel=1e-9)


def _loop_solver(gt: np.ndarray, edges: list[RegistrationEdge]):
    def solve(informations):
        g = PoseGraph(GraphConfig(loop_kernel="none", marginals=False))
        for T in gt:
            g.add_pose(T @ _exp(np.full(6, 1e-3)))
        for e, H in zip(edges, informations):
            g.add_edge(e.source, e.target, e.T, H, loop=e.kind == "loop")
        g.optimize(marginals=False)
        return g.graph, g.values
    return solve


def _bare_frame_loop(loop_variance: str, edges: list[RegistrationEdge]):
    """A ``_FrameLoop`` holding only what :meth:`estimate_loop_variance` reads: the config with
    ``graph.loop_variance``, the edges and an empty pose graph."""
    from gr_graph.frame_loop import _FrameLoop

    loop = _FrameLoop.__new__(_FrameLoop)
    loop.cfg = load_config(overrides={"graph": {"loop_variance": loop_variance}})
    loop.edges = edges
    loop.graph = PoseGraph(loop.cfg.graph)
    return loop


@pytest.mark.parametrize("loop_factor", [40.0, 1.0])
def test_loop_variance_factor_finds_overconfident_loops_with_odometry_fixed(loop_factor):
    """Odometry consistent with its information, loops' real errors ``loop_factor`` x what their
    information claims: the loops' factor is found from the residuals alone (30 loops,
    redundancy ~170: +-11 % at one sigma), consistent loops keep ~1; after scaling, the loops'
    NEES against ground truth is ~6, and the odometry edges are not touched."""
    rng = np.random.default_rng(3)
    gt, edges, _ = _simulated_graph(rng, true_factor=1.0, loop_factor=loop_factor)
    edges = [edges[i] for i in rng.permutation(len(edges))]  # loops interleaved with odometry edges
    odometry_info = [e.information.copy() for e in edges if e.kind == "odometry"]
    # the first iteration's sigma_L^2, independently: loop chi2 from the residuals at the optimum of
    # the unscaled graph over the loops' redundancy, their factors picked by edge kind
    graph, values = _loop_solver(gt, edges)([e.information for e in edges])
    poses = np.stack([values.atPose3(X(i)).matrix() for i in range(len(gt))])
    loop_rows = [i for i, e in enumerate(edges) if e.kind == "loop"]
    r = between_residuals(poses, [edges[i] for i in loop_rows])
    chi2 = sum(float(ri @ edges[i].information @ ri) for ri, i in zip(r, loop_rows))
    first = chi2 / factor_redundancies(graph, values, [[1 + i for i in loop_rows]])[0]
    lv = loop_variance_factor(_loop_solver(gt, edges), edges)
    assert lv.sigma_sq[0] == pytest.approx(first, rel=1e-6)
    assert lv.converged and lv.reason is None and lv.n_loops == 30 and abs(lv.sigma_sq[-1] - 1.0) < 1e-3
    assert loop_factor / 1.4 < 1.0 / lv.scale < loop_factor * 1.4
    assert 0 < lv.redundancy <= 180 and (lv.redundancy > 120 or loop_factor == 1.0)  # weak loops: ~6 each
    for e in edges:
        if e.kind == "loop":
            e.information = lv.scale * e.information
    kinds = np.array([e.kind for e in edges])
    nees = edge_nees(np.array([(e.source, e.target) for e in edges]), np.array([e.T for e in edges]),
                     np.array([e.information for e in edges]), gt)
    assert 3.0 < nees[kinds == "loop"].mean() < 12.0 and 4.0 < nees[kinds == "odometry"].mean() < 9.0
    assert all(np.array_equal(e.information, H) for e, H in zip([e for e in edges if e.kind == "odometry"],
                                                                 odometry_info))
    assert lv.summary()["method"] == "loop_variance_component"


def test_loop_variance_needs_loops_and_the_frame_loop_applies_it():
    rng = np.random.default_rng(4)
    gt, edges, _ = _simulated_graph(rng, K=15, n_loops=0)
    lv = loop_variance_factor(_loop_solver(gt, edges), edges)
    assert lv.reason == "no loops" and lv.scale == 1.0 and not lv.converged
    # the frame loop's step (graph.loop_variance: estimated): loops scaled, odometry kept, the
    # robust graph solved again and the summary kept for round.json
    gt, edges, _ = _simulated_graph(rng, K=60, n_loops=12, true_factor=1.0, loop_factor=30.0)
    before = [e.information.copy() for e in edges]
    loop = _bare_frame_loop("estimated", edges)
    res = loop.estimate_loop_variance(gt @ _exp(np.full(6, 1e-3)))
    scale = loop.loop_variance["scale"]
    assert loop.loop_variance["converged"] and 1 / 60 < scale < 1 / 15
    for e, H in zip(edges, before):
        np.testing.assert_allclose(e.information, scale * H if e.kind == "loop" else H, rtol=1e-12)
    assert loop.graph.n_loops == 12 and len(res.poses) == 60
    # the returned poses are the optimum of the (robust) graph with the scaled loops
    again = loop.graph.optimize(marginals=False)
    assert again.final_error == pytest.approx(res.final_error, rel=1e-6)
    np.testing.assert_allclose(again.poses, res.poses, atol=1e-6)
    # without loops nothing is estimated: no new solution, the graph and the edges untouched
    gt, edges, _ = _simulated_graph(rng, K=15, n_loops=0)
    before = [e.information.copy() for e in edges]
    loop.edges, graph = edges, PoseGraph(loop.cfg.graph)
    loop.graph = graph
    assert loop.estimate_loop_variance(gt) is None and loop.graph is graph
    assert loop.loop_variance["reason"] == "no loops" and loop.loop_variance["scale"] == 1.0
    assert all(np.array_equal(e.information, H) for e, H in zip(edges, before))


def _loop_z2(edges: list[RegistrationEdge], gt: np.ndarray) -> np.ndarray:
    """Mean squared error per axis of the loop edges against ground truth, in units of the
    standard deviations their information claims (1 each when consistent)."""
    from gr_graph.noise_consistency import edge_errors, gt_relative_poses

    loops = [e for e in edges if e.kind == "loop"]
    xi = edge_errors(np.array([e.T for e in loops]), gt_relative_poses(np.array([(e.source, e.target) for e in loops]), gt))
    return np.array(axis_stats(xi, np.array([e.information for e in loops]))["z2_mean"])


def test_loop_axis_variance_factors_find_the_axis_the_loops_err_on():
    """Loops whose pitch error is 3x what their information claims and whose other axes are as
    claimed (odometry consistent): the per-axis factors, from residuals alone, weaken pitch by
    ~1/9 and leave the rest near 1 (inflate only; measured 0.83-1); the loops' pitch z^2 against
    ground truth drops from ~9 to ~1. The first iteration's numerators and redundancies add up to
    the loops' chi2 and redundancy (bookkeeping: the axes split the same residuals)."""
    rng = np.random.default_rng(11)
    axes_sd = np.array([1.0, 3.0, 1.0, 1.0, 1.0, 1.0])
    gt, edges, _ = _simulated_graph(rng, K=240, n_loops=80, true_factor=1.0, loop_factor=1.0, loop_axes=axes_sd)
    before = _loop_z2(edges, gt)
    assert before[1] > 5.0 and np.all(before[[0, 2, 3, 4, 5]] < 2.0)  # the simulated over-confidence
    la = loop_axis_variance_factors(_loop_solver(gt, edges), edges)
    assert la.converged and la.reason is None and la.n_loops == 80
    scale = np.array(la.axis_scale)
    assert 1 / 9 / 1.6 < scale[1] < 1 / 9 * 1.6
    assert np.all(scale[[0, 2, 3, 4, 5]] > 0.6) and np.all(scale <= 1.0)
    # sum_j sigma_j^2 r_j of the first iteration = the loops' chi2 at the unscaled optimum
    graph, values = _loop_solver(gt, edges)([e.information for e in edges])
    chi2 = sum(2.0 * graph.at(1 + i).error(values) for i, e in enumerate(edges) if e.kind == "loop")
    r = factor_redundancies(graph, values, [[1 + i for i, e in enumerate(edges) if e.kind == "loop"]])[0]
    first = loop_axis_variance_factors(_loop_solver(gt, edges), edges, max_iterations=1)
    assert first.redundancy is not None and sum(first.redundancy) == pytest.approx(r, rel=1e-6)
    assert float(np.dot(first.sigma_sq[0], first.redundancy)) == pytest.approx(chi2, rel=1e-6)
    for e in edges:
        if e.kind == "loop":
            e.information = la.scaled_information(e.information)
    after = _loop_z2(edges, gt)
    assert 0.5 < after[1] < 1.8 and np.all(after < 2.0)
    assert la.summary()["method"] == "loop_axis_variance_components"


def test_loop_axis_variance_factors_leave_consistent_loops_and_never_strengthen():
    """Loops as good as claimed: every factor stays well above a 3x error's ~0.11 (80 loops, ~30
    redundancy per axis: the first iteration's sigma_j^2 is 1 +- 0.26, and the iterations to the
    fixed point amplify a deviation, measured down to 0.47 on one axis of this graph). Loops 4x better than claimed on
    every axis: inflate-only leaves them all at exactly 1; without it the factors grow (the
    loops strengthened). No loops: nothing estimated."""
    rng = np.random.default_rng(12)
    gt, edges, _ = _simulated_graph(rng, K=240, n_loops=80, true_factor=1.0, loop_factor=1.0)
    la = loop_axis_variance_factors(_loop_solver(gt, edges), edges)
    scale = np.array(la.axis_scale)
    assert la.reason is None and np.all(scale > 0.3) and np.all(scale <= 1.0) and np.prod(scale) ** (1 / 6) > 0.7
    gt, edges, _ = _simulated_graph(rng, K=240, n_loops=80, true_factor=1.0, loop_factor=1 / 16)
    la = loop_axis_variance_factors(_loop_solver(gt, edges), edges)
    assert la.converged and la.axis_scale == [1.0] * 6 and np.all(np.array(la.sigma_sq[0]) < 1.0)
    free = loop_axis_variance_factors(_loop_solver(gt, edges), edges, inflate_only=False)
    assert np.all(np.array(free.axis_scale) > 1.5)
    gt, edges, _ = _simulated_graph(rng, K=15, n_loops=0)
    la = loop_axis_variance_factors(_loop_solver(gt, edges), edges)
    assert la.reason == "no loops" and la.axis_scale == [1.0] * 6 and not la.converged


def test_loop_axis_redundancies_closed_form_with_correlated_information():
    """Pose 0 pinned by the prior, pose 1 measured by an odometry edge (information A) and a loop
    (B), both strongly correlating their axes: the loop's redundancy matrix is
    I - (A + B)^-1 B, its diagonal the per-axis redundancies (a whitening other than gtsam's own
    would give other numbers: the diagonal is not invariant, only its trace)."""
    rng = np.random.default_rng(14)

    def correlated(scales):
        Q, _ = np.linalg.qr(rng.normal(size=(6, 6)))
        return Q @ np.diag(scales) @ Q.T

    A = correlated([1e4, 4e3, 2e3, 900.0, 400.0, 100.0])
    B = correlated([3e3, 2e3, 1e3, 800.0, 300.0, 50.0])
    T01 = _exp(np.array([0.1, -0.2, 0.3, 1.0, 2.0, -0.5]))
    edges = [RegistrationEdge(1, 0, T01, A, A, 1.0, 0.0, 1, True, "", "odometry"),
             RegistrationEdge(1, 0, T01 @ _exp(np.full(6, 1e-4)), B, B, 1.0, 0.0, 1, True, "", "loop")]
    la = loop_axis_variance_factors(_loop_solver(np.stack([np.eye(4), T01]), edges), edges, max_iterations=1)
    expected = np.diag(np.eye(6) - np.linalg.solve(A + B, B))
    np.testing.assert_allclose(la.redundancy, expected, rtol=1e-4, atol=1e-6)
    assert np.ptp(expected) > 0.3  # the axes differ: a uniform share would not pass


def test_frame_loop_estimated_axes_scales_loops_twice_and_records_both():
    """graph.loop_variance: estimated_axes: the common factor first, then the per-axis factors
    on the scaled loops; every loop's information is the product, odometry untouched, both
    recorded for round.json."""
    rng = np.random.default_rng(13)
    gt, edges, _ = _simulated_graph(rng, K=120, n_loops=40, true_factor=1.0, loop_factor=4.0,
                                    loop_axes=np.array([1.0, 3.0, 1.0, 1.0, 1.0, 1.0]))
    before = [e.information.copy() for e in edges]
    loop = _bare_frame_loop("estimated_axes", edges)
    res = loop.estimate_loop_variance(gt @ _exp(np.full(6, 1e-3)))
    lv = loop.loop_variance
    assert res is not None and lv["method"] == "loop_variance_component" and lv["converged"]
    axes = lv["axes"]
    assert axes["method"] == "loop_axis_variance_components" and axes["reason"] is None
    root = np.sqrt(np.array(axes["axis_scale"]))
    assert axes["axis_scale"][1] < 0.5 and max(axes["axis_scale"]) <= 1.0
    for e, H in zip(edges, before):
        expected = lv["scale"] * root[:, None] * H * root[None, :] if e.kind == "loop" else H
        np.testing.assert_allclose(e.information, expected, rtol=1e-10)
    assert _loop_z2(edges, gt)[1] < 2.0


def test_frame_loop_per_axis_failure_keeps_the_common_factor(monkeypatch):
    """An exception in the per-axis stage (e.g. memory for the dense Jacobian block) does not lose
    the finished run: the loops keep the common factor, the graph is solved, the reason recorded."""
    import gr_graph.frame_loop as frame_loop

    def fails(*args, **kwargs):
        raise MemoryError("dense Jacobian block")

    monkeypatch.setattr(frame_loop, "loop_axis_variance_factors", fails)
    rng = np.random.default_rng(15)
    gt, edges, _ = _simulated_graph(rng, K=60, n_loops=12, true_factor=1.0, loop_factor=9.0)
    before = [e.information.copy() for e in edges]
    loop = _bare_frame_loop("estimated_axes", edges)
    res = loop.estimate_loop_variance(gt @ _exp(np.full(6, 1e-3)))
    assert res is not None and len(res.poses) == 60
    scale = loop.loop_variance["scale"]
    assert scale < 0.5 and loop.loop_variance["axes"]["reason"].startswith("failed: MemoryError")
    for e, H in zip(edges, before):
        np.testing.assert_allclose(e.information, scale * H if e.kind == "loop" else H, rtol=1e-12)


def test_round_noise_consistency_reads_a_round_and_names_a_bad_file(tmp_path, capsys):
    rng = np.random.default_rng(3)
    gt, edges, _ = _simulated_graph(rng, K=30, n_loops=6, true_factor=1.0)
    _, res = _solve(gt, edges, marginals=True)
    from gr_graph.pose_graph import position_covariance_world

    rd = tmp_path / "run" / "round_1"
    rd.mkdir(parents=True)
    arrays = {
        "poses": res.poses, "gt_poses": gt, "covariance": res.covariances,
        "position_cov_world": position_covariance_world(res.poses, res.covariances),
        "edges": np.array([(e.source, e.target) for e in edges]), "edge_T": np.array([e.T for e in edges]),
        "edge_information": np.array([e.information for e in edges]),
        "edge_kind": np.array([e.kind == "loop" for e in edges], np.uint8),
        "edge_ok": np.ones(len(edges), bool),
    }
    arrays["edge_ok"][3] = False
    np.savez(rd / "marginals.npz", **arrays)
    out = round_noise_consistency(rd)
    ref = edge_nees(arrays["edges"], arrays["edge_T"], arrays["edge_information"], gt)
    odo = (arrays["edge_kind"] == 0) & arrays["edge_ok"]
    assert out["edges"]["odometry"]["n"] == 28 and out["edges"]["loop"]["n"] == 6
    assert out["edges"]["odometry"]["mean"] == pytest.approx(ref[odo].mean())
    assert out["edges"]["n_flagged_left_out"] == 1
    # per axis: the edge errors against a Logmap of each edge written out here, variances from the information
    xi = np.array([gtsam.Pose3.Logmap(gtsam.Pose3(np.asarray(T)).between(gtsam.Pose3(np.linalg.inv(gt[b]) @ gt[a])))
                   for (a, b), T in zip(arrays["edges"], arrays["edge_T"])])
    var = np.array([np.diag(np.linalg.inv(i)) for i in arrays["edge_information"]])
    ax = out["edges"]["odometry"]["per_axis"]
    assert ax["axes"] == ["rot_x", "rot_y", "rot_z", "x", "y", "z"]
    assert ax["error_mean"] == pytest.approx(xi[odo].mean(0)) and ax["error_rms"] == pytest.approx(
        np.sqrt((xi[odo] ** 2).mean(0)))
    assert ax["z2_mean"] == pytest.approx((xi[odo] ** 2 / var[odo]).mean(0))
    # a singular information (no information along y): that axis counts as unconstrained, z^2 0
    info = np.diag([1.0, 1.0, 1.0, 4.0, 0.0, 4.0])[None]
    one = axis_stats(np.array([[0.1, 0.2, 0.3, 0.5, 7.0, 1.0]]), info)
    assert one["z2_mean"] == pytest.approx([0.01, 0.04, 0.09, 1.0, 0.0, 4.0])
    steps = [(np.linalg.norm(np.asarray(T)[:3, 3]), np.linalg.norm((np.linalg.inv(gt[b]) @ gt[a])[:3, 3]))
             for (a, b), T, kind, good in zip(arrays["edges"], arrays["edge_T"], arrays["edge_kind"],
                                              arrays["edge_ok"]) if kind == 0 and good]  # flagged edge 3 left out
    measured, true = np.sum(steps, axis=0)
    assert out["edges"]["odometry"]["path_error_percent"] == pytest.approx(100 * (measured / true - 1))
    assert out["position"]["n"] == 29 and out["position"]["n_left_out"] == 0
    full = position_nees(arrays["poses"], arrays["position_cov_world"], gt)
    assert out["position"]["mean"] == pytest.approx(full.mean())
    # marginals that failed for some poses (NaN) and a component anchored on its own first pose (round.json's
    # report): those poses are left out and counted, not averaged in as NaN or against world-frame errors
    failed = dict(arrays, position_cov_world=arrays["position_cov_world"].copy())
    failed["position_cov_world"][[4, 5]] = np.nan
    np.savez(rd / "marginals.npz", **failed)
    (rd / "round.json").write_text(json.dumps({"marginals": {"status": "anchored",
                                                              "unanchored_components": [[20, 24, 5]]}}))
    out = round_noise_consistency(rd)
    keep = np.ones(30, bool)
    keep[[4, 5, 20, 21, 22, 23, 24]] = False
    assert out["position"]["n_left_out"] == 7 and out["position"]["n"] == 22
    assert out["position"]["mean"] == pytest.approx(full[keep[1:]].mean())
    assert round_noise_consistency(rd, {"status": "failed"})["position"]["n_left_out"] == 2  # given, not read
    (rd / "round.json").unlink()
    np.savez(rd / "marginals.npz", **arrays)
    assert main([str(tmp_path / "run"), "--json", str(tmp_path / "nees.json")]) == 0
    assert "| 1 |" in capsys.readouterr().out
    assert json.loads((tmp_path / "nees.json").read_text())["1"]["edges"]["loop"]["n"] == 6
    del arrays["edge_T"]
    np.savez(rd / "marginals.npz", **arrays)
    with pytest.raises(ValueError, match="marginals.npz.*edge_T"):
        round_noise_consistency(rd)
    assert main([str(tmp_path / "run")]) == 2


def test_loop_edges_get_learned_information_unless_odometry_only():
    from factors.wls import solve_wls
    from gr_graph.edge_noise import LearnedEdgeNoise

    rng = np.random.default_rng(4)
    q = np.column_stack([rng.uniform(-20, 20, (2000, 2)), rng.uniform(-2, 2, 2000)])
    q[::3, 2] = 0.0
    C = np.tile(np.diag([0.04, 0.04, 0.01]), (len(q), 1, 1))
    T = _exp(np.array([0.0, 0.0, 0.02, 0.3, -0.1, 0.0]))
    p = (q - T[:3, 3]) @ T[:3, :3]  # maps exactly onto q under T
    preds = {900: (p, C), 100: (q, C)}
    loop = RegistrationEdge(5, 1, T, np.eye(6), 3 * np.eye(6), 1.0, 0.0, 1, True, "", "loop")
    cfg = load_config(overrides={"odometry": {"corr_max_distance": 0.5}})
    en = LearnedEdgeNoise(preds.get, cfg)
    en.apply(loop, 900, 100)
    H = solve_wls(p, q, C, T0=T).hessian
    np.testing.assert_allclose(loop.information, H, rtol=1e-8, atol=1e-12 * np.abs(H).max())
    assert en.summary()["loop"]["n_learned"] == 1 and en.summary()["n_learned"] == 0
    old = RegistrationEdge(5, 1, T, np.eye(6), 3 * np.eye(6), 1.0, 0.0, 1, True, "", "loop")
    en2 = LearnedEdgeNoise(preds.get, load_config(overrides={"training": {"learned_noise_edges": "odometry"}}))
    en2.apply(old, 900, 100)
    np.testing.assert_array_equal(old.information, 3 * np.eye(6))
    assert en2.summary()["loop"]["n_learned"] == 0


def _read_keeping_one(seq, predictor, record: str):
    """A densified view of ``seq`` that keeps the predictions of the last frame read only, after reading
    every frame, and what its method ``record`` gave for each frame right after it was read."""
    from gr_graph.config import PreprocessConfig, TrainingConfig
    from gr_graph.densify import densified_sequence

    view = densified_sequence(seq, predictor, TrainingConfig(tau_ani=0.9, samples_per_point=2),
                              preprocess=PreprocessConfig(), keep_predictions=1)
    kept = {}
    for i in range(len(seq)):
        view[i]
        kept[i] = getattr(view, record)(seq[i].index)
    return view, kept


def test_densified_view_predicts_an_evicted_frame_again():
    from test_learning_rounds import PlaneScenes, plane_predictor

    seq = PlaneScenes(n=4)
    calls = []

    def predictor(points):
        calls.append(len(points))
        return plane_predictor(points)

    view, kept = _read_keeping_one(seq, predictor, "predicted")
    assert view.predicted(seq[0].index) is None  # evicted
    pts, C = view.prediction(seq[0].index)  # predicted again, identical
    np.testing.assert_array_equal(pts, kept[0][0])
    np.testing.assert_array_equal(C, kept[0][1])
    assert view.n_recomputed == 1 and len(calls) == 5
    assert view.prediction(12345) is None  # never read through the view
    assert view.prediction_times(seq[0].index) is None  # frames without per-point times


def test_densified_view_gives_its_predictions_per_point_times():
    """The sweep fraction of each predicted point is that of the raw point nearest to it (the frame
    loop deskews the predictions with them), the same whether kept or made again."""
    from dataclasses import replace

    from scipy.spatial import cKDTree
    from test_learning_rounds import PlaneScenes, plane_predictor

    from gr_graph.datasets.registry import SequenceView

    timed = SequenceView(PlaneScenes(n=3), transform=lambda f: replace(f, time=np.linspace(0.0, 1.0, len(f.points))))
    view, kept = _read_keeping_one(timed, plane_predictor, "prediction_times")
    for i in range(3):
        raw = timed[i]
        times = view.prediction_times(raw.index)  # frames 0 and 1: made again
        np.testing.assert_array_equal(times, kept[i])
        pts, _ = view.prediction(raw.index)
        assert times.shape == (len(pts),)
        rows = np.rint(times * (len(raw.points) - 1)).astype(int)  # the times are unique: they name the raw rows
        nearest, _ = cKDTree(raw.points).query(pts)
        np.testing.assert_allclose(np.linalg.norm(raw.points[rows] - pts, axis=1), nearest, atol=1e-9)
    first = timed[0].index
    view.prediction(first)  # made again (evicted); its times come with it, read next without a second pass
    reads = []
    view.parent = SequenceView(timed, transform=lambda f: reads.append(f.index) or f)
    np.testing.assert_array_equal(view.prediction_times(first), kept[0])
    assert reads == []


def test_flagged_edges_are_left_out_of_the_variance_factor():
    """A failed registration (constant-velocity guess 60 m off, weak fallback information) does
    not enter sigma0^2; the loops still tie the two sides, so the redundancy counts them."""
    rng = np.random.default_rng(5)
    gt, edges, _ = _simulated_graph(rng, true_factor=4.0)
    _, res = _solve(gt, edges)
    ref = variance_factor(res.poses, edges)
    bad = edges[70]
    bad.T = bad.T @ _exp(np.array([0, 0, 0, 60.0, 0, 0]))
    bad.ok = False
    bad.information = np.diag(1.0 / np.array([0.05, 0.05, 0.05, 1.0, 1.0, 1.0]) ** 2)
    _, res = _solve(gt, edges)
    vf = variance_factor(res.poses, edges)
    assert vf.n_flagged == 1 and vf.redundancy == ref.redundancy - 6
    assert vf.sigma0_sq == pytest.approx(ref.sigma0_sq, rel=0.1)
    # the same edge counted as a measurement would dominate the sum
    bad.ok = True
    assert variance_factor(res.poses, edges).sigma0_sq > 3 * ref.sigma0_sq


@pytest.mark.slow
def test_frame_loop_gives_loops_learned_information_and_one_scale(tmp_path):
    """SLAM over the 160-frame revisit excerpt (16 rings) with learned edge noise from a fixed
    covariance model (small_gicp's plane covariances x 0.01 m^2, no network): loops get H(C) too,
    the older scan's covariances coming from far back; one scale multiplies every edge;
    at the calibrated solution sigma0^2 is 1; NEES against ground truth is finite."""
    from slam_support import FrameSubset, revisit_config, revisit_ranges

    from gr_graph.datasets.synthetic import SyntheticSequence
    from gr_graph.edge_noise import LearnedEdgeNoise, learned_information
    from gr_graph.frame_loop import run_slam
    from gr_graph.preprocess import preprocess_scan

    idx = np.concatenate([np.arange(a, b) for a, b in revisit_ranges()])
    seq = FrameSubset(SyntheticSequence(seed=0, n_rings=16), idx, "revisit16")
    cfg = revisit_config(tmp_path)
    asked: list[int] = []

    def predictions(frame_index: int):
        asked.append(frame_index)
        scan = preprocess_scan(seq.parent[frame_index].points, cfg.preprocess, index=frame_index)
        return scan.points, 0.01 * np.asarray(scan.cloud.covs())[:, :3, :3] + 1e-6 * np.eye(3)

    en = LearnedEdgeNoise(predictions, cfg)
    res = run_slam(seq, cfg, edge_noise=en)
    s = en.summary()
    loops = res.loops
    assert len(loops) >= 3 and s["loop"]["n_learned"] == len(loops) and s["loop"]["n_fallback"] == 0
    assert s["n_learned"] + s["n_fallback"] == len(res.edges) - len(loops)
    assert min(res.frame_index[e.target] for e in loops) < idx[60]  # the older scan is from the first stretch
    cal = s["calibration"]
    n_ok = sum(e.ok for e in res.edges)
    assert cal["method"] == "graph_residuals" and cal["redundancy"] == 6 * (n_ok - len(res.poses) + 1)
    assert cal["scale"] > 0 and np.isfinite(cal["scale"])
    # a loop's information is scale x its H(C), recomputed here from the same covariances
    e = loops[0]
    ps, pt = predictions(int(res.frame_index[e.source])), predictions(int(res.frame_index[e.target]))
    li = learned_information(e.T, ps[0], pt[0], pt[1], cfg.odometry.corr_max_distance,
                             min_eigenvalue=cfg.graph.min_information_eigenvalue)
    np.testing.assert_allclose(e.information, cal["scale"] * li.information, rtol=1e-6)
    # at the optimum of the calibrated Gaussian graph the variance factor is 1
    g = PoseGraph(cfg.graph.model_copy(update={"loop_kernel": "none"}))
    for T in res.poses:
        g.add_pose(T)
    for x in res.edges:
        g.add_edge(x.source, x.target, x.T, x.information, loop=x.kind == "loop")
    assert variance_factor(g.optimize(marginals=False).poses, res.edges).sigma0_sq == pytest.approx(1.0, rel=1e-3)
    gt = np.linalg.inv(seq.gt_poses[0]) @ seq.gt_poses
    edges = np.array([(x.source, x.target) for x in res.edges])
    nees = edge_nees(edges, np.array([x.T for x in res.edges]), np.array([x.information for x in res.edges]), gt)
    assert np.isfinite(nees).all()


def test_position_nees_split_into_horizontal_and_vertical():
    """Errors drawn from the marginals give horizontal ~2 and vertical ~1 and sum to the 3-D NEES
    when the covariances do not couple height and plane; a height drift the marginals do not
    know shows in the vertical part only."""
    from gr_graph.noise_consistency import position_nees_split

    rng = np.random.default_rng(4)
    K = 4000
    cov = np.zeros((K, 3, 3))
    cov[:, :2, :2] = np.array([[0.04, 0.01], [0.01, 0.09]])
    cov[:, 2, 2] = 0.25
    gt = np.tile(np.eye(4), (K, 1, 1))
    est = gt.copy()
    est[:, :3, 3] = rng.multivariate_normal(np.zeros(3), cov[0], size=K)
    split = position_nees_split(est, cov, gt)
    assert split["horizontal"]["mean"] == pytest.approx(2.0, abs=0.15)
    assert split["vertical"]["mean"] == pytest.approx(1.0, abs=0.1)
    assert split["horizontal"]["ideal_mean"] == 2 and split["vertical"]["ideal_mean"] == 1
    total = position_nees(est, cov, gt)
    assert split["horizontal"]["mean"] + split["vertical"]["mean"] == pytest.approx(float(np.mean(total)), rel=1e-9)
    np.testing.assert_allclose(split["error_rms_xyz"], np.sqrt(np.mean(est[1:, :3, 3] ** 2, axis=0)))
    drift = est.copy()
    drift[:, 2, 3] += 2.0  # 2 m of height error, 4 sigma
    bent = position_nees_split(drift, cov, gt)
    assert bent["horizontal"]["mean"] == split["horizontal"]["mean"]
    assert bent["vertical"]["mean"] > 15.0
