"""Counts of unusable network covariances in a learning round (gr_graph.covariance_health)."""

from __future__ import annotations

import json

import numpy as np

from gr_graph.covariance_health import covariance_failures
from gr_graph.densify import covariance_problem


def test_covariance_problem_names_nonfinite_and_indefinite():
    good = np.tile(np.diag([1.0, 1.0, 1e-6]), (5, 1, 1))
    assert covariance_problem(good) is None
    bad = good.copy()
    bad[2, 0, 0] = np.inf
    assert covariance_problem(bad) == "nonfinite_covariance"
    indef = good.copy()
    indef[4] = [[1.0, 0.0, 0.0], [0.0, 1.0, 1.0], [0.0, 1.0, 0.5]]  # eigenvalues 1, 1.78, -0.28
    assert covariance_problem(indef) == "non_pd_covariance"
    assert covariance_problem(np.zeros((0, 3, 3))) is None


def test_covariance_failures_gathers_densify_training_and_edges(tmp_path):
    stats = {"frames": 200, "fallbacks": {"nonfinite_covariance": 3, "non_pd_covariance": 1, "few_kept": 7}}
    ts = tmp_path / "summary.json"
    ts.write_text(json.dumps({"epochs_done": 3, "dataset": {"n_edges": 199},
                              "skip_counts": {"loss_error": 5, "nonfinite_output": 1, "degenerate_H": 9}}))
    en = {"mode": "learned", "fallbacks": {"no_covariances": 4, "degenerate": 2},
          "loop": {"fallbacks": {"no_covariances": 1}}}
    out = covariance_failures(stats, ts, en)
    assert out["frames_nonfinite"] == 3 and out["frames_non_pd"] == 1 and out["fraction_frames"] == 4 / 200
    assert out["training_pairs"] == 597 and out["training_pairs_skipped"] == 6  # degenerate_H is not a covariance failure
    assert out["fraction_pairs"] == 6 / 597
    assert out["edges_without_covariances"] == {"odometry": 4, "loop": 1}
    # no training summary (e.g. resumed without it): the training figures are None
    out = covariance_failures({"frames": 0, "fallbacks": {}}, tmp_path / "missing.json")
    assert out["training_pairs"] is None and out["fraction_frames"] == 0.0
